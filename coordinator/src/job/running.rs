//! What one running job holds: its credit ledger ([`super::credit`]), its exact film
//! ([`super::film`]), its statistics ([`super::statistics`]), the attempts' schedule, the
//! passes, and the ray caches. Owned by the job's actor ([`super::actor`]) and by nothing
//! else, so none of it is behind a lock; the methods here change it and say what to
//! send, and the actor sends it. The ledger, the film and the statistics keep their
//! state private: a report ([`super::report`]) is applied through their methods.
//!
//! A tile is complete when all of its credit is back, and a job when all its tiles are.
//!
//! **Attempts.** When a worker of the job is lost, the job starts its next attempt on the
//! survivors: every tile whose credit is not all back is cleared (its pixels set back to
//! exactly zero by subtracting their integer sums, its returned credit to 0) and dealt
//! again. Complete tiles keep their pixels: their credit is all back, so (by the
//! workers' contract, [`super::report`]) so is every contribution they will ever have.
//! Since a pixel belongs to one tile and its rays only add to that tile's pixels, the
//! final film is bit for bit that of an undisturbed run.

use std::sync::Arc;
use std::time::{Duration, Instant};

use dray_core::aov::AovSet;
use dray_core::film::Film;
use dray_proto::v1::{
    Assignment, JobRelease, JobSetup, JobState, ReportQueuesRequest, Tile, TileAssignment,
    assignment::Command,
};

use super::caches::JobCaches;
use super::credit::CreditLedger;
use super::film::JobFilm;
use super::record::JobRecord;
use super::sequences::Sequences;
use super::statistics::JobStatistics;
use crate::membership::{Membership, WorkerRecord};
use crate::owned_package::OwnedPackage;
use crate::scheduler::Schedule;
use crate::scheduler::auto::SceneSize;
use crate::scheduler::state::{JobSchedule, JobWorker, RoundOutcome};
use crate::store::{CommittedTile, Op, Resume};

/// Tiles per TileAssignment message, to stay well below gRPC's default 4 MiB message
/// limit on the worker's side even for a 16384x16384 image on one worker.
pub const TILES_PER_MESSAGE: usize = 4096;

/// What a job is started with: everything [`crate::dispatch`] prepared.
pub struct JobPlan {
    /// The job's record (state, progress, stats, film when done), which the actor
    /// takes over: it publishes what readers of the job's entry see.
    pub record: Arc<JobRecord>,
    /// What every worker of the job is told to set up; `attempt`, `routing` and
    /// `schedule` are filled from the schedule each time it is sent.
    pub setup: JobSetup,
    /// The schedule over the job's first workers (its first table).
    pub sched: JobSchedule,
    /// Every tile of the image (rectangle and starting credit), by index, then the
    /// tiles of the ray-cache coarse pass, if any (`Tile.coarse`).
    pub tiles: Vec<Tile>,
    /// Package to delete when the job ends (None for a package the user supplied).
    pub owned_package: Option<OwnedPackage>,
    /// Ray caches, for a job with `ray_cache` or `phm` (their first attempt's walls
    /// already open, or none, as `caches.opened` says).
    pub caches: Option<JobCaches>,
    /// For a job taken back from the job store: the tiles it keeps (its attempt is in
    /// `sched` already).
    pub resume: Option<Resume>,
    /// The scene's size as its schedule was chosen from: a worker joining a replicated
    /// job takes part only if its budget holds it.
    pub scene: SceneSize,
}

/// A job running on workers: the state its actor owns.
pub struct RunningJob {
    /// The job's record, where the actor publishes its progress (the job's one writer
    /// while it runs: `super::record`).
    pub record: Arc<JobRecord>,
    /// Package to delete when the job ends.
    pub owned_package: Option<OwnedPackage>,
    pub(super) setup: JobSetup,
    pub(super) sched: JobSchedule,
    /// Every tile and the credit back on each.
    pub(super) ledger: CreditLedger,
    /// The exact film and the pass images.
    pub(super) film: JobFilm,
    /// The counters the reports carry.
    pub(super) stats: JobStatistics,
    /// Whether the coarse pass (if any) is complete: until it is, only coarse tiles go
    /// out, so every image ray's lookup sees caches the coarse pass has filled (and,
    /// with `fill=false`, only those: the same bits every run).
    pub(super) coarse_done: bool,
    /// When the current attempt's coarse tiles went out (None without a coarse pass, or
    /// once it is complete): `JobStats.coarse_seconds` is measured from here.
    pub(super) coarse_started: Option<Instant>,
    /// Sequences applied per worker, this attempt.
    pub(super) seen: Sequences,
    pub(super) caches: Option<JobCaches>,
    /// Whether the per-worker detail in the public record is older than the totals
    /// (see [`RunningJob::publish_detail`]).
    detail_stale: std::cell::Cell<bool>,
    /// Image tiles completed since they were last posted to the job store (only for a
    /// job kept in one).
    pub(super) committed: Vec<usize>,
    /// The progressive pass the image's tiles are in (index into the entry's
    /// `passes.ranges()`), and per image tile how many passes it has complete: equal to
    /// `pass` while its credit comes back, one more once it is all back, and every pass
    /// for a tile taken back whole from the job store.
    pub(super) pass: usize,
    pub(super) tile_passes: Vec<u32>,
    /// Tiles adaptive sampling stopped, and the samples they did not take.
    pub(super) stopped: super::adaptive::Stopped,
    /// For a job whose workers trace passes ahead (`JobSetup.passes_ahead`): the image
    /// tiles a worker of the current attempt holds, which are not dealt again.
    held: Option<super::ahead::Held>,
    /// For a replicated job: the tiles of the current phase not dealt yet, dealt on
    /// demand so that a worker joining the job takes a share ([`super::backlog`]).
    backlog: Option<super::backlog::Backlog>,
    /// The scene's size as the schedule was chosen from.
    scene: SceneSize,
}

