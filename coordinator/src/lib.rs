//! The dray coordinator: the public `dray.v1.RenderService` and the internal
//! `dray.v1.ClusterService` over gRPC, with server reflection and the standard health
//! service, so `grpcurl` works without .proto files.
//!
//! **Where a job runs.** While no worker is registered, an accepted job is rendered in
//! this process with the single-process path of `dray render` (`dray_core::render` over
//! one BVH, or a [`dray_core::trace::DomainSet`] when `domains > 1`), one job at a time;
//! the image is the same, bit for bit, as `dray render` with the same settings. Once at
//! least one worker is registered, a job runs on the workers: the coordinator writes (or
//! reuses) a scene package, places domains and tiles by the job's schedule (image-plane,
//! domain or dynamic), moves domains towards the rays that wait for them, counts credit
//! and sums the pixels the workers send back, and traces again the tiles a lost worker
//! took with it (see [`dispatch`] for exactly what a worker receives).
//!
//! - [`validate`]: checks a [`JobSpec`](dray_proto::v1::JobSpec) against the limits and
//!   the scene root; every rejection is `INVALID_ARGUMENT` naming the field, quoting
//!   what was sent as [`text`] bounds it.
//! - [`job_group`]: a spec with `frames` made into one job per frame (a job group);
//!   [`animation_time`]: the moment of the animation a job's scene is loaded at.
//! - [`jobs`]: the job table (every job's record), cancellation, image encoding.
//! - [`local_render`]: jobs rendered in this process while no worker is registered.
//! - [`membership`]: registered workers, heartbeats, per-worker command outboxes;
//!   [`registration`]: what a registering worker or cache host must present.
//! - [`dispatch`]: a job's package, JobSetup and tiles: the plan a job starts from.
//! - [`job`]: one actor per running job, routed to by job id: credit per tile, the
//!   exact fixed-point film, attempts (restarting a job's unfinished tiles without a lost
//!   worker), round pacing, cache walls, releases.
//! - [`scheduler`]: the schedules as pure policies, each job's scheduling state,
//!   versioned routing tables; [`ownership`]: who owns which domain, which the
//!   scheduler computes and cache placement reads.
//! - [`metrics`]: the workers' scheduling counters summed into JobStats.
//! - [`pass_images`]: a job's progressive passes and the image after the last one.
//! - [`worker_list`]: ListWorkers, from the membership and the running jobs' views.
//! - [`caches`]: ray caches on domain walls: cache hosts, where each attempt's cache
//!   actors live, opening and closing their walls, and their statistics.
//! - [`cluster`]: the tonic `ClusterService` over the above.
//! - [`package_service`]: the tonic `PackageService`: running jobs' package files for
//!   workers that do not share the coordinator's disk.
//! - [`operator`]: the operator actions (retry, requeue, pause, resume), over
//!   [`priority`] (the deal queue: priorities, paused jobs) and [`job_events`] (each
//!   job's event log, lineage and attempts, kept in the job store).
//! - [`service`]: the tonic `RenderService` and [`serve`]; [`shutdown`]: the one way a
//!   coordinator stops ([`Coordinator::shutdown`]), for the CLI and the embedded mode.
//! - [`http`]: the web dashboard (`--http-listen`): a page and JSON endpoints over the
//!   same RenderService methods, live updates by server-sent events.

pub mod admission;
pub mod animation_time;
pub mod caches;
pub mod cluster;
pub mod cpu_tally;
pub mod dispatch;
pub mod http;
pub mod image_memo;
pub mod job;
pub mod job_events;
pub mod job_group;
pub mod jobs;
pub mod lighting;
pub mod local_render;
pub mod membership;
pub mod metrics;
pub mod operator;
pub mod owned_package;
pub mod ownership;
pub mod package_service;
pub mod pass_images;
pub mod priority;
pub mod registration;
pub mod scheduler;
pub mod service;
pub mod shutdown;
pub mod store;
pub mod text;
pub mod traffic;
pub mod validate;
pub mod view;
pub mod work_dir;
pub mod worker_list;

pub use service::{Coordinator, serve, serve_with};
