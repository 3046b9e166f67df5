//! Where rays leave a tracing step: this worker's queues, its peers' streams
//! ([`crate::peers`]) and the cache hosts' links ([`crate::cache_link`]).
//!
//! [`Links`] owns the streams to peers and the links to cache hosts, and makes the one
//! routing decision for every batch ([`destination`]): traced or held here, or sent to
//! an owner of its domain. The tracing threads hand it each step's results
//! ([`Links::deliver_step`]) and the rays they forward; the cache links hand it back
//! the rays a host answered or could not take (through [`Onward`], so that they need
//! not import this file). Results go into the job's report, posted to its actor.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use dray_cache::CacheHost;
use dray_core::ray::encoded_len;
use dray_proto::v1::TicketReturn;

use crate::cache_link::{self, CacheLinks, Onward};
use crate::jobs::{Job, Report};
use crate::member::Member;
use crate::peers::{PeerMessage, Peers};
use crate::queue::QueuedBatch;
use crate::routing::{Peer, Routes};
use crate::tickets::RayBundle;
use crate::tracer::Outbox;
use crate::traffic_trace::{Sent, StepRecord, thread_cpu_ns};
use crate::wake::Wake;
use crate::workload::Workload;

/// Times a batch may be forwarded before the job fails. A receiver whose table is
/// older than the sender's waits for its own instead of forwarding, so rays do not
/// bounce between tables; each forward follows a newer table, and this only catches a
/// routing bug.
pub const MAX_FORWARDS: u32 = 16;

/// Where a batch of rays bound for one domain goes (docs/architecture.md "Life of a
/// ray", 5 and 7). Rays at walls have gone to the walls' cache actors before this.
enum Destination {
    /// This worker's queue: it owns the domain under the job's table, or holds its rays
    /// until a worker is given the domain.
    Here,
    /// An owner of the domain, chosen over its replicas.
    Peer(Peer),
}

/// Why a batch has nowhere to go. Each fails the job: it means the routing tables
/// disagree, never a transient condition.
enum Unroutable {
    /// The batch was forwarded [`MAX_FORWARDS`] times already.
    Forwarded,
    /// The table has no owner for the domain.
    NoOwner,
}

/// Where a batch for `domain`, forwarded `forwards` times so far, goes under `routes`:
/// the one routing decision for the rays a step sends ([`Links::deliver`]) and for the
/// rays queued here for a domain this worker no longer owns ([`Links::forward`]).
/// Replicas of the domain take turns by `spread` (the job's), counted only when a peer
/// is chosen.
fn destination(
    routes: &Routes,
    domain: u32,
    forwards: u32,
    spread: &AtomicU64,
) -> Result<Destination, Unroutable> {
    if routes.owns(domain) || routes.is_held(domain) {
        return Ok(Destination::Here);
    }
    if forwards >= MAX_FORWARDS {
        return Err(Unroutable::Forwarded);
    }
    let spread = spread.fetch_add(1, Ordering::Relaxed) as u32;
    match routes.owner(domain, spread) {
        Some(peer) => Ok(Destination::Peer(peer.clone())),
        None => Err(Unroutable::NoOwner),
    }
}

/// The ways out of a tracing step.
pub(crate) struct Links {
    /// Who the worker is (named in the failures of jobs whose rays cannot be routed).
    member: Arc<Member>,
    /// Rays for domains this worker owns go to its queues.
    workload: Arc<Workload>,
    peers: Peers,
    caches: CacheLinks,
}

impl Links {
    /// Links that reach peers and cache hosts with `net`; `local`, the cache host in
    /// this process and its endpoint, is reached through its actors' mailboxes. Rays
    /// that leave wake the tracing threads (`wake`): room for camera rays again.
    pub fn new(
        member: Arc<Member>,
        workload: Arc<Workload>,
        wake: Arc<Wake>,
        net: dray_net::ClientOptions,
        local: Option<(String, CacheHost)>,
    ) -> Links {
        let runtime = tokio::runtime::Handle::current();
        Links {
            peers: Peers::new(runtime.clone(), member.clone(), net.clone(), wake.clone()),
            caches: CacheLinks::new(runtime, local, member.clone(), net, wake),
            member,
            workload,
        }
    }

    /// The cache host in this process, when `routes` make it this worker's replica of
    /// every wall (sender placement): its maps may then be consulted in place.
    pub fn local_cache_host(&self, routes: &Routes) -> Option<&CacheHost> {
        self.caches.local_host(routes)
    }

