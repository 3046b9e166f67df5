//! A job's actor: one task that owns a [`RunningJob`] and changes it, one event at a time,
//! from its mailbox, its timers and its cache-wall tasks (docs/architecture.md "The
//! coordinator"). Nothing else holds the job's state, so nothing locks it: a worker never
//! sees a table or tiles of an attempt the job has not made yet, and a report never sees
//! half a restart, because the changes and the commands they cause are made in one step.
//!
//! - **Round pacing** is the actor's timer: a queue report runs a round at once or, if
//!   the last round was less than the interval ago, arms the timer for when it may.
//! - **Stalls**: a job none of whose workers returned credit for the stall timeout fails.
//!   Heartbeats only say a worker is alive; a member that heartbeats but never traces
//!   (broken, or hostile) would otherwise hold its job forever.
//! - **Cache walls** (docs/caches.md): a job with ray caches or hit maps has its
//!   attempt's walls open on cache hosts before the attempt's tiles go out, and closed
//!   when the attempt ends. Those are network calls, so they run as tasks in the actor's
//!   own `JoinSet`, whose results come back to the actor's loop: a new attempt after a
//!   lost worker is *pending* (its old attempt cancelled, its tiles cleared, nothing
//!   sent) until its walls are open; walls that open for an attempt the job has left
//!   are closed again. A job that ends waits for its walls to close, so it turns
//!   terminal with its final statistics.
//!
//! When the job ends the actor leaves the registry first (later calls find no job), answers
//! what is left in its mailbox as for a job that is not running, closes its walls, and
//! then finishes the public record and removes the job's package.

use std::sync::Arc;
use std::time::{Duration, Instant};

use dashmap::DashMap;
use dray_proto::v1::{JobState, ReportContributionsRequest, assignment::Command};
use tokio::sync::mpsc;
use tokio::task::{JoinError, JoinSet};
use tracing::Instrument;

use super::caches::{self as cache_job, OpenAttempt};
use super::event::{JobEvent, JobHandle, ReportReply};
use super::report::{self, Applied, ReportOutcome};
use super::running::{Release, RunningJob, command};
use crate::caches::lifecycle::{self, AttemptWalls, Opened};
use crate::caches::placement::Placement;
use crate::membership::{LostWorker, Membership, WorkerRecord};
use crate::owned_package::remove_package;
use crate::scheduler::state::RoundOutcome;

/// Least time between two publications of a job's per-worker detail (an O(workers)
/// copy; the totals are published with every change).
pub const DETAIL_INTERVAL: Duration = Duration::from_millis(250);

/// How a job's actor paces itself.
#[derive(Clone, Copy, Debug)]
pub struct ActorConfig {
    /// Least time between two scheduling rounds.
    pub round_interval: Duration,
    /// A job none of whose workers returned credit for this long fails (None: never).
    pub stall_timeout: Option<Duration>,
}

/// What a cache-wall task came back with.
enum WallsDone {
    /// The walls of `walls.attempt` are open as `opened` (empty: none could be).
    Opened {
        walls: Box<AttemptWalls>,
        opened: Opened,
    },
    /// Walls were closed (their statistics are in the tally).
    Closed,
}

/// How the job ended.
struct Ending {
    state: JobState,
    error: String,
}

/// The actor of one job.
pub(super) struct JobActor {
    job: RunningJob,
    membership: Arc<Membership>,
    /// The registry's map, which the actor leaves when the job ends.
    registry: Arc<DashMap<String, JobHandle>>,
    config: ActorConfig,
    /// When the next round is due, if a queue report is waiting for one.
    round_at: Option<Instant>,
    /// When the per-worker detail is next published, if it is stale.
    detail_at: Option<Instant>,
    /// Tasks opening and closing this job's cache walls.
    walls: JoinSet<WallsDone>,
    ending: Option<Ending>,
}

impl JobActor {
    pub(super) fn new(
        job: RunningJob,
        membership: Arc<Membership>,
        registry: Arc<DashMap<String, JobHandle>>,
        config: ActorConfig,
    ) -> JobActor {
        JobActor {
            job,
            membership,
            registry,
            config,
            round_at: None,
            detail_at: None,
            walls: JoinSet::new(),
            ending: None,
        }
    }

