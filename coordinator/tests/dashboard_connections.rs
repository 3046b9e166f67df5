//! The dashboard's port under the gRPC servers' connection bounds (issue 45 item 1,
//! docs/security.md), against the real dashboard on loopback with real sockets: idle
//! sockets from one address take at most its places and never lock another address
//! out, and a client that sends its request head slowly is closed.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_coordinator::http::{Dashboard, serve};
use dray_net::connections::ConnectionLimits;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::sync::mpsc;

/// A safety deadline for what the tests wait for (never the thing tested).
const SAFETY: Duration = Duration::from_secs(60);

/// A dashboard with no API token on 127.0.0.1, bounded by `limits`.
async fn dashboard(limits: ConnectionLimits) -> (SocketAddr, tokio::sync::oneshot::Sender<()>) {
    let root = std::env::temp_dir().join(format!("dray-dashboard-conns-{}", std::process::id()));
    std::fs::create_dir_all(&root).expect("scene root");
    let coordinator = Coordinator::new(&root, 1).expect("coordinator");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("address");
    let d = Dashboard::new(coordinator, None).expect("dashboard");
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(async move {
        serve(listener, d, limits, async move {
            let _ = stopped.await;
        })
        .await
        .expect("the dashboard serves");
    });
    (addr, stop)
}

/// A connection to `addr` from `from`.
async fn connect_from(from: IpAddr, addr: SocketAddr) -> TcpStream {
    let socket = TcpSocket::new_v4().expect("socket");
    socket
        .bind(SocketAddr::new(from, 0))
        .expect("bind the source address");
    socket.connect(addr).await.expect("connect")
}

/// Open `n` sockets from `from` that never send a byte; each comes back on the channel
/// when the server has closed it.
async fn idle_sockets(
    from: IpAddr,
    addr: SocketAddr,
    n: usize,
) -> mpsc::UnboundedReceiver<TcpStream> {
    let (tx, rx) = mpsc::unbounded_channel();
    for _ in 0..n {
        let mut s = connect_from(from, addr).await;
        let tx = tx.clone();
        tokio::spawn(async move {
            let mut buf = [0u8; 256];
            while let Ok(k) = s.read(&mut buf).await {
                if k == 0 {
                    break;
                }
            }
            let _ = tx.send(s);
        });
    }
    rx
}

/// GET /api/session from `from`: the status line, or what went wrong.
async fn session_from(from: IpAddr, addr: SocketAddr) -> Result<String, String> {
    let mut s = connect_from(from, addr).await;
    s.write_all(b"GET /api/session HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        .await
        .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    tokio::time::timeout(SAFETY, s.read_to_end(&mut out))
        .await
        .map_err(|_| "no answer (safety deadline)".to_string())?
        .map_err(|e| e.to_string())?;
    let text = String::from_utf8_lossy(&out);
    text.lines()
        .next()
        .map(str::to_string)
        .ok_or_else(|| "closed without an answer".to_string())
}

fn limits(max_connections: usize, max_per_address: usize, handshake: Duration) -> ConnectionLimits {
    ConnectionLimits {
        max_connections,
        max_per_address,
        handshake_timeout: handshake,
        idle_timeout: None,
        emulate: None,
    }
}

/// 40 silent sockets from 127.0.0.1 against 32 places per address and 40 in all: the
/// 8 beyond its 32 are closed at once, another from it too, and 127.0.0.2 is answered
/// every time.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_the_dashboards_every_place() {
    let (addr, _stop) = dashboard(limits(40, 32, Duration::from_secs(600))).await;
    let here: IpAddr = "127.0.0.1".parse().expect("ip");
    let other: IpAddr = "127.0.0.2".parse().expect("ip");
    let mut rx = idle_sockets(here, addr, 40).await;
    for k in 0..8 {
        tokio::time::timeout(SAFETY, rx.recv())
            .await
            .unwrap_or_else(|_| panic!("{k} of the 8 sockets beyond 32 closed (safety deadline)"))
            .expect("open channel");
    }
    for probe in 0..8 {
        let answer = session_from(other, addr).await;
        assert!(
            answer
                .as_deref()
                .is_ok_and(|l| l.starts_with("HTTP/1.1 200")),
            "probe {probe} from another address: {answer:?}"
        );
    }
    assert!(
        session_from(here, addr).await.is_err(),
        "the address holding its 32 places gets no 33rd"
    );
}

/// A client that sends its request head a header at a time, never ending it, is closed
/// once the head has taken longer than the handshake timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_request_head_is_closed() {
    let (addr, _stop) = dashboard(limits(40, 32, Duration::from_secs(1))).await;
    let mut s = TcpStream::connect(addr).await.expect("connect");
    s.write_all(b"GET /api/session HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        .await
        .expect("the start of a head");
    let closed = tokio::time::timeout(SAFETY, async {
        let mut buf = [0u8; 256];
        loop {
            if s.write_all(b"X-Slow: 1\r\n").await.is_err() {
                return;
            }
            match tokio::time::timeout(Duration::from_millis(300), s.read(&mut buf)).await {
                Ok(Ok(0)) | Ok(Err(_)) => return,
                // An answer (408 or 400) comes before the close.
                Ok(Ok(_)) | Err(_) => {}
            }
        }
    })
    .await;
    assert!(
        closed.is_ok(),
        "the slow head was still open after {SAFETY:?}"
    );
}
