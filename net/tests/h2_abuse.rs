//! docs/security.md "Hardening, second round": HTTP/2 abuse the server stack (hyper and h2
//! under tonic) must survive, on
//! loopback and bounded in count: rapid reset, CONTINUATION flood, SETTINGS flood and
//! PING flood. After each, a health check on a new connection answers SERVING and
//! admission places are not leaked.
//!
//! What the stack does with each (asserted below):
//! - rapid reset: streams reset by the client free their admission places (hyper drops
//!   the call when its stream is reset), and h2 closes the connection with GOAWAY
//!   ENHANCE_YOUR_CALM once too many streams were reset before they were served;
//! - CONTINUATION flood: h2 counts CONTINUATION frames against the header list limit
//!   and closes the connection (GOAWAY ENHANCE_YOUR_CALM);
//! - a flood of empty DATA frames: h2 closes the connection (too_many_data_frames);
//! - SETTINGS and PING floods: not refused, but bounded: h2 answers each before it reads
//!   the next frame, so a client that does not read its answers stops being read
//!   (TCP backpressure); nothing queues on the server.

mod support;

use std::time::Duration;

use dray_net::ServerOptions;
use support::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const GET_JOB: &str = "/dray.v1.RenderService/GetJob";
const PREFACE: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";
const FRAMES: usize = 10_000;

const DATA: u8 = 0;
const HEADERS: u8 = 1;
const SETTINGS: u8 = 4;
const PING: u8 = 6;
const RST_STREAM: u8 = 3;
const GOAWAY: u8 = 7;
const CONTINUATION: u8 = 9;

/// One HTTP/2 frame: length (24 bits), type, flags, stream id (31 bits), payload.
fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
    let len = payload.len() as u32;
    let mut f = vec![(len >> 16) as u8, (len >> 8) as u8, len as u8, kind, flags];
    f.extend_from_slice(&(stream & 0x7fff_ffff).to_be_bytes());
    f.extend_from_slice(payload);
    f
}

/// Read frames from `s` until the server closes it; whether a GOAWAY came first.
/// `None` if the connection was still open after the safety deadline.
async fn until_closed(mut s: tokio::net::tcp::OwnedReadHalf) -> Option<bool> {
    let mut goaway = false;
    let mut pending = Vec::new();
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = match tokio::time::timeout(Duration::from_secs(60), s.read(&mut buf)).await {
            Err(_) => return None,
            Ok(Ok(0)) | Ok(Err(_)) => return Some(goaway),
            Ok(Ok(n)) => n,
        };
        pending.extend_from_slice(&buf[..n]);
        while pending.len() >= 9 {
            let len = (usize::from(pending[0]) << 16)
                | (usize::from(pending[1]) << 8)
                | usize::from(pending[2]);
            if pending.len() < 9 + len {
                break;
            }
            if pending[3] == GOAWAY {
                goaway = true;
            }
            pending.drain(..9 + len);
        }
    }
}

fn options() -> ServerOptions {
    ServerOptions {
        max_calls: 8,
        ..ServerOptions::default()
    }
}

async fn healthy(addr: std::net::SocketAddr) {
    assert!(
        eventually(30.0, || async { health(addr).await == Ok(SERVING) }).await,
        "health answers SERVING on a new connection"
    );
    let mut c = h2_connect(addr).await;
    assert_eq!(
        unary(&mut c, addr, GET_JOB).await,
        Some(0),
        "an API call is admitted"
    );
}

