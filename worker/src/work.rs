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
//! **Tracing never waits for the network**: results leave through [`crate::links`],
//! rays for other workers to per-peer outboxes, rays for domains this worker owns to
//! its own queues, without waiting. So no cycle of workers waiting on each other's full
//! queues can form.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::contain::contained;
use crate::domain_store::{DomainStore, JobKey, LoadError, LoadedDomain};
use crate::jobs::{Job, Report, Standing};
use crate::links::{Links, StepTiming};
use crate::member::Member;
use crate::queue::QueuedBatch;
use crate::routing::Routes;
use crate::tracer::{Outbox, Residency, TileRef};
use crate::traffic_trace::thread_cpu_ns;
use crate::workload::Workload;

/// Camera rays made in one tracing step.
const CAMERA_CHUNK: u64 = 4096;

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
pub(crate) fn tracer_thread(workload: &Workload, links: &Arc<Links>, member: &Member) {
    while !workload.is_stopping() {
        let seen = workload.wake().seen();
        if let Err(e) =
            crate::contain::contained_while("choosing work", || step(workload, links, member, seen))
        {
            tracing::error!(worker = %member.id(), "{e}");
            // Not a hot loop if it panics again at once.
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// One turn of a tracing thread: a piece of work, or a wait for some.
fn step(workload: &Workload, links: &Arc<Links>, member: &Member, seen: u64) {
    match next_work(workload, member) {
        Some(work) => trace(workload, links, member, work),
        None => {
            // Nothing to trace: hit-map outcomes gathered for the other workers' copies
            // go now rather than wait for a full batch (sender placement).
            for job in workload.jobs().all() {
                links.flush_merges(&job);
            }
            let start = Instant::now();
            workload.wake().wait(seen, Duration::from_millis(50));
            let idle = start.elapsed().as_secs_f64();
            for job in workload.jobs().all() {
                job.post(Report {
                    idle_seconds: idle,
                    ..Report::default()
                });
            }
        }
    }
}

/// The next piece of work, if any.
fn next_work(workload: &Workload, member: &Member) -> Option<Work> {
    let mut lengths = workload.queues().lengths();
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
            workload.jobs().get(&k.job_id).is_some_and(|j| {
                j.key.attempt == k.attempt
                    && !j.has_failed()
                    && j.routes().owns(k.domain)
                    && workload.store().is_resident(&j.key, k.domain)
            })
        })
        .map_or(0, |(_, n)| *n);
    // Under a memory budget, when no resident domain has rays, camera rays come before
    // a load, as many as the in-flight limit allows: each load then serves them too.
    // Made only once the queues drain, every chunk of camera rays walked the domains
    // again (and a job tracing passes ahead walked once per pass: issue 38).
    if resident_best == 0
        && workload.store().budget() > 0
        && let Some(w) = camera_work(workload, member)
    {
        return Some(w);
    }
    for (key, _) in lengths {
        let job = match workload.jobs().standing(&key.job_id, key.attempt) {
            Standing::Running(job) if !job.has_failed() => job,
            Standing::Running(_) | Standing::Gone => {
                workload.queues().drop_job(&key.job_id, key.attempt);
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
            if workload
                .queues()
                .front_version(&key)
                .is_some_and(|v| v > routes.version)
            {
                continue;
            }
            if let Some(b) = workload.queues().pop(&key) {
                return Some(Work::Forward(job, d, b));
            }
            continue;
        }
        let held = match workload.store().get(&job.key, d) {
            Some(h) => h,
            None if resident_best > 0 => continue,
            None => match load(workload, &job, d) {
                Ok(h) => {
                    // Threads that skipped this domain's rays while it loaded (and found
                    // nothing else) are asleep: wake them to share the rays now, rather
                    // than when their safety-net timeout ends (up to 50 ms of one idle
                    // thread at the start of every job).
                    workload.notify();
                    h
                }
                Err(LoadError::Busy { .. }) => continue,
                Err(e) => {
                    job.fail(format!("worker {}: {e}", member.id()));
                    continue;
                }
            },
        };
        if let Some(b) = workload.queues().pop(&key) {
            return Some(Work::Rays(job, held, b));
        }
    }
    camera_work(workload, member)
}

/// The next chunk of some job's camera rays, while the worker's rays in flight are under
/// its limit.
fn camera_work(workload: &Workload, member: &Member) -> Option<Work> {
    if workload.in_flight() >= workload.in_flight_limit() {
        return None;
    }
    for job in workload.jobs().all() {
        if job.has_failed() {
            continue;
        }
        if job.tiles().is_empty() || !camera_ready(workload, member, &job) {
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
fn camera_ready(workload: &Workload, member: &Member, job: &Arc<Job>) -> bool {
    let Some(d) = job.tracer.single_domain() else {
        return true;
    };
    if !job.routes().owns(d) || workload.store().is_resident(&job.key, d) {
        return true;
    }
    match load(workload, job, d) {
        Ok(_) => {
            workload.notify();
            true
        }
        Err(LoadError::Busy { .. }) => false,
        Err(e) => {
            job.fail(format!("worker {}: {e}", member.id()));
            false
        }
    }
}

/// Load domain `d` of `job` in the job's span; a load (not a domain found resident) goes
/// into the job's traffic trace, if it has one.
fn load(workload: &Workload, job: &Job, d: u32) -> Result<Arc<LoadedDomain>, LoadError> {
    let load = || {
        workload
            .store()
            .load_telling(&job.key, d, job.source.as_ref())
    };
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
fn trace(workload: &Workload, links: &Arc<Links>, member: &Member, work: Work) {
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
                store: workload.store(),
                key: &job.key,
                routes: &routes,
                held: Some(&held),
                views: job.wall_views(links.local_cache_host(&routes)),
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
                store: workload.store(),
                key: &job.key,
                routes: &routes,
                held: None,
                views: job.wall_views(links.local_cache_host(&routes)),
            };
            let r = contained(|| {
                job.tracer
                    .camera_rays(&tile, start, count, &residency, &mut out)
            });
            (job, r)
        }
        Work::Forward(job, d, batch) => {
            links.forward(&job, d, batch);
            return;
        }
    };
    match result {
        Ok(Ok(())) => links.deliver_step(&job, out, Report::default(), timing),
        Ok(Err(e)) => job.fail(format!("worker {}: {e}", member.id())),
        Err(panic) => job.fail(format!("worker {}: {panic}", member.id())),
    }
}
