//! The job table: every job the server accepted, its state and progress, and the finished
//! film (fixed-point sums, so GetImage can encode PNG at any exposure and tone curve, or
//! EXR).
//!
//! With workers registered, a job runs on them (`dispatch`, `job`). With none, it runs
//! in this process (`crate::local_render`). Either way its record is here, and the
//! table knows nothing of where jobs run.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant, SystemTime};

use dray_core::display::Display;
use dray_core::exposure::Exposure;
use dray_core::film::Film;
use dray_core::tiles::TileGrid;
use dray_core::tonemap::Tonemap;
use dray_proto::v1::{Job, JobEventKind, JobProgress, JobSpec, JobState, JobStats};

use crate::store::{JobStore, Op, StoredJob, to_millis};

/// One job.
pub struct JobEntry {
    /// Opaque id.
    pub id: String,
    /// The spec with defaults filled in.
    pub spec: JobSpec,
    /// When SubmitJob accepted it.
    pub submitted_at: SystemTime,
    /// Tiles in the image.
    pub tiles_total: u32,
    /// Shared with the scene load, which stops when it is set.
    cancel: Arc<AtomicBool>,
    tiles_done: AtomicU32,
    rays_in_flight: AtomicU64,
    inner: Mutex<Inner>,
    /// Woken when the job reaches a terminal state, so watchers see the end at once
    /// rather than at their next interval.
    ended: tokio::sync::Notify,
    /// Where its changes are kept across restarts (None: in memory only).
    store: Option<Arc<JobStore>>,
    /// Its progressive passes and the image after the last complete one.
    pub passes: crate::pass_images::PassImages,
    /// Its images as last encoded, shared by every caller (`image_memo`).
    pub images: crate::image_memo::ImageMemo,
    /// The job group it is a frame of (read from its id: `crate::job_group`).
    pub group: Option<dray_proto::v1::JobGroupMember>,
    /// What happened to it, its lineage and attempts (`job_events`).
    pub log: crate::job_events::EventLog,
}

struct Inner {
    state: JobState,
    started: Option<Instant>,
    elapsed_final: Option<Duration>,
    finished_at: Option<SystemTime>,
    error: String,
    stats: JobStats,
    film: Option<Arc<Film>>,
    /// Why the image is gone, once the retention policy dropped it.
    dropped: Option<String>,
    /// The image in the job store, for a job that finished before this coordinator
    /// started (its film is read from there when asked for).
    image_file: Option<PathBuf>,
    /// The spec as it runs, once the scene is prepared: on workers the domain count and
    /// layout come from the scene (or its package), so GetJob says what ran.
    resolved: Option<JobSpec>,
}