/// How a job's workers are released.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Release {
    /// Every tile's credit came back.
    Finish,
    /// Cancelled, failed or restarted.
    Cancel,
}

impl RunningJob {
    /// The state of a job about to start from `plan`.
    pub fn new(plan: JobPlan) -> RunningJob {
        let JobPlan {
            record,
            setup,
            sched,
            tiles,
            owned_package,
            caches,
            resume,
            scene,
        } = plan;
        let (w, h) = (record.spec.width, record.spec.height);
        // Validated when the job was accepted.
        let aovs = AovSet::parse(&record.spec.aovs).unwrap_or(AovSet::NONE);
        let stats = JobStatistics::new(sched.worker_ids());
        let ledger = CreditLedger::new(tiles);
        let image_tiles = ledger.image_tiles();
        let film = JobFilm::new(w, h, aovs, record.passes.total());
        let held = (setup.passes_ahead > 0).then(|| super::ahead::Held::new(image_tiles));
        let backlog =
            (sched.schedule() == Schedule::Replicated).then(super::backlog::Backlog::default);
        record.update_stats(|s| s.passes_ahead = setup.passes_ahead);
        let mut job = RunningJob {
            record,
            owned_package,
            setup,
            sched,
            coarse_done: !ledger.has_coarse(),
            coarse_started: None,
            ledger,
            film,
            stats,
            seen: Sequences::default(),
            caches,
            detail_stale: std::cell::Cell::new(true),
            committed: Vec::new(),
            pass: 0,
            tile_passes: vec![0; image_tiles],
            stopped: Default::default(),
            held,
            backlog,
            scene,
        };
        if let Some(r) = resume {
            job.keep(r.tiles);
        }
        job
    }

    /// Put back tiles committed before a coordinator restart: their exact sums (and AOV
    /// sums) into the film, how many passes each holds, and, for a tile adaptive
    /// sampling stopped, the samples its pixels stopped at. The job goes on from the
    /// first pass some tile has not finished; tiles further on are complete in it (and in
    /// every pass they hold; a stopped tile in all), so they are not dealt again. A tile
    /// that does not fit the job's grid, or lacks the AOVs the job writes (stored before
    /// schema 4), is left to be traced again.
    fn keep(&mut self, tiles: Vec<CommittedTile>) {
        let total = self.passes_total();
        let spp = self.record.spec.spp;
        let mut kept = 0usize;
        for c in tiles {
            let t = c.tile as usize;
            let passes = match c.stopped_at {
                Some(_) => total,
                None => c.passes.unwrap_or(total).min(total),
            };
            let fits = self
                .ledger
                .tiles()
                .get(t)
                .is_some_and(|x| !x.coarse && self.film.fits(x, &c));
            if !fits || passes == 0 || self.tile_passes[t] > 0 {
                tracing::warn!(
                    tile = c.tile,
                    "a stored tile does not fit the job: traced again"
                );
                continue;
            }
            let x = self.ledger.tile(t);
            let stopped_at = c.stopped_at;
            let pixels = self.film.keep(&x, c);
            if let Some(n) = stopped_at {
                self.stopped.tiles += 1;
                self.stopped.samples += pixels * u64::from(spp.saturating_sub(n));
            }
            self.tile_passes[t] = passes;
            kept += 1;
        }
        tracing::info!(
            job = %self.record.id,
            kept,
            stopped = self.stopped.tiles,
            aovs = self.film.has_aovs(),
            "committed tiles put back"
        );
        if kept == 0 {
            return;
        }
        let first_open = self.tile_passes.iter().copied().min().unwrap_or(0);
        // Taken back at a job's start, not on a report: the film as it is now is the
        // base of the pass it goes on from.
        let image = self.film.snapshot();
        self.enter_pass(
            (first_open as usize).min(total.saturating_sub(1) as usize),
            image,
        );
    }

    /// Go to pass `pass`, `image` being the film as it starts: the pass image (shown by
    /// GetImage when the pass is not the first, and the base a retried tile returns
    /// to). Tiles that hold more passes (taken back from the job store) are complete in
    /// it, and their pixels are final: they go into the next pass image now; the others
    /// start with no credit back and go into it as they finish.
    fn enter_pass(&mut self, pass: usize, image: Arc<Film>) {
        self.pass = pass;
        if pass > 0 {
            self.record.publish_pass(image.clone(), pass as u32);
            self.record.note(
                dray_proto::v1::JobEventKind::PassFinished,
                format!("pass {pass} of {} finished", self.record.passes.total()),
            );
        }
        let last = self.last_pass();
        self.film.enter_pass(image, last);
        let passes = &self.tile_passes;
        for t in self.ledger.enter_pass(|t| passes[t] as usize > pass) {
            self.copy_to_next(t);
        }
    }

