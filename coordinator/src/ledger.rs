//! The ledger: credit accounting and image assembly for jobs running on workers, and
//! each job's scheduling state beside it.
//!
//! Every tile starts with a fixed credit (docs/architecture.md "Credit"); workers hand
//! credit back with the contributions of terminated rays. A tile is complete when all of
//! its credit is back, and a job when all its tiles are. Credit beyond a tile's start
//! means something was counted twice, which would silently brighten the image, so it
//! fails the job instead.
//!
//! Pixel sums arrive in fixed point and are added with integer arithmetic into one
//! [`Film`] per job: addition is associative, so the image does not depend on which
//! worker reported what, or in which order. A report is applied at most once per
//! `(worker, job, attempt, sequence)`, so a worker may retry a call whose answer it lost.
//!
//! **Attempts.** When a worker of a running job is lost, the job starts its next attempt
//! on the survivors ([`Ledger::worker_lost`]): every tile whose credit is not all back is
//! cleared (its pixels set back to exactly zero by subtracting their integer sums, its
//! returned credit to 0) and dealt again, and everything a worker sends for an older
//! attempt is ignored from then on. Complete tiles keep their pixels: their credit is all
//! back, so (by the contract below) so is every contribution they will ever have. Since
//! a pixel belongs to one tile and its rays only add to that tile's pixels, the final
//! film is bit for bit that of an undisturbed run. Ray counters, non-finite counts and
//! scheduling counters of the dropped attempt stay counted (that work was done), so those
//! statistics, unlike the image, show the loss.
//!
//! Contract for workers: a ray's contribution must be reported in the same report as the
//! credit it returns, or an earlier one: the job succeeds (and its film is frozen) the
//! moment the last credit arrives. Sequences start at 1 for each attempt.
//!
//! Every change to a job (credit, attempt, table) and the commands it causes are made
//! under one lock, so a worker never sees a table or tiles of an attempt the ledger does
//! not know yet, and a report never sees half a restart.
//!
//! **Ray caches.** A job with `ray_cache` has its attempt's walls open on cache hosts
//! before the attempt's tiles go out, and closed when the attempt ends (see
//! [`crate::caches::job`] for who closes what). Those calls are network calls, so they
//! never run under the lock: a new attempt after a lost worker is *pending* (its old
//! attempt cancelled, its tiles cleared, nothing sent) while a task closes the old walls
//! and opens the new ones, then [`Ledger::caches_opened`] sends its setup and tiles,
//! unless the job moved on meanwhile. A job that ends with walls open turns terminal
//! only once they are closed, so its final statistics include the hosts'.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use dray_core::film::Film;
use dray_proto::v1::{
    Assignment, JobRelease, JobSetup, JobState, RayCounts, ReportContributionsRequest,
    ReportQueuesRequest, RoutingTable, Tile, TileAssignment, assignment::Command,
};
use tonic::Status;

use crate::caches::job::{self as cache_job, JobCaches, OpenAttempt};
use crate::caches::lifecycle::{self, Opened};
use crate::caches::placement::Placement;
use crate::dispatch::TILES_PER_MESSAGE;
use crate::jobs::JobEntry;
use crate::membership::{LostWorker, Membership, WorkerRecord};
use crate::metrics::{self, JobMetrics};
use crate::owned_package::{OwnedPackage, remove_package};
use crate::scheduler::state::{JobSchedule, JobWorker, RoundOutcome};
/// Sequences of one (worker, job) already applied: everything up to `upto`, plus the
/// ones above it that arrived out of order. Stays small when reports arrive in order.
#[derive(Default, Debug)]
struct SeqWindow {
    upto: u64,
    above: BTreeSet<u64>,
}

impl SeqWindow {
    fn contains(&self, s: u64) -> bool {
        s <= self.upto || self.above.contains(&s)
    }

    fn insert(&mut self, s: u64) {
        if s <= self.upto {
            return;
        }
        self.above.insert(s);
        while self.above.remove(&(self.upto + 1)) {
            self.upto += 1;
        }
    }
}

