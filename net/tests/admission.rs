//! docs/security.md "Hardening, second round", items 2 and 10, against a real server on
//! loopback: calls that send headers
//! and never a body, and streams that never end, cannot take other classes' places,
//! and free their own (body timeout; a stream's place goes with its stream).

mod support;

use std::time::Duration;

use dray_net::ServerOptions;
use support::*;
use tokio::sync::mpsc;

const GET_JOB: &str = "/dray.v1.RenderService/GetJob";
const WATCH_JOB: &str = "/dray.v1.RenderService/WatchJob";
const HEALTH_CHECK: &str = "/grpc.health.v1.Health/Check";
const HEARTBEAT: &str = "/dray.v1.ClusterService/Heartbeat";

const OK: i32 = 0;
const DEADLINE_EXCEEDED: i32 = 4;
const RESOURCE_EXHAUSTED: i32 = 8;
const UNIMPLEMENTED: i32 = 12;

const MAX_CALLS: usize = 8;
const BODY_TIMEOUT: Duration = Duration::from_secs(5);

fn options() -> ServerOptions {
    ServerOptions {
        max_calls: MAX_CALLS,
        body_timeout: BODY_TIMEOUT,
        ..ServerOptions::default()
    }
}

/// Send `n` calls to `path` that never end their request, on one connection: the even
/// ones with headers only (never a DATA frame), the odd ones with their message but no
/// END_STREAM (tonic reads a request to its end before the handler runs). Each call's
/// gRPC status arrives on the channel when it ends. The returned streams keep the calls
/// open.
async fn headers_only(
    addr: std::net::SocketAddr,
    path: &str,
    n: usize,
) -> (
    Vec<h2::SendStream<bytes::Bytes>>,
    mpsc::UnboundedReceiver<Option<i32>>,
) {
    let client = h2_connect(addr).await;
    let (tx, rx) = mpsc::unbounded_channel();
    let mut open = Vec::new();
    for i in 0..n {
        let mut ready = client
            .clone()
            .ready()
            .await
            .expect("the connection takes a stream");
        let (response, mut send) = ready
            .send_request(grpc_request(addr, path), false)
            .expect("headers sent");
        if i % 2 == 1 {
            // A shed call may already be answered and reset: its status says so.
            let _ = send.send_data(empty_message(), false);
        }
        open.push(send);
        let tx = tx.clone();
        tokio::spawn(async move {
            let status = match response.await {
                Ok(r) => grpc_status(r).await,
                Err(_) => None,
            };
            let _ = tx.send(status);
        });
    }
    (open, rx)
}

async fn next_status(rx: &mut mpsc::UnboundedReceiver<Option<i32>>) -> Option<i32> {
    tokio::time::timeout(Duration::from_secs(60), rx.recv())
        .await
        .expect("a call ends (safety deadline)")
        .expect("the channel is open")
}

async fn call(addr: std::net::SocketAddr, path: &str) -> Option<i32> {
    let mut client = h2_connect(addr).await;
    unary(&mut client, addr, path).await
}

/// 12 API calls that never end their request against 8 places: 4 are shed at once, 8 are held until
/// the body timeout; meanwhile health and the cluster's calls are admitted (their own
/// budgets), and once the held calls end with DEADLINE_EXCEEDED their places are free.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn headers_only_api_calls_cannot_starve_health_or_the_cluster() {
    let server = start(options()).await;
    let addr = server.addr;
    let (_open, mut statuses) = headers_only(addr, GET_JOB, MAX_CALLS + 4).await;
    for _ in 0..4 {
        assert_eq!(next_status(&mut statuses).await, Some(RESOURCE_EXHAUSTED));
    }
    // Every API place is held: a complete API call is shed...
    assert_eq!(call(addr, GET_JOB).await, Some(RESOURCE_EXHAUSTED));
    // ...but health answers and a cluster call passes admission (this server has no
    // ClusterService: it reaches the router, which answers UNIMPLEMENTED, not shed).
    assert_eq!(health(addr).await, Ok(SERVING));
    assert_eq!(call(addr, HEARTBEAT).await, Some(UNIMPLEMENTED));
    // The held calls end with DEADLINE_EXCEEDED once their body is late...
    for _ in 0..MAX_CALLS {
        assert_eq!(next_status(&mut statuses).await, Some(DEADLINE_EXCEEDED));
    }
    // ...and their places are free again.
    assert!(
        eventually(30.0, || async { call(addr, GET_JOB).await == Some(OK) }).await,
        "an API call is admitted after the held ones ended"
    );
}

