//! Opening and closing a job attempt's walls on its cache hosts, over
//! `dray.v1.CacheService` (cache.proto): the coordinator's only calls to cache hosts.
//!
//! Each call has its own deadline, and the hosts are called concurrently, so one dead
//! host costs an attempt at most one timeout, never its whole start. A host that
//! cannot open its walls is left out and its walls are placed on the others
//! ([`Placement::without`]) and opened there, until every wall is open or no host is
//! left (then the attempt runs without caches). A host that cannot close (its process
//! died, say) is lost to the job; what it held is gone with it.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use dray_proto::v1::cache_service_client::CacheServiceClient;
use dray_proto::v1::{
    CacheHost, CloseWallsRequest, OpenWallsRequest, PhmSettings, PhmStats, RayCacheSettings,
    RayCacheStats,
};
use tokio::task::JoinSet;

use super::geometry::WallGeometry;
use super::placement::Placement;
use super::tally;

/// Longest wait to connect to a cache host.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);
/// Longest wait for OpenWalls: it starts an actor per wall, which is quick.
pub const OPEN_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest wait for CloseWalls: it drops the caches and sums their statistics.
pub const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// What identifies one attempt's walls on every host, and what they are opened with.
#[derive(Clone, Debug)]
pub struct AttemptWalls {
    /// The job.
    pub job_id: String,
    /// The attempt.
    pub attempt: u32,
    /// The ray-cache knobs, defaults filled in (None: hit maps only).
    pub settings: Option<RayCacheSettings>,
    /// The hit-map knobs, defaults filled in (None: ray caches only).
    pub phm: Option<PhmSettings>,
    /// Scene and domain boxes.
    pub geometry: Arc<WallGeometry>,
    /// How to reach the hosts (the cluster token, TLS).
    pub net: dray_net::ClientOptions,
}

/// A host that failed a call, and why (for logs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HostFailure {
    /// The host.
    pub host: CacheHost,
    /// What went wrong.
    pub reason: String,
}

/// What [`open`] did.
#[derive(Clone, Debug, Default)]
pub struct Opened {
    /// The placement whose walls are all open (empty when no host could open any).
    pub placement: Placement,
    /// Hosts left out because they could not open their walls.
    pub failed: Vec<HostFailure>,
}

/// What [`close`] did.
#[derive(Clone, Debug, Default)]
pub struct Closed {
    /// The hosts' statistics, summed.
    pub stats: RayCacheStats,
    /// The hosts' hit-map statistics, summed.
    pub phm: PhmStats,
    /// Hosts that could not close.
    pub failed: Vec<HostFailure>,
    /// The most ray-cache entries one host held (each host is one process): what
    /// `JobStats.cache_bytes_per_process` is made from.
    pub host_entries_max: u64,
}

impl Closed {
    /// Add what closing an attempt's walls returned to the job's `tally`: the hosts'
    /// ray-cache and hit-map statistics, and the most entries one host held.
    pub fn add_to(&self, tally: &tally::CacheTally) {
        tally.add_host(&self.stats);
        tally.add_host_phm(&self.phm);
        tally.note_host_entries(self.host_entries_max);
    }
}

/// A client for the host at `endpoint`, with the connect and call deadlines.
async fn client(
    net: &dray_net::ClientOptions,
    endpoint: &str,
    timeout: Duration,
) -> Result<CacheServiceClient<dray_net::AuthChannel>, String> {
    let channel = net
        .endpoint(endpoint)
        .map_err(|e| format!("bad endpoint: {e}"))?
        .connect_timeout(CONNECT_TIMEOUT)
        .timeout(timeout)
        .tcp_nodelay(true)
        .connect()
        .await
        .map_err(|e| format!("cannot connect: {e}"))?;
    Ok(CacheServiceClient::new(net.wrap(channel)))
}

async fn open_one(
    net: dray_net::ClientOptions,
    host: CacheHost,
    req: OpenWallsRequest,
) -> Result<u32, HostFailure> {
    let fail = |reason: String| HostFailure {
        host: host.clone(),
        reason,
    };
    let call = async {
        let mut c = client(&net, &host.endpoint, OPEN_TIMEOUT).await?;
        c.open_walls(req)
            .await
            .map(|r| r.into_inner().actors)
            .map_err(|s| format!("OpenWalls failed ({:?}): {}", s.code(), s.message()))
    };
    match tokio::time::timeout(CONNECT_TIMEOUT + OPEN_TIMEOUT, call).await {
        Ok(r) => r.map_err(fail),
        Err(_) => Err(fail(format!("no answer within {OPEN_TIMEOUT:?}"))),
    }
}

