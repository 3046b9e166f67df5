//! The jobs this worker runs: one [`Job`] per job id (its current attempt), each with
//! its actor ([`crate::job_actor`]), and which attempts were released.
//!
//! A job is set up from the coordinator's `JobSetup`, swaps routing tables as the
//! scheduler sends them, and is released by a `JobRelease` (finished, cancelled, or
//! replaced by a newer attempt after a lost worker). Everything of a released attempt —
//! its queued rays, its resident domains, rays still arriving for it — is dropped.
//!
//! - [`job`]: the handle the worker's parts hold, and the events they post.
//! - [`ahead`]: what a job tracing passes ahead holds back of later passes.
//! - [`report`]: what a job has to report.
//! - [`tiles`]: the tiles whose camera rays are still to be made.

pub(crate) mod ahead;
pub mod job;
pub mod report;
pub mod tiles;

use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_sync::lock;
use tokio::task::JoinSet;

pub use job::Job;
pub(crate) use job::JobEvent;
pub use report::Report;

/// How long a job's actor waits for the worker to stop before it is aborted.
pub(crate) const STOP_GRACE: Duration = Duration::from_secs(2);

/// The jobs of this worker.
#[derive(Default)]
pub struct Jobs {
    /// By job id: the attempt running here.
    jobs: Mutex<HashMap<Arc<str>, Arc<Job>>>,
    /// By job id: the newest attempt released here; its rays and older are dropped.
    released: Mutex<HashMap<Arc<str>, u32>>,
    /// Every job's actor: each ends when its job is released.
    actors: Mutex<JoinSet<()>>,
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

    /// Start `job` with `actor` (which must be its actor's run, `JobActor::supervised`:
    /// it ends when the job is released). An older attempt of the same job is released
    /// first and returned; a job whose attempt was already released is refused (false).
    pub(crate) fn start(
        &self,
        job: Arc<Job>,
        actor: impl Future<Output = ()> + Send + 'static,
    ) -> (bool, Option<Arc<Job>>) {
        if self.is_released(&job.key.id, job.key.attempt) {
            return (false, None);
        }
        let span = job.span.clone();
        let mut actors = lock(&self.actors);
        // Actors of released jobs are done: let go of them.
        while actors.try_join_next().is_some() {}
        actors.spawn(tracing::Instrument::instrument(actor, span));
        drop(actors);
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

    /// Wait for every job's actor to end (they end once their jobs are released), at
    /// most [`STOP_GRACE`]; the rest are aborted.
    pub async fn join_actors(&self) {
        let mut actors = std::mem::take(&mut *lock(&self.actors));
        let joined = tokio::time::timeout(STOP_GRACE, async {
            while actors.join_next().await.is_some() {}
        })
        .await;
        if joined.is_err() {
            actors.shutdown().await;
        }
    }
}
