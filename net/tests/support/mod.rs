//! A real dray server (the shared builder, `dray_net::server::serve`) on a loopback
//! port, with a small RenderService whose GetJob answers at once and whose WatchJob
//! streams until the client goes away; a raw HTTP/2 client (`h2`) to send what tonic's
//! client never would; and health checks on a fresh connection.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::pin::Pin;
use std::time::{Duration, Instant};

use bytes::Bytes;
use dray_net::ServerOptions;
use dray_proto::v1::render_service_server::{RenderService, RenderServiceServer};
use dray_proto::v1::*;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// The RenderService of these tests: GetJob answers a default job; WatchJob sends a
/// message every 50 ms for as long as its stream lives.
pub struct Stub;

#[tonic::async_trait]
impl RenderService for Stub {
    async fn submit_job(
        &self,
        _: Request<SubmitJobRequest>,
    ) -> Result<Response<SubmitJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    type WatchJobStream = Pin<Box<dyn Stream<Item = Result<JobProgress, Status>> + Send>>;
    async fn watch_job(
        &self,
        _: Request<WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        tokio::spawn(async move {
            while tx.send(Ok(JobProgress::default())).await.is_ok() {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }
    async fn get_job(&self, _: Request<GetJobRequest>) -> Result<Response<GetJobResponse>, Status> {
        Ok(Response::new(GetJobResponse::default()))
    }
    async fn list_jobs(
        &self,
        _: Request<ListJobsRequest>,
    ) -> Result<Response<ListJobsResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn cancel_job(
        &self,
        _: Request<CancelJobRequest>,
    ) -> Result<Response<CancelJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn get_image(
        &self,
        _: Request<GetImageRequest>,
    ) -> Result<Response<GetImageResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    type WatchImageStream = Pin<Box<dyn Stream<Item = Result<GetImageResponse, Status>> + Send>>;
    async fn watch_image(
        &self,
        _: Request<WatchImageRequest>,
    ) -> Result<Response<Self::WatchImageStream>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn list_workers(
        &self,
        _: Request<ListWorkersRequest>,
    ) -> Result<Response<ListWorkersResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn retry_job(
        &self,
        _: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn requeue_job(
        &self,
        _: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn pause_job(
        &self,
        _: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn resume_job(
        &self,
        _: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
}

/// A server running until dropped.
pub struct Server {
    pub addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// Serve the stub with `options` on a loopback port.
pub async fn start(options: ServerOptions) -> Server {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("address");
    let (stop, stopped) = oneshot::channel::<()>();
    let routes = tonic::service::Routes::new(RenderServiceServer::new(Stub));
    tokio::spawn(async move {
        dray_net::server::serve(
            &options,
            listener,
            routes,
            &["dray.v1.RenderService"],
            async move {
                let _ = stopped.await;
            },
        )
        .await
        .expect("the server runs");
    });
    Server {
        addr,
        stop: Some(stop),
    }
}

/// A health check of the render service on a new connection: its status, or the error.
pub async fn health(addr: SocketAddr) -> Result<i32, String> {
    health_from(addr, None).await
}

/// [`health`] from the source address `from` (None: the system's choice).
pub async fn health_from(addr: SocketAddr, from: Option<std::net::IpAddr>) -> Result<i32, String> {
    use tonic_health::pb::HealthCheckRequest;
    use tonic_health::pb::health_client::HealthClient;
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .map_err(|e| e.to_string())?
        .local_address(from)
        .connect()
        .await
        .map_err(|e| e.to_string())?;
    HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: "dray.v1.RenderService".into(),
        })
        .await
        .map(|r| r.into_inner().status)
        .map_err(|s| format!("{:?}: {}", s.code(), s.message()))
}

/// SERVING in grpc.health.v1.
pub const SERVING: i32 = 1;

/// Wait until `f` holds, polling every 50 ms; false after `secs` (a safety deadline,
/// never the thing tested).
pub async fn eventually<F, Fut>(secs: f64, mut f: F) -> bool
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let end = Instant::now() + Duration::from_secs_f64(secs);
    loop {
        if f().await {
            return true;
        }
        if Instant::now() > end {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A raw HTTP/2 connection: a client that sends frames as it is told.
pub async fn h2_connect(addr: SocketAddr) -> h2::client::SendRequest<Bytes> {
    let tcp = TcpStream::connect(addr).await.expect("connect");
    let (client, connection) = h2::client::handshake(tcp).await.expect("HTTP/2 handshake");
    tokio::spawn(async move {
        let _ = connection.await;
    });
    client
}

/// A gRPC request's headers for `path`.
pub fn grpc_request(addr: SocketAddr, path: &str) -> http::Request<()> {
    http::Request::post(format!("http://{addr}{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .expect("a request")
}

/// An empty gRPC message (the 5-byte prefix of a zero-length message).
pub fn empty_message() -> Bytes {
    Bytes::from_static(&[0, 0, 0, 0, 0])
}

/// The gRPC status of a response: in its headers (trailers-only), else in its trailers
/// (after reading its body).
pub async fn grpc_status(response: http::Response<h2::RecvStream>) -> Option<i32> {
    if let Some(s) = response.headers().get("grpc-status") {
        return s.to_str().ok()?.parse().ok();
    }
    let mut body = response.into_body();
    while let Some(chunk) = body.data().await {
        let chunk = chunk.ok()?;
        let _ = body.flow_control().release_capacity(chunk.len());
    }
    let trailers = body.trailers().await.ok()??;
    trailers.get("grpc-status")?.to_str().ok()?.parse().ok()
}

/// A complete unary call on `client`: its gRPC status.
pub async fn unary(
    client: &mut h2::client::SendRequest<Bytes>,
    addr: SocketAddr,
    path: &str,
) -> Option<i32> {
    let mut ready = client.clone().ready().await.ok()?;
    let (response, mut send) = ready.send_request(grpc_request(addr, path), false).ok()?;
    // A shed call is answered (and its stream reset) as soon as its headers arrive: on a
    // multi-threaded runtime that can happen before the body goes out, and then sending
    // it fails. The answer is what the call got either way.
    let _ = send.send_data(empty_message(), true);
    grpc_status(response.await.ok()?).await
}
