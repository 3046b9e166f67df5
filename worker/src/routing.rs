//! A job's routing table as the worker uses it: who traces each domain, and where to
//! reach them.
//!
//! The coordinator's scheduler sends a new table (a larger version) whenever it moves or
//! replicates domains; a worker swaps it in while the job runs ([`Routes`] behind an
//! `Arc`, replaced whole), so a tracing step always sees one consistent table. Rays for a
//! domain this worker does not own under the current table go to an owner, whether they
//! were made here or arrived from a peer that used an older table (forwarding).
//!
//! Under the image-plane schedule the table is *local*: every worker owns every domain
//! for the rays it makes, so no ray leaves the worker that made it. A table may also
//! leave a domain without an owner: its rays are *held* where they are made until a
//! later table gives the domain to a worker.

use std::collections::HashMap;

use dray_proto::v1::RoutingTable;

/// Why a table cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RoutingError {
    #[error("routing table version {version} names domain {domain}, but the job has {domains}")]
    UnknownDomain {
        version: u64,
        domain: u32,
        domains: u32,
    },
    #[error(
        "routing table version {version} has {walls} wall placements and {hosts} cache hosts for {domains} domains (want 6 per domain, each naming a listed host)"
    )]
    BadWalls {
        version: u64,
        walls: usize,
        hosts: usize,
        domains: u32,
    },
    #[error(
        "routing table version {version} gives domain {domain} to worker {worker:?}, which it does not list"
    )]
    UnknownWorker {
        version: u64,
        domain: u32,
        worker: String,
    },
}

/// A peer: id and endpoint.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Peer {
    pub id: String,
    pub endpoint: String,
}

/// One version of a job's routing table, resolved for this worker.
#[derive(Clone, Debug)]
pub struct Routes {
    /// The table's version.
    pub version: u64,
    /// Image-plane: every ray stays here.
    pub local: bool,
    /// Per domain, indices into `peers` of its owners (one, or several for a
    /// replicated domain), in the table's order.
    owners: Vec<Vec<u32>>,
    peers: Vec<Peer>,
    /// This worker's index in `peers`, if listed.
    me: Option<u32>,
    /// Cache hosts' endpoints, and per wall (6 per domain) the index of its host; both
    /// empty when the job has no ray caches.
    cache_hosts: Vec<String>,
    wall_hosts: Vec<u32>,
    /// Sender placement: every cache host holds a replica of every wall.
    replicas: bool,
    /// Under sender placement, the index in `cache_hosts` of this worker's own host.
    my_host: Option<u32>,
}

impl Routes {
    /// Resolve `table` for worker `me` of a job with `domains` domains.
    pub fn new(table: &RoutingTable, me: &str, domains: u32) -> Result<Routes, RoutingError> {
        let peers: Vec<Peer> = table
            .workers
            .iter()
            .map(|w| Peer {
                id: w.worker_id.clone(),
                endpoint: w.endpoint.clone(),
            })
            .collect();
        let index: HashMap<&str, u32> = peers
            .iter()
            .enumerate()
            .map(|(i, p)| (p.id.as_str(), i as u32))
            .collect();
        let mut owners = vec![Vec::new(); domains as usize];
        if !table.local {
            for r in &table.routes {
                let slot =
                    owners
                        .get_mut(r.domain as usize)
                        .ok_or(RoutingError::UnknownDomain {
                            version: table.version,
                            domain: r.domain,
                            domains,
                        })?;
                let w = index.get(r.worker_id.as_str()).copied().ok_or_else(|| {
                    RoutingError::UnknownWorker {
                        version: table.version,
                        domain: r.domain,
                        worker: r.worker_id.clone(),
                    }
                })?;
                if !slot.contains(&w) {
                    slot.push(w);
                }
            }
        }
        let cache_hosts: Vec<String> = table
            .cache_hosts
            .iter()
            .map(|h| h.endpoint.clone())
            .collect();
        let walls_ok = (table.wall_hosts.is_empty() && cache_hosts.is_empty())
            || (table.wall_hosts.len() == 6 * domains as usize
                && table
                    .wall_hosts
                    .iter()
                    .all(|&h| (h as usize) < cache_hosts.len()));
        if !walls_ok {
            return Err(RoutingError::BadWalls {
                version: table.version,
                walls: table.wall_hosts.len(),
                hosts: cache_hosts.len(),
                domains,
            });
        }
        // A host beside a worker is listed under the worker's id.
        let my_host = table
            .cache_hosts
            .iter()
            .position(|h| h.host_id == me)
            .map(|i| i as u32)
            .filter(|_| table.cache_replicas);
        Ok(Routes {
            version: table.version,
            local: table.local,
            me: index.get(me).copied(),
            owners,
            peers,
            cache_hosts,
            wall_hosts: table.wall_hosts.clone(),
            replicas: table.cache_replicas,
            my_host,
        })
    }

