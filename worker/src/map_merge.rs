//! Sender placement's hit-map merges (Bolstad 2017): every worker holds a copy of every
//! wall's map and consults its own, so a probe's outcome, learned by the worker that
//! traced the probe, must reach the other copies too. Sending each outcome to every
//! copy would cost more than the rays the maps save; instead a worker teaches its own
//! copy at once and gathers outcomes here, counted per map cell, until `every` of them
//! have come in (or its tracing threads run out of work), and then sends one merge to
//! each other copy.
//!
//! Copies therefore lag each other by at most one batch per worker. Maps learn while a
//! job runs, so their decisions were never the same from run to run (docs/caches.md);
//! with thresholds that never decide, no copy ever decides, and the image is the exact
//! one on any number of workers.

use std::collections::BTreeMap;
use std::sync::Mutex;

/// One merge: per (wall, cell), the hits and misses gathered, in (wall, cell) order.
pub(crate) type Merge = Vec<(u32, u32, u32, u32)>;

/// The outcomes one worker gathered for one job since its last merge.
#[derive(Debug)]
pub struct MapMerges {
    every: u64,
    gathered: Mutex<Gathered>,
}

#[derive(Debug, Default)]
struct Gathered {
    /// (wall, cell) -> (hits, misses).
    cells: BTreeMap<(u32, u32), (u32, u32)>,
    outcomes: u64,
}

impl Gathered {
    fn take(&mut self) -> Option<Merge> {
        if self.outcomes == 0 {
            return None;
        }
        self.outcomes = 0;
        let cells = std::mem::take(&mut self.cells);
        Some(
            cells
                .into_iter()
                .map(|((w, c), (h, m))| (w, c, h, m))
                .collect(),
        )
    }
}

impl MapMerges {
    /// Merges of at least `every` outcomes (0 counts as 1).
    pub fn new(every: u32) -> MapMerges {
        MapMerges {
            every: u64::from(every.max(1)),
            gathered: Mutex::new(Gathered::default()),
        }
    }

    /// Gather probe `outcomes` (wall, cell, hit); the merge to send when they complete
    /// a batch.
    pub(crate) fn gather(&self, outcomes: &[(u32, u32, bool)]) -> Option<Merge> {
        let mut g = self.lock();
        for &(wall, cell, hit) in outcomes {
            let c = g.cells.entry((wall, cell)).or_default();
            if hit {
                c.0 = c.0.saturating_add(1);
            } else {
                c.1 = c.1.saturating_add(1);
            }
        }
        g.outcomes += outcomes.len() as u64;
        if g.outcomes >= self.every {
            g.take()
        } else {
            None
        }
    }

    /// Whatever has been gathered, as a merge (none when nothing has).
    pub(crate) fn take(&self) -> Option<Merge> {
        self.lock().take()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Gathered> {
        dray_sync::lock(&self.gathered)
    }
}

impl Default for MapMerges {
    fn default() -> Self {
        // Outcomes gathered before a merge when the job does not say.
        MapMerges::new(dray_cache::settings::DEFAULT_PHM_MERGE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outcomes_are_counted_per_cell_and_sent_in_batches() {
        let m = MapMerges::new(5);
        assert_eq!(m.gather(&[(3, 1, true), (0, 9, false)]), None);
        assert_eq!(m.gather(&[(3, 1, false), (3, 1, true)]), None);
        assert_eq!(
            m.gather(&[(0, 9, false)]),
            Some(vec![(0, 9, 0, 2), (3, 1, 2, 1)]),
            "the fifth outcome completes a batch, in (wall, cell) order"
        );
        assert_eq!(m.take(), None, "nothing gathered since");
        assert_eq!(m.gather(&[(7, 7, true)]), None);
        assert_eq!(m.take(), Some(vec![(7, 7, 1, 0)]));
        assert_eq!(m.take(), None);
        let every = MapMerges::new(0);
        assert_eq!(every.gather(&[(1, 2, true)]), Some(vec![(1, 2, 1, 0)]));
    }
}
