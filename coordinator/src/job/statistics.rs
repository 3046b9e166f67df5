//! A running job's statistics: what its workers' reports count besides pixels and credit
//! (rays by kind, non-finite and clamped contributions, bytes by kind, the reports'
//! own size, CPU time, the scheduling counters per worker). Summed here, a report at a
//! time, and copied into the public record's `JobStats` when the job publishes; nothing
//! else writes them. Unlike the image they show a lost worker: counters of an attempt
//! dropped stay counted (the work was done).

use dray_proto::v1::{JobStats, RayCounts, ReportContributionsRequest};

use crate::cpu_tally::CpuTally;
use crate::metrics::JobMetrics;

/// The counters of one job on workers.
#[derive(Debug)]
pub struct JobStatistics {
    rays: RayCounts,
    nonfinite: u64,
    /// Contributions the workers clamped to the film's largest.
    clamped: u64,
    /// Contributions the workers scaled down by `--clamp-indirect`.
    clamped_indirect: u64,
    ray_bytes_sent: u64,
    /// Bytes between processes by kind, summed over the workers' reports.
    traffic: dray_proto::v1::TrafficStats,
    /// The reports themselves: messages applied, their bytes and the AOVs' part.
    reports: dray_proto::v1::ReportStats,
    /// CPU seconds of the processes that ran the job.
    cpu: CpuTally,
    /// Scheduling counters per worker.
    metrics: JobMetrics,
}

impl JobStatistics {
    /// Nothing counted yet, for a job on `workers`.
    pub fn new(workers: impl IntoIterator<Item = String>) -> JobStatistics {
        let mut metrics = JobMetrics::default();
        for id in workers {
            metrics.add_worker(&id);
        }
        JobStatistics {
            rays: RayCounts::default(),
            nonfinite: 0,
            clamped: 0,
            clamped_indirect: 0,
            ray_bytes_sent: 0,
            traffic: Default::default(),
            reports: Default::default(),
            cpu: CpuTally::here(),
            metrics,
        }
    }

    /// Worker `id` joined the job.
    pub fn add_worker(&mut self, id: &str) {
        self.metrics.add_worker(id);
    }

    /// Count report `r` itself (once per sequence, as everything else in it is), a
    /// worker's failure report included.
    pub fn count_report(&mut self, r: &ReportContributionsRequest) {
        crate::traffic::add_report(&mut self.reports, r);
    }

    /// Add the counters report `r` carries (which `super::report::check` accepted).
    pub fn add(&mut self, r: &ReportContributionsRequest) {
        if let Some(t) = &r.traced {
            let (sum, add) = (self.rays.by_kind(), t.by_kind());
            self.rays = RayCounts::from_kinds(std::array::from_fn(|k| sum[k] + add[k]));
        }
        self.nonfinite += r.nonfinite;
        self.clamped = self.clamped.saturating_add(r.clamped);
        self.clamped_indirect = self.clamped_indirect.saturating_add(r.clamped_indirect);
        self.ray_bytes_sent += r.ray_bytes_sent;
        if let Some(t) = r.counters.as_ref().and_then(|c| c.traffic.as_ref()) {
            crate::traffic::add(&mut self.traffic, t);
        }
        if let Some(c) = r.counters.as_ref().and_then(|c| c.cpu.as_ref()) {
            self.cpu.note(c);
        }
        self.cpu.note_here();
        self.metrics
            .add(&r.worker_id, r.counters.as_ref(), r.traced.as_ref());
    }

    /// Copy the totals into `s`: O(1) in the number of workers.
    pub fn fill_totals(&self, s: &mut JobStats) {
        s.rays = Some(self.rays);
        s.nonfinite = self.nonfinite;
        s.clamped = self.clamped;
        s.clamped_indirect = self.clamped_indirect;
        s.ray_bytes_sent = self.ray_bytes_sent;
        s.traffic = Some(self.traffic);
        s.reports = Some(self.reports);
        s.cpu_seconds = self.cpu.seconds();
        self.metrics.fill_totals(s);
    }

    /// Copy the per-worker detail (`JobStats.workers_detail`) into `s`: O(workers).
    pub fn fill_detail(&self, s: &mut JobStats) {
        self.metrics.fill_detail(s);
    }

    /// Rays traced per worker (ListWorkers).
    pub fn traced(&self) -> impl Iterator<Item = (String, u64)> + '_ {
        self.metrics.traced()
    }

    /// The counts the finished film carries: non-finite, clamped and indirect-clamped
    /// contributions.
    pub fn film_counts(&self) -> (u64, u64, u64) {
        (self.nonfinite, self.clamped, self.clamped_indirect)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_add_up_and_saturate() {
        let mut s = JobStatistics::new(["w1".to_string()]);
        let r = ReportContributionsRequest {
            worker_id: "w1".into(),
            nonfinite: 2,
            clamped: u64::MAX,
            clamped_indirect: 1,
            ray_bytes_sent: 100,
            ..Default::default()
        };
        s.add(&r);
        s.add(&r);
        assert_eq!(s.film_counts(), (4, u64::MAX, 2));
        let mut stats = JobStats::default();
        s.fill_totals(&mut stats);
        assert_eq!(stats.ray_bytes_sent, 200);
    }
}
