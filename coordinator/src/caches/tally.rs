//! What the ray caches did for one job, summed: the cache hosts' statistics (returned by
//! CloseWalls when an attempt ends) and the workers' cache counters (in their
//! contribution reports), published as `JobStats.ray_cache`.
//!
//! Shared (`Arc`) between the job's actor and the tasks that close its walls, since
//! a host's statistics may arrive after the job has left the registry (a job that failed
//! or was cancelled) or while a new attempt's walls are being opened. Every change is
//! published to the job record under the tally's own lock, so two writers cannot leave
//! an older sum in place of a newer one.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

use dray_proto::v1::{JobStats, PhmStats, RayCacheStats, WorkerCounters};

/// Bytes a ray takes on the wire at most (records are 32 to 64 bytes, rays.proto): what
/// a ray not sent saves, as an upper bound (the ray was never encoded, so its own size is
/// not known).
pub const RAY_BYTES: u64 = dray_core::ray::RAY_RECORD_MAX_BYTES as u64;

/// Most lost hosts listed per job: the names come from workers' reports, which are
/// bounded each but not in number.
pub const MAX_LOST_HOSTS: usize = 256;

/// Sums of one job's cache statistics: ray caches and hit maps, each published only
/// when the job has it.
#[derive(Debug)]
pub struct CacheTally {
    inner: Mutex<(RayCacheStats, PhmStats)>,
    /// The most entries one cache host held when its walls closed, over the job's
    /// attempts (the per-process memory Little 2011 reports).
    host_entries_max: AtomicU64,
    caches: bool,
    phm: bool,
}

impl Default for CacheTally {
    /// A tally of ray caches only.
    fn default() -> Self {
        CacheTally::new(true, false)
    }
}

/// Add `b` into `a`, counter by counter (saturating).
pub fn add_phm(a: &mut PhmStats, b: &PhmStats) {
    let sum = |x: &mut u64, y: u64| *x = x.saturating_add(y);
    sum(&mut a.lookups, b.lookups);
    sum(&mut a.rays_skipped, b.rays_skipped);
    sum(&mut a.rays_occluded, b.rays_occluded);
    sum(&mut a.rays_shaded, b.rays_shaded);
    sum(&mut a.shading_learned, b.shading_learned);
    sum(&mut a.probes, b.probes);
    sum(&mut a.outcomes, b.outcomes);
    sum(&mut a.outcomes_merged, b.outcomes_merged);
    sum(&mut a.cells_decided_hit, b.cells_decided_hit);
    sum(&mut a.cells_decided_miss, b.cells_decided_miss);
    sum(&mut a.cells, b.cells);
    sum(&mut a.rays_not_sent, b.rays_not_sent);
    sum(&mut a.bytes_not_sent, b.bytes_not_sent);
}

/// Add `b` into `a`, counter by counter (saturating); `lost_hosts` are merged without
/// duplicates, in order, at most [`MAX_LOST_HOSTS`].
pub fn add(a: &mut RayCacheStats, b: &RayCacheStats) {
    let sum = |x: &mut u64, y: u64| *x = x.saturating_add(y);
    sum(&mut a.outer_lookups, b.outer_lookups);
    sum(&mut a.outer_hits, b.outer_hits);
    sum(&mut a.inner_lookups, b.inner_lookups);
    sum(&mut a.inner_hits, b.inner_hits);
    sum(&mut a.rays_not_sent, b.rays_not_sent);
    sum(&mut a.bytes_not_sent, b.bytes_not_sent);
    sum(&mut a.tickets_opened, b.tickets_opened);
    sum(&mut a.tickets_closed, b.tickets_closed);
    sum(&mut a.tickets_stored, b.tickets_stored);
    sum(&mut a.tickets_open, b.tickets_open);
    sum(&mut a.coarse_rays, b.coarse_rays);
    sum(&mut a.rays_bypassed, b.rays_bypassed);
    sum(&mut a.cache_bytes, b.cache_bytes);
    sum(&mut a.entries, b.entries);
    sum(&mut a.entries_dropped, b.entries_dropped);
    sum(&mut a.tickets_refused, b.tickets_refused);
    sum(&mut a.returns_rejected, b.returns_rejected);
    sum(&mut a.lookups_skipped, b.lookups_skipped);
    lose(a, b.lost_hosts.iter().map(String::as_str));
}

fn lose<'a>(a: &mut RayCacheStats, hosts: impl IntoIterator<Item = &'a str>) {
    let mut seen: BTreeSet<String> = a.lost_hosts.iter().cloned().collect();
    for h in hosts {
        if a.lost_hosts.len() >= MAX_LOST_HOSTS {
            break;
        }
        if seen.insert(h.to_string()) {
            a.lost_hosts.push(h.to_string());
        }
    }
}

impl CacheTally {
    /// A tally for a job with ray caches (`caches`) and/or hit maps (`phm`).
    pub fn new(caches: bool, phm: bool) -> CacheTally {
        CacheTally {
            inner: Mutex::new(Default::default()),
            host_entries_max: AtomicU64::new(0),
            caches,
            phm,
        }
    }

