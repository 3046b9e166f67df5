//! The worker process: what it owns, how it starts, and the one place it stops.
//!
//! The worker is a few narrow owners, each in its own file with its state private, and
//! each function takes the narrowest one it needs:
//! - [`crate::member`]: the id and member secret the coordinator gave it, and the
//!   client that speaks for it.
//! - [`crate::workload`]: the tracing side's state: the jobs running here
//!   ([`crate::jobs`], each with its actor, [`crate::job_actor`]), their ray queues
//!   ([`crate::queue`]), the resident domains ([`crate::domain_store`]), the wake for
//!   idle tracing threads, the stop flag.
//! - [`crate::links`]: where rays leave a step: the streams to peers
//!   ([`crate::peers`]) and the links to cache hosts ([`crate::cache_link`]).
//! - [`crate::site`]: what the worker announces at registration and plans its job
//!   setups with (packages in memory or fetched, the traffic-trace directory).
//!
//! Around them: [`crate::coordinator_link`] (connect, register, heartbeats and the
//! coordinator's command stream, again after a lost coordinator), [`crate::work`] (the
//! tracing threads: **tracing never waits for the network**) and [`crate::reporter`]
//! (the report messages the job actors send). This file only composes them: no module
//! imports it.
//!
//! Shutdown is in one place, `Running::stop`: a stop signal every task watches, the tracing
//! threads joined, every job released and its actor joined, the peer and cache links
//! ended, the server stopped.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::watch;

use crate::config::Limits;
pub use crate::config::{NodeError, WorkerConfig};
use crate::coordinator_link::{self, Owners};
use crate::domain_store::DomainStore;
use crate::links::Links;
use crate::member::Member;
use crate::peer_server::{PeerServer, PeerServerConfig};
use crate::queue::RayQueues;
pub use crate::site::VERSION;
use crate::site::{Site, hostname};
use crate::wake::Wake;
use crate::workload::Workload;

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
    let name = config.resolved_name(&hostname())?;
    let channel = coordinator_link::connect(&config, config.connect_timeout).await?;
    let threads = tracing_threads(&config);
    let limits = config.limits();
    let site = Site::new(&config, name, threads, &channel)?;
    let member = Arc::new(Member::new(channel));
    let wake = Arc::new(Wake::default());
    let queues = Arc::new(RayQueues::new(limits.queue_capacity));
    let workload = Arc::new(Workload::new(
        queues.clone(),
        domain_store(&config, &limits),
        wake.clone(),
        limits.in_flight_limit,
    ));
    let links = Arc::new(Links::new(
        member.clone(),
        workload.clone(),
        wake.clone(),
        config.net.clone(),
        config.cache_endpoint.clone().zip(config.cache_host.clone()),
    ));
    // The first registration: a refusal here is final (wrong version, bad address).
    let registration = coordinator_link::register(&member, &site, &endpoint).await?;
    if config.server.auth.cluster.is_none() {
        tracing::warn!(
            "no cluster token (--cluster-token-file or DRAY_CLUSTER_TOKEN): this worker's ray \
             streams are open to anyone who reaches its ports"
        );
    }
    wake_on_data(&queues, &wake);
    let peer_server = PeerServer::new(
        queues.clone(),
        PeerServerConfig {
            worker_id: member.id(),
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
    let tracers = spawn_tracers(threads, &workload, &links, &member)?;
    let running = Running {
        stop: stop_tx,
        workload: workload.clone(),
        links: links.clone(),
        tracers,
        server,
    };
    let owners = Owners {
        member,
        workload,
        links,
        site,
    };
    let session = coordinator_link::sessions(
        &owners,
        registration,
        endpoint,
        peer_server,
        config.rejoin_timeout,
    );

    let result = tokio::select! {
        r = session => r,
        _ = shutdown => Ok(()),
    };
    running.stop(result).await
}

/// Tracing threads: `--threads`, or one per core when it is 0.
fn tracing_threads(config: &WorkerConfig) -> usize {
    if config.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        config.threads
    }
}

/// The store of resident domains, within `limits`; its refusals name the memory
/// budget they come from, when there is one.
fn domain_store(config: &WorkerConfig, limits: &Limits) -> DomainStore {
    DomainStore::new(limits.domain_bytes, config.load_delay).with_note(
        if config.memory_budget > 0 {
            format!(
                " of the --memory-budget of {} bytes; the rest holds up to {} queued rays",
                config.memory_budget,
                limits.queue_capacity + limits.in_flight_limit
            )
        } else {
            String::new()
        },
    )
}

/// Rays pushed into `queues` wake an idle tracing thread (the hook holds the wake
/// weakly: the queues never keep it alive).
fn wake_on_data(queues: &RayQueues, wake: &Arc<Wake>) {
    let weak = Arc::downgrade(wake);
    queues.on_data(move || {
        if let Some(w) = weak.upgrade() {
            w.notify();
        }
    });
}

/// Start `threads` tracing threads over `workload`, their rays leaving through `links`.
fn spawn_tracers(
    threads: usize,
    workload: &Arc<Workload>,
    links: &Arc<Links>,
    member: &Arc<Member>,
) -> Result<Vec<std::thread::JoinHandle<()>>, NodeError> {
    let mut tracers = Vec::new();
    for i in 0..threads {
        let (w, l, m) = (workload.clone(), links.clone(), member.clone());
        let t = std::thread::Builder::new()
            .name(format!("dray-trace-{i}"))
            .spawn(move || crate::work::tracer_thread(&w, &l, &m))
            .map_err(|e| NodeError::Threads(e.to_string()))?;
        tracers.push(t);
    }
    Ok(tracers)
}

/// What a started worker stops: the stop signal every task watches, the tracing
/// threads, the jobs, the links and the server.
struct Running {
    stop: watch::Sender<bool>,
    workload: Arc<Workload>,
    links: Arc<Links>,
    tracers: Vec<std::thread::JoinHandle<()>>,
    server: tokio::task::JoinHandle<Result<(), String>>,
}

impl Running {
    /// The one place the worker stops, after its session ended with `result`; a server
    /// that failed is the error when the session was not.
    async fn stop(self, result: Result<(), NodeError>) -> Result<(), NodeError> {
        let _ = self.stop.send(true);
        self.workload.stop();
        for t in self.tracers {
            let _ = t.join();
        }
        for j in self.workload.jobs().release_all() {
            self.workload.forget(&j.key.id, j.key.attempt);
        }
        self.workload.jobs().join_actors().await;
        // End the streams to peers, so their servers can stop too, then our own server,
        // giving it a moment to finish its streams.
        self.links.close().await;
        match tokio::time::timeout(Duration::from_secs(2), self.server).await {
            Ok(Ok(Err(e))) if result.is_ok() => return Err(NodeError::Serve(e.to_string())),
            _ => {}
        }
        result
    }
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