    /// Start the job (its result goes to `started`), then serve its mailbox until it
    /// ends. A job that cannot start leaves without finishing its record: the
    /// dispatcher that started it says why.
    pub(super) async fn run(
        self,
        rx: mpsc::Receiver<JobEvent>,
        started: tokio::sync::oneshot::Sender<Result<(), String>>,
    ) {
        let span = tracing::info_span!("job", id = %self.job.record.id);
        let mut guard = Guard {
            id: self.job.record.id.clone(),
            registry: self.registry.clone(),
            record: self.job.record.clone(),
            armed: true,
        };
        self.serve(rx, started, &mut guard).instrument(span).await;
    }

    async fn serve(
        mut self,
        mut rx: mpsc::Receiver<JobEvent>,
        started: tokio::sync::oneshot::Sender<Result<(), String>>,
        guard: &mut Guard,
    ) {
        let start = self.start().await;
        let ok = start.is_ok();
        let _ = started.send(start);
        if !ok {
            guard.armed = false;
            return;
        }
        self.job.publish_detail();
        // Tiles taken back whole from the job store are complete in every pass: passes
        // they make up entirely are over at once.
        while self.job.pass_complete() {
            self.start_next_pass();
        }
        if self.job.all_complete() {
            // Taken back from the job store with every tile committed (the coordinator
            // stopped between the last tile and the job's end).
            tracing::info!("every tile was committed before the restart: job complete");
            self.send_all(self.job.releases(Release::Finish, "completed"));
            self.end(JobState::Succeeded, String::new());
        }
        while self.ending.is_none() {
            if self.detail_at.is_none() && self.job.detail_stale() {
                self.detail_at = Some(Instant::now() + DETAIL_INTERVAL);
            }
            let round_at = self.round_at;
            let detail_at = self.detail_at;
            let stall_at = self
                .config
                .stall_timeout
                .map(|t| self.job.ledger.last_progress() + t + Duration::from_millis(1));
            tokio::select! {
                ev = rx.recv() => match ev {
                    Some(ev) => self.on_event(ev).await,
                    None => self.fail("the coordinator dropped the job's mailbox".into()),
                },
                () = sleep_until(round_at) => {
                    self.round_at = None;
                    self.round(Instant::now());
                }
                () = sleep_until(stall_at) => self.check_stall(Instant::now()),
                () = sleep_until(detail_at) => {
                    self.detail_at = None;
                    self.job.publish_detail();
                }
                Some(done) = self.walls.join_next(), if !self.walls.is_empty() => {
                    self.on_walls(done);
                }
            }
        }
        // Out of the registry already (see `end`): answer what is queued, then close.
        rx.close();
        while let Ok(ev) = rx.try_recv() {
            answer_ended(ev);
        }
        self.finish().await;
        guard.armed = false;
    }

    /// Start the job on its workers (see [`RunningJob::start`]).
    async fn start(&mut self) -> Result<(), String> {
        self.job.start(&self.membership).await
    }

    /// Run the scheduling round if one is due at `now`; arm the timer when it is due
    /// later.
    fn round(&mut self, now: Instant) {
        if let RoundOutcome::NotBefore(at) =
            self.job
                .round(&self.membership, now, self.config.round_interval)
        {
            self.round_at = Some(at);
        }
    }

    fn send_attempt(&mut self) {
        self.job.send_attempt(&self.membership);
    }

    fn join(&mut self, w: &WorkerRecord) {
        self.job.join(&self.membership, w);
    }

    async fn on_event(&mut self, ev: JobEvent) {
        match ev {
            JobEvent::Report(r, reply) => {
                let _ = reply.send(self.report(&r));
            }
            JobEvent::QueueReport(r, reply) => {
                let version = self.job.queue_report(&r);
                let _ = reply.send(version);
                // A round already waiting for its time covers this report too.
                if version.is_some() && self.round_at.is_none() {
                    self.round(Instant::now());
                }
            }
            JobEvent::WorkerLost(lost) => self.worker_lost(&lost).await,
            JobEvent::WorkerJoined(w) => {
                if self.job.takes_joiners() && !self.job.record.is_terminal() {
                    self.join(&w);
                }
            }
            JobEvent::Cancel(reply) => {
                tracing::info!("job cancelled on its workers");
                self.send_all(self.job.releases(Release::Cancel, "cancelled by user"));
                self.end(JobState::Cancelled, String::new());
                let _ = reply.send(());
            }
            JobEvent::Routing(reply) => {
                let _ = reply.send(self.job.sched.table());
            }
            JobEvent::Schedule(reply) => {
                let _ = reply.send(self.job.sched.clone());
            }
            JobEvent::View(reply) => {
                let _ = reply.send(self.job.view());
            }
        }
    }