    /// These links as where the cache links deliver answered rays.
    fn onward(self: &Arc<Self>) -> Arc<dyn Onward> {
        self.clone()
    }

    /// Send the hit-map outcomes `job` gathered for other workers' copies of the maps,
    /// if any (sender placement).
    pub fn flush_merges(self: &Arc<Self>, job: &Arc<Job>) {
        cache_link::flush_merges(&self.caches, &self.onward(), job);
    }

    /// Return `returns` to their tickets' cache hosts, and wait until they (and, on
    /// replicated walls, every other replica) applied them
    /// ([`crate::cache_link::return_tickets`]).
    pub async fn return_tickets(self: &Arc<Self>, job: &Arc<Job>, returns: Vec<TicketReturn>) {
        cache_link::return_tickets(&self.caches, &self.onward(), job, returns).await;
    }

    /// End the streams to peers (so their servers can stop too), then the links to cache
    /// hosts, each after a moment to send what it holds.
    pub async fn close(&self) {
        self.peers.close().await;
        self.caches.close().await;
    }

    /// Rays queued here for `domain`, which this worker no longer owns: on to an owner.
    pub fn forward(&self, job: &Arc<Job>, domain: u32, batch: QueuedBatch) {
        if !job.is_active() {
            return;
        }
        let routes = job.routes();
        let n = batch.rays.len() as u64;
        let peer = match destination(&routes, domain, batch.forwards, job.spread()) {
            Ok(Destination::Peer(peer)) => peer,
            Ok(Destination::Here) => {
                // The table changed meanwhile: trace them here, or hold them here.
                self.workload.queues().push_local(domain, batch);
                return;
            }
            Err(Unroutable::Forwarded) => {
                job.fail(format!(
                    "worker {}: rays for domain {domain} were forwarded {} times (routing version {}); the routing tables disagree",
                    self.member.id(),
                    batch.forwards,
                    routes.version
                ));
                return;
            }
            Err(Unroutable::NoOwner) => {
                job.fail(format!(
                    "worker {}: routing version {} has no owner for domain {domain}",
                    self.member.id(),
                    routes.version
                ));
                return;
            }
        };
        let bytes = encoded_len(&batch.rays) as u64;
        let mut report = Report {
            rays_forwarded: n,
            rays_sent: n,
            bytes,
            ..Report::default()
        };
        report.traffic.rays(bytes, &batch.tickets);
        if let Some(t) = &job.trace {
            t.forward(Sent {
                domain,
                rays: n,
                bytes: report.traffic.get(crate::traffic::Kind::Rays),
            });
        }
        job.post(report);
        self.peers.send(
            &peer,
            PeerMessage {
                job: job.clone(),
                domain,
                rays: batch.rays,
                tickets: batch.tickets,
                forwards: batch.forwards + 1,
                routing_version: routes.version,
            },
        );
    }

    /// Results into the job's report, with `report` (counters of the caller's own), posted
    /// to the job's actor: one step's results travel together. Rays go to this worker's
    /// queues or to their owners, rays at walls to the walls' cache actors.
    pub fn deliver(self: &Arc<Self>, job: &Arc<Job>, out: Outbox, report: Report) {
        self.deliver_step(job, out, report, None);
    }

    /// [`Links::deliver`] for the step `timing` timed. With a traffic trace, every delivery
    /// is a `step` record there (one `timing` does not time, such as rays a cache actor
    /// answered, has no CPU and no rays in): so the trace's totals are the job's.
    pub(crate) fn deliver_step(
        self: &Arc<Self>,
        job: &Arc<Job>,
        mut out: Outbox,
        mut report: Report,
        timing: Option<StepTiming>,
    ) {
        let mut step = Departures {
            record: begin_record(job, timing.as_ref(), &out, &report),
            ..Departures::default()
        };
        report.phm_rays_not_sent += std::mem::take(&mut out.phm_not_sent);
        report.cache_rays_not_sent += std::mem::take(&mut out.cache_not_sent);
        let onward = self.onward();
        if !out.lookups.is_empty() {
            cache_link::send_lookups(&self.caches, &onward, job, std::mem::take(&mut out.lookups));
        }
        if !out.outcomes.is_empty() {
            let outcomes = std::mem::take(&mut out.outcomes);
            cache_link::send_outcomes(&self.caches, &onward, job, outcomes);
        }
        let rays = std::mem::take(&mut out.rays);
        if !self.route_rays(job, rays, &mut step) {
            return;
        }
        add_results(&mut report, out, &step);
        job.post(report);
        if let (Some(t), Some(rec)) = (&job.trace, step.record) {
            t.step(&rec);
        }
    }

