//! What the wall actors did, summed into the job's `RayCacheStats` and `PhmStats` when
//! its walls close.
//!
//! Each actor counts for itself (no shared counters, no locks on the lookup path); the
//! host adds the counts up once, at `CloseWalls`, splitting lookups and hits by outer
//! and inner walls because the two behave very differently (outer walls see camera
//! rays, which repeat; inner walls see scattered ones).

use dray_proto::v1::{PhmStats, RayCacheStats};

/// One wall actor's counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WallStats {
    /// Rays that asked to be answered (option bit 0).
    pub lookups: u64,
    /// Of those, answered from the store.
    pub hits: u64,
    /// Rays whose crossing point or direction could not be computed (parallel to the
    /// wall, non-finite, zero direction): no answer, no ticket.
    pub skipped: u64,
    pub tickets_opened: u64,
    pub tickets_closed: u64,
    /// Closed tickets whose radiance was stored.
    pub tickets_stored: u64,
    /// Tickets still open when the stats were taken.
    pub tickets_open: u64,
    /// Misses that asked for a ticket but got none (too many open, ids exhausted, a ray
    /// without credit).
    pub tickets_refused: u64,
    /// Entries in the store.
    pub entries: u64,
    /// Radiance not stored because the store was full.
    pub entries_dropped: u64,
    /// Returns carrying more credit than their ticket waited for (ignored).
    pub over_credit: u64,
    /// Returns for tickets that are not open here (ignored).
    pub stray_returns: u64,
    /// The wall's hit map (all zero without one).
    pub phm: MapStats,
}

/// One wall's hit-map counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapStats {
    /// Rays that consulted the map (option bit 2).
    pub lookups: u64,
    /// Of those, rays the map could not place in a cell (parallel to the wall, zero
    /// direction): answered as if there were no map, and not probed.
    pub unplaced: u64,
    /// Rays told to skip the domain (outcome 3).
    pub skipped: u64,
    /// Occlusion rays answered as occluded (outcome 4).
    pub occluded: u64,
    /// `shade`: rays answered with a cell's averaged shading (outcome 5).
    pub shaded: u64,
    /// `shade`: closed tickets whose radiance a cell's averaged shading took.
    pub shading_learned: u64,
    /// Rays sent on as probes (+8).
    pub probes: u64,
    /// Outcomes received for a cell of the map (including those a decided cell of an
    /// inconsistent map ignored), so that `probes == outcomes` when a job completes.
    pub outcomes: u64,
    /// Of those, outcomes a decided cell ignored (inconsistent mode).
    pub outcomes_frozen: u64,
    /// Outcomes naming a cell beyond the map, or with a hit byte other than 0 or 1
    /// (ignored).
    pub outcomes_rejected: u64,
    /// Outcomes merged in from another worker's copy of the map (sender placement),
    /// whether the cell took them or was frozen.
    pub outcomes_merged: u64,
    /// Cells of the map, and of those the cells whose decision at the time the stats
    /// were taken is a hit or a miss.
    pub cells: u64,
    pub cells_decided_hit: u64,
    pub cells_decided_miss: u64,
}

impl MapStats {
    /// Add another map's counters.
    pub fn merge(&mut self, o: &MapStats) {
        self.lookups += o.lookups;
        self.unplaced += o.unplaced;
        self.skipped += o.skipped;
        self.occluded += o.occluded;
        self.shaded += o.shaded;
        self.shading_learned += o.shading_learned;
        self.probes += o.probes;
        self.outcomes += o.outcomes;
        self.outcomes_frozen += o.outcomes_frozen;
        self.outcomes_rejected += o.outcomes_rejected;
        self.outcomes_merged += o.outcomes_merged;
        self.cells += o.cells;
        self.cells_decided_hit += o.cells_decided_hit;
        self.cells_decided_miss += o.cells_decided_miss;
    }

    /// Add this map's share to the job's statistics. The worker-side fields
    /// (`rays_not_sent`, `bytes_not_sent`) stay zero here.
    pub fn add_to(&self, stats: &mut PhmStats) {
        stats.lookups += self.lookups;
        stats.rays_skipped += self.skipped;
        stats.rays_occluded += self.occluded;
        stats.rays_shaded += self.shaded;
        stats.shading_learned += self.shading_learned;
        stats.probes += self.probes;
        stats.outcomes += self.outcomes;
        stats.outcomes_merged += self.outcomes_merged;
        stats.cells_decided_hit += self.cells_decided_hit;
        stats.cells_decided_miss += self.cells_decided_miss;
        stats.cells += self.cells;
    }
}

