//! `dray.v1.ClusterService`: the calls workers make to the coordinator, over the
//! [`Membership`] and the [`JobRegistry`] (one actor per running job).
//!
//! Stand-alone cache hosts (`dray cache`) register here too (RegisterCacheHost), and are
//! listed in [`Membership::cache_hosts`](crate::membership::Membership::cache_hosts).
//!
//! Workers dial out; the coordinator answers and pushes commands on each worker's
//! WatchAssignments stream. See cluster.proto for the protocol and [`crate::dispatch`] for
//! what a job's workers receive, in order. Reports and queue reports go to their job's
//! actor and are answered by it; registrations and lost workers are posted to every job.

use std::sync::Arc;
use std::time::{Duration, Instant};

use dray_proto::v1::cluster_service_server::ClusterService;
use dray_proto::v1::{
    Assignment, GetPeerPassRequest, GetPeerPassResponse, GetRoutingTableRequest,
    GetRoutingTableResponse, HeartbeatRequest, HeartbeatResponse, RegisterCacheHostRequest,
    RegisterCacheHostResponse, RegisterWorkerRequest, RegisterWorkerResponse,
    ReportContributionsRequest, ReportContributionsResponse, ReportQueuesRequest,
    ReportQueuesResponse, WatchAssignmentsRequest,
};
use dray_scene::partition::memory::MemoryPackages;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::job::{ActorConfig, JobRegistry};
use crate::membership::{HeartbeatConfig, Membership};
use crate::scheduler::SchedulerOptions;
pub use crate::work_dir::WorkDir;

/// Settings of the cluster side of the coordinator.
#[derive(Clone, Debug)]
pub struct ClusterOptions {
    /// Heartbeat interval and timeout told to workers.
    pub heartbeat: HeartbeatConfig,
    /// Where per-job scene packages are written (a directory per job, made new by the
    /// job and removed when the job is released). Workers read them at the same path
    /// when they share it (a shared volume), and fetch them over gRPC otherwise
    /// (`PackageService`). By default a private directory of this process (see
    /// [`WorkDir`]).
    pub work_dir: WorkDir,
    /// When set, packages for scenes are cut into this in-memory store instead of the
    /// work directory: for workers in the coordinator's own process (`dray render`),
    /// which read the same store. Workers elsewhere cannot, so a cluster leaves it unset.
    pub memory_packages: Option<Arc<MemoryPackages>>,
    /// Scheduler pacing.
    pub scheduler: SchedulerOptions,
    /// How the coordinator reaches cache hosts (the cluster token, TLS).
    pub clients: dray_net::ClientOptions,
    /// A job on workers none of which has returned credit for this long fails (None:
    /// never). Heartbeats prove a worker alive, not working.
    pub stall_timeout: Option<Duration>,
    /// Whether stand-alone cache hosts (`dray cache`) may register. Off by default: a
    /// host answers every lookup on the walls it holds, so it can change any image, and
    /// holding the cluster token must not be enough to become one (`--cache-hosts`).
    pub cache_hosts: bool,
    /// Jobs that may run on the workers at once (`--max-running-jobs`); the others wait
    /// QUEUED in [`Cluster::queue`], dealt by priority, pausable. None (the default):
    /// every job starts at once, beside the others, as before the limit existed: the
    /// workers share their threads between running jobs, so a limit trades the latency
    /// of a small job behind a large one for priorities that mean something, which is
    /// the operator's choice to make (docs/operator.md).
    pub max_running_jobs: Option<std::num::NonZeroUsize>,
}

impl Default for ClusterOptions {
    fn default() -> ClusterOptions {
        ClusterOptions {
            heartbeat: HeartbeatConfig::default(),
            work_dir: WorkDir::default(),
            memory_packages: None,
            scheduler: SchedulerOptions::default(),
            clients: dray_net::ClientOptions::plain(),
            stall_timeout: Some(DEFAULT_STALL_TIMEOUT),
            cache_hosts: false,
            max_running_jobs: None,
        }
    }
}

/// The default [`ClusterOptions::stall_timeout`]: long enough for the slowest domain
/// loads seen (minutes for out-of-core scenes), short enough that a stuck job ends.
pub const DEFAULT_STALL_TIMEOUT: Duration = Duration::from_secs(1800);

