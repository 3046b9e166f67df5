//! Why the cache host refused a request, and the gRPC status each reason becomes.
//!
//! Every request comes from the network, so every check that can fail has a variant
//! here that names the field; nothing a request contains can make the host panic.

use dray_core::ray::RecordError;
use tonic::{Code, Status};

use crate::settings::SettingsError;

#[derive(Debug, thiserror::Error)]
pub enum HostError {
    #[error("job_id must not be empty")]
    NoJobId,
    #[error(transparent)]
    Settings(#[from] SettingsError),
    #[error("scene_bounds: {0}")]
    SceneBounds(String),
    #[error("domain_bounds: {0}")]
    DomainBounds(String),
    #[error("walls: wall {wall} is out of range ({domains} domains have walls 0..{})", 6 * *domains as u64)]
    WallOutOfRange { wall: u32, domains: usize },
    #[error("walls: wall {wall} cannot be named by a ticket id (walls 0..{max})")]
    WallIndex { wall: u32, max: u32 },
    #[error("walls: {count} walls exceed the limit of {max} per job attempt")]
    TooManyWalls { count: usize, max: usize },
    #[error("replica: {replica} exceeds the largest replica number {max}")]
    Replica { replica: u32, max: u32 },
    #[error("entries {sequence}: {source}")]
    Entries {
        sequence: u64,
        #[source]
        source: crate::entry_record::EntryRecordError,
    },
    #[error("job {job_id:?} attempt {attempt} is older than the open attempt {open}")]
    StaleAttempt {
        job_id: String,
        attempt: u32,
        open: u32,
    },
    #[error("job {job_id:?} attempt {attempt} is already open with other settings or bounds")]
    Conflict { job_id: String, attempt: u32 },
    #[error("job {job_id:?} attempt {attempt} is not open on this cache host")]
    UnknownJob { job_id: String, attempt: u32 },
    #[error("lookups {sequence}: {detail}")]
    BadLookups { sequence: u64, detail: String },
    #[error("lookups {sequence}: {source}")]
    Record {
        sequence: u64,
        #[source]
        source: RecordError,
    },
    #[error("outcomes {sequence}: {detail}")]
    BadOutcomes { sequence: u64, detail: String },
    #[error("message without content")]
    Empty,
}

impl HostError {
    /// The gRPC code the caller sees.
    pub fn code(&self) -> Code {
        match self {
            HostError::StaleAttempt { .. } | HostError::Conflict { .. } => Code::FailedPrecondition,
            HostError::UnknownJob { .. } => Code::NotFound,
            _ => Code::InvalidArgument,
        }
    }
}

impl From<HostError> for Status {
    fn from(e: HostError) -> Status {
        Status::new(e.code(), e.to_string())
    }
}
