//! Serving a cache host over gRPC: `dray.v1.CacheService`, the standard health service
//! (so load balancers and `grpc_health_probe` see it) and server reflection (so
//! `grpcurl` works with no `.proto` files), as every dray server does.

use std::future::Future;

use tokio::net::TcpListener;

use crate::host::CacheHost;

/// Why the server could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cache host server failed: {0}")]
    Serve(#[from] dray_net::server::ServeError),
}

impl CacheHost {
    /// Serve this host on `listener` until `shutdown` completes, open and in plaintext.
    pub async fn serve(
        self,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<(), ServeError> {
        self.serve_with(&dray_net::ServerOptions::default(), listener, shutdown)
            .await
    }

    /// Serve this host on `listener` until `shutdown` completes, admitting calls per
    /// `options` (the cluster token, TLS, load shedding: dray-net's one server builder).
    pub async fn serve_with(
        self,
        options: &dray_net::ServerOptions,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<(), ServeError> {
        if let Ok(addr) = listener.local_addr() {
            tracing::info!(%addr, "cache host serving");
        }
        let routes = tonic::service::Routes::new(self.into_service());
        dray_net::server::serve(
            options,
            listener,
            routes,
            &[dray_proto::CACHE_SERVICE],
            shutdown,
        )
        .await?;
        Ok(())
    }
}

/// Serve a new, empty cache host on `listener` until `shutdown` completes.
pub async fn serve(
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    CacheHost::new().serve(listener, shutdown).await
}
