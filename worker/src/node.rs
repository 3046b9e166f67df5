//! The worker process: joins the coordinator, serves the ray stream, and runs its jobs.
//!
//! Tasks, and why each is separate:
//! - **assignments**: reads the coordinator's `WatchAssignments` stream in order. A
//!   `JobSetup` registers the job's owned domains with the ray queues at once (so a peer
//!   that is quicker to load can already send rays), then loads the domains on a blocking
//!   thread; tiles, cancellations and finishes follow in order.
//! - **tracer**: the only place rays are traced. It takes, in this order, rays it sent
//!   to itself, batches from peers, then camera rays of its tiles, and traces them on
//!   `threads` plain OS threads, each pulling its own work (no per-batch task hand-off,
//!   which cost more than tracing small batches). **Tracing never waits for the network**: outgoing rays go to per-peer
//!   outboxes. So no cycle of workers waiting on each other's full queues can form.
//!   Memory stays bounded because camera rays, the only source of new work, are made only
//!   while the rays in flight here (queued, looped back and waiting for peers) are below
//!   [`WorkerConfig::in_flight_limit`], and every camera ray has a bounded number of
//!   descendants.
//! - **peers**: one task per peer owns the gRPC stream to it and sends batches as the
//!   peer grants room (`peer_client`).
//! - **reporter**: every few milliseconds, per job, one `ReportContributions` with the
//!   pixel sums, returned credit and counters accumulated since the last one (a whole
//!   tracing step's results always travel in the same report), retried with the same
//!   sequence number on failure.
//! - **heartbeat**: liveness and load, as the coordinator asks.

use std::collections::{HashMap, HashSet, VecDeque};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use dray_core::integrator::RayKind;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::{
    Assignment, DomainQueue, HeartbeatRequest, JobSetup, RayCounts, RegisterWorkerRequest,
    ReportContributionsRequest, ReportQueuesRequest, TileAssignment, TileCredit,
    WatchAssignmentsRequest, assignment::Command,
};
use dray_proto::{RAY_RECORD_BYTES, RAY_RECORD_FORMAT, RayRecord};
use dray_scene::partition::memory::MemoryPackages;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tonic::transport::{Channel, Endpoint};

use crate::job::{build_tracer, owned_domains};
use crate::peer_client::{BatchKey, PeerClientConfig, PeerSender};
use crate::peer_server::{PeerServer, PeerServerConfig};
use crate::pixel_sums::PixelSums;
use crate::queue::{QueuedBatch, RayQueues};
use crate::tracer::{JobTracer, Outbox, TileRef};

/// The dray version, sent at registration: the coordinator refuses another build.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Camera rays made in one tracing step.
const CAMERA_CHUNK: u64 = 4096;
/// How often accumulated results are reported.
const REPORT_INTERVAL: Duration = Duration::from_millis(10);
/// Contributions per ReportContributions message: about 2 MB, half gRPC's default limit.
const MAX_SUMS_PER_REPORT: usize = 64 * 1024;
/// How often queue lengths are reported (the scheduler's input).
const QUEUE_REPORT_INTERVAL: Duration = Duration::from_millis(250);

/// How a worker runs.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator, e.g. `http://127.0.0.1:50051`.
    pub coordinator: String,
    /// Where peers reach this worker, e.g. `http://10.0.0.7:50052`; by default
    /// `http://` + the listening address.
    pub advertise: Option<String>,
    /// Tracing threads (0: all cores).
    pub threads: usize,
    /// Memory for resident domains, bytes (0: unlimited); reported to the scheduler.
    pub memory_budget: u64,
    /// Capacity of each per-domain ray queue, in rays.
    pub queue_capacity: usize,
    /// Rays in flight at this worker above which no camera rays are made.
    pub in_flight_limit: usize,
    /// How long to keep trying to reach the coordinator at start.
    pub connect_timeout: Duration,
    /// The in-memory package store of the coordinator in this process, when there is
    /// one (`dray render`): jobs whose package is `memory:N` read their domains from it.
    pub memory_packages: Option<Arc<MemoryPackages>>,
}

