//! Reports to the coordinator: every few milliseconds, per job attempt, one
//! `ReportContributions` with the pixel sums, returned credit and counters accumulated
//! since the last one (a whole tracing step's results always travel in the same
//! report), retried with the same sequence number on failure; and every
//! [`QUEUE_REPORT_INTERVAL`], the job's queue lengths and resident domains: the
//! scheduler's input.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use dray_proto::v1::{
    DomainQueue, ProcessCpu, RayCounts, ReportContributionsRequest, ReportQueuesRequest,
    TileCredit, WorkerCounters,
};
use tokio::sync::watch;

use crate::jobs::{Job, Report, lock};
use crate::node::Shared;

/// How often accumulated results are reported.
const REPORT_INTERVAL: Duration = Duration::from_millis(10);
/// Contributions per ReportContributions message: about 2 MB, half gRPC's default limit.
const MAX_SUMS_PER_REPORT: usize = 64 * 1024;
/// How often queue lengths are reported (the scheduler's input).
pub const QUEUE_REPORT_INTERVAL: Duration = Duration::from_millis(100);

/// [`report_loop`], started again a second after a panic: a bug met while reporting one
/// job must not silently stop the credit of every job on this worker (a job whose
/// report keeps panicking stalls, and the coordinator's stall timeout ends it).
pub(crate) async fn supervised(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    loop {
        match dray_net::contain::contained(report_loop(shared.clone(), stop.clone())).await {
            Ok(()) => return,
            Err(panic) => {
                tracing::error!(%panic, "the reporter panicked; it starts again in 1 s");
                tokio::select! {
                    _ = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
                    _ = stop.wait_for(|s| *s) => return,
                }
            }
        }
    }
}

pub(crate) async fn report_loop(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let mut last_queues = tokio::time::Instant::now();
    loop {
        tokio::select! {
            _ = tokio::time::sleep(REPORT_INTERVAL) => {}
            _ = stop.wait_for(|s| *s) => return,
        }
        let jobs = shared.jobs.all();
        let queue_tick = last_queues.elapsed() >= QUEUE_REPORT_INTERVAL;
        if queue_tick {
            crate::metrics::record_queued(shared.in_flight() as u64);
        }
        for job in &jobs {
            let queued: u64 = shared
                .queues
                .job_lengths(&job.key.id, job.key.attempt)
                .iter()
                .map(|(_, n)| *n as u64)
                .sum();
            job.note_queued(queued + job.outgoing.load(Ordering::Relaxed) as u64);
            report(&shared, job, queue_tick).await;
        }
        if queue_tick {
            last_queues = tokio::time::Instant::now();
            for job in &jobs {
                report_queues(&shared, job).await;
            }
        }
    }
}

/// Send what `job` accumulated (with `force`, even if that is only idle time).
/// Contributions go in chunks that stay well inside gRPC's message limit; the credit
/// travels in the last one, so no credit reaches the coordinator before the
/// contributions of the same rays. What is owed to ray-cache tickets goes to their
/// cache actors first, and the report waits until they have applied it: a tile whose
/// credit is complete at the coordinator has then closed every ticket of its rays.
async fn report(shared: &Arc<Shared>, job: &Arc<Job>, force: bool) {
    let store = shared.store.take_counters(&job.key);
    let mut report = {
        let mut r = lock(&job.report);
        if r.is_empty()
            && store.loads == 0
            && store.warm == 0
            && store.evictions == 0
            && !(force && r.idle_seconds > 0.0)
        {
            return;
        }
        std::mem::take(&mut *r)
    };
    if !report.tickets.is_empty() {
        let returns = report.tickets.drain();
        crate::cache_link::return_tickets(shared, job, returns).await;
        // Bytes and lost hosts noted while returning ride along with this report.
        let mut r = lock(&job.report);
        report.cache_bytes += std::mem::take(&mut r.cache_bytes);
        report.traffic.add(&std::mem::take(&mut r.traffic));
        for h in r.lost_cache_hosts.drain(..) {
            if !report.lost_cache_hosts.contains(&h) {
                report.lost_cache_hosts.push(h);
            }
        }
    }
    let mut sums = report.sums.drain();
    while sums.len() > MAX_SUMS_PER_REPORT {
        let rest = sums.split_off(MAX_SUMS_PER_REPORT);
        let chunk = std::mem::replace(&mut sums, rest);
        let request = request(shared, job, chunk, Vec::new(), &Report::default(), None);
        if !send_report(shared, job, request).await {
            return;
        }
    }
    report.credits.sort_unstable_by_key(|c| c.0);
    report.credits.dedup_by(|next, kept| {
        let same = next.0 == kept.0;
        if same {
            kept.1 = kept.1.saturating_add(next.1);
        }
        same
    });
    let credits: Vec<TileCredit> = std::mem::take(&mut report.credits)
        .into_iter()
        .map(|(tile, credit)| TileCredit {
            tile,
            credit: credit.to_wire(),
        })
        .collect();
    let counters = WorkerCounters {
        domain_loads: store.loads,
        domains_warm: store.warm,
        domain_load_seconds: store.load_seconds,
        evictions: store.evictions,
        rays_sent: report.rays_sent,
        rays_forwarded: report.rays_forwarded,
        idle_seconds: report.idle_seconds,
        queue_peak: job.queue_peak.load(Ordering::Relaxed),
        cache_rays_not_sent: report.cache_rays_not_sent,
        cache_rays_bypassed: report.cache_rays_bypassed,
        phm_rays_not_sent: report.phm_rays_not_sent,
        cache_bytes: report.cache_bytes,
        lost_cache_hosts: std::mem::take(&mut report.lost_cache_hosts),
        traffic: (!report.traffic.is_empty()).then(|| report.traffic.to_proto()),
        cpu: Some(ProcessCpu {
            process: dray_net::cpu::process_token(),
            at_setup: job.cpu_at_setup,
            now: dray_net::cpu::process_cpu_seconds(),
        }),
    };
    crate::metrics::record_report(
        &report.traced,
        report.rays_sent,
        report.bytes,
        store.loads,
        store.load_seconds,
    );
    let request = request(shared, job, sums, credits, &report, Some(counters));
    send_report(shared, job, request).await;
}

