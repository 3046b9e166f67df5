//! What a job's actor is told: typed events posted by the RPC handlers, the heartbeat
//! reaper and the registry. Events that an RPC must answer carry a one-shot reply; the
//! others are fire and forget. Timers (round pacing, the stall timeout) and the tasks
//! that open and close cache walls are the actor's own, not events.

use dray_proto::v1::{ReportContributionsRequest, ReportQueuesRequest, RoutingTable};
use tokio::sync::{mpsc, oneshot};
use tonic::Status;

use super::report::ReportOutcome;
use super::view::JobView;
use crate::membership::{LostWorker, WorkerRecord};
use crate::scheduler::state::JobSchedule;

/// How the registry reaches one job's actor: its mailbox, and what the PackageService
/// may serve for the job. Here, beside the events, so the actor (which removes its own
/// handle when its job ends) and the registry both name it without naming each other.
#[derive(Clone, Debug)]
pub struct JobHandle {
    pub(super) tx: mpsc::Sender<JobEvent>,
    /// The job's package path and checksum (fixed for its life): what the
    /// PackageService may serve for it.
    pub(super) package: (String, String),
    /// The job's environment map file (`JobSetup.env_map`), which the PackageService
    /// serves with the package.
    pub(super) env_map: Option<dray_proto::v1::EnvMapFile>,
}

/// One message to a job's actor.
#[derive(Debug)]
pub enum JobEvent {
    /// A ReportContributions call: credit, pixels and counters.
    Report(
        Box<ReportContributionsRequest>,
        oneshot::Sender<Result<ReportReply, Status>>,
    ),
    /// A ReportQueues call; answered with the job's routing version, or None when the
    /// job is not running at the report's attempt (or the worker is not one of its
    /// workers). A round may follow.
    QueueReport(ReportQueuesRequest, oneshot::Sender<Option<u64>>),
    /// A worker stopped heartbeating (or its peers could not reach it) and was dropped:
    /// a job it was part of starts its next attempt on the survivors, or fails.
    WorkerLost(LostWorker),
    /// A worker registered: a running job whose schedule takes joiners takes it on
    /// (`RunningJob::takes_joiners`).
    WorkerJoined(WorkerRecord),
    /// CancelJob (the job's record is marked CANCELLED already): release the workers.
    Cancel(oneshot::Sender<()>),
    /// The current routing table (GetRoutingTable).
    Routing(oneshot::Sender<RoutingTable>),
    /// A copy of the scheduling state (tests, benchmarks, introspection).
    Schedule(oneshot::Sender<JobSchedule>),
    /// Domains, owners, queues and rays per worker, for ListWorkers.
    View(oneshot::Sender<JobView>),
}

/// The answer to a [`JobEvent::Report`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReportReply {
    /// What happened to the report.
    pub outcome: ReportOutcome,
    /// Peers the reporting worker could not send rays to that are workers of the job
    /// (at most 16): the caller drops them from the cluster, as after missed heartbeats.
    pub unreachable: Vec<String>,
}

impl ReportReply {
    /// The answer for a job that is not running.
    pub fn inactive() -> ReportReply {
        ReportReply {
            outcome: ReportOutcome::Inactive,
            unreachable: Vec::new(),
        }
    }
}