fn terminal(s: JobState) -> bool {
    matches!(
        s,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

impl JobEntry {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        dray_sync::lock(&self.inner)
    }

    /// Current state.
    pub fn state(&self) -> JobState {
        self.lock().state
    }

    /// The finished film, once the job SUCCEEDED.
    pub fn film(&self) -> Option<Arc<Film>> {
        self.lock().film.clone()
    }

    /// Why the finished job's image was dropped, if it was ([`Retention`]).
    pub fn dropped(&self) -> Option<String> {
        self.lock().dropped.clone()
    }

    /// The finished image's file in the job store, for a job that finished before this
    /// coordinator started (see [`crate::store::image_file::read`]).
    pub fn image_file(&self) -> Option<PathBuf> {
        self.lock().image_file.clone()
    }

    /// The job store this job is kept in, if any.
    pub fn store(&self) -> Option<&Arc<JobStore>> {
        self.store.as_ref()
    }

    /// Progress as WatchJob and GetJob report it.
    pub fn progress(&self) -> JobProgress {
        let g = self.lock();
        let done = self.tiles_done.load(Ordering::Relaxed);
        let elapsed = g
            .elapsed_final
            .or_else(|| g.started.map(|s| s.elapsed()))
            .unwrap_or_default();
        // Passes differ in size: the ETA is from the fraction of samples traced.
        let fraction = self.passes.fraction(done, self.tiles_total);
        let eta = (g.state == JobState::Running && fraction > 0.0 && fraction < 1.0)
            .then(|| elapsed.mul_f64((1.0 - fraction) / fraction));
        let passes_done = if g.state == JobState::Succeeded {
            self.passes.total()
        } else {
            self.passes.done()
        };
        let rays = g.stats.rays.unwrap_or_default();
        JobProgress {
            job_id: self.id.clone(),
            state: g.state as i32,
            tiles_done: done,
            tiles_total: self.tiles_total,
            rays_traced: crate::metrics::total_rays(&rays),
            rays_in_flight: if terminal(g.state) {
                0
            } else {
                self.rays_in_flight.load(Ordering::Relaxed)
            },
            elapsed: prost_types::Duration::try_from(elapsed).ok(),
            eta: eta.and_then(|d| prost_types::Duration::try_from(d).ok()),
            error: g.error.clone(),
            stats: None,
            samples_done: self.passes.samples_after(passes_done),
            passes_done,
            passes_total: self.passes.total(),
        }
    }

    /// The job as GetJob, ListJobs and CancelJob report it.
    pub fn to_job(&self) -> Job {
        let progress = self.progress();
        let g = self.lock();
        Job {
            job_id: self.id.clone(),
            spec: Some(g.resolved.clone().unwrap_or_else(|| self.spec.clone())),
            progress: Some(progress),
            stats: Some(g.stats.clone()),
            submitted_at: Some(self.submitted_at.into()),
            finished_at: g.finished_at.map(Into::into),
            group: self.group.clone(),
            retried_from: self.log.retried_from(),
            attempts: self.log.attempts(),
            events: self.log.events(),
        }
    }

    /// Record an event in the job's log (and its store).
    pub(crate) fn note(&self, kind: JobEventKind, message: String) {
        self.log
            .record(&self.id, self.store.as_ref(), kind, message);
    }

    /// Hold a QUEUED job (`paused`) or put a PAUSED one back in the queue: the state
    /// it had when the move is refused. The caller checks that the job waits in the
    /// deal queue.
    pub(crate) fn hold(&self, paused: bool) -> Result<(), JobState> {
        let (from, to) = if paused {
            (JobState::Queued, JobState::Paused)
        } else {
            (JobState::Paused, JobState::Queued)
        };
        let mut g = self.lock();
        if g.state != from {
            return Err(g.state);
        }
        g.state = to;
        drop(g);
        if let Some(store) = &self.store {
            store.post(Op::State {
                id: self.id.clone(),
                state: to,
            });
        }
        Ok(())
    }

    /// Ask the job to stop. A queued or running job becomes CANCELLED at once (a running
    /// render stops before its next tile); a finished job keeps its state.
    pub fn cancel(&self) {
        self.cancel.store(true, Ordering::Relaxed);
        self.finish(JobState::Cancelled, String::new(), None);
    }

    /// Record the spec as it runs (see [`JobEntry::to_job`]).
    pub(crate) fn resolve(&self, spec: JobSpec) {
        if let Some(store) = &self.store {
            store.post(Op::Resolved {
                id: self.id.clone(),
                spec: spec.clone(),
            });
        }
        self.lock().resolved = Some(spec);
    }

    /// Whether CancelJob (or the server's shutdown) asked the job to stop.
    pub fn is_cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    /// The flag [`JobEntry::cancel`] sets, for work that runs apart from the job (its
    /// scene load) and stops when it is set.
    pub(crate) fn cancel_flag(&self) -> &Arc<AtomicBool> {
        &self.cancel
    }

    /// Set the number of committed tiles (distributed jobs count them in their actor).
    pub(crate) fn set_tiles_done(&self, done: u32) {
        self.tiles_done.store(done, Ordering::Relaxed);
    }

    /// Raise the number of committed tiles to `done` if it is below (the in-process
    /// render's progress, reported from several threads).
    pub(crate) fn raise_tiles_done(&self, done: u32) {
        self.tiles_done.fetch_max(done, Ordering::Relaxed);
    }

    /// Set the rays waiting at workers (from their latest queue reports).
    pub(crate) fn set_rays_in_flight(&self, n: u64) {
        self.rays_in_flight.store(n, Ordering::Relaxed);
    }

    /// Update the statistics in place.
    pub(crate) fn update_stats(&self, f: impl FnOnce(&mut JobStats)) {
        f(&mut self.lock().stats);
    }

    /// Whether the job reached SUCCEEDED, FAILED or CANCELLED.
    pub fn is_terminal(&self) -> bool {
        terminal(self.lock().state)
    }

    pub(crate) fn set_state(&self, s: JobState) {
        let mut g = self.lock();
        if !terminal(g.state) {
            if g.state != s
                && let Some(store) = &self.store
            {
                store.post(Op::State {
                    id: self.id.clone(),
                    state: s,
                });
            }
            let started = s == JobState::Running && g.state != JobState::Running;
            g.state = s;
            if g.started.is_none() {
                g.started = Some(Instant::now());
            }
            drop(g);
            if started {
                let n = self.log.attempts() + 1;
                self.note(JobEventKind::Started, format!("started: attempt {n}"));
            }
        }
    }

    /// Move to a terminal state unless the job is already in one. With a job store, a
    /// job succeeds only once its image is on disk: one whose image cannot be written
    /// (a full disk) ends FAILED naming the write (issue 45, item 7: it was SUCCEEDED
    /// with no image, and "not found" after a restart), as a render farm fails a frame
    /// whose output cannot be saved: the render is lost either way, and a client told
    /// SUCCEEDED would fetch nothing.
    pub(crate) fn finish(&self, s: JobState, error: String, film: Option<Film>) {
        let (s, error, film, image) = match (s, film, &self.store) {
            (JobState::Succeeded, Some(film), Some(store)) if !self.is_terminal() => {
                match blocking(|| store.keep_image(&self.id, &film)) {
                    Ok(()) => (s, error, Some(film), true),
                    Err(e) => {
                        tracing::error!(job = %self.id, "cannot keep the finished image: {e}");
                        (
                            JobState::Failed,
                            format!(
                                "the render finished but its image could not be written to \
                                 the state directory ({e}); free space in the --state-dir \
                                 and submit the job again"
                            ),
                            None,
                            false,
                        )
                    }
                }
            }
            (s, film, _) => (s, error, film, false),
        };
        let mut g = self.lock();
        if terminal(g.state) {
            if image && let Some(store) = &self.store {
                // A cancel came while the image was written: it is nobody's.
                store.forget_image(&self.id);
            }
            return;
        }
        g.state = s;
        let error_copy = error.clone();
        g.error = error;
        g.film = film.map(Arc::new);
        let elapsed = g.started.map(|t| t.elapsed()).unwrap_or_default();
        g.elapsed_final = Some(elapsed);
        let now = SystemTime::now();
        g.finished_at = Some(now);
        if let Some(store) = &self.store {
            store.post(Op::Finish {
                id: self.id.clone(),
                state: s,
                error: g.error.clone(),
                finished_ms: to_millis(now),
                elapsed_ms: i64::try_from(elapsed.as_millis()).unwrap_or(i64::MAX),
                stats: Box::new(g.stats.clone()),
                image,
            });
        }
        drop(g);
        let (kind, message) = match s {
            JobState::Succeeded => (JobEventKind::Succeeded, "succeeded".to_string()),
            JobState::Cancelled => (JobEventKind::Cancelled, "cancelled".to_string()),
            _ => (JobEventKind::Failed, format!("failed: {error_copy}")),
        };
        self.note(kind, message);
        if s == JobState::Succeeded {
            self.passes.complete();
        } else {
            self.passes.drop_image();
        }
        crate::metrics::otel::job_ended(s, elapsed);
        self.ended.notify_waiters();
    }

    /// Completes once the job is in a terminal state (at once if it already is).
    pub async fn wait_ended(&self) {
        loop {
            let notified = self.ended.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if terminal(self.lock().state) {
                return;
            }
            notified.await;
        }
    }
}

/// Run `f`, which blocks (a file write), where blocking is allowed: on a worker of the
/// multi-threaded runtime through `block_in_place` (its other tasks move to other
/// workers meanwhile); elsewhere (a blocking thread, a current-thread runtime, no
/// runtime) as it is.
fn blocking<T>(f: impl FnOnce() -> T) -> T {
    match tokio::runtime::Handle::try_current() {
        Ok(h) if h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(f)
        }
        _ => f(),
    }
}

