//! A malicious coordinator against a real worker (`dray_worker::run`, its real gRPC
//! client and assignment loop), on loopback: this file's coordinator is a real tonic
//! `ClusterService` server that registers the worker and sends it hostile setups.
//!
//! docs/security.md "Hardening, second round", item 5: one `JobSetup` with `domain_count =
//! 0xFFFFFFFF` made a worker
//! allocate 103 GB and abort. Item 9: a coordinator could make a worker hold 20,000 job
//! setups. Now each is refused with a failure report naming the bound, and the worker
//! goes on taking the next setup.

use std::collections::HashMap;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_proto::v1::cluster_service_server::{ClusterService, ClusterServiceServer};
use dray_proto::v1::{
    Assignment, GetPeerPassRequest, GetPeerPassResponse, GetRoutingTableRequest,
    GetRoutingTableResponse, HeartbeatRequest, HeartbeatResponse, JobRelease, JobSetup, JobSpec,
    RegisterCacheHostRequest, RegisterCacheHostResponse, RegisterWorkerRequest,
    RegisterWorkerResponse, ReportContributionsRequest, ReportContributionsResponse,
    ReportQueuesRequest, ReportQueuesResponse, Rgb, RoutingTable, WatchAssignmentsRequest,
    assignment::Command,
};
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::{LayoutSpec, open_package, write_scene_package};
use dray_worker::WorkerConfig;
use dray_worker::setup_bounds::MAX_JOBS;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

type Assignments = Pin<Box<dyn Stream<Item = Result<Assignment, Status>> + Send>>;

/// The hostile coordinator: hands its one worker the assignments the test sends, and
/// keeps every failure the worker reports, by job id.
struct Coordinator {
    assignments: Mutex<Option<mpsc::Receiver<Result<Assignment, Status>>>>,
    failures: Arc<Mutex<HashMap<String, String>>>,
}