    /// Copy image tile `t`'s pixels into the next pass image, if one is being built.
    fn copy_to_next(&mut self, t: usize) {
        self.film.copy_to_next(&self.ledger.tile(t));
    }

    /// Passes in the job.
    pub(super) fn passes_total(&self) -> u32 {
        self.record.passes.total()
    }

    /// Whether the image's tiles are in the last pass.
    pub(super) fn last_pass(&self) -> bool {
        self.pass + 1 >= self.passes_total() as usize
    }

    /// Image tile `t`'s credit is all back (the ledger counted it): it has one more pass
    /// complete (every pass, if adaptive sampling stops it), and is committed with it
    /// (kept in the job store when there is one), with its AOV sums and, if it stopped,
    /// the samples it stopped at (docs/noise.md).
    pub(super) fn tile_finished(&mut self, t: usize) {
        self.tile_passes[t] = self.pass as u32 + 1;
        self.maybe_stop(t);
        self.copy_to_next(t);
        if self.record.store().is_some() {
            self.committed.push(t);
        }
    }

    /// Image tile `t` has just finished the current pass: with a noise threshold, and a
    /// pass after which the job decides, stop it when its error is below the threshold
    /// ([`super::adaptive`]): its pixels keep the samples they stopped at, and it is
    /// complete in every later pass. Returns whether it stopped.
    fn maybe_stop(&mut self, t: usize) -> bool {
        let Some(threshold) = self.record.spec.noise_threshold else {
            return false;
        };
        let Some(range) = self.record.passes.ranges().get(self.pass).cloned() else {
            return false;
        };
        let tile = self.ledger.tile(t);
        if !super::adaptive::stops(&self.film, &tile, &range, self.last_pass(), threshold) {
            return false;
        }
        let n = self.film.stop_tile(&tile, range.end);
        self.tile_passes[t] = self.passes_total();
        self.stopped.tiles += 1;
        self.stopped.samples += n * u64::from(self.record.spec.spp.saturating_sub(range.end));
        true
    }

    /// Whether every image tile has finished a pass that is not the last: the next
    /// one can start.
    pub(super) fn pass_complete(&self) -> bool {
        self.coarse_done && !self.last_pass() && self.ledger.image_complete()
    }

    /// Start the next pass: the image so far becomes the pass image (shown by GetImage,
    /// and the base a retried tile returns to); every tile that has not finished it yet
    /// goes out again with the next samples. Returns the tiles to deal.
    pub(super) fn next_pass(&mut self) -> Vec<Tile> {
        let image = self.film.take_pass_image();
        self.enter_pass(self.pass + 1, image);
        self.publish();
        let mut tiles = self.incomplete_tiles();
        if let Some(held) = &self.held {
            // Their holders trace this pass already (tracing ahead).
            tiles.retain(|t| t.coarse || !held.holds(t.index as usize));
        }
        tiles
    }

    /// For a job tracing passes ahead, what tells every worker of the attempt that the
    /// job is in its current pass (they then report what they held of it): an empty
    /// TileAssignment with the pass, one shared copy. None for any other job.
    pub(super) fn pass_markers(&self) -> Option<(Vec<String>, Arc<Assignment>)> {
        self.held.as_ref()?;
        let marker = Arc::new(command(Command::Tiles(TileAssignment {
            job_id: self.record.id.clone(),
            tiles: Vec::new(),
            pass: self.pass as u32,
        })));
        Some((self.sched.worker_ids(), marker))
    }

    /// Post the tiles completed since the last call, with their exact sums, to the job
    /// store (a channel send: the store's own thread writes them).
    pub(super) fn persist_committed(&mut self) {
        if self.committed.is_empty() {
            return;
        }
        let Some(store) = self.record.store() else {
            self.committed.clear();
            return;
        };
        let tiles = self
            .committed
            .drain(..)
            .map(|t| {
                self.film
                    .committed(t as u32, &self.ledger.tile(t), self.tile_passes[t])
            })
            .collect();
        store.post(Op::Tiles {
            id: self.record.id.clone(),
            tiles,
        });
    }

    /// Record in the job store that the current attempt has started, and wait until it
    /// is on disk: a job taken back after a restart must start past every attempt its
    /// workers may have seen (they refuse an attempt they released). Rare (a start, a
    /// lost worker), so the short wait is not on any hot path; it is awaited, so the
    /// actor's task waits and the runtime's thread serves other jobs meanwhile.
    pub(super) fn persist_attempt(&self) -> impl std::future::Future<Output = ()> + Send + use<> {
        // Taken now: the future holds no borrow of the job (which is not `Sync`).
        let durable = self.record.store().cloned().map(|store| {
            let op = Op::Attempt {
                id: self.record.id.clone(),
                attempt: self.sched.attempt(),
            };
            (store, op)
        });
        async move {
            if let Some((store, op)) = durable
                && !store
                    .post_durable(op, std::time::Duration::from_secs(10))
                    .await
            {
                tracing::warn!("the job store did not confirm the job's new attempt");
            }
        }
    }

    /// The job's id.
    pub fn id(&self) -> &str {
        &self.record.id
    }

    /// The scheduling state.
    pub fn schedule(&self) -> &JobSchedule {
        &self.sched
    }

    /// The package workers are told to load (`JobSetup.package_path`,
    /// `JobSetup.package_checksum`).
    pub fn package(&self) -> (String, String) {
        (
            self.setup.package_path.clone(),
            self.setup.package_checksum.clone(),
        )
    }