/// All jobs the server knows, and the gate that runs them one at a time.
pub struct JobTable {
    jobs: Mutex<Vec<Arc<JobEntry>>>,
    next_id: AtomicU64,
    /// Makes this coordinator's job ids differ from an earlier run's: a worker that
    /// outlived a coordinator restart must not take a new `job-1` for the old one.
    nonce: u32,
    retention: Retention,
    /// Where jobs are kept across restarts, once set ([`JobTable::keep_in`]).
    store: OnceLock<Arc<JobStore>>,
}

/// How long finished jobs keep their images: the coordinator would otherwise hold every
/// image it ever made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Retention {
    /// Images of at most this many finished jobs are kept (the newest).
    pub keep_finished: usize,
    /// An image is dropped this long after its job finished (None: never, by age).
    pub ttl: Option<Duration>,
    /// The kept images add up to at most this many bytes (the newest first; None: the
    /// coordinator's `--max-job-bytes`, see [`crate::Coordinator::with_admission`]). A
    /// finished 2048² image holds 96 MiB of exact sums: without a byte budget,
    /// `keep_finished` large images were the only bound.
    pub max_bytes: Option<u64>,
}

impl Retention {
    /// The default [`Retention::keep_finished`] (`dray coordinator --keep-finished`).
    pub const KEEP_FINISHED: usize = 100;
    /// The default [`Retention::ttl`] (`dray coordinator --finished-ttl`).
    pub const TTL: Duration = Duration::from_secs(24 * 3600);
}

