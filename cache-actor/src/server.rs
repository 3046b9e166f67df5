//! Serving a cache host over gRPC: `dray.v1.CacheService`, the standard health service
//! (so load balancers and `grpc_health_probe` see it) and server reflection (so
//! `grpcurl` works with no `.proto` files), as every dray server does.

use std::future::Future;

use dray_proto::v1::cache_service_server::CacheServiceServer;
use tokio::net::TcpListener;

use crate::host::CacheHost;

/// Why the server could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot build the reflection service: {0}")]
    Reflection(String),
    #[error("cache host server failed: {0}")]
    Transport(#[from] tonic::transport::Error),
}

impl CacheHost {
    /// Serve this host on `listener` until `shutdown` completes.
    pub async fn serve(
        self,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<(), ServeError> {
        let (health_reporter, health_service) = tonic_health::server::health_reporter();
        health_reporter
            .set_serving::<CacheServiceServer<CacheHost>>()
            .await;
        let reflection = dray_proto::reflection::reflection_v1()
            .map_err(|e| ServeError::Reflection(e.to_string()))?;
        let reflection_alpha = dray_proto::reflection::reflection_v1alpha()
            .map_err(|e| ServeError::Reflection(e.to_string()))?;
        if let Ok(addr) = listener.local_addr() {
            tracing::info!(%addr, "cache host serving");
        }
        tonic::transport::Server::builder()
            .add_service(health_service)
            .add_service(reflection)
            .add_service(reflection_alpha)
            .add_service(self.into_service())
            .serve_with_incoming_shutdown(
                // TCP_NODELAY: lookups are small request/answer round trips, which would
                // otherwise wait out the peer's delayed ACK.
                tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
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