async fn close_one(
    net: dray_net::ClientOptions,
    host: CacheHost,
    req: CloseWallsRequest,
) -> Result<(RayCacheStats, PhmStats), HostFailure> {
    let fail = |reason: String| HostFailure {
        host: host.clone(),
        reason,
    };
    let call = async {
        let mut c = client(&net, &host.endpoint, CLOSE_TIMEOUT).await?;
        c.close_walls(req)
            .await
            .map(|r| {
                let r = r.into_inner();
                (r.stats.unwrap_or_default(), r.phm.unwrap_or_default())
            })
            .map_err(|s| format!("CloseWalls failed ({:?}): {}", s.code(), s.message()))
    };
    match tokio::time::timeout(CONNECT_TIMEOUT + CLOSE_TIMEOUT, call).await {
        Ok(r) => r.map_err(fail),
        Err(_) => Err(fail(format!("no answer within {CLOSE_TIMEOUT:?}"))),
    }
}

/// Open `placement`'s walls for `a` on every host; re-place the walls of hosts that fail
/// on the others until every wall is open or no host is left.
pub async fn open(a: &AttemptWalls, placement: Placement) -> Opened {
    let mut placement = placement;
    let mut failed_all = Vec::new();
    // (host index in `placement`, walls to open there)
    let mut todo: Vec<(usize, Vec<u32>)> = (0..placement.hosts().len())
        .map(|h| (h, placement.walls_of(h)))
        .collect();
    while !todo.is_empty() {
        let mut calls = JoinSet::new();
        for (h, walls) in todo.drain(..) {
            let host = placement.hosts()[h].clone();
            let req = OpenWallsRequest {
                job_id: a.job_id.clone(),
                attempt: a.attempt,
                settings: a.settings.clone(),
                scene_bounds: a.geometry.scene_bounds.to_vec(),
                domain_bounds: a.geometry.domain_bounds.clone(),
                walls,
                phm: a.phm.clone(),
                replica: placement.replica_of(h),
            };
            let net = a.net.clone();
            // In the job's span, so the call carries its trace context to the host.
            calls.spawn(tracing::Instrument::instrument(
                async move { (h, open_one(net, host, req).await) },
                tracing::Span::current(),
            ));
        }
        let mut failed = BTreeSet::new();
        while let Some(joined) = calls.join_next().await {
            match joined {
                Ok((_, Ok(actors))) => {
                    tracing::debug!(job = %a.job_id, attempt = a.attempt, actors, "walls opened");
                }
                Ok((h, Err(f))) => {
                    tracing::warn!(
                        job = %a.job_id,
                        attempt = a.attempt,
                        host = %f.host.host_id,
                        endpoint = %f.host.endpoint,
                        "cache host left out: {}",
                        f.reason
                    );
                    failed.insert(h);
                    failed_all.push(f);
                }
                // A call task that panicked: its host cannot be told apart, so the
                // attempt is not trusted with caches at all.
                Err(e) => {
                    tracing::error!(job = %a.job_id, "OpenWalls task died: {e}");
                    failed.extend(0..placement.hosts().len());
                }
            }
        }
        if failed.is_empty() {
            break;
        }
        let (next, gained) = placement.without(&failed);
        placement = next;
        todo = gained;
    }
    Opened {
        placement,
        failed: failed_all,
    }
}

/// Close attempt `attempt` of `job_id` on every host of `placement` and sum what they
/// return.
pub async fn close(
    job_id: &str,
    attempt: u32,
    placement: &Placement,
    net: &dray_net::ClientOptions,
) -> Closed {
    let mut calls = JoinSet::new();
    for host in placement.hosts() {
        let req = CloseWallsRequest {
            job_id: job_id.to_string(),
            attempt,
        };
        calls.spawn(close_one(net.clone(), host.clone(), req));
    }
    let mut out = Closed::default();
    while let Some(joined) = calls.join_next().await {
        match joined {
            Ok(Ok((stats, phm))) => {
                out.host_entries_max = out.host_entries_max.max(stats.entries);
                tally::add(&mut out.stats, &stats);
                tally::add_phm(&mut out.phm, &phm);
            }
            Ok(Err(f)) => {
                tracing::warn!(
                    job = %job_id,
                    attempt,
                    host = %f.host.host_id,
                    endpoint = %f.host.endpoint,
                    "cache host lost: {}",
                    f.reason
                );
                out.failed.push(f);
            }
            Err(e) => tracing::error!(job = %job_id, "CloseWalls task died: {e}"),
        }
    }
    out
}