impl Default for JobTable {
    fn default() -> JobTable {
        JobTable::new()
    }
}

impl Default for Retention {
    fn default() -> Retention {
        Retention {
            keep_finished: Retention::KEEP_FINISHED,
            ttl: Some(Retention::TTL),
            max_bytes: None,
        }
    }
}

impl JobTable {
    /// An empty table.
    pub fn new() -> JobTable {
        JobTable {
            jobs: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(1),
            nonce: {
                let t = SystemTime::now()
                    .duration_since(SystemTime::UNIX_EPOCH)
                    .unwrap_or_default();
                (t.subsec_nanos() ^ (t.as_secs() as u32).rotate_left(13))
                    ^ std::process::id().rotate_left(7)
            },
            retention: Retention::default(),
            store: OnceLock::new(),
        }
    }

    /// Keep every job accepted from now on in `store`. Once only (later calls are
    /// ignored); before any job is accepted.
    pub fn keep_in(&self, store: Arc<JobStore>) {
        let _ = self.store.set(store);
    }

    /// Put back the jobs a store held (in submission order), as this coordinator's. Ended
    /// jobs come back as they ended, with their images in the store; the others come
    /// back QUEUED and are returned, in order, with what they had stored, for the caller
    /// to run again.
    pub fn restore(&self, stored: Vec<StoredJob>) -> Vec<(Arc<JobEntry>, StoredJob)> {
        let mut resumable = Vec::new();
        for j in stored {
            let ended = terminal(j.state);
            // A held job stays held across the restart.
            let state = match j.state {
                s if ended => s,
                JobState::Paused => JobState::Paused,
                _ => JobState::Queued,
            };
            let entry = Arc::new(JobEntry {
                group: crate::job_group::member_of(&j.id),
                id: j.id.clone(),
                tiles_total: TileGrid::image(j.spec.width, j.spec.height).count(),
                spec: j.spec.clone(),
                submitted_at: j.submitted_at,
                cancel: Arc::new(AtomicBool::new(false)),
                tiles_done: AtomicU32::new(0),
                rays_in_flight: AtomicU64::new(0),
                inner: Mutex::new(Inner {
                    state,
                    started: None,
                    elapsed_final: ended.then(|| j.elapsed.unwrap_or_default()),
                    finished_at: j.finished_at,
                    error: j.error.clone(),
                    stats: j.stats.clone(),
                    film: None,
                    dropped: j.dropped.clone(),
                    image_file: j.image.clone(),
                    resolved: j.resolved.clone(),
                }),
                ended: tokio::sync::Notify::new(),
                store: self.store.get().cloned(),
                passes: crate::pass_images::PassImages::new(&j.spec.passes, j.spec.spp),
                images: Default::default(),
                log: crate::job_events::EventLog::restored(
                    j.events.clone(),
                    j.retried_from.clone(),
                ),
            });
            if ended {
                if state == JobState::Succeeded {
                    entry.set_tiles_done(entry.tiles_total);
                }
            } else {
                entry.note(
                    JobEventKind::Restored,
                    format!(
                        "taken back by a restarted coordinator ({} then); {}",
                        j.state.as_str_name(),
                        if state == JobState::Paused {
                            "paused until resumed"
                        } else {
                            "queued again"
                        }
                    ),
                );
                if j.state != state
                    && let Some(store) = &entry.store
                {
                    store.post(Op::State {
                        id: j.id.clone(),
                        state,
                    });
                }
                resumable.push((entry.clone(), j));
            }
            self.jobs().push(entry);
        }
        resumable
    }

