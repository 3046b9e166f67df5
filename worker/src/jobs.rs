//! The jobs this worker runs: one [`Job`] per job id (its current attempt), what it has
//! to report, and which attempts were released.
//!
//! A job is set up from the coordinator's `JobSetup`, swaps routing tables as the
//! scheduler sends them, and is released by a `JobRelease` (finished, cancelled, or
//! replaced by a newer attempt after a lost worker). Everything of a released attempt —
//! its queued rays, its resident domains, rays still arriving for it — is dropped.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};

use dray_core::credit::Credit;
use dray_core::integrator::RayKind;
use dray_proto::v1::RoutingTable;
use tokio::sync::watch;

use crate::domain_store::{DomainSource, JobKey};
use crate::pixel_sums::PixelSums;
use crate::routing::Routes;
use crate::tickets::TicketLedger;
use crate::tracer::{JobTracer, TileRef};

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Results of one job attempt waiting to be reported.
#[derive(Default)]
pub struct Report {
    pub sums: PixelSums,
    pub credits: Vec<(u32, Credit)>,
    pub traced: [u64; RayKind::COUNT],
    pub nonfinite: u64,
    pub bytes: u64,
    pub rays_sent: u64,
    pub rays_forwarded: u64,
    pub idle_seconds: f64,
    /// Peers the job's rays could not be sent to.
    pub unreachable: Vec<String>,
    pub failure: Option<String>,
    /// Contributions and credit owed to ray-cache tickets; returned to their cache
    /// actors (and acknowledged) before the same credit goes to the coordinator.
    pub tickets: TicketLedger,
    /// Rays a cache answered whose domain another worker owns (not sent).
    pub cache_rays_not_sent: u64,
    /// Rays that went past an unreachable cache host.
    pub cache_rays_bypassed: u64,
    /// Rays a hit map skipped past, or answered as occluded at, a domain another worker
    /// owns (not sent).
    pub phm_rays_not_sent: u64,
    /// Bytes of lookups and ticket returns sent to cache hosts.
    pub cache_bytes: u64,
    /// Cache hosts found unreachable.
    pub lost_cache_hosts: Vec<String>,
    /// Bytes exchanged with other processes, by kind.
    pub traffic: crate::traffic::Traffic,
}

impl Report {
    /// Whether there is nothing to report but idle time (which rides along with the
    /// next report, or with the queue report's tick).
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
            && self.credits.is_empty()
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
            && self.bytes == 0
            && self.rays_sent == 0
            && self.rays_forwarded == 0
            && self.unreachable.is_empty()
            && self.failure.is_none()
            && self.tickets.is_empty()
            && self.cache_rays_not_sent == 0
            && self.cache_rays_bypassed == 0
            && self.phm_rays_not_sent == 0
            && self.cache_bytes == 0
            && self.lost_cache_hosts.is_empty()
            && self.traffic.is_empty()
    }
}

/// One job attempt on this worker.
pub struct Job {
    pub key: JobKey,
    pub tracer: JobTracer,
    /// Where its domains are loaded from.
    pub source: Arc<dyn DomainSource>,
    routes: RwLock<Arc<Routes>>,
    /// The whole routing table `routes` was made from: the base the coordinator's
    /// deltas (a round's moved domains) apply to.
    table: Mutex<Option<RoutingTable>>,
    /// Tiles whose camera rays are still to be made, with the next ray index.
    pub tiles: Mutex<VecDeque<(TileRef, u64)>>,
    pub report: Mutex<Report>,
    pub sequence: AtomicU64,
    active: AtomicBool,
    /// Set once the job has failed here: its rays are dropped from then on.
    failed: AtomicBool,
    /// Turns true when the job is released, for tasks waiting on its behalf.
    released: watch::Sender<bool>,
    /// Rays of this job waiting for a peer. Counted per job, so rays stuck on the way to
    /// a lost peer stop counting once their job is released.
    pub outgoing: AtomicUsize,
    /// Rays of this job waiting for a cache actor's answer.
    pub awaiting_cache: AtomicUsize,
    /// Most rays queued here for this job at once, so far.
    pub queue_peak: AtomicU64,
    /// Picks among the owners of replicated domains.
    pub spread: AtomicU64,
    /// This process's CPU clock when the job was set up here (reported with every
    /// report, for `JobStats.cpu_seconds`).
    pub cpu_at_setup: f64,
    /// Hit-map outcomes gathered for the other workers' copies of the maps (sender
    /// placement).
    pub merges: crate::map_merge::MapMerges,
    /// Views of this job's walls (ray caches and hit maps) on the cache host in this
    /// process, once its walls are open there (sender placement).
    views: std::sync::OnceLock<Arc<dray_cache::WallViews>>,
    /// This job's span here (a child of the coordinator's, when traces are exported):
    /// tracing work and domain loads run in it.
    pub span: tracing::Span,
}

