//! The one server builder: every dray server (coordinator, worker, cache host) is
//! served by [`serve`], with the same layers in the same order:
//!
//! 0. [`crate::trace::TraceLayer`]: a call carrying a W3C `traceparent` runs in a span
//!    whose parent is the caller's (only when the process exports traces).
//! 1. [`AuthLayer`]: the caller's credential for the method's class ([`crate::auth`]);
//!    refused calls cost nothing further.
//! 2. [`AdmissionLayer`]: at most `max_calls` calls in progress; more are refused at
//!    once with RESOURCE_EXHAUSTED (load shedding), and public API calls end with
//!    DEADLINE_EXCEEDED after `api_timeout`.
//! 3. [`ContainLayer`]: a handler that panics answers INTERNAL with the panic's message
//!    instead of taking the connection (and every other call on it) down.
//!
//! Health (`grpc.health.v1`) and reflection (v1 and v1alpha) are added to every
//! server; TCP_NODELAY is set on every connection (small replies would otherwise wait
//! out the peer's delayed ACK); TLS when configured.

use std::future::Future;
use std::time::Duration;

use tokio::net::TcpListener;
use tonic::service::Routes;
use tonic::transport::ServerTlsConfig;
use tonic::transport::server::TcpIncoming;

use crate::admission::AdmissionLayer;
use crate::auth::{AuthLayer, AuthPolicy};
use crate::contain::ContainLayer;
use crate::credential::Token;
use crate::tls::{TlsError, TlsFiles};

/// Calls in progress a server takes by default before shedding.
pub const DEFAULT_MAX_CALLS: usize = 1024;
/// How long a public API call may take by default.
pub const DEFAULT_API_TIMEOUT: Duration = Duration::from_secs(120);

/// How a server admits calls.
#[derive(Clone, Debug)]
pub struct ServerOptions {
    pub auth: AuthPolicy,
    pub tls: Option<ServerTlsConfig>,
    /// Calls in progress at once; more are shed.
    pub max_calls: usize,
    /// Longest a public API call may run (its handler, not a stream it returns).
    pub api_timeout: Duration,
}

impl Default for ServerOptions {
    /// Open, plaintext, default limits.
    fn default() -> Self {
        ServerOptions {
            auth: AuthPolicy::default(),
            tls: None,
            max_calls: DEFAULT_MAX_CALLS,
            api_timeout: DEFAULT_API_TIMEOUT,
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
        .layer(AdmissionLayer::new(options.max_calls, options.api_timeout))
        .layer(ContainLayer)
        .into_inner();
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = &options.tls {
        builder = builder.tls_config(tls.clone())?;
    }
    builder
        .layer(layers)
        .add_routes(routes)
        .serve_with_incoming_shutdown(
            TcpIncoming::from(listener).with_nodelay(Some(true)),
            shutdown,
        )
        .await?;
    Ok(())
}
