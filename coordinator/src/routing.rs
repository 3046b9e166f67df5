//! Domain assignment: which worker owns each domain of a job.
//!
//! Behind one trait, [`Router`], so the dynamic ray-weighted scheduler (a later issue)
//! replaces the static [`RoundRobin`] without touching dispatch or accounting. Tables are
//! versioned (cluster.proto `RoutingTable.version`); the first table of a job is version 1.

use dray_proto::v1::{DomainRoute, RoutingTable, WorkerEndpoint};

/// Decides domain ownership for a job.
pub trait Router: Send + Sync {
    /// The first routing table of job `job_id` over `domain_count` domains and the job's
    /// `workers` (non-empty, in a deterministic order). Version 1.
    fn initial(&self, job_id: &str, domain_count: u32, workers: &[WorkerEndpoint]) -> RoutingTable;
}

/// Static round robin: domain `d` goes to `workers[d % n]`. With several domains per
/// worker (the normal case) this spreads neighbouring kd/grid cells over workers, which
/// evens out load better than contiguous blocks when the interesting part of a scene is
/// small.
#[derive(Clone, Copy, Debug, Default)]
pub struct RoundRobin;

impl Router for RoundRobin {
    fn initial(&self, job_id: &str, domain_count: u32, workers: &[WorkerEndpoint]) -> RoutingTable {
        let routes = if workers.is_empty() {
            Vec::new()
        } else {
            (0..domain_count)
                .map(|d| DomainRoute {
                    domain: d,
                    worker_id: workers[d as usize % workers.len()].worker_id.clone(),
                })
                .collect()
        };
        RoutingTable {
            job_id: job_id.to_string(),
            version: 1,
            workers: workers.to_vec(),
            routes,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_robin_deals_domains_in_turn() {
        let ws: Vec<WorkerEndpoint> = ["a", "b", "c"]
            .iter()
            .map(|id| WorkerEndpoint {
                worker_id: id.to_string(),
                endpoint: format!("http://{id}:1"),
            })
            .collect();
        let t = RoundRobin.initial("j", 7, &ws);
        assert_eq!(t.version, 1);
        assert_eq!(t.job_id, "j");
        let owners: Vec<&str> = t.routes.iter().map(|r| r.worker_id.as_str()).collect();
        assert_eq!(owners, ["a", "b", "c", "a", "b", "c", "a"]);
        assert!(
            t.routes
                .iter()
                .enumerate()
                .all(|(i, r)| r.domain == i as u32)
        );
        assert_eq!(t.workers.len(), 3);
    }
}
