//! What one running job tells `ListWorkers`: which worker owns which domain, each
//! worker's latest queue report and the rays each worker traced. The job's actor makes
//! this snapshot when asked ([`super::JobEvent::View`]), so nothing is copied while no
//! one looks: at 10,000 workers a copy per report would cost more than the job.

use std::collections::BTreeMap;
use std::time::SystemTime;

use dray_proto::v1::DomainQueue;

/// One running job's domains and workers, as of one moment.
#[derive(Clone, Debug, Default)]
pub struct JobView {
    /// The job.
    pub job_id: String,
    /// When it was submitted (ListWorkers lists jobs newest first).
    pub submitted_at: Option<SystemTime>,
    /// Its schedule's name, routing table version and attempt.
    pub schedule: String,
    pub version: u64,
    pub attempt: u32,
    /// Domains in the job.
    pub domains: u32,
    /// Image-plane: every worker traces its own rays in every domain (no owners).
    pub local: bool,
    /// Owners by domain (index = domain); empty when `local`.
    pub owners: Vec<Vec<String>>,
    /// The job's workers, in job order.
    pub workers: Vec<String>,
    /// Each worker's latest queue report (this attempt).
    pub queues: BTreeMap<String, Vec<DomainQueue>>,
    /// Rays each worker traced for the job so far (all attempts).
    pub traced: BTreeMap<String, u64>,
}

impl JobView {
    /// Rays waiting for each domain (index = domain) over all the job's workers, in one
    /// pass over the queue reports. Reports naming a domain beyond the job's count are
    /// left out.
    pub fn queued_by_domain(&self) -> Vec<u64> {
        let mut out = vec![0u64; self.domains as usize];
        for q in self.queues.values().flatten() {
            if let Some(n) = out.get_mut(q.domain as usize) {
                *n = n.saturating_add(q.rays_queued);
            }
        }
        out
    }

    /// Whether the routing table names `worker` an owner of domain `d`.
    pub fn owns(&self, worker: &str, d: u32) -> bool {
        self.owners
            .get(d as usize)
            .is_some_and(|o| o.iter().any(|w| w == worker))
    }
}
