//! The registry of running jobs: routes each call to its job's actor by job id, as a
//! cache host routes lookups to its wall actors, and holds every job actor in one
//! `JoinSet`, so there is one place they live and one way they stop (dropping the
//! registry aborts them; see the actor's guard for what an aborted job's record says).
//!
//! Routing is a concurrent map (`dashmap`) from job id to the actor's bounded mailbox;
//! no lock is held across a job's work, so jobs do not wait for each other. A full
//! mailbox makes the caller wait: reports are back-pressured, not dropped.

use std::sync::{Arc, Mutex};

use dashmap::DashMap;
use dashmap::mapref::entry::Entry;
use dray_proto::v1::{ReportContributionsRequest, ReportQueuesRequest, RoutingTable};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tonic::Status;

use super::actor::{ActorConfig, JobActor};
use super::event::{JobEvent, JobHandle, ReportReply};
use super::running::{JobPlan, RunningJob};
use super::view::JobView;
use crate::membership::{LostWorker, Membership, WorkerRecord};
use crate::scheduler::state::JobSchedule;

/// Events a job's mailbox holds before senders wait.
pub const MAILBOX: usize = 256;

/// Every job running on workers, each served by its own actor.
pub struct JobRegistry {
    jobs: Arc<DashMap<String, JobHandle>>,
    actors: Mutex<JoinSet<()>>,
    membership: Arc<Membership>,
    config: ActorConfig,
}

impl JobRegistry {
    /// No jobs; the actors send commands through `membership`.
    pub fn new(membership: Arc<Membership>, config: ActorConfig) -> JobRegistry {
        JobRegistry {
            jobs: Arc::new(DashMap::new()),
            actors: Mutex::new(JoinSet::new()),
            membership,
            config,
        }
    }

    /// Start a job's actor, which sends each of the job's workers its JobSetup and
    /// tiles. Fails (sending nothing) when the job was cancelled meanwhile, or names the
    /// first worker that is gone. Must be called inside a tokio runtime.
    pub async fn start(&self, plan: JobPlan) -> Result<(), String> {
        let job = RunningJob::new(plan);
        let id = job.id().to_string();
        let (tx, rx) = mpsc::channel(MAILBOX);
        match self.jobs.entry(id.clone()) {
            Entry::Occupied(_) => return Err(format!("job {id} is already running")),
            Entry::Vacant(v) => {
                v.insert(JobHandle {
                    tx,
                    package: job.package(),
                    env_map: job.env_map_file(),
                });
            }
        }
        let (started_tx, started) = oneshot::channel();
        let actor = JobActor::new(job, self.membership.clone(), self.jobs.clone(), self.config);
        {
            let mut actors = dray_sync::lock(&self.actors);
            // Collect the actors that ended since, so the set holds only live ones.
            while let Some(done) = actors.try_join_next() {
                if let Err(e) = done
                    && e.is_panic()
                {
                    tracing::error!("a job's actor panicked: {e}");
                }
            }
            actors.spawn(actor.run(rx, started_tx));
        }
        started
            .await
            .unwrap_or_else(|_| Err(format!("job {id}'s actor stopped before it started")))
    }

    /// The mailbox of job `id`, if it is running.
    fn mailbox(&self, id: &str) -> Option<mpsc::Sender<JobEvent>> {
        self.jobs.get(id).map(|h| h.tx.clone())
    }

    /// Post `ev` to job `id`; false when it is not running.
    async fn post(&self, id: &str, ev: JobEvent) -> bool {
        match self.mailbox(id) {
            Some(tx) => tx.send(ev).await.is_ok(),
            None => false,
        }
    }

    /// Ask job `id` something; None when it is not running (or ends before it answers).
    async fn ask<T>(&self, id: &str, ev: impl FnOnce(oneshot::Sender<T>) -> JobEvent) -> Option<T> {
        let (tx, rx) = oneshot::channel();
        if !self.post(id, ev(tx)).await {
            return None;
        }
        rx.await.ok()
    }