impl Job {
    pub fn new(
        key: JobKey,
        tracer: JobTracer,
        source: Arc<dyn DomainSource>,
        routes: Routes,
    ) -> Job {
        Job {
            key,
            tracer,
            source,
            routes: RwLock::new(Arc::new(routes)),
            table: Mutex::new(None),
            tiles: Mutex::new(VecDeque::new()),
            report: Mutex::new(Report::default()),
            sequence: AtomicU64::new(0),
            active: AtomicBool::new(true),
            failed: AtomicBool::new(false),
            released: watch::channel(false).0,
            outgoing: AtomicUsize::new(0),
            awaiting_cache: AtomicUsize::new(0),
            queue_peak: AtomicU64::new(0),
            spread: AtomicU64::new(0),
            cpu_at_setup: dray_net::cpu::process_cpu_seconds(),
            span: tracing::Span::none(),
            merges: crate::map_merge::MapMerges::default(),
            views: std::sync::OnceLock::new(),
        }
    }

    /// The same job, merging hit-map outcomes into other workers' copies every `every`
    /// outcomes ([`crate::map_merge`]).
    pub fn with_merges_every(mut self, every: u32) -> Job {
        self.merges = crate::map_merge::MapMerges::new(every);
        self
    }

    /// Views of the job's walls on `host` (the cache host in this process, when it
    /// holds this worker's replicas), asked of the host until its walls are open.
    pub fn wall_views(
        &self,
        host: Option<&dray_cache::CacheHost>,
    ) -> Option<Arc<dray_cache::WallViews>> {
        if let Some(v) = self.views.get() {
            return Some(v.clone());
        }
        let views = host?.wall_views(&self.key.id, self.key.attempt)?;
        Some(self.views.get_or_init(|| views).clone())
    }

    /// The same job, with `span` as its span.
    pub fn with_span(mut self, span: tracing::Span) -> Job {
        self.span = span;
        self
    }

    /// The current routing table.
    pub fn routes(&self) -> Arc<Routes> {
        self.routes
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Keep `table` (a whole table) as the base of later deltas, if it is newer than the
    /// one kept.
    pub fn keep_table(&self, table: RoutingTable) {
        let mut g = lock(&self.table);
        if g.as_ref().is_none_or(|t| t.version < table.version) {
            *g = Some(table);
        }
    }

    /// The whole table that `delta` (cluster.proto, `RoutingTable.base_version`) leads
    /// to from the table kept here; None when the kept table is not its base (the
    /// caller asks the coordinator for the whole table).
    pub fn patch_table(&self, delta: &RoutingTable) -> Option<RoutingTable> {
        crate::routing::patch(lock(&self.table).as_ref()?, delta)
    }

    /// Swap in `routes` if it is newer; returns the table it replaced.
    pub fn set_routes(&self, routes: Routes) -> Option<Arc<Routes>> {
        let mut g = self.routes.write().unwrap_or_else(|p| p.into_inner());
        if routes.version <= g.version {
            return None;
        }
        Some(std::mem::replace(&mut *g, Arc::new(routes)))
    }

    pub fn is_active(&self) -> bool {
        self.active.load(Ordering::Relaxed)
    }

    /// Resolves once the job is released.
    pub async fn released(&self) {
        let mut rx = self.released.subscribe();
        let _ = rx.wait_for(|r| *r).await;
    }

    fn deactivate(&self) {
        self.active.store(false, Ordering::Relaxed);
        self.released.send_replace(true);
    }

    /// Whether the job failed here (it traces nothing more; the coordinator will
    /// release it).
    pub fn has_failed(&self) -> bool {
        self.failed.load(Ordering::Relaxed)
    }

    /// Fail the job: the reason goes to the coordinator with the next report.
    pub fn fail(&self, message: String) {
        if self.failed.swap(true, Ordering::Relaxed) {
            return;
        }
        let mut r = lock(&self.report);
        if r.failure.is_none() {
            tracing::error!(job = %self.key.id, "{message}");
            r.failure = Some(message);
        }
    }

    /// Note that `queued` rays wait here for this job now.
    pub fn note_queued(&self, queued: u64) {
        self.queue_peak.fetch_max(queued, Ordering::Relaxed);
    }
}

/// The jobs of this worker.
#[derive(Default)]
pub struct Jobs {
    /// By job id: the attempt running here.
    jobs: Mutex<HashMap<Arc<str>, Arc<Job>>>,
    /// By job id: the newest attempt released here; its rays and older are dropped.
    released: Mutex<HashMap<Arc<str>, u32>>,
}

/// What to do with rays of a job attempt.
#[derive(Clone)]
pub enum Standing {
    /// Trace them: the attempt runs here.
    Running(Arc<Job>),
    /// Keep them: the attempt's setup has not arrived yet.
    Pending,
    /// Drop them: the attempt was released or replaced.
    Gone,
}

impl Jobs {
    pub fn get(&self, id: &str) -> Option<Arc<Job>> {
        lock(&self.jobs).get(id).cloned()
    }