/// A job running on workers.
pub struct DistJob {
    /// The public job record (state, progress, stats, film when done).
    pub entry: Arc<JobEntry>,
    /// Package to delete when the job is released (None for a package the user
    /// supplied).
    pub owned_package: Option<OwnedPackage>,
    /// What every worker of the job is told to set up; `attempt`, `routing` and
    /// `schedule` are filled from `sched` each time it is sent.
    setup: JobSetup,
    sched: JobSchedule,
    /// Every tile of the image (rectangle and starting credit), by index, then the
    /// tiles of the ray-cache coarse pass, if any (`Tile.coarse`).
    tiles: Vec<Tile>,
    tile_back: Vec<u64>,
    /// Image tiles complete (coarse tiles are not counted: progress is the image's).
    tiles_done: u32,
    /// The image's tiles: `tiles[..image_tiles]`; the rest are the coarse pass's.
    image_tiles: usize,
    /// Whether the coarse pass (if any) is complete: until it is, only coarse tiles go
    /// out, so every image ray's lookup sees caches the coarse pass has filled (and,
    /// with `fill=false`, only those: the same bits every run).
    coarse_done: bool,
    tiles_retried: u32,
    film: Film,
    /// Sequences applied per worker, this attempt.
    seen: HashMap<String, SeqWindow>,
    rays: RayCounts,
    nonfinite: u64,
    ray_bytes_sent: u64,
    /// Bytes between processes by kind, summed over the workers' reports.
    traffic: dray_proto::v1::TrafficStats,
    /// CPU seconds of the processes that ran the job.
    cpu: crate::cpu_tally::CpuTally,
    metrics: JobMetrics,
    /// Ray caches, for a job with `ray_cache`.
    caches: Option<JobCaches>,
    /// When a worker last returned credit (or the job or its latest attempt started):
    /// a job with none for the stall timeout is failed (see [`Ledger::fail_stalled`]).
    last_progress: Instant,
}

impl DistJob {
    /// A job whose workers get `setup` (the template) and `tiles` (every tile of the
    /// `entry.spec` image, each with its starting credit), scheduled by `sched`.
    pub fn new(
        entry: Arc<JobEntry>,
        setup: JobSetup,
        sched: JobSchedule,
        tiles: Vec<Tile>,
        owned_package: Option<OwnedPackage>,
    ) -> DistJob {
        let (w, h) = (entry.spec.width, entry.spec.height);
        let mut metrics = JobMetrics::default();
        for id in sched.worker_ids() {
            metrics.add_worker(&id);
        }
        let image_tiles = tiles.iter().filter(|t| !t.coarse).count();
        DistJob {
            entry,
            owned_package,
            setup,
            sched,
            image_tiles,
            coarse_done: image_tiles == tiles.len(),
            tile_back: vec![0; tiles.len()],
            tiles,
            tiles_done: 0,
            tiles_retried: 0,
            film: Film::new(w, h),
            seen: HashMap::new(),
            rays: RayCounts::default(),
            nonfinite: 0,
            ray_bytes_sent: 0,
            traffic: Default::default(),
            cpu: crate::cpu_tally::CpuTally::here(),
            metrics,
            caches: None,
            last_progress: Instant::now(),
        }
    }

    /// The same job with ray caches (their first attempt's walls already open, or
    /// none, as `caches.opened` says).
    pub fn with_caches(mut self, caches: JobCaches) -> DistJob {
        self.caches = Some(caches);
        self
    }

    /// The scheduling state.
    pub fn schedule(&self) -> &JobSchedule {
        &self.sched
    }

    /// The JobSetup of the current attempt and table.
    fn current_setup(&self) -> JobSetup {
        JobSetup {
            attempt: self.sched.attempt(),
            routing: Some(self.sched.table()),
            schedule: self.sched.schedule().name().to_string(),
            ..self.setup.clone()
        }
    }

    /// For each worker of the current attempt, in job order: its JobSetup, then `tiles`
    /// dealt by the schedule's rule, in messages of at most [`TILES_PER_MESSAGE`].
    fn start_commands(&self, tiles: &[Tile]) -> Vec<(String, Assignment)> {
        self.commands(tiles, true)
    }

    /// `tiles` dealt to the current attempt's workers, each worker's JobSetup first when
    /// `setup`.
    fn commands(&self, tiles: &[Tile], setup: bool) -> Vec<(String, Assignment)> {
        let job_setup = self.current_setup();
        let mut out = Vec::new();
        for (w, mine) in self.sched.deal(tiles) {
            if setup {
                out.push((w.clone(), command(Command::Setup(job_setup.clone()))));
            }
            for chunk in mine.chunks(TILES_PER_MESSAGE) {
                out.push((
                    w.clone(),
                    command(Command::Tiles(TileAssignment {
                        job_id: self.entry.id.clone(),
                        tiles: chunk.to_vec(),
                    })),
                ));
            }
        }
        out
    }

    fn tile_complete(&self, t: usize) -> bool {
        self.tile_back[t] == self.tiles[t].credit
    }

    /// The tiles whose credit is not all back, of the phase the job is in: the coarse
    /// pass's until it is complete, then the image's.
    fn incomplete_tiles(&self) -> Vec<Tile> {
        let range = if self.coarse_done {
            0..self.image_tiles
        } else {
            self.image_tiles..self.tiles.len()
        };
        range
            .filter(|&t| !self.tile_complete(t))
            .map(|t| self.tiles[t])
            .collect()
    }

    /// Whether every tile, image and coarse, is complete.
    fn all_complete(&self) -> bool {
        self.coarse_done && self.tiles_done as usize == self.image_tiles
    }

