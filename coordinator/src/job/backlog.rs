//! Dealing a replicated job's tiles on demand (issue 40): a worker that joins a running
//! job takes a share of the tiles nobody has started.
//!
//! Under the replicated schedule every worker holds the whole scene and traces whole
//! paths for its tiles, so a tile's pixels do not depend on who traces it (counter-based
//! random numbers of seed, pixel, sample and bounce; exact integer sums in the film). If
//! the tiles of a pass were all dealt when it starts, a worker that registers later
//! would find none left to take, and would wait for the next pass (or for nothing, in a
//! one-pass job). So a replicated job deals each phase (a pass, an attempt) in windows:
//! every worker starts with up to [`Backlog::window`] tiles (round robin, as before, so
//! each gets a share of the cheap and the costly parts of the image), and the rest wait
//! here. When a worker's report completes tiles and it has at most half a window left
//! unfinished, it is topped up to a window; a worker that joins gets a window at once.
//!
//! The window is a quarter of a worker's even share of the phase (at least
//! [`MIN_WINDOW`] tiles): a worker is topped up about six times a pass, one small
//! TileAssignment each, and the half window it still holds when asked keeps its threads
//! busy across the report interval (100 ms, 10 ms once it has made every camera ray it
//! was dealt). A phase small enough to deal whole is dealt whole, as before.

use std::collections::{BTreeMap, VecDeque};

use dray_proto::v1::Tile;

/// A worker's window is its even share of a phase divided by this.
pub const WINDOW_PARTS: usize = 4;

/// The fewest tiles a window holds: below this a worker would wait on the round trip of
/// its reports more than it traces.
pub const MIN_WINDOW: usize = 8;

/// The tiles of the current phase not dealt yet, and what each worker was dealt of it.
#[derive(Debug, Default)]
pub struct Backlog {
    /// Tiles not dealt yet, in the order they go out.
    waiting: VecDeque<Tile>,
    /// Per worker, the tiles (indices) dealt to it in this phase that were not complete
    /// when last looked at (pruned as its reports come).
    out: BTreeMap<String, Vec<u32>>,
    /// Tiles a worker is topped up to.
    window: usize,
    /// Tiles dealt after a phase started (top-ups and joins), over the job's life.
    dealt_later: u64,
}

impl Backlog {
    /// A new phase of `tiles` over `workers` workers: forget the last phase and return
    /// the tiles to deal now (the first `workers` windows, in order), keeping the rest.
    pub fn start(&mut self, tiles: &[Tile], workers: usize) -> Vec<Tile> {
        self.out.clear();
        let n = workers.max(1);
        self.window = tiles.len().div_ceil(n * WINDOW_PARTS).max(MIN_WINDOW);
        let now = tiles.len().min(n.saturating_mul(self.window));
        self.waiting = tiles[now..].iter().copied().collect();
        tiles[..now].to_vec()
    }

    /// Record that `worker` was dealt `tiles` in this phase.
    pub fn dealt(&mut self, worker: &str, tiles: &[Tile]) {
        if tiles.is_empty() {
            return;
        }
        self.out
            .entry(worker.to_string())
            .or_default()
            .extend(tiles.iter().map(|t| t.index));
    }

    /// The tiles to deal `worker` now: none while tiles wait for nobody, or while it has
    /// more than half a window unfinished (`complete` says which tiles are); else enough
    /// to bring it back to a window.
    pub fn top_up(&mut self, worker: &str, complete: impl Fn(u32) -> bool) -> Vec<Tile> {
        if self.waiting.is_empty() {
            return Vec::new();
        }
        let open = self.out.get_mut(worker).map_or(0, |out| {
            out.retain(|&t| !complete(t));
            out.len()
        });
        if open > self.window / 2 {
            return Vec::new();
        }
        let n = (self.window - open).min(self.waiting.len());
        let tiles: Vec<Tile> = self.waiting.drain(..n).collect();
        self.dealt_later += tiles.len() as u64;
        self.dealt(worker, &tiles);
        tiles
    }

    /// Tiles of the current phase not dealt yet.
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }

    /// Tiles a worker is topped up to in the current phase.
    pub fn window(&self) -> usize {
        self.window
    }

    /// Tiles dealt after their phase started (top-ups and joins), over the job's life.
    pub fn dealt_later(&self) -> u64 {
        self.dealt_later
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiles(n: u32) -> Vec<Tile> {
        (0..n)
            .map(|index| Tile {
                index,
                credit: 1,
                ..Default::default()
            })
            .collect()
    }

    #[test]
    fn a_small_phase_is_dealt_whole() {
        let mut b = Backlog::default();
        let now = b.start(&tiles(12), 2);
        assert_eq!(now.len(), 12);
        assert_eq!(b.waiting(), 0);
        assert!(b.top_up("a", |_| true).is_empty());
    }

    /// Every tile goes out exactly once, whoever asks, and a worker is topped up only
    /// once half its window is complete.
    #[test]
    fn tiles_go_out_once_in_windows_to_whoever_has_room() {
        let all = tiles(400);
        let mut b = Backlog::default();
        let now = b.start(&all, 2);
        // 400 tiles over 2 workers in quarters of 200: windows of 50.
        assert_eq!((b.window(), now.len(), b.waiting()), (50, 100, 300));
        let (a, rest) = now.split_at(50);
        b.dealt("a", a);
        b.dealt("b", rest);
        let mut done = vec![false; 400];
        let mut seen: Vec<u32> = now.iter().map(|t| t.index).collect();
        // Nothing complete: no room.
        assert!(b.top_up("a", |t| done[t as usize]).is_empty());
        // 24 of a's complete: 26 open, still more than half.
        for t in &a[..24] {
            done[t.index as usize] = true;
        }
        assert!(b.top_up("a", |t| done[t as usize]).is_empty());
        done[a[24].index as usize] = true;
        let more = b.top_up("a", |t| done[t as usize]);
        assert_eq!(more.len(), 25, "back to a window of 50");
        seen.extend(more.iter().map(|t| t.index));
        // A joiner gets a whole window at once.
        let joined = b.top_up("c", |t| done[t as usize]);
        assert_eq!(joined.len(), 50);
        seen.extend(joined.iter().map(|t| t.index));
        // Drain the rest to "b" as it completes everything.
        loop {
            let d = |t: u32| t < 400 && (done[t as usize] || seen.contains(&t));
            let more = b.top_up("b", d);
            if more.is_empty() {
                break;
            }
            seen.extend(more.iter().map(|t| t.index));
        }
        seen.sort_unstable();
        assert_eq!(seen, (0..400).collect::<Vec<_>>());
        assert_eq!(b.dealt_later(), 300);
        // A new phase forgets the last one.
        let now = b.start(&all[..40], 3);
        assert_eq!((b.window(), now.len(), b.waiting()), (8, 24, 16));
    }
}