    /// Every job running here.
    pub fn all(&self) -> Vec<Arc<Job>> {
        lock(&self.jobs).values().cloned().collect()
    }

    /// What rays of attempt `attempt` of job `id` are for.
    pub fn standing(&self, id: &str, attempt: u32) -> Standing {
        if lock(&self.released).get(id).is_some_and(|&r| attempt <= r) {
            return Standing::Gone;
        }
        match lock(&self.jobs).get(id) {
            Some(j) if j.key.attempt == attempt => Standing::Running(j.clone()),
            Some(j) if j.key.attempt > attempt => Standing::Gone,
            _ => Standing::Pending,
        }
    }

    /// Whether a setup for job `id` may be taken: a new attempt of a job held here
    /// replaces it, and a new job is refused once [`MAX_JOBS`] are held
    /// (docs/security.md "Hardening, second round", item 9: a coordinator made a worker
    /// hold 20,000 setups, 202 MB). The assignment loop
    /// takes setups one at a time (each is planned before the next is read), so the
    /// jobs held are the running ones plus at most the one being planned.
    ///
    /// [`MAX_JOBS`]: crate::setup_bounds::MAX_JOBS
    pub fn admit(&self, id: &str) -> Result<(), String> {
        let jobs = lock(&self.jobs);
        let max = crate::setup_bounds::MAX_JOBS;
        if jobs.len() >= max && !jobs.contains_key(id) {
            return Err(format!(
                "job setup refused: this worker already holds {} jobs, its bound ({max} at once)",
                jobs.len()
            ));
        }
        Ok(())
    }

    /// Jobs held here.
    pub fn len(&self) -> usize {
        lock(&self.jobs).len()
    }

    /// Whether no job is held here.
    pub fn is_empty(&self) -> bool {
        lock(&self.jobs).is_empty()
    }

    /// Whether attempt `attempt` of `id` was released here (or superseded).
    pub fn is_released(&self, id: &str, attempt: u32) -> bool {
        matches!(self.standing(id, attempt), Standing::Gone)
    }

    /// Start `job`. An older attempt of the same job is released first and returned;
    /// a job whose attempt was already released is refused (false).
    pub fn insert(&self, job: Arc<Job>) -> (bool, Option<Arc<Job>>) {
        if self.is_released(&job.key.id, job.key.attempt) {
            return (false, None);
        }
        let mut jobs = lock(&self.jobs);
        let old = jobs.insert(job.key.id.clone(), job.clone());
        drop(jobs);
        if let Some(o) = &old {
            self.mark_released(&o.key.id, o.key.attempt);
            o.deactivate();
        }
        (true, old)
    }

    fn mark_released(&self, id: &Arc<str>, attempt: u32) {
        let mut r = lock(&self.released);
        let e = r.entry(id.clone()).or_insert(attempt);
        *e = (*e).max(attempt);
    }

    /// Release attempt `attempt` (and older) of job `id`; returns the job if it was
    /// running here.
    pub fn release(&self, id: &str, attempt: u32) -> Option<Arc<Job>> {
        let id: Arc<str> = id.into();
        self.mark_released(&id, attempt);
        let mut jobs = lock(&self.jobs);
        let gone = match jobs.get(&id) {
            Some(j) if j.key.attempt <= attempt => jobs.remove(&id),
            _ => None,
        };
        drop(jobs);
        if let Some(j) = &gone {
            j.deactivate();
        }
        gone
    }

    /// Release every job (the coordinator was lost); returns them.
    pub fn release_all(&self) -> Vec<Arc<Job>> {
        let all: Vec<Arc<Job>> = lock(&self.jobs).drain().map(|(_, j)| j).collect();
        for j in &all {
            self.mark_released(&j.key.id, j.key.attempt);
            j.deactivate();
        }
        all
    }
}