    /// Each batch of a step's `rays` to its domain's destination under the job's table:
    /// this worker's queues or a peer. False when a batch has none (the job failed: the
    /// step's results are not reported).
    fn route_rays(
        &self,
        job: &Arc<Job>,
        rays: impl IntoIterator<Item = (u32, RayBundle)>,
        step: &mut Departures,
    ) -> bool {
        let routes = job.routes();
        for (d, bundle) in rays {
            if bundle.is_empty() {
                continue;
            }
            match destination(&routes, d, 0, job.spread()) {
                Ok(Destination::Peer(peer)) => {
                    self.send_to_peer(job, &routes, &peer, d, bundle, step)
                }
                // Traced here, or held here until a worker is given the domain.
                Ok(Destination::Here) => self.keep_here(job, &routes, d, bundle, step),
                // Never forwarded yet: only a table without an owner gets here.
                Err(Unroutable::NoOwner | Unroutable::Forwarded) => {
                    job.fail(format!(
                        "worker {}: a ray goes to domain {d}, which routing version {} does not route",
                        self.member.id(),
                        routes.version
                    ));
                    return false;
                }
            }
        }
        true
    }

    /// A step's rays for domain `d` into this worker's queue (noted in the step's
    /// record, as not remote).
    fn keep_here(
        &self,
        job: &Job,
        routes: &Routes,
        d: u32,
        bundle: RayBundle,
        step: &mut Departures,
    ) {
        let (rays, tickets) = (bundle.rays, bundle.tickets);
        if let Some(r) = &mut step.record {
            let bytes = crate::traffic::ray_bytes(encoded_len(&rays) as u64, &tickets);
            r.out.push((
                Sent {
                    domain: d,
                    rays: rays.len() as u64,
                    bytes,
                },
                false,
            ));
        }
        self.workload.queues().push_local(
            d,
            QueuedBatch {
                job_id: job.key.id.clone(),
                attempt: job.key.attempt,
                routing_version: routes.version,
                forwards: 0,
                rays,
                tickets,
            },
        );
    }

    /// A step's rays for domain `d` to `peer`, counted in the step's departures (and
    /// noted in its record, as remote).
    fn send_to_peer(
        &self,
        job: &Arc<Job>,
        routes: &Routes,
        peer: &Peer,
        d: u32,
        bundle: RayBundle,
        step: &mut Departures,
    ) {
        let (rays, tickets) = (bundle.rays, bundle.tickets);
        let n = encoded_len(&rays) as u64;
        step.rays += rays.len() as u64;
        step.bytes += n;
        if let Some(r) = &mut step.record {
            r.out.push((
                Sent {
                    domain: d,
                    rays: rays.len() as u64,
                    bytes: crate::traffic::ray_bytes(n, &tickets),
                },
                true,
            ));
        }
        step.traffic.rays(n, &tickets);
        self.peers.send(
            peer,
            PeerMessage {
                job: job.clone(),
                domain: d,
                rays,
                tickets,
                forwards: 0,
                routing_version: routes.version,
            },
        );
    }
}

/// Where one step's rays went: what it sent to peers, for its report, and the traffic
/// trace's record of the step (when the job has a trace).
#[derive(Default)]
struct Departures {
    record: Option<StepRecord>,
    /// Rays sent to peers.
    rays: u64,
    /// Their encoded bytes.
    bytes: u64,
    traffic: crate::traffic::Traffic,
}

/// The traffic trace's record of a step, begun before its rays leave (where they go
/// is added as they go); `None` when the job has no trace.
fn begin_record(
    job: &Job,
    timing: Option<&StepTiming>,
    out: &Outbox,
    report: &Report,
) -> Option<StepRecord> {
    let t = job.trace.as_ref()?;
    let now = t.now_ns();
    let (domain, rays_in, t0_ns, cpu_ns) = match timing {
        Some(s) => (
            s.domain,
            s.rays_in,
            s.t0_ns,
            thread_cpu_ns().saturating_sub(s.cpu0_ns),
        ),
        None => (None, 0, now, 0),
    };
    Some(StepRecord {
        domain,
        rays_in,
        t0_ns,
        t1_ns: now,
        cpu_ns,
        traced: out.traced.iter().sum(),
        lookups: out.lookups.len() as u64,
        cache_not_sent: report.cache_rays_not_sent + out.cache_not_sent,
        phm_not_sent: report.phm_rays_not_sent + out.phm_not_sent,
        out: Vec::new(),
    })
}

