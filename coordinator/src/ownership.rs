//! Who owns which domain of a job: the value a scheduling policy
//! ([`crate::scheduler::policy`]) computes, before it is a versioned table
//! ([`crate::scheduler::table::JobRouting`]). A leaf module beside `scheduler/` and
//! `caches/`, both of which read it: cache placement (`crate::caches::placement`) reads
//! ownership alone, and the scheduler's tables carry that placement, so with this type
//! inside either folder the two would import each other.

use dray_proto::v1::DomainRoute;

/// The owners of every domain of a job, by worker id, or "local" (image-plane: every
/// worker traces its own rays, nothing is routed).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Ownership {
    local: bool,
    /// Index = domain. Each list is non-empty for a routed job (more than one owner when
    /// a hot domain is replicated) and has no duplicates.
    owners: Vec<Vec<String>>,
}

impl Ownership {
    /// No routing: every worker traces every ray it makes (image-plane).
    pub fn local() -> Ownership {
        Ownership {
            local: true,
            owners: Vec::new(),
        }
    }

    /// Explicit owners, index = domain.
    pub fn from_owners(owners: Vec<Vec<String>>) -> Ownership {
        Ownership {
            local: false,
            owners,
        }
    }

    /// Domain `d` to `workers[d % n]`. With several domains per worker (the normal case)
    /// this spreads neighbouring kd or grid cells over workers, which evens out load
    /// better than contiguous blocks when the interesting part of a scene is small.
    /// No workers: no owners (a table nobody can use, but no panic).
    pub fn round_robin(domains: u32, workers: &[String]) -> Ownership {
        let owners = if workers.is_empty() {
            Vec::new()
        } else {
            (0..domains as usize)
                .map(|d| vec![workers[d % workers.len()].clone()])
                .collect()
        };
        Ownership::from_owners(owners)
    }

    /// Whether rays stay where they are made (image-plane).
    pub fn is_local(&self) -> bool {
        self.local
    }

    /// Domains with an owner list (0 when local).
    pub fn domains(&self) -> usize {
        self.owners.len()
    }

    /// The owners of domain `d` (empty when local or out of range).
    pub fn owners(&self, d: u32) -> &[String] {
        self.owners.get(d as usize).map_or(&[], Vec::as_slice)
    }

    /// Every domain's owners, index = domain.
    pub fn all_owners(&self) -> &[Vec<String>] {
        &self.owners
    }

    /// Whether `worker` owns domain `d`.
    pub fn owns(&self, worker: &str, d: u32) -> bool {
        self.owners(d).iter().any(|o| o == worker)
    }

    /// The domains `worker` owns, ascending.
    pub fn owned_by<'a>(&'a self, worker: &'a str) -> impl Iterator<Item = u32> + 'a {
        self.owners
            .iter()
            .enumerate()
            .filter(move |(_, o)| o.iter().any(|w| w == worker))
            .map(|(d, _)| d as u32)
    }

    /// The wire form: one entry per (domain, owner), by domain, owners in order.
    pub fn to_proto(&self) -> Vec<DomainRoute> {
        self.owners
            .iter()
            .enumerate()
            .flat_map(|(d, owners)| {
                owners.iter().map(move |w| DomainRoute {
                    domain: d as u32,
                    worker_id: w.clone(),
                })
            })
            .collect()
    }
}