/// A header block for a call to `path` (:method POST, :scheme http, :path literal).
fn header_block(path: &str) -> Vec<u8> {
    let mut block = vec![0x83, 0x86, 0x04, path.len() as u8];
    block.extend_from_slice(path.as_bytes());
    block
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rapid_reset_leaks_no_places() {
    let server = start(options()).await;
    let s = TcpStream::connect(server.addr).await.expect("connect");
    let (read, mut write) = s.into_split();
    let reader = tokio::spawn(until_closed(read));
    write.write_all(PREFACE).await.expect("preface");
    write
        .write_all(&frame(SETTINGS, 0, 0, &[]))
        .await
        .expect("settings");
    let block = header_block(GET_JOB);
    let mut written = 0;
    for i in 0..FRAMES as u32 / 2 {
        let stream = 2 * i + 1;
        // HEADERS (END_HEADERS, no END_STREAM), then RST_STREAM CANCEL at once.
        let mut pair = frame(HEADERS, 0x4, stream, &block);
        pair.extend(frame(RST_STREAM, 0, stream, &[0, 0, 0, 8]));
        if write.write_all(&pair).await.is_err() {
            break;
        }
        written += 2;
    }
    drop(write);
    let outcome = reader.await.expect("reader");
    eprintln!("rapid reset: {written} frames written; closed: {outcome:?}");
    assert_eq!(
        outcome,
        Some(true),
        "the connection is closed with a GOAWAY"
    );
    // With 8 places, one leaked place per reset stream would refuse every call now.
    healthy(server.addr).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn continuation_flood_is_refused_with_goaway() {
    let server = start(options()).await;
    let s = TcpStream::connect(server.addr).await.expect("connect");
    let (read, mut write) = s.into_split();
    let reader = tokio::spawn(until_closed(read));
    write.write_all(PREFACE).await.expect("preface");
    write
        .write_all(&frame(SETTINGS, 0, 0, &[]))
        .await
        .expect("settings");
    // HEADERS without END_HEADERS (:method POST, :scheme http, :path /), then
    // CONTINUATION frames that never end the block, each a literal header field.
    write
        .write_all(&frame(HEADERS, 0, 1, &[0x83, 0x86, 0x84]))
        .await
        .expect("headers");
    let mut field = vec![0x00, 7];
    field.extend_from_slice(b"x-flood");
    field.push(100);
    field.extend_from_slice(&[b'a'; 100]);
    let continuation = frame(CONTINUATION, 0, 1, &field);
    let mut written = 0;
    for _ in 0..FRAMES {
        if write.write_all(&continuation).await.is_err() {
            break;
        }
        written += 1;
    }
    let outcome = reader.await.expect("reader");
    eprintln!("CONTINUATION flood: {written} frames written; closed: {outcome:?}");
    assert_eq!(
        outcome,
        Some(true),
        "the connection is closed with a GOAWAY"
    );
    healthy(server.addr).await;
}

/// A flood of `kind` frames on stream 0 from a client that never reads the answers.
async fn flood_unread(kind: u8, payload: &[u8]) {
    let server = start(options()).await;
    let mut s = TcpStream::connect(server.addr).await.expect("connect");
    s.write_all(PREFACE).await.expect("preface");
    s.write_all(&frame(SETTINGS, 0, 0, &[]))
        .await
        .expect("settings");
    let one = frame(kind, 0, 0, payload);
    let writer = tokio::spawn(async move {
        let mut written = 0;
        for _ in 0..FRAMES {
            if s.write_all(&one).await.is_err() {
                break;
            }
            written += 1;
        }
        (written, s)
    });
    // While the flood runs (or is held back by backpressure), the server serves others.
    healthy(server.addr).await;
    match tokio::time::timeout(Duration::from_secs(30), writer).await {
        Ok(Ok((written, _s))) => eprintln!("flood of type {kind}: {written} frames written"),
        Ok(Err(e)) => panic!("writer: {e}"),
        Err(_) => eprintln!("flood of type {kind}: the server stopped reading (backpressure)"),
    }
    healthy(server.addr).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn settings_flood_is_bounded() {
    // SETTINGS_MAX_CONCURRENT_STREAMS = 100.
    flood_unread(SETTINGS, &[0, 3, 0, 0, 0, 100]).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ping_flood_is_bounded() {
    flood_unread(PING, &[1, 2, 3, 4, 5, 6, 7, 8]).await;
}

/// Many tiny DATA frames on one stream: h2 refuses them past a bound
/// (too_many_data_frames) rather than doing work per frame forever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn empty_data_frame_flood_is_refused() {
    let server = start(options()).await;
    let s = TcpStream::connect(server.addr).await.expect("connect");
    let (read, mut write) = s.into_split();
    let reader = tokio::spawn(until_closed(read));
    write.write_all(PREFACE).await.expect("preface");
    write
        .write_all(&frame(SETTINGS, 0, 0, &[]))
        .await
        .expect("settings");
    // A complete header block (END_HEADERS) for a ClusterService call, then empty DATA.
    let mut block = vec![0x83, 0x86];
    // :path, literal without indexing, indexed name 4.
    let path = b"/dray.v1.ClusterService/Heartbeat";
    block.push(0x04);
    block.push(path.len() as u8);
    block.extend_from_slice(path);
    write
        .write_all(&frame(HEADERS, 0x4, 1, &block))
        .await
        .expect("headers");
    let empty = frame(DATA, 0, 1, &[]);
    let mut written = 0;
    for _ in 0..FRAMES {
        if write.write_all(&empty).await.is_err() {
            break;
        }
        written += 1;
    }
    drop(write);
    let outcome = reader.await.expect("reader");
    eprintln!("empty DATA flood: {written} frames written; closed: {outcome:?}");
    assert_eq!(
        outcome,
        Some(true),
        "the connection is closed with a GOAWAY"
    );
    healthy(server.addr).await;
}