#[tonic::async_trait]
impl ClusterService for Coordinator {
    async fn register_worker(
        &self,
        _r: Request<RegisterWorkerRequest>,
    ) -> Result<Response<RegisterWorkerResponse>, Status> {
        Ok(Response::new(RegisterWorkerResponse {
            // No heartbeat_interval: the worker beats every second.
            worker_id: "w1".into(),
            ..Default::default()
        }))
    }
    async fn heartbeat(
        &self,
        _r: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatResponse>, Status> {
        Ok(Response::new(HeartbeatResponse::default()))
    }
    type WatchAssignmentsStream = Assignments;
    async fn watch_assignments(
        &self,
        _r: Request<WatchAssignmentsRequest>,
    ) -> Result<Response<Assignments>, Status> {
        let rx = self
            .assignments
            .lock()
            .unwrap()
            .take()
            .ok_or_else(|| Status::failed_precondition("one assignment stream only"))?;
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }
    async fn get_routing_table(
        &self,
        _r: Request<GetRoutingTableRequest>,
    ) -> Result<Response<GetRoutingTableResponse>, Status> {
        Err(Status::unimplemented("not in this test"))
    }
    async fn report_queues(
        &self,
        _r: Request<ReportQueuesRequest>,
    ) -> Result<Response<ReportQueuesResponse>, Status> {
        Ok(Response::new(ReportQueuesResponse::default()))
    }
    async fn report_contributions(
        &self,
        r: Request<ReportContributionsRequest>,
    ) -> Result<Response<ReportContributionsResponse>, Status> {
        let r = r.into_inner();
        // Reports of jobs that run (idle time rides along) keep them running.
        let job_active = r.failure.is_empty();
        if !job_active {
            self.failures.lock().unwrap().insert(r.job_id, r.failure);
        }
        Ok(Response::new(ReportContributionsResponse { job_active }))
    }
    async fn register_cache_host(
        &self,
        _r: Request<RegisterCacheHostRequest>,
    ) -> Result<Response<RegisterCacheHostResponse>, Status> {
        Err(Status::unimplemented("not in this test"))
    }
    async fn get_peer_pass(
        &self,
        _r: Request<GetPeerPassRequest>,
    ) -> Result<Response<GetPeerPassResponse>, Status> {
        Err(Status::unimplemented("not in this test"))
    }
}

/// A setup of the Cornell box package at `dir` (valid: the worker plans it).
fn setup(id: &str, dir: &std::path::Path, sum: &str, domains: u32) -> Assignment {
    Assignment {
        command: Some(Command::Setup(JobSetup {
            job_id: id.into(),
            spec: Some(JobSpec {
                width: 16,
                height: 16,
                spp: 1,
                integrator: "path".into(),
                max_depth: Some(5),
                ao_samples: Some(16),
                ..Default::default()
            }),
            environment: Some(Rgb::default()),
            package_path: dir.to_str().unwrap().into(),
            package_checksum: sum.into(),
            domain_count: domains,
            tile_size: 16,
            tile_credit: 1 << 40,
            routing: Some(RoutingTable {
                job_id: id.into(),
                version: 1,
                local: true,
                ..Default::default()
            }),
            schedule: "image-plane".into(),
            ..Default::default()
        })),
    }
}

/// Wait (bounded, failing loudly) for the worker's failure report for `id`.
async fn failure_of(failures: &Mutex<HashMap<String, String>>, id: &str) -> String {
    for _ in 0..1200 {
        if let Some(f) = failures.lock().unwrap().get(id) {
            return f.clone();
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!(
        "no failure reported for {id} within 60 s; reported: {:?}",
        failures.lock().unwrap()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_setups_are_refused_and_the_worker_goes_on() {
    let dir = std::env::temp_dir().join(format!("dray-worker-bounds-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = dray_scene::load("cornell").unwrap();
    write_scene_package(&dir, &scene, &LayoutSpec::GridCount(2)).unwrap();
    let sum = to_hex(checksum(&std::fs::read(dir.join(MANIFEST_FILE)).unwrap()));
    let domains = open_package(&dir).unwrap().domain_count();

    let (tx, rx) = mpsc::channel(4 * MAX_JOBS);
    let failures = Arc::new(Mutex::new(HashMap::new()));
    let coordinator = Coordinator {
        assignments: Mutex::new(Some(rx)),
        failures: failures.clone(),
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap();
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(ClusterServiceServer::new(coordinator))
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let config = WorkerConfig {
        coordinator: format!("http://{address}"),
        threads: 1,
        package_fetch: dray_worker::package_fetch::FetchMode::Never,
        ..WorkerConfig::default()
    };
    let worker_listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let worker = tokio::spawn(dray_worker::run(config, worker_listener, async move {
        let _ = stopped.await;
    }));
    let send = |a: Assignment| {
        let tx = tx.clone();
        async move { tx.send(Ok(a)).await.unwrap() }
    };

    // Item 5: the setup that made the worker allocate 103 GB (this test process would
    // abort); then fields beyond the coordinator's limits, each named.
    send(setup("huge-domains", &dir, &sum, u32::MAX)).await;
    let f = failure_of(&failures, "huge-domains").await;
    assert!(f.contains("domain_count") && f.contains("1..=65536"), "{f}");
    let mut wide = setup("huge-image", &dir, &sum, domains);
    if let Some(Command::Setup(s)) = &mut wide.command {
        s.spec.as_mut().unwrap().width = u32::MAX;
    }
    send(wide).await;
    let f = failure_of(&failures, "huge-image").await;
    assert!(f.contains("spec.width"), "{f}");

    // Item 9: MAX_JOBS jobs are held, the next is refused; a released one makes room.
    for i in 0..MAX_JOBS {
        send(setup(&format!("job-{i}"), &dir, &sum, domains)).await;
    }
    send(setup("one-too-many", &dir, &sum, domains)).await;
    let f = failure_of(&failures, "one-too-many").await;
    assert!(f.contains(&format!("already holds {MAX_JOBS} jobs")), "{f}");
    // Setups are taken in order: every earlier one was set up, none failed.
    {
        let g = failures.lock().unwrap();
        let failed: Vec<&String> = g.keys().filter(|k| k.starts_with("job-")).collect();
        assert!(failed.is_empty(), "valid setups failed: {g:?}");
    }
    send(Assignment {
        command: Some(Command::Finish(JobRelease {
            job_id: "job-0".into(),
            attempt: 0,
            reason: "done".into(),
        })),
    })
    .await;
    send(setup("after-a-release", &dir, &sum, domains)).await;
    // A marker behind it: once its refusal arrives, the setup before it was handled.
    send(setup("marker", &dir, &sum, 0)).await;
    let f = failure_of(&failures, "marker").await;
    assert!(f.contains("domain_count"), "{f}");
    assert!(
        !failures.lock().unwrap().contains_key("after-a-release"),
        "{:?}",
        failures.lock().unwrap().get("after-a-release")
    );
    assert!(!worker.is_finished(), "the worker stopped");

    let _ = stop.send(());
    let _ = tokio::time::timeout(Duration::from_secs(30), worker).await;
    let _ = std::fs::remove_dir_all(&dir);
}