/// The other way round: headers-only health checks fill the health budget; the API is
/// still served, and health answers again after the body timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn headers_only_health_checks_cannot_starve_the_api() {
    let server = start(options()).await;
    let addr = server.addr;
    let (_open, mut statuses) = headers_only(addr, HEALTH_CHECK, MAX_CALLS + 2).await;
    for _ in 0..2 {
        assert_eq!(next_status(&mut statuses).await, Some(RESOURCE_EXHAUSTED));
    }
    assert!(health(addr).await.is_err(), "the health budget is full");
    assert_eq!(call(addr, GET_JOB).await, Some(OK));
    for _ in 0..MAX_CALLS {
        assert_eq!(next_status(&mut statuses).await, Some(DEADLINE_EXCEEDED));
    }
    assert!(
        eventually(30.0, || async { health(addr).await == Ok(SERVING) }).await,
        "health answers after the held checks ended"
    );
}

/// Streaming responses keep their place until the stream ends: WatchJob streams that
/// are never read are bounded by the API budget (and by the streams one connection may
/// open); closing some frees their places.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unread_streams_are_bounded_and_free_their_places_when_they_end() {
    let server = start(ServerOptions {
        max_streams_per_connection: 4,
        ..options()
    })
    .await;
    let addr = server.addr;
    // Three connections of 4 streams each: 12 streams against 8 places.
    let mut admitted = Vec::new();
    let mut shed = 0;
    let mut clients = Vec::new();
    for _ in 0..3 {
        let mut client = h2_connect(addr).await;
        // The server's SETTINGS are in once a call has been answered.
        assert_eq!(unary(&mut client, addr, GET_JOB).await, Some(OK));
        assert_eq!(
            client.current_max_send_streams(),
            4,
            "streams per connection"
        );
        clients.push(client);
    }
    for client in clients {
        for _ in 0..4 {
            let mut ready = client.clone().ready().await.expect("a stream");
            let (response, mut send) = ready
                .send_request(grpc_request(addr, WATCH_JOB), false)
                .expect("headers sent");
            // A shed stream may be answered and reset before its body goes out.
            let _ = send.send_data(empty_message(), true);
            let response = tokio::time::timeout(Duration::from_secs(60), response)
                .await
                .expect("response headers (safety deadline)")
                .expect("a response");
            match response.headers().get("grpc-status") {
                // A trailers-only answer: refused.
                Some(s) => {
                    assert_eq!(s.to_str().ok(), Some("8"), "shed with RESOURCE_EXHAUSTED");
                    shed += 1;
                }
                // A stream, never read.
                None => admitted.push((client.clone(), response)),
            }
        }
    }
    assert_eq!((admitted.len(), shed), (MAX_CALLS, 4));
    // The API budget is held by the streams; health is not.
    assert_eq!(call(addr, GET_JOB).await, Some(RESOURCE_EXHAUSTED));
    assert_eq!(health(addr).await, Ok(SERVING));
    // Closing two streams (the client resets them) frees two places.
    admitted.truncate(MAX_CALLS - 2);
    assert!(
        eventually(30.0, || async { call(addr, GET_JOB).await == Some(OK) }).await,
        "a place is free once a stream ended"
    );
}
