//! Routing tables: who owns which domain of a job, and the versioned table sent to its
//! workers (cluster.proto `RoutingTable`).
//!
//! [`Ownership`] is the ownership alone, the value a [`policy`](super::policy) computes
//! (the worker's `routing::Routes` is its view of the table it receives);
//! [`JobRouting`] adds what makes it a message (job, attempt, version, endpoints). Only
//! [`JobRouting`] bumps versions, so "a new table" always means "version + 1".

use std::collections::BTreeSet;

use dray_proto::v1::{DomainRoute, RoutingTable, WorkerEndpoint};

use crate::caches::placement::Placement;
pub use crate::ownership::Ownership;

/// A job's current routing table: [`Ownership`] plus the job, the attempt, the version,
/// the workers' endpoints and the attempt's cache placement.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobRouting {
    job_id: String,
    attempt: u32,
    version: u64,
    workers: Vec<WorkerEndpoint>,
    routes: Ownership,
    /// Where the attempt's cache actors live (empty: no caches). Set once per attempt,
    /// before its first table goes out, and kept by every later table of the attempt.
    caches: Placement,
}

impl JobRouting {
    /// The first table of a job: version 1, attempt 0.
    pub fn new(job_id: &str, workers: Vec<WorkerEndpoint>, routes: Ownership) -> JobRouting {
        JobRouting {
            job_id: job_id.to_string(),
            attempt: 0,
            version: 1,
            workers,
            routes,
            caches: Placement::none(),
        }
    }

    /// Make the first table attempt `attempt`'s, before it is sent: a job a restarted
    /// coordinator takes back starts past the attempts workers may still remember.
    pub fn set_first_attempt(&mut self, attempt: u32) {
        self.attempt = attempt;
    }

    /// The version (1 for the first table; never decreases, across attempts too).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The job attempt the table belongs to.
    pub fn attempt(&self) -> u32 {
        self.attempt
    }

    /// The ownership.
    pub fn routes(&self) -> &Ownership {
        &self.routes
    }

    /// The job's workers, in the order tiles and round robin deal over them.
    pub fn workers(&self) -> &[WorkerEndpoint] {
        &self.workers
    }

    /// The workers' ids, in order.
    pub fn worker_ids(&self) -> Vec<String> {
        self.workers.iter().map(|w| w.worker_id.clone()).collect()
    }

    /// Whether `worker` is one of the job's workers.
    pub fn has_worker(&self, worker: &str) -> bool {
        self.workers.iter().any(|w| w.worker_id == worker)
    }

    /// Replace the ownership: a new version. Returns the new version.
    pub fn set_routes(&mut self, routes: Ownership) -> u64 {
        self.routes = routes;
        self.version += 1;
        self.version
    }

    /// Add a worker at the end of the list (it owns nothing yet): a new version.
    pub fn add_worker(&mut self, worker: WorkerEndpoint) -> u64 {
        self.workers.push(worker);
        self.version += 1;
        self.version
    }

    /// Remove a worker that owns nothing from the list: a new version. None (and no
    /// change) when it is not listed or owns a domain.
    pub fn remove_worker(&mut self, worker: &str) -> Option<u64> {
        let i = self.workers.iter().position(|w| w.worker_id == worker)?;
        if self.routes.owned_by(worker).next().is_some() {
            return None;
        }
        self.workers.remove(i);
        self.version += 1;
        Some(self.version)
    }

    /// Start attempt `attempt` over `workers` with `routes`: a new version, with no
    /// caches until [`JobRouting::set_caches`] places the new attempt's.
    pub fn restart(
        &mut self,
        attempt: u32,
        workers: Vec<WorkerEndpoint>,
        routes: Ownership,
    ) -> u64 {
        self.attempt = attempt;
        self.workers = workers;
        self.routes = routes;
        self.caches = Placement::none();
        self.version += 1;
        self.version
    }

    /// Set the attempt's cache placement. Not a new version: it is set before any table
    /// of the attempt is sent, and never changes while the attempt runs.
    pub fn set_caches(&mut self, caches: Placement) {
        self.caches = caches;
    }

    /// The attempt's cache placement.
    pub fn caches(&self) -> &Placement {
        &self.caches
    }

    /// The message workers receive.
    pub fn table(&self) -> RoutingTable {
        RoutingTable {
            job_id: self.job_id.clone(),
            version: self.version,
            workers: self.workers.clone(),
            routes: self.routes.to_proto(),
            attempt: self.attempt,
            local: self.routes.is_local(),
            cache_hosts: self.caches.hosts().to_vec(),
            wall_hosts: self.caches.wall_hosts().to_vec(),
            cache_replicas: self.caches.is_replicated(),
            base_version: 0,
        }
    }

