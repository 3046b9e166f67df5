//! One job attempt on this worker, as the worker's other parts see it: a handle to the
//! job's actor ([`crate::job_actor`]).
//!
//! The handle holds what never changes once the job is set up (its key, tracer, domain
//! source and span), the views the actor publishes (the routing table in force, the
//! tiles left to start), the few flags and counters every part reads, and the actor's
//! mailbox. Nothing here is written but through the handle's methods: results, tiles
//! and routing tables are posted to the actor, which alone gathers reports, validates
//! tiles and applies routing deltas.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};

use dray_proto::v1::{RoutingTable, TileAssignment};
use tokio::sync::{mpsc, watch};

use crate::domain_store::{DomainSource, JobKey};
use crate::routing::Routes;
use crate::tracer::{JobTracer, TileRef};

use super::report::Report;
use super::tiles::TileQueue;

/// What a job's actor is told.
pub(crate) enum JobEvent {
    /// Results and counters to add to the next report.
    Results(Box<Report>),
    /// Tiles the coordinator dealt this worker.
    Tiles(TileAssignment),
    /// A routing table from the coordinator: whole, or a delta of the kept one.
    Routing(RoutingTable),
}

/// The receiving end of a job's mailbox, for its actor.
pub(crate) type Mailbox = mpsc::UnboundedReceiver<JobEvent>;

/// One job attempt on this worker.
pub struct Job {
    pub key: JobKey,
    pub tracer: JobTracer,
    /// Where its domains are loaded from.
    pub source: Arc<dyn DomainSource>,
    /// This job's span here (a child of the coordinator's, when traces are exported):
    /// tracing work and domain loads run in it.
    pub span: tracing::Span,
    /// This process's CPU clock when the job was set up here (reported with every
    /// report, for `JobStats.cpu_seconds`).
    pub cpu_at_setup: f64,
    /// The routing table in force, published by the actor.
    routes: RwLock<Arc<Routes>>,
    /// Tiles whose camera rays are still to be made, dealt in by the actor.
    tiles: TileQueue,
    /// The actor's mailbox. Unbounded, and never waited on: tracing never waits. What
    /// waits in it is bounded by the work in flight, which the in-flight limit bounds.
    mailbox: mpsc::UnboundedSender<JobEvent>,
    active: AtomicBool,
    /// Set once the job has failed here: its rays are dropped from then on.
    failed: AtomicBool,
    /// Turns true when the job is released, for tasks waiting on its behalf.
    released: watch::Sender<bool>,
    /// Rays of this job waiting for a peer. Counted per job, so rays stuck on the way to
    /// a lost peer stop counting once their job is released.
    outgoing: AtomicUsize,
    /// Rays of this job waiting for a cache actor's answer.
    awaiting_cache: AtomicUsize,
    /// Picks among the owners of replicated domains.
    spread: AtomicU64,
    /// Hit-map outcomes gathered for the other workers' copies of the maps (sender
    /// placement).
    pub merges: crate::map_merge::MapMerges,
    /// Views of this job's walls (ray caches and hit maps) on the cache host in this
    /// process, once its walls are open there (sender placement).
    views: std::sync::OnceLock<Arc<dray_cache::WallViews>>,
    /// The job's traffic trace here, when it asked for one and this worker keeps traces
    /// (`crate::traffic_trace`); `None` costs the tracing threads nothing.
    pub trace: Option<crate::traffic_trace::TrafficTrace>,
}

impl Job {
    /// A job attempt routed by `routes`, and the mailbox its actor reads.
    pub(crate) fn new(
        key: JobKey,
        tracer: JobTracer,
        source: Arc<dyn DomainSource>,
        routes: Routes,
    ) -> (Job, Mailbox) {
        let (mailbox, rx) = mpsc::unbounded_channel();
        let job = Job {
            key,
            tracer,
            source,
            span: tracing::Span::none(),
            cpu_at_setup: dray_net::cpu::process_cpu_seconds(),
            routes: RwLock::new(Arc::new(routes)),
            tiles: TileQueue::default(),
            mailbox,
            active: AtomicBool::new(true),
            failed: AtomicBool::new(false),
            released: watch::channel(false).0,
            outgoing: AtomicUsize::new(0),
            awaiting_cache: AtomicUsize::new(0),
            spread: AtomicU64::new(0),
            merges: crate::map_merge::MapMerges::default(),
            views: std::sync::OnceLock::new(),
            trace: None,
        };
        (job, rx)
    }