impl Default for WorkerConfig {
    fn default() -> Self {
        WorkerConfig {
            coordinator: "http://127.0.0.1:50051".into(),
            advertise: None,
            threads: 0,
            memory_budget: 0,
            queue_capacity: 1 << 18,
            in_flight_limit: 1 << 18,
            connect_timeout: Duration::from_secs(10),
            memory_packages: None,
        }
    }
}

/// Why a worker stopped.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("invalid coordinator address {address:?}: {message}")]
    Address { address: String, message: String },
    #[error("cannot reach the coordinator at {address} (tried for {seconds} s): {message}")]
    Unreachable {
        address: String,
        seconds: u64,
        message: String,
    },
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
    #[error("lost the coordinator: {0}")]
    Lost(String),
    #[error("cannot start the tracing threads: {0}")]
    Threads(String),
    #[error("the ray-stream server failed: {0}")]
    Serve(String),
}

/// Results of one job waiting to be reported.
#[derive(Default)]
struct Report {
    sums: PixelSums,
    credits: Vec<(u32, u64)>,
    traced: [u64; RayKind::COUNT],
    nonfinite: u64,
    bytes: u64,
    failure: Option<String>,
}

impl Report {
    fn is_empty(&self) -> bool {
        self.sums.is_empty()
            && self.credits.is_empty()
            && self.traced.iter().all(|&n| n == 0)
            && self.nonfinite == 0
            && self.bytes == 0
            && self.failure.is_none()
    }
}

