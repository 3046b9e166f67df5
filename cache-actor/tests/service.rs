//! The cache host over real gRPC on loopback: open walls, look rays up, return
//! tickets, hit, close with statistics, and refuse bad requests without going down.

use std::net::SocketAddr;

use dray_cache::{CacheHost, OPTION_ANSWER, OPTION_PHM, OPTION_TICKET};
use dray_core::credit::Credit;
use dray_core::film::FIXED_SCALE;
use dray_core::integrator::RayKind;
use dray_core::ray::{FLAG_COARSE, RayRecord, encode_rays};
use dray_core::wall::PhmBins;
use dray_proto::v1::cache_service_client::CacheServiceClient;
use dray_proto::v1::{
    CacheAnswers, CacheLookups, CacheRequest, CacheResponse, CloseWallsRequest, OpenWallsRequest,
    PhmMerge, PhmOutcomes, PhmSettings, PhmStats, RayCacheSettings, RayCacheStats, TicketAck,
    TicketReturn, TicketReturns, cache_request, cache_response,
};
use glam::Vec3;
use tokio::sync::{mpsc, oneshot};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Status, Streaming};

struct Server {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

async fn start() -> Server {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(async move {
        CacheHost::new()
            .serve(listener, async {
                let _ = stopped.await;
            })
            .await
            .unwrap();
    });
    Server {
        addr,
        stop: Some(stop),
        task,
    }
}

impl Server {
    async fn client(&self) -> CacheServiceClient<Channel> {
        CacheServiceClient::connect(format!("http://{}", self.addr))
            .await
            .unwrap()
            .max_decoding_message_size(dray_cache::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(dray_cache::MAX_MESSAGE_BYTES)
    }

    async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        self.task.await.unwrap();
    }
}

/// One Exchange stream, asked one message at a time.
struct Exchange {
    tx: mpsc::Sender<CacheRequest>,
    rx: Streaming<CacheResponse>,
}

impl Exchange {
    async fn open(client: &mut CacheServiceClient<Channel>) -> Exchange {
        let (tx, rx) = mpsc::channel(4);
        let rx = client
            .exchange(ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        Exchange { tx, rx }
    }

    async fn ask(&mut self, msg: Option<cache_request::Msg>) -> Result<CacheResponse, Status> {
        self.tx.send(CacheRequest { msg }).await.unwrap();
        match self.rx.message().await {
            Ok(Some(r)) => Ok(r),
            Ok(None) => Err(Status::unknown("stream ended")),
            Err(s) => Err(s),
        }
    }

    async fn lookup(&mut self, l: CacheLookups) -> Result<CacheAnswers, Status> {
        match self.ask(Some(cache_request::Msg::Lookups(l))).await?.msg {
            Some(cache_response::Msg::Answers(a)) => Ok(a),
            other => panic!("expected answers, got {other:?}"),
        }
    }

    async fn give_back(&mut self, r: TicketReturns) -> Result<TicketAck, Status> {
        match self.ask(Some(cache_request::Msg::Returns(r))).await?.msg {
            Some(cache_response::Msg::Ack(a)) => Ok(a),
            other => panic!("expected an ack, got {other:?}"),
        }
    }

    async fn merge(&mut self, m: PhmMerge) -> Result<TicketAck, Status> {
        match self.ask(Some(cache_request::Msg::Merge(m))).await?.msg {
            Some(cache_response::Msg::Ack(a)) => Ok(a),
            other => panic!("expected an ack, got {other:?}"),
        }
    }

    async fn report(&mut self, o: PhmOutcomes) -> Result<TicketAck, Status> {
        match self.ask(Some(cache_request::Msg::Outcomes(o))).await?.msg {
            Some(cache_response::Msg::Ack(a)) => Ok(a),
            other => panic!("expected an ack, got {other:?}"),
        }
    }
}

/// Scene [0,2]x[0,1]x[0,1] cut in two along x.
fn open_request(job: &str, attempt: u32, radius: f32, walls: Vec<u32>) -> OpenWallsRequest {
    OpenWallsRequest {
        job_id: job.into(),
        attempt,
        settings: Some(RayCacheSettings {
            radius,
            ..Default::default()
        }),
        scene_bounds: vec![0.0, 0.0, 0.0, 2.0, 1.0, 1.0],
        domain_bounds: vec![
            0.0, 0.0, 0.0, 1.0, 1.0, 1.0, //
            1.0, 0.0, 0.0, 2.0, 1.0, 1.0,
        ],
        walls,
        phm: None,
        replica: 0,
    }
}

/// A camera-like ray from outside the scene entering domain 0 through its -x face.
fn camera_ray() -> RayRecord {
    RayRecord {
        credit: Credit::from_wire(1000),
        origin: Vec3::new(-1.0, 0.5, 0.5),
        dir: Vec3::new(1.0, 0.1, -0.05),
        tmax: f32::INFINITY,
        weight: Vec3::new(0.5, 0.25, 0.75),
        bsdf_pdf: 0.0,
        pixel: 42,
        sample: 3,
        depth: 0,
        kind: RayKind::Camera,
        flags: 0,
    }
}

/// A diffuse ray inside domain 0 crossing into domain 1 (wall 6 = domain 1, -x).
fn inner_ray() -> RayRecord {
    RayRecord {
        credit: Credit::from_wire(77),
        origin: Vec3::new(0.5, 0.5, 0.5),
        dir: Vec3::new(1.0, 0.0, 0.2),
        weight: Vec3::splat(0.3),
        depth: 1,
        kind: RayKind::Diffuse,
        ..camera_ray()
    }
}

fn lookups(job: &str, attempt: u32, sequence: u64, rays: &[(RayRecord, u32, u32)]) -> CacheLookups {
    let mut records = Vec::new();
    encode_rays(&rays.iter().map(|r| r.0).collect::<Vec<_>>(), &mut records);
    CacheLookups {
        job_id: job.into(),
        attempt,
        sequence,
        count: rays.len() as u32,
        records,
        walls: rays.iter().map(|r| r.1).collect(),
        options: rays.iter().map(|r| r.2).collect(),
    }
}

fn ret(ticket: u64, rgb: [i64; 3], credit: u64) -> TicketReturn {
    TicketReturn {
        ticket,
        r: rgb[0],
        g: rgb[1],
        b: rgb[2],
        credit,
        tainted: false,
    }
}

const BOTH: u32 = OPTION_ANSWER | OPTION_TICKET;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tickets_fill_the_cache_and_later_rays_hit() {
    let server = start().await;
    let mut client = server.client().await;
    let all: Vec<u32> = (0..11).collect(); // every wall but 11 (domain 1, +z)
    let opened = client
        .open_walls(open_request("job", 1, 1e-6, all.clone()))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(opened.actors, 11);
    // Re-opening the same attempt is idempotent.
    let again = client
        .open_walls(open_request("job", 1, 1e-6, all))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(again.actors, 11);

    let mut ex = Exchange::open(&mut client).await;
    let cam = camera_ray();
    // First lookup: the store is empty, so a miss with a ticket; the inner ray gets one
    // too; a ray for a wall not served here, and one only asking, get plain misses.
    let a = ex
        .lookup(lookups(
            "job",
            1,
            1,
            &[
                (cam, 0, BOTH),
                (inner_ray(), 6, BOTH),
                (cam, 11, BOTH),
                (cam, 0, 0),
            ],
        ))
        .await
        .unwrap();
    assert_eq!(a.sequence, 1);
    assert_eq!(a.outcomes, vec![2, 2, 0, 0]);
    assert!(a.radiance.is_empty());
    assert_eq!(a.tickets.len(), 2);
    let (t_cam, t_inner) = (a.tickets[0], a.tickets[1]);
    assert_eq!(t_cam >> 32, 0);
    assert_eq!(t_inner >> 32, 6);

    // The camera ray's descendants hand back (3, 1, 0.5) x weight, in three parts.
    let sums = [3i64 << 24, 1 << 24, 1 << 23];
    let parts = [
        ret(t_cam, [sums[0] - 5, sums[1], 0], 400),
        ret(t_cam, [5, 0, sums[2] - 1], 100),
        ret(t_cam, [0, 0, 1], 500),
    ];
    let ack = ex
        .give_back(TicketReturns {
            job_id: "job".into(),
            attempt: 1,
            sequence: 2,
            returns: parts[..2].to_vec(),
        })
        .await
        .unwrap();
    assert_eq!(ack.sequence, 2);
    // Not whole yet: no hit.
    let a = ex
        .lookup(lookups("job", 1, 3, &[(cam, 0, OPTION_ANSWER)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0]);
    // The last part, plus strays: an unknown ticket, a wall not served, over-credit.
    let ack = ex
        .give_back(TicketReturns {
            job_id: "job".into(),
            attempt: 1,
            sequence: 4,
            returns: vec![
                parts[2],
                ret(12345, [1, 1, 1], 1),
                ret(dray_cache::ticket_id::ticket_id(0, 11, 1), [1, 1, 1], 1),
                ret(t_inner, [1, 1, 1], 78),
            ],
        })
        .await
        .unwrap();
    assert_eq!(ack.sequence, 4);

    // The same ray again: a hit, whose radiance is sum / weight exactly.
    let a = ex
        .lookup(lookups("job", 1, 5, &[(cam, 0, BOTH), (cam, 11, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![1, 0]);
    let w = cam.weight.to_array();
    let expected: Vec<f32> = (0..3)
        .map(|c| ((sums[c] as f64 / FIXED_SCALE) / f64::from(w[c])) as f32)
        .collect();
    assert_eq!(a.radiance, expected);
    assert_eq!(a.radiance, vec![6.0, 4.0, (0.5f64 / 0.75) as f32]);
    assert!(a.tickets.is_empty());

    // Slightly moved (beyond 1e-6 on the wall): a miss, but still within the angle.
    let mut moved = cam;
    moved.origin.y += 1e-4;
    let a = ex
        .lookup(lookups("job", 1, 6, &[(moved, 0, OPTION_ANSWER)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0]);

    // Lookups and returns for a job or attempt not open here: misses and acks.
    let a = ex
        .lookup(lookups("other", 1, 7, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!((a.sequence, a.outcomes), (7, vec![0]));
    let a = ex
        .lookup(lookups("job", 2, 8, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0]);
    let ack = ex
        .give_back(TicketReturns {
            job_id: "other".into(),
            attempt: 1,
            sequence: 9,
            returns: vec![ret(t_cam, [1, 1, 1], 1)],
        })
        .await
        .unwrap();
    assert_eq!(ack.sequence, 9);

    let stats = client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap();
    assert_eq!(
        stats,
        RayCacheStats {
            // Lookups 1 (ticket), 3 (partial), 5 (hit), 6 (moved) on wall 0; 1 on wall 6.
            outer_lookups: 4,
            outer_hits: 1,
            inner_lookups: 1,
            inner_hits: 0,
            tickets_opened: 2,
            tickets_closed: 1,
            tickets_stored: 1,
            tickets_open: 1,
            entries: 1,
            // The unknown ticket and the over-credit one (the wall not served here is
            // counted by the host, not by a wall).
            returns_rejected: 2,
            ..Default::default()
        }
    );
    // Closed: closing again is NOT_FOUND, lookups now miss.
    let e = client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 1,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let a = ex
        .lookup(lookups("job", 1, 10, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0]);
    drop(ex);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn radius_zero_never_hits() {
    let server = start().await;
    let mut client = server.client().await;
    client
        .open_walls(open_request("zero", 1, 0.0, vec![0]))
        .await
        .unwrap();
    let mut ex = Exchange::open(&mut client).await;
    let cam = camera_ray();
    let a = ex
        .lookup(lookups("zero", 1, 1, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![2]);
    ex.give_back(TicketReturns {
        job_id: "zero".into(),
        attempt: 1,
        sequence: 2,
        returns: vec![ret(a.tickets[0], [1 << 24; 3], cam.credit.to_wire())],
    })
    .await
    .unwrap();
    // Stored, yet the same ray misses again (and gets a new ticket).
    let a = ex
        .lookup(lookups("zero", 1, 3, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![2]);
    assert_eq!(a.tickets[0] & 0xffff_ffff, 2);
    let stats = client
        .close_walls(CloseWallsRequest {
            job_id: "zero".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap();
    assert_eq!((stats.outer_lookups, stats.outer_hits), (2, 0));
    assert_eq!((stats.tickets_stored, stats.tickets_open), (1, 1));
    drop(ex);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn attempts_replace_older_ones() {
    let server = start().await;
    let mut client = server.client().await;
    client
        .open_walls(open_request("job", 2, 0.1, vec![0]))
        .await
        .unwrap();
    let e = client
        .open_walls(open_request("job", 1, 0.1, vec![0]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    // Same attempt, different settings: refused.
    let e = client
        .open_walls(open_request("job", 2, 0.2, vec![0]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    // Same attempt, more walls: added.
    let r = client
        .open_walls(open_request("job", 2, 0.1, vec![0, 1, 6]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.actors, 3);
    let r = client
        .open_walls(open_request("job", 3, 0.1, vec![0, 1]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.actors, 2);
    let e = client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 2,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = client
        .close_walls(CloseWallsRequest {
            job_id: "nope".into(),
            attempt: 1,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 3,
        })
        .await
        .unwrap();
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_clean_errors_and_the_server_stays_up() {
    let server = start().await;
    let mut client = server.client().await;

    // OpenWalls: a wall out of range, a bad angle, a bad retrieve, short bounds.
    let e = client
        .open_walls(open_request("job", 1, 0.1, vec![0, 12]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("walls"), "{}", e.message());
    let mut bad_angle = open_request("job", 1, 0.1, vec![0]);
    if let Some(s) = bad_angle.settings.as_mut() {
        s.angle_deg = Some(120.0);
    }
    let e = client.open_walls(bad_angle).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("angle_deg"), "{}", e.message());
    let mut nan_radius = open_request("job", 1, f32::NAN, vec![0]);
    nan_radius.scene_bounds.truncate(5);
    let e = client.open_walls(nan_radius).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    let mut short = open_request("job", 1, 0.1, vec![0]);
    short.domain_bounds.truncate(9);
    let e = client.open_walls(short).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("domain_bounds"), "{}", e.message());

    // Nothing was opened by the bad requests.
    let e = client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 1,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);

    client
        .open_walls(open_request("job", 1, 0.1, vec![0]))
        .await
        .unwrap();
    let cam = camera_ray();

    // A count that does not match the records ends the stream with INVALID_ARGUMENT.
    let mut ex = Exchange::open(&mut client).await;
    let mut l = lookups("job", 1, 1, &[(cam, 0, BOTH)]);
    l.count = 2;
    assert_eq!(
        ex.lookup(l).await.unwrap_err().code(),
        Code::InvalidArgument
    );

    // Walls or options missing, a truncated record, a bad ray kind, an empty message.
    type Edit = Box<dyn Fn(&mut CacheLookups)>;
    let bad: Vec<Edit> = vec![
        Box::new(|l| {
            l.walls.pop();
        }),
        Box::new(|l| l.options.push(1)),
        Box::new(|l| {
            l.records.pop();
        }),
        // Kind 7 in the first record's header (bits 0-2; rays.proto: 6 and 7 reject).
        Box::new(|l| l.records[0] |= 0b111),
        Box::new(|l| l.records[8..12].copy_from_slice(&f32::NAN.to_le_bytes())),
        Box::new(|l| {
            l.count = u32::MAX;
        }),
    ];
    for edit in bad {
        let mut ex = Exchange::open(&mut client).await;
        let mut l = lookups("job", 1, 1, &[(cam, 0, BOTH), (cam, 0, BOTH)]);
        edit(&mut l);
        assert_eq!(
            ex.lookup(l).await.unwrap_err().code(),
            Code::InvalidArgument
        );
    }
    let mut ex = Exchange::open(&mut client).await;
    assert_eq!(
        ex.ask(None).await.unwrap_err().code(),
        Code::InvalidArgument
    );

    // Rays the cache cannot place (parallel to the wall, zero direction) and any wall
    // index are answered, not refused.
    let mut ex = Exchange::open(&mut client).await;
    let mut parallel = cam;
    parallel.dir = Vec3::new(0.0, 1.0, 0.0);
    let mut zero = cam;
    zero.dir = Vec3::ZERO;
    let mut no_credit = cam;
    no_credit.credit = Credit::ZERO;
    let a = ex
        .lookup(lookups(
            "job",
            1,
            1,
            &[
                (parallel, 0, BOTH),
                (zero, 0, BOTH),
                (cam, u32::MAX, BOTH),
                (no_credit, 0, BOTH),
                (cam, 0, u32::MAX),
            ],
        ))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0, 0, 0, 0, 2]);

    // The server is still up: a good request works.
    let a = ex
        .lookup(lookups("job", 1, 2, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![2]);
    let stats = client
        .close_walls(CloseWallsRequest {
            job_id: "job".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap();
    // parallel, zero, no credit, all option bits, and the last one.
    assert_eq!(stats.outer_lookups, 5);
    assert_eq!(stats.tickets_opened, 2);
    assert_eq!(stats.tickets_open, 2);

    // Health is served.
    let channel = Channel::from_shared(format!("http://{}", server.addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let status = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "dray.v1.CacheService".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        status.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    drop(ex);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_streams_close_every_ticket_once() {
    let server = start().await;
    let mut client = server.client().await;
    client
        .open_walls(open_request("many", 1, 1e-6, (0..12).collect()))
        .await
        .unwrap();
    // 4 streams x 100 rays on a 20 x 20 grid of crossing points.
    let ray = |i: u32| RayRecord {
        credit: Credit::from_wire(10),
        origin: Vec3::new(
            -1.0,
            0.025 + 0.05 * (i % 20) as f32,
            0.025 + 0.05 * (i / 20) as f32,
        ),
        dir: Vec3::X,
        weight: Vec3::ONE,
        pixel: i,
        ..camera_ray()
    };
    let radiance = |i: u32| [i64::from(i) << 20, 1 << 24, 0];
    let mut streams = Vec::new();
    for _ in 0..4 {
        streams.push(Exchange::open(&mut client).await);
    }
    let mut tasks = Vec::new();
    for (s, mut ex) in streams.into_iter().enumerate() {
        tasks.push(tokio::spawn(async move {
            let rays: Vec<(RayRecord, u32, u32)> = (0..100)
                .map(|k| (ray(s as u32 * 100 + k), 0, BOTH))
                .collect();
            let a = ex.lookup(lookups("many", 1, 1, &rays)).await.unwrap();
            assert_eq!(a.outcomes, vec![2; 100]);
            (ex, a.tickets)
        }));
    }
    let mut streams = Vec::new();
    let mut tickets = Vec::new();
    for t in tasks {
        let (ex, ts) = t.await.unwrap();
        streams.push(ex);
        tickets.extend(ts);
    }
    assert_eq!(tickets.len(), 400);
    // Every ticket's credit comes back in two parts on two different streams.
    let mut tasks = Vec::new();
    for (s, mut ex) in streams.into_iter().enumerate() {
        let mine: Vec<TicketReturn> = tickets
            .iter()
            .enumerate()
            .flat_map(|(i, &t)| {
                let rgb = radiance(i as u32);
                let first = ret(t, [rgb[0], 0, 0], 4);
                let second = ret(t, [0, rgb[1], rgb[2]], 6);
                [(i % 4, first), ((i + 1) % 4, second)]
            })
            .filter(|(owner, _)| *owner == s)
            .map(|(_, r)| r)
            .collect();
        tasks.push(tokio::spawn(async move {
            let ack = ex
                .give_back(TicketReturns {
                    job_id: "many".into(),
                    attempt: 1,
                    sequence: 2,
                    returns: mine,
                })
                .await
                .unwrap();
            assert_eq!(ack.sequence, 2);
            ex
        }));
    }
    let mut streams = Vec::new();
    for t in tasks {
        streams.push(t.await.unwrap());
    }
    // Every ray now hits, with its own radiance.
    for (s, ex) in streams.iter_mut().enumerate() {
        let rays: Vec<(RayRecord, u32, u32)> = (0..100)
            .map(|k| (ray(s as u32 * 100 + k), 0, BOTH))
            .collect();
        let a = ex.lookup(lookups("many", 1, 3, &rays)).await.unwrap();
        assert_eq!(a.outcomes, vec![1; 100]);
        for k in 0..100 {
            let i = s * 100 + k;
            let rgb = radiance(i as u32);
            let want = rgb.map(|c| (c as f64 / FIXED_SCALE) as f32);
            assert_eq!(a.radiance[3 * k..3 * k + 3], want, "ray {i}");
        }
    }
    let stats = client
        .close_walls(CloseWallsRequest {
            job_id: "many".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap();
    assert_eq!(
        stats,
        RayCacheStats {
            outer_lookups: 800,
            outer_hits: 400,
            tickets_opened: 400,
            tickets_closed: 400,
            tickets_stored: 400,
            entries: 400,
            ..Default::default()
        }
    );
    drop(streams);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_fill_only_the_coarse_pass_stores() {
    let server = start().await;
    let mut client = server.client().await;
    let mut req = open_request("frozen", 1, 1e-6, vec![0]);
    if let Some(s) = req.settings.as_mut() {
        s.fill = Some(false);
    }
    client.open_walls(req).await.unwrap();
    let mut ex = Exchange::open(&mut client).await;
    let main = camera_ray();
    let mut coarse = main;
    coarse.origin.z += 0.25;
    coarse.flags = FLAG_COARSE;
    // The coarse ray only asks for a ticket, as the worker sends it.
    let a = ex
        .lookup(lookups(
            "frozen",
            1,
            1,
            &[(main, 0, BOTH), (coarse, 0, OPTION_TICKET)],
        ))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![2, 2]);
    ex.give_back(TicketReturns {
        job_id: "frozen".into(),
        attempt: 1,
        sequence: 2,
        returns: vec![
            ret(a.tickets[0], [1 << 24; 3], main.credit.to_wire()),
            ret(a.tickets[1], [1 << 24; 3], coarse.credit.to_wire()),
        ],
    })
    .await
    .unwrap();
    // The main-pass ray stored nothing; the coarse one did.
    let mut at_coarse = main;
    at_coarse.origin.z += 0.25;
    let a = ex
        .lookup(lookups(
            "frozen",
            1,
            3,
            &[(main, 0, OPTION_ANSWER), (at_coarse, 0, OPTION_ANSWER)],
        ))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0, 1]);
    let stats = client
        .close_walls(CloseWallsRequest {
            job_id: "frozen".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap();
    assert_eq!((stats.tickets_closed, stats.tickets_stored), (2, 1));
    // The coarse ray only filled: it is not a lookup.
    assert_eq!((stats.outer_lookups, stats.outer_hits), (3, 1));
    drop(ex);
    server.stop().await;
}

/// Hit maps only (no ray cache) on every wall of the 2 x 1 x 1 grid.
fn phm_request(job: &str, phm: PhmSettings) -> OpenWallsRequest {
    OpenWallsRequest {
        settings: None,
        phm: Some(phm),
        ..open_request(job, 1, 0.0, (0..12).collect())
    }
}

/// Wall 6: domain 1 ([1,2]x[0,1]x[0,1]), face -x.
const WALL: u32 = 6;

/// The map cell of `ray` at wall 6, as a worker bins it.
fn cell_at_wall6(ray: &RayRecord) -> u32 {
    PhmBins::new(4, 12)
        .cell(Vec3::X, Vec3::new(2.0, 1.0, 1.0), 0, ray.origin, ray.dir)
        .expect("the ray crosses wall 6")
}

/// A shadow ray in domain 0 heading into domain 1 through wall 6, near (y, z).
fn shadow_ray(y: f32, z: f32, pixel: u32) -> RayRecord {
    RayRecord {
        origin: Vec3::new(0.5, y, z),
        dir: Vec3::new(1.0, 0.01, 0.02),
        pixel,
        kind: RayKind::Shadow,
        depth: 1,
        ..camera_ray()
    }
}

fn outcomes(job: &str, sequence: u64, per: &[(u32, u32, u8, usize)]) -> PhmOutcomes {
    let mut o = PhmOutcomes {
        job_id: job.into(),
        attempt: 1,
        sequence,
        ..Default::default()
    };
    for &(wall, cell, hit, n) in per {
        for _ in 0..n {
            o.walls.push(wall);
            o.cells.push(cell);
            o.hits.push(hit);
        }
    }
    o
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hit_maps_learn_skip_and_occlude() {
    let server = start().await;
    let mut client = server.client().await;
    // No re-probes, so every answer at a decided cell is exact.
    let phm = PhmSettings {
        reprobe: Some(0.0),
        kinds: "shadow,camera".into(),
        ..Default::default()
    };
    let opened = client
        .open_walls(phm_request("maps", phm.clone()))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(opened.actors, 12);
    // Re-opening with the same maps is fine; with other maps it is refused.
    client
        .open_walls(phm_request("maps", phm.clone()))
        .await
        .unwrap();
    let e = client
        .open_walls(phm_request(
            "maps",
            PhmSettings {
                prior: Some(5.0),
                ..phm.clone()
            },
        ))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);

    let mut ex = Exchange::open(&mut client).await;
    let (a, b) = (shadow_ray(0.2, 0.2, 1), shadow_ray(0.8, 0.7, 2));
    let (cell_a, cell_b) = (cell_at_wall6(&a), cell_at_wall6(&b));
    assert_ne!(cell_a, cell_b);
    // Fresh maps: probes. A camera ray asking the (absent) ray cache too is a plain
    // miss plus a probe; a ray not asking the map gets nothing from it.
    let cam = RayRecord {
        kind: RayKind::Camera,
        ..a
    };
    let answers = ex
        .lookup(lookups(
            "maps",
            1,
            1,
            &[
                (a, WALL, OPTION_PHM),
                (b, WALL, OPTION_PHM),
                (cam, WALL, BOTH | OPTION_PHM),
                (a, WALL, BOTH),
            ],
        ))
        .await
        .unwrap();
    assert_eq!(answers.outcomes, vec![8, 8, 8, 0]);
    assert!(answers.tickets.is_empty() && answers.radiance.is_empty());

    // 1000 misses at a's cell, 1000 hits at b's (100 / 1200 <= 0.1, 1100 / 1200 >= 0.9).
    let ack = ex
        .report(outcomes(
            "maps",
            2,
            &[(WALL, cell_a, 0, 1000), (WALL, cell_b, 1, 1000)],
        ))
        .await
        .unwrap();
    assert_eq!(ack.sequence, 2);

    // Other rays in the same cells: a's cell skips any kind; b's cell occludes shadow
    // rays and probes camera rays. The same rays on another wall are still probes.
    let a2 = shadow_ray(0.21, 0.19, 3);
    let b2 = shadow_ray(0.79, 0.71, 4);
    assert_eq!((cell_at_wall6(&a2), cell_at_wall6(&b2)), (cell_a, cell_b));
    let cam_a = RayRecord {
        kind: RayKind::Camera,
        ..a2
    };
    let cam_b = RayRecord {
        kind: RayKind::Camera,
        ..b2
    };
    let answers = ex
        .lookup(lookups(
            "maps",
            1,
            3,
            &[
                (a2, WALL, OPTION_PHM),
                (cam_a, WALL, BOTH | OPTION_PHM),
                (b2, WALL, OPTION_PHM),
                (cam_b, WALL, OPTION_PHM),
                (cam_b, WALL, BOTH | OPTION_PHM),
                (b2, 1, OPTION_PHM),
            ],
        ))
        .await
        .unwrap();
    assert_eq!(answers.outcomes, vec![3, 3, 4, 8, 8, 8]);

    // Outcomes that fit nothing are acknowledged and ignored: a cell beyond the map, a
    // wall not open, a hit byte that is neither 0 nor 1, another job.
    let ack = ex
        .report(outcomes(
            "maps",
            4,
            &[(WALL, 192, 1, 3), (12, 0, 1, 2), (WALL, cell_a, 7, 1)],
        ))
        .await
        .unwrap();
    assert_eq!(ack.sequence, 4);
    let ack = ex
        .report(outcomes("nope", 5, &[(WALL, cell_a, 1, 5000)]))
        .await
        .unwrap();
    assert_eq!(ack.sequence, 5);
    // So a's cell still skips.
    let answers = ex
        .lookup(lookups("maps", 1, 6, &[(a, WALL, OPTION_PHM)]))
        .await
        .unwrap();
    assert_eq!(answers.outcomes, vec![3]);

    let closed = client
        .close_walls(CloseWallsRequest {
            job_id: "maps".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner();
    // No ray cache: no ray-cache statistics.
    assert_eq!(closed.stats, None);
    assert_eq!(
        closed.phm,
        Some(PhmStats {
            lookups: 3 + 6 + 1,
            rays_skipped: 3,
            rays_occluded: 1,
            probes: 3 + 3,
            outcomes: 2000,
            cells_decided_hit: 1,
            cells_decided_miss: 1,
            cells: 12 * 192,
            ..Default::default()
        })
    );
    drop(ex);
    server.stop().await;
}

/// Sender placement's merges (another worker's outcomes, counted per cell) teach a
/// copy of a map what the same outcomes one by one would, are counted as merged rather
/// than as outcomes, and bad merges get clean errors.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn merges_teach_a_copy_of_the_maps() {
    let server = start().await;
    let mut client = server.client().await;
    let phm = PhmSettings {
        reprobe: Some(0.0),
        ..Default::default()
    };
    client.open_walls(phm_request("copy", phm)).await.unwrap();
    let mut ex = Exchange::open(&mut client).await;
    let (a, b) = (shadow_ray(0.2, 0.2, 1), shadow_ray(0.8, 0.7, 2));
    let (cell_a, cell_b) = (cell_at_wall6(&a), cell_at_wall6(&b));
    // 1000 misses at a's cell, 1000 hits at b's, in two merges; 12 more to another job.
    let merge = |sequence, job: &str, per: &[(u32, u32, u32, u32)]| PhmMerge {
        job_id: job.into(),
        attempt: 1,
        sequence,
        walls: per.iter().map(|p| p.0).collect(),
        cells: per.iter().map(|p| p.1).collect(),
        hits: per.iter().map(|p| p.2).collect(),
        misses: per.iter().map(|p| p.3).collect(),
    };
    let ack = ex
        .merge(merge(
            1,
            "copy",
            &[(WALL, cell_a, 0, 600), (WALL, cell_b, 600, 0)],
        ))
        .await
        .unwrap();
    assert_eq!(ack.sequence, 1);
    ex.merge(merge(
        2,
        "copy",
        &[(WALL, cell_a, 0, 400), (WALL, cell_b, 400, 0)],
    ))
    .await
    .unwrap();
    ex.merge(merge(3, "other", &[(WALL, cell_a, 12, 0)]))
        .await
        .unwrap();
    let answers = ex
        .lookup(lookups(
            "copy",
            1,
            4,
            &[(a, WALL, OPTION_PHM), (b, WALL, OPTION_PHM)],
        ))
        .await
        .unwrap();
    assert_eq!(answers.outcomes, vec![3, 4], "a skips, b is occluded");
    // Mismatched lengths end the stream with a clean error.
    let mut bad = merge(5, "copy", &[(WALL, cell_a, 1, 1)]);
    bad.misses.clear();
    let e = ex.merge(bad).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e}");
    assert!(e.message().contains("misses"), "{}", e.message());
    let closed = client
        .close_walls(CloseWallsRequest {
            job_id: "copy".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner();
    let p = closed.phm.expect("hit-map statistics");
    assert_eq!((p.outcomes, p.outcomes_merged), (0, 2000), "{p:?}");
    assert_eq!((p.cells_decided_hit, p.cells_decided_miss), (1, 1), "{p:?}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hit_maps_and_ray_caches_share_the_walls() {
    let server = start().await;
    let mut client = server.client().await;
    let mut req = open_request("both", 1, 1e-6, vec![0, 6]);
    req.phm = Some(PhmSettings {
        prior: Some(1.0),
        mode: "inconsistent".into(),
        ..Default::default()
    });
    client.open_walls(req).await.unwrap();
    let mut ex = Exchange::open(&mut client).await;
    let cam = camera_ray();
    let all = BOTH | OPTION_PHM;
    // A miss with a ticket, and a probe: 2 + 8, the ticket in `tickets`.
    let a = ex
        .lookup(lookups(
            "both",
            1,
            1,
            &[(cam, 0, all), (cam, 0, OPTION_PHM)],
        ))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![10, 8]);
    assert_eq!(a.tickets.len(), 1);
    ex.give_back(TicketReturns {
        job_id: "both".into(),
        attempt: 1,
        sequence: 2,
        returns: vec![ret(a.tickets[0], [1 << 24; 3], cam.credit.to_wire())],
    })
    .await
    .unwrap();
    // Now a ray-cache hit: never a probe (it does not go on).
    let a = ex
        .lookup(lookups("both", 1, 3, &[(cam, 0, all)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![1]);
    assert_eq!(a.radiance.len(), 3);

    // Inconsistent: 8 misses decide (1 / 10 <= 0.1) and later hits are ignored.
    let cell = PhmBins::new(4, 12)
        .cell(Vec3::ZERO, Vec3::ONE, 0, cam.origin, cam.dir)
        .unwrap();
    ex.report(outcomes("both", 4, &[(0, cell, 0, 8), (0, cell, 1, 50)]))
        .await
        .unwrap();
    // The map speaks first: skipped, however the ray cache would have answered.
    let mut other = cam;
    other.pixel = 7;
    let a = ex
        .lookup(lookups("both", 1, 5, &[(cam, 0, all), (other, 0, all)]))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![3, 3]);
    assert!(a.radiance.is_empty() && a.tickets.is_empty());
    let closed = client
        .close_walls(CloseWallsRequest {
            job_id: "both".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner();
    let stats = closed.stats.unwrap();
    // Skipped rays never reached the ray cache.
    assert_eq!((stats.outer_lookups, stats.outer_hits), (2, 1));
    assert_eq!(
        closed.phm.unwrap(),
        PhmStats {
            lookups: 5,
            rays_skipped: 2,
            probes: 2,
            outcomes: 58,
            cells_decided_miss: 1,
            cells: 2 * 192,
            ..Default::default()
        }
    );
    drop(ex);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_hit_map_requests_get_clean_errors() {
    let server = start().await;
    let mut client = server.client().await;
    // Neither a ray cache nor maps.
    let mut neither = open_request("bad", 1, 0.1, vec![0]);
    neither.settings = None;
    let e = client.open_walls(neither).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("neither"), "{}", e.message());
    // Each bad field is named.
    let bad = [
        (
            PhmSettings {
                res: Some(0),
                ..Default::default()
            },
            "phm.res",
        ),
        (
            PhmSettings {
                dirs: Some(300),
                ..Default::default()
            },
            "phm.dirs",
        ),
        (
            PhmSettings {
                prior: Some(f32::NAN),
                ..Default::default()
            },
            "phm.prior",
        ),
        (
            PhmSettings {
                miss: Some(0.7),
                ..Default::default()
            },
            "phm.miss",
        ),
        (
            PhmSettings {
                hit: Some(0.3),
                ..Default::default()
            },
            "phm.hit",
        ),
        (
            PhmSettings {
                mode: "maybe".into(),
                ..Default::default()
            },
            "phm.mode",
        ),
        (
            PhmSettings {
                reprobe: Some(-0.5),
                ..Default::default()
            },
            "phm.reprobe",
        ),
        (
            PhmSettings {
                kinds: "photon".into(),
                ..Default::default()
            },
            "phm.kinds",
        ),
    ];
    for (phm, field) in bad {
        let e = client
            .open_walls(phm_request("bad", phm))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains(field), "{field}: {}", e.message());
    }
    // Nothing was opened.
    let e = client
        .close_walls(CloseWallsRequest {
            job_id: "bad".into(),
            attempt: 1,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);

    client
        .open_walls(phm_request("bad", PhmSettings::default()))
        .await
        .unwrap();
    // Lengths that differ end the stream with INVALID_ARGUMENT ...
    type Edit = Box<dyn Fn(&mut PhmOutcomes)>;
    let edits: Vec<Edit> = vec![
        Box::new(|o| {
            o.walls.pop();
        }),
        Box::new(|o| o.cells.push(0)),
        Box::new(|o| {
            o.hits.pop();
        }),
    ];
    for edit in edits {
        let mut ex = Exchange::open(&mut client).await;
        let mut o = outcomes("bad", 1, &[(WALL, 0, 1, 2)]);
        edit(&mut o);
        let e = ex.report(o).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains("outcomes 1"), "{}", e.message());
    }
    // ... and the server stays up.
    let mut ex = Exchange::open(&mut client).await;
    let ack = ex
        .report(outcomes("bad", 2, &[(WALL, 0, 1, 2)]))
        .await
        .unwrap();
    assert_eq!(ack.sequence, 2);
    // Rays the map cannot place get no answer from it, and are no probes.
    let mut parallel = shadow_ray(0.5, 0.5, 1);
    parallel.dir = Vec3::Y;
    let a = ex
        .lookup(lookups(
            "bad",
            1,
            3,
            &[
                (parallel, WALL, OPTION_PHM),
                (shadow_ray(0.5, 0.5, 2), WALL, u32::MAX),
            ],
        ))
        .await
        .unwrap();
    assert_eq!(a.outcomes, vec![0, 8]);
    let closed = client
        .close_walls(CloseWallsRequest {
            job_id: "bad".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner();
    let phm = closed.phm.unwrap();
    assert_eq!((phm.lookups, phm.probes, phm.outcomes), (2, 1, 2));
    drop(ex);
    server.stop().await;
}

/// Sender placement: two hosts hold replicas 3 and 4 of the same walls. A replica's
/// tickets carry its number; a ticket that closes there stores, and the ack hands the
/// entry back so that the other replica can store it (WallEntries), after which a ray
/// looked up at either replica hits with the same radiance. Returns naming another
/// replica are strays.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_share_what_they_store() {
    let (a, b) = (start().await, start().await);
    let (mut ca, mut cb) = (a.client().await, b.client().await);
    let walls: Vec<u32> = (0..12).collect();
    for (c, replica) in [(&mut ca, 3), (&mut cb, 4)] {
        let mut req = open_request("rep", 1, 1e-6, walls.clone());
        req.replica = replica;
        c.open_walls(req).await.unwrap();
    }
    let mut too_many = open_request("rep2", 1, 1e-6, walls.clone());
    too_many.replica = 4096;
    let e = ca.open_walls(too_many).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("replica"), "{e:?}");

    let (mut xa, mut xb) = (Exchange::open(&mut ca).await, Exchange::open(&mut cb).await);
    let cam = camera_ray();
    let got = xa
        .lookup(lookups("rep", 1, 1, &[(cam, 0, BOTH)]))
        .await
        .unwrap();
    assert_eq!(got.outcomes, vec![2]);
    let t = got.tickets[0];
    assert_eq!(dray_cache::ticket_id::ticket_replica(t), 3);
    assert_eq!(dray_cache::ticket_id::ticket_wall(t), 0);

    // The same ticket returned to replica 4 is not its own: ignored, nothing stored.
    let stray = xb
        .give_back(TicketReturns {
            job_id: "rep".into(),
            attempt: 1,
            sequence: 1,
            returns: vec![ret(t, [1 << 24, 1 << 24, 1 << 24], 1000)],
        })
        .await
        .unwrap();
    assert!(stray.walls.is_empty() && stray.entries.is_empty());

    // Returned to replica 3: whole, stored, and handed back.
    let ack = xa
        .give_back(TicketReturns {
            job_id: "rep".into(),
            attempt: 1,
            sequence: 2,
            returns: vec![ret(t, [1 << 24, 1 << 23, 1 << 22], 1000)],
        })
        .await
        .unwrap();
    assert_eq!(ack.walls, vec![0]);
    assert_eq!(
        ack.entries.len(),
        dray_cache::entry_record::ENTRY_RECORD_BYTES
    );
    // Replica 4 does not have it yet.
    let before = xb
        .lookup(lookups("rep", 1, 2, &[(cam, 0, OPTION_ANSWER)]))
        .await
        .unwrap();
    assert_eq!(before.outcomes, vec![0]);
    // Copied over, it answers as replica 3 does.
    let copied = match xb
        .ask(Some(cache_request::Msg::Entries(
            dray_proto::v1::WallEntries {
                job_id: "rep".into(),
                attempt: 1,
                sequence: 3,
                walls: ack.walls.clone(),
                entries: ack.entries.clone(),
            },
        )))
        .await
        .unwrap()
        .msg
    {
        Some(cache_response::Msg::Ack(a)) => a,
        other => panic!("expected an ack, got {other:?}"),
    };
    assert_eq!(copied.sequence, 3);
    let at_a = xa
        .lookup(lookups("rep", 1, 3, &[(cam, 0, OPTION_ANSWER)]))
        .await
        .unwrap();
    let at_b = xb
        .lookup(lookups("rep", 1, 4, &[(cam, 0, OPTION_ANSWER)]))
        .await
        .unwrap();
    assert_eq!(at_a.outcomes, vec![1]);
    assert_eq!(at_b.outcomes, at_a.outcomes);
    assert_eq!(at_b.radiance, at_a.radiance);

    // Entries that are not whole records end the stream with a clean error.
    let bad = xb
        .ask(Some(cache_request::Msg::Entries(
            dray_proto::v1::WallEntries {
                job_id: "rep".into(),
                attempt: 1,
                sequence: 5,
                walls: vec![0],
                entries: vec![0; 10],
            },
        )))
        .await
        .unwrap_err();
    assert_eq!(bad.code(), Code::InvalidArgument, "{bad:?}");

    drop((xa, xb));
    let closed = ca
        .close_walls(CloseWallsRequest {
            job_id: "rep".into(),
            attempt: 1,
        })
        .await
        .unwrap()
        .into_inner();
    let stats = closed.stats.unwrap();
    assert_eq!((stats.tickets_opened, stats.tickets_stored), (1, 1));
    a.stop().await;
    b.stop().await;
}