    /// The job's environment map file (`JobSetup.env_map`), fixed for its life.
    pub fn env_map_file(&self) -> Option<dray_proto::v1::EnvMapFile> {
        self.setup.env_map.clone()
    }

    /// Send each worker of the first attempt its JobSetup and tiles, and mark the job
    /// RUNNING. Fails (sending nothing) when the job was cancelled meanwhile, or names
    /// the first worker that is gone. A dynamic job also takes on the workers that
    /// registered after its workers were chosen.
    pub async fn start(&mut self, membership: &Membership) -> Result<(), String> {
        if self.record.is_terminal() {
            return Err(format!("job {} ended before it started", self.record.id));
        }
        let workers = self.sched.worker_ids();
        if let Some(w) = workers.iter().find(|w| membership.get(w).is_none()) {
            return Err(format!(
                "worker {w} left the cluster while the job was being prepared"
            ));
        }
        self.persist_attempt().await;
        for (w, a) in self.attempt_commands() {
            if !membership.send_shared(&w, a) {
                // The worker expired between the check above and here; the job cannot
                // run without it.
                for (w, a) in self.releases(Release::Cancel, "a worker left during setup") {
                    membership.send(&w, a);
                }
                return Err(format!(
                    "worker {w} left the cluster while job {} was being set up",
                    self.record.id
                ));
            }
        }
        self.record.set_state(JobState::Running);
        self.publish();
        if self.takes_joiners() {
            // Workers that registered before the job's actor existed: this is their join.
            for w in membership.workers() {
                self.join(membership, &w);
            }
        }
        Ok(())
    }

    /// Store a queue report; the job's routing version, or None when the job is not
    /// running at the report's attempt (or the worker is not one of its workers).
    pub fn queue_report(&mut self, r: &ReportQueuesRequest) -> Option<u64> {
        if self.record.is_terminal()
            || r.attempt != self.sched.attempt()
            || !self.sched.has_worker(&r.worker_id)
        {
            return None;
        }
        self.sched.record_queues(r);
        // Rays queued at the job's workers, as of each one's latest report: what
        // JobProgress.rays_in_flight shows (rays on the wire are not counted).
        self.record.set_rays_in_flight(self.sched.rays_queued());
        Some(self.sched.version())
    }

    /// Run the scheduling round if one is due at `now` (at most one per `interval`),
    /// sending a changed table to every worker of the job, as a delta from the table
    /// they hold (one shared copy for all of them).
    pub fn round(
        &mut self,
        membership: &Membership,
        now: Instant,
        interval: Duration,
    ) -> RoundOutcome {
        if self.record.is_terminal() {
            return RoundOutcome::Waiting;
        }
        let out = self.sched.round(now, interval);
        match &out {
            RoundOutcome::Changed(delta, changes) => {
                tracing::debug!(version = delta.version, ?changes, "routing table changed");
                // Every worker holds the version before the round (every table of the
                // attempt goes to every worker, in order): the delta is enough.
                membership.send_all(
                    &self.sched.worker_ids(),
                    command(Command::Routing(delta.clone())),
                );
                self.publish();
            }
            RoundOutcome::Unchanged => self.publish(),
            RoundOutcome::NotBefore(_) | RoundOutcome::Waiting => {}
        }
        out
    }

    /// Send every worker of the current attempt its JobSetup and the incomplete tiles.
    pub fn send_attempt(&mut self, membership: &Membership) {
        for (w, a) in self.attempt_commands() {
            // A survivor that is gone too has its own loss event queued: it restarts
            // the job again then.
            if !membership.send_shared(&w, a) {
                tracing::debug!(worker = %w, "survivor gone before its new attempt");
            }
        }
    }

    /// Whether a worker that registers while the job runs becomes one of its workers:
    /// under the dynamic schedule (rounds give it domains), the replicated one (it takes
    /// tiles nobody has started, and a share of each later pass) and image-plane (a
    /// share of each later pass). The domain schedule's owners are fixed.
    pub(super) fn takes_joiners(&self) -> bool {
        match self.sched.schedule() {
            Schedule::Dynamic { .. }
            | Schedule::DynamicFromImagePlane { .. }
            | Schedule::Replicated
            | Schedule::ImagePlane => true,
            Schedule::Domain => false,
        }
    }

    /// Add `w` to the job if it is not a worker of it yet: the others get the new table
    /// (listing it), it gets a JobSetup of the current attempt. Under the dynamic
    /// schedule it has no tiles and owns nothing; being idle, it gets domains from the
    /// next rounds. Under the replicated schedule it is dealt a window of the tiles
    /// nobody has started (if its budget holds the scene: otherwise it stays out of the
    /// job, which it could only fail); under image-plane, its share of the next pass.
    pub fn join(&mut self, membership: &Membership, w: &WorkerRecord) {
        if membership.get(&w.id).is_none() {
            // Lost before its join was handled (its loss event comes next).
            return;
        }
        if self.caches_pending() {
            // The attempt has not been sent to anyone yet; it joins when it is.
            return;
        }
        let replicated = self.sched.schedule() == Schedule::Replicated;
        if replicated && !self.scene.fits(w.memory_budget_bytes) && !self.sched.has_worker(&w.id) {
            tracing::info!(
                worker = %w.id,
                budget = w.memory_budget_bytes,
                scene_bytes = self.scene.bytes,
                "worker's budget does not hold the replicated scene: it stays out of the job"
            );
            return;
        }
        let Some(table) = self.sched.add_worker(JobWorker {
            endpoint: w.endpoint(),
            budget: w.memory_budget_bytes,
        }) else {
            return;
        };
        self.stats.add_worker(&w.id);
        let others: Vec<String> = self
            .sched
            .worker_ids()
            .into_iter()
            .filter(|o| *o != w.id)
            .collect();
        membership.send_all(&others, command(Command::Routing(table.clone())));
        membership.send(&w.id, command(Command::Setup(self.current_setup())));
        let tiles = self.top_up(&w.id);
        let dealt: usize = tiles.iter().map(|(_, a)| tile_count(a)).sum();
        for (id, a) in tiles {
            membership.send_shared(&id, a);
        }
        tracing::info!(
            worker = %w.id,
            endpoint = %w.endpoint,
            version = table.version,
            tiles = dealt,
            "worker joined the running job"
        );
        self.publish();
    }

