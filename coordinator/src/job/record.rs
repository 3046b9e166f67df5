//! The one writer of a job's public record (docs/architecture.md "Who owns what").
//!
//! A job's state, progress, statistics and finished film are a [`JobStatus`] that only
//! its [`JobRecord`] changes, and publishes through a `tokio::sync::watch` channel; the
//! [`JobEntry`] every reader holds (GetJob, ListJobs, WatchJob, GetImage, the dashboard,
//! the deal queue) keeps the receiving end and cannot write. The record goes with the
//! job: the submission path holds it while the scene loads and the job waits for a slot,
//! then the in-process renderer (`crate::local_render`) or, on workers, the job's actor
//! (`super::actor`), which publishes what its ledger, film and statistics say. What the
//! job is asked from outside (CancelJob, PauseJob and ResumeJob, the table's retention
//! dropping a finished image) are methods of this same type, so every change to a job's
//! record is made here, in one step under the channel's lock, and a reader never sees a
//! state without the fields that go with it.

use std::ops::Deref;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Instant, SystemTime};

use dray_core::film::Film;
use dray_proto::v1::{JobEventKind, JobSpec, JobState, JobStats};
use tokio::sync::watch;

use super::entry::JobEntry;
use super::status::{JobStatus, terminal};
use crate::store::{JobStore, Op, to_millis};

/// The writing side of one job's record: made with its [`JobEntry`] by the job table,
/// held by whatever runs the job. Reads through it are the entry's ([`Deref`]).
pub struct JobRecord {
    entry: Arc<JobEntry>,
    status: watch::Sender<JobStatus>,
    /// Shared with the scene load and the package cut, which stop when it is set; the
    /// entry reads it.
    cancel: Arc<AtomicBool>,
    /// Where its changes are kept across restarts (None: in memory only).
    store: Option<Arc<JobStore>>,
}

impl Deref for JobRecord {
    type Target = JobEntry;

    fn deref(&self) -> &JobEntry {
        &self.entry
    }
}

impl JobRecord {
    /// The record of job `id` (its log so far `log`), starting as `status`, kept in
    /// `store` when given.
    pub(crate) fn new(
        id: String,
        spec: JobSpec,
        submitted_at: SystemTime,
        log: crate::job_events::EventLog,
        status: JobStatus,
        store: Option<Arc<JobStore>>,
    ) -> JobRecord {
        let cancel = Arc::new(AtomicBool::new(false));
        let (tx, rx) = watch::channel(status);
        let entry = JobEntry::new(id, spec, submitted_at, log, cancel.clone(), rx);
        JobRecord {
            entry: Arc::new(entry),
            status: tx,
            cancel,
            store,
        }
    }

    /// The read-only view, for readers.
    pub fn entry(&self) -> &Arc<JobEntry> {
        &self.entry
    }

    /// The job store this job is kept in, if any.
    pub fn store(&self) -> Option<&Arc<JobStore>> {
        self.store.as_ref()
    }

    /// Change the status with `f`; readers are told only when `f` says it changed.
    fn modify(&self, f: impl FnOnce(&mut JobStatus) -> bool) -> bool {
        self.status.send_if_modified(f)
    }

    /// Record an event in the job's log (and its store).
    pub(crate) fn note(&self, kind: JobEventKind, message: String) {
        self.entry
            .log
            .record(&self.entry.id, self.store.as_ref(), kind, message);
    }

    /// Name the job this one was retried from, in its log (and its store).
    pub(crate) fn set_retried_from(&self, from: &str) {
        self.entry
            .log
            .set_retried_from(&self.entry.id, self.store.as_ref(), from);
    }

    /// The flag [`JobRecord::cancel`] sets, for work that runs apart from the job (its
    /// scene load, its package cut, the in-process render) and stops when it is set.
    pub(crate) fn cancel_flag(&self) -> &Arc<AtomicBool> {
        &self.cancel
    }

    /// Ask the job to stop. A queued or running job becomes CANCELLED at once (a running
    /// render stops before its next tile); a finished job keeps its state.
    pub fn cancel(&self) {
        self.cancel.store(true, Ordering::Relaxed);
        self.finish(JobState::Cancelled, String::new(), None);
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
        let mut refused = None;
        self.modify(|s| {
            if s.state != from {
                refused = Some(s.state);
                return false;
            }
            s.state = to;
            self.post(Op::State {
                id: self.entry.id.clone(),
                state: to,
            });
            true
        });
        if let Some(state) = refused {
            return Err(state);
        }
        Ok(())
    }

    /// Record the spec as it runs (see [`JobEntry::to_job`]).
    pub(crate) fn resolve(&self, spec: JobSpec) {
        self.modify(|s| {
            self.post(Op::Resolved {
                id: self.entry.id.clone(),
                spec: spec.clone(),
            });
            s.resolved = Some(spec);
            true
        });
    }

    /// Set the number of committed tiles (distributed jobs count them in their actor).
    pub(crate) fn set_tiles_done(&self, done: u32) {
        self.modify(|s| std::mem::replace(&mut s.tiles_done, done) != done);
    }

