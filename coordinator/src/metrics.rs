//! A job's scheduling metrics: the workers' counters (ReportContributionsRequest.counters,
//! deltas except the queue peak) summed per worker and over the job, for JobStats.
//!
//! Kept per worker id for every worker that took part, lost and joined ones included,
//! in id order so `workers_detail` reads the same on every call.

use std::collections::BTreeMap;

use dray_proto::v1::{JobStats, RayCounts, WorkerCounters, WorkerJobStats};

/// A counter report that cannot be right.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CounterError {
    /// A seconds field that is negative, NaN or infinite.
    #[error("counters.{field}: {value} is not a finite, non-negative number of seconds")]
    Seconds {
        /// The field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// Too many lost cache hosts in one report, or a name too long to be an endpoint.
    #[error(
        "counters.lost_cache_hosts: {count} names, the longest {longest} bytes (at most \
         {MAX_LOST_CACHE_HOSTS} of at most {MAX_HOST_NAME} bytes)"
    )]
    LostCacheHosts {
        /// Names in the report.
        count: usize,
        /// Bytes of the longest.
        longest: usize,
    },
}

/// Most lost cache hosts one report may name.
pub const MAX_LOST_CACHE_HOSTS: usize = 64;
/// Longest cache host name (an endpoint URL) a report may carry, in bytes.
pub const MAX_HOST_NAME: usize = 2048;

/// Check a worker's counters before anything is applied.
pub fn check(c: &WorkerCounters) -> Result<(), CounterError> {
    for (field, value) in [
        ("domain_load_seconds", c.domain_load_seconds),
        ("idle_seconds", c.idle_seconds),
    ] {
        if !value.is_finite() || value < 0.0 {
            return Err(CounterError::Seconds { field, value });
        }
    }
    let longest = c
        .lost_cache_hosts
        .iter()
        .map(String::len)
        .max()
        .unwrap_or(0);
    if c.lost_cache_hosts.len() > MAX_LOST_CACHE_HOSTS || longest > MAX_HOST_NAME {
        return Err(CounterError::LostCacheHosts {
            count: c.lost_cache_hosts.len(),
            longest,
        });
    }
    Ok(())
}

/// Total rays in `r`, all kinds.
pub fn total_rays(r: &RayCounts) -> u64 {
    r.by_kind().iter().fold(0u64, |a, &b| a.saturating_add(b))
}

/// Per-worker sums for one job, and the job's totals kept as reports arrive, so the
/// totals cost the same to publish for 10,000 workers as for one; the per-worker detail
/// ([`JobMetrics::fill_detail`]) is O(workers) and published less often.
#[derive(Clone, Debug, Default)]
pub struct JobMetrics {
    workers: BTreeMap<String, WorkerJobStats>,
    rays_sent: u64,
    rays_forwarded: u64,
    domain_loads: u64,
    /// Load seconds in whole nanoseconds (integers: the sum does not depend on the order
    /// reports arrived in).
    domain_load_ns: u64,
    domains_warm: u64,
    evictions: u64,
    queue_peak: u64,
}

impl JobMetrics {
    /// Make sure `worker` is listed (with zeros until it reports).
    pub fn add_worker(&mut self, worker: &str) {
        self.entry(worker);
    }

    fn entry(&mut self, worker: &str) -> &mut WorkerJobStats {
        self.workers
            .entry(worker.to_string())
            .or_insert_with(|| WorkerJobStats {
                worker_id: worker.to_string(),
                ..Default::default()
            })
    }

    /// Workers that took part.
    pub fn workers(&self) -> usize {
        self.workers.len()
    }

