//! One job's scheduling state: the schedule, the current table, the workers with their
//! budgets, and what the latest queue reports said. Each job's actor
//! ([`crate::job::actor`]) owns one next to the job's credit, so an attempt bump, its new
//! table and its tiles change in one step; the actor's timer paces its rounds.
//!
//! Every method is synchronous and clock-free apart from the `now` it is given, so this
//! too is tested without a server.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use dray_proto::v1::{DomainQueue, ReportQueuesRequest, RoutingTable, Tile, WorkerEndpoint};

use super::policy::{Change, RoundInput, Schedule, leave_image_plane, rebalance, views};
use super::table::JobRouting;
use crate::caches::placement::Placement;

/// A worker as a job knows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobWorker {
    /// Id and endpoint.
    pub endpoint: WorkerEndpoint,
    /// Memory budget for resident domains (0 = unlimited).
    pub budget: u64,
}

/// What [`JobSchedule::round`] did.
#[derive(Clone, Debug, PartialEq)]
pub enum RoundOutcome {
    /// A round ran and changed the table: send this delta (from the version before the
    /// round, which every worker of the job holds) to every worker of the job.
    Changed(RoutingTable, Vec<Change>),
    /// A round ran; nothing to change.
    Unchanged,
    /// No round is due before this instant (reports are fresh but the last round was
    /// too recent).
    NotBefore(Instant),
    /// Nothing to do until a new queue report arrives (or the schedule is static).
    Waiting,
}

/// Rays queued in one worker's report (saturating: a hostile report cannot wrap it).
fn queued_in(queues: &[DomainQueue]) -> u64 {
    queues
        .iter()
        .fold(0u64, |a, q| a.saturating_add(q.rays_queued))
}

/// Scheduling state of one running job.
#[derive(Clone, Debug)]
pub struct JobSchedule {
    schedule: Schedule,
    domains: u32,
    routing: JobRouting,
    budgets: BTreeMap<String, u64>,
    /// Latest queue report per worker, this attempt only.
    reports: BTreeMap<String, Vec<DomainQueue>>,
    /// Rays queued over `reports`, kept as reports arrive and leave.
    queued: u64,
    /// Domains given out by a round whose new owner has not reported them resident yet.
    loading: BTreeSet<(u32, String)>,
    /// Workers that may hold some of this attempt's credit: those it started with, every
    /// joiner dealt tiles of a later pass ([`JobSchedule::deal`]) and every owner a
    /// round gave a domain (rays were sent to it).
    /// A worker outside this set holds no credit, so losing it loses nothing.
    holders: BTreeSet<String>,
    /// A report arrived since the last round.
    fresh: bool,
    last_round: Option<Instant>,
    rounds: u32,
}

impl JobSchedule {
    /// A job `job_id` of `domains` domains on `workers` (non-empty, in job order), with
    /// the schedule's first table (version 1, attempt 0).
    pub fn new(job_id: &str, schedule: Schedule, domains: u32, workers: &[JobWorker]) -> Self {
        let ids: Vec<String> = workers
            .iter()
            .map(|w| w.endpoint.worker_id.clone())
            .collect();
        let routes = schedule.initial_routes(domains, &ids);
        JobSchedule {
            schedule,
            domains,
            routing: JobRouting::new(
                job_id,
                workers.iter().map(|w| w.endpoint.clone()).collect(),
                routes,
            ),
            budgets: workers
                .iter()
                .map(|w| (w.endpoint.worker_id.clone(), w.budget))
                .collect(),
            reports: BTreeMap::new(),
            queued: 0,
            loading: BTreeSet::new(),
            holders: ids.iter().cloned().collect(),
            fresh: false,
            last_round: None,
            rounds: 0,
        }
    }

    /// The schedule.
    pub fn schedule(&self) -> Schedule {
        self.schedule
    }

    /// The current table, as sent to workers.
    pub fn table(&self) -> RoutingTable {
        self.routing.table()
    }

    /// The current table's version.
    pub fn version(&self) -> u64 {
        self.routing.version()
    }

