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
    /// Seconds to keep trying to reach the coordinator at start.
    #[arg(long, default_value_t = 10)]
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
    #[command(flatten)]
    pub member: crate::net_flags::MemberArgs,
}

pub fn run(a: WorkerArgs) -> Result<()> {
    let (server, net) = a.member.options()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async {
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
            net,
            server,
            ..dray_worker::WorkerConfig::default()
        };
        let shutdown = async {
            let _ = tokio::signal::ctrl_c().await;
        };
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
    })
}