    /// The same table with another retention policy.
    pub fn with_retention(mut self, retention: Retention) -> JobTable {
        // (The budget defaults to --max-job-bytes in `with_admission`.)
        self.retention = retention;
        self
    }

    /// Jobs not yet in a terminal state (queued, preparing or running).
    pub fn active(&self) -> usize {
        self.jobs().iter().filter(|j| !terminal(j.state())).count()
    }

    /// Drop the images the retention policy no longer keeps: those of finished jobs
    /// beyond the newest `keep_finished`, beyond the byte budget, and those older than
    /// the TTL. The jobs stay listed (GetJob), and GetImage says why there is no image.
    /// Runs when a job is submitted and when an image is asked for.
    pub fn sweep(&self) {
        let now = SystemTime::now();
        let mut kept = 0usize;
        let mut kept_bytes = 0u64;
        let budget = self.retention.max_bytes.unwrap_or(u64::MAX);
        for j in self.jobs().iter().rev() {
            let mut g = j.lock();
            if !terminal(g.state) || (g.film.is_none() && g.image_file.is_none()) {
                continue;
            }
            // A stored image holds exactly the sums the film would.
            let bytes = g.film.as_ref().map_or_else(
                || u64::from(j.spec.width) * u64::from(j.spec.height) * 24,
                |f| f.heap_bytes(),
            );
            let expired = match (self.retention.ttl, g.finished_at) {
                (Some(ttl), Some(at)) => now.duration_since(at).is_ok_and(|age| age > ttl),
                _ => false,
            };
            let why = if expired {
                "it finished longer ago than the coordinator's --finished-ttl"
            } else if kept >= self.retention.keep_finished {
                "the coordinator keeps the images of its newest --keep-finished jobs only"
            } else if kept_bytes.saturating_add(bytes) > budget {
                "the newer finished images already take the coordinator's \
                 --keep-finished-bytes (default: --max-job-bytes)"
            } else {
                kept += 1;
                kept_bytes = kept_bytes.saturating_add(bytes);
                continue;
            };
            g.film = None;
            g.image_file = None;
            g.dropped = Some(why.to_string());
            if let Some(store) = &j.store {
                store.post(Op::Dropped {
                    id: j.id.clone(),
                    why: why.to_string(),
                });
            }
        }
    }