    /// One ReportContributions call: checked, applied, and the transitions it causes.
    fn report(&mut self, r: &ReportContributionsRequest) -> Result<ReportReply, tonic::Status> {
        let outcome = match report::check(&self.job, r)? {
            Some(outcome) => outcome,
            None => self.apply(r),
        };
        // Peers this worker could not send rays to are lost to the job (their rays were
        // dropped); only peers of a job still running, named by one of its workers, count.
        let unreachable = if outcome.job_active() {
            r.unreachable_peers
                .iter()
                .take(16)
                .filter(|p| **p != r.worker_id && self.job.sched.has_worker(p))
                .cloned()
                .collect()
        } else {
            Vec::new()
        };
        Ok(ReportReply {
            outcome,
            unreachable,
        })
    }

    fn apply(&mut self, r: &ReportContributionsRequest) -> ReportOutcome {
        let _span = tracing::info_span!("report", attempt = r.attempt).entered();
        match report::apply(&mut self.job, r) {
            Applied::WorkerFailed(msg) => {
                tracing::warn!(worker = %r.worker_id, "{msg}");
                self.fail(msg);
                ReportOutcome::Failed
            }
            Applied::Overdrawn(msg) => {
                self.job.publish();
                tracing::error!("{msg}");
                self.fail(msg);
                ReportOutcome::Failed
            }
            Applied::Counted => {
                self.job.persist_committed();
                self.job.publish();
                if self.job.coarse_pass_complete() {
                    self.start_image_pass();
                }
                if self.job.pass_complete() {
                    self.start_next_pass();
                }
                if self.job.all_complete() {
                    tracing::info!(tiles = self.job.ledger.tile_count(), "job complete");
                    self.send_all(self.job.releases(Release::Finish, "completed"));
                    self.end(JobState::Succeeded, String::new());
                    ReportOutcome::Completed
                } else {
                    // A replicated job tops the reporting worker up from the tiles
                    // nobody has started once it has room (`super::backlog`).
                    for (w, a) in self.job.top_up(&r.worker_id) {
                        if !self.membership.send_shared(&w, a) {
                            tracing::debug!(worker = %w, "worker gone before its top-up");
                        }
                    }
                    ReportOutcome::Applied
                }
            }
        }
    }

    /// The coarse pass is complete, and with it every ticket of its rays (workers report
    /// credit only once the cache actors have its ticket returns): the image's tiles go
    /// out now.
    fn start_image_pass(&mut self) {
        let job = &mut self.job;
        job.coarse_done = true;
        if let Some(t0) = job.coarse_started.take() {
            let seconds = t0.elapsed().as_secs_f64();
            job.record.update_stats(|s| s.coarse_seconds = seconds);
            tracing::info!(seconds, "coarse pass time");
        }
        let coarse = job.ledger.coarse_tiles().len();
        let rays: u64 = job
            .ledger
            .coarse_tiles()
            .iter()
            .map(|t| u64::from(t.width) * u64::from(t.height))
            .sum();
        if let Some(c) = &job.caches {
            c.tally.add_host(&dray_proto::v1::RayCacheStats {
                coarse_rays: rays,
                ..Default::default()
            });
        }
        tracing::info!(
            tiles = coarse,
            "coarse pass complete; the image's tiles go out"
        );
        let tiles = job.incomplete_tiles();
        let commands = job.commands(&tiles, false);
        for (w, a) in commands {
            if !self.membership.send_shared(&w, a) {
                tracing::debug!(worker = %w, "worker gone before the image's tiles");
            }
        }
    }

