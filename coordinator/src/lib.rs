//! The dray coordinator: the public `dray.v1.RenderService` over gRPC, with server
//! reflection and the standard health service, so `grpcurl` works without .proto files.
//!
//! **This slice does not wire workers yet.** An accepted job is rendered in this process
//! with the single-process path of `dray render` (`dray_core::render` over one BVH, or a
//! [`dray_core::trace::DomainSet`] when `domains > 1`), on a blocking thread so the server
//! keeps answering. Jobs run one at a time in submission order; the others wait QUEUED.
//! The image is the same, bit for bit, as `dray render` with the same settings.
//!
//! - [`validate`]: checks a [`JobSpec`](dray_proto::v1::JobSpec) against the limits and
//!   the scene root; every rejection is `INVALID_ARGUMENT` naming the field.
//! - [`jobs`]: the job table, the render task, cancellation, and image encoding.
//! - [`service`]: the tonic `RenderService` implementation and [`serve`].

pub mod cluster;
pub mod dispatch;
pub mod jobs;
pub mod ledger;
pub mod membership;
pub mod routing;
pub mod service;
pub mod validate;

pub use service::{Coordinator, serve};
