//! Ray caches, the coordinator's side, on a live server over real TCP: validation of
//! `JobSpec.ray_cache` (and the server serving on after a refusal), RegisterCacheHost,
//! where each attempt's walls are placed (beside the owners of their domains, on
//! stand-alone hosts when there are any, around hosts that cannot open), OpenWalls
//! before the tiles go out, CloseWalls when the attempt ends (completed, cancelled,
//! replaced after a lost worker), and the statistics in JobStats. Workers are played by
//! the tests through the generated client; cache hosts are fake CacheService servers
//! that record what they are asked.

mod support;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_coordinator::membership::{HeartbeatConfig, VERSION};
use dray_proto::v1::assignment::Command;
use dray_proto::v1::cache_service_server::{CacheService, CacheServiceServer};
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CacheRequest, CacheResponse, CancelJobRequest, CloseWallsRequest, CloseWallsResponse, JobSpec,
    JobState, OpenWallsRequest, OpenWallsResponse, PhmSettings, RayCacheSettings, RayCacheStats,
    RegisterCacheHostRequest, RegisterWorkerRequest, ReportContributionsRequest, SubmitJobRequest,
    Tile, TileCredit, WorkerCounters,
};
use tonic::{Code, Request, Response, Status, Streaming};

use support::*;

/// What a fake cache host was asked, in order.
#[derive(Clone, Debug)]
enum Call {
    Open(Box<OpenWallsRequest>),
    Close(CloseWallsRequest),
}

#[derive(Clone)]
struct HostService {
    calls: Arc<Mutex<Vec<Call>>>,
    close_stats: RayCacheStats,
    refuse_open: bool,
}

#[tonic::async_trait]
impl CacheService for HostService {
    async fn open_walls(
        &self,
        r: Request<OpenWallsRequest>,
    ) -> Result<Response<OpenWallsResponse>, Status> {
        let r = r.into_inner();
        let actors = r.walls.len() as u32;
        self.calls.lock().unwrap().push(Call::Open(Box::new(r)));
        if self.refuse_open {
            return Err(Status::resource_exhausted("this fake host is full"));
        }
        Ok(Response::new(OpenWallsResponse { actors }))
    }

    async fn close_walls(
        &self,
        r: Request<CloseWallsRequest>,
    ) -> Result<Response<CloseWallsResponse>, Status> {
        self.calls.lock().unwrap().push(Call::Close(r.into_inner()));
        Ok(Response::new(CloseWallsResponse {
            stats: Some(self.close_stats.clone()),
            ..Default::default()
        }))
    }

    type ExchangeStream = tokio_stream::Empty<Result<CacheResponse, Status>>;

    async fn exchange(
        &self,
        _r: Request<Streaming<CacheRequest>>,
    ) -> Result<Response<Self::ExchangeStream>, Status> {
        Err(Status::unimplemented("a fake cache host answers no rays"))
    }
}

/// A fake cache host on a free port, stopped when dropped.
struct FakeHost {
    endpoint: String,
    calls: Arc<Mutex<Vec<Call>>>,
    _task: AbortOnDrop,
}

impl FakeHost {
    async fn start(close_stats: RayCacheStats, refuse_open: bool) -> FakeHost {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let calls = Arc::new(Mutex::new(Vec::new()));
        let svc = HostService {
            calls: calls.clone(),
            close_stats,
            refuse_open,
        };
        let task = tokio::spawn(async move {
            let _ = tonic::transport::Server::builder()
                .add_service(CacheServiceServer::new(svc))
                .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener))
                .await;
        });
        FakeHost {
            endpoint: format!("http://{addr}"),
            calls,
            _task: AbortOnDrop(task),
        }
    }

    fn calls(&self) -> Vec<Call> {
        self.calls.lock().unwrap().clone()
    }

    fn opens(&self) -> Vec<OpenWallsRequest> {
        self.calls()
            .into_iter()
            .filter_map(|c| match c {
                Call::Open(r) => Some(*r),
                Call::Close(_) => None,
            })
            .collect()
    }

    fn closes(&self) -> Vec<CloseWallsRequest> {
        self.calls()
            .into_iter()
            .filter_map(|c| match c {
                Call::Close(r) => Some(r),
                Call::Open(_) => None,
            })
            .collect()
    }

    /// The calls as ("open"|"close", attempt), in order.
    fn trace(&self) -> Vec<(&'static str, u32)> {
        self.calls()
            .into_iter()
            .map(|c| match c {
                Call::Open(r) => ("open", r.attempt),
                Call::Close(r) => ("close", r.attempt),
            })
            .collect()
    }
}

