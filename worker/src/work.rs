//! The tracing threads: choose work, trace it, hand the results on.
//!
//! Work, in order of preference:
//! 1. **The fullest queue** (Navrátil et al.: each process works on its fullest queue).
//!    If this worker no longer owns the queue's domain (the routing table moved it),
//!    its rays are forwarded to an owner. If the domain is not resident, this thread
//!    loads it (other threads go on with other work) — but only when no resident
//!    domain has rays waiting, so that rays for absent domains gather and each load
//!    serves as many as it can. A domain another thread is loading, or that cannot get
//!    room yet, is skipped for the next queue.
//! 2. **Camera rays** of the job's tiles, while the rays in flight here are below the
//!    in-flight limit: the only source of new work, so this bounds memory.
//!
//! **Tracing never waits for the network**: rays for other workers go to per-peer
//! outboxes ([`crate::peers`]), rays for domains this worker owns to its own queues
//! without waiting. So no cycle of workers waiting on each other's full queues can form.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use dray_core::ray::encoded_len;

use crate::contain::contained;
use crate::domain_store::{DomainStore, JobKey, LoadError, LoadedDomain};
use crate::jobs::{Job, Report, Standing};
use crate::node::Shared;
use crate::peers::PeerMessage;
use crate::queue::QueuedBatch;
use crate::routing::{Peer, Routes};
use crate::tracer::{Outbox, Residency, TileRef};
use crate::traffic_trace::{Sent, StepRecord, thread_cpu_ns};

/// Camera rays made in one tracing step.
const CAMERA_CHUNK: u64 = 4096;
/// Times a batch may be forwarded before the job fails. A receiver whose table is
/// older than the sender's waits for its own instead of forwarding, so rays do not
/// bounce between tables; each forward follows a newer table, and this only catches a
/// routing bug.
pub const MAX_FORWARDS: u32 = 16;

/// One piece of work for a tracing thread.
enum Work {
    /// Rays queued for a domain this worker owns, and the domain, held so that no
    /// eviction can take it between choosing the work and tracing it.
    Rays(Arc<Job>, Arc<LoadedDomain>, QueuedBatch),
    /// Rays queued for a domain this worker no longer owns.
    Forward(Arc<Job>, u32, QueuedBatch),
    /// Camera rays `start..start + count` of a tile.
    Camera(Arc<Job>, TileRef, u64, u64),
}

/// What a step may trace here: domains resident and owned under the job's table.
struct StepResidency<'a> {
    store: &'a DomainStore,
    key: &'a JobKey,
    routes: &'a Routes,
    /// The domain the work was chosen for, already held.
    held: Option<&'a Arc<LoadedDomain>>,
    /// The job's walls in this process, to consult in place (sender placement).
    views: Option<Arc<dray_cache::WallViews>>,
}

impl Residency for StepResidency<'_> {
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>> {
        if let Some(h) = self.held
            && h.domain == d
        {
            return Some(h.clone());
        }
        if self.routes.owns(d) {
            self.store.get(self.key, d)
        } else {
            None
        }
    }

    fn walls(&self) -> bool {
        self.routes.has_caches()
    }

    fn map(&self, wall: u32) -> Option<&dray_cache::MapView> {
        self.views.as_deref()?.map(wall)
    }

    fn cache(&self, wall: u32) -> Option<&dray_cache::StoreView> {
        self.views.as_deref()?.cache(wall)
    }
}

