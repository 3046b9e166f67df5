//! The ray stream end to end: a real tonic server on 127.0.0.1:0 and a real client.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use dray_core::integrator::RayKind;
use dray_core::ray::FLAG_TICKETED;
use dray_core::ray::RayRecord;
use dray_proto::v1::{RayBatch, RayStreamRequest, RayTicket, ray_stream_request};
use dray_worker::{
    BatchKey, PeerClientConfig, PeerError, PeerSender, PeerServer, PeerServerConfig, QueueKey,
    RayQueues,
};
use glam::Vec3;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::transport::{Endpoint, Server};

/// Aborts the task on drop, so a failing test still stops its server or sender.
struct AbortOnDrop<T>(JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn start_server(
    queues: Arc<RayQueues>,
    config: PeerServerConfig,
) -> (dray_net::AuthChannel, AbortOnDrop<()>) {
    serve(PeerServer::new(queues, config)).await
}

async fn serve(peer_server: PeerServer) -> (dray_net::AuthChannel, AbortOnDrop<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("local addr");
    let service = peer_server.into_service();
    let server = AbortOnDrop(tokio::spawn(async move {
        let _ = Server::builder()
            .add_service(service)
            .serve_with_incoming(TcpListenerStream::new(listener))
            .await;
    }));
    let channel = Endpoint::from_shared(format!("http://{addr}"))
        .expect("endpoint")
        .connect()
        .await
        .expect("connect");
    (dray_net::ClientOptions::plain().wrap(channel), server)
}

/// SplitMix64, so the rays are varied but reproducible.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn finite(&mut self) -> f32 {
        loop {
            let f = f32::from_bits(self.next() as u32);
            if f.is_finite() {
                return f;
            }
        }
    }
    fn vec3(&mut self) -> Vec3 {
        Vec3::new(self.finite(), self.finite(), self.finite())
    }
}

fn rays(n: usize, seed: u64, ticket_every: usize) -> Vec<RayRecord> {
    let mut rng = Rng(seed);
    (0..n)
        .map(|i| RayRecord {
            credit: dray_core::credit::Credit::from_wire(rng.next()),
            origin: rng.vec3(),
            dir: rng.vec3(),
            tmax: if i % 3 == 0 {
                f32::INFINITY
            } else {
                rng.finite()
            },
            weight: rng.vec3(),
            bsdf_pdf: rng.finite(),
            pixel: rng.next() as u32,
            sample: rng.next() as u32,
            depth: rng.next() as u16 & dray_core::ray::MAX_RECORD_DEPTH,
            kind: RayKind::ALL[(rng.next() % RayKind::COUNT as u64) as usize],
            flags: if ticket_every > 0 && i % ticket_every == 0 {
                FLAG_TICKETED
            } else {
                0
            },
        })
        .collect()
}

fn key(domain: u32) -> BatchKey {
    BatchKey {
        job_id: "job-1".into(),
        domain,
        routing_version: 3,
        attempt: 0,
        forwards: 0,
    }
}

fn qk(domain: u32) -> QueueKey {
    QueueKey {
        job_id: "job-1".into(),
        attempt: 0,
        domain,
    }
}