    /// The current attempt.
    pub fn attempt(&self) -> u32 {
        self.routing.attempt()
    }

    /// The current routing state.
    pub fn routing(&self) -> &JobRouting {
        &self.routing
    }

    /// Start at attempt `attempt` instead of 0, before the first table is sent (a job
    /// taken back from the job store).
    pub fn set_first_attempt(&mut self, attempt: u32) {
        self.routing.set_first_attempt(attempt);
    }

    /// Set the current attempt's cache placement (before its first table is sent).
    pub fn set_caches(&mut self, caches: Placement) {
        self.routing.set_caches(caches);
    }

    /// Domains of the job.
    pub fn domains(&self) -> u32 {
        self.domains
    }

    /// Rounds run so far.
    pub fn rounds(&self) -> u32 {
        self.rounds
    }

    /// The job's workers' ids, in job order.
    pub fn worker_ids(&self) -> Vec<String> {
        self.routing.worker_ids()
    }

    /// Whether `worker` is one of the job's workers.
    pub fn has_worker(&self, worker: &str) -> bool {
        // `budgets` lists exactly the table's workers, and is a map: O(log N), where
        // the table's list is a scan (every report asks).
        self.budgets.contains_key(worker)
    }

    /// Deal `tiles` over the current workers by the schedule's tile rule, each stamped
    /// with the current attempt: (worker id, its tiles) in job order. A worker dealt a
    /// tile holds this attempt's credit from then on, joiners too (a later pass is dealt
    /// over every worker of the job): losing it needs a new attempt, not
    /// [`JobSchedule::remove_unused`], or its tiles would never finish.
    pub fn deal(&mut self, tiles: &[Tile]) -> Vec<(String, Vec<Tile>)> {
        let ids = self.worker_ids();
        let attempt = self.attempt();
        let dealt: Vec<(String, Vec<Tile>)> = self
            .schedule
            .deal_tiles(tiles.len(), ids.len())
            .into_iter()
            .zip(ids)
            .map(|(positions, id)| {
                let mine = positions
                    .into_iter()
                    .filter_map(|j| tiles.get(j))
                    .map(|t| Tile { attempt, ..*t })
                    .collect();
                (id, mine)
            })
            .collect();
        for (id, mine) in &dealt {
            if !mine.is_empty() {
                self.holders.insert(id.clone());
            }
        }
        dealt
    }

    /// `tiles` for `worker` alone (a top-up or a joiner's first tiles), stamped with the
    /// current attempt; like [`JobSchedule::deal`], `worker` holds this attempt's credit
    /// from then on.
    pub fn deal_to(&mut self, worker: &str, tiles: &[Tile]) -> Vec<Tile> {
        if !tiles.is_empty() {
            self.holders.insert(worker.to_string());
        }
        let attempt = self.attempt();
        tiles.iter().map(|t| Tile { attempt, ..*t }).collect()
    }

    /// Store a queue report of the current attempt from one of the job's workers (the
    /// caller checks both). A domain the report shows resident is no longer loading there.
    pub fn record_queues(&mut self, r: &ReportQueuesRequest) {
        for q in r.queues.iter().filter(|q| q.resident) {
            self.loading.remove(&(q.domain, r.worker_id.clone()));
        }
        let old = self.reports.insert(r.worker_id.clone(), r.queues.clone());
        self.queued = self
            .queued
            .saturating_sub(old.as_deref().map_or(0, queued_in))
            .saturating_add(queued_in(&r.queues));
        self.fresh = true;
    }

    /// Each worker's latest queue report, this attempt.
    pub fn reports(&self) -> &BTreeMap<String, Vec<DomainQueue>> {
        &self.reports
    }

    /// Rays queued at the job's workers, as of each one's latest report.
    pub fn rays_queued(&self) -> u64 {
        self.queued
    }

