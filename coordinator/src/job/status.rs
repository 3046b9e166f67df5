//! A job's state and progress as its record last published them: what the single writer
//! (`JobRecord`, job/record.rs) sends and every read-only view (`JobEntry`, job/entry.rs)
//! reads. A leaf: both sides import it, and neither imports the other's module for it.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use dray_core::film::Film;
use dray_proto::v1::{JobSpec, JobState, JobStats};

/// A job's state and progress as last published: what its `JobEntry` reads.
#[derive(Clone, Debug, Default)]
pub struct JobStatus {
    pub(crate) state: JobState,
    pub(crate) started: Option<Instant>,
    pub(crate) elapsed_final: Option<Duration>,
    pub(crate) finished_at: Option<SystemTime>,
    pub(crate) error: String,
    pub(crate) stats: JobStats,
    pub(crate) film: Option<Arc<Film>>,
    /// Why the image is gone, once the retention policy dropped it.
    pub(crate) dropped: Option<String>,
    /// The image in the job store, for a job that finished before this coordinator
    /// started (its film is read from there when asked for).
    pub(crate) image_file: Option<PathBuf>,
    /// The spec as it runs, once the scene is prepared: on workers the domain count and
    /// layout come from the scene (or its package), so GetJob says what ran.
    pub(crate) resolved: Option<JobSpec>,
    /// Tiles committed in the current pass.
    pub(crate) tiles_done: u32,
    /// Rays waiting at workers, from their latest queue reports.
    pub(crate) rays_in_flight: u64,
}

impl JobStatus {
    /// A job just accepted: QUEUED, nothing done.
    pub(crate) fn queued() -> JobStatus {
        JobStatus {
            state: JobState::Queued,
            ..JobStatus::default()
        }
    }
}

/// Whether `s` is SUCCEEDED, FAILED or CANCELLED.
pub(crate) fn terminal(s: JobState) -> bool {
    matches!(
        s,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}
