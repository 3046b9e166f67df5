//! The worker process: what it owns, how it starts, and the one place it stops.
//!
//! The worker is a few small owners around one [`Shared`] state, each in its own file:
//! - [`crate::coordinator_link`]: connect, register, heartbeats and the coordinator's
//!   command stream (job setups, tiles, routing tables, releases); registers again when
//!   the coordinator restarts or declared this worker lost.
//! - [`crate::jobs`]: the job attempts running here, each with its actor: the one owner
//!   of what the job has to report, of its routing table and of the tiles dealt to it.
//! - [`crate::domain_store`]: which domains are resident, loaded on demand and evicted
//!   least-recently-used within the memory budget.
//! - [`crate::queue`]: the ray queues, per job attempt and domain.
//! - [`crate::work`]: the tracing threads: pick the fullest queue (loading its domain
//!   if needed), forward rays for domains this worker no longer owns, make camera rays,
//!   trace, and hand the results on. **Tracing never waits for the network.**
//! - [`crate::peers`]: one task per peer owning the gRPC stream to it.
//! - [`crate::reporter`]: the report messages the job actors send the coordinator.
//!
//! Shutdown is in one place, [`run`]: a stop signal every task watches, the tracing
//! threads joined, every job released and its actor joined, the peer tasks held in a
//! join set and ended, the server stopped.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::Duration;

use dray_net::AuthChannel;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_scene::partition::memory::MemoryPackages;
use tokio::net::TcpListener;
use tokio::sync::watch;

use crate::cache_link::CacheLinks;
use crate::config::Limits;
pub use crate::config::{NodeError, WorkerConfig};
use crate::coordinator_link;
use crate::domain_store::DomainStore;
use crate::jobs::Jobs;
use crate::peer_server::{PeerServer, PeerServerConfig};
use crate::peers::Peers;
use crate::queue::RayQueues;
use dray_sync::lock;

/// The dray version, sent at registration: the coordinator refuses another build.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Wakes idle tracing threads when work arrives.
#[derive(Default)]
pub(crate) struct Wake {
    generation: Mutex<u64>,
    cond: Condvar,
}

impl Wake {
    pub fn notify(&self) {
        *lock(&self.generation) += 1;
        self.cond.notify_all();
    }

    /// The current generation, to pass to [`Wake::wait`].
    pub fn seen(&self) -> u64 {
        *lock(&self.generation)
    }

    /// Sleep until a notification after `seen`, or `timeout` (a safety net only).
    pub fn wait(&self, seen: u64, timeout: Duration) {
        let g = lock(&self.generation);
        if *g == seen {
            let _ = self.cond.wait_timeout(g, timeout);
        }
    }
}

/// What the worker's parts share.
pub(crate) struct Shared {
    id: RwLock<String>,
    /// The coordinator's secret for this worker (RegisterWorkerResponse.member_token),
    /// sent with every call that names the worker.
    member: RwLock<String>,
    pub client: ClusterServiceClient<AuthChannel>,
    /// How to reach peers and cache hosts (token, TLS).
    pub net: dray_net::ClientOptions,
    pub queues: Arc<RayQueues>,
    pub store: DomainStore,
    pub jobs: Jobs,
    pub peers: Peers,
    /// The streams to cache hosts (ray caches).
    pub caches: CacheLinks,
    pub wake: Wake,
    pub limits: Limits,
    pub memory_packages: Option<Arc<MemoryPackages>>,
    /// Fetches job packages from the coordinator when they are not on this disk (none
    /// with `FetchMode::Never`).
    pub fetcher: Option<Arc<crate::package_fetch::PackageFetcher>>,
    pub memory_budget: u64,
    pub threads: usize,
    /// The cache host beside this worker, announced at registration.
    pub cache_endpoint: Option<String>,
    /// Its name, announced at registration (`WorkerConfig::resolved_name`).
    pub name: String,
    /// Set when the worker stops: tracing threads leave.
    pub stopping: AtomicBool,
    /// Where jobs that ask for a traffic trace write it (none: they record nothing).
    pub trace_dir: Option<std::path::PathBuf>,
}

impl Shared {
    /// This worker's id at the coordinator (changes when it registers again).
    pub fn id(&self) -> String {
        dray_sync::read(&self.id).clone()
    }

    /// Take the id and secret the coordinator gave at registration.
    pub fn set_member(&self, id: &str, token: &str) {
        *dray_sync::write(&self.id) = id.to_string();
        *dray_sync::write(&self.member) = token.to_string();
    }

    /// `msg` as a request speaking for this worker: with its member secret attached.
    pub fn as_member<T>(&self, msg: T) -> tonic::Request<T> {
        let mut req = tonic::Request::new(msg);
        let token = dray_sync::read(&self.member).clone();
        if let Ok(v) = tonic::metadata::MetadataValue::try_from(token.as_str())
            && !token.is_empty()
        {
            req.metadata_mut().insert("x-dray-member", v);
        }
        req
    }

    pub fn notify(&self) {
        self.wake.notify();
    }

    /// Rays waiting here in any form, for the jobs still running.
    pub fn in_flight(&self) -> usize {
        let outgoing: usize = self.jobs.all().iter().map(|j| j.waiting()).sum();
        self.queues.total() + outgoing
    }