    /// Run a round if one is due at `now`: the schedule is dynamic, a report arrived
    /// since the last round, and the last round was at least `interval` ago.
    pub fn round(&mut self, now: Instant, interval: Duration) -> RoundOutcome {
        if !self.schedule.is_dynamic() || !self.fresh {
            return RoundOutcome::Waiting;
        }
        if let Some(last) = self.last_round {
            let due = last + interval;
            if now < due {
                return RoundOutcome::NotBefore(due);
            }
        }
        self.fresh = false;
        self.last_round = Some(now);
        self.rounds = self.rounds.saturating_add(1);
        let ids = self.worker_ids();
        let workers = views(&ids, &self.budgets, &self.reports);
        let input = RoundInput {
            domains: self.domains,
            routes: self.routing.routes(),
            workers: &workers,
            loading: &self.loading,
            replicate: self.schedule.replicates(),
        };
        // `dynamic-from-image-plane` leaves image-plane once every worker of the job has
        // reported its queues (what each holds is then known); until then, no change.
        let leaving = input.routes.is_local();
        let decision = if leaving {
            let all_reported = ids.iter().all(|w| self.reports.contains_key(w));
            all_reported.then(|| leave_image_plane(&input)).flatten()
        } else {
            rebalance(&input)
        };
        let Some(decision) = decision else {
            return RoundOutcome::Unchanged;
        };
        if leaving {
            // Owners by residency: nothing is being loaded for the table, and every
            // worker already holds credit (each was dealt tiles). Workers held a local
            // table, which a delta cannot patch: they get the whole one.
            tracing::info!(
                domains = self.domains,
                "dynamic-from-image-plane: image-plane phase over, domains owned"
            );
            self.routing.set_routes(decision.routes);
            return RoundOutcome::Changed(self.routing.table(), decision.changes);
        }
        for (d, w) in decision.changes.iter().filter_map(Change::given) {
            self.loading.insert((d, w.to_string()));
            self.holders.insert(w.to_string());
        }
        let base = self.routing.version();
        self.routing.set_routes(decision.routes);
        self.forget_stale_loads();
        let moved = decision.changes.iter().map(Change::domain).collect();
        RoundOutcome::Changed(self.routing.delta(base, &moved), decision.changes)
    }

    /// Drop loading marks of workers that no longer own the domain.
    fn forget_stale_loads(&mut self) {
        let routes = self.routing.routes();
        self.loading.retain(|(d, w)| routes.owns(w, *d));
    }

    /// Add `worker` to the job (it owns nothing until a round gives it domains): a new
    /// table. None when it is already a worker of the job.
    pub fn add_worker(&mut self, worker: JobWorker) -> Option<RoutingTable> {
        if self.has_worker(&worker.endpoint.worker_id) {
            return None;
        }
        self.budgets
            .insert(worker.endpoint.worker_id.clone(), worker.budget);
        self.routing.add_worker(worker.endpoint);
        Some(self.table())
    }

    /// Drop `lost` from the job without a new attempt if it holds none of this
    /// attempt's credit (a worker that joined and was never given a domain or a tile): a new table
    /// for the others. None when it is not a worker of the job or may hold credit.
    pub fn remove_unused(&mut self, lost: &str) -> Option<RoutingTable> {
        if self.holders.contains(lost) {
            return None;
        }
        self.routing.remove_worker(lost)?;
        self.budgets.remove(lost);
        if let Some(old) = self.reports.remove(lost) {
            self.queued = self.queued.saturating_sub(queued_in(&old));
        }
        Some(self.table())
    }