    /// Whether the current attempt waits for its cache walls to open.
    fn caches_pending(&self) -> bool {
        self.caches.as_ref().is_some_and(|c| c.pending.is_some())
    }

    /// Set every pixel of tile `t` back to zero, exactly (wrapping integer sums: adding
    /// the negated sum gives 0 whatever the sum was).
    fn clear_tile(&mut self, t: usize) {
        let tile = self.tiles[t];
        if tile.coarse {
            // Coarse rays add nothing to the image.
            self.tile_back[t] = 0;
            return;
        }
        let width = self.film.width;
        for y in tile.y0..tile.y0.saturating_add(tile.height).min(self.film.height) {
            for x in tile.x0..tile.x0.saturating_add(tile.width).min(width) {
                let p = y * width + x;
                let s = self.film.sum_fixed(p);
                self.film.add_fixed(p, s.map(i64::wrapping_neg));
            }
        }
        self.tile_back[t] = 0;
    }

    /// Copy counters and scheduling figures into the public job record.
    fn publish(&self) {
        self.entry.set_tiles_done(self.tiles_done);
        self.entry.update_stats(|s| {
            s.rays = Some(self.rays);
            s.nonfinite = self.nonfinite;
            s.ray_bytes_sent = self.ray_bytes_sent;
            s.traffic = Some(self.traffic);
            s.cpu_seconds = self.cpu.seconds();
            self.metrics.fill(s);
            s.tiles_retried = self.tiles_retried;
            s.scheduler_rounds = self.sched.rounds();
            s.routing_version = self.sched.version();
            s.schedule = self.sched.schedule().name().to_string();
        });
        if let Some(c) = &self.caches {
            c.tally.publish(&self.entry);
        }
    }
}

fn command(c: Command) -> Assignment {
    Assignment { command: Some(c) }
}

/// What happened to a report (for logs and tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReportOutcome {
    /// Applied; the job goes on.
    Applied,
    /// This sequence was applied before; nothing changed.
    Duplicate,
    /// Applied, and it completed the job.
    Completed,
    /// The job failed (the worker's failure, or a credit error).
    Failed,
    /// The job is not running (unknown, finished, cancelled or failed).
    Inactive,
    /// The report belongs to an attempt the job has dropped (a worker was lost since);
    /// nothing was counted and the worker should release that attempt.
    Stale,
}

impl ReportOutcome {
    /// `ReportContributionsResponse.job_active`.
    pub fn job_active(self) -> bool {
        matches!(self, ReportOutcome::Applied | ReportOutcome::Duplicate)
    }

    /// Whether the job left the ledger with this report.
    pub fn ended(self) -> bool {
        matches!(self, ReportOutcome::Completed | ReportOutcome::Failed)
    }
}

/// All jobs running on workers.
pub struct Ledger {
    jobs: Mutex<HashMap<String, DistJob>>,
    membership: Arc<Membership>,
    /// This ledger, for the tasks it starts to open and close cache walls, which come
    /// back to it. Dangling for a ledger made with [`Ledger::new`]: a new attempt then
    /// runs without caches.
    me: Weak<Ledger>,
}

/// How a job leaves the ledger.
enum Release {
    Finish,
    Cancel,
}

impl Ledger {
    /// No jobs; commands go out through `membership`.
    pub fn new(membership: Arc<Membership>) -> Ledger {
        Ledger {
            jobs: Mutex::new(HashMap::new()),
            membership,
            me: Weak::new(),
        }
    }