    /// Bytes of resident domains and queued rays.
    pub fn memory_used(&self) -> u64 {
        self.store.used_bytes() + (self.in_flight() * dray_core::ray::RAY_RECORD_MAX_BYTES) as u64
    }

    /// Drop everything of a released job attempt.
    pub fn forget(&self, job_id: &str, attempt: u32) {
        self.queues.drop_job(job_id, attempt);
        self.store.release(job_id, attempt);
        self.notify();
    }
}

/// Run a worker until `shutdown` completes, or until the coordinator is lost for good.
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
    // A bad --name is refused before anything is dialled.
    let name = config.resolved_name(&coordinator_link::hostname())?;
    let channel = coordinator_link::connect(&config, config.connect_timeout).await?;
    let threads = if config.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        config.threads
    };
    let limits = config.limits();
    let fetcher = match config.package_fetch {
        crate::package_fetch::FetchMode::Never => None,
        mode => Some(Arc::new(
            crate::package_fetch::PackageFetcher::new(
                channel.clone(),
                tokio::runtime::Handle::current(),
                config.package_cache.clone(),
                mode,
            )
            .map_err(|e| NodeError::PackageCache(e.to_string()))?,
        )),
    };
    let queues = Arc::new(RayQueues::new(limits.queue_capacity));
    let shared = Arc::new(Shared {
        id: RwLock::new(String::new()),
        member: RwLock::new(String::new()),
        client: ClusterServiceClient::new(channel),
        net: config.net.clone(),
        queues: queues.clone(),
        store: DomainStore::new(limits.domain_bytes, config.load_delay).with_note(
            if config.memory_budget > 0 {
                format!(
                    " of the --memory-budget of {} bytes; the rest holds up to {} queued rays",
                    config.memory_budget,
                    limits.queue_capacity + limits.in_flight_limit
                )
            } else {
                String::new()
            },
        ),
        jobs: Jobs::default(),
        peers: Peers::new(tokio::runtime::Handle::current()),
        caches: CacheLinks::new(
            tokio::runtime::Handle::current(),
            config.cache_endpoint.clone().zip(config.cache_host.clone()),
        ),
        wake: Wake::default(),
        limits,
        memory_packages: config.memory_packages.clone(),
        fetcher,
        memory_budget: config.memory_budget,
        threads,
        cache_endpoint: config.cache_endpoint.clone(),
        name,
        stopping: AtomicBool::new(false),
        trace_dir: config.trace_dir.clone(),
    });
    // The first registration: a refusal here is final (wrong version, bad address).
    let registration = coordinator_link::register(&shared, &endpoint).await?;
    if config.server.auth.cluster.is_none() {
        tracing::warn!(
            "no cluster token (--cluster-token-file or DRAY_CLUSTER_TOKEN): this worker's ray \
             streams are open to anyone who reaches its ports"
        );
    }
    let weak = Arc::downgrade(&shared);
    queues.on_data(move || {
        if let Some(s) = weak.upgrade() {
            s.notify();
        }
    });

    let peer_server = PeerServer::new(
        queues.clone(),
        PeerServerConfig {
            worker_id: shared.id(),
            ..PeerServerConfig::default()
        },
    );
    let (stop_tx, stop_rx) = watch::channel(false);
    let server = tokio::spawn(serve(
        config.server.clone(),
        listener,
        peer_server.clone(),
        stop_rx.clone(),
    ));

    let mut tracers = Vec::new();
    for i in 0..threads {
        let s = shared.clone();
        let t = std::thread::Builder::new()
            .name(format!("dray-trace-{i}"))
            .spawn(move || crate::work::tracer_thread(&s))
            .map_err(|e| NodeError::Threads(e.to_string()))?;
        tracers.push(t);
    }
    let session = coordinator_link::sessions(
        shared.clone(),
        registration,
        endpoint,
        peer_server,
        config.rejoin_timeout,
    );

    let result = tokio::select! {
        r = session => r,
        _ = shutdown => Ok(()),
    };
    // The one place the worker stops.
    let _ = stop_tx.send(true);
    shared.stopping.store(true, Ordering::Relaxed);
    shared.notify();
    for t in tracers {
        let _ = t.join();
    }
    for j in shared.jobs.release_all() {
        shared.forget(&j.key.id, j.key.attempt);
    }
    shared.jobs.join_actors().await;
    // End the streams to peers, so their servers can stop too, then our own server,
    // giving it a moment to finish its streams.
    shared.peers.close().await;
    shared.caches.close().await;
    match tokio::time::timeout(Duration::from_secs(2), server).await {
        Ok(Ok(Err(e))) if result.is_ok() => return Err(NodeError::Serve(e.to_string())),
        _ => {}
    }
    result
}

/// The worker's gRPC server (ray streams, health, reflection) until `stop`.
async fn serve(
    options: dray_net::ServerOptions,
    listener: TcpListener,
    peer_server: PeerServer,
    mut stop: watch::Receiver<bool>,
) -> Result<(), String> {
    let routes = tonic::service::Routes::new(peer_server.into_service());
    dray_net::server::serve(
        &options,
        listener,
        routes,
        &[dray_proto::RAY_EXCHANGE_SERVICE],
        async move {
            let _ = stop.wait_for(|s| *s).await;
        },
    )
    .await
    .map_err(|e| e.to_string())
}