    /// The same job, merging hit-map outcomes into other workers' copies every `every`
    /// outcomes ([`crate::map_merge`]).
    pub fn with_merges_every(mut self, every: u32) -> Job {
        self.merges = crate::map_merge::MapMerges::new(every);
        self
    }

    /// The same job, recording its traffic to `trace`.
    pub fn with_trace(mut self, trace: Option<crate::traffic_trace::TrafficTrace>) -> Job {
        self.trace = trace;
        self
    }

    /// The same job, with `span` as its span.
    pub fn with_span(mut self, span: tracing::Span) -> Job {
        self.span = span;
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

    /// Add `report` to the job's next report. Results of a released job are dropped.
    pub fn post(&self, report: Report) {
        let _ = self.mailbox.send(JobEvent::Results(Box::new(report)));
    }

    /// Hand `event` to the job's actor.
    pub(crate) fn tell(&self, event: JobEvent) {
        let _ = self.mailbox.send(event);
    }

    /// The current routing table.
    pub fn routes(&self) -> Arc<Routes> {
        dray_sync::read(&self.routes).clone()
    }

    /// Publish `routes` if it is newer than the table in force; returns the table it
    /// replaced. Only the actor calls this.
    pub(crate) fn publish_routes(&self, routes: Routes) -> Option<Arc<Routes>> {
        let mut g = dray_sync::write(&self.routes);
        if routes.version <= g.version {
            return None;
        }
        Some(std::mem::replace(&mut *g, Arc::new(routes)))
    }

    /// The tiles left to start.
    pub fn tiles(&self) -> &TileQueue {
        &self.tiles
    }

    pub fn is_active(&self) -> bool {
        self.active.load(Ordering::Relaxed)
    }

    /// Resolves once the job is released.
    pub async fn released(&self) {
        let mut rx = self.released.subscribe();
        let _ = rx.wait_for(|r| *r).await;
    }

    pub(super) fn deactivate(&self) {
        self.active.store(false, Ordering::Relaxed);
        // The job's work here is over: its trace is whole for whoever reads it now.
        if let Some(t) = &self.trace {
            t.flush();
        }
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
        tracing::error!(job = %self.key.id, "{message}");
        self.post(Report {
            failure: Some(message),
            ..Report::default()
        });
    }

    /// `n` more rays of this job wait for a peer.
    pub fn outgoing_add(&self, n: usize) {
        self.outgoing.fetch_add(n, Ordering::Relaxed);
    }

    /// `n` rays of this job no longer wait for a peer.
    pub fn outgoing_sub(&self, n: usize) {
        self.outgoing.fetch_sub(n, Ordering::Relaxed);
    }

    /// Rays of this job waiting for a peer.
    pub fn outgoing(&self) -> usize {
        self.outgoing.load(Ordering::Relaxed)
    }

    /// `n` more rays of this job wait for a cache actor's answer.
    pub fn awaiting_cache_add(&self, n: usize) {
        self.awaiting_cache.fetch_add(n, Ordering::Relaxed);
    }

    /// `n` rays of this job no longer wait for a cache actor's answer.
    pub fn awaiting_cache_sub(&self, n: usize) {
        self.awaiting_cache.fetch_sub(n, Ordering::Relaxed);
    }

    /// Rays of this job waiting here for a peer or a cache actor (not in queues).
    pub fn waiting(&self) -> usize {
        self.outgoing() + self.awaiting_cache.load(Ordering::Relaxed)
    }

    /// The replica to send the next batch to, among the owners of a replicated domain.
    pub fn spread(&self) -> &AtomicU64 {
        &self.spread
    }
}

/// A tile of the job as the coordinator dealt it.
pub(crate) fn tile_ref(t: &dray_proto::v1::Tile) -> TileRef {
    TileRef {
        index: t.index,
        x0: t.x0,
        y0: t.y0,
        width: t.width,
        height: t.height,
        credit: dray_core::credit::Credit::from_wire(t.credit),
        coarse: t.coarse,
        first_sample: t.first_sample,
        samples: t.samples,
    }
}