    /// Start the next attempt without `lost`: the survivors (in job order) get the
    /// schedule's ownership after a loss, and everything learnt from queue reports is
    /// forgotten (they described the attempt that is being dropped). Returns the new
    /// table, or None when `lost` was not a worker of the job or no worker is left.
    pub fn restart_without(&mut self, lost: &str) -> Option<RoutingTable> {
        if !self.has_worker(lost) {
            return None;
        }
        let survivors: Vec<WorkerEndpoint> = self
            .routing
            .workers()
            .iter()
            .filter(|w| w.worker_id != lost)
            .cloned()
            .collect();
        if survivors.is_empty() {
            return None;
        }
        let ids: Vec<String> = survivors.iter().map(|w| w.worker_id.clone()).collect();
        let routes = self
            .schedule
            .routes_after_loss(self.routing.routes(), self.domains, &ids);
        let attempt = self.attempt().saturating_add(1);
        self.routing.restart(attempt, survivors, routes);
        self.budgets.remove(lost);
        self.reports.clear();
        self.queued = 0;
        self.loading.clear();
        self.holders = self.routing.worker_ids().into_iter().collect();
        self.fresh = false;
        Some(self.table())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn worker(id: &str, budget: u64) -> JobWorker {
        JobWorker {
            endpoint: WorkerEndpoint {
                worker_id: id.into(),
                endpoint: format!("http://{id}:1"),
            },
            budget,
        }
    }

    fn report(w: &str, queues: &[(u32, u64, bool)]) -> ReportQueuesRequest {
        ReportQueuesRequest {
            worker_id: w.into(),
            job_id: "j".into(),
            queues: queues
                .iter()
                .map(|&(domain, rays_queued, resident)| DomainQueue {
                    domain,
                    rays_queued,
                    resident,
                    resident_bytes: 10,
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn rounds_are_paced_and_need_fresh_reports() {
        let ws = [worker("a", 0), worker("b", 0)];
        let mut s = JobSchedule::new("j", Schedule::Dynamic { replicate: false }, 4, &ws);
        let t0 = Instant::now();
        let iv = Duration::from_millis(100);
        assert_eq!(s.round(t0, iv), RoundOutcome::Waiting);
        // a owns 0 and 2, b owns 1 and 3. Rays wait for 0 and 2 only: b is idle and
        // gets the most wanted (2), which a has not loaded.
        s.record_queues(&report("a", &[(0, 5, true), (2, 9, false)]));
        let RoundOutcome::Changed(t, changes) = s.round(t0, iv) else {
            panic!("expected a change");
        };
        assert_eq!((t.version, s.rounds()), (2, 1));
        assert_eq!(changes[0].given(), Some((2, "b")));
        s.record_queues(&report("a", &[(0, 5, true), (2, 9, false)]));
        assert_eq!(
            s.round(t0 + Duration::from_millis(10), iv),
            RoundOutcome::NotBefore(t0 + iv)
        );
        // b is loading 2: it is not moved again, nothing changes.
        assert_eq!(s.round(t0 + iv, iv), RoundOutcome::Unchanged);
        assert_eq!((s.version(), s.rounds()), (2, 2));
        assert_eq!(s.round(t0 + 3 * iv, iv), RoundOutcome::Waiting);
    }

    /// `dynamic-from-image-plane`: a local table until every worker has reported, then
    /// one whole table (a delta cannot patch a local one) owning every domain, then
    /// dynamic rounds sending deltas.
    #[test]
    fn dynamic_from_image_plane_leaves_it_once_every_worker_reported() {
        let ws = [worker("a", 0), worker("b", 0)];
        let sched = Schedule::DynamicFromImagePlane { replicate: false };
        let mut s = JobSchedule::new("j", sched, 4, &ws);
        assert!(s.table().local);
        let t0 = Instant::now();
        let iv = Duration::ZERO;
        s.record_queues(&report("a", &[(0, 5, true), (2, 9, false)]));
        assert_eq!(
            s.round(t0, iv),
            RoundOutcome::Unchanged,
            "b has not reported"
        );
        assert!(s.table().local);
        s.record_queues(&report("b", &[(1, 3, true)]));
        let RoundOutcome::Changed(t, changes) = s.round(t0, iv) else {
            panic!("expected the first ownership");
        };
        assert_eq!((t.version, t.base_version, t.local), (2, 0, false));
        assert_eq!(changes.len(), 4);
        let owner = |d: u32| {
            t.routes
                .iter()
                .filter(|r| r.domain == d)
                .map(|r| r.worker_id.as_str())
                .collect::<Vec<_>>()
        };
        assert_eq!((owner(0), owner(1)), (vec!["a"], vec!["b"]));
        assert_eq!((owner(2), owner(3)), (vec!["a"], vec!["b"]));
        // Rays wait for 2 at a, which a does not hold; b's domains are unwanted: b
        // gets 2 in a round's delta.
        s.record_queues(&report("a", &[(0, 0, true), (2, 9, false)]));
        s.record_queues(&report("b", &[(1, 0, true)]));
        let RoundOutcome::Changed(d, changes) = s.round(t0, iv) else {
            panic!("expected a round's change");
        };
        assert_eq!(d.base_version, 2);
        assert_eq!(changes[0].given(), Some((2, "b")));
    }

    #[test]
    fn static_schedules_never_round_and_loss_restarts() {
        let ws = [worker("a", 0), worker("b", 0), worker("c", 0)];
        let mut s = JobSchedule::new("j", Schedule::Domain, 6, &ws);
        s.record_queues(&report("a", &[(1, 100, false)]));
        assert_eq!(
            s.round(Instant::now(), Duration::ZERO),
            RoundOutcome::Waiting
        );
        let t = s.restart_without("b").unwrap();
        assert_eq!((t.version, t.attempt), (2, 1));
        let owners: Vec<&str> = t.routes.iter().map(|r| r.worker_id.as_str()).collect();
        assert_eq!(owners, ["a", "c", "a", "c", "a", "c"]);
        assert_eq!(s.rays_queued(), 0, "reports of the old attempt are dropped");
        assert!(s.restart_without("b").is_none());
        s.restart_without("a").unwrap();
        assert!(s.restart_without("c").is_none(), "the last worker");
    }

    #[test]
    fn a_joiner_lost_before_it_was_given_anything_costs_no_attempt() {
        let ws = [worker("a", 0)];
        let mut s = JobSchedule::new("j", Schedule::Dynamic { replicate: false }, 2, &ws);
        assert!(s.remove_unused("a").is_none(), "a was dealt tiles");
        s.add_worker(worker("b", 0)).unwrap();
        let t = s.remove_unused("b").unwrap();
        assert_eq!((t.version, t.attempt, t.workers.len()), (3, 0, 1));
        // A joiner a round gave a domain may hold credit: losing it needs a new attempt.
        s.add_worker(worker("c", 0)).unwrap();
        s.record_queues(&report("a", &[(0, 5, true), (1, 5, false)]));
        assert!(matches!(
            s.round(Instant::now(), Duration::ZERO),
            RoundOutcome::Changed(..)
        ));
        assert!(s.remove_unused("c").is_none());
        let t = s.restart_without("c").unwrap();
        assert_eq!((t.attempt, t.workers.len()), (1, 1));
    }

    /// Issue 38: a pass after the first is dealt over every worker of the job, joiners
    /// too; a joiner lost holding next-pass tiles held credit, and dropping it without a
    /// new attempt left those tiles undone for good (the job hung).
    #[test]
    fn a_joiner_dealt_tiles_of_a_later_pass_costs_an_attempt_when_lost() {
        let ws = [worker("a", 0), worker("b", 0)];
        let mut s = JobSchedule::new("j", Schedule::Dynamic { replicate: false }, 2, &ws);
        s.add_worker(worker("c", 0)).unwrap();
        let tiles: Vec<Tile> = (0..6)
            .map(|index| Tile {
                index,
                ..Default::default()
            })
            .collect();
        let dealt = s.deal(&tiles);
        assert!(dealt.iter().any(|(w, mine)| w == "c" && !mine.is_empty()));
        assert!(
            s.remove_unused("c").is_none(),
            "c holds tiles of this attempt"
        );
        let t = s.restart_without("c").unwrap();
        assert_eq!((t.attempt, t.workers.len()), (1, 2));
        // A joiner dealt nothing (more workers than tiles) still goes without an attempt.
        s.add_worker(worker("d", 0)).unwrap();
        s.add_worker(worker("e", 0)).unwrap();
        let dealt = s.deal(&tiles[..2]);
        assert!(dealt.iter().any(|(w, mine)| w == "e" && mine.is_empty()));
        assert!(s.remove_unused("e").is_some());
    }
}
