//! dray's worker actor: owns spatial domains of a job's scene, traces the rays that
//! enter them, and streams the rays that leave to the domains' owners.
//!
//! Why it is built this way (see [`node`] for how the parts fit):
//! - [`domain_store`]: the domain is the unit of residency, loading and scheduling;
//!   domains load on demand and are evicted least-recently-used within a memory budget,
//!   so a worker can serve a scene larger than its memory.
//! - [`queue`]: bounded ray queues per (job attempt, domain): the per-domain lengths are
//!   the worker's queue report, and bounded because rays multiply as they bounce: an
//!   unbounded queue would turn a ray explosion into an out-of-memory kill.
//! - [`routing`]: the job's versioned routing table, swapped while the job runs when
//!   the scheduler moves domains; rays for domains this worker does not own are
//!   forwarded.
//! - [`tracer`]: the compute step, with no I/O.
//! - [`peer_server`] / [`peer_client`]: the ray stream between workers, with credit
//!   flow control so a full queue stalls the sender instead of growing memory.
//! - [`package_fetch`]: scene packages fetched from the coordinator, domain by domain,
//!   so a worker needs no shared volume with it.

pub(crate) mod cache_link;
pub(crate) mod cache_requests;
pub mod config;
pub(crate) mod contain;
pub(crate) mod coordinator_link;
pub(crate) mod domain_sources;
pub mod domain_store;
pub mod env_map;
pub(crate) mod job_actor;
pub(crate) mod job_error;
pub mod jobs;
pub(crate) mod links;
pub mod map_merge;
pub(crate) mod member;
pub(crate) mod metrics;
pub mod node;
pub mod package_fetch;
pub mod peer_client;
pub mod peer_server;
pub(crate) mod peers;
pub mod pixel_sums;
pub mod plan;
pub mod queue;
pub(crate) mod reporter;
pub mod routing;
pub mod setup_bounds;
pub(crate) mod site;
pub mod tickets;
pub mod tracer;
pub mod traffic;
pub mod traffic_trace;
pub(crate) mod wake;
pub(crate) mod work;
pub(crate) mod workload;

pub use config::{Limits, NodeError, WorkerConfig};
pub use domain_store::{
    Content, Contents, DomainSource, DomainStore, JobKey, LoadError, LoadedDomain,
};
pub use node::run;
pub use peer_client::{BatchKey, PeerClientConfig, PeerError, PeerSender};
pub use peer_server::{PeerServer, PeerServerConfig, StreamError};
pub use queue::{QueueError, QueueKey, QueuedBatch, RayQueues};
pub use tracer::{JobTracer, Outbox, Residency, TileRef, TraceError};