fn host_stats(outer_hits: u64) -> RayCacheStats {
    RayCacheStats {
        outer_lookups: 100,
        outer_hits,
        inner_lookups: 40,
        inner_hits: 4,
        tickets_opened: 136,
        tickets_closed: 130,
        tickets_stored: 120,
        tickets_open: 6,
        ..Default::default()
    }
}

fn worker_with_host(endpoint: &str, cache_endpoint: &str) -> RegisterWorkerRequest {
    RegisterWorkerRequest {
        cache_endpoint: cache_endpoint.into(),
        ..register_request(endpoint)
    }
}

/// `spec` with ray caches placed remotely (each wall once, beside its domain's owner):
/// what most tests here check.
fn cached(spec: JobSpec) -> JobSpec {
    JobSpec {
        ray_cache: Some(RayCacheSettings {
            radius: 0.01,
            placement: "remote".into(),
            ..Default::default()
        }),
        ..spec
    }
}

/// Every tile's whole credit, with cache counters.
fn all_credit(
    job: &str,
    attempt: u32,
    sequence: u64,
    tiles: &[Tile],
) -> ReportContributionsRequest {
    ReportContributionsRequest {
        job_id: job.into(),
        sequence,
        attempt,
        credits: tiles
            .iter()
            .map(|t| TileCredit {
                tile: t.index,
                credit: t.credit,
            })
            .collect(),
        counters: Some(WorkerCounters {
            cache_rays_not_sent: 7,
            cache_rays_bypassed: 1,
            cache_bytes: 500,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// The walls of `domains`, ascending.
fn walls_of(domains: &[u32]) -> Vec<u32> {
    domains.iter().flat_map(|d| 6 * d..6 * d + 6).collect()
}

/// Poll GetJob until `f` holds for the job's cache statistics.
async fn wait_cache_stats(
    channel: &tonic::transport::Channel,
    id: &str,
    f: impl Fn(&RayCacheStats) -> bool,
) -> RayCacheStats {
    let deadline = tokio::time::Instant::now() + PATIENCE;
    loop {
        let s = get_job(channel, id).await.stats.unwrap().ray_cache;
        if let Some(s) = s.filter(|s| f(s)) {
            return s;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "HANG: cache statistics never came within PATIENCE"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_ray_cache_values_are_refused_naming_the_field_and_the_server_serves_on() {
    let server = Server::start("cache-bad", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut c = RenderServiceClient::new(channel.clone());
    let with = |rc: RayCacheSettings| JobSpec {
        ray_cache: Some(rc),
        ..spec(8, 8, 1)
    };
    let base = RayCacheSettings::default;
    let bad = [
        (
            with(RayCacheSettings {
                radius: -1.0,
                ..base()
            }),
            "ray_cache.radius must be finite and >= 0, got -1",
        ),
        (
            with(RayCacheSettings {
                radius: f32::NAN,
                ..base()
            }),
            "ray_cache.radius",
        ),
        (
            with(RayCacheSettings {
                angle_deg: Some(0.0),
                ..base()
            }),
            "ray_cache.angle_deg",
        ),
        (
            with(RayCacheSettings {
                angle_deg: Some(91.0),
                ..base()
            }),
            "ray_cache.angle_deg",
        ),
        (
            with(RayCacheSettings {
                retrieve: "median".into(),
                ..base()
            }),
            "ray_cache.retrieve",
        ),
        (
            with(RayCacheSettings {
                coarse: 5000,
                ..base()
            }),
            "ray_cache.coarse",
        ),
        (
            with(RayCacheSettings {
                kinds: "camera+diffuse".into(),
                ..base()
            }),
            "ray_cache.kinds",
        ),
        (
            with(RayCacheSettings {
                kinds: "shadow".into(),
                ..base()
            }),
            "ray_cache.kinds: \"shadow\"",
        ),
    ];
    let phm = |p: PhmSettings| JobSpec {
        phm: Some(p),
        ..spec(8, 8, 1)
    };
    let bad_phm = [
        (
            phm(PhmSettings {
                res: Some(0),
                ..Default::default()
            }),
            "phm.res",
        ),
        (
            phm(PhmSettings {
                dirs: Some(1000),
                ..Default::default()
            }),
            "phm.dirs",
        ),
        (
            phm(PhmSettings {
                prior: Some(f32::NAN),
                ..Default::default()
            }),
            "phm.prior",
        ),
        (
            phm(PhmSettings {
                miss: Some(0.6),
                ..Default::default()
            }),
            "phm.miss",
        ),
        (
            phm(PhmSettings {
                hit: Some(0.4),
                ..Default::default()
            }),
            "phm.hit",
        ),
        (
            phm(PhmSettings {
                mode: "sometimes".into(),
                ..Default::default()
            }),
            "phm.mode",
        ),
        (
            phm(PhmSettings {
                reprobe: Some(2.0),
                ..Default::default()
            }),
            "phm.reprobe",
        ),
        (
            phm(PhmSettings {
                kinds: "shadow,bogus".into(),
                ..Default::default()
            }),
            "phm.kinds",
        ),
    ];
    for (spec, want) in bad.into_iter().chain(bad_phm) {
        let e = c
            .submit_job(SubmitJobRequest { spec: Some(spec) })
            .await
            .expect_err(want);
        assert_eq!(e.code(), Code::InvalidArgument, "{}", e.message());
        assert!(
            e.message().starts_with(want),
            "{:?} for {want:?}",
            e.message()
        );
    }
    // Good settings, but nothing to run caches on: no worker is registered.
    let e = c
        .submit_job(SubmitJobRequest {
            spec: Some(cached(spec(8, 8, 1))),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().starts_with("ray_cache:"), "{}", e.message());
    // The server serves on: a job without caches renders here.
    let id = submit(&channel, spec(8, 8, 1)).await;
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    assert!(
        job.stats.unwrap().ray_cache.is_none(),
        "no caches, no cache stats"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn walls_open_beside_their_owners_before_the_tiles_and_close_with_the_job() {
    let server = Server::start("cache-run", slow_heartbeat()).await;
    let channel = server.channel().await;
    let ha = FakeHost::start(host_stats(90), false).await;
    let hb = FakeHost::start(host_stats(80), false).await;
    let mut a = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7101", &ha.endpoint),
    )
    .await;
    let mut b = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7102", &hb.endpoint),
    )
    .await;
    let spec = JobSpec {
        schedule: "domain".into(),
        ..cached(spec(64, 32, 4))
    };
    let id = submit(&channel, spec).await;
    let (sa, ta) = a.setup_and_tiles(1).await;
    let (sb, tb) = b.setup_and_tiles(1).await;
    // Both hosts were opened before the setups went out.
    let (oa, ob) = (ha.opens(), hb.opens());
    assert_eq!((oa.len(), ob.len()), (1, 1));
    // Domain schedule over [a, b]: a owns 0 and 2, b owns 1 and 3; walls go beside.
    assert_eq!(oa[0].walls, walls_of(&[0, 2]));
    assert_eq!(ob[0].walls, walls_of(&[1, 3]));
    let settings = oa[0].settings.clone().unwrap();
    assert_eq!(
        settings,
        RayCacheSettings {
            radius: 0.01,
            angle_deg: Some(10.0),
            retrieve: "nearest".into(),
            coarse: 0,
            kinds: "camera,reflection,refraction,diffuse".into(),
            fill: Some(true),
            placement: "remote".into(),
        }
    );
    for o in [&oa[0], &ob[0]] {
        assert_eq!(o.replica, 0, "remote walls are the only actors");
        assert_eq!((o.job_id.as_str(), o.attempt), (id.as_str(), 0));
        assert_eq!(o.scene_bounds.len(), 6);
        assert_eq!(o.domain_bounds.len(), 4 * 6);
        assert!(
            o.scene_bounds[..3]
                .iter()
                .zip(&o.scene_bounds[3..])
                .all(|(lo, hi)| lo < hi)
        );
    }
    // The tables list the hosts and the host of every wall.
    let table = sa.routing.clone().unwrap();
    assert_eq!(table, sb.routing.clone().unwrap());
    let hosts: Vec<(&str, &str)> = table
        .cache_hosts
        .iter()
        .map(|h| (h.host_id.as_str(), h.endpoint.as_str()))
        .collect();
    assert_eq!(
        hosts,
        [
            (a.id.as_str(), ha.endpoint.as_str()),
            (b.id.as_str(), hb.endpoint.as_str())
        ]
    );
    let by_domain: Vec<u32> = table.wall_hosts.chunks(6).map(|c| c[0]).collect();
    assert_eq!(table.wall_hosts.len(), 24);
    assert_eq!(by_domain, [0, 1, 0, 1]);
    // The workers and GetJob read the settings with their defaults.
    assert_eq!(sa.spec.unwrap().ray_cache, Some(settings.clone()));
    let job = get_job(&channel, &id).await;
    assert_eq!(job.spec.unwrap().ray_cache, Some(settings));
    assert_eq!(
        job.stats.unwrap().ray_cache,
        Some(RayCacheStats::default()),
        "cache statistics from the start"
    );

    assert!(a.report(all_credit(&id, 0, 1, &ta)).await.unwrap());
    let running = wait_cache_stats(&channel, &id, |s| s.rays_not_sent == 7).await;
    assert_eq!(running.bytes_not_sent, 7 * 64);
    assert!(!b.report(all_credit(&id, 0, 1, &tb)).await.unwrap());
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    // Both hosts were closed before the job turned SUCCEEDED, and their statistics are
    // in the final ones, with the workers'.
    assert_eq!(ha.trace(), [("open", 0), ("close", 0)]);
    assert_eq!(hb.trace(), [("open", 0), ("close", 0)]);
    assert_eq!(ha.closes()[0].job_id, id);
    let s = job.stats.unwrap().ray_cache.unwrap();
    assert_eq!((s.outer_lookups, s.outer_hits), (200, 170));
    assert_eq!((s.inner_lookups, s.inner_hits), (80, 8));
    assert_eq!(
        (
            s.tickets_opened,
            s.tickets_closed,
            s.tickets_stored,
            s.tickets_open
        ),
        (272, 260, 240, 12)
    );
    assert_eq!((s.rays_not_sent, s.bytes_not_sent), (14, 14 * 64));
    assert_eq!((s.rays_bypassed, s.cache_bytes), (2, 1000));
    assert!(s.lost_hosts.is_empty());
    for w in [&mut a, &mut b] {
        assert!(matches!(w.next().await, Command::Finish(_)));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sender_placement_opens_a_replica_of_every_wall_beside_every_worker() {
    let server = Server::start("cache-sender", slow_heartbeat()).await;
    let channel = server.channel().await;
    let ha = FakeHost::start(host_stats(90), false).await;
    let hb = FakeHost::start(host_stats(80), false).await;
    let mut a = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7111", &ha.endpoint),
    )
    .await;
    let mut b = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7112", &hb.endpoint),
    )
    .await;
    // The default placement is sender.
    let job = JobSpec {
        schedule: "domain".into(),
        ray_cache: Some(RayCacheSettings {
            radius: 0.01,
            ..Default::default()
        }),
        ..spec(64, 32, 4)
    };
    let id = submit(&channel, job).await;
    let (sa, ta) = a.setup_and_tiles(1).await;
    let (_sb, tb) = b.setup_and_tiles(1).await;
    let (oa, ob) = (ha.opens(), hb.opens());
    assert_eq!((oa.len(), ob.len()), (1, 1));
    // Every wall on both hosts, as replicas 1 and 2 (their places in the table, plus 1).
    assert_eq!(oa[0].walls, (0..24).collect::<Vec<u32>>());
    assert_eq!(ob[0].walls, oa[0].walls);
    assert_eq!((oa[0].replica, ob[0].replica), (1, 2));
    assert_eq!(oa[0].settings.as_ref().unwrap().placement, "sender");
    let table = sa.routing.clone().unwrap();
    assert!(table.cache_replicas);
    let hosts: Vec<&str> = table
        .cache_hosts
        .iter()
        .map(|h| h.host_id.as_str())
        .collect();
    assert_eq!(hosts, [a.id.as_str(), b.id.as_str()]);
    // Each wall still has a home beside its owner, for workers without a host.
    let by_domain: Vec<u32> = table.wall_hosts.chunks(6).map(|c| c[0]).collect();
    assert_eq!(by_domain, [0, 1, 0, 1]);

    assert!(a.report(all_credit(&id, 0, 1, &ta)).await.unwrap());
    assert!(!b.report(all_credit(&id, 0, 1, &tb)).await.unwrap());
    wait_state(&channel, &id, JobState::Succeeded).await;
    assert_eq!(ha.trace(), [("open", 0), ("close", 0)]);
    assert_eq!(hb.trace(), [("open", 0), ("close", 0)]);
    for w in [&mut a, &mut b] {
        assert!(matches!(w.next().await, Command::Finish(_)));
    }
    // A job with hit maps replicates them too (their placement follows the cache's);
    // with remote placement each wall is opened once.
    for (n, placement) in [(1, "sender"), (2, "remote")] {
        let with_maps = JobSpec {
            schedule: "domain".into(),
            ray_cache: Some(RayCacheSettings {
                radius: 0.01,
                placement: placement.into(),
                ..Default::default()
            }),
            phm: Some(Default::default()),
            ..spec(64, 32, 4)
        };
        submit(&channel, with_maps).await;
        a.setup_and_tiles(1).await;
        b.setup_and_tiles(1).await;
        let (oa, ob) = (ha.opens(), hb.opens());
        assert_eq!(oa[n].phm.as_ref().unwrap().placement, placement);
        if placement == "sender" {
            assert_eq!((oa[n].replica, ob[n].replica), (1, 2));
            assert_eq!((oa[n].walls.len(), ob[n].walls.len()), (24, 24));
        } else {
            assert_eq!((oa[n].replica, ob[n].replica), (0, 0));
            assert_eq!(oa[n].walls.len() + ob[n].walls.len(), 24);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_host_that_cannot_open_is_left_out_and_its_walls_go_to_the_others() {
    let server = Server::start("cache-fail", slow_heartbeat()).await;
    let channel = server.channel().await;
    let ha = FakeHost::start(host_stats(90), false).await;
    // Nothing listens on port 1: b's host cannot be reached.
    let dead = "http://127.0.0.1:1";
    let mut a = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7201", &ha.endpoint),
    )
    .await;
    let mut b = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7202", dead),
    )
    .await;
    let spec = JobSpec {
        schedule: "domain".into(),
        ..cached(spec(64, 32, 4))
    };
    let id = submit(&channel, spec).await;
    let (sa, ta) = a.setup_and_tiles(1).await;
    let (_, tb) = b.setup_and_tiles(1).await;
    // a's host opened its own walls, then b's (re-placed on the only host left).
    let walls: Vec<Vec<u32>> = ha.opens().into_iter().map(|o| o.walls).collect();
    assert_eq!(walls, [walls_of(&[0, 2]), walls_of(&[1, 3])]);
    let table = sa.routing.unwrap();
    assert_eq!(table.cache_hosts.len(), 1);
    assert_eq!(table.cache_hosts[0].endpoint, ha.endpoint);
    assert_eq!(table.wall_hosts, [0; 24]);
    let s = get_job(&channel, &id)
        .await
        .stats
        .unwrap()
        .ray_cache
        .unwrap();
    assert_eq!(s.lost_hosts, [dead]);
    a.report(all_credit(&id, 0, 1, &ta)).await.unwrap();
    b.report(all_credit(&id, 0, 1, &tb)).await.unwrap();
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    assert_eq!(ha.closes().len(), 1);
    let s = job.stats.unwrap().ray_cache.unwrap();
    assert_eq!(s.outer_hits, 90);
    assert_eq!(s.lost_hosts, [dead]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_every_host_refusing_the_job_runs_without_caches() {
    let server = Server::start("cache-none-open", slow_heartbeat()).await;
    let channel = server.channel().await;
    let refusing = FakeHost::start(host_stats(1), true).await;
    let mut w = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7301", &refusing.endpoint),
    )
    .await;
    let id = submit(&channel, cached(spec(32, 32, 2))).await;
    let (setup, tiles) = w.setup_and_tiles(1).await;
    let table = setup.routing.unwrap();
    assert!(table.cache_hosts.is_empty() && table.wall_hosts.is_empty());
    assert_eq!(refusing.opens().len(), 1);
    w.report(all_credit(&id, 0, 1, &tiles)).await.unwrap();
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    let s = job.stats.unwrap().ray_cache.unwrap();
    assert_eq!(s.lost_hosts, std::slice::from_ref(&refusing.endpoint));
    assert_eq!(s.rays_not_sent, 7, "the workers' counters still count");
    assert!(refusing.closes().is_empty(), "nothing was open there");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_any_cache_host_the_job_fails_saying_so() {
    let server = Server::start("cache-nohost", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7401").await;
    let id = submit(&channel, cached(spec(32, 32, 1))).await;
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains(
            "ray caches need a cache host: workers announced none and no `dray cache` registered"
        ),
        "{err}"
    );
    assert!(w.next_within(Duration::from_millis(200)).await.is_none());
    // A job without caches still runs there.
    let id = submit(&channel, spec(32, 32, 1)).await;
    let (setup, _) = w.setup_and_tiles(1).await;
    assert_eq!(setup.job_id, id);
    assert!(setup.routing.unwrap().cache_hosts.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn standalone_hosts_register_and_take_the_walls_and_cancel_closes_them() {
    let server = Server::start("cache-standalone", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut cluster = ClusterServiceClient::new(channel.clone());
    let register = |endpoint: &str, version: &str| RegisterCacheHostRequest {
        endpoint: endpoint.into(),
        version: version.into(),
        hostname: "test".into(),
        member_token: String::new(),
    };
    let e = cluster
        .register_cache_host(register("http://127.0.0.1:7500", "0.0.0-other"))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().starts_with("version:"), "{}", e.message());
    let e = cluster
        .register_cache_host(register("127.0.0.1:7500", VERSION))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("endpoint:"), "{}", e.message());
    let hs = FakeHost::start(host_stats(50), false).await;
    let id = cluster
        .register_cache_host(register(&hs.endpoint, VERSION))
        .await
        .unwrap()
        .into_inner()
        .host_id;
    assert_eq!(id, "cache-1");

    // The worker hosts caches too, but a registered `dray cache` takes them all.
    let hw = FakeHost::start(host_stats(1), false).await;
    let mut w = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7501", &hw.endpoint),
    )
    .await;
    let job_id = submit(&channel, cached(spec(32, 32, 3))).await;
    let (setup, _) = w.setup_and_tiles(1).await;
    let table = setup.routing.unwrap();
    assert_eq!(table.cache_hosts.len(), 1);
    assert_eq!(
        (
            table.cache_hosts[0].host_id.as_str(),
            table.cache_hosts[0].endpoint.as_str()
        ),
        ("cache-1", hs.endpoint.as_str())
    );
    assert_eq!(hs.opens()[0].walls, walls_of(&[0, 1, 2]));
    assert!(hw.calls().is_empty());

    RenderServiceClient::new(channel.clone())
        .cancel_job(CancelJobRequest {
            job_id: job_id.clone(),
        })
        .await
        .unwrap();
    assert!(matches!(w.next().await, Command::Cancel(_)));
    // The walls are closed and their statistics follow the cancelled job.
    let s = wait_cache_stats(&channel, &job_id, |s| s.outer_hits == 50).await;
    assert_eq!(s.tickets_open, 6);
    assert_eq!(hs.trace(), [("open", 0), ("close", 0)]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_worker_closes_the_old_attempt_and_opens_the_new_one_first() {
    let server = Server::start(
        "cache-lost",
        HeartbeatConfig {
            interval: Duration::from_millis(50),
            timeout: Duration::from_millis(3000),
        },
    )
    .await;
    let channel = server.channel().await;
    let ha = FakeHost::start(host_stats(10), false).await;
    let hb = FakeHost::start(host_stats(20), false).await;
    let mut a = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7601", &ha.endpoint),
    )
    .await;
    let _alive = a.keep_alive(Duration::from_millis(50));
    let mut b = FakeWorker::join_with(
        channel.clone(),
        worker_with_host("http://127.0.0.1:7602", &hb.endpoint),
    )
    .await;
    let spec = JobSpec {
        schedule: "domain".into(),
        ..cached(spec(64, 32, 2))
    };
    let id = submit(&channel, spec).await;
    a.setup_and_tiles(1).await;
    b.setup_and_tiles(1).await;
    // b never heartbeats: it is lost, and the job starts attempt 1 on a alone, with its
    // walls all on a's host, opened after attempt 0's were closed everywhere.
    match a.next().await {
        Command::Cancel(r) => assert_eq!(r.attempt, 0),
        other => panic!("expected the old attempt's cancel, got {other:?}"),
    }
    let (setup, tiles) = a.setup_and_tiles(2).await;
    assert_eq!(setup.attempt, 1);
    let table = setup.routing.unwrap();
    assert_eq!(table.attempt, 1);
    assert_eq!(table.cache_hosts.len(), 1);
    assert_eq!(table.cache_hosts[0].endpoint, ha.endpoint);
    assert_eq!(table.wall_hosts, [0; 12]);
    assert_eq!(ha.trace(), [("open", 0), ("close", 0), ("open", 1)]);
    assert_eq!(ha.opens()[1].walls, walls_of(&[0, 1]));
    assert_eq!(hb.trace(), [("open", 0), ("close", 0)]);
    assert!(tiles.iter().all(|t| t.attempt == 1));

    a.report(all_credit(&id, 1, 1, &tiles)).await.unwrap();
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    assert_eq!(ha.trace().last(), Some(&("close", 1)));
    let s = job.stats.unwrap().ray_cache.unwrap();
    // Three closes: a's host twice, b's once.
    assert_eq!(s.outer_hits, 10 + 10 + 20);
    assert!(s.lost_hosts.is_empty(), "{:?}", s.lost_hosts);
}
