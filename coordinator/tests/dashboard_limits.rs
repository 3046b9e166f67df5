//! What one dashboard client may hold, against the real dashboard on loopback over real
//! sockets (issue 45, items 4 and 12; docs/security.md "Hardening, third round"):
//!
//! - the API's calls in progress, the image endpoint's included, are bounded by
//!   `--max-calls` as the gRPC API's are: one beyond is refused with 429
//!   RESOURCE_EXHAUSTED at once, and the place comes back when a call ends;
//! - one session's event streams beyond its share are refused while another session
//!   still gets one, and the global cap holds over all sessions;
//! - a cookie copied before logout is refused after it, and a stream it opened ends.

use std::net::SocketAddr;
use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_coordinator::http::events::{MAX_STREAMS, MAX_STREAMS_PER_CLIENT};
use dray_coordinator::http::{Dashboard, serve};
use dray_net::Token;
use dray_net::connections::ConnectionLimits;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// A safety deadline for what the tests wait for (never the thing tested).
const SAFETY: Duration = Duration::from_secs(60);
const TOKEN: &str = "0123456789abcdef-dashboard-limits";

/// A dashboard on 127.0.0.1 (with the API token when `token`), at most `max_calls`
/// calls in progress; stops when the sender is dropped.
async fn dashboard(
    name: &str,
    token: bool,
    max_calls: usize,
) -> (SocketAddr, tokio::sync::oneshot::Sender<()>) {
    let root = std::env::temp_dir().join(format!(
        "dray-dashboard-limits-{}-{name}",
        std::process::id()
    ));
    std::fs::create_dir_all(&root).expect("scene root");
    let coordinator = Coordinator::new(&root, 1).expect("coordinator");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("address");
    let token = token.then(|| Token::parse(TOKEN, "test").expect("token"));
    let d = Dashboard::new(coordinator, token)
        .expect("dashboard")
        .with_max_calls(max_calls);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(async move {
        let limits = ConnectionLimits {
            max_connections: 1024,
            max_per_address: 1024,
            handshake_timeout: SAFETY,
            idle_timeout: None,
            emulate: None,
        };
        serve(listener, d, limits, async move {
            let _ = stopped.await;
        })
        .await
        .expect("the dashboard serves");
    });
    (addr, stop)
}

/// A whole answer: its status code, head and body.
struct Answer {
    status: u16,
    head: String,
    body: String,
}

/// `method path` with `headers` and `body`, on a connection of its own.
async fn call(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[String],
    body: &str,
) -> Answer {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n");
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    req.push_str(&format!("Content-Length: {}\r\n\r\n{body}", body.len()));
    s.write_all(req.as_bytes()).await.expect("send");
    let mut out = Vec::new();
    tokio::time::timeout(SAFETY, s.read_to_end(&mut out))
        .await
        .expect("an answer (safety deadline)")
        .expect("read");
    let text = String::from_utf8_lossy(&out).to_string();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    Answer {
        status: status_of(head),
        head: head.to_string(),
        body: body.to_string(),
    }
}

fn status_of(head: &str) -> u16 {
    head.split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status in {head:?}"))
}

/// An event stream opened with `headers`: its status, and the connection (open while
/// the stream is, for a 200), with what was read past the head (for a refusal: its
/// whole body).
async fn open_stream(addr: SocketAddr, path: &str, headers: &[String]) -> (u16, TcpStream, String) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n");
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).await.expect("send");
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    let head_end = loop {
        let n = tokio::time::timeout(SAFETY, s.read(&mut buf))
            .await
            .expect("a head (safety deadline)")
            .expect("read");
        assert!(
            n > 0,
            "closed before a head: {:?}",
            String::from_utf8_lossy(&got)
        );
        got.extend_from_slice(&buf[..n]);
        if let Some(k) = got.windows(4).position(|w| w == b"\r\n\r\n") {
            break k;
        }
    };
    let head = String::from_utf8_lossy(&got[..head_end]).to_ascii_lowercase();
    let status = status_of(&head);
    if status != 200 {
        let length: usize = head
            .lines()
            .find_map(|l| l.strip_prefix("content-length: "))
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or(0);
        while got.len() < head_end + 4 + length {
            let n = tokio::time::timeout(SAFETY, s.read(&mut buf))
                .await
                .expect("a body (safety deadline)")
                .expect("read");
            assert!(n > 0, "closed within the body");
            got.extend_from_slice(&buf[..n]);
        }
    }
    let rest = String::from_utf8_lossy(&got[head_end + 4..]).to_string();
    (status, s, rest)
}