    /// The tiles `worker` is dealt now, as messages: under the replicated schedule, a
    /// top-up from the current phase's tiles nobody has started when it has room for it
    /// ([`super::backlog::Backlog::top_up`]: after its reports complete tiles, or as it
    /// joins); nothing otherwise.
    pub(super) fn top_up(&mut self, worker: &str) -> Vec<(String, Arc<Assignment>)> {
        if !self.sched.has_worker(worker) || self.record.is_terminal() {
            return Vec::new();
        }
        let Some(backlog) = self.backlog.as_mut() else {
            return Vec::new();
        };
        let ledger = &self.ledger;
        let more = backlog.top_up(worker, |t| ledger.complete_if_any(t as usize));
        if more.is_empty() {
            return Vec::new();
        }
        let waiting = backlog.waiting();
        let later = backlog.dealt_later();
        let more = self.sched.deal_to(worker, &more);
        tracing::debug!(
            worker,
            tiles = more.len(),
            waiting,
            dealt_later = later,
            "tiles dealt on demand"
        );
        self.record.update_stats(|s| s.tiles_dealt_later = later);
        self.tile_messages(worker, &more)
    }

    /// The JobSetup of the current attempt and table.
    pub(super) fn current_setup(&self) -> JobSetup {
        JobSetup {
            attempt: self.sched.attempt(),
            routing: Some(self.sched.table()),
            schedule: self.sched.schedule().name().to_string(),
            pass: self.pass as u32,
            ..self.setup.clone()
        }
    }

    /// For each worker of the current attempt, in job order: its JobSetup, then the
    /// incomplete tiles of the phase the job is in, dealt by the schedule's rule, in
    /// messages of at most [`TILES_PER_MESSAGE`].
    pub(super) fn attempt_commands(&mut self) -> Vec<(String, Arc<Assignment>)> {
        if !self.coarse_done {
            // The attempt starts with its coarse pass: its clock starts now.
            self.coarse_started = Some(Instant::now());
        }
        if let Some(held) = self.held.as_mut() {
            // A new attempt's workers start afresh: they hold what they are dealt now.
            held.clear();
        }
        self.commands(&self.incomplete_tiles(), true)
    }

