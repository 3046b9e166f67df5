//! A coordinator on a live server over real TCP, and tests playing its workers through
//! the generated tonic client (the real protocol, no worker code): shared by the
//! cluster and scheduling tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_coordinator::cluster::ClusterOptions;
use dray_coordinator::membership::{HeartbeatConfig, VERSION};
use dray_coordinator::scheduler::SchedulerOptions;
use dray_proto::v1::assignment::Command;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    Assignment, DomainQueue, GetJobRequest, HeartbeatRequest, Job, JobSetup, JobSpec, JobState,
    RegisterWorkerRequest, ReportContributionsRequest, ReportQueuesRequest, SubmitJobRequest, Tile,
    WatchAssignmentsRequest,
};
use tonic::codec::Streaming;
use tonic::transport::Channel;

/// Longest wait for anything the coordinator should do promptly: a hang guard, only
/// reached when a test fails (generous, as CI machines are loaded).
pub const PATIENCE: Duration = Duration::from_secs(120);

/// A coordinator on a free port; stopped (and its work directory removed) when dropped,
/// even if the test panics.
pub struct Server {
    pub addr: std::net::SocketAddr,
    pub work_dir: PathBuf,
    /// The coordinator served (a handle on the same state), for looking inside.
    pub coordinator: Coordinator,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    pub async fn start(name: &str, heartbeat: HeartbeatConfig) -> Server {
        Server::start_in(name, heartbeat, &std::env::temp_dir()).await
    }

    pub async fn start_in(name: &str, heartbeat: HeartbeatConfig, root: &Path) -> Server {
        Server::start_with(name, heartbeat, SchedulerOptions::default(), root).await
    }

    pub async fn start_with(
        name: &str,
        heartbeat: HeartbeatConfig,
        scheduler: SchedulerOptions,
        root: &Path,
    ) -> Server {
        let stall = Some(dray_coordinator::cluster::DEFAULT_STALL_TIMEOUT);
        Server::start_full(name, heartbeat, scheduler, stall, root).await
    }

    /// [`Server::start_with`], failing jobs without progress for `stall_timeout`.
    pub async fn start_full(
        name: &str,
        heartbeat: HeartbeatConfig,
        scheduler: SchedulerOptions,
        stall_timeout: Option<std::time::Duration>,
        root: &Path,
    ) -> Server {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let work_dir =
            std::env::temp_dir().join(format!("dray-cluster-test-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&work_dir);
        // A work directory must exist (jobs make only their own folders in it).
        std::fs::create_dir_all(&work_dir).unwrap();
        let coordinator = Coordinator::new(root, 1)
            .unwrap()
            .with_cluster_options(ClusterOptions {
                heartbeat,
                work_dir: work_dir.clone().into(),
                memory_packages: None,
                scheduler,
                clients: dray_net::ClientOptions::plain(),
                stall_timeout,
                // These tests register fake stand-alone cache hosts.
                cache_hosts: true,
                max_running_jobs: None,
            });
        let served = coordinator.clone();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            dray_coordinator::serve(listener, served, async {
                rx.await.ok();
            })
            .await
            .unwrap();
        });
        Server {
            addr,
            work_dir,
            coordinator,
            stop: Some(tx),
            task,
        }
    }

