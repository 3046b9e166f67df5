//! Reports to the coordinator, as messages: one `ReportContributions` per report a
//! job's actor ([`crate::job_actor`]) sends, in chunks that stay inside gRPC's
//! message limit, retried with the same sequence number on failure; and the job's queue
//! lengths and resident domains, the scheduler's input.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use dray_proto::v1::{
    DomainQueue, ProcessCpu, RayCounts, ReportContributionsRequest, ReportQueuesRequest,
    TileCredit, WorkerCounters,
};

use dray_core::aov::AOV_WORDS;

use crate::domain_store::StoreCounters;
use crate::jobs::{Job, Report};
use crate::member::Member;
use crate::workload::Workload;

/// How often accumulated results are reported.
pub const REPORT_INTERVAL: Duration = Duration::from_millis(10);
/// Contributions per ReportContributions message: about 2 MB, half gRPC's default limit.
const MAX_SUMS_PER_REPORT: usize = 64 * 1024;
/// AOV entries per message (eight words each, against a contribution's three): about
/// the same 2 MB.
const MAX_AOVS_PER_REPORT: usize = 24 * 1024;
/// How often queue lengths are reported (the scheduler's input).
pub const QUEUE_REPORT_INTERVAL: Duration = Duration::from_millis(100);

/// How a report's messages went.
pub(crate) enum Sent {
    /// Every message was taken.
    Delivered,
    /// The coordinator says the job is over here.
    JobOver,
    /// The coordinator could not be reached (or the job was released meanwhile).
    GaveUp,
}

