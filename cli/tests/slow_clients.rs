//! docs/security.md "Hardening, second round", item 2, with real processes: API calls that
//! send headers and never a body
//! used to hold every `--max-calls` place of the coordinator; health checks, heartbeats
//! and registrations were refused, every worker was declared lost and the running job
//! failed. Now the API has its own places: while a client holds all of them, a worker
//! keeps beating (it is not declared lost past its heartbeat timeout), another worker
//! registers, and `dray health` answers. (The release of the places after the body
//! timeout, streams, connection floods and HTTP/2 abuse are in `net/tests/`.)

mod common;
mod support;

use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use support::{Proc, capture_stderr, dray, eventually, worker};

const SUBMIT_JOB: &str = "/dray.v1.RenderService/SubmitJob";
const MAX_CALLS: usize = 8;
/// The coordinator's heartbeat timeout: long enough that a loaded machine's late beats
/// lose no worker, short enough to be outlived while the API places are held (20 s).
const WORKER_TIMEOUT: Duration = Duration::from_millis(5000);

fn text(log: &Arc<Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

/// Open `n` SubmitJob calls that send their headers and nothing else, on one HTTP/2
/// connection, and wait until `refused` of them have been refused with
/// RESOURCE_EXHAUSTED; returns the streams that keep the others open.
async fn headers_only(addr: &str, n: usize, refused: usize) -> Vec<h2::SendStream<bytes::Bytes>> {
    let tcp = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let (client, connection) = h2::client::handshake(tcp).await.expect("HTTP/2");
    tokio::spawn(async move {
        let _ = connection.await;
    });
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let mut open = Vec::new();
    for _ in 0..n {
        let mut ready = client.clone().ready().await.expect("a stream");
        let request = http::Request::post(format!("http://{addr}{SUBMIT_JOB}"))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(())
            .expect("a request");
        let (response, send) = ready.send_request(request, false).expect("headers");
        open.push(send);
        let tx = tx.clone();
        tokio::spawn(async move {
            if let Ok(r) = response.await {
                let status = r
                    .headers()
                    .get("grpc-status")
                    .and_then(|s| s.to_str().ok().map(str::to_string));
                let _ = tx.send(status);
            }
        });
    }
    let mut seen = 0;
    while seen < refused {
        let status = tokio::time::timeout(Duration::from_secs(60), rx.recv())
            .await
            .unwrap_or_else(|_| panic!("{seen} of {refused} calls refused (safety deadline)"))
            .expect("open channel");
        assert_eq!(
            status.as_deref(),
            Some("8"),
            "a call beyond the API's places is refused"
        );
        seen += 1;
    }
    open
}

#[test]
fn headers_only_api_calls_do_not_starve_heartbeats_registration_or_health() {
    let dir = common::tmp("slow-clients");
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(&dir)
        .args(["--max-calls", &MAX_CALLS.to_string()])
        .args([
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            &WORKER_TIMEOUT.as_millis().to_string(),
        ])
        .env("DRAY_LOG", "warn,dray_coordinator=info")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut coordinator = Proc::spawn(cmd);
    let log = capture_stderr(&mut coordinator.child);
    let addr = support::listening_address(&mut coordinator.child)
        .unwrap_or_else(|first| panic!("no address in {first:?}"));
    let _first = worker(&addr);
    assert!(
        eventually(60.0, || text(&log).matches("worker registered").count()
            >= 1),
        "the worker registered: {}",
        text(&log)
    );
    let first_registered = std::time::Instant::now();

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("runtime");
    // Every API place is held (the calls beyond them are refused at once)...
    let _open = rt.block_on(headers_only(&addr, 4 * MAX_CALLS, 3 * MAX_CALLS));

    // ...and meanwhile a second worker registers...
    let _second = worker(&addr);
    assert!(
        eventually(60.0, || text(&log).matches("worker registered").count()
            >= 2),
        "a worker registers while the API is full: {}",
        text(&log)
    );
    // ...health answers...
    let out = dray()
        .args(["health", &addr])
        .env_remove("DRAY_TLS_CERT")
        .env_remove("DRAY_TLS_KEY")
        .env_remove("DRAY_TLS_CA")
        .output()
        .expect("dray health");
    assert!(
        out.status.success(),
        "dray health: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    // ...and the first worker's heartbeats keep it a member past its heartbeat timeout
    // (the scenario needs the API held that long; the places are held for the body
    // timeout, 20 s by default). An absence over a span of time is what is tested, and
    // no event stands for it (heartbeats are silent), so the span is let pass: a timeout
    // and a half since the first worker was seen registered, not a fixed sleep.
    let quiet_until = first_registered + WORKER_TIMEOUT.mul_f64(1.4);
    std::thread::sleep(quiet_until.saturating_duration_since(std::time::Instant::now()));
    assert_eq!(
        text(&log).matches("worker lost").count(),
        0,
        "no worker is lost while the API is full: {}",
        text(&log)
    );
}
