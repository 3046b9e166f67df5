//! dray's worker actor. This first slice is the worker's ray intake: the peer-to-peer
//! ray streams (`dray.v1.RayExchangeService.RayStream`) and the bounded per-domain ray
//! queues they fill.
//!
//! Why it is built this way:
//! - [`queue`]: one bounded queue per owned domain, because the domain is the unit of
//!   tracing and scheduling (the per-domain lengths are the worker's queue report), and
//!   bounded because rays multiply as they bounce: an unbounded queue would turn a ray
//!   explosion into an out-of-memory kill.
//! - [`peer_server`]: the receiving end. It grants credit only as batches get into a
//!   queue, so a full queue stops the sender at the other end within one window, with
//!   no rays dropped and no memory growth; malformed input ends that stream with a status
//!   naming the problem and never panics.
//! - [`peer_client`]: the sending end, one per peer. Rays are packed (64 bytes each, see
//!   `dray_proto::ray_record`) into one batch per destination domain, sent when full or
//!   when a short delay passes, and never beyond the receiver's grant.

pub mod credit;
pub mod job;
pub mod node;
pub mod peer_client;
pub mod peer_server;
pub mod pixel_sums;
pub mod queue;
pub mod tracer;

pub use node::{NodeError, WorkerConfig, run};
pub use peer_client::{BatchKey, PeerClientConfig, PeerError, PeerSender};
pub use peer_server::{PeerServer, PeerServerConfig, StreamError};
pub use queue::{QueueError, QueuedBatch, RayQueues};
pub use tracer::{JobTracer, Outbox, TileRef, TraceError};