    /// Whether rays crossing walls go to cache actors under this table.
    pub fn has_caches(&self) -> bool {
        !self.wall_hosts.is_empty()
    }

    /// The endpoint of the cache host serving `wall`, if the job has caches.
    pub fn cache_host(&self, wall: u32) -> Option<&str> {
        self.cache_host_index(wall)
            .and_then(|h| self.cache_host_endpoint(h))
    }

    /// The index (into the table's cache hosts) of the wall's home host: its only
    /// actor under remote placement, the replica used by workers with no host of their
    /// own under sender placement.
    pub fn cache_host_index(&self, wall: u32) -> Option<u32> {
        self.wall_hosts.get(wall as usize).copied()
    }

    /// The index of the host this worker looks `wall` up at: its own host's replica
    /// under sender placement (a lookup in this process), else the wall's home.
    pub fn lookup_host_index(&self, wall: u32) -> Option<u32> {
        match self.my_host {
            Some(h) if (wall as usize) < self.wall_hosts.len() => Some(h),
            _ => self.cache_host_index(wall),
        }
    }

    /// The endpoint of the host holding `ticket`'s actor: the replica its bits name,
    /// or its wall's home when it names none.
    pub fn ticket_host(&self, ticket: u64) -> Option<&str> {
        match dray_cache::ticket_id::ticket_replica(ticket) {
            0 => self.cache_host(dray_cache::ticket_id::ticket_wall(ticket)),
            r => self.cache_host_endpoint(r - 1),
        }
    }

    /// The endpoint of the cache host beside this worker, when it holds a replica of
    /// every wall (sender placement).
    pub fn my_host_endpoint(&self) -> Option<&str> {
        self.my_host.and_then(|h| self.cache_host_endpoint(h))
    }

    /// Whether every cache host holds a replica of every wall (sender placement).
    pub fn cache_replicas(&self) -> bool {
        self.replicas
    }

    /// The endpoints of every cache host in the table.
    pub fn cache_host_endpoints(&self) -> &[String] {
        &self.cache_hosts
    }

    /// The endpoint of cache host `index`.
    pub fn cache_host_endpoint(&self, index: u32) -> Option<&str> {
        self.cache_hosts.get(index as usize).map(String::as_str)
    }

    /// Cache hosts in the table.
    pub fn cache_host_count(&self) -> usize {
        self.cache_hosts.len()
    }

    /// Whether this worker traces rays bound for domain `d`.
    pub fn owns(&self, d: u32) -> bool {
        self.local
            || self
                .me
                .is_some_and(|me| self.owners.get(d as usize).is_some_and(|o| o.contains(&me)))
    }

    /// The domains this worker owns, ascending (every domain under a local table).
    pub fn owned(&self) -> Vec<u32> {
        (0..self.owners.len() as u32)
            .filter(|&d| self.owns(d))
            .collect()
    }

    /// The peer that should trace rays bound for `d` that this worker does not own;
    /// `spread` picks among the owners of a replicated domain (any value will do: the
    /// image does not depend on who traces what). None under a local table, for a
    /// domain the table does not have, and for a domain it gives to no worker (see
    /// [`Routes::is_held`]).
    pub fn owner(&self, d: u32, spread: u32) -> Option<&Peer> {
        if self.local {
            return None;
        }
        let o = self.owners.get(d as usize)?;
        let pick = o.get(spread as usize % o.len().max(1))?;
        self.peers.get(*pick as usize)
    }

    /// Whether rays for `d` wait where they are: a table may leave a domain without an
    /// owner (a scheduler that gives workers only the domains they can hold), and its
    /// rays then stay queued at the worker that made them, counted in its queue report,
    /// until a later table gives the domain to someone.
    pub fn is_held(&self, d: u32) -> bool {
        !self.local && self.owners.get(d as usize).is_some_and(Vec::is_empty)
    }

    /// Every peer of the job.
    pub fn peers(&self) -> &[Peer] {
        &self.peers
    }
}