const LIMIT: Duration = Duration::from_secs(10);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rays_arrive_bit_exact_in_their_domain_queues() {
    tokio::time::timeout(LIMIT, async {
        let queues = Arc::new(RayQueues::new(100_000));
        let (channel, _server) =
            start_server(Arc::clone(&queues), PeerServerConfig::default()).await;
        let config = PeerClientConfig {
            sender_id: "w0".into(),
            batch_rays: 500,
            ..PeerClientConfig::default()
        };
        let mut sender = PeerSender::open(channel, config).await.expect("open");
        let to3 = rays(2000, 1, 7);
        let to7 = rays(1500, 2, 0);
        // Interleave the two destinations in uneven chunks (16 chunks each).
        assert_eq!(to3.chunks(130).len(), to7.chunks(97).len());
        let mut ticket = 0u64;
        for (c3, c7) in to3.chunks(130).zip(to7.chunks(97)) {
            let tickets: Vec<RayTicket> = c3
                .iter()
                .enumerate()
                .filter(|(_, r)| r.flags & FLAG_TICKETED != 0)
                .map(|(i, _)| {
                    ticket += 1;
                    RayTicket {
                        record: i as u32,
                        ticket,
                    }
                })
                .collect();
            sender.send(&key(3), c3, &tickets).await.expect("send 3");
            sender.send(&key(7), c7, &[]).await.expect("send 7");
        }
        sender.close().await.expect("close");

        assert_eq!(queues.job_lengths("job-1", 0), vec![(3, 2000), (7, 1500)]);
        for (domain, sent) in [(3u32, &to3), (7, &to7)] {
            let mut got = Vec::new();
            let mut got_tickets = Vec::new();
            while let Some(b) = queues.pop(&qk(domain)) {
                assert_eq!(&*b.job_id, "job-1");
                assert_eq!(b.routing_version, 3);
                for t in &b.tickets {
                    let r = &b.rays[t.record as usize];
                    assert!(r.flags & FLAG_TICKETED != 0);
                    got_tickets.push(t.ticket);
                }
                got.extend(b.rays);
            }
            assert_eq!(got.len(), sent.len(), "domain {domain}");
            for (a, b) in sent.iter().zip(&got) {
                assert_eq!(a.to_bytes(), b.to_bytes(), "domain {domain}");
            }
            if domain == 3 {
                let expected: Vec<u64> = (1..=ticket).collect();
                assert_eq!(got_tickets, expected);
            }
        }
        assert!(queues.is_empty());
    })
    .await
    .expect("test timed out");
}