    /// `tiles` dealt to the current attempt's workers, each worker's JobSetup first when
    /// `setup`. The JobSetup (which carries the whole routing table) is one shared copy
    /// for every worker: at 10,000 workers a copy each would be gigabytes. A replicated
    /// job deals only the first windows of them now and keeps the rest for whoever has
    /// room later ([`super::backlog`]).
    pub(super) fn commands(
        &mut self,
        tiles: &[Tile],
        setup: bool,
    ) -> Vec<(String, Arc<Assignment>)> {
        let job_setup = setup.then(|| Arc::new(command(Command::Setup(self.current_setup()))));
        let workers = self.sched.worker_ids().len();
        let now: std::borrow::Cow<'_, [Tile]> = match self.backlog.as_mut() {
            Some(b) => b.start(tiles, workers).into(),
            None => tiles.into(),
        };
        let mut out = Vec::new();
        for (w, mine) in self.sched.deal(&now) {
            if let Some(s) = &job_setup {
                out.push((w.clone(), s.clone()));
            }
            if let Some(b) = self.backlog.as_mut() {
                b.dealt(&w, &mine);
            }
            out.extend(self.tile_messages(&w, &mine));
        }
        out
    }

    /// `tiles` for `worker` (stamped with the attempt), in messages of at most
    /// [`TILES_PER_MESSAGE`]; image tiles dealt are held by it when the job traces ahead.
    fn tile_messages(&mut self, worker: &str, tiles: &[Tile]) -> Vec<(String, Arc<Assignment>)> {
        if let Some(held) = self.held.as_mut() {
            for t in tiles.iter().filter(|t| !t.coarse) {
                held.deal(t.index as usize);
            }
        }
        let pass = self.pass as u32;
        tiles
            .chunks(TILES_PER_MESSAGE)
            .map(|chunk| {
                (
                    worker.to_string(),
                    Arc::new(command(Command::Tiles(TileAssignment {
                        job_id: self.record.id.clone(),
                        tiles: chunk.to_vec(),
                        pass,
                    }))),
                )
            })
            .collect()
    }

    /// The release of the current attempt, for each of its workers.
    pub(super) fn releases(&self, how: Release, reason: &str) -> Vec<(String, Assignment)> {
        self.releases_of(self.sched.attempt(), how, reason)
    }

    /// The release of attempt `attempt`, for each worker of the current attempt.
    pub(super) fn releases_of(
        &self,
        attempt: u32,
        how: Release,
        reason: &str,
    ) -> Vec<(String, Assignment)> {
        self.sched
            .worker_ids()
            .into_iter()
            .map(|w| {
                let release = JobRelease {
                    job_id: self.record.id.clone(),
                    reason: reason.to_string(),
                    attempt,
                };
                let c = match how {
                    Release::Finish => Command::Finish(release),
                    Release::Cancel => Command::Cancel(release),
                };
                (w, command(c))
            })
            .collect()
    }

    pub(super) fn tile_complete(&self, t: usize) -> bool {
        self.ledger.complete(t)
    }

    /// The tiles whose credit is not all back, of the phase the job is in: the coarse
    /// pass's until it is complete, then the image's, in the current pass's samples.
    pub(super) fn incomplete_tiles(&self) -> Vec<Tile> {
        let image_tiles = self.ledger.image_tiles();
        let range = if self.coarse_done {
            0..image_tiles
        } else {
            image_tiles..self.ledger.tile_count()
        };
        let samples = self.record.passes.ranges().get(self.pass).cloned();
        range
            .filter(|&t| !self.tile_complete(t))
            .map(|t| match &samples {
                Some(s) if !self.ledger.tile(t).coarse => Tile {
                    first_sample: s.start,
                    samples: s.len() as u32,
                    ..self.ledger.tile(t)
                },
                _ => self.ledger.tile(t),
            })
            .collect()
    }

    /// Whether every tile, image and coarse, is complete in the last pass.
    pub(super) fn all_complete(&self) -> bool {
        self.coarse_done && self.last_pass() && self.ledger.image_complete()
    }

    /// Whether the coarse pass has just completed (every coarse tile's credit is back
    /// while the job still waits for it).
    pub(super) fn coarse_pass_complete(&self) -> bool {
        !self.coarse_done && self.ledger.coarse_complete()
    }

    /// Whether the current attempt waits for its cache walls to open.
    pub(super) fn caches_pending(&self) -> bool {
        self.caches.as_ref().is_some_and(|c| c.pending.is_some())
    }

    /// Set every pixel of tile `t` back to what it was when the current pass started
    /// (zero in the first), exactly: wrapping integer sums, adding the difference gives
    /// the base whatever the sum was.
    pub(super) fn clear_tile(&mut self, t: usize) {
        let tile = self.ledger.tile(t);
        // Coarse rays add nothing to the image.
        if !tile.coarse {
            self.film.clear_tile(&tile);
        }
        self.ledger.clear(t);
    }

    /// Clear the tiles a new attempt traces again (every incomplete tile, and the whole
    /// coarse pass when the job has one: the new attempt's walls open empty), forget the
    /// old attempt's sequences, and return how many tiles go out again.
    pub(super) fn clear_for_retry(&mut self) -> usize {
        if self.ledger.has_coarse() {
            self.coarse_done = false;
        }
        let again = self.ledger.for_retry();
        for &t in &again {
            self.clear_tile(t);
        }
        self.seen.clear();
        again.len()
    }

    /// Publish counters and scheduling figures through the job's record: O(1) in the
    /// number of workers, so a job can publish with every report. The per-worker detail
    /// is left for [`RunningJob::publish_detail`] (the actor runs it a little later).
    pub fn publish(&self) {
        self.record.publish(self.ledger.done(), |s| {
            self.stats.fill_totals(s);
            s.tiles_stopped = self.stopped.tiles;
            s.samples_saved = self.stopped.samples;
            s.tiles_retried = self.ledger.retried();
            s.scheduler_rounds = self.sched.rounds();
            s.routing_version = self.sched.version();
            s.schedule = self.sched.schedule().name().to_string();
            if let Some(c) = &self.caches {
                c.tally.fill(s);
            }
        });
        self.detail_stale.set(true);
    }

    /// What ListWorkers shows of this job: owners, queues, rays per worker.
    pub(super) fn view(&self) -> super::view::JobView {
        let routes = self.sched.routing().routes();
        super::view::JobView {
            job_id: self.record.id.clone(),
            submitted_at: Some(self.record.submitted_at),
            schedule: self.sched.schedule().name().to_string(),
            version: self.sched.version(),
            attempt: self.sched.attempt(),
            domains: self.sched.domains(),
            local: routes.is_local(),
            owners: routes.all_owners().to_vec(),
            workers: self.sched.worker_ids(),
            queues: self.sched.reports().clone(),
            traced: self.stats.traced().collect(),
        }
    }

    /// Copy the per-worker detail (`JobStats.workers_detail`) into the public record:
    /// O(workers), so the actor does it at most a few times a second and at the end.
    pub fn publish_detail(&self) {
        self.record.update_stats(|s| self.stats.fill_detail(s));
        self.detail_stale.set(false);
    }

    /// Whether the per-worker detail is older than the last [`RunningJob::publish`].
    pub fn detail_stale(&self) -> bool {
        self.detail_stale.get()
    }
}

/// An assignment carrying `c`.
pub(super) fn command(c: Command) -> Assignment {
    Assignment { command: Some(c) }
}

