//! `dray worker`: join a coordinator, own the domains it assigns, and trace rays with the
//! other workers until Ctrl-C or until the coordinator is lost.
//!
//! By default the process also hosts ray caches: a `dray_cache` CacheService on its own
//! listener (`--cache-listen`, default the worker's host with a free port), announced to
//! the coordinator when the worker registers, so jobs with `ray_cache` can place cache
//! actors beside the domains this worker owns. `--no-cache-host` leaves it out. The
//! cache host stops after the worker; if it fails, the worker stops too, naming it.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;

use crate::cache_host::{LocalCacheHost, advertised_host};

#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// The coordinator's address, e.g. http://127.0.0.1:50051 (or host:port).
    #[arg(long)]
    pub coordinator: String,
    /// Address to serve the worker-to-worker ray stream on, e.g. 127.0.0.1:50052 (port 0
    /// picks a free port).
    #[arg(long)]
    pub listen: String,
    /// Address other workers use to reach this one (default: http:// + the listening
    /// address); set it when listening on 0.0.0.0 or behind a Kubernetes service.
    #[arg(long)]
    pub advertise: Option<String>,
    /// Tracing threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Memory for resident domains and queued rays, in bytes (suffixes K, M, G, T are
    /// powers of 1024: 512M, 2GiB; 0 = unlimited). A quarter goes to rays, the rest to
    /// domains, which load on demand and are evicted least-recently-used; a job with a
    /// domain larger than that fails with a clear error. Reported to the scheduler.
    #[arg(long, default_value = "0", value_name = "BYTES", value_parser = crate::bytes::parse_bytes)]
    pub memory_budget: u64,
    /// Milliseconds added to every domain load, to emulate slow shared storage in
    /// experiments.
    #[arg(long, default_value_t = 0, value_name = "MS")]
    pub load_delay_ms: u64,
    /// Write the traffic traces of jobs that ask for one (`dray submit --trace`) into
    /// this directory, one file per job attempt (docs/caches.md "The trace's schema").
    /// Without it such jobs record nothing here.
    #[arg(long, value_name = "DIR")]
    pub trace_dir: Option<std::path::PathBuf>,
    /// Seconds to keep trying to reach the coordinator at start.
    #[arg(long, default_value_t = dray_worker::WorkerConfig::default().connect_timeout.as_secs())]
    pub connect_timeout: u64,
    /// Address to serve this process's ray caches on (port 0 picks a free port);
    /// advertised at the worker's advertised host with the bound port. Default: the
    /// worker's listening host, port 0.
    #[arg(long, value_name = "ADDR")]
    pub cache_listen: Option<String>,
    /// Host no ray caches in this process (jobs with ray caches then use other workers'
    /// or stand-alone `dray cache` hosts).
    #[arg(long, conflicts_with = "cache_listen")]
    pub no_cache_host: bool,
    /// When to fetch a job's scene package from the coordinator (over gRPC, domain by
    /// domain as they are first loaded) instead of reading it at the path the
    /// coordinator names: "auto" when that path does not hold the job's package (no
    /// shared volume), "always", or "never" (the path must be on a shared volume).
    #[arg(long, value_name = "MODE", default_value = "auto", value_parser = parse_fetch_mode)]
    pub fetch_packages: dray_worker::package_fetch::FetchMode,
    /// Directory for fetched packages (kept for later jobs of the same package; one
    /// directory per worker, locked while it runs: a second worker given the same one
    /// refuses to start). Default: a directory in the system's temp directory, removed
    /// when the worker stops.
    #[arg(long, value_name = "DIR")]
    pub package_cache: Option<std::path::PathBuf>,
    /// This worker's name in the coordinator's logs, ListWorkers, job events and the
    /// dashboard, beside its id: 1 to 64 of A-Z a-z 0-9 . _ - (`dray cluster` names its
    /// workers worker-1, worker-2, ...). Default: the host name (a Kubernetes pod's
    /// name), or none when that is not a valid name. Names need not be unique.
    #[arg(long, value_name = "NAME", value_parser = parse_name)]
    pub name: Option<String>,
    #[command(flatten)]
    pub member: crate::net_flags::MemberArgs,
    #[command(flatten)]
    pub otlp: crate::telemetry::OtlpArgs,
}

pub fn run(a: WorkerArgs) -> Result<()> {
    crate::threads::limit_build_threads(a.threads);
    if let Some(d) = &a.trace_dir
        && !d.is_dir()
    {
        anyhow::bail!("--trace-dir {}: not a directory", d.display());
    }
    let (server, net) = a.member.options()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let result = rt.block_on(async {
        let listener = tokio::net::TcpListener::bind(&a.listen)
            .await
            .with_context(|| format!("cannot listen on {}", a.listen))?;
        let addr = listener
            .local_addr()
            .context("cannot read the bound address")?;
        // One line on stdout, so scripts and tests can find the port.
        println!("dray worker listening on {addr}");

        let mut cache = if a.no_cache_host {
            None
        } else {
            let listen = a
                .cache_listen
                .clone()
                .unwrap_or_else(|| SocketAddr::new(addr.ip(), 0).to_string());
            let host = a.advertise.as_deref().and_then(advertised_host);
            let h = LocalCacheHost::start(&listen, None, host.as_deref(), &server).await?;
            println!("dray worker cache host listening on {}", h.addr);
            Some(h)
        };
        let config = dray_worker::WorkerConfig {
            coordinator: a.coordinator.clone(),
            advertise: a.advertise.clone(),
            threads: a.threads,
            memory_budget: a.memory_budget,
            load_delay: Duration::from_millis(a.load_delay_ms),
            connect_timeout: Duration::from_secs(a.connect_timeout),
            cache_endpoint: cache.as_ref().map(|h| h.endpoint.clone()),
            cache_host: cache.as_ref().map(|h| h.host.clone()),
            net,
            server,
            package_fetch: a.fetch_packages,
            package_cache: a.package_cache.clone(),
            trace_dir: a.trace_dir.clone(),
            name: a.name.clone(),
            ..dray_worker::WorkerConfig::default()
        };
        // Ctrl-C or SIGTERM (dray cluster and Kubernetes stop workers with SIGTERM) ends
        // the worker in order, so main flushes the OpenTelemetry exporters.
        let shutdown = crate::coordinator_cmd::stop_signal();
        let worker = dray_worker::run(config, listener, shutdown);
        let result = match cache.as_mut() {
            Some(h) => tokio::select! {
                r = worker => r.context("worker stopped"),
                e = h.ended() => Err(e),
            },
            None => worker.await.context("worker stopped"),
        };
        if let Some(h) = cache {
            h.stop().await;
        }
        result
    });
    // A domain load or a trace on a blocking thread would hold the process past the
    // stop signal if dropping the runtime waited for it.
    rt.shutdown_timeout(Duration::from_millis(500));
    result
}

/// `--name`: 1 to 64 of A-Z a-z 0-9 . _ - (`dray_proto::worker_name`).
pub fn parse_name(s: &str) -> Result<String, String> {
    if s.is_empty() {
        return Err("a name is 1 to 64 characters; leave --name out for the host name".into());
    }
    dray_proto::worker_name::check_worker_name(s)
        .map(|()| s.to_string())
        .map_err(|e| e.to_string())
}

/// `--fetch-packages`: auto, always or never.
pub fn parse_fetch_mode(s: &str) -> Result<dray_worker::package_fetch::FetchMode, String> {
    dray_worker::package_fetch::FetchMode::from_name(s)
        .ok_or_else(|| format!("{s:?} is not one of auto, always, never"))
}