    pub async fn channel(&self) -> Channel {
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

pub fn slow_heartbeat() -> HeartbeatConfig {
    HeartbeatConfig {
        interval: Duration::from_secs(1),
        timeout: Duration::from_secs(60),
    }
}

pub fn register_request(endpoint: &str) -> RegisterWorkerRequest {
    RegisterWorkerRequest {
        endpoint: endpoint.into(),
        threads: 2,
        memory_budget_bytes: 0,
        version: VERSION.into(),
        record_format: dray_proto::RAY_RECORD_FORMAT,
        hostname: "test".into(),
        cache_endpoint: String::new(),
        name: String::new(),
    }
}

/// Aborts a task when dropped.
pub struct AbortOnDrop(pub tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A test playing one worker.
pub struct FakeWorker {
    pub id: String,
    /// Its member secret (RegisterWorkerResponse.member_token).
    pub token: String,
    pub client: ClusterServiceClient<Channel>,
    pub stream: Streaming<Assignment>,
}

/// `msg` as a call speaking for the worker whose secret is `token`.
pub fn as_member<T>(token: &str, msg: T) -> tonic::Request<T> {
    let mut req = tonic::Request::new(msg);
    req.metadata_mut().insert(
        dray_net::auth::MEMBER_HEADER,
        token.parse().expect("token metadata"),
    );
    req
}

impl FakeWorker {
    pub async fn join(channel: Channel, endpoint: &str) -> FakeWorker {
        FakeWorker::join_with(channel, register_request(endpoint)).await
    }

    pub async fn join_with(channel: Channel, req: RegisterWorkerRequest) -> FakeWorker {
        let mut client = ClusterServiceClient::new(channel);
        let r = client.register_worker(req).await.unwrap().into_inner();
        assert!(!r.worker_id.is_empty());
        assert!(r.heartbeat_interval.is_some() && r.heartbeat_timeout.is_some());
        assert!(!r.member_token.is_empty());
        let stream = client
            .watch_assignments(as_member(
                &r.member_token,
                WatchAssignmentsRequest {
                    worker_id: r.worker_id.clone(),
                },
            ))
            .await
            .unwrap()
            .into_inner();
        FakeWorker {
            id: r.worker_id,
            token: r.member_token,
            client,
            stream,
        }
    }

    /// Heartbeat every `every` until the returned guard is dropped.
    pub fn keep_alive(&self, every: Duration) -> AbortOnDrop {
        let mut client = self.client.clone();
        let id = self.id.clone();
        let token = self.token.clone();
        AbortOnDrop(tokio::spawn(async move {
            loop {
                let _ = client
                    .heartbeat(as_member(
                        &token,
                        HeartbeatRequest {
                            worker_id: id.clone(),
                            memory_used_bytes: 0,
                            rays_queued: 0,
                        },
                    ))
                    .await;
                tokio::time::sleep(every).await;
            }
        }))
    }

    pub async fn next(&mut self) -> Command {
        tokio::time::timeout(PATIENCE, self.stream.message())
            .await
            .expect("no assignment in time")
            .expect("assignment stream failed")
            .expect("assignment stream ended")
            .command
            .expect("assignment without a command")
    }

    /// The next command if one arrives within `wait`.
    pub async fn next_within(&mut self, wait: Duration) -> Option<Command> {
        match tokio::time::timeout(wait, self.stream.message()).await {
            Err(_) => None,
            Ok(m) => {
                m.expect("assignment stream failed")
                    .expect("assignment stream ended")
                    .command
            }
        }
    }

    /// The JobSetup, then tiles until `expect_tiles` have come.
    pub async fn setup_and_tiles(&mut self, expect_tiles: usize) -> (JobSetup, Vec<Tile>) {
        let setup = match self.next().await {
            Command::Setup(s) => s,
            other => panic!("expected a JobSetup first, got {other:?}"),
        };
        let tiles = self.tiles(&setup.job_id, expect_tiles).await;
        (setup, tiles)
    }

    /// TileAssignments of `job` until `expect` tiles have come.
    pub async fn tiles(&mut self, job: &str, expect: usize) -> Vec<Tile> {
        let mut tiles = Vec::new();
        while tiles.len() < expect {
            match self.next().await {
                Command::Tiles(t) => {
                    assert_eq!(t.job_id, job);
                    tiles.extend(t.tiles);
                }
                other => panic!("expected tiles, got {other:?}"),
            }
        }
        assert_eq!(tiles.len(), expect, "more tiles than expected");
        tiles
    }

    pub async fn report(&mut self, r: ReportContributionsRequest) -> Result<bool, tonic::Status> {
        self.client
            .report_contributions(as_member(
                &self.token,
                ReportContributionsRequest {
                    worker_id: self.id.clone(),
                    ..r
                },
            ))
            .await
            .map(|r| r.into_inner().job_active)
    }

    /// ReportQueues for `job` at `attempt` with `(domain, rays_queued, resident,
    /// resident_bytes)` entries; returns the answered routing version.
    pub async fn report_queues(
        &mut self,
        job: &str,
        attempt: u32,
        routing_version: u64,
        queues: &[(u32, u64, bool, u64)],
    ) -> u64 {
        let token = self.token.clone();
        self.client
            .report_queues(as_member(
                &token,
                ReportQueuesRequest {
                    worker_id: self.id.clone(),
                    job_id: job.into(),
                    routing_version,
                    queues: queues
                        .iter()
                        .map(
                            |&(domain, rays_queued, resident, resident_bytes)| DomainQueue {
                                domain,
                                rays_queued,
                                resident,
                                resident_bytes,
                            },
                        )
                        .collect(),
                    memory_used_bytes: 0,
                    attempt,
                },
            ))
            .await
            .unwrap()
            .into_inner()
            .routing_version
    }
}

/// A small job on the dynamic schedule: these tests are about the protocol of owned
/// domains (tables, rounds, joins, losses), which `auto`, the default, would replace by
/// the replicated schedule on fake workers without a budget.
pub fn spec(width: u32, height: u32, domains: u32) -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width,
        height,
        spp: 1,
        domains,
        schedule: "dynamic".into(),
        ..Default::default()
    }
}

pub async fn submit(channel: &Channel, spec: JobSpec) -> String {
    RenderServiceClient::new(channel.clone())
        .submit_job(SubmitJobRequest { spec: Some(spec) })
        .await
        .unwrap()
        .into_inner()
        .job_id
}

pub async fn get_job(channel: &Channel, id: &str) -> Job {
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
pub async fn wait_state(channel: &Channel, id: &str, state: JobState) -> Job {
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

pub fn fixed(v: f64) -> i64 {
    (v * (1u64 << 24) as f64) as i64
}

/// Read an EXR file's RGB as (width, pixels).
pub fn read_exr(bytes: &[u8]) -> (usize, Vec<[f32; 3]>) {
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

pub fn assert_dir_gone(dir: &Path) {
    assert!(
        !dir.exists(),
        "the job's package {} was not removed",
        dir.display()
    );
}