/// Tiles an assignment deals (0 for any other command).
fn tile_count(a: &Assignment) -> usize {
    match &a.command {
        Some(Command::Tiles(t)) => t.tiles.len(),
        _ => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::super::report::tests::{job_of, job_with, report};
    use super::super::report::{Applied, apply};
    use dray_proto::v1::{Assignment, JobSetup, assignment::Command};

    /// The tiles in `commands` (TileAssignments), as (first sample, tile), and the
    /// passes the assignments and setups name.
    fn dealt(commands: &[(String, std::sync::Arc<Assignment>)]) -> (Vec<(u32, u32)>, Vec<u32>) {
        let (mut tiles, mut passes) = (Vec::new(), Vec::new());
        for (_, a) in commands {
            match &a.command {
                Some(Command::Tiles(t)) => {
                    passes.push(t.pass);
                    tiles.extend(t.tiles.iter().map(|x| (x.first_sample, x.index)));
                }
                Some(Command::Setup(s)) => passes.push(s.pass),
                _ => {}
            }
        }
        tiles.sort_unstable();
        (tiles, passes)
    }

    /// A job whose workers trace passes ahead deals a tile once per attempt: later passes
    /// send every worker a marker and only the tiles no worker holds; a new attempt deals
    /// every incomplete tile again, in the pass the job is in.
    #[test]
    fn a_job_tracing_ahead_deals_each_tile_once_per_attempt() {
        // Three tiles, 8 spp: passes 0..1, 1..2, 2..4, 4..8.
        let setup = JobSetup {
            passes_ahead: 3,
            ..Default::default()
        };
        let mut j = job_with(3, 8, setup);
        let (tiles, passes) = dealt(&j.attempt_commands());
        assert_eq!(tiles, vec![(0, 0), (0, 1), (0, 2)]);
        assert!(passes.iter().all(|&p| p == 0));
        for t in 0..3u32 {
            assert_eq!(
                apply(&mut j, &report("w1", u64::from(t) + 1, &[(t, 10)])),
                Applied::Counted
            );
        }
        assert!(j.pass_complete());
        assert!(
            j.next_pass().is_empty(),
            "every tile is held: none dealt again"
        );
        let (workers, marker) = j.pass_markers().expect("markers for a job tracing ahead");
        assert_eq!(workers.len(), 2, "every worker of the attempt");
        assert_eq!(dealt(&[(workers[0].clone(), marker)]), (vec![], vec![1]));
        // Tile 0 finishes pass 1; then a worker is lost: the new attempt deals tiles 1
        // and 2 in pass 1 (held again by their new workers), and its setup names pass 1.
        assert_eq!(
            apply(&mut j, &report("w1", 4, &[(0, 10)])),
            Applied::Counted
        );
        assert!(j.sched.restart_without("w2").is_some());
        assert_eq!(j.clear_for_retry(), 2);
        let (tiles, passes) = dealt(&j.attempt_commands());
        assert_eq!(tiles, vec![(1, 1), (1, 2)]);
        assert!(passes.iter().all(|&p| p == 1), "{passes:?}");
        for t in 1..3u32 {
            assert_eq!(
                apply(&mut j, &report("w1", u64::from(t), &[(t, 10)])),
                Applied::Counted
            );
        }
        assert!(j.pass_complete());
        // Pass 2: tile 0 was not dealt in this attempt (complete before it), so it goes out.
        let next: Vec<(u32, u32)> = j
            .next_pass()
            .iter()
            .map(|t| (t.first_sample, t.index))
            .collect();
        assert_eq!(next, vec![(2, 0)]);
        // A job that does not trace ahead has no markers, and deals every tile each pass.
        let mut plain = job_of(3, 8);
        plain.attempt_commands();
        assert!(plain.pass_markers().is_none());
    }

    /// A replicated job deals each phase in windows and the rest on demand: a worker is
    /// topped up once half its window is complete, a worker that joins takes a window at
    /// once, a new attempt deals the incomplete tiles afresh, and every tile goes out
    /// once per attempt until the job is complete.
    #[test]
    fn a_replicated_job_deals_on_demand_and_a_joiner_takes_a_share() {
        use super::super::report::tests::job_under;
        use crate::scheduler::Schedule;
        use crate::scheduler::state::JobWorker;
        use std::collections::BTreeMap;

        // 40 tiles, one pass, two workers: windows of 8 (a quarter of 20 is 5, at
        // least 8), 16 dealt at once, 24 waiting.
        let mut j = job_under(40, 1, JobSetup::default(), Schedule::Replicated);
        let by_worker = |c: &[(String, std::sync::Arc<Assignment>)]| {
            let mut m: BTreeMap<String, Vec<u32>> = BTreeMap::new();
            for (w, a) in c {
                if let Some(Command::Tiles(t)) = &a.command {
                    m.entry(w.clone())
                        .or_default()
                        .extend(t.tiles.iter().map(|x| x.index));
                }
            }
            m
        };
        let first = by_worker(&j.attempt_commands());
        assert_eq!(first["w1"], [0, 2, 4, 6, 8, 10, 12, 14]);
        assert_eq!(first["w2"], [1, 3, 5, 7, 9, 11, 13, 15]);
        let mut seq: BTreeMap<String, u64> = BTreeMap::new();
        let finish = |seq: &mut BTreeMap<String, u64>, j: &mut super::RunningJob, w: &str, t| {
            let s = seq.entry(w.to_string()).or_default();
            *s += 1;
            assert_eq!(apply(j, &report(w, *s, &[(t, 10)])), Applied::Counted);
        };
        // Three of w1's done: 5 open, more than half a window.
        for t in [0, 2, 4] {
            finish(&mut seq, &mut j, "w1", t);
        }
        assert!(j.top_up("w1").is_empty());
        finish(&mut seq, &mut j, "w1", 6);
        let more = by_worker(&j.top_up("w1"));
        assert_eq!(more["w1"], [16, 17, 18, 19], "back to a window of 8");
        // A worker that joins takes a window of what nobody has started.
        j.sched
            .add_worker(JobWorker {
                endpoint: dray_proto::v1::WorkerEndpoint {
                    worker_id: "w3".into(),
                    ..Default::default()
                },
                budget: 0,
            })
            .expect("a new worker");
        let joined = by_worker(&j.top_up("w3"));
        assert_eq!(joined["w3"], (20..28).collect::<Vec<u32>>());
        let mut later = 0;
        j.record.update_stats(|s| later = s.tiles_dealt_later);
        assert_eq!(later, 12, "JobStats.tiles_dealt_later");
        // w2 is lost: the new attempt deals every incomplete tile afresh over w1 and w3
        // (36 of them: windows of max(8, 36 / 8) = 8 each, 16 at once).
        assert!(j.sched.restart_without("w2").is_some());
        assert_eq!(j.clear_for_retry(), 36);
        seq.clear();
        let again = by_worker(&j.attempt_commands());
        assert_eq!(again["w1"].len() + again["w3"].len(), 16);
        // Every worker finishes what it holds and asks for more until none is left:
        // each incomplete tile goes out exactly once in this attempt.
        let mut dealt: Vec<u32> = again.values().flatten().copied().collect();
        let mut open = again;
        while !j.all_complete() {
            let Some((w, tiles)) = open.pop_first() else {
                panic!(
                    "tiles left but none dealt: {} waiting",
                    j.backlog.as_ref().map_or(0, |b| b.waiting())
                );
            };
            for t in tiles {
                finish(&mut seq, &mut j, &w, t);
            }
            for (w, more) in by_worker(&j.top_up(&w)) {
                dealt.extend(&more);
                open.entry(w).or_default().extend(more);
            }
        }
        dealt.sort_unstable();
        let mut want: Vec<u32> = (0..40).filter(|t| ![0, 2, 4, 6].contains(t)).collect();
        want.sort_unstable();
        assert_eq!(dealt, want);
    }

    /// Pixels in one tile of [`job_of`]'s jobs.
    const TILE_PIXELS: u64 = 4;

    /// The film and the latest pass image hold the same sums in every pixel.
    fn assert_image_is_film(j: &super::RunningJob, passes_done: u32) {
        let img = j.record.passes.latest().expect("a pass image");
        assert_eq!(img.passes_done, passes_done);
        let film = j.film.film();
        for p in 0..film.width * film.height {
            assert_eq!(img.film.sum_fixed(p), film.sum_fixed(p), "pixel {p}");
        }
    }

    /// Nothing proportional to the image on the report path: however a pass ends, a
    /// report copies at most the pixels of the tiles whose credit it brings back (into
    /// the next pass image), and the pass images are the film as each pass ended, bit
    /// for bit; a tile traced again goes back to its pass image exactly.
    #[test]
    fn a_report_copies_at_most_the_tiles_it_finishes() {
        // Three 2x2 tiles side by side (a 6x2 image), 8 spp: passes 0..1, 1..2, 2..4,
        // 4..8 (the third pass's image is built in the first one's buffer).
        let mut j = job_of(3, 8);
        assert_eq!(j.passes_total(), 4);
        let mut seq = 0;
        for pass in 0..4u32 {
            if pass == 1 {
                // Half of tile 0's credit of pass 1, then a lost worker: back to the
                // image after pass 0.
                let mut r = report("w2", 1, &[(0, 4)]);
                r.pixels = vec![0, 7];
                r.sums = vec![9, 9, 9, 1, 2, 3];
                assert_eq!(apply(&mut j, &r), Applied::Counted);
                j.clear_tile(0);
                assert_image_is_film(&j, 1);
            }
            for t in 0..3u32 {
                seq += 1;
                let mut r = report("w1", seq, &[(t, 10)]);
                // One pixel in each row of tile t.
                r.pixels = vec![2 * t, 6 + 2 * t + 1];
                r.sums = vec![i64::from(pass) + 1, i64::from(t), 7, 1, 2, 3];
                let before = j.film.pass_copied();
                assert_eq!(apply(&mut j, &r), Applied::Counted);
                if j.pass_complete() {
                    j.next_pass();
                }
                let copied = j.film.pass_copied() - before;
                assert!(
                    copied <= TILE_PIXELS,
                    "the report finishing tile {t} of pass {pass} copied {copied} pixels, \
                     more than its tile's {TILE_PIXELS}"
                );
            }
            if pass < 3 {
                assert_eq!(j.pass, pass as usize + 1, "pass {pass} ended");
                assert_image_is_film(&j, pass + 1);
            }
        }
        assert!(j.all_complete());
        assert_eq!(
            j.film.film().sum_fixed(0),
            [10, 0, 28],
            "four passes' sums of pixel 0"
        );
    }
}
