//! The coordinator's ClusterService on a live server over real TCP, with a test playing
//! the worker through the generated tonic client: registration (and its refusals),
//! heartbeats, the assignment stream (JobSetup, tiles, releases), contribution reports
//! with credit and fixed-point pixel sums (dedupe by sequence, failures, over-returned
//! credit), cancellation, and a worker lost to silence.

use std::path::{Path, PathBuf};
use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_coordinator::cluster::ClusterOptions;
use dray_coordinator::dispatch::{TILE_CREDIT, package_checksum};
use dray_coordinator::membership::{HeartbeatConfig, VERSION};
use dray_proto::v1::assignment::Command;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    Assignment, CancelJobRequest, GetImageRequest, GetJobRequest, GetRoutingTableRequest,
    HeartbeatRequest, ImageFormat, Job, JobSetup, JobSpec, JobState, RayCounts,
    RegisterWorkerRequest, ReportContributionsRequest, ReportQueuesRequest, SubmitJobRequest, Tile,
    TileCredit, WatchAssignmentsRequest,
};
use tonic::Code;
use tonic::codec::Streaming;
use tonic::transport::Channel;

/// Longest wait for anything the coordinator should do promptly; only reached when a
/// test fails.
const PATIENCE: Duration = Duration::from_secs(20);

/// A coordinator on a free port; stopped (and its work directory removed) when dropped,
/// even if the test panics.
struct Server {
    addr: std::net::SocketAddr,
    work_dir: PathBuf,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    async fn start(name: &str, heartbeat: HeartbeatConfig) -> Server {
        Server::start_in(name, heartbeat, &std::env::temp_dir()).await
    }

    async fn start_in(name: &str, heartbeat: HeartbeatConfig, root: &Path) -> Server {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let work_dir =
            std::env::temp_dir().join(format!("dray-cluster-test-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&work_dir);
        let coordinator = Coordinator::new(root, 1)
            .unwrap()
            .with_cluster_options(ClusterOptions {
                heartbeat,
                work_dir: work_dir.clone(),
                memory_packages: None,
            });
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            dray_coordinator::serve(listener, coordinator, async {
                rx.await.ok();
            })
            .await
            .unwrap();
        });
        Server {
            addr,
            work_dir,
            stop: Some(tx),
            task,
        }
    }

    async fn channel(&self) -> Channel {
        tonic::transport::Endpoint::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        self.task.abort();
        let _ = std::fs::remove_dir_all(&self.work_dir);
    }
}

fn slow_heartbeat() -> HeartbeatConfig {
    HeartbeatConfig {
        interval: Duration::from_secs(1),
        timeout: Duration::from_secs(60),
    }
}

fn register_request(endpoint: &str) -> RegisterWorkerRequest {
    RegisterWorkerRequest {
        endpoint: endpoint.into(),
        threads: 2,
        memory_budget_bytes: 0,
        version: VERSION.into(),
        record_format: dray_proto::RAY_RECORD_FORMAT,
        hostname: "test".into(),
    }
}

/// A test playing one worker.
struct FakeWorker {
    id: String,
    client: ClusterServiceClient<Channel>,
    stream: Streaming<Assignment>,
}

impl FakeWorker {
    async fn join(channel: Channel, endpoint: &str) -> FakeWorker {
        let mut client = ClusterServiceClient::new(channel);
        let r = client
            .register_worker(register_request(endpoint))
            .await
            .unwrap()
            .into_inner();
        assert!(!r.worker_id.is_empty());
        assert!(r.heartbeat_interval.is_some() && r.heartbeat_timeout.is_some());
        let stream = client
            .watch_assignments(WatchAssignmentsRequest {
                worker_id: r.worker_id.clone(),
            })
            .await
            .unwrap()
            .into_inner();
        FakeWorker {
            id: r.worker_id,
            client,
            stream,
        }
    }

    async fn next(&mut self) -> Command {
        tokio::time::timeout(PATIENCE, self.stream.message())
            .await
            .expect("no assignment in time")
            .expect("assignment stream failed")
            .expect("assignment stream ended")
            .command
            .expect("assignment without a command")
    }

    /// The JobSetup, then tiles until `tiles_total` are accounted for.
    async fn setup_and_tiles(&mut self, expect_tiles: usize) -> (JobSetup, Vec<Tile>) {
        let setup = match self.next().await {
            Command::Setup(s) => s,
            other => panic!("expected a JobSetup first, got {other:?}"),
        };
        let mut tiles = Vec::new();
        while tiles.len() < expect_tiles {
            match self.next().await {
                Command::Tiles(t) => {
                    assert_eq!(t.job_id, setup.job_id);
                    tiles.extend(t.tiles);
                }
                other => panic!("expected tiles, got {other:?}"),
            }
        }
        (setup, tiles)
    }