/// The whole table that `delta` (cluster.proto, `RoutingTable.base_version`) leads to
/// from `base`; None when `base` is not its base (another version, attempt or job).
pub fn patch(base: &RoutingTable, delta: &RoutingTable) -> Option<RoutingTable> {
    if base.version != delta.base_version
        || base.attempt != delta.attempt
        || base.job_id != delta.job_id
    {
        return None;
    }
    let moved: std::collections::HashSet<u32> = delta.routes.iter().map(|r| r.domain).collect();
    let mut t = base.clone();
    t.routes.retain(|r| !moved.contains(&r.domain));
    t.routes.extend(
        delta
            .routes
            .iter()
            .filter(|r| !r.worker_id.is_empty())
            .cloned(),
    );
    t.version = delta.version;
    t.base_version = 0;
    Some(t)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use dray_proto::v1::{DomainRoute, WorkerEndpoint};

    /// A table of workers a and b, each domain routed to the workers listed for it.
    pub(crate) fn table(routes: &[(u32, &str)], local: bool) -> RoutingTable {
        RoutingTable {
            job_id: "j".into(),
            version: 3,
            workers: ["a", "b"]
                .iter()
                .map(|w| WorkerEndpoint {
                    worker_id: w.to_string(),
                    endpoint: format!("http://{w}"),
                })
                .collect(),
            routes: routes
                .iter()
                .map(|(d, w)| DomainRoute {
                    domain: *d,
                    worker_id: w.to_string(),
                })
                .collect(),
            attempt: 0,
            local,
            ..Default::default()
        }
    }

    #[test]
    fn owners_and_replicas() {
        let t = table(&[(0, "a"), (1, "b"), (2, "a"), (2, "b")], false);
        let r = Routes::new(&t, "a", 3).unwrap();
        assert_eq!(r.owned(), vec![0, 2]);
        assert!(!r.owns(1));
        assert_eq!(r.owner(1, 7).map(|p| p.id.as_str()), Some("b"));
        let picks: Vec<&str> = (0..2).map(|s| r.owner(2, s).unwrap().id.as_str()).collect();
        assert_eq!(
            picks,
            ["a", "b"],
            "a replicated domain spreads over its owners"
        );
    }

    #[test]
    fn a_local_table_owns_everything() {
        let r = Routes::new(&table(&[], true), "b", 4).unwrap();
        assert_eq!(r.owned(), vec![0, 1, 2, 3]);
        assert!(r.owner(1, 0).is_none());
    }

    #[test]
    fn a_domain_without_an_owner_is_held() {
        let r = Routes::new(&table(&[(0, "a")], false), "b", 2).unwrap();
        assert!(r.is_held(1) && !r.is_held(0));
        assert!(!r.owns(1));
        assert!(r.owner(1, 0).is_none());
        assert!(!Routes::new(&table(&[], true), "b", 2).unwrap().is_held(1));
    }

    #[test]
    fn bad_tables_are_errors() {
        let e = Routes::new(&table(&[(0, "a"), (5, "a")], false), "a", 2).unwrap_err();
        assert!(matches!(e, RoutingError::UnknownDomain { domain: 5, .. }));
        let e = Routes::new(&table(&[(0, "z")], false), "a", 1).unwrap_err();
        assert!(e.to_string().contains("\"z\""), "{e}");
    }

    #[test]
    fn a_delta_patches_its_base_and_only_its_base() {
        let mut base = table(&[(0, "a"), (1, "a"), (1, "b"), (2, "b")], false);
        base.version = 4;
        let delta = RoutingTable {
            job_id: base.job_id.clone(),
            version: 5,
            base_version: 4,
            attempt: base.attempt,
            routes: vec![
                DomainRoute {
                    domain: 0,
                    worker_id: "b".into(),
                },
                DomainRoute {
                    domain: 1,
                    worker_id: String::new(),
                },
            ],
            ..Default::default()
        };
        let t = patch(&base, &delta).expect("its base");
        assert_eq!((t.version, t.base_version), (5, 0));
        assert_eq!(t.workers, base.workers, "the base's workers hold");
        let r = Routes::new(&t, "b", 3).unwrap();
        assert!(r.owns(0) && r.owns(2), "b was given 0 and keeps 2");
        assert!(r.is_held(1), "1 has no owner now");
        let mut other = base.clone();
        other.version = 3;
        assert!(
            patch(&other, &delta).is_none(),
            "not its base: ask for the whole table"
        );
    }
}