impl WallStats {
    /// Add another wall's counters.
    pub fn merge(&mut self, o: &WallStats) {
        self.lookups += o.lookups;
        self.hits += o.hits;
        self.skipped += o.skipped;
        self.tickets_opened += o.tickets_opened;
        self.tickets_closed += o.tickets_closed;
        self.tickets_stored += o.tickets_stored;
        self.tickets_open += o.tickets_open;
        self.tickets_refused += o.tickets_refused;
        self.entries += o.entries;
        self.entries_dropped += o.entries_dropped;
        self.over_credit += o.over_credit;
        self.stray_returns += o.stray_returns;
        self.phm.merge(&o.phm);
    }

    /// Add this wall's share to the job's statistics; `outer` says whether the wall is on
    /// the scene bounds.
    pub fn add_to(&self, outer: bool, stats: &mut RayCacheStats) {
        if outer {
            stats.outer_lookups += self.lookups;
            stats.outer_hits += self.hits;
        } else {
            stats.inner_lookups += self.lookups;
            stats.inner_hits += self.hits;
        }
        stats.tickets_opened += self.tickets_opened;
        stats.tickets_closed += self.tickets_closed;
        stats.tickets_stored += self.tickets_stored;
        stats.tickets_open += self.tickets_open;
        stats.entries += self.entries;
        stats.entries_dropped += self.entries_dropped;
        stats.tickets_refused += self.tickets_refused;
        stats.returns_rejected += self.over_credit + self.stray_returns;
        stats.lookups_skipped += self.skipped;
    }
}

/// Whether the `n`-th occurrence (from 1) of a warning should be logged: the 1st, 2nd,
/// 4th, 8th ... so a misbehaving peer cannot flood the log, yet the count stays visible.
pub fn worth_logging(n: u64) -> bool {
    n.is_power_of_two()
}

/// Whether a count going from `before` to `after` passed a point [`worth_logging`]
/// logs at (for counters that grow by more than one at a time).
pub fn log_point_between(before: u64, after: u64) -> bool {
    after > before && (before == 0 || after.ilog2() > before.ilog2())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outer_and_inner_are_split() {
        let w = WallStats {
            lookups: 5,
            hits: 2,
            tickets_opened: 3,
            tickets_closed: 2,
            tickets_stored: 1,
            tickets_open: 1,
            ..Default::default()
        };
        let mut s = RayCacheStats::default();
        w.add_to(true, &mut s);
        w.add_to(false, &mut s);
        assert_eq!((s.outer_lookups, s.outer_hits), (5, 2));
        assert_eq!((s.inner_lookups, s.inner_hits), (5, 2));
        assert_eq!(
            (
                s.tickets_opened,
                s.tickets_closed,
                s.tickets_stored,
                s.tickets_open
            ),
            (6, 4, 2, 2)
        );
        assert!(worth_logging(1) && worth_logging(64) && !worth_logging(3) && !worth_logging(0));
        assert!(log_point_between(0, 1) && log_point_between(3, 9) && log_point_between(7, 8));
        assert!(!log_point_between(4, 7) && !log_point_between(5, 5));
    }

    #[test]
    fn map_stats_add_up() {
        let m = MapStats {
            lookups: 10,
            unplaced: 1,
            skipped: 3,
            occluded: 2,
            shaded: 8,
            shading_learned: 9,
            probes: 4,
            outcomes: 4,
            outcomes_frozen: 1,
            outcomes_rejected: 1,
            outcomes_merged: 6,
            cells: 192,
            cells_decided_hit: 5,
            cells_decided_miss: 7,
        };
        let mut w = WallStats {
            phm: m,
            ..Default::default()
        };
        w.merge(&WallStats {
            phm: m,
            ..Default::default()
        });
        assert_eq!(w.phm.lookups, 20);
        assert_eq!(w.phm.cells, 384);
        let mut s = PhmStats::default();
        m.add_to(&mut s);
        assert_eq!(
            s,
            PhmStats {
                lookups: 10,
                rays_skipped: 3,
                rays_occluded: 2,
                rays_shaded: 8,
                shading_learned: 9,
                probes: 4,
                outcomes: 4,
                outcomes_merged: 6,
                cells_decided_hit: 5,
                cells_decided_miss: 7,
                cells: 192,
                ..Default::default()
            }
        );
    }
}
