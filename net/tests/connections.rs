//! docs/security.md "Hardening, second round", item 4, against a real server on loopback:
//! sockets that never speak cannot
//! exhaust the server's descriptors: beyond the connection limit they are closed at
//! once, and the others are closed after the handshake (or idle) timeout.

mod support;

use std::time::Duration;

use dray_net::ServerOptions;
use support::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::mpsc;

fn open_descriptors() -> usize {
    std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count())
}

/// Open `n` sockets that never send a byte; each comes back on the channel (still
/// open on this side) when the server has closed it.
async fn idle_sockets(addr: std::net::SocketAddr, n: usize) -> mpsc::UnboundedReceiver<TcpStream> {
    let (tx, rx) = mpsc::unbounded_channel();
    for _ in 0..n {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        let tx = tx.clone();
        tokio::spawn(async move {
            let mut buf = [0u8; 1024];
            // The server may send its SETTINGS and PINGs: read until it closes.
            loop {
                match s.read(&mut buf).await {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {}
                }
            }
            let _ = tx.send(s);
        });
    }
    rx
}

async fn closed(rx: &mut mpsc::UnboundedReceiver<TcpStream>, n: usize) -> Vec<TcpStream> {
    let mut done = Vec::new();
    while done.len() < n {
        let s = tokio::time::timeout(Duration::from_secs(60), rx.recv())
            .await
            .unwrap_or_else(|_| {
                panic!(
                    "{} of {n} sockets closed by the server (safety deadline)",
                    done.len()
                )
            })
            .expect("open channel");
        done.push(s);
    }
    done
}

/// 200 silent sockets against a limit of 16: the 184 beyond it are closed at once, and
/// the server holds at most 16 descriptors for them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sockets_beyond_the_limit_are_closed_at_once() {
    let limit = 16;
    let n = 200;
    let server = start(ServerOptions {
        max_connections: limit,
        handshake_timeout: Duration::from_secs(600),
        ..ServerOptions::default()
    })
    .await;
    let before = open_descriptors();
    let mut rx = idle_sockets(server.addr, n).await;
    let _closed = closed(&mut rx, n - limit).await;
    // This process holds the 200 client sockets; the server's side of them is at most
    // the limit (plus a little slack for the runtime's own descriptors).
    let now = open_descriptors();
    assert!(
        now <= before + n + limit + 8,
        "{now} descriptors open, {before} before {n} sockets against a limit of {limit}"
    );
}

/// One address cannot lock the others out (issue 38): 40 silent sockets from
/// 127.0.0.1 against 32 places per address and 40 in all; the 8 beyond its 32 are
/// closed at once, and health from 127.0.0.2 answers every probe.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_every_place() {
    let server = start(ServerOptions {
        max_connections: 40,
        max_connections_per_address: 32,
        handshake_timeout: Duration::from_secs(600),
        ..ServerOptions::default()
    })
    .await;
    let mut rx = idle_sockets(server.addr, 40).await;
    let _closed = closed(&mut rx, 8).await;
    let other = Some("127.0.0.2".parse().expect("address"));
    for probe in 0..8 {
        assert_eq!(
            health_from(server.addr, other).await,
            Ok(SERVING),
            "probe {probe} from another address"
        );
    }
}

/// Silent sockets (and one that sends half a preface) are closed after the handshake
/// timeout; the server then answers health checks.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_sockets_are_closed_after_the_handshake_timeout() {
    let n = 100;
    let server = start(ServerOptions {
        max_connections: 16,
        handshake_timeout: Duration::from_secs(1),
        ..ServerOptions::default()
    })
    .await;
    let mut rx = idle_sockets(server.addr, n).await;
    let mut half = TcpStream::connect(server.addr).await.expect("connect");
    half.write_all(b"PRI * HTTP/2.0\r\n").await.expect("write");
    let _closed = closed(&mut rx, n).await;
    let mut buf = [0u8; 256];
    let mut ended = false;
    for _ in 0..1000 {
        match tokio::time::timeout(Duration::from_secs(60), half.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => {
                ended = true;
                break;
            }
            Ok(Ok(_)) => {}
            Err(_) => break,
        }
    }
    assert!(
        ended,
        "a half preface is closed after the handshake timeout"
    );
    assert!(
        eventually(30.0, || async { health(server.addr).await == Ok(SERVING) }).await,
        "health answers once the silent sockets are gone"
    );
}

/// A peer that completes the HTTP/2 preface and then neither sends nor answers PINGs
/// is closed (keep-alive, and the idle timeout behind it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_that_goes_quiet_after_the_preface_is_closed() {
    let server = start(ServerOptions {
        keepalive_interval: Some(Duration::from_secs(1)),
        keepalive_timeout: Duration::from_secs(1),
        idle_timeout: Duration::from_secs(3),
        ..ServerOptions::default()
    })
    .await;
    let mut s = TcpStream::connect(server.addr).await.expect("connect");
    s.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
        .await
        .expect("preface");
    // An empty SETTINGS frame.
    s.write_all(&[0, 0, 0, 4, 0, 0, 0, 0, 0])
        .await
        .expect("settings");
    let mut buf = [0u8; 256];
    let mut ended = false;
    for _ in 0..1000 {
        match tokio::time::timeout(Duration::from_secs(60), s.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => {
                ended = true;
                break;
            }
            Ok(Ok(_)) => {}
            Err(_) => break,
        }
    }
    assert!(ended, "the quiet connection is closed");
    assert_eq!(health(server.addr).await, Ok(SERVING));
}
