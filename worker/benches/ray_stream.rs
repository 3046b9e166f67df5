//! One ray stream on loopback, encode to decode (issue 3's benchmark; target at least
//! 5 million rays per second): the client packs rays into records (32 to 64 bytes) and batches,
//! streams them over real gRPC on 127.0.0.1, the server decodes them into a domain queue,
//! and a task drains the queue. Each iteration sends `RAYS` rays and waits until the
//! receiver has acknowledged them all (queued), so credit-based flow control is included.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use dray_core::integrator::RayKind;
use dray_core::ray::RayRecord;
use dray_proto::v1::{RayBatch, RayStreamRequest, ray_stream_request};
use dray_worker::{
    BatchKey, PeerClientConfig, PeerSender, PeerServer, PeerServerConfig, RayQueues,
};
use glam::Vec3;
use prost::Message;
use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::transport::{Endpoint, Server};

const RAYS: usize = 1 << 20;
const BATCH_RAYS: usize = 4096;
const WINDOW: u64 = 64 * 1024;
const HTTP2_WINDOW: u32 = 8 << 20;

fn rays(n: usize) -> Vec<RayRecord> {
    (0..n)
        .map(|i| {
            let f = i as f32;
            RayRecord {
                credit: dray_core::credit::Credit::from_wire(i as u64 * 7919),
                origin: Vec3::new(f, f * 0.5, -f),
                dir: Vec3::new(0.3, -0.4, 0.866),
                tmax: f32::INFINITY,
                weight: Vec3::new(0.5, 0.25, 0.125),
                bsdf_pdf: 0.25,
                pixel: i as u32,
                sample: (i % 64) as u32,
                depth: (i % 8) as u16,
                kind: RayKind::ALL[i % RayKind::COUNT],
                flags: 0,
            }
        })
        .collect()
}

fn ray_stream(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let queues = Arc::new(RayQueues::new(4 * WINDOW as usize));
    let drained = Arc::new(AtomicU64::new(0));
    let (mut sender, server, drainer) = rt.block_on(async {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let service = PeerServer::new(
            Arc::clone(&queues),
            PeerServerConfig {
                worker_id: "bench".into(),
                stream_window: WINDOW,
            },
        )
        .into_service();
        let server = tokio::spawn(
            Server::builder()
                .tcp_nodelay(true)
                .initial_stream_window_size(HTTP2_WINDOW)
                .initial_connection_window_size(HTTP2_WINDOW)
                .add_service(service)
                .serve_with_incoming(TcpListenerStream::new(listener)),
        );
        let drainer = {
            let queues = Arc::clone(&queues);
            let drained = Arc::clone(&drained);
            tokio::spawn(async move {
                loop {
                    let (_, batch) = queues.pop_any().await;
                    drained.fetch_add(batch.rays.len() as u64, Ordering::Relaxed);
                }
            })
        };
        let channel = Endpoint::from_shared(format!("http://{addr}"))
            .expect("endpoint")
            .tcp_nodelay(true)
            .initial_stream_window_size(HTTP2_WINDOW)
            .initial_connection_window_size(HTTP2_WINDOW)
            .connect()
            .await
            .expect("connect");
        let sender = PeerSender::open(
            dray_net::ClientOptions::plain().wrap(channel),
            PeerClientConfig {
                sender_id: "bench-client".into(),
                receiver_id: "bench".into(),
                batch_rays: BATCH_RAYS,
                max_delay: Duration::from_millis(2),
                // The bench's server has no member secret: no pass is asked for.
                sender_pass: String::new(),
            },
        )
        .await
        .expect("open");
        (sender, server, drainer)
    });
    let input = rays(RAYS);
    let key = BatchKey {
        job_id: "bench-job".into(),
        domain: 0,
        routing_version: 1,
        attempt: 0,
        forwards: 0,
    };

    let mut group = c.benchmark_group("ray_stream");
    group.throughput(Throughput::Elements(RAYS as u64));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(8));
    group.bench_function("loopback_encode_stream_decode", |b| {
        b.iter_custom(|iters| {
            rt.block_on(async {
                let start = Instant::now();
                for _ in 0..iters {
                    // Hand rays over in tracer-sized chunks, as a worker would.
                    for chunk in input.chunks(1024) {
                        sender.send(&key, chunk, &[]).await.expect("send");
                    }
                    sender.drain().await.expect("drain");
                }
                start.elapsed()
            })
        });
    });
    group.finish();

    // Bytes per ray on the wire: the records plus the protobuf header of a full batch
    // and gRPC's 5-byte message prefix (HTTP/2 frame headers not counted).
    let mut records = Vec::new();
    dray_core::ray::encode_rays(&input[..BATCH_RAYS], &mut records);
    let message = RayStreamRequest {
        msg: Some(ray_stream_request::Msg::Batch(RayBatch {
            job_id: key.job_id.clone(),
            domain: key.domain,
            routing_version: key.routing_version,
            sequence: sender.rays_sent() / BATCH_RAYS as u64,
            count: BATCH_RAYS as u32,
            records,
            tickets: Vec::new(),
            forwards: 0,
            attempt: 0,
        })),
    };
    let wire = message.encoded_len() + 5;
    eprintln!(
        "ray_stream: {} rays sent, {} drained; batch of {BATCH_RAYS} rays = {wire} bytes \
         on the wire ({} header), {:.4} bytes per ray",
        sender.rays_sent(),
        drained.load(Ordering::Relaxed),
        wire - dray_core::ray::encoded_len(&input[..BATCH_RAYS]),
        wire as f64 / BATCH_RAYS as f64,
    );
    drop(sender);
    drainer.abort();
    server.abort();
}

criterion_group!(benches, ray_stream);
criterion_main!(benches);
