//! A running job's credit ledger (docs/architecture.md "Credit"): every tile starts with
//! a fixed credit, workers hand it back with the contributions of terminated rays, and a
//! tile is complete when all of it is back. The ledger is the only place that counts
//! it: [`super::report`] hands it a report's credits, a new pass or attempt resets it,
//! and the rest of the job asks it which tiles are complete.
//!
//! Credit arrives, and is kept per tile, as the wire carries it; the sums are made on
//! [`Credit`]. Credit beyond a tile's start means something was counted twice, which
//! would silently brighten the image: the ledger reports it (and keeps the tile as it
//! was) so the job can fail.

use std::time::Instant;

use dray_core::credit::Credit;
use dray_proto::v1::{Tile, TileCredit};
use tonic::Status;

/// Every tile of a job (the image's, then the coarse pass's) and the credit back on each.
#[derive(Debug)]
pub struct CreditLedger {
    /// Every tile of the image (rectangle and starting credit), by index, then the
    /// tiles of the ray-cache coarse pass, if any (`Tile.coarse`).
    tiles: Vec<Tile>,
    /// Credit returned per tile.
    back: Vec<u64>,
    /// The image's tiles: `tiles[..image_tiles]`; the rest are the coarse pass's.
    image_tiles: usize,
    /// Image tiles complete (coarse tiles are not counted: progress is the image's).
    done: u32,
    /// Tiles cleared to be traced again by a later attempt, in all.
    retried: u32,
    /// When a worker last returned credit (or the job or its latest attempt started):
    /// a job with none for the stall timeout fails.
    last_progress: Instant,
}

/// What a report's credits did to the ledger.
#[derive(Debug, Default)]
pub struct Credited {
    /// Image tiles whose credit came all back with it, in the order credited.
    pub finished: Vec<usize>,
    /// The first credit that would have gone beyond its tile's start, as the failure
    /// message names it; the credits after it were not counted.
    pub overdrawn: Option<Overdrawn>,
}

/// Credit returned beyond a tile's start.
#[derive(Debug)]
pub struct Overdrawn {
    /// The tile.
    pub tile: u32,
    /// The credit the report returned to it.
    pub credit: Credit,
    /// Its credit back before the report.
    pub back: u64,
    /// Its starting credit.
    pub start: u64,
}

impl CreditLedger {
    /// A ledger over `tiles` (image tiles first, then coarse ones), with no credit back.
    pub fn new(tiles: Vec<Tile>) -> CreditLedger {
        let image_tiles = tiles.iter().filter(|t| !t.coarse).count();
        CreditLedger {
            back: vec![0; tiles.len()],
            tiles,
            image_tiles,
            done: 0,
            retried: 0,
            last_progress: Instant::now(),
        }
    }

    /// Every tile, image then coarse.
    pub fn tiles(&self) -> &[Tile] {
        &self.tiles
    }

    /// Tile `t` (its rectangle and starting credit).
    pub fn tile(&self, t: usize) -> Tile {
        self.tiles[t]
    }

    /// How many tiles there are, image and coarse.
    pub fn tile_count(&self) -> usize {
        self.tiles.len()
    }

    /// The image's tiles: `tiles()[..image_tiles()]`.
    pub fn image_tiles(&self) -> usize {
        self.image_tiles
    }

    /// Whether the job has a coarse pass (tiles after the image's).
    pub fn has_coarse(&self) -> bool {
        self.image_tiles < self.tiles.len()
    }

    /// The coarse pass's tiles.
    pub fn coarse_tiles(&self) -> &[Tile] {
        &self.tiles[self.image_tiles..]
    }

    /// Image tiles complete in the current pass.
    pub fn done(&self) -> u32 {
        self.done
    }

    /// Whether every image tile is complete in the current pass.
    pub fn image_complete(&self) -> bool {
        self.done as usize == self.image_tiles
    }

    /// Tiles cleared for a later attempt, in all (`JobStats.tiles_retried`).
    pub fn retried(&self) -> u32 {
        self.retried
    }

    /// When credit last came back (or the job or its latest attempt started).
    pub fn last_progress(&self) -> Instant {
        self.last_progress
    }

    /// Whether tile `t`'s credit is all back.
    pub fn complete(&self, t: usize) -> bool {
        self.back[t] == self.tiles[t].credit
    }

    /// Whether tile `t` is complete, for a tile that may not exist (false then).
    pub fn complete_if_any(&self, t: usize) -> bool {
        self.tiles
            .get(t)
            .is_some_and(|x| self.back.get(t) == Some(&x.credit))
    }

    /// Whether every coarse tile is complete.
    pub fn coarse_complete(&self) -> bool {
        (self.image_tiles..self.tiles.len()).all(|t| self.complete(t))
    }