/// One job on this worker.
struct Job {
    id: Arc<str>,
    tracer: JobTracer,
    /// Owner worker id of each domain.
    owners: Vec<String>,
    /// Endpoint of each worker of the job.
    endpoints: HashMap<String, String>,
    routing_version: u64,
    /// Tiles whose camera rays are still to be made, with the next ray index.
    tiles: Mutex<VecDeque<(TileRef, u64)>>,
    report: Mutex<Report>,
    sequence: AtomicU64,
    active: AtomicBool,
    /// Rays of this job looped back or waiting for a peer. Counted per job, so rays
    /// stuck on the way to a lost peer stop counting once their job is released.
    outgoing: AtomicUsize,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Job {
    fn fail(&self, message: String) {
        let mut r = lock(&self.report);
        if r.failure.is_none() {
            tracing::error!(job = %self.id, "{message}");
            r.failure = Some(message);
        }
    }
}

/// Rays a worker sent to itself: the job, the domain, the rays.
type LocalBatch = (Arc<Job>, u32, Vec<RayRecord>);

/// Rays for one peer.
struct PeerMessage {
    job: Arc<Job>,
    domain: u32,
    rays: Vec<RayRecord>,
}

struct Node {
    id: String,
    client: ClusterServiceClient<Channel>,
    queues: Arc<RayQueues>,
    jobs: Mutex<HashMap<String, Arc<Job>>>,
    /// Jobs released here; late rays for them are dropped.
    released: Mutex<HashSet<String>>,
    /// Batches that arrived before their job's setup was loaded.
    parked: Mutex<Vec<(u32, QueuedBatch)>>,
    /// Rays this worker sent to itself.
    local: Mutex<VecDeque<LocalBatch>>,
    peers: Mutex<HashMap<String, mpsc::UnboundedSender<PeerMessage>>>,
    /// Wakes idle tracing threads when work arrives.
    wake: (Mutex<u64>, Condvar),
    /// The async runtime, for tasks started from tracing threads (peer streams).
    runtime: tokio::runtime::Handle,
    config: WorkerConfig,
}

/// Run a worker until `shutdown` completes or the coordinator is lost.
pub async fn run(
    config: WorkerConfig,
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), NodeError> {
    let local_addr: SocketAddr = listener
        .local_addr()
        .map_err(|e| NodeError::Serve(e.to_string()))?;
    let endpoint = config
        .advertise
        .clone()
        .unwrap_or_else(|| format!("http://{local_addr}"));
    let channel = connect(&config).await?;
    let mut client = ClusterServiceClient::new(channel);
    let threads = if config.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        config.threads
    };
    let reg = client
        .register_worker(RegisterWorkerRequest {
            endpoint: endpoint.clone(),
            threads: threads as u32,
            memory_budget_bytes: config.memory_budget,
            version: VERSION.into(),
            record_format: RAY_RECORD_FORMAT,
            hostname: hostname(),
        })
        .await
        .map_err(|s| NodeError::Refused(s.message().to_string()))?
        .into_inner();
    let id = reg.worker_id.clone();
    tracing::info!(worker = %id, %endpoint, "registered");
    let heartbeat = reg
        .heartbeat_interval
        .and_then(|d| Duration::try_from(d).ok())
        .unwrap_or(Duration::from_secs(1));
    let queues = Arc::new(RayQueues::new([], config.queue_capacity.max(1)));
    let node = Arc::new(Node {
        id: id.clone(),
        client: client.clone(),
        queues: queues.clone(),
        jobs: Mutex::new(HashMap::new()),
        released: Mutex::new(HashSet::new()),
        parked: Mutex::new(Vec::new()),
        local: Mutex::new(VecDeque::new()),
        peers: Mutex::new(HashMap::new()),
        wake: (Mutex::new(0), Condvar::new()),
        runtime: tokio::runtime::Handle::current(),
        config,
    });
    let weak = Arc::downgrade(&node);
    queues.on_data(move || {
        if let Some(n) = weak.upgrade() {
            n.notify();
        }
    });

    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    health_reporter
        .set_serving::<dray_proto::v1::ray_exchange_service_server::RayExchangeServiceServer<PeerServer>>()
        .await;
    let reflection =
        dray_proto::reflection::reflection_v1().map_err(|e| NodeError::Serve(e.to_string()))?;
    let reflection_alpha = dray_proto::reflection::reflection_v1alpha()
        .map_err(|e| NodeError::Serve(e.to_string()))?;
    let peer_server = PeerServer::new(
        queues.clone(),
        PeerServerConfig {
            worker_id: id.clone(),
            accept_unknown_domains: true,
            ..PeerServerConfig::default()
        },
    );
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut stop_server = stop_rx.clone();
    let server = tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(health_service)
            .add_service(reflection)
            .add_service(reflection_alpha)
            .add_service(peer_server.into_service())
            .serve_with_incoming_shutdown(
                // TCP_NODELAY: without it every small reply (registration, job setup,
                // reports) waited out the peer's 40 ms delayed ACK.
                tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
                async move {
                    let _ = stop_server.wait_for(|s| *s).await;
                },
            ),
    );

    let stopping = Arc::new(AtomicBool::new(false));
    let mut tracers = Vec::new();
    for i in 0..threads {
        let (node, stopping) = (node.clone(), stopping.clone());
        let t = std::thread::Builder::new()
            .name(format!("dray-trace-{i}"))
            .spawn(move || node.tracer_thread(&stopping))
            .map_err(|e| NodeError::Threads(e.to_string()))?;
        tracers.push(t);
    }
    let reporter = tokio::spawn(node.clone().report_loop(stop_rx.clone()));
    let beats = tokio::spawn(node.clone().heartbeat_loop(heartbeat, stop_rx.clone()));
    let assignments = node.clone().assignment_loop();

    let result = tokio::select! {
        r = assignments => r,
        r = beats => r.unwrap_or_else(|e| Err(NodeError::Lost(e.to_string()))),
        _ = shutdown => Ok(()),
    };
    let _ = stop_tx.send(true);
    stopping.store(true, Ordering::Relaxed);
    node.notify();
    for t in tracers {
        let _ = t.join();
    }
    reporter.abort();
    // End the streams to peers, so their servers can stop too, and give our own server
    // a moment to finish its streams before it is dropped.
    lock(&node.peers).clear();
    match tokio::time::timeout(Duration::from_secs(2), server).await {
        Ok(Ok(Err(e))) if result.is_ok() => return Err(NodeError::Serve(e.to_string())),
        _ => {}
    }
    result
}

