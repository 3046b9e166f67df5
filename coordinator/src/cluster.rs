//! `dray.v1.ClusterService`: the calls workers make to the coordinator, over the
//! [`Membership`], the [`Ledger`] and the [`Router`].
//!
//! Workers dial out; the coordinator answers and pushes commands on each worker's
//! WatchAssignments stream. See cluster.proto for the protocol and [`crate::dispatch`] for
//! what a job's workers receive, in order.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use dray_proto::v1::cluster_service_server::ClusterService;
use dray_proto::v1::{
    Assignment, GetRoutingTableRequest, GetRoutingTableResponse, HeartbeatRequest,
    HeartbeatResponse, RegisterWorkerRequest, RegisterWorkerResponse, ReportContributionsRequest,
    ReportContributionsResponse, ReportQueuesRequest, ReportQueuesResponse,
    WatchAssignmentsRequest,
};
use dray_scene::partition::memory::MemoryPackages;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::ledger::Ledger;
use crate::membership::{HeartbeatConfig, Membership};
use crate::routing::{RoundRobin, Router};

/// Settings of the cluster side of the coordinator.
#[derive(Clone, Debug)]
pub struct ClusterOptions {
    /// Heartbeat interval and timeout told to workers.
    pub heartbeat: HeartbeatConfig,
    /// Where per-job scene packages are written (a directory per job, removed when the
    /// job is released). Must be readable by the workers at the same path.
    pub work_dir: PathBuf,
    /// When set, packages for scenes are cut into this in-memory store instead of the
    /// work directory: for workers in the coordinator's own process (`dray render`),
    /// which read the same store. Workers elsewhere cannot, so a cluster leaves it unset.
    pub memory_packages: Option<Arc<MemoryPackages>>,
}

impl Default for ClusterOptions {
    fn default() -> ClusterOptions {
        ClusterOptions {
            heartbeat: HeartbeatConfig::default(),
            work_dir: std::env::temp_dir().join(format!("dray-coordinator-{}", std::process::id())),
            memory_packages: None,
        }
    }
}

/// Membership, accounting and routing of the coordinator's workers.
pub struct Cluster {
    /// Registered workers and their command outboxes.
    pub membership: Arc<Membership>,
    /// Jobs running on workers.
    pub ledger: Ledger,
    /// Domain assignment.
    pub router: Box<dyn Router>,
    /// Settings.
    pub options: ClusterOptions,
}

impl Cluster {
    /// A cluster with no workers, routing round robin.
    pub fn new(options: ClusterOptions) -> Cluster {
        let membership = Arc::new(Membership::new(options.heartbeat));
        Cluster {
            ledger: Ledger::new(membership.clone()),
            membership,
            router: Box::new(RoundRobin),
            options,
        }
    }

    /// Drop workers silent for too long and fail their jobs. Returns how many were
    /// dropped.
    pub fn reap(&self, now: Instant) -> usize {
        let lost = self.membership.expire(now);
        for w in &lost {
            self.ledger.worker_lost(&w.id, &w.endpoint, w.silent_for);
        }
        lost.len()
    }

    /// Call [`Cluster::reap`] periodically, forever (the server aborts it on shutdown).
    pub async fn reaper(self: Arc<Self>) {
        // A quarter of the timeout: a lost worker is noticed within 1.25 timeouts.
        let period = (self.options.heartbeat.timeout / 4).max(Duration::from_millis(10));
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            self.reap(Instant::now());
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
        let hb = self.cluster.membership.heartbeat;
        Ok(Response::new(RegisterWorkerResponse {
            worker_id: w.id,
            heartbeat_interval: duration(hb.interval),
            heartbeat_timeout: duration(hb.timeout),
        }))
    }

    async fn heartbeat(
        &self,
        r: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatResponse>, Status> {
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
        let Some(w) = self.cluster.membership.get(id) else {
            return Err(Status::not_found(format!(
                "worker_id: {id:?} is not registered (register again)"
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
        match self.cluster.ledger.routing(id) {
            Some(t) => Ok(Response::new(GetRoutingTableResponse { routing: Some(t) })),
            None => Err(Status::not_found(format!(
                "job_id: no running job {id:?} on this cluster"
            ))),
        }
    }

    async fn report_queues(
        &self,
        r: Request<ReportQueuesRequest>,
    ) -> Result<Response<ReportQueuesResponse>, Status> {
        let r = r.into_inner();
        self.cluster.membership.touch(&r.worker_id);
        // 0 tells the worker the job is no longer running (versions start at 1).
        let routing_version = self.cluster.ledger.report_queues(r).unwrap_or(0);
        Ok(Response::new(ReportQueuesResponse { routing_version }))
    }

    async fn report_contributions(
        &self,
        r: Request<ReportContributionsRequest>,
    ) -> Result<Response<ReportContributionsResponse>, Status> {
        let r = r.into_inner();
        self.cluster.membership.touch(&r.worker_id);
        let outcome = self.cluster.ledger.report(&r)?;
        Ok(Response::new(ReportContributionsResponse {
            job_active: outcome.job_active(),
        }))
    }
}