/// The messages of `report`, numbered on from `sequence`, with `store`'s counters and
/// the job's `queue_peak`. Contributions go in chunks that stay well inside gRPC's
/// message limit; the credit travels in the last one, so no credit reaches the
/// coordinator before the contributions of the same rays.
pub(crate) fn requests(
    member: &Member,
    job: &Job,
    mut report: Report,
    store: StoreCounters,
    queue_peak: u64,
    sequence: &mut u64,
) -> Vec<ReportContributionsRequest> {
    let mut out = Vec::new();
    let mut sums = report.sums.drain();
    while sums.len() > MAX_SUMS_PER_REPORT {
        let rest = sums.split_off(MAX_SUMS_PER_REPORT);
        let chunk = std::mem::replace(&mut sums, rest);
        *sequence += 1;
        out.push(request(
            member,
            job,
            *sequence,
            (chunk, Vec::new()),
            Vec::new(),
            &Report::default(),
            None,
        ));
    }
    // AOV sums travel like the contributions: before the credit of the same rays.
    let mut aovs = report.aovs.drain();
    while aovs.len() > MAX_AOVS_PER_REPORT {
        let rest = aovs.split_off(MAX_AOVS_PER_REPORT);
        let chunk = std::mem::replace(&mut aovs, rest);
        *sequence += 1;
        out.push(request(
            member,
            job,
            *sequence,
            (Vec::new(), chunk),
            Vec::new(),
            &Report::default(),
            None,
        ));
    }
    if job.tracer.pass_tags().is_some() {
        // A job tracing passes ahead: what its actor lets go is of the job's pass (or
        // earlier); the coordinator counts credit by tile.
        for c in &mut report.credits {
            c.0 = crate::tracer::pass_tag::split_tile_key(c.0).1;
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
        queue_peak,
        cache_rays_not_sent: report.cache_rays_not_sent,
        cache_rays_bypassed: report.cache_rays_bypassed,
        phm_rays_not_sent: report.phm_rays_not_sent,
        cache_bytes: report.cache_bytes,
        lost_cache_hosts: std::mem::take(&mut report.lost_cache_hosts),
        traffic: (!report.traffic.is_empty())
            .then(|| std::mem::take(&mut report.traffic).to_proto()),
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
    *sequence += 1;
    out.push(request(
        member,
        job,
        *sequence,
        (sums, aovs),
        credits,
        &report,
        Some(counters),
    ));
    out
}

/// Sums of `N` words by sum key, as a report's chunk carries them.
type Entries<const N: usize> = Vec<(u64, [i64; N])>;

/// Send `requests` in order, each retried with its sequence number (the coordinator
/// applies it once); stops at the first that cannot be sent.
pub(crate) async fn send_all(
    member: &Member,
    job: &Job,
    requests: Vec<ReportContributionsRequest>,
) -> Sent {
    for r in requests {
        match send_report(member, job, r).await {
            Sent::Delivered => {}
            other => return other,
        }
    }
    Sent::Delivered
}

fn request(
    member: &Member,
    job: &Job,
    sequence: u64,
    (sums, aovs): (Entries<3>, Entries<AOV_WORDS>),
    credits: Vec<TileCredit>,
    r: &Report,
    counters: Option<WorkerCounters>,
) -> ReportContributionsRequest {
    let t = &r.traced;
    ReportContributionsRequest {
        worker_id: member.id(),
        job_id: job.key.id.to_string(),
        attempt: job.key.attempt,
        sequence,
        // The pixel is a sum key's low half (`tracer::pass_tag`).
        pixels: sums.iter().map(|(k, _)| *k as u32).collect(),
        sums: sums.iter().flat_map(|(_, v)| *v).collect(),
        aov_pixels: aovs.iter().map(|(k, _)| *k as u32).collect(),
        aov_sums: aovs.iter().flat_map(|(_, v)| *v).collect(),
        credits,
        traced: Some(RayCounts::from_kinds(*t)),
        nonfinite: r.nonfinite,
        clamped: r.clamped,
        clamped_indirect: r.clamped_indirect,
        ray_bytes_sent: r.bytes,
        failure: r.failure.clone().unwrap_or_default(),
        counters,
        unreachable_peers: r.unreachable.clone(),
    }
}

/// Send one report, retrying with the same sequence number (the coordinator applies
/// it once).
async fn send_report(member: &Member, job: &Job, request: ReportContributionsRequest) -> Sent {
    let mut client = member.client();
    for attempt in 0..20u32 {
        if !job.is_active() {
            return Sent::GaveUp;
        }
        match client
            .report_contributions(member.as_member(request.clone()))
            .await
        {
            Ok(r) if !r.get_ref().job_active => return Sent::JobOver,
            Ok(_) => return Sent::Delivered,
            Err(s) => {
                tracing::warn!(job = %job.key.id, attempt, "report failed: {}", s.message());
                tokio::time::sleep(Duration::from_millis(50 << attempt.min(5))).await;
            }
        }
    }
    tracing::error!(job = %job.key.id, "giving up reporting to the coordinator");
    Sent::GaveUp
}

/// Tell the coordinator that attempt `attempt` of `job_id` fails here, under `sequence`.
pub(crate) async fn report_failure(
    member: &Member,
    job_id: &str,
    attempt: u32,
    sequence: u64,
    message: String,
) {
    let mut client = member.client();
    let _ = client
        .report_contributions(member.as_member(ReportContributionsRequest {
            worker_id: member.id(),
            job_id: job_id.to_string(),
            sequence,
            failure: message,
            attempt,
            ..Default::default()
        }))
        .await;
}

/// The job's queue lengths and resident domains, for the scheduler.
pub(crate) async fn report_queues(member: Arc<Member>, workload: Arc<Workload>, job: Arc<Job>) {
    let mut entries: BTreeMap<u32, DomainQueue> = BTreeMap::new();
    for (d, n) in workload.queues().job_lengths(&job.key.id, job.key.attempt) {
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
    for (d, bytes) in workload.store().resident(&job.key) {
        let e = entries.entry(d).or_insert(DomainQueue {
            domain: d,
            ..DomainQueue::default()
        });
        e.resident = true;
        e.resident_bytes = bytes;
    }
    let mut client = member.client();
    let r = client
        .report_queues(member.as_member(ReportQueuesRequest {
            worker_id: member.id(),
            job_id: job.key.id.to_string(),
            routing_version: job.routes().version,
            queues: entries.into_values().collect(),
            memory_used_bytes: workload.memory_used(),
            attempt: job.key.attempt,
        }))
        .await;
    if let Ok(r) = r
        && r.get_ref().routing_version > job.routes().version
    {
        tracing::debug!(job = %job.key.id, "a newer routing table is on its way");
    }
}
