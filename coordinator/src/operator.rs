//! The operator actions of RenderService (issue 42): RetryJob and RequeueJob (a new job
//! with the same spec, linked to the old one by `Job.retried_from`, each side's event log
//! naming the other), PauseJob and ResumeJob (a queued job held in the deal queue,
//! `priority`). The dashboard's buttons call these same methods (`http::api`).

use dray_proto::v1::{JobEventKind, JobState, PauseJobResponse, RetryJobRequest, RetryJobResponse};
use tonic::Status;

use crate::Coordinator;

impl Coordinator {
    /// RetryJob (`requeue` false: a FAILED or CANCELLED job only) and RequeueJob (any job
    /// not waiting in the queue; a preparing or running one is cancelled first). The new
    /// job is validated and admitted as a submission is, with the old job's spec (as
    /// accepted, defaults filled in) and `r.priority` when given.
    pub(crate) async fn retry_or_requeue(
        &self,
        r: RetryJobRequest,
        requeue: bool,
    ) -> Result<RetryJobResponse, Status> {
        let old = self.record(&r.job_id)?;
        let state = old.state();
        let call = if requeue { "RequeueJob" } else { "RetryJob" };
        match state {
            JobState::Failed | JobState::Cancelled => {}
            JobState::Succeeded if requeue => {}
            JobState::Preparing | JobState::Running if requeue => {
                old.cancel();
                self.cluster().jobs.cancel(&old.id).await;
            }
            JobState::Queued | JobState::Paused => {
                return Err(Status::failed_precondition(format!(
                    "job {:?} is {}: it is in the queue already ({call} runs a job again)",
                    old.id,
                    state.as_str_name()
                )));
            }
            _ => {
                return Err(Status::failed_precondition(format!(
                    "job {:?} is {}: RetryJob runs again a job that FAILED or was CANCELLED \
                     (RequeueJob also takes one that succeeded or is running)",
                    old.id,
                    state.as_str_name()
                )));
            }
        }
        let mut spec = old.spec.clone();
        if let Some(p) = r.priority {
            spec.priority = p;
        }
        let id = self.submit(spec, None).await?;
        let new = self.record(&id)?;
        new.set_retried_from(&old.id);
        let verb = if requeue { "requeued" } else { "retried" };
        new.note(
            JobEventKind::Retried,
            format!("{verb} from {} ({})", old.id, state.as_str_name()),
        );
        old.note(JobEventKind::Retried, format!("{verb} as {}", new.id));
        Ok(RetryJobResponse {
            job: Some(new.to_job()),
            previous: Some(old.to_job()),
        })
    }

    /// PauseJob (`paused`) and ResumeJob. Only a job waiting in a deal queue can be
    /// paused (the coordinator's own, or the cluster's under `--max-running-jobs`; without
    /// that limit jobs on workers start at once), and a started job is not held.
    pub(crate) fn hold_job(&self, id: &str, paused: bool) -> Result<PauseJobResponse, Status> {
        let job = self.record(id)?;
        let held = if paused {
            self.queues()
                .find(|q| q.is_waiting(&job.id))
                .map_or_else(|| Err(job.state()), |q| q.hold(&job, true))
        } else {
            // A job held before a restart may be waiting nowhere yet: it is resumed all
            // the same.
            job.hold(false)
        };
        if let Err(state) = held {
            let what = if paused {
                "only a QUEUED job waiting for its turn can be paused (on workers a job \
                 waits only under the coordinator's --max-running-jobs, else it starts at \
                 once; cancel or requeue a started one)"
            } else {
                "only a PAUSED job can be resumed"
            };
            return Err(Status::failed_precondition(format!(
                "job {:?} is {}: {what}",
                job.id,
                state.as_str_name()
            )));
        }
        for q in self.queues() {
            q.poke();
        }
        let (kind, msg) = if paused {
            (JobEventKind::Paused, "paused: held in the queue")
        } else {
            (JobEventKind::Resumed, "resumed: back in the queue")
        };
        job.note(kind, msg.to_string());
        Ok(PauseJobResponse {
            job: Some(job.to_job()),
        })
    }
}