fn request(
    shared: &Shared,
    job: &Job,
    sums: Vec<(u32, [i64; 3])>,
    credits: Vec<TileCredit>,
    r: &Report,
    counters: Option<WorkerCounters>,
) -> ReportContributionsRequest {
    let t = &r.traced;
    ReportContributionsRequest {
        worker_id: shared.id(),
        job_id: job.key.id.to_string(),
        attempt: job.key.attempt,
        sequence: job.sequence.fetch_add(1, Ordering::Relaxed) + 1,
        pixels: sums.iter().map(|(p, _)| *p).collect(),
        sums: sums.iter().flat_map(|(_, v)| *v).collect(),
        credits,
        traced: Some(RayCounts::from_kinds(*t)),
        nonfinite: r.nonfinite,
        ray_bytes_sent: r.bytes,
        failure: r.failure.clone().unwrap_or_default(),
        counters,
        unreachable_peers: r.unreachable.clone(),
    }
}

/// Send one report, retrying with the same sequence number (the coordinator applies
/// it once). False when the job is over or the coordinator cannot be reached.
async fn send_report(shared: &Shared, job: &Arc<Job>, request: ReportContributionsRequest) -> bool {
    let mut client = shared.client.clone();
    for attempt in 0..20u32 {
        if !job.is_active() {
            return false;
        }
        match client
            .report_contributions(shared.as_member(request.clone()))
            .await
        {
            Ok(r) => {
                if !r.into_inner().job_active {
                    tracing::info!(job = %job.key.id, attempt = job.key.attempt, "the coordinator says the job is over");
                    if let Some(j) = shared.jobs.release(&job.key.id, job.key.attempt) {
                        shared.forget(&j.key.id, j.key.attempt);
                    }
                    return false;
                }
                return true;
            }
            Err(s) => {
                tracing::warn!(job = %job.key.id, attempt, "report failed: {}", s.message());
                tokio::time::sleep(Duration::from_millis(50 << attempt.min(5))).await;
            }
        }
    }
    tracing::error!(job = %job.key.id, "giving up reporting to the coordinator");
    false
}

/// The job's queue lengths and resident domains, for the scheduler.
async fn report_queues(shared: &Shared, job: &Arc<Job>) {
    let mut entries: BTreeMap<u32, DomainQueue> = BTreeMap::new();
    for (d, n) in shared.queues.job_lengths(&job.key.id, job.key.attempt) {
        entries.insert(
            d,
            DomainQueue {
                domain: d,
                rays_queued: n as u64,
                resident: false,
                resident_bytes: job.source.estimate_bytes(d),
            },
        );
    }
    for (d, bytes) in shared.store.resident(&job.key) {
        let e = entries.entry(d).or_insert(DomainQueue {
            domain: d,
            ..DomainQueue::default()
        });
        e.resident = true;
        e.resident_bytes = bytes;
    }
    let mut client = shared.client.clone();
    let r = client
        .report_queues(shared.as_member(ReportQueuesRequest {
            worker_id: shared.id(),
            job_id: job.key.id.to_string(),
            routing_version: job.routes().version,
            queues: entries.into_values().collect(),
            memory_used_bytes: shared.memory_used(),
            attempt: job.key.attempt,
        }))
        .await;
    if let Ok(r) = r
        && r.get_ref().routing_version > job.routes().version
    {
        tracing::debug!(job = %job.key.id, "a newer routing table is on its way");
    }
}