    fn jobs(&self) -> MutexGuard<'_, Vec<Arc<JobEntry>>> {
        dray_sync::lock(&self.jobs)
    }

    /// Whether the job store (if any) is writing: `Err(why)` while its last transaction
    /// failed, so a new job would not survive a restart.
    pub fn store_health(&self) -> Result<(), String> {
        self.store.get().map_or(Ok(()), |s| s.health())
    }

    /// Wait until every job record posted so far (a new job's included) is on disk, at
    /// most 10 s, without holding a runtime thread. False when the store could not
    /// write it. True without a store.
    pub async fn confirm_kept(&self) -> bool {
        let Some(store) = self.store.get().cloned() else {
            return true;
        };
        // Everything posted before is confirmed with it, the entry's Insert included.
        store
            .post_durable(Op::Nothing, std::time::Duration::from_secs(10))
            .await
    }

    /// The job store jobs are kept in, if any.
    pub fn store(&self) -> Option<&Arc<JobStore>> {
        self.store.get()
    }

    /// A new job group's id, unique as job ids are (`crate::job_group`).
    pub fn new_group_id(&self) -> String {
        let n = self.next_id.fetch_add(1, Ordering::Relaxed);
        crate::job_group::group_id(n, self.nonce)
    }

    /// Add a job QUEUED, without starting anything: the caller runs it (in process with
    /// [`JobTable::submit`], or on workers through the dispatcher).
    pub fn insert(&self, spec: JobSpec) -> Arc<JobEntry> {
        self.insert_as(spec, None)
    }

    /// [`JobTable::insert`] under `id` when given (a frame of a job group, whose id
    /// [`JobTable::new_group_id`] and `crate::job_group::frame_id` made), else a new id.
    pub fn insert_as(&self, spec: JobSpec, id: Option<String>) -> Arc<JobEntry> {
        self.sweep();
        let id = id.unwrap_or_else(|| {
            let n = self.next_id.fetch_add(1, Ordering::Relaxed);
            format!("job-{n}-{:08x}", self.nonce)
        });
        let entry = Arc::new(JobEntry {
            group: crate::job_group::member_of(&id),
            id,
            tiles_total: TileGrid::image(spec.width, spec.height).count(),
            submitted_at: SystemTime::now(),
            cancel: Arc::new(AtomicBool::new(false)),
            tiles_done: AtomicU32::new(0),
            rays_in_flight: AtomicU64::new(0),
            inner: Mutex::new(Inner {
                state: JobState::Queued,
                started: None,
                elapsed_final: None,
                finished_at: None,
                error: String::new(),
                stats: JobStats::default(),
                film: None,
                dropped: None,
                image_file: None,
                resolved: None,
            }),
            ended: tokio::sync::Notify::new(),
            store: self.store.get().cloned(),
            passes: crate::pass_images::PassImages::new(&spec.passes, spec.spp),
            images: Default::default(),
            log: Default::default(),
            spec,
        });
        if let Some(store) = &entry.store {
            store.post(Op::Insert {
                id: entry.id.clone(),
                spec: entry.spec.clone(),
                submitted_ms: to_millis(entry.submitted_at),
            });
        }
        self.jobs().push(entry.clone());
        entry.note(
            JobEventKind::Queued,
            format!("queued at priority {}", entry.spec.priority),
        );
        crate::metrics::otel::job_accepted();
        entry
    }

    /// The job with id `id`.
    pub fn get(&self, id: &str) -> Option<Arc<JobEntry>> {
        self.jobs().iter().find(|j| j.id == id).cloned()
    }

    /// All jobs, newest first.
    pub fn list(&self) -> Vec<Arc<JobEntry>> {
        self.jobs().iter().rev().cloned().collect()
    }
}

/// The film as an 8-bit sRGB PNG through `display` (exposure, tone curve): the same
/// bytes `dray render --output` writes with the same `--exposure` and `--tonemap`. Called
/// on the assembled film, so an automatic exposure sees the whole image, whatever the
/// number of workers that traced it.
pub fn encode_png(film: &Film, spp: u32, display: Display) -> Result<Vec<u8>, String> {
    display.encode_png(film, spp)
}

