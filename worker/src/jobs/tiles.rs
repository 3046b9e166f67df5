//! The tiles of a job attempt whose camera rays are still to be made here.
//!
//! The job's actor deals tiles in as the coordinator sends them
//! ([`crate::job_actor`]); tracing threads take camera rays from the front tile, a chunk at
//! a time, so several threads share a tile. Tiles wait by pass: a job tracing passes
//! ahead (`JobSetup.passes_ahead`) queues every later pass of a tile it is dealt, and
//! threads take from the earliest pass open to them, so a later pass's camera rays
//! follow the earlier ones' and never pass them.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Mutex;

use crate::tracer::TileRef;

use dray_sync::lock;

/// Tiles with the index of their next camera ray, by pass.
pub struct TileQueue {
    inner: Mutex<Queued>,
}

struct Queued {
    by_pass: BTreeMap<u32, VecDeque<(TileRef, u64)>>,
    /// Tiles queued, in all passes.
    len: usize,
    /// The last pass whose tiles threads may take.
    open_through: u32,
}

impl Default for TileQueue {
    fn default() -> TileQueue {
        TileQueue {
            inner: Mutex::new(Queued {
                by_pass: BTreeMap::new(),
                len: 0,
                open_through: u32::MAX,
            }),
        }
    }
}

/// Why tiles were refused.
#[derive(Debug, PartialEq, Eq)]
pub struct TooManyTiles {
    pub queued: usize,
    pub dealt: usize,
}

impl TileQueue {
    /// Queue `tiles`, each in its pass, unless the queue would then hold more than
    /// `limit` (the job's tiles in all the passes it may queue): a coordinator
    /// repeating tiles cannot grow the queue without end.
    pub fn deal(&self, tiles: Vec<(u32, TileRef)>, limit: u64) -> Result<(), TooManyTiles> {
        let mut q = lock(&self.inner);
        if (q.len + tiles.len()) as u64 > limit {
            return Err(TooManyTiles {
                queued: q.len,
                dealt: tiles.len(),
            });
        }
        q.len += tiles.len();
        for (pass, t) in tiles {
            q.by_pass.entry(pass).or_default().push_back((t, 0));
        }
        Ok(())
    }

    /// Let threads take tiles of passes up to `pass` (a job tracing ahead widens it as
    /// its passes start).
    pub fn open_through(&self, pass: u32) {
        lock(&self.inner).open_through = pass;
    }

    /// Whether no camera ray is left to make in the passes open to threads.
    pub fn is_empty(&self) -> bool {
        let q = lock(&self.inner);
        q.by_pass.range(..=q.open_through).next().is_none()
    }

    /// The next `chunk` camera rays (at most) of the front tile of the earliest open
    /// pass, each tile having `per_tile(tile)` in all: the tile and the range
    /// `start..start + count`.
    pub fn take(
        &self,
        chunk: u64,
        per_tile: impl Fn(&TileRef) -> u64,
    ) -> Option<(TileRef, u64, u64)> {
        let mut guard = lock(&self.inner);
        let q = &mut *guard;
        let (&pass, queue) = q.by_pass.range_mut(..=q.open_through).next()?;
        let (tile, next) = queue.front_mut()?;
        let total = per_tile(tile);
        let start = *next;
        let count = chunk.min(total.saturating_sub(start));
        let t = *tile;
        *next += count;
        if *next >= total {
            queue.pop_front();
            let empty = queue.is_empty();
            q.len -= 1;
            if empty {
                q.by_pass.remove(&pass);
            }
        }
        Some((t, start, count))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_core::credit::Credit;

    fn tile(index: u32) -> TileRef {
        TileRef {
            index,
            x0: 0,
            y0: 0,
            width: 2,
            height: 2,
            credit: Credit::from_wire(1),
            coarse: false,
            first_sample: 0,
            samples: 0,
        }
    }

    #[test]
    fn threads_share_a_tile_in_chunks_and_the_queue_is_bounded() {
        let q = TileQueue::default();
        assert!(q.take(3, |_| 4).is_none());
        q.deal(vec![(0, tile(0)), (0, tile(1))], 2)
            .expect("within the bound");
        assert_eq!(
            q.deal(vec![(0, tile(2))], 2),
            Err(TooManyTiles {
                queued: 2,
                dealt: 1
            })
        );
        let got: Vec<(u32, u64, u64)> = std::iter::from_fn(|| q.take(3, |_| 4))
            .map(|(t, s, n)| (t.index, s, n))
            .collect();
        assert_eq!(got, vec![(0, 0, 3), (0, 3, 1), (1, 0, 3), (1, 3, 1)]);
        assert!(q.is_empty());
    }

    #[test]
    fn later_passes_wait_behind_earlier_ones_and_beyond_the_open_pass() {
        let q = TileQueue::default();
        q.open_through(0);
        // Dealt in pass 0 with its later passes (as a job tracing ahead queues them),
        // then a tile of pass 0 dealt later still goes first.
        q.deal(vec![(0, tile(0)), (1, tile(0)), (2, tile(0))], 8)
            .expect("within the bound");
        q.deal(vec![(0, tile(1)), (1, tile(1))], 8)
            .expect("within the bound");
        let take = || q.take(4, |_| 4).map(|(t, _, _)| t.index);
        assert_eq!((take(), take(), take()), (Some(0), Some(1), None));
        assert!(q.is_empty(), "pass 1 is not open yet");
        q.open_through(2);
        assert!(!q.is_empty());
        assert_eq!(
            (take(), take(), take(), take()),
            (Some(0), Some(1), Some(0), None)
        );
    }
}
