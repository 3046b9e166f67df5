//! One job's ray caches, as the job's actor holds them next to its credit: the resolved
//! knobs, the boxes, the statistics so far, and which attempt's walls are open.
//!
//! **Who closes what.** An attempt's walls are opened before its tiles go out and
//! closed when it ends. `opened` names the attempt whose walls are open; whoever ends
//! that attempt takes it (`Option::take`) and closes it: the job's end (completed,
//! failed, cancelled), or the start of the next attempt after a lost worker, which
//! closes the old walls before opening the new ones (a host drops older attempts of a
//! job when a newer one opens, so the order matters for the statistics). `pending`
//! names an attempt whose walls are being opened and whose tiles wait for that; if the
//! attempt is replaced or the job ends meanwhile, the actor closes what that task opened.

use std::sync::Arc;

use dray_cache::settings::{Placement as WallPlacement, WallSettings};
use dray_proto::v1::{PhmSettings, RayCacheSettings};

use crate::caches::geometry::WallGeometry;
use crate::caches::lifecycle::AttemptWalls;
use crate::caches::placement::{Candidates, Placement};
use crate::caches::tally::CacheTally;
use crate::membership::Membership;
use crate::scheduler::state::JobSchedule;

/// The attempt whose walls are open, and where.
#[derive(Clone, Debug)]
pub struct OpenAttempt {
    /// The attempt.
    pub attempt: u32,
    /// Its hosts and walls.
    pub placement: Placement,
}

/// A job's ray caches.
#[derive(Debug)]
pub struct JobCaches {
    /// The ray-cache knobs, defaults filled in (None: hit maps only).
    pub settings: Option<RayCacheSettings>,
    /// The hit-map knobs, defaults filled in (None: ray caches only).
    pub phm: Option<PhmSettings>,
    /// Scene and domain boxes.
    pub geometry: Arc<WallGeometry>,
    /// Statistics so far (shared with the tasks that close walls).
    pub tally: Arc<CacheTally>,
    /// The attempt whose walls are open, if any.
    pub opened: Option<OpenAttempt>,
    /// The attempt whose walls are being opened, if any (its tiles wait).
    pub pending: Option<u32>,
    /// How to reach the cache hosts (the cluster token, TLS).
    pub net: dray_net::ClientOptions,
    /// Where the walls are, parsed from the knobs (`None`: no walls, or knobs that
    /// failed to parse, which validation keeps from happening).
    placement: Option<WallPlacement>,
}

impl JobCaches {
    /// Caches for a job, nothing open yet.
    pub fn new(
        settings: Option<RayCacheSettings>,
        phm: Option<PhmSettings>,
        geometry: Arc<WallGeometry>,
        net: dray_net::ClientOptions,
    ) -> JobCaches {
        let placement = WallSettings::from_proto(settings.as_ref(), phm.as_ref())
            .inspect_err(|e| tracing::warn!("a job's cache settings do not parse: {e}"))
            .ok()
            .and_then(|w| w.placement());
        JobCaches {
            placement,
            tally: Arc::new(CacheTally::new(settings.is_some(), phm.is_some())),
            settings,
            phm,
            geometry,
            opened: None,
            pending: None,
            net,
        }
    }

    /// Whether the job's walls, with their caches and maps, are replicated beside
    /// every worker (sender placement: dray's own for ray caches, which Little 2011
    /// does not replicate; after Bolstad 2017's per-server map proxies for hit maps).
    /// Validation made the two settings agree when the job has both.
    pub fn sender_placement(&self) -> bool {
        self.placement == Some(WallPlacement::Sender)
    }

    /// What opening attempt `attempt` of `job_id` sends.
    pub fn attempt_walls(&self, job_id: &str, attempt: u32) -> AttemptWalls {
        AttemptWalls {
            job_id: job_id.to_string(),
            attempt,
            settings: self.settings.clone(),
            phm: self.phm.clone(),
            geometry: self.geometry.clone(),
            net: self.net.clone(),
        }
    }
}

/// The hosts the current attempt of `sched` may use: the registered stand-alone hosts,
/// else the cache hosts its workers announced (see [`Candidates::choose`]).
pub fn candidates(membership: &Membership, sched: &JobSchedule) -> Candidates {
    let workers: Vec<(String, String)> = sched
        .worker_ids()
        .into_iter()
        .map(|id| {
            let e = membership
                .get(&id)
                .and_then(|w| w.cache_endpoint)
                .unwrap_or_default();
            (id, e)
        })
        .collect();
    Candidates::choose(membership.cache_hosts.list(), &workers)
}

/// Place the walls of `sched`'s job on `c` by its current (the attempt's first) table:
/// replicated on every host when the job asks for sender placement and the hosts are
/// beside workers (stand-alone `dray cache` hosts send nothing, so they hold each wall
/// once).
pub fn place(c: &Candidates, sched: &JobSchedule, domains: u32, caches: &JobCaches) -> Placement {
    let beside = c.beside(sched.routing().routes(), domains);
    if caches.sender_placement() && !c.beside_worker.is_empty() {
        Placement::replicated(domains, c, &beside)
    } else {
        Placement::place(domains, c, &beside)
    }
}