/// The display transform a GetImage request asks for: `exposure` absent is automatic,
/// `tonemap` empty the default curve. Errors name the request's field.
pub fn requested_display(exposure: Option<f32>, tonemap: &str) -> Result<Display, String> {
    let exposure = match exposure {
        None => Exposure::Auto,
        Some(ev) => Exposure::stops(ev).map_err(|e| format!("exposure: {e}"))?,
    };
    let tonemap = Tonemap::parse(tonemap).map_err(|e| format!("tonemap: {e}"))?;
    Ok(Display { exposure, tonemap })
}

/// The film as linear f32 RGB OpenEXR, the bytes `dray render --exr` writes.
pub fn encode_exr(film: &Film, spp: u32) -> Result<Vec<u8>, String> {
    film.encode_exr(spp)
        .map_err(|e| format!("cannot encode EXR: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn get_image_display_errors_name_the_field() {
        assert_eq!(requested_display(None, ""), Ok(Display::default()));
        assert_eq!(
            requested_display(Some(0.0), "clamp"),
            Ok(Display::fixed(0.0))
        );
        assert_eq!(
            requested_display(Some(-2.0), "reinhard").map(|d| d.exposure),
            Ok(Exposure::Stops(-2.0))
        );
        for (e, t, want) in [
            (
                Some(f32::NAN),
                "",
                "exposure: NaN is out of range (-64..=64 stops)",
            ),
            (
                Some(65.0),
                "",
                "exposure: 65 is out of range (-64..=64 stops)",
            ),
            (None, "ACES", "tonemap: unknown tone curve \"ACES\""),
        ] {
            let got = requested_display(e, t).expect_err(want);
            assert!(got.starts_with(want), "{got}");
        }
    }

    fn spec(seed: u64) -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            width: 4,
            height: 2,
            spp: 1,
            seed,
            ..Default::default()
        }
    }

    fn film(v: i64) -> Film {
        let mut f = Film::new(4, 2);
        for p in 0..8 {
            f.add_fixed(p, [v, -v, p as i64]);
        }
        f
    }

    /// Finished jobs come back from the store with their images, and the retention
    /// policy deletes a dropped image's file and records why.
    #[test]
    fn finished_images_are_kept_and_dropped_in_the_store() {
        let dir = tempfile::tempdir().unwrap();
        let (old, new) = {
            let (store, _) = JobStore::open(dir.path()).unwrap();
            let store = Arc::new(store);
            let table = JobTable::new();
            table.keep_in(store.clone());
            let old = table.insert(spec(1));
            old.finish(JobState::Succeeded, String::new(), Some(film(3)));
            let new = table.insert(spec(2));
            new.finish(JobState::Succeeded, String::new(), Some(film(5)));
            store.flush();
            (old.id.clone(), new.id.clone())
        };
        let image = |id: &str| dir.path().join("images").join(format!("{id}.film"));
        assert!(image(&old).is_file() && image(&new).is_file());

        let (store, stored) = JobStore::open(dir.path()).unwrap();
        let store = Arc::new(store);
        let table = JobTable::new().with_retention(Retention {
            keep_finished: 1,
            ..Retention::default()
        });
        table.keep_in(store.clone());
        assert!(table.restore(stored).is_empty(), "nothing to run again");
        let get = |id: &str| table.get(id).unwrap();
        assert_eq!(get(&old).state(), JobState::Succeeded);
        let kept = crate::store::image_file::read(&get(&old).image_file().unwrap()).unwrap();
        assert_eq!(kept, film(3), "the image comes back exactly");

        table.sweep();
        store.flush();
        assert!(
            get(&old)
                .dropped()
                .is_some_and(|w| w.contains("--keep-finished"))
        );
        assert!(get(&old).image_file().is_none());
        assert!(!image(&old).exists(), "the dropped image's file is deleted");
        assert!(image(&new).is_file(), "the newest is kept");
        drop(table);
        store.seal();
        let (_store, stored) = JobStore::open(dir.path()).unwrap();
        let old = stored.iter().find(|j| j.id == old).unwrap();
        assert!(old.image.is_none());
        assert!(
            old.dropped
                .as_deref()
                .is_some_and(|w| w.contains("--keep-finished"))
        );
    }
}