    /// Every image tile finished a pass that is not the last: the next pass's tiles go
    /// out (the scheduler's rule deals them again, so a worker that joined meanwhile
    /// gets its share).
    fn start_next_pass(&mut self) {
        let tiles = self.job.next_pass();
        tracing::info!(
            pass = self.job.pass,
            passes = self.job.passes_total(),
            tiles = tiles.len(),
            "pass complete; the next pass's tiles go out"
        );
        if let Some((workers, marker)) = self.job.pass_markers() {
            for w in workers {
                self.membership.send_shared(&w, marker.clone());
            }
        }
        for (w, a) in self.job.commands(&tiles, false) {
            if !self.membership.send_shared(&w, a) {
                tracing::debug!(worker = %w, "worker gone before the next pass's tiles");
            }
        }
    }

    /// Fail the job if none of its workers returned credit for the stall timeout.
    fn check_stall(&mut self, now: Instant) {
        let Some(timeout) = self.config.stall_timeout else {
            return;
        };
        let quiet = now.saturating_duration_since(self.job.ledger.last_progress());
        if quiet <= timeout {
            return;
        }
        let msg = format!(
            "no progress for {:.0} s: none of the job's workers ({}) returned any \
             credit (the coordinator's --stall-timeout is {} s)",
            quiet.as_secs_f64(),
            self.job.sched.worker_ids().join(", "),
            timeout.as_secs()
        );
        tracing::warn!("{msg}");
        self.fail(msg);
    }

    /// Worker `lost` was dropped. If it was one of the job's, the job starts its next
    /// attempt on the survivors: they are told to cancel the old attempt, then get a
    /// JobSetup with the new attempt and table, then the tiles that were not complete,
    /// dealt by the job's schedule. With no survivor the job fails, naming the worker. A
    /// worker that joined a dynamic job and was never given a domain held no credit: the
    /// others only get a table without it.
    async fn worker_lost(&mut self, lost: &LostWorker) {
        if self.job.record.is_terminal() || !self.job.sched.has_worker(&lost.id) {
            return;
        }
        if let Some(table) = self.job.sched.remove_unused(&lost.id) {
            tracing::info!(
                worker = %lost.id,
                endpoint = %lost.endpoint,
                version = table.version,
                "worker lost before it was given work; the job goes on without it"
            );
            self.membership.send_all(
                &self.job.sched.worker_ids(),
                command(Command::Routing(table.clone())),
            );
            self.job.publish();
            return;
        }
        let old = self.job.sched.attempt();
        if self.job.sched.restart_without(&lost.id).is_some() {
            self.retrace(old, lost).await;
            return;
        }
        let msg = format!(
            "worker {} at {} was lost ({}), and no worker is left to trace its tiles again",
            lost.label(),
            lost.endpoint,
            lost.cause
        );
        tracing::warn!(worker = %lost.id, name = %lost.name, endpoint = %lost.endpoint, "{msg}");
        self.fail(msg);
    }

    /// Clear and re-deal the incomplete tiles, the schedule having just moved to a new
    /// attempt without `lost` (`old` is the attempt dropped).
    async fn retrace(&mut self, old: u32, lost: &LostWorker) {
        self.job.persist_committed();
        self.job.persist_attempt().await;
        let n = self.job.clear_for_retry();
        let attempt = self.job.sched.attempt();
        let reason = format!(
            "worker {} at {} was lost ({}); {n} tiles are traced again as attempt {attempt}",
            lost.label(),
            lost.endpoint,
            lost.cause
        );
        tracing::warn!(
            worker = %lost.id,
            name = %lost.name,
            endpoint = %lost.endpoint,
            attempt,
            tiles = n,
            workers = self.job.sched.worker_ids().len(),
            "{reason}"
        );
        let record = &self.job.record;
        record.note(dray_proto::v1::JobEventKind::WorkerLost, reason.clone());
        let n = record.log.attempts() + 1;
        record.note(
            dray_proto::v1::JobEventKind::Started,
            format!(
                "started: attempt {n}, on the {} workers left",
                self.job.sched.worker_ids().len()
            ),
        );
        self.send_all(self.job.releases_of(old, Release::Cancel, &reason));
        self.job.record.set_rays_in_flight(0);
        if !self.reopen_caches() {
            self.send_attempt();
        }
        self.job.publish();
    }

