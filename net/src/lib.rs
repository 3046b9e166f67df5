//! How dray's actors talk to each other and to their users: the one place where gRPC
//! servers and clients are set up.
//!
//! - [`credential`]: bearer tokens (read from a file or the environment, compared in
//!   constant time, never printed).
//! - [`auth`]: which credential each service needs. The public API (`RenderService`)
//!   takes the **API token**; the cluster's own services (`ClusterService`,
//!   `RayExchangeService`, `CacheService`) take the **cluster token**, which API clients
//!   never hold; health and reflection stay open, for probes and grpcurl.
//! - [`server`]: one builder for the coordinator, the workers and the cache hosts,
//!   made of tower layers: authentication, admission (a bound on calls in progress per
//!   class of caller, beyond which calls are refused at once rather than queued),
//!   request timeouts; plus health, reflection, TCP_NODELAY and TLS.
//! - [`connections`]: connections bounded before authentication (a maximum, handshake
//!   and idle timeouts).
//! - [`emulate`]: an opt-in emulated interconnect (per-connection latency and bandwidth)
//!   on every accepted connection, to price communication as on a real cluster.
//! - [`body_deadline`]: a request body that must arrive whole in time.
//! - [`client`]: channels that present a token (and speak TLS when asked).
//! - [`tls`]: certificate files for both sides.
//! - [`trace`]: W3C trace context in gRPC metadata (when the process exports traces).
//! - [`contain`]: panics in handlers and tasks become errors with their message.
//! - [`traffic`]: the kinds of bytes between processes a job's traffic counts.

pub mod admission;
pub mod auth;
pub mod body_deadline;
pub mod client;
pub mod connections;
pub mod contain;
pub mod cpu;
pub mod credential;
pub mod emulate;
pub mod peer_pass;
pub mod server;
pub mod tls;
pub mod trace;
pub mod traffic;

/// The coordinator's conventional port: where `dray cluster` puts it (`--base-port`),
/// what `dray health` asks by default, and where a worker looks for it by default.
pub const DEFAULT_PORT: u16 = 50051;

pub use auth::{Access, AuthPolicy};
pub use client::{AuthChannel, ClientOptions};
pub use credential::Token;
pub use emulate::LinkEmulation;
pub use server::ServerOptions;
pub use tls::TlsFiles;
