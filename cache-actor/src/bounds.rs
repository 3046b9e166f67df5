//! The largest values a job may ask for, defined once for both sides of the cluster.
//!
//! The coordinator refuses a job beyond them (its configurable
//! `dray_coordinator::validate::Limits` default to these and are capped by them), and a
//! worker refuses a setup beyond them before anything is sized by it
//! (`dray_worker::setup_bounds`, docs/security.md "Hardening, second round", item 5). With
//! one definition a legitimate job can never pass the one and fail on the other.
//!
//! They live in dray-cache beside [`crate::settings`] because it is the lowest crate that
//! both the coordinator and the worker depend on and that knows the job's protobuf types;
//! it depends only on dray-core, dray-proto, dray-net and dray-sync, so neither side's
//! crate is pulled below the other (the dependency graph stays acyclic).

/// Largest image side, in pixels.
pub const MAX_SIDE: u32 = 16384;
/// Largest samples per pixel: the film is sized for it ([`dray_core::film::MAX_SPP`]).
pub const MAX_SPP: u32 = dray_core::film::MAX_SPP;
/// Largest `max_depth`: tiles' credit is sized for it
/// ([`dray_core::integrator::MAX_DEPTH`]).
pub const MAX_DEPTH: u32 = dray_core::integrator::MAX_DEPTH;
/// Largest `ao_samples`.
pub const MAX_AO_SAMPLES: u32 = 4096;
/// Largest number of domains.
pub const MAX_DOMAINS: u32 = 65536;
/// Largest `ray_cache.coarse` (a coarse pass of N x N camera rays).
pub const MAX_COARSE: u32 = 4096;
/// Largest `phm.res` (texels per wall edge).
pub const MAX_PHM_RES: u32 = 64;
/// Largest `phm.dirs` (direction bins).
pub const MAX_PHM_DIRS: u32 = 256;
/// Jobs (setups being planned and jobs running) a worker holds at once; more are
/// refused. About 10 KB a setup: 2.5 MB at the bound.
pub const MAX_WORKER_JOBS: usize = 256;
/// The largest `--max-jobs` a coordinator accepts: half of [`MAX_WORKER_JOBS`], leaving
/// room for jobs that ended at the coordinator while a worker has not yet released them,
/// so a worker never refuses a job the coordinator admitted.
pub const MAX_COORDINATOR_JOBS: usize = MAX_WORKER_JOBS / 2;
