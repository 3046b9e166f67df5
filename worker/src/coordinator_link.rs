//! The worker's side of `ClusterService`: connect, register, heartbeat, and act on the
//! coordinator's commands (job setups, tiles, routing tables, releases) in order.
//!
//! A worker outlives its coordinator: when the coordinator restarts (or declared this
//! worker lost after a long stall), the worker drops its jobs — they died with the
//! coordinator, or were given to others — registers again under a new id and takes the
//! next job. Only a coordinator unreachable for longer than the rejoin timeout stops it.

use std::sync::Arc;
use std::time::Duration;

use dray_net::AuthChannel;
use dray_proto::v1::{
    Assignment, HeartbeatRequest, JobSetup, RegisterWorkerResponse, WatchAssignmentsRequest,
    assignment::Command,
};

use crate::config::{NodeError, WorkerConfig};
use crate::domain_store::JobKey;
use crate::job_actor::JobActor;
use crate::jobs::{Job, JobEvent};
use crate::links::Links;
use crate::member::Member;
use crate::peer_server::PeerServer;
use crate::routing::Routes;
use crate::site::Site;
use crate::workload::Workload;

/// What the coordinator's commands act on: this worker's owners, each handed on to
/// what needs it (a job's actor gets the member, the workload and the links; planning a
/// setup the site). A plain composition: nothing below this file sees it.
pub(crate) struct Owners {
    pub member: Arc<Member>,
    pub workload: Arc<Workload>,
    pub links: Arc<Links>,
    pub site: Site,
}