    /// For a job with caches whose new attempt has just been made: mark the attempt
    /// pending and start the task that closes the old attempt's walls and places and
    /// opens the new one's; [`JobActor::caches_opened`] sends the attempt when it is
    /// back. False when the job has no caches: the caller sends the attempt at once.
    fn reopen_caches(&mut self) -> bool {
        let Some(c) = self.job.caches.as_mut() else {
            return false;
        };
        let attempt = self.job.sched.attempt();
        let prev = c.opened.take();
        let candidates = cache_job::candidates(&self.membership, &self.job.sched);
        let placement = cache_job::place(&candidates, &self.job.sched, self.job.sched.domains(), c);
        c.pending = Some(attempt);
        let walls = c.attempt_walls(&self.job.record.id, attempt);
        let tally = c.tally.clone();
        self.walls.spawn(async move {
            if let Some(p) = prev {
                let closed =
                    lifecycle::close(&walls.job_id, p.attempt, &p.placement, &walls.net).await;
                closed.add_to(&tally);
                tally.lose(closed.failed.iter().map(|f| f.host.endpoint.as_str()));
            }
            let opened = if placement.is_empty() {
                tracing::warn!(
                    attempt,
                    "no cache host is left: the attempt runs without ray caches"
                );
                Opened::default()
            } else {
                lifecycle::open(&walls, placement).await
            };
            WallsDone::Opened {
                walls: Box::new(walls),
                opened,
            }
        });
        true
    }

    /// A cache-wall task is back.
    fn on_walls(&mut self, done: Result<WallsDone, JoinError>) {
        match done {
            Ok(WallsDone::Closed) => {}
            Ok(WallsDone::Opened { walls, opened }) => {
                let attempt = walls.attempt;
                if self.caches_opened(attempt, opened.placement.clone()) {
                    if let Some(c) = &self.job.caches {
                        c.tally
                            .lose(opened.failed.iter().map(|f| f.host.endpoint.as_str()));
                    }
                } else {
                    // The job moved on to another attempt while these walls opened:
                    // close them again. A host failing now is no loss (a newer attempt
                    // opening on it drops this one).
                    self.close_later(*walls, opened.placement);
                }
                self.job.publish();
            }
            Err(e) => {
                // A wall task panicked: the attempt it was opening runs without caches.
                tracing::error!("a task opening or closing cache walls failed: {e}");
                let pending = self.job.caches.as_ref().and_then(|c| c.pending);
                if let Some(attempt) = pending {
                    self.caches_opened(attempt, Placement::default());
                }
            }
        }
    }

    /// Close `placement`'s walls of `walls.attempt` on a task of the actor.
    fn close_later(&mut self, walls: AttemptWalls, placement: Placement) {
        let Some(c) = &self.job.caches else { return };
        let tally = c.tally.clone();
        self.walls.spawn(async move {
            let closed =
                lifecycle::close(&walls.job_id, walls.attempt, &placement, &walls.net).await;
            closed.add_to(&tally);
            WallsDone::Closed
        });
    }

    /// The walls of pending attempt `attempt` are open as `placement` (empty: none
    /// could be; the attempt runs without caches): put the placement in the attempt's
    /// tables and send its setup and tiles. False, changing nothing, when the job has
    /// ended or moved on to another attempt meanwhile (the caller closes the walls).
    fn caches_opened(&mut self, attempt: u32, placement: Placement) -> bool {
        if self.ending.is_some()
            || self.job.record.is_terminal()
            || self.job.sched.attempt() != attempt
        {
            return false;
        }
        let Some(c) = self.job.caches.as_mut() else {
            return false;
        };
        if c.pending != Some(attempt) {
            return false;
        }
        c.pending = None;
        c.opened = (!placement.is_empty()).then(|| OpenAttempt {
            attempt,
            placement: placement.clone(),
        });
        tracing::info!(
            attempt,
            hosts = placement.hosts().len(),
            "cache walls open; the attempt starts"
        );
        self.job.sched.set_caches(placement);
        self.send_attempt();
        self.job.publish();
        if self.job.sched.schedule().is_dynamic() {
            // Workers that registered while the attempt was pending were not joined.
            for w in self.membership.workers() {
                self.join(&w);
            }
        }
        true
    }