    /// Raise the number of committed tiles to `done` if it is below (the in-process
    /// render's progress, reported from several threads).
    pub(crate) fn raise_tiles_done(&self, done: u32) {
        self.modify(|s| {
            let raised = done > s.tiles_done;
            s.tiles_done = s.tiles_done.max(done);
            raised
        });
    }

    /// Set the rays waiting at workers (from their latest queue reports).
    pub(crate) fn set_rays_in_flight(&self, n: u64) {
        self.modify(|s| std::mem::replace(&mut s.rays_in_flight, n) != n);
    }

    /// Publish a running job's progress: its committed tiles and statistics, in one
    /// step (a reader never sees the tiles of one report with the counters of another).
    pub(crate) fn publish(&self, tiles_done: u32, f: impl FnOnce(&mut JobStats)) {
        self.modify(|s| {
            s.tiles_done = tiles_done;
            f(&mut s.stats);
            true
        });
    }

    /// Update the statistics in place.
    pub(crate) fn update_stats(&self, f: impl FnOnce(&mut JobStats)) {
        self.modify(|s| {
            f(&mut s.stats);
            true
        });
    }

    /// Move to `state` unless the job is terminal (RUNNING notes an attempt started).
    pub(crate) fn set_state(&self, state: JobState) {
        let mut was = None;
        self.modify(|s| {
            if terminal(s.state) {
                return false;
            }
            // Posted under the channel's lock, as every change: the store sees the
            // job's changes in the order readers do.
            if s.state != state {
                self.post(Op::State {
                    id: self.entry.id.clone(),
                    state,
                });
            }
            was = Some(s.state);
            s.state = state;
            if s.started.is_none() {
                s.started = Some(Instant::now());
            }
            true
        });
        let Some(was) = was else { return };
        if state == JobState::Running && was != JobState::Running {
            let n = self.entry.log.attempts() + 1;
            self.note(JobEventKind::Started, format!("started: attempt {n}"));
        }
    }

    /// Move to a terminal state unless the job is already in one. With a job store, a
    /// job succeeds only once its image is on disk: one whose image cannot be written
    /// (a full disk) ends FAILED naming the write (issue 45, item 7: it was SUCCEEDED
    /// with no image, and "not found" after a restart), as a render farm fails a frame
    /// whose output cannot be saved: the render is lost either way, and a client told
    /// SUCCEEDED would fetch nothing.
    pub(crate) fn finish(&self, state: JobState, error: String, film: Option<Film>) {
        let id = &self.entry.id;
        let (state, error, film, image) = match (state, film, &self.store) {
            (JobState::Succeeded, Some(film), Some(store)) if !self.entry.is_terminal() => {
                match blocking(|| store.keep_image(id, &film)) {
                    Ok(()) => (state, error, Some(film), true),
                    Err(e) => {
                        tracing::error!(job = %id, "cannot keep the finished image: {e}");
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
        let now = SystemTime::now();
        let mut ended = None;
        self.modify(|s| {
            if terminal(s.state) {
                return false;
            }
            let elapsed = s.started.map(|t| t.elapsed()).unwrap_or_default();
            s.state = state;
            s.error = error.clone();
            s.film = film.map(Arc::new);
            s.elapsed_final = Some(elapsed);
            s.finished_at = Some(now);
            self.post(Op::Finish {
                id: id.clone(),
                state,
                error: error.clone(),
                finished_ms: to_millis(now),
                elapsed_ms: i64::try_from(elapsed.as_millis()).unwrap_or(i64::MAX),
                stats: Box::new(s.stats.clone()),
                image,
            });
            // The log and the pass images too, before readers are told: a watcher woken
            // by the end sees the event that says why, and the final image.
            let (kind, message) = match state {
                JobState::Succeeded => (JobEventKind::Succeeded, "succeeded".to_string()),
                JobState::Cancelled => (JobEventKind::Cancelled, "cancelled".to_string()),
                _ => (JobEventKind::Failed, format!("failed: {error}")),
            };
            self.note(kind, message);
            if state == JobState::Succeeded {
                self.entry.passes.complete();
            } else {
                self.entry.passes.drop_image();
            }
            ended = Some(elapsed);
            true
        });
        let Some(elapsed) = ended else {
            if image && let Some(store) = &self.store {
                // A cancel came while the image was written: it is nobody's.
                store.forget_image(id);
            }
            return;
        };
        crate::metrics::otel::job_ended(state, elapsed);
    }

    /// Drop the finished image for `why` (the table's retention policy), if the job
    /// still has one; false when it had none.
    pub(crate) fn drop_image(&self, why: &str) -> bool {
        self.modify(|s| {
            if s.film.is_none() && s.image_file.is_none() {
                return false;
            }
            s.film = None;
            s.image_file = None;
            s.dropped = Some(why.to_string());
            self.post(Op::Dropped {
                id: self.entry.id.clone(),
                why: why.to_string(),
            });
            true
        })
    }

    /// Pass `passes_done - 1` is complete and `film` is the image so far: readers of the
    /// job's pass images see it.
    pub(crate) fn publish_pass(&self, film: Arc<Film>, passes_done: u32) {
        self.entry.passes.publish(film, passes_done);
    }

    /// Post `op` to the job store, if the job is kept in one.
    fn post(&self, op: Op) {
        if let Some(store) = &self.store {
            store.post(op);
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
