//! A job as its readers see it (GetJob, ListJobs, WatchJob, GetImage, the dashboard,
//! the deal queues): what it is, fixed at submission, and the status its
//! [`JobRecord`](super::record::JobRecord) last published. Nothing here writes.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::SystemTime;

use dray_core::film::Film;
use dray_core::tiles::TileGrid;
use dray_proto::v1::{Job, JobProgress, JobSpec, JobState};
use tokio::sync::watch;

use super::status::{JobStatus, terminal};

/// One job, as its readers see it: what it is (fixed at submission) and the status its
/// record last published. Nothing here writes: the job's
/// [`JobRecord`](super::record::JobRecord), held by what runs the job, is its one writer.
pub struct JobEntry {
    /// Opaque id.
    pub id: String,
    /// The spec with defaults filled in.
    pub spec: JobSpec,
    /// When SubmitJob accepted it.
    pub submitted_at: SystemTime,
    /// Tiles in the image.
    pub tiles_total: u32,
    /// Set by [`JobRecord::cancel`](super::record::JobRecord::cancel).
    cancel: Arc<AtomicBool>,
    /// The status as the record last published it.
    status: watch::Receiver<JobStatus>,
    /// Its progressive passes and the image after the last complete one.
    pub passes: crate::pass_images::PassImages,
    /// Its images as last encoded, shared by every caller (`image_memo`).
    pub images: crate::image_memo::ImageMemo,
    /// The job group it is a frame of (read from its id: `crate::job_group`).
    pub group: Option<dray_proto::v1::JobGroupMember>,
    /// What happened to it, its lineage and attempts (`job_events`).
    pub log: crate::job_events::EventLog,
}

impl JobEntry {
    /// The entry of job `id`, reading `status` and `cancel` (which its record sets).
    pub(super) fn new(
        id: String,
        spec: JobSpec,
        submitted_at: SystemTime,
        log: crate::job_events::EventLog,
        cancel: Arc<AtomicBool>,
        status: watch::Receiver<JobStatus>,
    ) -> JobEntry {
        JobEntry {
            group: crate::job_group::member_of(&id),
            id,
            tiles_total: TileGrid::image(spec.width, spec.height).count(),
            submitted_at,
            cancel,
            status,
            passes: crate::pass_images::PassImages::new(&spec.passes, spec.spp),
            images: Default::default(),
            log,
            spec,
        }
    }

    /// The status as last published (a read lock on it while the guard lives: keep it
    /// short).
    fn status(&self) -> watch::Ref<'_, JobStatus> {
        self.status.borrow()
    }

    /// Current state.
    pub fn state(&self) -> JobState {
        self.status().state
    }

    /// The finished film, once the job SUCCEEDED.
    pub fn film(&self) -> Option<Arc<Film>> {
        self.status().film.clone()
    }

    /// Why the finished job's image was dropped, if it was
    /// (the job table's `Retention`).
    pub fn dropped(&self) -> Option<String> {
        self.status().dropped.clone()
    }

    /// The finished image's file in the job store, for a job that finished before this
    /// coordinator started (see [`crate::store::image_file::read`]).
    pub fn image_file(&self) -> Option<PathBuf> {
        self.status().image_file.clone()
    }

    /// When it ended, if it has.
    pub fn finished_at(&self) -> Option<SystemTime> {
        self.status().finished_at
    }

    /// Progress as WatchJob and GetJob report it.
    pub fn progress(&self) -> JobProgress {
        let g = self.status();
        let done = g.tiles_done;
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
                g.rays_in_flight
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
        let g = self.status();
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

    /// Whether CancelJob (or the server's shutdown) asked the job to stop.
    pub fn is_cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    /// Whether the job reached SUCCEEDED, FAILED or CANCELLED.
    pub fn is_terminal(&self) -> bool {
        terminal(self.state())
    }

    /// Completes once the job is in a terminal state (at once if it already is, and
    /// once its record is gone: nothing can end it then).
    pub async fn wait_ended(&self) {
        let mut rx = self.status.clone();
        let _ = rx.wait_for(|s| terminal(s.state)).await;
    }
}
