//! The tiles of a job attempt whose camera rays are still to be made here.
//!
//! The job's actor deals tiles in as the coordinator sends them
//! ([`super::actor`]); tracing threads take camera rays from the front tile, a chunk at
//! a time, so several threads share a tile.

use std::collections::VecDeque;
use std::sync::Mutex;

use crate::tracer::TileRef;

use super::lock;

/// Tiles with the index of their next camera ray.
#[derive(Default)]
pub struct TileQueue {
    tiles: Mutex<VecDeque<(TileRef, u64)>>,
}

/// Why tiles were refused.
#[derive(Debug, PartialEq, Eq)]
pub struct TooManyTiles {
    pub queued: usize,
    pub dealt: usize,
}

impl TileQueue {
    /// Queue `tiles`, unless the queue would then hold more than `limit` (the job's
    /// tile count): a coordinator repeating tiles cannot grow the queue without end.
    pub fn deal(&self, tiles: Vec<TileRef>, limit: u64) -> Result<(), TooManyTiles> {
        let mut q = lock(&self.tiles);
        if (q.len() + tiles.len()) as u64 > limit {
            return Err(TooManyTiles {
                queued: q.len(),
                dealt: tiles.len(),
            });
        }
        q.extend(tiles.into_iter().map(|t| (t, 0)));
        Ok(())
    }

    /// Whether no camera ray is left to make.
    pub fn is_empty(&self) -> bool {
        lock(&self.tiles).is_empty()
    }

    /// The next `chunk` camera rays (at most) of the front tile, each tile having
    /// `per_tile(tile)` in all: the tile and the range `start..start + count`.
    pub fn take(
        &self,
        chunk: u64,
        per_tile: impl Fn(&TileRef) -> u64,
    ) -> Option<(TileRef, u64, u64)> {
        let mut q = lock(&self.tiles);
        let (tile, next) = q.front_mut()?;
        let total = per_tile(tile);
        let start = *next;
        let count = chunk.min(total.saturating_sub(start));
        let t = *tile;
        *next += count;
        if *next >= total {
            q.pop_front();
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
        q.deal(vec![tile(0), tile(1)], 2).expect("within the bound");
        assert_eq!(
            q.deal(vec![tile(2)], 2),
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
}