    /// A shared ledger, which can start the tasks that open a new attempt's cache walls
    /// (the server's; [`Ledger::new`] is enough for jobs without caches).
    pub fn shared(membership: Arc<Membership>) -> Arc<Ledger> {
        Arc::new_cyclic(|me| Ledger {
            jobs: Mutex::new(HashMap::new()),
            membership,
            me: me.clone(),
        })
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<String, DistJob>> {
        self.jobs.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Start accounting `job` and, under the same lock, send each of its workers its
    /// JobSetup and tiles, so that a cancel racing with the start either sees the job or
    /// is seen by it. Fails (sending nothing) when the job was cancelled meanwhile, or
    /// names the first worker that is gone. A dynamic job also takes on the workers that
    /// registered after its workers were chosen.
    pub fn start(&self, job: DistJob) -> Result<(), String> {
        let mut g = self.lock();
        if job.entry.is_terminal() {
            return Err(format!("job {} ended before it started", job.entry.id));
        }
        let workers = job.sched.worker_ids();
        if let Some(w) = workers.iter().find(|w| self.membership.get(w).is_none()) {
            return Err(format!(
                "worker {w} left the cluster while the job was being prepared"
            ));
        }
        for (w, a) in job.start_commands(&job.incomplete_tiles()) {
            if !self.membership.send(&w, a) {
                // Cannot happen while we hold the ledger lock unless the worker expired
                // between the check above and here; the job cannot run without it.
                let id = job.entry.id.clone();
                drop(g);
                self.release_workers(&job, Release::Cancel, "a worker left during setup");
                return Err(format!(
                    "worker {w} left the cluster while job {id} was being set up"
                ));
            }
        }
        job.entry.set_state(JobState::Running);
        job.publish();
        let id = job.entry.id.clone();
        let job = g.entry(id).insert_entry(job).into_mut();
        if job.sched.schedule().is_dynamic() {
            // Their WorkerJoined events found no job to join; this is the join.
            for w in self.membership.workers() {
                self.join(job, &w);
            }
        }
        Ok(())
    }

    /// Apply one ReportContributions call.
    pub fn report(&self, r: &ReportContributionsRequest) -> Result<ReportOutcome, Status> {
        let mut g = self.lock();
        let Some(job) = g.get_mut(&r.job_id) else {
            return Ok(ReportOutcome::Inactive);
        };
        if job.entry.is_terminal() {
            return Ok(ReportOutcome::Inactive);
        }
        let attempt = job.sched.attempt();
        if r.attempt < attempt {
            return Ok(ReportOutcome::Stale);
        }
        if r.attempt > attempt {
            return Err(Status::invalid_argument(format!(
                "attempt: {} is newer than job {:?}'s attempt {attempt}",
                r.attempt, r.job_id
            )));
        }
        if !job.sched.has_worker(&r.worker_id) {
            return Err(Status::permission_denied(format!(
                "worker_id: {} is not a worker of job {:?}",
                crate::validate::bounded(&r.worker_id),
                r.job_id
            )));
        }
        if r.sequence == 0 {
            return Err(Status::invalid_argument(
                "sequence: must start at 1 (0 is the unset value)",
            ));
        }
        if job
            .seen
            .get(&r.worker_id)
            .is_some_and(|s| s.contains(r.sequence))
        {
            return Ok(ReportOutcome::Duplicate);
        }
        let _span = tracing::info_span!("job", id = %r.job_id, attempt).entered();
        // Check everything before changing anything, so a malformed report leaves the
        // ledger as it was (and may be sent again, fixed, under the same sequence).
        if r.sums.len() != 3 * r.pixels.len() {
            return Err(Status::invalid_argument(format!(
                "sums: {} values for {} pixels (three per pixel expected)",
                r.sums.len(),
                r.pixels.len()
            )));
        }
        let npix = u64::from(job.film.width) * u64::from(job.film.height);
        if let Some(p) = r.pixels.iter().find(|&&p| u64::from(p) >= npix) {
            return Err(Status::invalid_argument(format!(
                "pixels: {p} is outside the {}x{} image",
                job.film.width, job.film.height
            )));
        }
        if let Some(c) = r
            .credits
            .iter()
            .find(|c| c.tile as usize >= job.tiles.len())
        {
            return Err(Status::invalid_argument(format!(
                "credits: tile {} does not exist (the job has {} tiles)",
                c.tile,
                job.tiles.len()
            )));
        }
        if let Some(c) = &r.counters {
            metrics::check(c).map_err(|e| Status::invalid_argument(e.to_string()))?;
        }
        job.seen
            .entry(r.worker_id.clone())
            .or_default()
            .insert(r.sequence);
        if !r.failure.is_empty() {
            // Workers often name themselves already ("worker w1: ..."): say it once.
            let failure = r.failure.trim();
            let failure = failure
                .strip_prefix(&format!("worker {}: ", r.worker_id))
                .unwrap_or(failure);
            let msg = format!("worker {} failed: {failure}", r.worker_id);
            tracing::warn!(worker = %r.worker_id, "{msg}");
            let job = g.remove(&r.job_id);
            drop(g);
            if let Some(job) = job {
                self.fail(job, msg);
            }
            return Ok(ReportOutcome::Failed);
        }
        for (i, &p) in r.pixels.iter().enumerate() {
            let s = &r.sums[3 * i..3 * i + 3];
            job.film.add_fixed(p, [s[0], s[1], s[2]]);
        }
        let mut overdrawn = None;
        for c in &r.credits {
            let t = c.tile as usize;
            let start = job.tiles[t].credit;
            match job.tile_back[t].checked_add(c.credit) {
                Some(b) if b <= start => {
                    if c.credit > 0 {
                        job.last_progress = Instant::now();
                    }
                    let was = job.tile_back[t] == start;
                    job.tile_back[t] = b;
                    if !was && b == start && t < job.image_tiles {
                        job.tiles_done += 1;
                    }
                }
                _ => {
                    overdrawn = Some((c.tile, c.credit));
                    break;
                }
            }
        }
        if let Some(t) = &r.traced {
            let k = &mut job.rays;
            k.camera += t.camera;
            k.shadow += t.shadow;
            k.reflection += t.reflection;
            k.refraction += t.refraction;
            k.diffuse += t.diffuse;
            k.ambient_occlusion += t.ambient_occlusion;
        }
        job.nonfinite += r.nonfinite;
        job.ray_bytes_sent += r.ray_bytes_sent;
        if let Some(t) = r.counters.as_ref().and_then(|c| c.traffic.as_ref()) {
            crate::traffic::add(&mut job.traffic, t);
        }
        if let Some(c) = r.counters.as_ref().and_then(|c| c.cpu.as_ref()) {
            job.cpu.note(c);
        }
        job.cpu.note_here();
        job.metrics
            .add(&r.worker_id, r.counters.as_ref(), r.traced.as_ref());
        if let (Some(c), Some(caches)) = (&r.counters, &job.caches) {
            caches.tally.add_worker(c);
        }
        job.publish();
        if let Some((tile, credit)) = overdrawn {
            let t = tile as usize;
            let msg = format!(
                "credit accounting error: worker {} returned {credit} credit to tile {tile}, \
                 which already had {} of its {} back; rays were counted twice",
                r.worker_id, job.tile_back[t], job.tiles[t].credit
            );
            tracing::error!("{msg}");
            let job = g.remove(&r.job_id);
            drop(g);
            if let Some(job) = job {
                self.fail(job, msg);
            }
            return Ok(ReportOutcome::Failed);
        }
        if !job.coarse_done && (job.image_tiles..job.tiles.len()).all(|t| job.tile_complete(t)) {
            // The coarse pass is complete, and with it every ticket of its rays (workers
            // report credit only once the cache actors have its ticket returns): the
            // image's tiles go out now.
            job.coarse_done = true;
            let coarse = job.tiles.len() - job.image_tiles;
            let rays: u64 = job.tiles[job.image_tiles..]
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
            for (w, a) in job.commands(&job.incomplete_tiles(), false) {
                if !self.membership.send(&w, a) {
                    tracing::debug!(worker = %w, "worker gone before the image's tiles");
                }
            }
        }
        if job.all_complete() {
            let Some(job) = g.remove(&r.job_id) else {
                return Ok(ReportOutcome::Inactive);
            };
            drop(g);
            tracing::info!(tiles = job.tiles.len(), "job complete");
            self.release_workers(&job, Release::Finish, "completed");
            self.end(job, JobState::Succeeded, String::new());
            return Ok(ReportOutcome::Completed);
        }
        Ok(ReportOutcome::Applied)
    }

    fn fail(&self, job: DistJob, msg: String) {
        self.release_workers(&job, Release::Cancel, &msg);
        self.end(job, JobState::Failed, msg);
    }

    /// Finish `job`, out of the ledger and its workers released, as `state` (with its
    /// film when it succeeded), and remove its package. Its open cache walls are closed
    /// first, on a task, and their statistics added, so the job turns terminal with its
    /// final statistics (a cancelled job is marked CANCELLED by the caller already: its
    /// statistics follow).
    fn end(&self, job: DistJob, state: JobState, error: String) {
        let DistJob {
            entry,
            owned_package,
            mut film,
            nonfinite,
            mut caches,
            ..
        } = job;
        film.nonfinite = nonfinite;
        let film = (state == JobState::Succeeded).then_some(film);
        let open = caches
            .as_mut()
            .and_then(|c| c.opened.take().map(|o| (o, c.tally.clone(), c.net.clone())));
        let finish = move |entry: &JobEntry| {
            entry.finish(state, error, film);
            remove_package(owned_package.as_ref());
        };
        let Some((open, tally, net)) = open else {
            return finish(&entry);
        };
        let Ok(rt) = tokio::runtime::Handle::try_current() else {
            tracing::warn!(job = %entry.id, "no async runtime to close the job's cache walls");
            return finish(&entry);
        };
        rt.spawn(async move {
            let closed = lifecycle::close(&entry.id, open.attempt, &open.placement, &net).await;
            tally.add_host(&closed.stats);
            tally.add_host_phm(&closed.phm);
            tally.lose(closed.failed.iter().map(|f| f.host.endpoint.as_str()));
            tally.publish(&entry);
            finish(&entry);
        });
    }

    fn release_workers(&self, job: &DistJob, how: Release, reason: &str) {
        let attempt = job.sched.attempt();
        for w in job.sched.worker_ids() {
            let release = JobRelease {
                job_id: job.entry.id.clone(),
                reason: reason.to_string(),
                attempt,
            };
            let c = match how {
                Release::Finish => Command::Finish(release),
                Release::Cancel => Command::Cancel(release),
            };
            self.membership.send(&w, command(c));
        }
    }

    /// Fail every job whose workers have returned no credit for longer than `timeout`
    /// at `now`, and return their ids. Heartbeats only say a worker is alive; a member
    /// that heartbeats but never traces (broken, or hostile) would otherwise hold its
    /// jobs forever. The message names the job's workers and the setting.
    pub fn fail_stalled(&self, now: Instant, timeout: Duration) -> Vec<String> {
        let mut g = self.lock();
        let mut stalled: Vec<String> = g
            .iter()
            .filter(|(_, j)| now.saturating_duration_since(j.last_progress) > timeout)
            .map(|(id, _)| id.clone())
            .collect();
        stalled.sort();
        for id in &stalled {
            let Some(job) = g.remove(id) else { continue };
            let quiet = now.saturating_duration_since(job.last_progress);
            let msg = format!(
                "no progress for {:.0} s: none of the job's workers ({}) returned any \
                 credit (the coordinator's --stall-timeout is {} s)",
                quiet.as_secs_f64(),
                job.sched.worker_ids().join(", "),
                timeout.as_secs()
            );
            tracing::warn!(job = %id, "{msg}");
            self.fail(job, msg);
        }
        stalled
    }

    /// Stop job `id` on its workers (CancelJob). False when it is not running here.
    /// The caller marks the job CANCELLED first.
    pub fn cancel(&self, id: &str) -> bool {
        let job = self.lock().remove(id);
        match job {
            Some(job) => {
                tracing::info!(job = %id, "job cancelled on its workers");
                self.release_workers(&job, Release::Cancel, "cancelled by user");
                self.end(job, JobState::Cancelled, String::new());
                true
            }
            None => false,
        }
    }

    /// Worker `lost` was dropped (no heartbeat). Each job it was part of starts its next
    /// attempt on the survivors: they are told to cancel the old attempt, then get a
    /// JobSetup with the new attempt and table, then the tiles that were not complete,
    /// dealt by the job's schedule. A job with no survivor fails, naming the worker. A
    /// worker that joined a dynamic job and was never given a domain held no credit: the
    /// job only sends the others a table without it.
    pub fn worker_lost(&self, lost: &LostWorker) {
        let mut g = self.lock();
        let mut ids: Vec<String> = g
            .iter()
            .filter(|(_, j)| j.sched.has_worker(&lost.id))
            .map(|(k, _)| k.clone())
            .collect();
        ids.sort();
        for id in ids {
            let Some(job) = g.get_mut(&id) else { continue };
            if let Some(table) = job.sched.remove_unused(&lost.id) {
                // It joined and was given nothing: no credit was with it.
                tracing::info!(
                    job = %id,
                    worker = %lost.id,
                    endpoint = %lost.endpoint,
                    version = table.version,
                    "worker lost before it was given work; the job goes on without it"
                );
                for w in job.sched.worker_ids() {
                    self.membership
                        .send(&w, command(Command::Routing(table.clone())));
                }
                job.publish();
                continue;
            }
            let old = job.sched.attempt();
            if job.sched.restart_without(&lost.id).is_some() {
                self.retrace(job, old, lost);
                job.last_progress = Instant::now();
                continue;
            }
            let Some(job) = g.remove(&id) else { continue };
            let msg = format!(
                "worker {} ({}) was lost ({}), and no worker is left to trace its tiles again",
                lost.id, lost.endpoint, lost.cause
            );
            tracing::warn!(job = %id, worker = %lost.id, endpoint = %lost.endpoint, "{msg}");
            self.fail(job, msg);
        }
    }

    /// Clear and re-deal the incomplete tiles of `job`, whose schedule has just moved to
    /// a new attempt without `lost` (`old` is the attempt dropped).
    fn retrace(&self, job: &mut DistJob, old: u32, lost: &LostWorker) {
        let mut incomplete: Vec<usize> = (0..job.tiles.len())
            .filter(|&t| !job.tile_complete(t))
            .collect();
        if job.image_tiles < job.tiles.len() {
            // The new attempt's walls open empty: its coarse pass runs again, whole,
            // before its image tiles.
            job.coarse_done = false;
            incomplete.extend((job.image_tiles..job.tiles.len()).filter(|&t| job.tile_complete(t)));
            incomplete.sort_unstable();
        }
        for &t in &incomplete {
            job.clear_tile(t);
        }
        job.seen.clear();
        job.tiles_retried = job.tiles_retried.saturating_add(incomplete.len() as u32);
        let attempt = job.sched.attempt();
        let reason = format!(
            "worker {} ({}) was lost ({}); {} tiles are traced again as attempt {attempt}",
            lost.id,
            lost.endpoint,
            lost.cause,
            incomplete.len()
        );
        tracing::warn!(
            job = %job.entry.id,
            worker = %lost.id,
            endpoint = %lost.endpoint,
            attempt,
            tiles = incomplete.len(),
            workers = job.sched.worker_ids().len(),
            "{reason}"
        );
        for w in job.sched.worker_ids() {
            let release = JobRelease {
                job_id: job.entry.id.clone(),
                reason: reason.clone(),
                attempt: old,
            };
            self.membership.send(&w, command(Command::Cancel(release)));
        }
        job.entry.set_rays_in_flight(0);
        if !self.reopen_caches(job) {
            self.send_attempt(job);
        }
        job.publish();
    }

    /// Send every worker of `job`'s current attempt its JobSetup and the incomplete
    /// tiles, dealt by the schedule.
    fn send_attempt(&self, job: &DistJob) {
        for (w, a) in job.start_commands(&job.incomplete_tiles()) {
            // A survivor that is gone too has its own loss event queued: it restarts
            // the job again then.
            if !self.membership.send(&w, a) {
                tracing::debug!(worker = %w, "survivor gone before its new attempt");
            }
        }
    }

    /// For a job with ray caches whose new attempt has just been made (its old attempt
    /// cancelled, its tiles cleared): mark the attempt pending and start the task that
    /// closes the old attempt's walls, places and opens the new one's, and hands over to
    /// [`Ledger::caches_opened`], which sends the setup and tiles. False when the job has
    /// no caches, or no task can be started (no runtime, a ledger made with
    /// [`Ledger::new`]): the caller sends the attempt at once, without caches.
    fn reopen_caches(&self, job: &mut DistJob) -> bool {
        let Some(c) = job.caches.as_mut() else {
            return false;
        };
        let attempt = job.sched.attempt();
        let (Some(ledger), Ok(rt)) = (self.me.upgrade(), tokio::runtime::Handle::try_current())
        else {
            // The old walls stay `opened`: the job's end closes them, if it can.
            tracing::warn!(job = %job.entry.id, attempt, "no async runtime: the attempt runs without ray caches");
            return false;
        };
        let prev = c.opened.take();
        let candidates = cache_job::candidates(&self.membership, &job.sched);
        let placement = cache_job::place(&candidates, &job.sched, job.sched.domains(), c);
        c.pending = Some(attempt);
        let walls = c.attempt_walls(&job.entry.id, attempt);
        let tally = c.tally.clone();
        let entry = job.entry.clone();
        rt.spawn(async move {
            if let Some(p) = prev {
                let closed =
                    lifecycle::close(&walls.job_id, p.attempt, &p.placement, &walls.net).await;
                tally.add_host(&closed.stats);
                tally.add_host_phm(&closed.phm);
                tally.lose(closed.failed.iter().map(|f| f.host.endpoint.as_str()));
            }
            let opened = if placement.is_empty() {
                tracing::warn!(job = %walls.job_id, attempt, "no cache host is left: the attempt runs without ray caches");
                Opened::default()
            } else {
                lifecycle::open(&walls, placement).await
            };
            if ledger.caches_opened(&walls.job_id, attempt, opened.placement.clone()) {
                tally.lose(opened.failed.iter().map(|f| f.host.endpoint.as_str()));
            } else {
                // Replaced by a newer attempt, or the job ended, while the walls were
                // opening: close them again. A host failing now is no loss (a newer
                // attempt opening on it drops this one).
                let closed =
                    lifecycle::close(&walls.job_id, attempt, &opened.placement, &walls.net).await;
                tally.add_host(&closed.stats);
                tally.add_host_phm(&closed.phm);
            }
            tally.publish(&entry);
        });
        true
    }

    /// The walls of `job_id`'s pending attempt `attempt` are open as `placement` (empty:
    /// no host could open them, the attempt runs without caches): put the placement in
    /// its tables and send its setup and tiles. False, changing nothing, when the job
    /// has ended or moved on to another attempt meanwhile (the caller closes the walls).
    pub fn caches_opened(&self, job_id: &str, attempt: u32, placement: Placement) -> bool {
        let mut g = self.lock();
        let Some(job) = g.get_mut(job_id) else {
            return false;
        };
        if job.entry.is_terminal() || job.sched.attempt() != attempt {
            return false;
        }
        let Some(c) = job.caches.as_mut() else {
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
            job = %job_id,
            attempt,
            hosts = placement.hosts().len(),
            "cache walls open; the attempt starts"
        );
        job.sched.set_caches(placement);
        self.send_attempt(job);
        job.publish();
        if job.sched.schedule().is_dynamic() {
            // Workers that registered while the attempt was pending were not joined.
            for w in self.membership.workers() {
                self.join(job, &w);
            }
        }
        true
    }

    /// Worker `w` registered: every running dynamic job takes it on (static schedules
    /// deal work once, so a joiner waits for the next job).
    pub fn worker_joined(&self, w: &WorkerRecord) {
        let mut g = self.lock();
        let mut ids: Vec<String> = g.keys().cloned().collect();
        ids.sort();
        for id in ids {
            if let Some(job) = g.get_mut(&id)
                && job.sched.schedule().is_dynamic()
                && !job.entry.is_terminal()
            {
                self.join(job, w);
            }
        }
    }

    /// Add `w` to dynamic `job` if it is not a worker of it yet: the others get the new
    /// table (listing it), it gets a JobSetup of the current attempt. It has no tiles and
    /// owns nothing; being idle, it gets domains from the next rounds.
    fn join(&self, job: &mut DistJob, w: &WorkerRecord) {
        if self.membership.get(&w.id).is_none() {
            // Lost before its join was handled (its loss event comes next).
            return;
        }
        if job.caches_pending() {
            // The attempt has not been sent to anyone yet; it joins when it is.
            return;
        }
        let Some(table) = job.sched.add_worker(JobWorker {
            endpoint: w.endpoint(),
            budget: w.memory_budget_bytes,
        }) else {
            return;
        };
        job.metrics.add_worker(&w.id);
        for other in job.sched.worker_ids().iter().filter(|o| **o != w.id) {
            self.membership
                .send(other, command(Command::Routing(table.clone())));
        }
        self.membership
            .send(&w.id, command(Command::Setup(job.current_setup())));
        tracing::info!(
            job = %job.entry.id,
            worker = %w.id,
            endpoint = %w.endpoint,
            version = table.version,
            "worker joined the running job"
        );
        job.publish();
    }

    /// Run `job`'s scheduling round if one is due at `now` (at most one per `interval`),
    /// sending a changed table to every worker of the job. None when the job is not
    /// running.
    pub fn round(&self, job: &str, now: Instant, interval: Duration) -> Option<RoundOutcome> {
        let mut g = self.lock();
        let job = g.get_mut(job)?;
        if job.entry.is_terminal() {
            return None;
        }
        let out = job.sched.round(now, interval);
        match &out {
            RoundOutcome::Changed(table, changes) => {
                tracing::debug!(
                    job = %job.entry.id,
                    version = table.version,
                    ?changes,
                    "routing table changed"
                );
                for w in job.sched.worker_ids() {
                    self.membership
                        .send(&w, command(Command::Routing(table.clone())));
                }
                job.publish();
            }
            RoundOutcome::Unchanged => job.publish(),
            RoundOutcome::NotBefore(_) | RoundOutcome::Waiting => {}
        }
        Some(out)
    }

    /// Store a queue report; returns the job's routing version, or None when the job is
    /// not running at the report's attempt (or the worker is not one of its workers).
    pub fn report_queues(&self, r: &ReportQueuesRequest) -> Option<u64> {
        let mut g = self.lock();
        let job = g.get_mut(&r.job_id)?;
        if job.entry.is_terminal()
            || r.attempt != job.sched.attempt()
            || !job.sched.has_worker(&r.worker_id)
        {
            return None;
        }
        job.sched.record_queues(r);
        // Rays queued at the job's workers, as of each one's latest report: what
        // JobProgress.rays_in_flight shows (rays on the wire are not counted).
        job.entry.set_rays_in_flight(job.sched.rays_queued());
        Some(job.sched.version())
    }

    /// A copy of `job`'s scheduling state (for tests and introspection).
    pub fn schedule(&self, job: &str) -> Option<JobSchedule> {
        self.lock().get(job).map(|j| j.sched.clone())
    }

    /// The current routing table of `job`.
    pub fn routing(&self, job: &str) -> Option<RoutingTable> {
        self.lock().get(job).map(|j| j.sched.table())
    }

    /// Whether `worker` is one of the workers of running job `job`.
    pub fn has_worker(&self, job: &str, worker: &str) -> bool {
        self.lock()
            .get(job)
            .is_some_and(|j| j.sched.has_worker(worker))
    }

    /// The package of running job `job`, as its workers are told
    /// (`JobSetup.package_path`, `JobSetup.package_checksum`): what the PackageService
    /// may serve for it, and only while the job runs.
    pub fn package(&self, job: &str) -> Option<(String, String)> {
        self.lock().get(job).map(|j| {
            (
                j.setup.package_path.clone(),
                j.setup.package_checksum.clone(),
            )
        })
    }

    /// Whether `job` is running on workers.
    pub fn contains(&self, job: &str) -> bool {
        self.lock().contains_key(job)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seq_window_dedupes_in_and_out_of_order() {
        let mut w = SeqWindow::default();
        assert!(!w.contains(1));
        w.insert(1);
        w.insert(3);
        assert!(w.contains(1) && w.contains(3) && !w.contains(2));
        w.insert(2);
        assert_eq!(w.upto, 3);
        assert!(w.above.is_empty());
        assert!(w.contains(2) && !w.contains(4));
    }
}