    /// The delta that takes a worker from table `base_version` to this one when only
    /// `domains` changed owners: their owners, in order (one entry with an empty worker
    /// id for a domain left with none), and nothing else (cluster.proto,
    /// `RoutingTable.base_version`). A round sends this to every worker instead of the
    /// whole table: bytes proportional to what moved, and no O(domains) copy.
    pub fn delta(&self, base_version: u64, domains: &BTreeSet<u32>) -> RoutingTable {
        let mut routes = Vec::new();
        for &d in domains {
            let owners = self.routes.owners(d);
            if owners.is_empty() {
                routes.push(DomainRoute {
                    domain: d,
                    worker_id: String::new(),
                });
            }
            routes.extend(owners.iter().map(|w| DomainRoute {
                domain: d,
                worker_id: w.clone(),
            }));
        }
        RoutingTable {
            job_id: self.job_id.clone(),
            version: self.version,
            attempt: self.attempt,
            base_version,
            routes,
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_delta_lists_every_owner_of_the_changed_domains_and_nothing_else() {
        let mut routing = JobRouting::new(
            "j",
            ["a", "b"]
                .iter()
                .map(|w| WorkerEndpoint {
                    worker_id: w.to_string(),
                    endpoint: format!("http://{w}"),
                })
                .collect(),
            Ownership::from_owners(vec![
                vec!["a".into()],
                vec!["a".into(), "b".into()],
                vec![],
                vec!["b".into()],
            ]),
        );
        routing.set_routes(Ownership::from_owners(vec![
            vec!["a".into()],
            vec!["a".into(), "b".into()],
            vec![],
            vec![],
        ]));
        let d = routing.delta(1, &[1, 3].into_iter().collect());
        assert_eq!((d.version, d.base_version), (2, 1));
        assert!(d.workers.is_empty() && d.cache_hosts.is_empty());
        let got: Vec<(u32, &str)> = d
            .routes
            .iter()
            .map(|r| (r.domain, r.worker_id.as_str()))
            .collect();
        assert_eq!(got, vec![(1, "a"), (1, "b"), (3, "")]);
    }

    fn ids(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn round_robin_deals_domains_in_turn() {
        let r = Ownership::round_robin(7, &ids(&["a", "b", "c"]));
        let owners: Vec<String> = r.to_proto().into_iter().map(|r| r.worker_id).collect();
        assert_eq!(owners, ["a", "b", "c", "a", "b", "c", "a"]);
        assert!(
            r.to_proto()
                .iter()
                .enumerate()
                .all(|(i, r)| r.domain == i as u32)
        );
        assert_eq!(r.owned_by("b").collect::<Vec<_>>(), [1, 4]);
        assert!(Ownership::round_robin(3, &[]).to_proto().is_empty());
    }

    #[test]
    fn versions_only_grow() {
        let ws = vec![WorkerEndpoint {
            worker_id: "a".into(),
            endpoint: "http://a:1".into(),
        }];
        let mut t = JobRouting::new("j", ws.clone(), Ownership::round_robin(2, &ids(&["a"])));
        assert_eq!((t.version(), t.attempt()), (1, 0));
        assert_eq!(t.set_routes(Ownership::local()), 2);
        let m = t.table();
        assert!(m.local && m.routes.is_empty());
        assert_eq!(t.restart(1, ws, Ownership::round_robin(2, &ids(&["a"]))), 3);
        let m = t.table();
        assert_eq!(
            (m.version, m.attempt, m.local, m.routes.len()),
            (3, 1, false, 2)
        );
    }

    #[test]
    fn every_table_of_an_attempt_carries_its_cache_placement() {
        use crate::caches::placement::Candidates;
        let ws = vec![WorkerEndpoint {
            worker_id: "a".into(),
            endpoint: "http://a:1".into(),
        }];
        let mut t = JobRouting::new("j", ws.clone(), Ownership::round_robin(2, &ids(&["a"])));
        assert!(t.table().cache_hosts.is_empty() && t.table().wall_hosts.is_empty());
        let c = Candidates::choose(Vec::new(), &[("a".into(), "http://a:2".into())]);
        let p = Placement::place(2, &c, &c.beside(t.routes(), 2));
        t.set_caches(p.clone());
        assert_eq!(t.version(), 1, "placing caches is not a new table");
        t.set_routes(Ownership::local());
        let m = t.table();
        assert_eq!(m.cache_hosts[0].endpoint, "http://a:2");
        assert_eq!(m.wall_hosts, [0; 12]);
        // A new attempt starts with none (until its own are placed).
        t.restart(1, ws, Ownership::round_robin(2, &ids(&["a"])));
        assert!(t.table().cache_hosts.is_empty());
        assert!(t.caches().is_empty());
    }
}