    async fn report(&mut self, r: ReportContributionsRequest) -> Result<bool, tonic::Status> {
        self.client
            .report_contributions(ReportContributionsRequest {
                worker_id: self.id.clone(),
                ..r
            })
            .await
            .map(|r| r.into_inner().job_active)
    }
}

fn spec(width: u32, height: u32, domains: u32) -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width,
        height,
        spp: 1,
        domains,
        ..Default::default()
    }
}

async fn submit(channel: &Channel, spec: JobSpec) -> String {
    RenderServiceClient::new(channel.clone())
        .submit_job(SubmitJobRequest { spec: Some(spec) })
        .await
        .unwrap()
        .into_inner()
        .job_id
}

async fn get_job(channel: &Channel, id: &str) -> Job {
    RenderServiceClient::new(channel.clone())
        .get_job(GetJobRequest { job_id: id.into() })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap()
}

/// Poll GetJob until the job is in `state` (the ledger updates synchronously with each
/// report, so this returns at once unless something is wrong).
async fn wait_state(channel: &Channel, id: &str, state: JobState) -> Job {
    let deadline = tokio::time::Instant::now() + PATIENCE;
    loop {
        let job = get_job(channel, id).await;
        let p = job.progress.clone().unwrap();
        if p.state() == state {
            return job;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "job {id} is {:?} ({}), expected {state:?}",
            p.state(),
            p.error
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

fn fixed(v: f64) -> i64 {
    (v * (1u64 << 24) as f64) as i64
}

/// Read an EXR file's RGB as (width, pixels).
fn read_exr(bytes: &[u8]) -> (usize, Vec<[f32; 3]>) {
    use exr::prelude::*;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgb_channels(
            |res, _| (res.width(), vec![[0f32; 3]; res.width() * res.height()]),
            |(w, px), pos, (r, g, b): (f32, f32, f32)| px[pos.y() * *w + pos.x()] = [r, g, b],
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .unwrap();
    image.layer_data.channel_data.pixels
}

fn assert_dir_gone(dir: &Path) {
    assert!(
        !dir.exists(),
        "the job's package {} was not removed",
        dir.display()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_runs_on_a_registered_worker_and_returns_its_sums() {
    let server = Server::start("run", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;

    // 70x40 pixels: 3 x 2 tiles of at most 32, edge tiles smaller.
    let id = submit(&channel, spec(70, 40, 3)).await;
    let (setup, tiles) = w.setup_and_tiles(6).await;
    assert_eq!(setup.job_id, id);
    assert_eq!(setup.tile_size, 32);
    assert_eq!(setup.tile_credit, 1 << 62);
    assert_eq!(setup.domain_count, 3);
    let s = setup.spec.clone().unwrap();
    assert_eq!(
        (s.width, s.height, s.spp, s.integrator.as_str()),
        (70, 40, 1, "path")
    );
    assert_eq!(s.max_depth, Some(5));
    assert_eq!(
        s.camera.as_deref(),
        Some("0"),
        "camera resolved to an index"
    );
    assert_eq!((s.domains, s.layout.as_str()), (3, "kd"));
    assert!(setup.environment.is_some());
    assert!(
        setup.effects.iter().any(|e| e == "direct_light"),
        "cornell is lit: {:?}",
        setup.effects
    );
    // The package is real, absolute, and its checksum is the manifest's.
    let pkg = PathBuf::from(&setup.package_path);
    assert!(pkg.is_absolute() && pkg.starts_with(&server.work_dir));
    let manifest = std::fs::read(pkg.join("manifest.json")).unwrap();
    assert_eq!(setup.package_checksum, package_checksum(&manifest));
    let opened = dray_scene::partition::open_package(&pkg).unwrap();
    assert_eq!(opened.domain_count(), 3);
    // Routing: version 1, every domain to the only worker.
    let routing = setup.routing.clone().unwrap();
    assert_eq!(routing.version, 1);
    assert_eq!(routing.workers.len(), 1);
    assert_eq!(routing.workers[0].worker_id, w.id);
    assert_eq!(routing.workers[0].endpoint, "http://127.0.0.1:7001");
    let domains: Vec<u32> = routing.routes.iter().map(|r| r.domain).collect();
    assert_eq!(domains, [0, 1, 2]);
    assert!(routing.routes.iter().all(|r| r.worker_id == w.id));
    let fetched = w
        .client
        .get_routing_table(GetRoutingTableRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner()
        .routing
        .unwrap();
    assert_eq!(fetched, routing);
    // Tiles: row-major, index = (y0/32)*3 + x0/32, full credit.
    let mut idx: Vec<u32> = tiles.iter().map(|t| t.index).collect();
    idx.sort();
    assert_eq!(idx, [0, 1, 2, 3, 4, 5]);
    for t in &tiles {
        assert_eq!(t.index, (t.y0 / 32) * 3 + t.x0 / 32);
        assert_eq!(t.credit, TILE_CREDIT);
        assert_eq!(t.attempt, 0);
        assert_eq!(t.width, 32.min(70 - t.x0));
        assert_eq!(t.height, 32.min(40 - t.y0));
    }

    // Queue reports are stored and answered with the routing version.
    let v = w
        .client
        .report_queues(ReportQueuesRequest {
            worker_id: w.id.clone(),
            job_id: id.clone(),
            routing_version: 1,
            queues: vec![
                dray_proto::v1::DomainQueue {
                    domain: 0,
                    rays_queued: 40,
                    resident: true,
                    resident_bytes: 1000,
                },
                dray_proto::v1::DomainQueue {
                    domain: 2,
                    rays_queued: 2,
                    resident: true,
                    resident_bytes: 1000,
                },
            ],
            memory_used_bytes: 1,
        })
        .await
        .unwrap()
        .into_inner()
        .routing_version;
    assert_eq!(v, 1);
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!(p.rays_in_flight, 42, "rays queued at the workers");

    // Report 1: two pixel sums (one pixel twice) and half of every tile's credit.
    let half = TILE_CREDIT / 2;
    let first = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        pixels: vec![0, 71, 0],
        sums: vec![
            fixed(0.5),
            fixed(0.25),
            fixed(1.0),
            fixed(2.0),
            0,
            fixed(0.125),
            fixed(0.5),
            fixed(0.25),
            0,
        ],
        credits: (0..6)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        traced: Some(RayCounts {
            camera: 10,
            shadow: 7,
            ..Default::default()
        }),
        nonfinite: 1,
        ray_bytes_sent: 640,
        ..Default::default()
    };
    assert!(w.report(first.clone()).await.unwrap());
    // The same sequence again (a retry after a lost answer) changes nothing.
    assert!(w.report(first.clone()).await.unwrap());
    let job = get_job(&channel, &id).await;
    let p = job.progress.unwrap();
    assert_eq!(p.state(), JobState::Running);
    assert_eq!((p.tiles_done, p.tiles_total), (0, 6));
    assert_eq!(p.rays_traced, 17, "the repeated report was counted twice");
    let stats = job.stats.unwrap();
    assert_eq!((stats.workers, stats.domains), (1, 3));
    assert_eq!(stats.ray_bytes_sent, 640);

    // A malformed report is refused and changes nothing.
    let bad = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        pixels: vec![1],
        sums: vec![1, 2],
        ..Default::default()
    };
    assert_eq!(
        w.report(bad).await.unwrap_err().code(),
        Code::InvalidArgument
    );
    let outside = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        pixels: vec![70 * 40],
        sums: vec![1, 2, 3],
        ..Default::default()
    };
    assert_eq!(
        w.report(outside).await.unwrap_err().code(),
        Code::InvalidArgument
    );

    // Report 3 arrives before report 2 (out of order is fine): tiles 0..3 complete.
    let third = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 3,
        pixels: vec![70 * 40 - 1],
        sums: vec![fixed(3.0), fixed(3.0), fixed(3.0)],
        credits: (0..3)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        traced: Some(RayCounts {
            diffuse: 5,
            ..Default::default()
        }),
        ..Default::default()
    };
    assert!(w.report(third).await.unwrap());
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!((p.tiles_done, p.rays_traced), (3, 22));
    assert!(p.eta.is_some(), "an ETA once some tiles are done");

    // Report 2 returns the rest: the job succeeds and the worker is told to finish.
    let second = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        credits: (3..6)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        ..Default::default()
    };
    assert!(!w.report(second).await.unwrap(), "the job is over");
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    assert_eq!(job.progress.unwrap().tiles_done, 6);
    let stats = job.stats.unwrap();
    assert_eq!(stats.nonfinite, 1);
    assert_eq!(
        stats.rays.unwrap(),
        RayCounts {
            camera: 10,
            shadow: 7,
            diffuse: 5,
            ..Default::default()
        }
    );
    match w.next().await {
        Command::Finish(r) => assert_eq!(r.job_id, id),
        other => panic!("expected a finish release, got {other:?}"),
    }
    assert_dir_gone(&pkg);
    // Reports for a finished job are told it is over.
    let late = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 4,
        ..Default::default()
    };
    assert!(!w.report(late).await.unwrap());

    // The image holds exactly the sums sent (spp 1: radiance = sum / 2^24).
    let img = RenderServiceClient::new(channel.clone())
        .get_image(GetImageRequest {
            job_id: id.clone(),
            format: ImageFormat::Exr as i32,
            exposure: 0.0,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((img.width, img.height), (70, 40));
    let (width, px) = read_exr(&img.data);
    assert_eq!(width, 70);
    assert_eq!(px[0], [1.0, 0.5, 1.0]);
    assert_eq!(px[71], [2.0, 0.0, 0.125]);
    assert_eq!(px[70 * 40 - 1], [3.0, 3.0, 3.0]);
    let lit = px.iter().filter(|p| **p != [0.0; 3]).count();
    assert_eq!(lit, 3, "only the reported pixels are lit");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_and_domains_are_dealt_round_robin_over_two_workers() {
    let server = Server::start("two", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let mut b = FakeWorker::join(channel.clone(), "http://127.0.0.1:7002").await;
    // 100x70: 4 x 3 = 12 tiles, 6 each. Domains left to the coordinator.
    let id = submit(&channel, spec(100, 70, 0)).await;
    let (sa, ta) = a.setup_and_tiles(6).await;
    let (sb, tb) = b.setup_and_tiles(6).await;
    assert_eq!(sa, sb, "every worker of a job gets the same setup");
    let routing = sa.routing.unwrap();
    let ids: Vec<&str> = routing
        .workers
        .iter()
        .map(|w| w.worker_id.as_str())
        .collect();
    assert_eq!(ids.len(), 2);
    assert!(ids.contains(&a.id.as_str()) && ids.contains(&b.id.as_str()));
    assert!(sa.domain_count >= 1);
    assert_eq!(routing.routes.len(), sa.domain_count as usize);
    for r in &routing.routes {
        assert_eq!(r.worker_id, ids[r.domain as usize % 2]);
    }
    let job = get_job(&channel, &id).await;
    assert_eq!(job.spec.unwrap().domains, sa.domain_count);
    let first = if ids[0] == a.id { &ta } else { &tb };
    let second = if ids[0] == a.id { &tb } else { &ta };
    assert!(first.iter().all(|t| t.index % 2 == 0));
    assert!(second.iter().all(|t| t.index % 2 == 1));
    // Both workers return their tiles' credit: the job succeeds once both have.
    for (w, tiles) in [(&mut a, &ta), (&mut b, &tb)] {
        let r = ReportContributionsRequest {
            job_id: id.clone(),
            sequence: 1,
            credits: tiles
                .iter()
                .map(|t| TileCredit {
                    tile: t.index,
                    credit: t.credit,
                })
                .collect(),
            ..Default::default()
        };
        w.report(r).await.unwrap();
    }
    wait_state(&channel, &id, JobState::Succeeded).await;
    assert!(matches!(a.next().await, Command::Finish(_)));
    assert!(matches!(b.next().await, Command::Finish(_)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_failure_fails_the_job_and_cancels_it_everywhere() {
    let server = Server::start("fail", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(32, 32, 1)).await;
    let (setup, _) = w.setup_and_tiles(1).await;
    let pkg = PathBuf::from(setup.package_path);
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        failure: "domain 0: checksum mismatch".into(),
        ..Default::default()
    };
    assert!(!w.report(r).await.unwrap());
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains("domain 0: checksum mismatch") && err.contains(&w.id),
        "{err}"
    );
    match w.next().await {
        Command::Cancel(r) => {
            assert_eq!(r.job_id, id);
            assert!(r.reason.contains("checksum mismatch"), "{}", r.reason);
        }
        other => panic!("expected a cancel release, got {other:?}"),
    }
    assert_dir_gone(&pkg);
    let again = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        ..Default::default()
    };
    assert!(!w.report(again).await.unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn credit_beyond_a_tiles_start_fails_the_job() {
    let server = Server::start("overdraw", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(64, 32, 1)).await;
    w.setup_and_tiles(2).await;
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![
            TileCredit {
                tile: 1,
                credit: TILE_CREDIT,
            },
            TileCredit { tile: 1, credit: 1 },
        ],
        ..Default::default()
    };
    assert!(!w.report(r).await.unwrap());
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains("tile 1") && err.contains("counted twice"),
        "{err}"
    );
    assert!(matches!(w.next().await, Command::Cancel(_)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_sends_a_cancel_release_and_later_reports_are_inactive() {
    let server = Server::start("cancel", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(64, 64, 2)).await;
    let (setup, _) = w.setup_and_tiles(4).await;
    let r = RenderServiceClient::new(channel.clone())
        .cancel_job(CancelJobRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        r.job.unwrap().progress.unwrap().state(),
        JobState::Cancelled
    );
    match w.next().await {
        Command::Cancel(r) => assert_eq!(r.job_id, id),
        other => panic!("expected a cancel release, got {other:?}"),
    }
    assert_dir_gone(Path::new(&setup.package_path));
    let late = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![TileCredit {
            tile: 0,
            credit: TILE_CREDIT,
        }],
        ..Default::default()
    };
    assert!(!w.report(late).await.unwrap());
    assert_eq!(
        get_job(&channel, &id).await.progress.unwrap().state(),
        JobState::Cancelled
    );
    let missing = w
        .client
        .get_routing_table(GetRoutingTableRequest { job_id: id.clone() })
        .await
        .unwrap_err();
    assert_eq!(missing.code(), Code::NotFound);
    // An unknown job is inactive too.
    let unknown = ReportContributionsRequest {
        job_id: "no-such-job".into(),
        sequence: 1,
        ..Default::default()
    };
    assert!(!w.report(unknown).await.unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registration_refuses_mismatches_and_heartbeats_ask_strangers_to_reregister() {
    let server = Server::start("register", slow_heartbeat()).await;
    let mut c = ClusterServiceClient::new(server.channel().await);
    let old = RegisterWorkerRequest {
        version: "0.0.0-other".into(),
        ..register_request("http://127.0.0.1:7001")
    };
    let e = c.register_worker(old).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().contains("0.0.0-other") && e.message().contains(VERSION));
    let format = RegisterWorkerRequest {
        record_format: dray_proto::RAY_RECORD_FORMAT + 1,
        ..register_request("http://127.0.0.1:7001")
    };
    let e = c.register_worker(format).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().starts_with("record_format:"), "{}", e.message());
    let e = c
        .register_worker(register_request("nowhere"))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    for bad in ["http://", "https:///x", ""] {
        let e = c.register_worker(register_request(bad)).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{bad:?}");
    }
    // A short host name is fine.
    c.register_worker(register_request("http://w"))
        .await
        .unwrap();

    let hb = |id: &str| HeartbeatRequest {
        worker_id: id.into(),
        memory_used_bytes: 0,
        rays_queued: 0,
    };
    let r = c.heartbeat(hb("w1-00000000")).await.unwrap().into_inner();
    assert!(r.reregister, "an unknown id must re-register");
    let id = c
        .register_worker(register_request("http://127.0.0.1:7001"))
        .await
        .unwrap()
        .into_inner()
        .worker_id;
    let r = c.heartbeat(hb(&id)).await.unwrap().into_inner();
    assert!(!r.reregister);
    // Watching assignments needs a registered id.
    let e = c
        .watch_assignments(WatchAssignmentsRequest {
            worker_id: "stranger".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_worker_is_dropped_and_its_jobs_fail_naming_it() {
    let server = Server::start(
        "lost",
        HeartbeatConfig {
            interval: Duration::from_millis(50),
            timeout: Duration::from_millis(300),
        },
    )
    .await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7009").await;
    let id = submit(&channel, spec(32, 32, 1)).await;
    w.setup_and_tiles(1).await;
    // The worker never heartbeats: within ~1.25 timeouts it is dropped.
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains(&w.id) && err.contains("http://127.0.0.1:7009"),
        "{err}"
    );
    let r = w
        .client
        .heartbeat(HeartbeatRequest {
            worker_id: w.id.clone(),
            memory_used_bytes: 0,
            rays_queued: 0,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(r.reregister);
    // Its assignment stream ends: it is no longer a member (it learns to drop its jobs
    // from the heartbeat answer).
    let end = tokio::time::timeout(PATIENCE, w.stream.message())
        .await
        .expect("the dropped worker's stream did not end")
        .unwrap();
    assert!(end.is_none(), "unexpected command {end:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_package_is_used_as_it_is_and_kept() {
    let root =
        std::env::temp_dir().join(format!("dray-cluster-test-{}-pkgroot", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    struct Cleanup(PathBuf);
    impl Drop for Cleanup {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
    let _cleanup = Cleanup(root.clone());
    let scene = dray_scene::load("cornell").unwrap();
    let pkg = root.join("cornell-pkg");
    dray_scene::partition::write_scene_package(
        &pkg,
        &scene,
        &dray_scene::partition::LayoutSpec::GridCount(2),
    )
    .unwrap();
    let server = Server::start_in("pkg", slow_heartbeat(), &root).await;
    let channel = server.channel().await;
    let mut render = RenderServiceClient::new(channel.clone());
    let package_spec = JobSpec {
        scene: "cornell-pkg".into(),
        ..spec(32, 32, 0)
    };

    // Without workers a package cannot render (the in-process path needs a whole mesh).
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(package_spec.clone()),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition, "{}", e.message());
    // A package cannot be moved.
    let moved = JobSpec {
        translate: Some(dray_proto::v1::Vec3 {
            x: 1.0,
            y: 0.0,
            z: 0.0,
        }),
        ..package_spec.clone()
    };
    let e = render
        .submit_job(SubmitJobRequest { spec: Some(moved) })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("translate:"), "{}", e.message());
    // A directory that is not a package is refused.
    std::fs::create_dir_all(root.join("empty")).unwrap();
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(JobSpec {
                scene: "empty".into(),
                ..spec(32, 32, 0)
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);

    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, package_spec).await;
    let (setup, tiles) = w.setup_and_tiles(1).await;
    assert_eq!(
        PathBuf::from(&setup.package_path),
        pkg.canonicalize().unwrap()
    );
    assert_eq!(setup.domain_count, 2);
    let s = setup.spec.unwrap();
    assert_eq!((s.domains, s.layout.as_str()), (2, "grid"));
    assert_eq!(s.camera.as_deref(), Some("0"));
    let manifest = std::fs::read(pkg.join("manifest.json")).unwrap();
    assert_eq!(setup.package_checksum, package_checksum(&manifest));
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![TileCredit {
            tile: tiles[0].index,
            credit: TILE_CREDIT,
        }],
        ..Default::default()
    };
    w.report(r).await.unwrap();
    wait_state(&channel, &id, JobState::Succeeded).await;
    assert!(
        pkg.join("manifest.json").is_file(),
        "the user's package must not be removed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cluster_service_is_listed_and_healthy_and_shutdown_ends_worker_streams() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let coordinator = Coordinator::new(&std::env::temp_dir(), 1).unwrap();
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let mut task = tokio::spawn(dray_coordinator::serve(listener, coordinator, async {
        rx.await.ok();
    }));
    struct Abort(tokio::task::AbortHandle);
    impl Drop for Abort {
        fn drop(&mut self) {
            self.0.abort();
        }
    }
    let _abort = Abort(task.abort_handle());
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();

    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let h = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "dray.v1.ClusterService".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        h.status(),
        tonic_health::pb::health_check_response::ServingStatus::Serving
    );
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let mut reflect = ServerReflectionClient::new(channel.clone());
    let req = tonic_reflection::pb::v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = reflect
        .server_reflection_info(tokio_stream::iter([req]))
        .await
        .unwrap()
        .into_inner();
    match replies.message().await.unwrap().unwrap().message_response {
        Some(MessageResponse::ListServicesResponse(l)) => {
            let names: Vec<String> = l.service.into_iter().map(|s| s.name).collect();
            for want in ["dray.v1.RenderService", "dray.v1.ClusterService"] {
                assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
            }
        }
        other => panic!("unexpected reflection reply {other:?}"),
    }
    drop(replies);
    drop(reflect);

    // A worker's stream is open; shutting down must still finish.
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    tx.send(()).unwrap();
    let end = tokio::time::timeout(PATIENCE, w.stream.message())
        .await
        .expect("the stream did not end on shutdown");
    assert!(matches!(end, Ok(None)), "{end:?}");
    drop(w);
    drop(health);
    drop(channel);
    tokio::time::timeout(PATIENCE, &mut task)
        .await
        .expect("serve did not return after shutdown")
        .unwrap()
        .unwrap();
}
