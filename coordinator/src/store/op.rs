//! The operations the store's writer thread applies ([`super::writer`]), each in its own
//! file's transaction code (`writer.rs`, `events.rs`): a leaf both import.

use dray_proto::v1::{JobSpec, JobState, JobStats};
use tokio::sync::oneshot;

use super::CommittedTile;

/// One change to the store.
#[derive(Debug)]
pub enum Op {
    /// Nothing (a [`super::JobStore::flush`] carrier).
    Nothing,
    /// A job was accepted, QUEUED.
    Insert {
        /// Its id.
        id: String,
        /// Its spec as accepted.
        spec: JobSpec,
        /// When, in milliseconds since the Unix epoch.
        submitted_ms: i64,
    },
    /// The spec it runs with on workers.
    Resolved {
        /// The job.
        id: String,
        /// The resolved spec.
        spec: JobSpec,
    },
    /// A state that is not an ending.
    State {
        /// The job.
        id: String,
        /// The state.
        state: JobState,
    },
    /// The job started attempt `attempt` on workers.
    Attempt {
        /// The job.
        id: String,
        /// The attempt.
        attempt: u32,
    },
    /// Tiles whose credit is all back, with their sums.
    Tiles {
        /// The job.
        id: String,
        /// The tiles.
        tiles: Vec<CommittedTile>,
    },
    /// The job ended: its committed tiles are forgotten (the image holds them).
    Finish {
        /// The job.
        id: String,
        /// SUCCEEDED, FAILED or CANCELLED.
        state: JobState,
        /// Why it failed.
        error: String,
        /// When, in milliseconds since the Unix epoch.
        finished_ms: i64,
        /// How long it ran, in milliseconds.
        elapsed_ms: i64,
        /// Its final statistics.
        stats: Box<JobStats>,
        /// Its image is on disk ([`super::JobStore::keep_image`] wrote it): the row names
        /// it. A job that succeeded always has one (one whose image could not be written
        /// did not succeed).
        image: bool,
    },
    /// The retention policy dropped the job's image.
    Dropped {
        /// The job.
        id: String,
        /// Why.
        why: String,
    },
    /// An event of the job's log (`crate::job_events`).
    Event {
        /// The job.
        id: String,
        /// When, in milliseconds since the Unix epoch.
        at_ms: i64,
        /// A `dray.v1.JobEventKind`.
        kind: i32,
        /// For a human.
        message: String,
    },
    /// The job runs `from` again (RetryJob, RequeueJob).
    RetriedFrom {
        /// The new job.
        id: String,
        /// The job it runs again.
        from: String,
    },
    /// Answered once every earlier operation is committed (`true`), or with `false`
    /// when the transaction holding them failed (a full disk).
    Flush(Confirm),
}

/// Where a flush is answered: a oneshot a task on the runtime awaits without holding a
/// runtime thread, or a channel a plain thread (a test, a tool) blocks on.
#[derive(Debug)]
pub enum Confirm {
    /// Awaited by a task ([`super::JobStore::post_durable`]).
    Task(oneshot::Sender<bool>),
    /// Blocked on by a thread ([`super::JobStore::flush`]).
    Thread(std::sync::mpsc::SyncSender<bool>),
}

impl Confirm {
    pub(super) fn send(self, ok: bool) {
        match self {
            Confirm::Task(tx) => {
                let _ = tx.send(ok);
            }
            Confirm::Thread(tx) => {
                let _ = tx.send(ok);
            }
        }
    }
}
