//! The one server builder: every dray server (coordinator, worker, cache host) is
//! served by [`serve`], with the same layers in the same order:
//!
//! 0. [`crate::trace::TraceLayer`]: a call carrying a W3C `traceparent` runs in a span
//!    whose parent is the caller's (only when the process exports traces).
//! 1. [`AuthLayer`]: the caller's credential for the method's class ([`crate::auth`]);
//!    refused calls cost nothing further.
//! 2. [`AdmissionLayer`]: at most `max_calls` calls in progress **per class of caller**
//!    (health, reflection, the public API, the cluster: no class takes another's
//!    places); more are refused at once with RESOURCE_EXHAUSTED (load shedding). A call
//!    holds its place until its response has been sent (a stream: until it ends); a
//!    single-message request must arrive whole within `body_timeout` (a call whose
//!    client sends headers and no body, or no END_STREAM, ends with DEADLINE_EXCEEDED
//!    and frees its place); public
//!    API calls end with DEADLINE_EXCEEDED after `api_timeout`.
//! 3. [`ContainLayer`]: a handler that panics answers INTERNAL with the panic's message
//!    instead of taking the connection (and every other call on it) down.
//!
//! Below the layers, connections are bounded before anyone is authenticated
//! ([`crate::connections`]): at most `max_connections` open at once, and at most
//! `max_connections_per_address` from one source address (more are closed as soon as
//! accepted); a connection must start its handshake (the HTTP/2 preface or TLS)
//! within `handshake_timeout`, and a TLS handshake must end within it; a connection
//! from which nothing is read for `idle_timeout` is closed. HTTP/2 keep-alive PINGs
//! every `keepalive_interval` (answered within `keepalive_timeout`) keep live peers
//! talking and close dead ones; a connection has at most
//! `max_streams_per_connection` streams open at once (HTTP/2
//! SETTINGS_MAX_CONCURRENT_STREAMS: a client's further streams wait or are refused).
//! hyper's HTTP/2 defaults stay in force against protocol abuse: a header list is
//! bounded (16 KiB, which also bounds CONTINUATION frames), streams reset before the
//! server accepts them are bounded (rapid reset), and so are the resets a client makes
//! the server send.
//!
//! Health (`grpc.health.v1`) and reflection (v1 and v1alpha) are added to every
//! server; TCP_NODELAY is set on every connection (small replies would otherwise wait
//! out the peer's delayed ACK); TLS when configured.
//!
//! With `emulate` set, every accepted connection is shaped as a link of a real cluster
//! (latency and bandwidth, both directions; [`crate::emulate`]), beneath TLS. Off by
//! default; only experiments that price communication turn it on.

use std::future::Future;
use std::time::Duration;

use tokio::net::TcpListener;
use tonic::service::Routes;
use tonic::transport::ServerTlsConfig;
use tonic::transport::server::TcpIncoming;

use crate::admission::AdmissionLayer;
use crate::auth::{AuthLayer, AuthPolicy};
use crate::connections::{ConnectionLimits, Limited};
use crate::contain::ContainLayer;
use crate::credential::Token;
use crate::emulate::LinkEmulation;
use crate::tls::{TlsError, TlsFiles};

/// Calls in progress a server takes by default before shedding.
pub const DEFAULT_MAX_CALLS: usize = 1024;
/// How long a public API call may take by default.
pub const DEFAULT_API_TIMEOUT: Duration = Duration::from_secs(120);
/// How long a single-message request's message may take to arrive by default (requests
/// are at most a few MiB; this is generous even on a slow link).
pub const DEFAULT_BODY_TIMEOUT: Duration = Duration::from_secs(20);
/// Connections a server keeps open at once by default (well under the usual
/// descriptor limits of a server process).
pub const DEFAULT_MAX_CONNECTIONS: usize = 4096;
/// Connections one source address keeps open at once by default: a quarter of
/// [`DEFAULT_MAX_CONNECTIONS`], so one address cannot lock the others out, and room
/// for a whole `dray cluster` on one host (all on 127.0.0.1).
pub const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: usize = 1024;
/// How long a new connection may take to start its handshake (or to finish TLS).
pub const DEFAULT_HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a connection may send nothing at all before it is closed.
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(60);
/// How often a server PINGs a connection it has heard nothing from.
pub const DEFAULT_KEEPALIVE_INTERVAL: Duration = Duration::from_secs(20);
/// How long a PING may wait for its answer before the connection is closed.
pub const DEFAULT_KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);
/// Streams one connection may have open at once by default.
pub const DEFAULT_MAX_STREAMS_PER_CONNECTION: u32 = 512;