/// A registered worker accepts a stream only from the sender its pass was made for:
/// holding the cluster token and naming another worker is not enough.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_needs_the_senders_pass() {
    {
        let secret = "receiver-member-secret-0123456789";
        let queues = Arc::new(RayQueues::new(100_000));
        let server = PeerServer::new(Arc::clone(&queues), PeerServerConfig::default());
        server.set_member_secret(secret);
        let (channel, _server) = serve(server).await;
        let open = |sender: &str, pass: String| PeerClientConfig {
            sender_id: sender.into(),
            sender_pass: pass,
            ..PeerClientConfig::default()
        };
        let good = dray_net::peer_pass::peer_pass(secret, "w0");
        let refused = [
            ("no pass", open("w0", String::new())),
            ("another sender's pass", open("w1", good.clone())),
            (
                "a pass for another receiver",
                open(
                    "w0",
                    dray_net::peer_pass::peer_pass("other-secret-0123456789", "w0"),
                ),
            ),
        ];
        for (what, config) in refused {
            match PeerSender::open(channel.clone(), config).await {
                Err(PeerError::Status(s)) => {
                    assert_eq!(s.code(), tonic::Code::PermissionDenied, "{what}: {s:?}")
                }
                Err(e) => panic!("{what}: {e:?}"),
                Ok(_) => panic!("{what}: the stream was accepted"),
            }
        }
        let mut sender = PeerSender::open(channel, open("w0", good))
            .await
            .expect("the sender's own pass opens the stream");
        sender
            .send(&key(3), &rays(10, 5, 0), &[])
            .await
            .expect("send");
        sender.close().await.expect("close");
        assert_eq!(queues.job_lengths("job-1", 0), vec![(3, 10)]);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_queue_stalls_the_sender_until_drained() {
    tokio::time::timeout(LIMIT, async {
        const CAPACITY: usize = 256;
        const TOTAL: usize = 4000;
        let queues = Arc::new(RayQueues::new(CAPACITY));
        let (channel, _server) =
            start_server(Arc::clone(&queues), PeerServerConfig::default()).await;
        let config = PeerClientConfig {
            batch_rays: 64,
            ..PeerClientConfig::default()
        };
        let mut sender = PeerSender::open(channel, config).await.expect("open");
        let window = sender.rays_granted();
        assert_eq!(
            window, CAPACITY as u64,
            "window is clamped to the queue capacity"
        );
        let all = rays(TOTAL, 5, 0);
        let progress = Arc::new(AtomicU64::new(0));
        let sending = {
            let all = all.clone();
            let progress = Arc::clone(&progress);
            AbortOnDrop(tokio::spawn(async move {
                for chunk in all.chunks(50) {
                    sender.send(&key(0), chunk, &[]).await?;
                    progress.store(sender.rays_sent(), Ordering::SeqCst);
                }
                sender.close().await?;
                Ok::<(), PeerError>(())
            }))
        };

        // Nobody drains: the sender must stop within one window past the queue.
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(
            !sending.0.is_finished(),
            "sender finished despite a full queue"
        );
        let sent = progress.load(Ordering::SeqCst);
        assert!(
            sent <= (CAPACITY as u64) + window,
            "sender sent {sent} rays beyond its grant"
        );
        assert_eq!(queues.len(&qk(0)), CAPACITY);

        // Drain slowly; the rest arrives, and the queue never exceeds its capacity.
        let mut got = Vec::new();
        while got.len() < TOTAL {
            assert!(queues.len(&qk(0)) <= CAPACITY);
            match queues.pop(&qk(0)) {
                Some(b) => got.extend(b.rays),
                None => tokio::time::sleep(Duration::from_millis(1)).await,
            }
        }
        let mut sending = sending;
        let done = tokio::time::timeout(Duration::from_secs(5), &mut sending.0)
            .await
            .expect("sender finished");
        done.expect("sender task").expect("sender ok");
        assert_eq!(got.len(), TOTAL);
        for (a, b) in all.iter().zip(&got) {
            assert_eq!(a.to_bytes(), b.to_bytes());
        }
    })
    .await
    .expect("test timed out");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_batch_is_refused_and_the_server_keeps_serving() {
    tokio::time::timeout(LIMIT, async {
        let queues = Arc::new(RayQueues::new(10_000));
        let (channel, _server) =
            start_server(Arc::clone(&queues), PeerServerConfig::default()).await;

        // One record and 36 bytes of a second, in a batch that says it holds two.
        let mut bad = PeerSender::open(channel.clone(), PeerClientConfig::default())
            .await
            .expect("open");
        let mut records = Vec::new();
        dray_core::ray::encode_rays(&rays(1, 9, 0), &mut records);
        records.extend_from_slice(&[0u8; 36]);
        bad.send_raw(RayStreamRequest {
            msg: Some(ray_stream_request::Msg::Batch(RayBatch {
                job_id: "job-1".into(),
                domain: 1,
                routing_version: 1,
                sequence: 1,
                count: 2,
                records,
                tickets: Vec::new(),
                forwards: 0,
                attempt: 0,
            })),
        })
        .await
        .expect("send raw");
        match bad.closed().await {
            Err(PeerError::Status(s)) => {
                assert_eq!(s.code(), tonic::Code::InvalidArgument, "{s:?}");
                assert!(
                    s.message().contains("ends inside record 1 (truncated)"),
                    "{}",
                    s.message()
                );
            }
            other => panic!("expected an error status, got {other:?}"),
        }

        // A batch for any domain is taken: a domain this worker does not own is
        // forwarded by the tracing side, not refused by the stream.
        let mut stray = PeerSender::open(channel.clone(), PeerClientConfig::default())
            .await
            .expect("open");
        stray
            .send(&key(42), &rays(3, 10, 0), &[])
            .await
            .expect("buffer");
        stray.close().await.expect("close");
        assert_eq!(queues.len(&qk(42)), 3);
        assert_eq!(queues.drop_job("job-1", 0), 3);
        assert!(queues.is_empty());

        // The server still serves a well-formed stream on the same connection.
        let good = rays(300, 11, 0);
        let mut sender = PeerSender::open(channel, PeerClientConfig::default())
            .await
            .expect("open");
        sender.send(&key(1), &good, &[]).await.expect("send");
        sender.close().await.expect("close");
        assert_eq!(queues.len(&qk(1)), 300);
    })
    .await
    .expect("test timed out");
}

/// The engine's record and the protocol's numbers describe the same wire format.
#[test]
fn the_record_is_the_protocols_record() {
    assert_eq!(
        dray_core::ray::RAY_RECORD_MAX_BYTES,
        dray_proto::RAY_RECORD_MAX_BYTES
    );
    assert_eq!(
        dray_core::ray::RAY_RECORD_FORMAT,
        dray_proto::RAY_RECORD_FORMAT
    );
    let mut bytes = Vec::new();
    dray_core::ray::encode_rays(&rays(3, 1, 0), &mut bytes);
    assert!(bytes.len() <= 3 * dray_proto::RAY_RECORD_MAX_BYTES);
    assert_eq!(
        dray_core::ray::decode_rays(&bytes, 3)
            .expect("decodes")
            .len(),
        3
    );
}
