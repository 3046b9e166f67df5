//! The job store: every job the coordinator accepted, kept on disk under its state
//! directory so that a coordinator killed at any moment and started again on the same
//! directory loses no job, no finished image and no committed tile (docs/architecture.md
//! "Durability").
//!
//! - [`db`]: the directory's lock, the SQLite database (schema, version, checks) and
//!   what a restarted coordinator reads back from it.
//! - [`writer`]: one thread that owns the database connection and applies, in order and
//!   in batched transactions, what the coordinator posts to it; nothing on the request
//!   or report path waits for a disk.
//! - [`image_file`]: finished images as files beside the database, written atomically.
//! - [`state_dir`]: the directory taken only when no other user can change it, its
//!   files opened without following links.
//!
//! SQLite (through `rusqlite`, compiled in with its `bundled` feature, so no system
//! library is needed) was chosen because it gives transactions that survive a kill at
//! any point, one file, a schema version (`PRAGMA user_version`) and an integrity check,
//! and is what Blender's Flamenco Manager keeps its queue in. Images are not put in the
//! database: they are large, written once, and read whole.

pub mod db;
pub mod events;
pub mod image_file;
pub mod op;
pub mod state_dir;
pub mod writer;

use std::path::PathBuf;
use std::time::{Duration, SystemTime};

use dray_core::aov::AOV_WORDS;
use dray_proto::v1::{JobEvent, JobSpec, JobState, JobStats};

pub use db::{JobStore, SCHEMA_VERSION};
pub use op::{Confirm, Op};

/// Why the store cannot be opened or used. Every message is one line naming the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Another coordinator holds the state directory's lock.
    #[error(
        "{file} is locked by another coordinator{holder}: two coordinators cannot share one \
         state directory (stop the other one, or give this one another --state-dir)"
    )]
    Locked {
        /// The lock file.
        file: PathBuf,
        /// ", pid N" when the lock file names its holder.
        holder: String,
    },
    /// The file is not a dray job store, or is damaged.
    #[error(
        "{file}: cannot open the job store: {why}; nothing was deleted (move the state \
         directory aside to start with an empty store)"
    )]
    Corrupt {
        /// The file.
        file: PathBuf,
        /// What is wrong with it.
        why: String,
    },
    /// Written by a newer dray.
    #[error(
        "{file}: written by a newer dray (format {found}; this coordinator reads up to \
         {supported}); nothing was changed: run the newer coordinator, or give this one \
         another --state-dir"
    )]
    Newer {
        /// The file.
        file: PathBuf,
        /// Its version.
        found: u32,
        /// The newest this build reads.
        supported: u32,
    },
    /// A file or directory could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The database refused a statement.
    #[error("{file}: {source}")]
    Sql {
        /// The database file.
        file: PathBuf,
        /// Why.
        source: rusqlite::Error,
    },
    /// The state directory, or something in it, could be changed by another user, or is
    /// a link where the store makes its own files (`state_dir`).
    #[error("{path}: {why}; nothing in it was opened or changed")]
    Unsafe {
        /// The directory or file.
        path: PathBuf,
        /// What is wrong and how to fix it.
        why: String,
    },
}

/// A tile whose credit was all back, with the exact sums of its pixels (row-major within
/// the tile), so a resumed job keeps it instead of tracing it again.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CommittedTile {
    /// The tile's index in the job's grid.
    pub tile: u32,
    /// Its pixels' fixed-point sums.
    pub sums: Vec<[i64; 3]>,
    /// Progressive passes the sums hold (the tile is complete in passes `0..passes`);
    /// None: every pass (tiles written before passes were kept per tile).
    pub passes: Option<u32>,
    /// Its pixels' AOV sums (`Film::aovs`, row-major as `sums`), for a job that writes
    /// AOVs. None for a job without them, and for a tile stored before schema 4 (which
    /// a job with AOVs traces again rather than keep without them).
    pub aovs: Option<Vec<[i64; AOV_WORDS]>>,
    /// The samples its pixels stopped at, when adaptive sampling stopped the tile
    /// (`Film::set_stop`; it is then complete in every pass); None when it did not.
    pub stopped_at: Option<u32>,
}

/// One job as the store holds it.
#[derive(Clone, Debug)]
pub struct StoredJob {
    /// Its id.
    pub id: String,
    /// The spec as accepted (defaults filled in).
    pub spec: JobSpec,
    /// The spec as it ran on workers, once known.
    pub resolved: Option<JobSpec>,
    /// Its state when the store last heard of it.
    pub state: JobState,
    /// Why it failed.
    pub error: String,
    /// When SubmitJob accepted it.
    pub submitted_at: SystemTime,
    /// When it ended.
    pub finished_at: Option<SystemTime>,
    /// How long it ran, once ended.
    pub elapsed: Option<Duration>,
    /// Its statistics (final for an ended job).
    pub stats: JobStats,
    /// The newest attempt it started on workers (a resumed job starts the next one:
    /// workers that outlived the coordinator have released this one).
    pub attempt: Option<u32>,
    /// Its image file, when it succeeded and the image is kept.
    pub image: Option<PathBuf>,
    /// Why its image was dropped, if it was.
    pub dropped: Option<String>,
    /// Its committed tiles (jobs not ended only).
    pub tiles: Vec<CommittedTile>,
    /// Its event log, oldest first ([`events`]).
    pub events: Vec<JobEvent>,
    /// The job it runs again (RetryJob, RequeueJob).
    pub retried_from: Option<String>,
}

/// Milliseconds since the Unix epoch, as the store keeps times.
pub(crate) fn to_millis(t: SystemTime) -> i64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// The time `ms` milliseconds after the Unix epoch.
pub(crate) fn from_millis(ms: i64) -> SystemTime {
    SystemTime::UNIX_EPOCH + Duration::from_millis(u64::try_from(ms).unwrap_or(0).min(MAX_MILLIS))
}

/// The last millisecond of year 9999, the latest time a protobuf `Timestamp` may hold: a
/// stored time beyond it (a damaged or hand-edited row: `submitted_ms = i64::MAX`) made
/// ListJobs answer a Timestamp that grpcurl and other JSON clients refuse, so every
/// listing failed (issue 45, item 11). Times are clamped to it when read.
const MAX_MILLIS: u64 = 253_402_300_799_999;

/// Where a job taken back from the store starts again on workers.
#[derive(Clone, Debug, Default)]
pub struct Resume {
    /// The attempt to start (one past the newest the store saw started: workers that
    /// outlived the old coordinator have released that one).
    pub attempt: u32,
    /// The tiles it keeps.
    pub tiles: Vec<CommittedTile>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stored_times_stay_within_what_a_timestamp_holds() {
        let t = from_millis(i64::MAX);
        let ms = t
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap()
            .as_millis();
        assert_eq!(ms, u128::from(MAX_MILLIS));
        assert_eq!(from_millis(-5), SystemTime::UNIX_EPOCH);
        assert_eq!(
            from_millis(1_700_000_000_000),
            SystemTime::UNIX_EPOCH + Duration::from_millis(1_700_000_000_000)
        );
    }
}