/// A step's results (what is left of its outbox once its rays left) and what it `sent`
/// to peers into its report.
fn add_results(r: &mut Report, mut out: Outbox, sent: &Departures) {
    r.sums.extend(&out.sums);
    r.aovs.extend(&out.aovs);
    r.credits.append(&mut out.credits);
    for (k, n) in out.traced.iter().enumerate() {
        r.traced[k] += n;
    }
    r.nonfinite += out.nonfinite;
    r.clamped += out.clamped;
    r.clamped_indirect += out.clamped_indirect;
    r.tickets.merge(std::mem::take(&mut out.tickets));
    r.bytes += sent.bytes;
    r.rays_sent += sent.rays;
    r.traffic.add(&sent.traffic);
}

impl Onward for Links {
    fn deliver_onward(self: Arc<Self>, job: &Arc<Job>, out: Outbox, report: Report) {
        Links::deliver(&self, job, out, report);
    }
}

/// When a traced step began, for the job's traffic trace (only a job with one takes
/// the clocks).
pub(crate) struct StepTiming {
    domain: Option<u32>,
    rays_in: u64,
    t0_ns: u64,
    cpu0_ns: u64,
}

impl StepTiming {
    pub(crate) fn start(job: &Job, domain: Option<u32>, rays_in: u64) -> Option<StepTiming> {
        let t = job.trace.as_ref()?;
        Some(StepTiming {
            domain,
            rays_in,
            t0_ns: t.now_ns(),
            cpu0_ns: thread_cpu_ns(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::routing::tests::table;

    /// Worker `me`'s view of a table over four domains: 0 on a, 1 on b, 2 on both,
    /// 3 on none (held).
    fn routes(me: &str) -> Routes {
        let t = table(&[(0, "a"), (1, "b"), (2, "a"), (2, "b")], false);
        Routes::new(&t, me, 4).expect("routes")
    }

    /// The destination as a name: "here", the peer's id, or the reason it has none.
    fn to(routes: &Routes, domain: u32, forwards: u32, spread: &AtomicU64) -> String {
        match destination(routes, domain, forwards, spread) {
            Ok(Destination::Here) => "here".into(),
            Ok(Destination::Peer(p)) => p.id,
            Err(Unroutable::Forwarded) => "forwarded too often".into(),
            Err(Unroutable::NoOwner) => "no owner".into(),
        }
    }

    #[test]
    fn a_batch_goes_here_to_an_owner_or_nowhere() {
        let a = routes("a");
        let spread = AtomicU64::new(0);
        assert_eq!(to(&a, 0, 0, &spread), "here", "owned");
        assert_eq!(to(&a, 2, 0, &spread), "here", "owned, replicated");
        assert_eq!(to(&a, 3, 0, &spread), "here", "held until a worker has it");
        assert_eq!(
            to(&a, 0, MAX_FORWARDS, &spread),
            "here",
            "owned: never too often"
        );
        assert_eq!(to(&a, 1, MAX_FORWARDS, &spread), "forwarded too often");
        assert_eq!(spread.load(Ordering::Relaxed), 0, "no peer chosen yet");
        assert_eq!(to(&a, 1, 0, &spread), "b");
        assert_eq!(to(&a, 1, MAX_FORWARDS - 1, &spread), "b");
        assert_eq!(to(&a, 9, 0, &spread), "no owner", "not in the table");
        assert_eq!(spread.load(Ordering::Relaxed), 3);
    }

    #[test]
    fn replicas_take_turns() {
        // A worker the table does not list owns nothing: every domain goes to a peer.
        let c = routes("c");
        let spread = AtomicU64::new(0);
        let picks: Vec<String> = (0..4).map(|_| to(&c, 2, 0, &spread)).collect();
        assert_eq!(picks, ["a", "b", "a", "b"]);
        assert_eq!(to(&c, 0, 0, &spread), "a");
    }
}