/// Membership, accounting and scheduling of the coordinator's workers.
pub struct Cluster {
    /// Registered workers and their command outboxes.
    pub membership: Arc<Membership>,
    /// Jobs running on workers, one actor each: credit, film, schedule, caches.
    pub jobs: Arc<JobRegistry>,
    /// Settings.
    pub options: ClusterOptions,
    /// Package cuts in progress (a job's folder being written), so that a stopping
    /// coordinator can wait for them to stop before it removes their folders.
    pub(crate) cuts: std::sync::atomic::AtomicUsize,
    /// Jobs waiting for one of the `max_running_jobs` slots on the workers (None: no
    /// limit, jobs start at once).
    pub queue: Option<Arc<crate::priority::DealQueue>>,
    /// The layouts the frames of recent job groups are cut with (`job_group`).
    pub(crate) group_layouts: Arc<crate::job_group::GroupLayouts>,
}

impl Cluster {
    /// A cluster with no workers.
    pub fn new(options: ClusterOptions) -> Cluster {
        let membership = Arc::new(Membership::new(options.heartbeat));
        let jobs = Arc::new(JobRegistry::new(
            membership.clone(),
            ActorConfig {
                round_interval: options.scheduler.round_interval,
                stall_timeout: options.stall_timeout,
            },
        ));
        let queue = options
            .max_running_jobs
            .map(|n| Arc::new(crate::priority::DealQueue::new("cluster", n.get())));
        Cluster {
            jobs,
            membership,
            options,
            cuts: std::sync::atomic::AtomicUsize::new(0),
            queue,
            group_layouts: Arc::default(),
        }
    }

    /// Drop workers silent for too long; their jobs restart on the survivors (or fail
    /// when none is left). Returns how many workers were dropped. (A job that makes no
    /// progress fails on its own actor's stall timer.)
    pub async fn reap(&self, now: Instant) -> usize {
        // Cache hosts refresh at the heartbeat interval and are dropped after the same
        // silence as workers; a job using one that died already bypasses it.
        self.membership
            .cache_hosts
            .expire(now, self.membership.heartbeat.timeout);
        let lost = self.membership.expire(now);
        let n = lost.len();
        for w in lost {
            self.jobs.worker_lost(&w).await;
        }
        n
    }

    /// Call [`Cluster::reap`] periodically, forever (the server aborts it on shutdown).
    pub async fn reaper(self: Arc<Self>) {
        // A quarter of the timeout: a lost worker is noticed within 1.25 timeouts.
        let period = (self.options.heartbeat.timeout / 4).max(Duration::from_millis(10));
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            self.reap(Instant::now()).await;
        }
    }
}

/// The tonic service over a shared [`Cluster`].
#[derive(Clone)]
pub struct ClusterApi {
    /// The cluster state.
    pub cluster: Arc<Cluster>,
}

fn duration(d: Duration) -> Option<prost_types::Duration> {
    prost_types::Duration::try_from(d).ok()
}

#[tonic::async_trait]
impl ClusterService for ClusterApi {
    async fn register_worker(
        &self,
        r: Request<RegisterWorkerRequest>,
    ) -> Result<Response<RegisterWorkerResponse>, Status> {
        let w = self.cluster.membership.register(r.get_ref())?;
        let w_token = w.member_token.expose().to_string();
        let hb = self.cluster.membership.heartbeat;
        let id = w.id.clone();
        self.cluster.jobs.worker_joined(&w).await;
        Ok(Response::new(RegisterWorkerResponse {
            worker_id: id,
            heartbeat_interval: duration(hb.interval),
            heartbeat_timeout: duration(hb.timeout),
            member_token: w_token,
        }))
    }