    /// A report's credits may be counted: every one names a tile of the job.
    pub fn check(&self, credits: &[TileCredit]) -> Result<(), Status> {
        match credits.iter().find(|c| c.tile as usize >= self.tiles.len()) {
            Some(c) => Err(Status::invalid_argument(format!(
                "credits: tile {} does not exist (the job has {} tiles)",
                c.tile,
                self.tiles.len()
            ))),
            None => Ok(()),
        }
    }

    /// Count `credits` (which [`CreditLedger::check`] accepted), in order, until one
    /// would overdraw its tile.
    pub fn add(&mut self, credits: &[TileCredit]) -> Credited {
        let mut out = Credited::default();
        for c in credits {
            let t = c.tile as usize;
            let start = Credit::from_wire(self.tiles[t].credit);
            let back = Credit::from_wire(self.back[t]);
            let credit = Credit::from_wire(c.credit);
            match back.checked_add(credit) {
                Some(b) if b <= start => {
                    if !credit.is_zero() {
                        self.last_progress = Instant::now();
                    }
                    self.back[t] = b.to_wire();
                    if back != start && b == start && t < self.image_tiles {
                        self.done += 1;
                        out.finished.push(t);
                    }
                }
                _ => {
                    out.overdrawn = Some(Overdrawn {
                        tile: c.tile,
                        credit,
                        back: self.back[t],
                        start: self.tiles[t].credit,
                    });
                    break;
                }
            }
        }
        out
    }

    /// A new pass: image tile `t` starts complete when `complete(t)` (it holds more
    /// passes), else with no credit back. Returns the tiles that start complete.
    pub fn enter_pass(&mut self, complete: impl Fn(usize) -> bool) -> Vec<usize> {
        self.done = 0;
        let mut whole = Vec::new();
        for t in 0..self.image_tiles {
            if complete(t) {
                self.back[t] = self.tiles[t].credit;
                self.done += 1;
                whole.push(t);
            } else {
                self.back[t] = 0;
            }
        }
        whole
    }

    /// Tile `t` has no credit back (its pixels are cleared by the film).
    pub fn clear(&mut self, t: usize) {
        self.back[t] = 0;
    }

    /// The tiles a new attempt traces again: every incomplete tile, and the whole coarse
    /// pass when the job has one (the new attempt's walls open empty). Counts them as
    /// retried and restarts the stall clock; the caller clears them.
    pub fn for_retry(&mut self) -> Vec<usize> {
        let mut again: Vec<usize> = (0..self.tiles.len())
            .filter(|&t| !self.complete(t))
            .collect();
        if self.has_coarse() {
            again.extend((self.image_tiles..self.tiles.len()).filter(|&t| self.complete(t)));
            again.sort_unstable();
        }
        self.retried = self.retried.saturating_add(again.len() as u32);
        self.last_progress = Instant::now();
        again
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ledger() -> CreditLedger {
        let tile = |i: u32, coarse: bool| Tile {
            index: i,
            credit: 10,
            coarse,
            ..Default::default()
        };
        CreditLedger::new(vec![tile(0, false), tile(1, false), tile(2, true)])
    }

    fn credit(tile: u32, credit: u64) -> TileCredit {
        TileCredit { tile, credit }
    }

    #[test]
    fn credit_completes_image_tiles_and_stops_at_an_overdraw() {
        let mut l = ledger();
        assert!(l.check(&[credit(3, 1)]).is_err(), "tile 3 of 3");
        let c = l.add(&[credit(0, 4), credit(1, 10), credit(2, 10)]);
        assert_eq!(c.finished, [1], "a coarse tile is not the image's progress");
        assert!(c.overdrawn.is_none());
        assert_eq!(l.done(), 1);
        assert!(l.coarse_complete());
        let c = l.add(&[credit(0, 6), credit(0, 1), credit(1, 0)]);
        assert_eq!(c.finished, [0]);
        let o = c.overdrawn.expect("tile 0 overdrawn");
        assert_eq!((o.tile, o.back, o.start), (0, 10, 10));
        assert!(l.image_complete());
    }

    #[test]
    fn a_retry_takes_the_incomplete_tiles_and_the_whole_coarse_pass() {
        let mut l = ledger();
        l.add(&[credit(1, 10), credit(2, 10)]);
        assert_eq!(l.for_retry(), [0, 2]);
        assert_eq!(l.retried(), 2);
        let whole = l.enter_pass(|t| t == 0);
        assert_eq!(whole, [0]);
        assert_eq!(l.done(), 1);
        assert!(l.complete(0) && !l.complete(1));
    }
}