/// How a server admits connections and calls. The limits' defaults are the `DEFAULT_`
/// constants of this module.
#[derive(Clone, Debug)]
pub struct ServerOptions {
    pub auth: AuthPolicy,
    pub tls: Option<ServerTlsConfig>,
    /// Calls in progress at once in each class of caller (health, reflection, API,
    /// cluster); more are shed. A streaming call counts until its stream ends.
    pub max_calls: usize,
    /// Longest a public API call may run (its handler, not a stream it returns).
    pub api_timeout: Duration,
    /// Longest a single-message request (every method but the client- and
    /// bidi-streaming ones) may take to arrive whole (its message and its end), from
    /// its headers.
    pub body_timeout: Duration,
    /// Connections open at once; more are closed as soon as they are accepted.
    pub max_connections: usize,
    /// Connections open at once from one source address (an IPv6 one by its /64);
    /// more from it are closed as soon as they are accepted.
    pub max_connections_per_address: usize,
    /// Longest a new connection may take to send its first bytes (the HTTP/2 preface
    /// or a TLS ClientHello), and a TLS handshake to finish.
    pub handshake_timeout: Duration,
    /// A connection from which nothing is read for this long is closed. Used only with
    /// keep-alive, and then at least `keepalive_interval + keepalive_timeout` + 5 s.
    pub idle_timeout: Duration,
    /// HTTP/2 keep-alive: a PING after this long without hearing from the peer;
    /// `None` turns keep-alive (and with it the idle timeout) off.
    pub keepalive_interval: Option<Duration>,
    /// How long a keep-alive PING may wait for its answer.
    pub keepalive_timeout: Duration,
    /// Streams (calls) one connection may have open at once.
    pub max_streams_per_connection: u32,
    /// Shape every accepted connection as a link with this bandwidth and latency (an
    /// emulated interconnect); `None` leaves connections alone.
    pub emulate: Option<LinkEmulation>,
}

impl Default for ServerOptions {
    /// Open, plaintext, default limits.
    fn default() -> Self {
        ServerOptions {
            auth: AuthPolicy::default(),
            tls: None,
            max_calls: DEFAULT_MAX_CALLS,
            api_timeout: DEFAULT_API_TIMEOUT,
            body_timeout: DEFAULT_BODY_TIMEOUT,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
            handshake_timeout: DEFAULT_HANDSHAKE_TIMEOUT,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
            keepalive_interval: Some(DEFAULT_KEEPALIVE_INTERVAL),
            keepalive_timeout: DEFAULT_KEEPALIVE_TIMEOUT,
            max_streams_per_connection: DEFAULT_MAX_STREAMS_PER_CONNECTION,
            emulate: None,
        }
    }
}

/// Why a server could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Tls(#[from] TlsError),
    #[error(transparent)]
    Policy(#[from] crate::auth::PolicyError),
    #[error("the reflection service: {0}")]
    Reflection(String),
    #[error("the gRPC server: {0}")]
    Transport(#[from] tonic::transport::Error),
}

impl ServerOptions {
    /// Options with these tokens and TLS files, default limits.
    pub fn new(
        api: Option<Token>,
        cluster: Option<Token>,
        tls: &TlsFiles,
    ) -> Result<ServerOptions, ServeError> {
        Ok(ServerOptions {
            auth: AuthPolicy { api, cluster }.checked()?,
            tls: tls.server()?,
            ..ServerOptions::default()
        })
    }

    /// The connection limits these options ask for (the idle timeout only with
    /// keep-alive, and long enough for a PING to be answered).
    pub fn connection_limits(&self) -> ConnectionLimits {
        let slack = Duration::from_secs(5);
        ConnectionLimits {
            max_connections: self.max_connections,
            max_per_address: self.max_connections_per_address,
            handshake_timeout: self.handshake_timeout,
            idle_timeout: self
                .keepalive_interval
                .map(|i| self.idle_timeout.max(i + self.keepalive_timeout + slack)),
            emulate: self.emulate,
        }
    }
}

/// Serve `routes` on `listener` until `shutdown`, with health (every name in
/// `serving` reported SERVING) and reflection added.
pub async fn serve(
    options: &ServerOptions,
    listener: TcpListener,
    routes: Routes,
    serving: &[&str],
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    let (reporter, health) = tonic_health::server::health_reporter();
    for name in serving {
        reporter
            .set_service_status(*name, tonic_health::ServingStatus::Serving)
            .await;
    }
    let reflection = dray_proto::reflection::reflection_v1()
        .map_err(|e| ServeError::Reflection(e.to_string()))?;
    let reflection_alpha = dray_proto::reflection::reflection_v1alpha()
        .map_err(|e| ServeError::Reflection(e.to_string()))?;
    let routes = routes
        .add_service(health)
        .add_service(reflection)
        .add_service(reflection_alpha);
    let layers = tower::ServiceBuilder::new()
        .layer(crate::trace::TraceLayer)
        .layer(AuthLayer::new(options.auth.clone()))
        .layer(AdmissionLayer::new(
            options.max_calls,
            options.api_timeout,
            options.body_timeout,
        ))
        .layer(ContainLayer)
        .into_inner();
    let mut builder = tonic::transport::Server::builder()
        .http2_keepalive_interval(options.keepalive_interval)
        .http2_keepalive_timeout(Some(options.keepalive_timeout))
        .max_concurrent_streams(Some(options.max_streams_per_connection.max(1)));
    if let Some(tls) = &options.tls {
        builder = builder.tls_config(tls.clone().timeout(options.handshake_timeout))?;
    }
    if let Some(link) = &options.emulate {
        // Loud on purpose: a server that is slowed on purpose must not pass unnoticed.
        tracing::warn!(
            link = %link,
            "every connection this server accepts is shaped (an emulated interconnect, for experiments)"
        );
    }
    let incoming = Limited::new(
        TcpIncoming::from(listener).with_nodelay(Some(true)),
        options.connection_limits(),
    );
    builder
        .layer(layers)
        .add_routes(routes)
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    Ok(())
}
