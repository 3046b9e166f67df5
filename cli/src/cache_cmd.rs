//! `dray cache`: a stand-alone cache host. It serves `dray.v1.CacheService` (with health
//! and reflection) and offers it to a coordinator with RegisterCacheHost; while any is
//! registered, the coordinator places jobs' cache actors on the stand-alone hosts
//! instead of beside the workers, taking that memory and work off the workers.
//!
//! It registers once, at start (retrying until `--connect-timeout` while the
//! coordinator is not up yet); there are no heartbeats for cache hosts yet, so a
//! coordinator that restarts does not know it until it is started again. Ctrl-C or
//! SIGTERM stops it; a job whose walls it held then says so in its statistics
//! (`lost_hosts`) and its rays go past it, traced exactly.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use dray_proto::v1::RegisterCacheHostRequest;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use tokio::signal::unix::{SignalKind, signal};

use crate::cache_host::LocalCacheHost;
use crate::submit_cmd::endpoint_url;

/// Serve ray caches for a coordinator's jobs. (The one-line help of `dray cache` is
/// the doc comment of `Command::Cache` in main.rs.)
#[derive(Args, Debug)]
pub struct CacheArgs {
    /// The coordinator's address, e.g. http://127.0.0.1:50051 (or host:port).
    #[arg(long)]
    pub coordinator: String,
    /// Address to serve the CacheService on (port 0 picks a free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    pub listen: String,
    /// Address workers and the coordinator use to reach this host (default: http:// +
    /// the listening address); set it when listening on 0.0.0.0 or behind a Kubernetes
    /// service.
    #[arg(long, value_name = "URL")]
    pub advertise: Option<String>,
    /// Seconds to keep trying to reach the coordinator at start.
    #[arg(long, default_value_t = 10)]
    pub connect_timeout: u64,
    #[command(flatten)]
    pub member: crate::net_flags::MemberArgs,
}

pub fn run(a: CacheArgs) -> Result<()> {
    endpoint_url(&a.coordinator)?;
    let (server, net) = a.member.options()?;
    let url = net.url(&a.coordinator);
    if let Some(adv) = &a.advertise
        && !(adv.starts_with("http://") || adv.starts_with("https://"))
    {
        bail!("--advertise {adv}: expected a URL such as http://10.0.0.7:7100");
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async {
        // Before anything starts, so a signal during start-up stops it cleanly.
        let mut term = signal(SignalKind::terminate()).context("cannot handle SIGTERM")?;
        let mut int = signal(SignalKind::interrupt()).context("cannot handle SIGINT")?;
        let mut host = LocalCacheHost::start(&a.listen, a.advertise.clone(), None, &server).await?;
        // One line on stdout, so scripts and tests can find the port.
        println!("dray cache listening on {}", host.addr);
        let registered = tokio::select! {
            r = register(&net, &url, &host.endpoint, Duration::from_secs(a.connect_timeout)) => r,
            _ = term.recv() => {
                host.stop().await;
                return Ok(());
            }
            _ = int.recv() => {
                host.stop().await;
                return Ok(());
            }
        };
        let id = match registered {
            Ok(id) => id,
            Err(e) => {
                host.stop().await;
                return Err(e);
            }
        };
        eprintln!(
            "dray cache: registered with {url} as {id}, serving at {}",
            host.endpoint
        );
        let why = tokio::select! {
            _ = term.recv() => "terminated",
            _ = int.recv() => "interrupted",
            e = host.ended() => return Err(e),
        };
        eprintln!("dray cache: {why}; stopping");
        host.stop().await;
        Ok(())
    })
}

/// RegisterCacheHost at `url` for `endpoint`, retrying connections for up to `patience`;
/// the host id. A refusal (another dray version, a bad endpoint) is final.
async fn register(
    net: &dray_net::ClientOptions,
    url: &str,
    endpoint: &str,
    patience: Duration,
) -> Result<String> {
    let deadline = Instant::now() + patience;
    let target = net
        .endpoint(url)
        .with_context(|| format!("--coordinator: {url} is not a valid address"))?
        .connect_timeout(Duration::from_secs(2))
        .timeout(Duration::from_secs(10));
    let channel = loop {
        match target.connect().await {
            Ok(c) => break c,
            Err(e) if Instant::now() >= deadline => {
                return Err(e).with_context(|| {
                    format!(
                        "cannot reach the coordinator at {url} (tried for {} s)",
                        patience.as_secs()
                    )
                });
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    let req = RegisterCacheHostRequest {
        endpoint: endpoint.to_string(),
        version: dray_coordinator::membership::VERSION.to_string(),
        hostname: hostname(),
    };
    let r = ClusterServiceClient::new(net.wrap(channel))
        .register_cache_host(req)
        .await
        .map_err(|s| {
            anyhow::anyhow!(
                "the coordinator at {url} refused this cache host: {}",
                s.message()
            )
        })?;
    Ok(r.into_inner().host_id)
}

/// This machine's name, for the coordinator's logs.
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".into())
}
