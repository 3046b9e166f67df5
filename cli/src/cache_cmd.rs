//! `dray cache`: a stand-alone cache host. It serves `dray.v1.CacheService` (with health
//! and reflection) and offers it to a coordinator with RegisterCacheHost; while any is
//! registered, the coordinator places jobs' cache actors on the stand-alone hosts
//! instead of beside the workers, taking that memory and work off the workers.
//!
//! It registers at start (retrying until `--connect-timeout` while the coordinator is
//! not up yet), and only with a coordinator started with `--cache-hosts`. Then it calls
//! again every refresh interval the coordinator gave, with the member secret it got,
//! to stay listed: a coordinator drops a host silent for its heartbeat timeout, and a
//! coordinator that restarted lists it anew at the next refresh. Ctrl-C or SIGTERM
//! stops it; a job whose walls it held then says so in its statistics (`lost_hosts`)
//! and its rays go past it, traced exactly.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::{RegisterCacheHostRequest, RegisterCacheHostResponse};
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
        let mut listing = match registered {
            Ok(l) => l,
            Err(e) => {
                host.stop().await;
                return Err(e);
            }
        };
        eprintln!(
            "dray cache: registered with {url} as {}, serving at {}",
            listing.host_id, host.endpoint
        );
        let mut tick = tokio::time::interval(listing.refresh);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tick.tick().await;
        let why = loop {
            tokio::select! {
                _ = term.recv() => break "terminated",
                _ = int.recv() => break "interrupted",
                e = host.ended() => return Err(e),
                _ = tick.tick() => listing.refresh(&url).await,
            }
        };
        eprintln!("dray cache: {why}; stopping");
        host.stop().await;
        Ok(())
    })
}

/// This host's listing at a coordinator: what it sends to stay listed.
struct Listing {
    client: ClusterServiceClient<dray_net::AuthChannel>,
    request: RegisterCacheHostRequest,
    host_id: String,
    refresh: Duration,
}

impl Listing {
    /// Take the coordinator's answer: id, secret (sent with every later call) and
    /// refresh interval.
    fn take(&mut self, r: RegisterCacheHostResponse) {
        self.host_id = r.host_id;
        self.request.member_token = r.member_token;
        if let Some(d) = r.refresh_interval.and_then(|d| Duration::try_from(d).ok()) {
            // Never busier than 10 calls a second, whatever a coordinator says.
            self.refresh = d.max(Duration::from_millis(100));
        }
    }

    /// Call RegisterCacheHost again to stay listed. Failures are logged and the next
    /// refresh tries again (the coordinator may be restarting).
    async fn refresh(&mut self, url: &str) {
        match self.client.register_cache_host(self.request.clone()).await {
            Ok(r) => {
                let before = self.host_id.clone();
                self.take(r.into_inner());
                if self.host_id != before {
                    eprintln!(
                        "dray cache: the coordinator at {url} had dropped this host; listed \
                         again as {}",
                        self.host_id
                    );
                }
            }
            Err(s) if s.code() == tonic::Code::PermissionDenied => {
                // Another process holds this endpoint's listing: start over next time.
                eprintln!("dray cache: refresh refused by {url}: {}", s.message());
                self.request.member_token.clear();
            }
            Err(s) => eprintln!("dray cache: cannot refresh with {url}: {}", s.message()),
        }
    }
}

/// RegisterCacheHost at `url` for `endpoint`, retrying connections for up to `patience`;
/// the listing. A refusal (another dray version, a bad endpoint, a coordinator without
/// `--cache-hosts`) is final.
async fn register(
    net: &dray_net::ClientOptions,
    url: &str,
    endpoint: &str,
    patience: Duration,
) -> Result<Listing> {
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
        member_token: String::new(),
    };
    let mut client = ClusterServiceClient::new(net.wrap(channel));
    let r = client.register_cache_host(req.clone()).await.map_err(|s| {
        anyhow::anyhow!(
            "the coordinator at {url} refused this cache host: {}",
            s.message()
        )
    })?;
    let mut listing = Listing {
        client,
        request: req,
        host_id: String::new(),
        refresh: Duration::from_secs(1),
    };
    listing.take(r.into_inner());
    Ok(listing)
}

/// This machine's name, for the coordinator's logs.
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".into())
}