/// Connect to the coordinator, retrying for `patience`: in a cluster the workers often
/// start before the coordinator listens.
pub(crate) async fn connect(
    config: &WorkerConfig,
    patience: Duration,
) -> Result<AuthChannel, NodeError> {
    let address = config.net.url(&config.coordinator);
    let endpoint = config
        .net
        .endpoint(&config.coordinator)
        .map_err(|e| NodeError::Address {
            address: config.coordinator.clone(),
            message: e.to_string(),
        })?;
    let endpoint = endpoint.connect_timeout(Duration::from_secs(2));
    let start = tokio::time::Instant::now();
    loop {
        match endpoint.connect().await {
            Ok(c) => return Ok(config.net.wrap(c)),
            Err(e) => {
                if start.elapsed() >= patience {
                    return Err(NodeError::Unreachable {
                        address,
                        seconds: patience.as_secs(),
                        message: error_chain(&e),
                    });
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

/// An error and its sources in one line (tonic's messages often repeat their source's
/// text already, so repeats are skipped).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut message = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !message.contains(&text) {
            message = format!("{message}: {text}");
        }
        source = s.source();
    }
    message
}

/// Register `site` with the coordinator once, reached at `endpoint`; the id and secret
/// are kept by `member`.
pub(crate) async fn register(
    member: &Member,
    site: &Site,
    endpoint: &str,
) -> Result<RegisterWorkerResponse, NodeError> {
    let reg = member
        .client()
        .register_worker(site.registration(endpoint))
        .await
        .map_err(|s| NodeError::Refused(s.message().to_string()))?
        .into_inner();
    member.set_member(&reg.worker_id, &reg.member_token);
    tracing::info!(worker = %reg.worker_id, name = %site.name(), %endpoint, "registered");
    Ok(reg)
}

/// Serve the coordinator: one session per registration, registering again after a
/// lost coordinator, for as long as it can be reached within `rejoin`.
pub(crate) async fn sessions(
    owners: &Owners,
    mut registration: RegisterWorkerResponse,
    endpoint: String,
    peer_server: PeerServer,
    rejoin: Duration,
) -> Result<(), NodeError> {
    loop {
        peer_server.set_worker_id(&registration.worker_id);
        peer_server.set_member_secret(&registration.member_token);
        let heartbeat = registration
            .heartbeat_interval
            .and_then(|d| Duration::try_from(d).ok())
            .unwrap_or(Duration::from_secs(1));
        let lost = tokio::select! {
            e = assignment_loop(owners) => e,
            e = heartbeat_loop(&owners.member, &owners.workload, heartbeat) => e,
        };
        tracing::warn!(worker = %owners.member.id(), "{lost}; dropping this worker's jobs and registering again");
        let workload = &owners.workload;
        for j in workload.jobs().release_all() {
            workload.forget(&j.key.id, j.key.attempt);
        }
        let start = tokio::time::Instant::now();
        registration = loop {
            match register(&owners.member, &owners.site, &endpoint).await {
                Ok(r) => break r,
                Err(e) if start.elapsed() >= rejoin => {
                    return Err(NodeError::Lost(format!(
                        "{lost}, and could not register again within {} s: {e}",
                        rejoin.as_secs()
                    )));
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(500)).await,
            }
        };
    }
}

/// Read the coordinator's commands in order until the stream fails.
async fn assignment_loop(owners: &Owners) -> NodeError {
    let (member, workload) = (&owners.member, &owners.workload);
    let stream = member
        .client()
        .watch_assignments(member.as_member(WatchAssignmentsRequest {
            worker_id: member.id(),
        }))
        .await;
    let mut stream = match stream {
        Ok(s) => s.into_inner(),
        Err(s) => return NodeError::Lost(s.message().to_string()),
    };
    loop {
        let msg = match stream.message().await {
            Ok(Some(m)) => m,
            Ok(None) => return NodeError::Lost("the assignment stream ended".into()),
            Err(s) => return NodeError::Lost(s.message().to_string()),
        };
        let Assignment { command } = msg;
        match command {
            Some(Command::Setup(setup)) => setup_job(owners, setup).await,
            Some(Command::Tiles(t)) => match workload.jobs().get(&t.job_id) {
                Some(job) => job.tell(JobEvent::Tiles(t)),
                None => tracing::warn!(job = %t.job_id, "tiles for a job this worker does not run"),
            },
            Some(Command::Routing(r)) => {
                if let Some(job) = workload.jobs().get(&r.job_id) {
                    job.tell(JobEvent::Routing(r));
                }
            }
            Some(Command::Cancel(r)) | Some(Command::Finish(r)) => {
                tracing::info!(job = %r.job_id, attempt = r.attempt, reason = %r.reason, "job released");
                if let Some(j) = workload.jobs().release(&r.job_id, r.attempt) {
                    workload.forget(&j.key.id, j.key.attempt);
                } else {
                    workload.forget(&r.job_id, r.attempt);
                }
            }
            None => {}
        }
    }
}

/// Heartbeats until the coordinator says it does not know this worker or cannot be
/// reached five times in a row.
async fn heartbeat_loop(member: &Member, workload: &Workload, every: Duration) -> NodeError {
    let mut client = member.client();
    let mut failures = 0u32;
    loop {
        tokio::time::sleep(every).await;
        let rays_queued = workload.in_flight() as u64;
        crate::metrics::record_queued(rays_queued);
        let r = client
            .heartbeat(member.as_member(HeartbeatRequest {
                worker_id: member.id(),
                memory_used_bytes: workload.memory_used(),
                rays_queued,
            }))
            .await;
        match r {
            Ok(r) if r.get_ref().reregister => {
                return NodeError::Lost(
                    "the coordinator no longer knows this worker (it restarted or declared it lost)"
                        .into(),
                );
            }
            Ok(_) => failures = 0,
            Err(s) => {
                failures += 1;
                if failures >= 5 {
                    return NodeError::Lost(s.message().to_string());
                }
            }
        }
    }
}

/// Set up a job attempt: plan it (reads the manifest; domains load on demand) and start
/// taking its rays. A newer attempt replaces an older one.
async fn setup_job(owners: &Owners, setup: JobSetup) {
    let (member, workload) = (&owners.member, &owners.workload);
    let job_id = setup.job_id.clone();
    let attempt = setup.attempt;
    if workload.jobs().is_released(&job_id, attempt) {
        return;
    }
    // Before anything is sized by the setup, and before it is planned.
    let refused = crate::setup_bounds::check_setup(&setup)
        .map_err(|e| e.to_string())
        .and_then(|()| workload.jobs().admit(&job_id));
    if let Err(e) = refused {
        let me = member.id();
        // An id beyond the bound is not kept among the released ones.
        let keep = job_id.len() <= crate::setup_bounds::MAX_ID_BYTES;
        let message = format!("worker {me}: {e}");
        report_refusal(member, workload, &job_id, attempt, message, keep).await;
        return;
    }
    let planned = owners.site.plan(&setup).await;
    let me = member.id();
    let routes = setup
        .routing
        .as_ref()
        .ok_or_else(|| "job setup has no routing table".to_string())
        .and_then(|t| Routes::new(t, &me, setup.domain_count).map_err(|e| e.to_string()));
    let (plan, routes) = match (planned, routes) {
        (Ok(p), Ok(r)) => (p, r),
        (Err(e), _) | (_, Err(e)) => {
            let message = format!("worker {me}: {e}");
            report_refusal(member, workload, &job_id, attempt, message, true).await;
            return;
        }
    };
    let key = JobKey {
        id: job_id.as_str().into(),
        attempt,
    };
    workload.store().open(&key, plan.content);
    let span = tracing::info_span!("job", id = %job_id, attempt);
    dray_net::trace::set_parent(&span, &setup.trace_context);
    let trace = owners.site.traffic_trace(&setup, &me);
    let (job, mailbox) = Job::new(key, plan.tracer, plan.source, routes);
    let job = Arc::new(
        job.with_span(span)
            .with_merges_every(plan.merge_every)
            .with_trace(trace),
    );
    // Tracing passes ahead when the coordinator asks and the tracer tags them (see
    // `plan::tracer`).
    let ahead = (setup.passes_ahead > 0 && job.tracer.pass_tags().is_some())
        .then(|| crate::jobs::ahead::Ahead::new(setup.passes_ahead, setup.pass));
    let actor = JobActor::new(
        member.clone(),
        workload.clone(),
        owners.links.clone(),
        job.clone(),
        mailbox,
        setup.routing,
        ahead,
    );
    let owned = job.routes().owned().len();
    let (started, replaced) = workload.jobs().start(job.clone(), actor.supervised());
    if let Some(old) = replaced {
        workload.forget(&old.key.id, old.key.attempt);
    }
    if started {
        tracing::info!(job = %job_id, attempt, owned, schedule = %setup.schedule, "job set up");
    }
    workload.notify();
}

/// Tell the coordinator that `job_id` fails here, and drop it; `release` keeps its id
/// among the released ones (so that its late rays are dropped).
async fn report_refusal(
    member: &Member,
    workload: &Workload,
    job_id: &str,
    attempt: u32,
    message: String,
    release: bool,
) {
    let shown: String = job_id.chars().take(64).collect();
    tracing::error!(job = %shown, "{message}");
    // Nothing was reported for the attempt before: its first sequence number.
    crate::reporter::report_failure(member, job_id, attempt, 1, message).await;
    if release {
        workload.jobs().release(job_id, attempt);
    }
    workload.forget(job_id, attempt);
}