/// Connect to the coordinator, retrying until `connect_timeout` passes: in a cluster the
/// workers often start before the coordinator listens.
async fn connect(config: &WorkerConfig) -> Result<Channel, NodeError> {
    let address = if config.coordinator.contains("://") {
        config.coordinator.clone()
    } else {
        format!("http://{}", config.coordinator)
    };
    let endpoint = Endpoint::from_shared(address.clone()).map_err(|e| NodeError::Address {
        address: config.coordinator.clone(),
        message: e.to_string(),
    })?;
    let endpoint = endpoint.connect_timeout(Duration::from_secs(2));
    let start = tokio::time::Instant::now();
    loop {
        match endpoint.connect().await {
            Ok(c) => return Ok(c),
            Err(e) => {
                if start.elapsed() >= config.connect_timeout {
                    let mut message = e.to_string();
                    let mut source = std::error::Error::source(&e);
                    while let Some(s) = source {
                        // tonic's messages often repeat their source's text already.
                        let text = s.to_string();
                        if !message.contains(&text) {
                            message = format!("{message}: {text}");
                        }
                        source = s.source();
                    }
                    return Err(NodeError::Unreachable {
                        address,
                        seconds: config.connect_timeout.as_secs(),
                        message,
                    });
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
}

impl Node {
    fn job(&self, id: &str) -> Option<Arc<Job>> {
        lock(&self.jobs).get(id).cloned()
    }

    async fn assignment_loop(self: Arc<Self>) -> Result<(), NodeError> {
        let mut client = self.client.clone();
        let mut stream = client
            .watch_assignments(WatchAssignmentsRequest {
                worker_id: self.id.clone(),
            })
            .await
            .map_err(|s| NodeError::Lost(s.message().to_string()))?
            .into_inner();
        loop {
            let msg = match stream.message().await {
                Ok(Some(m)) => m,
                Ok(None) => return Err(NodeError::Lost("the assignment stream ended".into())),
                Err(s) => return Err(NodeError::Lost(s.message().to_string())),
            };
            let Assignment { command } = msg;
            match command {
                Some(Command::Setup(setup)) => self.setup(setup).await,
                Some(Command::Tiles(t)) => self.add_tiles(t),
                Some(Command::Routing(r)) => {
                    tracing::warn!(job = %r.job_id, version = r.version,
                        "routing changes are not supported yet; keeping the initial table");
                }
                Some(Command::Cancel(r)) | Some(Command::Finish(r)) => {
                    self.release(&r.job_id, &r.reason)
                }
                None => {}
            }
        }
    }

    async fn setup(self: &Arc<Self>, setup: JobSetup) {
        let job_id = setup.job_id.clone();
        let Some(routing) = setup.routing.clone() else {
            self.report_setup_failure(&job_id, "job setup has no routing table".into())
                .await;
            return;
        };
        // Register the queues first: a faster peer may send rays before we have loaded.
        for d in owned_domains(&routing, &self.id) {
            self.queues.add_domain(d);
        }
        let id = self.id.clone();
        let setup2 = setup.clone();
        let memory = self.config.memory_packages.clone();
        let built =
            tokio::task::spawn_blocking(move || build_tracer(&setup2, &id, memory.as_deref()))
                .await;
        let tracer = match built {
            Ok(Ok(t)) => t,
            Ok(Err(e)) => {
                self.report_setup_failure(&job_id, format!("worker {}: {e}", self.id))
                    .await;
                return;
            }
            Err(e) => {
                self.report_setup_failure(&job_id, format!("worker {}: {e}", self.id))
                    .await;
                return;
            }
        };
        let mut owners = vec![String::new(); setup.domain_count as usize];
        for r in &routing.routes {
            if let Some(o) = owners.get_mut(r.domain as usize) {
                o.clone_from(&r.worker_id);
            }
        }
        let job = Arc::new(Job {
            id: job_id.as_str().into(),
            tracer,
            owners,
            endpoints: routing
                .workers
                .iter()
                .map(|w| (w.worker_id.clone(), w.endpoint.clone()))
                .collect(),
            routing_version: routing.version,
            tiles: Mutex::new(VecDeque::new()),
            report: Mutex::new(Report::default()),
            sequence: AtomicU64::new(0),
            active: AtomicBool::new(true),
            outgoing: AtomicUsize::new(0),
        });
        tracing::info!(
            job = %job.id,
            triangles = job.tracer.resident().scene.mesh.indices.len(),
            domains = job.tracer.resident().domains.len(),
            "job loaded"
        );
        lock(&self.jobs).insert(job_id, job);
        self.notify();
    }

    async fn report_setup_failure(&self, job_id: &str, message: String) {
        tracing::error!(job = %job_id, "{message}");
        let mut client = self.client.clone();
        let _ = client
            .report_contributions(ReportContributionsRequest {
                worker_id: self.id.clone(),
                job_id: job_id.to_string(),
                sequence: 1,
                failure: message,
                ..Default::default()
            })
            .await;
        lock(&self.released).insert(job_id.to_string());
    }

    fn add_tiles(&self, t: TileAssignment) {
        let Some(job) = self.job(&t.job_id) else {
            tracing::warn!(job = %t.job_id, "tiles for a job this worker does not run");
            return;
        };
        let mut tiles = lock(&job.tiles);
        for tile in t.tiles {
            tiles.push_back((
                TileRef {
                    index: tile.index,
                    x0: tile.x0,
                    y0: tile.y0,
                    width: tile.width,
                    height: tile.height,
                    credit: tile.credit,
                },
                0,
            ));
        }
        drop(tiles);
        self.notify();
    }

    fn release(&self, job_id: &str, reason: &str) {
        tracing::info!(job = %job_id, reason, "job released");
        lock(&self.released).insert(job_id.to_string());
        if let Some(job) = lock(&self.jobs).remove(job_id) {
            job.active.store(false, Ordering::Relaxed);
        }
        lock(&self.parked).retain(|(_, b)| &*b.job_id != job_id);
        lock(&self.local).retain(|(j, _, _)| &*j.id != job_id);
        self.notify();
    }

    /// Rays waiting here in any form, for the jobs still running.
    fn in_flight(&self) -> usize {
        let queued: usize = self.queues.lengths().iter().map(|(_, n)| n).sum();
        let outgoing: usize = lock(&self.jobs)
            .values()
            .map(|j| j.outgoing.load(Ordering::Relaxed))
            .sum();
        queued + outgoing
    }

    /// The next piece of work, if any: looped-back rays, then peers' batches, then
    /// camera rays.
    fn next_work(&self) -> Option<Work> {
        if let Some((job, d, rays)) = lock(&self.local).pop_front() {
            job.outgoing.fetch_sub(rays.len(), Ordering::Relaxed);
            return Some(Work::Rays(job, d, rays));
        }
        // Parked batches whose job has arrived since.
        {
            let mut parked = lock(&self.parked);
            if let Some(i) = parked
                .iter()
                .position(|(_, b)| self.job(&b.job_id).is_some())
            {
                let (d, b) = parked.swap_remove(i);
                if let Some(job) = self.job(&b.job_id) {
                    return Some(Work::Rays(job, d, b.rays));
                }
            }
        }
        for (d, n) in self.queues.lengths() {
            if n == 0 {
                continue;
            }
            let Some(b) = self.queues.pop(d) else {
                continue;
            };
            match self.job(&b.job_id) {
                Some(job) => return Some(Work::Rays(job, d, b.rays)),
                None => {
                    if !lock(&self.released).contains(&*b.job_id) {
                        lock(&self.parked).push((d, b));
                    }
                }
            }
        }
        if self.in_flight() < self.config.in_flight_limit {
            let jobs: Vec<Arc<Job>> = lock(&self.jobs).values().cloned().collect();
            for job in jobs {
                let mut tiles = lock(&job.tiles);
                let Some((tile, next)) = tiles.front_mut() else {
                    continue;
                };
                let total = tile.camera_rays(job.tracer.settings().spp);
                let start = *next;
                let count = CAMERA_CHUNK.min(total - start);
                let t = *tile;
                *next += count;
                if *next >= total {
                    tiles.pop_front();
                }
                drop(tiles);
                return Some(Work::Camera(job, t, start, count));
            }
        }
        None
    }

    /// Wake the tracing threads.
    fn notify(&self) {
        let (m, c) = &self.wake;
        *lock(m) += 1;
        c.notify_all();
    }

    /// One tracing thread: take work, trace it, hand the results on; sleep when there is
    /// none, until new rays or tiles arrive (the timeout is only a safety net).
    fn tracer_thread(self: Arc<Self>, stopping: &AtomicBool) {
        let (m, c) = &self.wake;
        while !stopping.load(Ordering::Relaxed) {
            let seen = *lock(m);
            match self.next_work() {
                Some(work) => self.trace(work),
                None => {
                    let g = lock(m);
                    if *g == seen {
                        let _ = c.wait_timeout(g, Duration::from_millis(50));
                    }
                }
            }
        }
    }

    /// Trace one piece of work and hand the results on.
    fn trace(self: &Arc<Self>, work: Work) {
        let mut out = Outbox::default();
        let (job, result) = match work {
            Work::Rays(job, d, rays) => {
                if !job.active.load(Ordering::Relaxed) {
                    return;
                }
                let _span =
                    tracing::trace_span!("batch", job = %job.id, domain = d, rays = rays.len())
                        .entered();
                let r = job.tracer.trace_batch(d, &rays, &mut out);
                (job, r)
            }
            Work::Camera(job, tile, start, count) => {
                if !job.active.load(Ordering::Relaxed) {
                    return;
                }
                let _span =
                    tracing::trace_span!("tile", job = %job.id, tile = tile.index, start).entered();
                let r = job.tracer.camera_rays(&tile, start, count, &mut out);
                (job, r)
            }
        };
        match result {
            Ok(()) => self.deliver(&job, out),
            Err(e) => job.fail(format!("worker {}: {e}", self.id)),
        }
    }

    /// Results into the job's report; rays to their domains' owners.
    fn deliver(self: &Arc<Self>, job: &Arc<Job>, out: Outbox) {
        let mut bytes = 0u64;
        let mut looped = false;
        for (d, rays) in out.rays {
            if rays.is_empty() {
                continue;
            }
            let n = rays.len();
            let Some(owner) = job.owners.get(d as usize) else {
                job.fail(format!(
                    "a ray goes to domain {d}, which the layout does not have"
                ));
                return;
            };
            job.outgoing.fetch_add(n, Ordering::Relaxed);
            if *owner == self.id {
                lock(&self.local).push_back((job.clone(), d, rays));
                looped = true;
                continue;
            }
            bytes += (n * RAY_RECORD_BYTES) as u64;
            let Some(endpoint) = job.endpoints.get(owner) else {
                job.fail(format!("domain {d}'s owner {owner} has no endpoint"));
                return;
            };
            let sender = self.peer(endpoint, owner);
            if sender
                .send(PeerMessage {
                    job: job.clone(),
                    domain: d,
                    rays,
                })
                .is_err()
            {
                job.outgoing.fetch_sub(n, Ordering::Relaxed);
                job.fail(format!(
                    "the stream to worker {owner} at {endpoint} is closed"
                ));
            }
        }
        let mut r = lock(&job.report);
        r.sums.extend(&out.sums);
        let mut credits = out.credits;
        r.credits.append(&mut credits);
        for (k, n) in out.traced.iter().enumerate() {
            r.traced[k] += n;
        }
        r.nonfinite += out.nonfinite;
        r.bytes += bytes;
        drop(r);
        if looped {
            self.notify();
        }
    }

    /// The outbox of the stream to `worker_id` at `endpoint`, opening it if needed.
    fn peer(
        self: &Arc<Self>,
        endpoint: &str,
        worker_id: &str,
    ) -> mpsc::UnboundedSender<PeerMessage> {
        let mut peers = lock(&self.peers);
        if let Some(tx) = peers.get(endpoint)
            && !tx.is_closed()
        {
            return tx.clone();
        }
        let (tx, rx) = mpsc::unbounded_channel();
        peers.insert(endpoint.to_string(), tx.clone());
        self.runtime.spawn(
            self.clone()
                .peer_loop(endpoint.to_string(), worker_id.to_string(), rx),
        );
        tx
    }

    async fn peer_loop(
        self: Arc<Self>,
        endpoint: String,
        worker_id: String,
        mut rx: mpsc::UnboundedReceiver<PeerMessage>,
    ) {
        let config = PeerClientConfig {
            sender_id: self.id.clone(),
            receiver_id: worker_id.clone(),
            ..PeerClientConfig::default()
        };
        let opened = async {
            let channel = Endpoint::from_shared(endpoint.clone())
                .map_err(|e| e.to_string())?
                .connect_timeout(Duration::from_secs(5))
                .connect()
                .await
                .map_err(|e| e.to_string())?;
            PeerSender::open(channel, config)
                .await
                .map_err(|e| e.to_string())
        }
        .await;
        let mut sender = match opened {
            Ok(s) => s,
            Err(e) => {
                self.peer_failed(&mut rx, &endpoint, &worker_id, &e);
                return;
            }
        };
        loop {
            let deadline = sender.next_deadline();
            let msg = match deadline {
                Some(at) => {
                    tokio::select! {
                        m = rx.recv() => m,
                        _ = tokio::time::sleep_until(at) => {
                            if let Err(e) = sender.flush_due().await {
                                self.peer_failed(&mut rx, &endpoint, &worker_id, &e.to_string());
                                return;
                            }
                            continue;
                        }
                    }
                }
                None => rx.recv().await,
            };
            let Some(m) = msg else {
                let _ = sender.flush().await;
                return;
            };
            let n = m.rays.len();
            let key = BatchKey {
                job_id: m.job.id.to_string(),
                domain: m.domain,
                routing_version: m.job.routing_version,
            };
            // A peer that stops granting room (it was lost) must not hold this stream
            // forever: once the job is released, its rays are dropped with the stream.
            let sent = if m.job.active.load(Ordering::Relaxed) {
                tokio::select! {
                    r = sender.send(&key, &m.rays, &[]) => r.map_err(|e| e.to_string()),
                    _ = released(&m.job) => {
                        Err("the job was released while its rays waited for the peer".to_string())
                    }
                }
            } else {
                Ok(())
            };
            m.job.outgoing.fetch_sub(n, Ordering::Relaxed);
            // Room for camera rays again, perhaps.
            self.notify();
            if let Err(e) = sent {
                m.job.fail(format!(
                    "worker {}: cannot send rays to worker {worker_id} at {endpoint}: {e}",
                    self.id
                ));
                self.peer_failed(&mut rx, &endpoint, &worker_id, &e);
                return;
            }
        }
    }

    /// A peer cannot be reached: fail every job with rays for it, now and later.
    fn peer_failed(
        &self,
        rx: &mut mpsc::UnboundedReceiver<PeerMessage>,
        endpoint: &str,
        worker_id: &str,
        error: &str,
    ) {
        lock(&self.peers).remove(endpoint);
        rx.close();
        while let Ok(m) = rx.try_recv() {
            m.job.outgoing.fetch_sub(m.rays.len(), Ordering::Relaxed);
            m.job.fail(format!(
                "worker {}: cannot send rays to worker {worker_id} at {endpoint}: {error}",
                self.id
            ));
        }
    }

    async fn report_loop(self: Arc<Self>, mut stop: tokio::sync::watch::Receiver<bool>) {
        let mut last_queues = tokio::time::Instant::now();
        loop {
            tokio::select! {
                _ = tokio::time::sleep(REPORT_INTERVAL) => {}
                _ = stop.changed() => return,
            }
            let jobs: Vec<Arc<Job>> = lock(&self.jobs).values().cloned().collect();
            for job in &jobs {
                self.report(job).await;
            }
            if last_queues.elapsed() >= QUEUE_REPORT_INTERVAL {
                last_queues = tokio::time::Instant::now();
                for job in &jobs {
                    self.report_queues(job).await;
                }
            }
        }
    }

    /// Send what `job` accumulated. Contributions go in chunks that stay well inside
    /// gRPC's message limit; the credit travels in the last one, so no credit reaches
    /// the coordinator before the contributions of the same rays.
    async fn report(&self, job: &Arc<Job>) {
        let mut report = std::mem::take(&mut *lock(&job.report));
        if report.is_empty() {
            return;
        }
        let mut sums = report.sums.drain();
        while sums.len() > MAX_SUMS_PER_REPORT {
            let rest = sums.split_off(MAX_SUMS_PER_REPORT);
            let chunk = std::mem::replace(&mut sums, rest);
            let request = self.request(job, chunk, Vec::new(), [0; RayKind::COUNT], 0, 0, None);
            if !self.send_report(job, request).await {
                return;
            }
        }
        report.credits.sort_unstable_by_key(|c| c.0);
        let mut credits: Vec<TileCredit> = Vec::new();
        for (tile, credit) in report.credits {
            match credits.last_mut() {
                Some(c) if c.tile == tile => c.credit += credit,
                _ => credits.push(TileCredit { tile, credit }),
            }
        }
        let request = self.request(
            job,
            sums,
            credits,
            report.traced,
            report.nonfinite,
            report.bytes,
            report.failure,
        );
        self.send_report(job, request).await;
    }

    #[allow(clippy::too_many_arguments)]
    fn request(
        &self,
        job: &Job,
        sums: Vec<(u32, [i64; 3])>,
        credits: Vec<TileCredit>,
        t: [u64; RayKind::COUNT],
        nonfinite: u64,
        bytes: u64,
        failure: Option<String>,
    ) -> ReportContributionsRequest {
        ReportContributionsRequest {
            worker_id: self.id.clone(),
            job_id: job.id.to_string(),
            sequence: job.sequence.fetch_add(1, Ordering::Relaxed) + 1,
            pixels: sums.iter().map(|(p, _)| *p).collect(),
            sums: sums.iter().flat_map(|(_, v)| *v).collect(),
            credits,
            traced: Some(RayCounts {
                camera: t[RayKind::Camera as usize],
                shadow: t[RayKind::Shadow as usize],
                reflection: t[RayKind::Reflection as usize],
                refraction: t[RayKind::Refraction as usize],
                diffuse: t[RayKind::Diffuse as usize],
                ambient_occlusion: t[RayKind::AmbientOcclusion as usize],
            }),
            nonfinite,
            ray_bytes_sent: bytes,
            failure: failure.unwrap_or_default(),
        }
    }

    /// Send one report, retrying with the same sequence number (the coordinator applies
    /// it once). False when the job is over or the coordinator cannot be reached.
    async fn send_report(&self, job: &Arc<Job>, request: ReportContributionsRequest) -> bool {
        let mut client = self.client.clone();
        for attempt in 0..20u32 {
            match client.report_contributions(request.clone()).await {
                Ok(r) => {
                    if !r.into_inner().job_active {
                        self.release(&job.id, "the coordinator says the job is over");
                        return false;
                    }
                    return true;
                }
                Err(s) => {
                    tracing::warn!(job = %job.id, attempt, "report failed: {}", s.message());
                    tokio::time::sleep(Duration::from_millis(50 << attempt.min(5))).await;
                }
            }
        }
        tracing::error!(job = %job.id, "giving up reporting to the coordinator");
        false
    }

    async fn report_queues(&self, job: &Arc<Job>) {
        let resident: HashSet<u32> = job
            .tracer
            .resident()
            .domains
            .iter()
            .map(|d| d.domain)
            .collect();
        let queues = self
            .queues
            .lengths()
            .into_iter()
            .filter(|(d, _)| resident.contains(d))
            .map(|(d, n)| DomainQueue {
                domain: d,
                rays_queued: n as u64,
                resident: true,
                resident_bytes: 0,
            })
            .collect();
        let mut client = self.client.clone();
        let _ = client
            .report_queues(ReportQueuesRequest {
                worker_id: self.id.clone(),
                job_id: job.id.to_string(),
                routing_version: job.routing_version,
                queues,
                memory_used_bytes: self.memory_used(),
            })
            .await;
    }

    fn memory_used(&self) -> u64 {
        lock(&self.jobs)
            .values()
            .map(|j| j.tracer.resident().bytes())
            .sum()
    }

    async fn heartbeat_loop(
        self: Arc<Self>,
        every: Duration,
        mut stop: tokio::sync::watch::Receiver<bool>,
    ) -> Result<(), NodeError> {
        let mut client = self.client.clone();
        let mut failures = 0u32;
        loop {
            tokio::select! {
                _ = tokio::time::sleep(every) => {}
                _ = stop.changed() => return Ok(()),
            }
            let r = client
                .heartbeat(HeartbeatRequest {
                    worker_id: self.id.clone(),
                    memory_used_bytes: self.memory_used(),
                    rays_queued: self.in_flight() as u64,
                })
                .await;
            match r {
                Ok(r) if r.get_ref().reregister => {
                    return Err(NodeError::Lost(
                        "the coordinator no longer knows this worker (it restarted or declared it lost)".into(),
                    ));
                }
                Ok(_) => failures = 0,
                Err(s) => {
                    failures += 1;
                    if failures >= 5 {
                        return Err(NodeError::Lost(s.message().to_string()));
                    }
                }
            }
        }
    }
}

/// Resolves once `job` is released (polled: release is rare and this only runs while
/// a send is blocked on a peer).
async fn released(job: &Job) {
    while job.active.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

enum Work {
    Rays(Arc<Job>, u32, Vec<RayRecord>),
    Camera(Arc<Job>, TileRef, u64, u64),
}