/// One tracing thread: take work, trace it, hand the results on; sleep when there is
/// none, until new rays or tiles arrive (the timeout is only a safety net).
///
/// Tracing and loads contain their own panics and fail their job with them (see
/// [`crate::contain`]). A panic anywhere else in a step (choosing work, delivering
/// results) is caught here too: logged, and the thread goes on after a short pause, so
/// the worker never loses a tracing thread to one.
pub(crate) fn tracer_thread(shared: &Arc<Shared>) {
    while !shared.stopping.load(Ordering::Relaxed) {
        let seen = shared.wake.seen();
        if let Err(e) = crate::contain::contained_while("choosing work", || step(shared, seen)) {
            tracing::error!(worker = %shared.id(), "{e}");
            // Not a hot loop if it panics again at once.
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// One turn of a tracing thread: a piece of work, or a wait for some.
fn step(shared: &Arc<Shared>, seen: u64) {
    match next_work(shared) {
        Some(work) => trace(shared, work),
        None => {
            // Nothing to trace: hit-map outcomes gathered for the other workers' copies
            // go now rather than wait for a full batch (sender placement).
            for job in shared.jobs.all() {
                crate::cache_link::flush_merges(shared, &job);
            }
            let start = Instant::now();
            shared.wake.wait(seen, Duration::from_millis(50));
            let idle = start.elapsed().as_secs_f64();
            for job in shared.jobs.all() {
                job.post(Report {
                    idle_seconds: idle,
                    ..Report::default()
                });
            }
        }
    }
}

/// The next piece of work, if any.
fn next_work(shared: &Shared) -> Option<Work> {
    let mut lengths = shared.queues.lengths();
    // Fullest first; ties in key order, so threads agree.
    lengths.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    // The fullest queue whose domain is already here: while any resident domain has
    // rays, no other domain is loaded (nor one evicted for it). Rays for the domains
    // that are not here gather meanwhile, so each load serves as many rays as it can:
    // loads are what an out-of-core worker pays for.
    // Only domains this worker owns count: rays queued for a resident domain that the
    // table moved away are forwarded, not traced, and must not hold back a load.
    let resident_best = lengths
        .iter()
        .find(|(k, _)| {
            shared.jobs.get(&k.job_id).is_some_and(|j| {
                j.key.attempt == k.attempt
                    && !j.has_failed()
                    && j.routes().owns(k.domain)
                    && shared.store.is_resident(&j.key, k.domain)
            })
        })
        .map_or(0, |(_, n)| *n);
    // Under a memory budget, when no resident domain has rays, camera rays come before
    // a load, as many as the in-flight limit allows: each load then serves them too.
    // Made only once the queues drain, every chunk of camera rays walked the domains
    // again (and a job tracing passes ahead walked once per pass: issue 38).
    if resident_best == 0
        && shared.store.budget() > 0
        && let Some(w) = camera_work(shared)
    {
        return Some(w);
    }
    for (key, _) in lengths {
        let job = match shared.jobs.standing(&key.job_id, key.attempt) {
            Standing::Running(job) if !job.has_failed() => job,
            Standing::Running(_) | Standing::Gone => {
                shared.queues.drop_job(&key.job_id, key.attempt);
                continue;
            }
            // Its setup is on the way: keep the rays.
            Standing::Pending => continue,
        };
        let d = key.domain;
        let routes = job.routes();
        if routes.is_held(d) {
            // No worker has the domain now: its rays wait here for a table that gives it.
            continue;
        }
        if !routes.owns(d) {
            // A sender with a newer table than ours says this worker owns the domain:
            // our table is on its way; forwarding now could bounce the rays back.
            if shared
                .queues
                .front_version(&key)
                .is_some_and(|v| v > routes.version)
            {
                continue;
            }
            if let Some(b) = shared.queues.pop(&key) {
                return Some(Work::Forward(job, d, b));
            }
            continue;
        }
        let held = match shared.store.get(&job.key, d) {
            Some(h) => h,
            None if resident_best > 0 => continue,
            None => match load(shared, &job, d) {
                Ok(h) => {
                    // Threads that skipped this domain's rays while it loaded (and found
                    // nothing else) are asleep: wake them to share the rays now, rather
                    // than when their safety-net timeout ends (up to 50 ms of one idle
                    // thread at the start of every job).
                    shared.notify();
                    h
                }
                Err(LoadError::Busy { .. }) => continue,
                Err(e) => {
                    job.fail(format!("worker {}: {e}", shared.id()));
                    continue;
                }
            },
        };
        if let Some(b) = shared.queues.pop(&key) {
            return Some(Work::Rays(job, held, b));
        }
    }
    camera_work(shared)
}

/// The next chunk of some job's camera rays, while the worker's rays in flight are under
/// its limit.
fn camera_work(shared: &Shared) -> Option<Work> {
    if shared.in_flight() >= shared.limits.in_flight_limit {
        return None;
    }
    for job in shared.jobs.all() {
        if job.has_failed() {
            continue;
        }
        if job.tiles().is_empty() || !camera_ready(shared, &job) {
            continue;
        }
        let spp = job.tracer.settings().spp;
        if let Some((t, start, count)) = job.tiles().take(CAMERA_CHUNK, |t| t.camera_rays(spp)) {
            return Some(Work::Camera(job, t, start, count));
        }
    }
    None
}

/// Whether `job`'s camera rays (some are left) can be made now. A job of one domain has
/// it loaded first, by the thread that would make them: made earlier, every camera ray
/// would be packed, queued for the domain and unpacked again instead of traced at once,
/// and making them would take the cores from the domain's build. False while another
/// thread loads it (that thread wakes the others when it is done) or when the load fails
/// (the job fails with it).
fn camera_ready(shared: &Shared, job: &Arc<Job>) -> bool {
    let Some(d) = job.tracer.single_domain() else {
        return true;
    };
    if !job.routes().owns(d) || shared.store.is_resident(&job.key, d) {
        return true;
    }
    match load(shared, job, d) {
        Ok(_) => {
            shared.notify();
            true
        }
        Err(LoadError::Busy { .. }) => false,
        Err(e) => {
            job.fail(format!("worker {}: {e}", shared.id()));
            false
        }
    }
}

/// Load domain `d` of `job` in the job's span; a load (not a domain found resident) goes
/// into the job's traffic trace, if it has one.
fn load(shared: &Shared, job: &Job, d: u32) -> Result<Arc<LoadedDomain>, LoadError> {
    let load = || shared.store.load_telling(&job.key, d, job.source.as_ref());
    let Some(t) = &job.trace else {
        return job.span.in_scope(load).map(|(h, _)| h);
    };
    let (t0, cpu0) = (t.now_ns(), thread_cpu_ns());
    let (h, loaded) = job.span.in_scope(load)?;
    if loaded {
        t.load(d, h.bytes, t0, t.now_ns(), thread_cpu_ns() - cpu0);
    }
    Ok(h)
}

/// Trace one piece of work and hand the results on.
fn trace(shared: &Arc<Shared>, work: Work) {
    let mut out = Outbox::default();
    let timing;
    let (job, result) = match work {
        Work::Rays(job, held, batch) => {
            if !job.is_active() {
                return;
            }
            let d = held.domain;
            timing = StepTiming::start(&job, Some(d), batch.rays.len() as u64);
            let _span = tracing::trace_span!(parent: &job.span, "batch", job = %job.key.id, domain = d, rays = batch.rays.len())
                .entered();
            let routes = job.routes();
            let residency = StepResidency {
                store: &shared.store,
                key: &job.key,
                routes: &routes,
                held: Some(&held),
                views: job.wall_views(shared.caches.local_host(&routes)),
            };
            let r = contained(|| {
                job.tracer
                    .trace_batch(d, &batch.rays, &batch.tickets, &residency, &mut out)
            });
            (job, r)
        }
        Work::Camera(job, tile, start, count) => {
            if !job.is_active() {
                return;
            }
            timing = StepTiming::start(&job, None, count);
            let _span =
                tracing::trace_span!(parent: &job.span, "tile", job = %job.key.id, tile = tile.index, start).entered();
            let routes = job.routes();
            let residency = StepResidency {
                store: &shared.store,
                key: &job.key,
                routes: &routes,
                held: None,
                views: job.wall_views(shared.caches.local_host(&routes)),
            };
            let r = contained(|| {
                job.tracer
                    .camera_rays(&tile, start, count, &residency, &mut out)
            });
            (job, r)
        }
        Work::Forward(job, d, batch) => {
            forward(shared, &job, d, batch);
            return;
        }
    };
    match result {
        Ok(Ok(())) => deliver_step(shared, &job, out, Report::default(), timing),
        Ok(Err(e)) => job.fail(format!("worker {}: {e}", shared.id())),
        Err(panic) => job.fail(format!("worker {}: {panic}", shared.id())),
    }
}

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
/// the one routing decision for the rays a step sends ([`deliver_with`]) and for the rays
/// queued here for a domain this worker no longer owns ([`forward`]). Replicas of the
/// domain take turns by `spread` (the job's), counted only when a peer is chosen.
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

/// Rays queued here for `domain`, which this worker no longer owns: on to an owner.
fn forward(shared: &Arc<Shared>, job: &Arc<Job>, domain: u32, batch: QueuedBatch) {
    if !job.is_active() {
        return;
    }
    let routes = job.routes();
    let n = batch.rays.len() as u64;
    let peer = match destination(&routes, domain, batch.forwards, job.spread()) {
        Ok(Destination::Peer(peer)) => peer,
        Ok(Destination::Here) => {
            // The table changed meanwhile: trace them here, or hold them here.
            shared.queues.push_local(domain, batch);
            return;
        }
        Err(Unroutable::Forwarded) => {
            job.fail(format!(
                "worker {}: rays for domain {domain} were forwarded {} times (routing version {}); the routing tables disagree",
                shared.id(),
                batch.forwards,
                routes.version
            ));
            return;
        }
        Err(Unroutable::NoOwner) => {
            job.fail(format!(
                "worker {}: routing version {} has no owner for domain {domain}",
                shared.id(),
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
            bytes: report.traffic.rays,
        });
    }
    job.post(report);
    shared.peers.send(
        shared,
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
pub(crate) fn deliver_with(shared: &Arc<Shared>, job: &Arc<Job>, out: Outbox, report: Report) {
    deliver_step(shared, job, out, report, None);
}

/// When a traced step began, for the job's traffic trace (only a job with one takes
/// the clocks).
struct StepTiming {
    domain: Option<u32>,
    rays_in: u64,
    t0_ns: u64,
    cpu0_ns: u64,
}

impl StepTiming {
    fn start(job: &Job, domain: Option<u32>, rays_in: u64) -> Option<StepTiming> {
        let t = job.trace.as_ref()?;
        Some(StepTiming {
            domain,
            rays_in,
            t0_ns: t.now_ns(),
            cpu0_ns: thread_cpu_ns(),
        })
    }
}

/// [`deliver_with`] for the step `timing` timed. With a traffic trace, every delivery
/// is a `step` record there (one `timing` does not time, such as rays a cache actor
/// answered, has no CPU and no rays in): so the trace's totals are the job's.
fn deliver_step(
    shared: &Arc<Shared>,
    job: &Arc<Job>,
    mut out: Outbox,
    mut report: Report,
    timing: Option<StepTiming>,
) {
    let mut record = job.trace.as_ref().map(|t| {
        let now = t.now_ns();
        let (domain, rays_in, t0_ns, cpu_ns) = match &timing {
            Some(s) => (
                s.domain,
                s.rays_in,
                s.t0_ns,
                thread_cpu_ns().saturating_sub(s.cpu0_ns),
            ),
            None => (None, 0, now, 0),
        };
        StepRecord {
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
        }
    });
    report.phm_rays_not_sent += std::mem::take(&mut out.phm_not_sent);
    report.cache_rays_not_sent += std::mem::take(&mut out.cache_not_sent);
    if !out.lookups.is_empty() {
        crate::cache_link::send_lookups(shared, job, std::mem::take(&mut out.lookups));
    }
    if !out.outcomes.is_empty() {
        crate::cache_link::send_outcomes(shared, job, std::mem::take(&mut out.outcomes));
    }
    let routes = job.routes();
    let mut sent = 0u64;
    let mut bytes = 0u64;
    let mut traffic = crate::traffic::Traffic::default();
    for (d, bundle) in out.rays {
        if bundle.is_empty() {
            continue;
        }
        let (rays, tickets) = (bundle.rays, bundle.tickets);
        let peer = match destination(&routes, d, 0, job.spread()) {
            Ok(Destination::Peer(peer)) => peer,
            Ok(Destination::Here) => {
                if let Some(r) = &mut record {
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
                // Traced here, or held here until a worker is given the domain.
                shared.queues.push_local(
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
                continue;
            }
            // Never forwarded yet: only a table without an owner gets here.
            Err(Unroutable::NoOwner | Unroutable::Forwarded) => {
                job.fail(format!(
                    "worker {}: a ray goes to domain {d}, which routing version {} does not route",
                    shared.id(),
                    routes.version
                ));
                return;
            }
        };
        let n = encoded_len(&rays) as u64;
        sent += rays.len() as u64;
        bytes += n;
        if let Some(r) = &mut record {
            r.out.push((
                Sent {
                    domain: d,
                    rays: rays.len() as u64,
                    bytes: crate::traffic::ray_bytes(n, &tickets),
                },
                true,
            ));
        }
        traffic.rays(n, &tickets);
        shared.peers.send(
            shared,
            &peer,
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
    let r = &mut report;
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
    r.bytes += bytes;
    r.rays_sent += sent;
    r.traffic.add(&traffic);
    job.post(report);
    if let (Some(t), Some(rec)) = (&job.trace, record) {
        t.step(&rec);
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