    /// Rays traced per worker (all kinds), in worker id order.
    pub fn traced(&self) -> impl Iterator<Item = (String, u64)> + '_ {
        self.workers
            .iter()
            .map(|(id, w)| (id.clone(), w.rays_traced))
    }

    /// Add one report's counters (checked with [`check`]) and traced rays.
    pub fn add(&mut self, worker: &str, c: Option<&WorkerCounters>, traced: Option<&RayCounts>) {
        if let Some(c) = c {
            self.rays_sent = self.rays_sent.saturating_add(c.rays_sent);
            self.rays_forwarded = self.rays_forwarded.saturating_add(c.rays_forwarded);
            self.domain_loads = self.domain_loads.saturating_add(c.domain_loads);
            // `check` made it finite and non-negative.
            self.domain_load_ns = self
                .domain_load_ns
                .saturating_add((c.domain_load_seconds * 1e9).round() as u64);
            self.domains_warm = self.domains_warm.saturating_add(c.domains_warm);
            self.evictions = self.evictions.saturating_add(c.evictions);
            self.queue_peak = self.queue_peak.max(c.queue_peak);
        }
        let w = self.entry(worker);
        if let Some(c) = c {
            w.domain_loads = w.domain_loads.saturating_add(c.domain_loads);
            w.domains_warm = w.domains_warm.saturating_add(c.domains_warm);
            w.domain_load_seconds += c.domain_load_seconds;
            w.evictions = w.evictions.saturating_add(c.evictions);
            w.idle_seconds += c.idle_seconds;
            w.queue_peak = w.queue_peak.max(c.queue_peak);
        }
        if let Some(t) = traced {
            w.rays_traced = w.rays_traced.saturating_add(total_rays(t));
        }
    }

    /// Write the totals into `s` (the fields this type owns except the per-worker
    /// detail; the rest is left alone). O(1).
    pub fn fill_totals(&self, s: &mut JobStats) {
        s.domain_loads = self.domain_loads;
        s.domain_load_seconds = self.domain_load_ns as f64 * 1e-9;
        s.domains_warm = self.domains_warm;
        s.evictions = self.evictions;
        s.queue_peak = self.queue_peak;
        s.rays_exchanged = self.rays_sent;
        s.rays_forwarded = self.rays_forwarded;
        s.workers = self.workers.len() as u32;
    }

    /// Write the per-worker detail into `s` (`workers_detail`, in worker id order).
    /// O(workers).
    pub fn fill_detail(&self, s: &mut JobStats) {
        s.workers_detail = self.workers.values().cloned().collect();
    }

    /// Write everything into `s`: [`JobMetrics::fill_totals`] and
    /// [`JobMetrics::fill_detail`].
    pub fn fill(&self, s: &mut JobStats) {
        self.fill_totals(s);
        self.fill_detail(s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `RayCounts::by_kind` and `from_kinds` (in dray-proto, which knows no engine) put
    /// each kind where render.proto numbers its field: kind `k`, field `k + 1`, named as
    /// the engine names the kind.
    #[test]
    fn ray_counts_follow_the_engines_ray_kinds() {
        use dray_core::integrator::RayKind;
        use prost::Message;
        let fds = prost_types::FileDescriptorSet::decode(dray_proto::FILE_DESCRIPTOR_SET)
            .expect("the descriptor set decodes");
        let fields = &fds
            .file
            .iter()
            .filter(|f| f.package() == "dray.v1")
            .flat_map(|f| &f.message_type)
            .find(|m| m.name() == "RayCounts")
            .expect("render.proto has RayCounts")
            .field;
        assert_eq!(fields.len(), RayKind::COUNT);
        for k in RayKind::ALL {
            let number = k as i32 + 1;
            let field = fields.iter().find(|f| f.number() == number);
            assert_eq!(field.map(|f| f.name()), Some(k.name()), "field {number}");
            let mut one = [0; RayKind::COUNT];
            one[k as usize] = 1;
            let counts = RayCounts::from_kinds(one);
            // A varint field: its key (number << 3), then the value 1.
            assert_eq!(counts.encode_to_vec(), [(number << 3) as u8, 1], "{k:?}");
            assert_eq!(counts.by_kind(), one);
        }
    }

    #[test]
    fn deltas_sum_and_peaks_take_the_max() {
        let mut m = JobMetrics::default();
        m.add_worker("b");
        let c = |loads, peak| WorkerCounters {
            domain_loads: loads,
            domain_load_seconds: 0.5,
            evictions: 1,
            rays_sent: 10,
            rays_forwarded: 2,
            idle_seconds: 0.25,
            queue_peak: peak,
            ..Default::default()
        };
        let traced = RayCounts {
            camera: 3,
            shadow: 4,
            ..Default::default()
        };
        m.add("a", Some(&c(2, 50)), Some(&traced));
        m.add("a", Some(&c(1, 40)), None);
        let mut s = JobStats::default();
        m.fill(&mut s);
        assert_eq!((s.domain_loads, s.evictions, s.queue_peak), (3, 2, 50));
        assert_eq!((s.rays_exchanged, s.rays_forwarded, s.workers), (20, 4, 2));
        assert_eq!(s.domain_load_seconds, 1.0);
        let a = &s.workers_detail[0];
        assert_eq!(
            (a.worker_id.as_str(), a.rays_traced, a.idle_seconds),
            ("a", 7, 0.5)
        );
        assert_eq!(s.workers_detail[1].worker_id, "b");
        assert!(
            check(&WorkerCounters {
                idle_seconds: f64::NAN,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            check(&WorkerCounters {
                lost_cache_hosts: vec!["http://h:1".into(); MAX_LOST_CACHE_HOSTS + 1],
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            check(&WorkerCounters {
                lost_cache_hosts: vec!["x".repeat(MAX_HOST_NAME + 1)],
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            check(&WorkerCounters {
                lost_cache_hosts: vec!["http://h:1".into(); MAX_LOST_CACHE_HOSTS],
                ..Default::default()
            })
            .is_ok()
        );
    }
}

/// The coordinator's OpenTelemetry metrics, through the global meter: a no-op unless the
/// process installed a meter provider (`dray coordinator --otlp-endpoint`). The workers
/// export their own counters (rays, bytes, domain loads, queues); these are the job-level
/// ones only the coordinator sees.
pub mod otel {
    use std::sync::OnceLock;
    use std::time::Duration;

    use dray_proto::v1::JobState;
    use opentelemetry::KeyValue;
    use opentelemetry::metrics::{Histogram, UpDownCounter};

    struct Instruments {
        job_duration: Histogram<f64>,
        jobs_active: UpDownCounter<i64>,
        queue_wait: Histogram<f64>,
    }

    fn instruments() -> &'static Instruments {
        static I: OnceLock<Instruments> = OnceLock::new();
        I.get_or_init(|| {
            let m = opentelemetry::global::meter("dray-coordinator");
            Instruments {
                job_duration: m
                    .f64_histogram("dray.coordinator.job.duration")
                    .with_description("Time from a job's start to its end, by final state")
                    .with_unit("s")
                    .with_boundaries(vec![
                        0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0,
                    ])
                    .build(),
                jobs_active: m
                    .i64_up_down_counter("dray.coordinator.jobs.active")
                    .with_description("Jobs queued, preparing or running")
                    .with_unit("{job}")
                    .build(),
                queue_wait: m
                    .f64_histogram("dray.coordinator.job.queue_wait")
                    .with_description(
                        "Time a job waited in a deal queue for a render slot, by queue \
                         (process: the coordinator's own renderer; cluster: \
                         --max-running-jobs)",
                    )
                    .with_unit("s")
                    .with_boundaries(vec![
                        0.01, 0.1, 0.5, 1.0, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0,
                    ])
                    .build(),
            }
        })
    }

    /// A job was accepted.
    pub fn job_accepted() {
        instruments().jobs_active.add(1, &[]);
    }

    /// A job was dealt a slot of deal queue `queue` after waiting `waited`.
    pub fn job_dealt(queue: &'static str, waited: Duration) {
        instruments()
            .queue_wait
            .record(waited.as_secs_f64(), &[KeyValue::new("queue", queue)]);
    }

    /// A job ended in `state` after running for `elapsed`.
    pub fn job_ended(state: JobState, elapsed: Duration) {
        let i = instruments();
        i.jobs_active.add(-1, &[]);
        let state = state
            .as_str_name()
            .trim_start_matches("JOB_STATE_")
            .to_lowercase();
        i.job_duration
            .record(elapsed.as_secs_f64(), &[KeyValue::new("state", state)]);
    }
}