    /// Apply one ReportContributions call to its job.
    pub async fn report(&self, r: ReportContributionsRequest) -> Result<ReportReply, Status> {
        let id = r.job_id.clone();
        self.ask(&id, |tx| JobEvent::Report(Box::new(r), tx))
            .await
            .unwrap_or_else(|| Ok(ReportReply::inactive()))
    }

    /// Store a queue report in its job; the job's routing version, or None when the job
    /// is not running at the report's attempt (or the worker is not one of its workers).
    pub async fn report_queues(&self, r: ReportQueuesRequest) -> Option<u64> {
        let id = r.job_id.clone();
        self.ask(&id, |tx| JobEvent::QueueReport(r, tx))
            .await
            .flatten()
    }

    /// Worker `lost` was dropped: every job is told (each checks whether it was one of
    /// its workers).
    pub async fn worker_lost(&self, lost: &LostWorker) {
        for tx in self.all() {
            let _ = tx.send(JobEvent::WorkerLost(lost.clone())).await;
        }
    }

    /// Worker `w` registered: every job is told (running dynamic jobs take it on).
    pub async fn worker_joined(&self, w: &WorkerRecord) {
        for tx in self.all() {
            let _ = tx.send(JobEvent::WorkerJoined(w.clone())).await;
        }
    }

    fn all(&self) -> Vec<mpsc::Sender<JobEvent>> {
        self.jobs.iter().map(|h| h.tx.clone()).collect()
    }

    /// Stop job `id` on its workers (CancelJob; the caller marks it CANCELLED first).
    /// False when it is not running here.
    pub async fn cancel(&self, id: &str) -> bool {
        self.ask(id, JobEvent::Cancel).await.is_some()
    }

    /// The current routing table of job `id`.
    pub async fn routing(&self, id: &str) -> Option<RoutingTable> {
        self.ask(id, JobEvent::Routing).await
    }

    /// A copy of job `id`'s scheduling state (for tests and introspection).
    pub async fn schedule(&self, id: &str) -> Option<JobSchedule> {
        self.ask(id, JobEvent::Schedule).await
    }

    /// A snapshot of every running job's domains, owners and queues (ListWorkers). A
    /// job whose actor does not answer within `wait` (busy with a long report) is left
    /// out rather than holding the listing.
    pub async fn views(&self, wait: std::time::Duration) -> Vec<JobView> {
        let mut asks = JoinSet::new();
        for tx in self.all() {
            asks.spawn(async move {
                let (reply, rx) = oneshot::channel();
                tx.send(JobEvent::View(reply)).await.ok()?;
                tokio::time::timeout(wait, rx).await.ok()?.ok()
            });
        }
        let mut views = Vec::new();
        while let Some(done) = asks.join_next().await {
            if let Ok(Some(v)) = done {
                views.push(v);
            }
        }
        views
    }

    /// The package of running job `id` (`JobSetup.package_path`,
    /// `JobSetup.package_checksum`): what the PackageService may serve for it, and only
    /// while the job runs.
    pub fn package(&self, id: &str) -> Option<(String, String)> {
        self.jobs.get(id).map(|h| h.package.clone())
    }

    /// The environment map file of running job `id` (`JobSetup.env_map`), if it has
    /// one: the PackageService serves it with the package, only while the job runs.
    pub fn env_map(&self, id: &str) -> Option<dray_proto::v1::EnvMapFile> {
        self.jobs.get(id).and_then(|h| h.env_map.clone())
    }

    /// Whether job `id` is running on workers.
    pub fn contains(&self, id: &str) -> bool {
        self.jobs.contains_key(id)
    }

    /// How many jobs are running on workers.
    pub fn len(&self) -> usize {
        self.jobs.len()
    }

    /// Whether no job is running on workers.
    pub fn is_empty(&self) -> bool {
        self.jobs.is_empty()
    }
}