    async fn heartbeat(
        &self,
        r: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatResponse>, Status> {
        self.cluster
            .membership
            .check_member(&r.get_ref().worker_id, r.metadata())?;
        let r = r.into_inner();
        let known =
            self.cluster
                .membership
                .heartbeat(&r.worker_id, r.memory_used_bytes, r.rays_queued);
        Ok(Response::new(HeartbeatResponse { reregister: !known }))
    }

    type WatchAssignmentsStream = ReceiverStream<Result<Assignment, Status>>;

    async fn watch_assignments(
        &self,
        r: Request<WatchAssignmentsRequest>,
    ) -> Result<Response<Self::WatchAssignmentsStream>, Status> {
        let id = &r.get_ref().worker_id;
        self.cluster.membership.check_member(id, r.metadata())?;
        let Some(w) = self.cluster.membership.get(id) else {
            return Err(Status::not_found(format!(
                "worker_id: {} is not registered (register again)",
                crate::text::bounded(id)
            )));
        };
        self.cluster.membership.touch(id);
        tracing::debug!(worker = %id, "assignment stream opened");
        Ok(Response::new(w.outbox.stream()))
    }

    async fn get_routing_table(
        &self,
        r: Request<GetRoutingTableRequest>,
    ) -> Result<Response<GetRoutingTableResponse>, Status> {
        let id = &r.get_ref().job_id;
        match self.cluster.jobs.routing(id).await {
            Some(t) => Ok(Response::new(GetRoutingTableResponse { routing: Some(t) })),
            None => Err(Status::not_found(format!(
                "job_id: no running job {} on this cluster",
                crate::text::bounded(id)
            ))),
        }
    }

    async fn report_queues(
        &self,
        r: Request<ReportQueuesRequest>,
    ) -> Result<Response<ReportQueuesResponse>, Status> {
        self.cluster
            .membership
            .check_member(&r.get_ref().worker_id, r.metadata())?;
        let r = r.into_inner();
        self.cluster.membership.touch(&r.worker_id);
        // 0 tells the worker the job is not running at that attempt (versions start at
        // 1): it is over, or a lost worker made it start again (the release of the old
        // attempt is then on its way).
        let routing_version = self.cluster.jobs.report_queues(r).await.unwrap_or(0);
        Ok(Response::new(ReportQueuesResponse { routing_version }))
    }

    async fn report_contributions(
        &self,
        r: Request<ReportContributionsRequest>,
    ) -> Result<Response<ReportContributionsResponse>, Status> {
        self.cluster
            .membership
            .check_member(&r.get_ref().worker_id, r.metadata())?;
        let r = r.into_inner();
        self.cluster.membership.touch(&r.worker_id);
        let reporter = r.worker_id.clone();
        let reply = self.cluster.jobs.report(r).await?;
        // Peers this worker could not send rays to are lost to the job (their rays were
        // dropped): the job restarts on the others, as after a missed heartbeat. The job
        // named only its own workers, and only while it runs.
        for peer in &reply.unreachable {
            if let Some(lost) =
                self.cluster
                    .membership
                    .drop_unreachable(peer, &reporter, Instant::now())
            {
                self.cluster.jobs.worker_lost(&lost).await;
            }
        }
        let outcome = reply.outcome;
        Ok(Response::new(ReportContributionsResponse {
            job_active: outcome.job_active(),
        }))
    }

    async fn register_cache_host(
        &self,
        r: Request<RegisterCacheHostRequest>,
    ) -> Result<Response<RegisterCacheHostResponse>, Status> {
        if !self.cluster.options.cache_hosts {
            return Err(Status::failed_precondition(
                "this coordinator takes no stand-alone cache hosts (start it with \
                 --cache-hosts; without them, cache actors run beside the workers)",
            ));
        }
        let registered = self.cluster.membership.cache_hosts.register(r.get_ref())?;
        let heartbeat = self.cluster.membership.heartbeat;
        Ok(Response::new(RegisterCacheHostResponse {
            host_id: registered.host_id,
            member_token: registered.member_token,
            refresh_interval: duration(heartbeat.interval),
            expiry: duration(heartbeat.timeout),
        }))
    }

    async fn get_peer_pass(
        &self,
        r: Request<GetPeerPassRequest>,
    ) -> Result<Response<GetPeerPassResponse>, Status> {
        let (id, peer) = (&r.get_ref().worker_id, &r.get_ref().peer_id);
        let membership = &self.cluster.membership;
        if membership.get(id).is_none() {
            return Err(Status::not_found(format!(
                "worker_id: {} is not registered (register again)",
                crate::text::bounded(id)
            )));
        }
        // A registered caller must prove it is `id`.
        membership.check_member(id, r.metadata())?;
        let Some(p) = membership.get(peer) else {
            return Err(Status::not_found(format!(
                "peer_id: {} is not registered",
                crate::text::bounded(peer)
            )));
        };
        Ok(Response::new(GetPeerPassResponse {
            pass: dray_net::peer_pass::peer_pass(p.member_token.expose(), id),
        }))
    }
}