    fn both(&self) -> MutexGuard<'_, (RayCacheStats, PhmStats)> {
        dray_sync::lock(&self.inner)
    }

    /// Add a host's hit-map statistics for a closed attempt.
    pub fn add_host_phm(&self, s: &PhmStats) {
        add_phm(&mut self.both().1, s);
    }

    /// The hit-map sums so far.
    pub fn phm_stats(&self) -> PhmStats {
        self.both().1
    }

    /// Add a worker's cache counters (deltas): rays answered instead of sent to another
    /// worker (and their bytes), rays that went past an unreachable host, bytes sent to
    /// hosts, hosts found unreachable.
    pub fn add_worker(&self, c: &WorkerCounters) {
        add_phm(
            &mut self.both().1,
            &PhmStats {
                rays_not_sent: c.phm_rays_not_sent,
                bytes_not_sent: c.phm_rays_not_sent.saturating_mul(RAY_BYTES),
                ..Default::default()
            },
        );
        add(
            &mut self.both().0,
            &RayCacheStats {
                rays_not_sent: c.cache_rays_not_sent,
                bytes_not_sent: c.cache_rays_not_sent.saturating_mul(RAY_BYTES),
                rays_bypassed: c.cache_rays_bypassed,
                cache_bytes: c.cache_bytes,
                lost_hosts: c.lost_cache_hosts.clone(),
                ..Default::default()
            },
        );
    }

    /// Add a host's statistics for a closed attempt.
    pub fn add_host(&self, s: &RayCacheStats) {
        add(&mut self.both().0, s);
    }

    /// Note that one host held `entries` ray-cache entries (an attempt's walls closed).
    pub fn note_host_entries(&self, entries: u64) {
        self.host_entries_max.fetch_max(entries, Ordering::Relaxed);
    }

    /// The most memory one cache host's entries took (bytes, estimated:
    /// [`dray_cache::store::ENTRY_BYTES`] each).
    pub fn bytes_per_process(&self) -> u64 {
        self.host_entries_max
            .load(Ordering::Relaxed)
            .saturating_mul(dray_cache::store::ENTRY_BYTES)
    }

    /// Record hosts lost to the job (OpenWalls or CloseWalls failed).
    pub fn lose<'a>(&self, hosts: impl IntoIterator<Item = &'a str>) {
        lose(&mut self.both().0, hosts);
    }

    /// The sums so far.
    pub fn stats(&self) -> RayCacheStats {
        self.both().0.clone()
    }

    /// Write the sums into a job's statistics `s` (`JobStats.ray_cache`, `phm`), as
    /// `record.update_stats(|s| tally.fill(s))`: ours is a leaf lock taken under the
    /// job record's, which orders the writes. Savings are net of what consulting caches and
    /// maps cost between processes, from the traffic the job published first (zero
    /// before any worker reported).
    pub fn fill(&self, s: &mut JobStats) {
        let g = self.both();
        let traffic = s.traffic.unwrap_or_default();
        s.cache_bytes_per_process = if self.caches {
            self.bytes_per_process()
        } else {
            0
        };
        s.ray_cache = self.caches.then(|| {
            let mut c = g.0.clone();
            c.bytes_not_sent_net = crate::traffic::cache_net(c.bytes_not_sent, &traffic);
            c
        });
        s.phm = self.phm.then(|| {
            let mut p = g.1;
            p.bytes_not_sent_net = crate::traffic::phm_net(p.bytes_not_sent, &traffic);
            p
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn workers_and_hosts_sum_and_lost_hosts_are_listed_once() {
        let t = CacheTally::default();
        t.add_worker(&WorkerCounters {
            cache_rays_not_sent: 10,
            cache_rays_bypassed: 3,
            cache_bytes: 1000,
            lost_cache_hosts: vec!["http://h2:1".into()],
            ..Default::default()
        });
        t.add_worker(&WorkerCounters {
            cache_rays_not_sent: 5,
            lost_cache_hosts: vec!["http://h2:1".into(), "http://h3:1".into()],
            ..Default::default()
        });
        let host = RayCacheStats {
            outer_lookups: 100,
            outer_hits: 90,
            inner_lookups: 50,
            inner_hits: 5,
            tickets_opened: 55,
            tickets_closed: 54,
            tickets_stored: 50,
            tickets_open: 1,
            ..Default::default()
        };
        t.add_host(&host);
        t.add_host(&host);
        t.lose(["http://h3:1", "http://h1:1"]);
        let s = t.stats();
        assert_eq!((s.rays_not_sent, s.bytes_not_sent), (15, 15 * 64));
        assert_eq!((s.rays_bypassed, s.cache_bytes), (3, 1000));
        assert_eq!((s.outer_lookups, s.outer_hits), (200, 180));
        assert_eq!((s.inner_lookups, s.inner_hits), (100, 10));
        assert_eq!(
            (
                s.tickets_opened,
                s.tickets_closed,
                s.tickets_stored,
                s.tickets_open
            ),
            (110, 108, 100, 2)
        );
        assert_eq!(s.lost_hosts, ["http://h2:1", "http://h3:1", "http://h1:1"]);
    }

    #[test]
    fn lost_hosts_are_bounded() {
        let t = CacheTally::default();
        let names: Vec<String> = (0..1000).map(|i| format!("h{i}")).collect();
        t.lose(names.iter().map(String::as_str));
        assert_eq!(t.stats().lost_hosts.len(), MAX_LOST_HOSTS);
    }
}
