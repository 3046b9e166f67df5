//! Why a job could not be set up on this worker: the one error of planning a job
//! ([`crate::plan`]) and of reading its environment map ([`crate::env_map`]), apart
//! from both so that neither imports the other for it.

/// Why a job could not be set up on this worker.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("job setup is missing {0}")]
    Missing(&'static str),
    #[error("cannot read the package {path}: {message}")]
    Package { path: String, message: String },
    #[error(
        "the package at {path} is not the one the coordinator wrote (manifest checksum {found}, expected {expected}); is the work directory shared?"
    )]
    Checksum {
        path: String,
        found: String,
        expected: String,
    },
    #[error("job setup: {0}")]
    Invalid(String),
}