/// Log in with the token: the `Cookie` header of the new session.
async fn login(addr: SocketAddr) -> String {
    let a = call(
        addr,
        "POST",
        "/api/login",
        &[
            "X-Dray-Csrf: 1".into(),
            "Content-Type: application/json".into(),
        ],
        &format!(r#"{{"token": "{TOKEN}"}}"#),
    )
    .await;
    assert_eq!(a.status, 200, "{} {}", a.head, a.body);
    let set = a
        .head
        .lines()
        .find_map(|l| {
            l.strip_prefix("set-cookie: ")
                .or_else(|| l.strip_prefix("Set-Cookie: "))
        })
        .unwrap_or_else(|| panic!("no cookie in {}", a.head));
    format!("Cookie: {}", set.split(';').next().expect("name=value"))
}

/// `--max-calls 2`: with two calls in progress (event streams, which hold their place
/// until they end, as a gRPC stream does), the image endpoint is refused at once with
/// RESOURCE_EXHAUSTED; once one ends it is answered again (here: the job is unknown).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_image_endpoint_is_under_max_calls() {
    let (addr, _stop) = dashboard("calls", false, 2).await;
    let image = "/api/jobs/no-such-job/image.png";
    assert_eq!(call(addr, "GET", image, &[], "").await.status, 404);
    let (s1, first, _) = open_stream(addr, "/api/events", &[]).await;
    let (s2, _second, _) = open_stream(addr, "/api/events", &[]).await;
    assert_eq!((s1, s2), (200, 200));
    let refused = call(addr, "GET", image, &[], "").await;
    assert_eq!(refused.status, 429, "{} {}", refused.head, refused.body);
    assert!(
        refused.body.contains("RESOURCE_EXHAUSTED") && refused.body.contains("--max-calls"),
        "{}",
        refused.body
    );
    // Other endpoints share the budget.
    assert_eq!(call(addr, "GET", "/api/jobs", &[], "").await.status, 429);
    // The page itself and the session endpoint are outside it (no data, no work).
    assert_eq!(call(addr, "GET", "/api/session", &[], "").await.status, 200);
    // One stream ends: its place comes back.
    drop(first);
    tokio::time::timeout(SAFETY, async {
        loop {
            let a = call(addr, "GET", image, &[], "").await;
            if a.status != 429 {
                assert_eq!(a.status, 404, "{} {}", a.head, a.body);
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    .expect("the ended stream's place came back (safety deadline)");
}

/// One session opens streams until refused: it gets its share and no more, while
/// another session still gets one; sessions together stop at the global cap.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_sessions_streams_beyond_its_share_are_refused() {
    let (addr, _stop) = dashboard("streams", true, 1024).await;
    let mine = login(addr).await;
    let other = login(addr).await;
    let mut open = Vec::new();
    for k in 0..MAX_STREAMS_PER_CLIENT {
        let (status, s, _) = open_stream(addr, "/api/events", std::slice::from_ref(&mine)).await;
        assert_eq!(status, 200, "stream {k} of the session's share");
        open.push(s);
    }
    let (status, _, body) = open_stream(addr, "/api/events", std::slice::from_ref(&mine)).await;
    assert_eq!(status, 503, "{body}");
    assert!(body.contains("its share"), "{body}");
    // A bearer client from the same address is another client.
    let (status, s, _) = open_stream(
        addr,
        "/api/events",
        &[format!("Authorization: Bearer {TOKEN}")],
    )
    .await;
    assert_eq!(status, 200);
    open.push(s);
    let (status, s, _) = open_stream(addr, "/api/events", std::slice::from_ref(&other)).await;
    assert_eq!(status, 200, "another session gets a stream");
    open.push(s);
    // Fill the rest of the global cap with more sessions' shares.
    while open.len() < MAX_STREAMS {
        let session = login(addr).await;
        for _ in 0..MAX_STREAMS_PER_CLIENT.min(MAX_STREAMS - open.len()) {
            let (status, s, _) =
                open_stream(addr, "/api/events", std::slice::from_ref(&session)).await;
            assert_eq!(status, 200, "{} open", open.len());
            open.push(s);
        }
    }
    let fresh = login(addr).await;
    let (status, _, body) = open_stream(addr, "/api/events", &[fresh]).await;
    assert_eq!(status, 503, "beyond the global cap: {body}");
    assert!(
        body.contains(&format!("{MAX_STREAMS} event streams")),
        "{body}"
    );
}

/// A cookie copied before logout is refused after it (401), and an event stream it
/// had open ends with a `failed` event; another session is untouched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cookie_used_after_logout_is_refused() {
    let (addr, _stop) = dashboard("logout", true, 1024).await;
    let cookie = login(addr).await;
    let other = login(addr).await;
    assert_eq!(
        call(addr, "GET", "/api/jobs", std::slice::from_ref(&cookie), "")
            .await
            .status,
        200
    );
    let (status, mut stream, mut seen) = open_stream(
        addr,
        "/api/events?interval_ms=250",
        std::slice::from_ref(&cookie),
    )
    .await;
    assert_eq!(status, 200);
    let out = call(
        addr,
        "POST",
        "/api/logout",
        &[cookie.clone(), "X-Dray-Csrf: 1".into()],
        "",
    )
    .await;
    assert_eq!(out.status, 200, "{} {}", out.head, out.body);
    assert!(
        out.head.to_ascii_lowercase().contains("max-age=0"),
        "{}",
        out.head
    );
    let after = call(addr, "GET", "/api/jobs", std::slice::from_ref(&cookie), "").await;
    assert_eq!(after.status, 401, "{} {}", after.head, after.body);
    assert!(after.body.contains("logged out"), "{}", after.body);
    assert_eq!(
        call(addr, "GET", "/api/jobs", std::slice::from_ref(&other), "")
            .await
            .status,
        200
    );
    // The stream the copied cookie opened ends.
    tokio::time::timeout(SAFETY, async {
        let mut buf = [0u8; 4096];
        while !seen.contains("event: failed") {
            let n = stream.read(&mut buf).await.expect("read");
            assert!(n > 0, "closed without the failed event: {seen}");
            seen.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
    })
    .await
    .expect("the logged-out session's stream ended (safety deadline)");
    assert!(seen.contains("session has ended"), "{seen}");
}