    /// Release the workers and end as FAILED with `msg`.
    fn fail(&mut self, msg: String) {
        self.send_all(self.job.releases(Release::Cancel, &msg));
        self.end(JobState::Failed, msg);
    }

    /// End the job as `state`: it leaves the registry now (later calls find no job);
    /// the loop stops and [`JobActor::finish`] completes the record.
    fn end(&mut self, state: JobState, error: String) {
        if self.ending.is_some() {
            return;
        }
        self.registry.remove(&self.job.record.id);
        self.ending = Some(Ending { state, error });
    }

    fn send_all(&self, commands: Vec<(String, dray_proto::v1::Assignment)>) {
        for (w, a) in commands {
            self.membership.send(&w, a);
        }
    }

    /// Close the open walls (and any that the actor's wall tasks still open), add their
    /// statistics, then finish the public record as the ending says (with the film when
    /// it succeeded) and remove the package. A cancelled job is marked CANCELLED
    /// already: its statistics follow.
    async fn finish(mut self) {
        let Some(Ending { state, error }) = self.ending.take() else {
            return;
        };
        self.job.publish_detail();
        let open = self
            .job
            .caches
            .as_mut()
            .and_then(|c| c.opened.take().map(|o| (o, c.tally.clone(), c.net.clone())));
        if let Some((open, tally, net)) = open {
            let id = &self.job.record.id;
            let closed = lifecycle::close(id, open.attempt, &open.placement, &net).await;
            closed.add_to(&tally);
            tally.lose(closed.failed.iter().map(|f| f.host.endpoint.as_str()));
        }
        while let Some(done) = self.walls.join_next().await {
            if let Ok(WallsDone::Opened { walls, opened }) = done {
                // Opened for an attempt the job never sent: close again.
                let closed =
                    lifecycle::close(&walls.job_id, walls.attempt, &opened.placement, &walls.net)
                        .await;
                if let Some(c) = &self.job.caches {
                    closed.add_to(&c.tally);
                }
            }
        }
        let RunningJob {
            record,
            owned_package,
            film,
            stats,
            caches,
            ..
        } = self.job;
        if let Some(c) = &caches {
            record.update_stats(|s| c.tally.fill(s));
        }
        let (nonfinite, clamped, clamped_indirect) = stats.film_counts();
        let film = (state == JobState::Succeeded)
            .then(|| film.into_film(nonfinite, clamped, clamped_indirect));
        record.finish(state, error, film);
        remove_package(owned_package.as_ref());
    }
}

/// Answer an event that arrived after the job ended, as for a job that is not running.
fn answer_ended(ev: JobEvent) {
    match ev {
        JobEvent::Report(_, reply) => {
            let _ = reply.send(Ok(ReportReply::inactive()));
        }
        JobEvent::QueueReport(_, reply) => {
            let _ = reply.send(None);
        }
        JobEvent::Cancel(reply) => {
            let _ = reply.send(());
        }
        // Dropping the reply says "no such job".
        JobEvent::Routing(_)
        | JobEvent::Schedule(_)
        | JobEvent::View(_)
        | JobEvent::WorkerLost(_)
        | JobEvent::WorkerJoined(_) => {}
    }
}

async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(t) => tokio::time::sleep_until(t.into()).await,
        None => std::future::pending().await,
    }
}

/// Whatever way the actor's task stops (a panic, an abort at shutdown), the job leaves
/// the registry, and a job that did not end properly is failed rather than left
/// RUNNING for ever.
struct Guard {
    id: String,
    registry: Arc<DashMap<String, JobHandle>>,
    record: Arc<super::record::JobRecord>,
    armed: bool,
}

impl Drop for Guard {
    fn drop(&mut self) {
        self.registry.remove(&self.id);
        if self.armed && !self.record.is_terminal() {
            self.record.finish(
                JobState::Failed,
                "internal error: the coordinator stopped serving this job (its actor \
                 stopped; see the coordinator's log)"
                    .into(),
                None,
            );
        }
    }
}
