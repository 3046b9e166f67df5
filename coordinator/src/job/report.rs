//! One ReportContributions call against a running job, in three steps each testable
//! alone: [`check`] (is it for this attempt, from a worker of the job, new, and
//! well-formed?), [`apply`] (add its pixels, credit and counters), and the transitions
//! the actor makes from what `apply` found (the coarse pass complete, the job complete,
//! credit overdrawn: see [`super::actor`]).
//!
//! A report is applied at most once per `(worker, job, attempt, sequence)`, so a worker
//! may retry a call whose answer it lost. Its own bytes are counted as it is applied
//! (`JobStats.reports`, `crate::traffic::add_report`). Everything is checked before
//! anything changes, so a malformed report leaves the job as it was (and may be sent
//! again, fixed, under the same sequence).
//!
//! **Contract for workers:** a ray's contribution must be reported in the same report as
//! the credit it returns, or an earlier one: the job succeeds (and its film is frozen)
//! the moment the last credit arrives. Sequences start at 1 for each attempt. Credit
//! beyond a tile's start means something was counted twice, which would silently
//! brighten the image, so it fails the job instead.

use dray_proto::v1::ReportContributionsRequest;
use tonic::Status;

use super::running::RunningJob;
use crate::metrics;

/// What happened to a report (for logs and tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReportOutcome {
    /// Applied; the job goes on.
    Applied,
    /// This sequence was applied before; nothing changed.
    Duplicate,
    /// Applied, and it completed the job.
    Completed,
    /// The job failed (the worker's failure, or a credit error).
    Failed,
    /// The job is not running (unknown, finished, cancelled or failed).
    Inactive,
    /// The report belongs to an attempt the job has dropped (a worker was lost since);
    /// nothing was counted and the worker should release that attempt.
    Stale,
}

impl ReportOutcome {
    /// `ReportContributionsResponse.job_active`.
    pub fn job_active(self) -> bool {
        matches!(self, ReportOutcome::Applied | ReportOutcome::Duplicate)
    }

    /// Whether the job ended with this report.
    pub fn ended(self) -> bool {
        matches!(self, ReportOutcome::Completed | ReportOutcome::Failed)
    }
}

/// Whether `r` may be applied to `job`: `Ok(None)` when it may, `Ok(Some(outcome))` when
/// it is answered without being applied (stale attempt, duplicate sequence), an error
/// naming the field when it is malformed or from a worker that is not the job's.
pub fn check(
    job: &RunningJob,
    r: &ReportContributionsRequest,
) -> Result<Option<ReportOutcome>, Status> {
    if job.record.is_terminal() {
        return Ok(Some(ReportOutcome::Inactive));
    }
    let attempt = job.sched.attempt();
    if r.attempt < attempt {
        return Ok(Some(ReportOutcome::Stale));
    }
    if r.attempt > attempt {
        return Err(Status::invalid_argument(format!(
            "attempt: {} is newer than job {:?}'s attempt {attempt}",
            r.attempt, r.job_id
        )));
    }
    if !job.sched.has_worker(&r.worker_id) {
        return Err(Status::permission_denied(format!(
            "worker_id: {} is not a worker of job {:?}",
            crate::text::bounded(&r.worker_id),
            r.job_id
        )));
    }
    if r.sequence == 0 {
        return Err(Status::invalid_argument(
            "sequence: must start at 1 (0 is the unset value)",
        ));
    }
    if job.seen.contains(&r.worker_id, r.sequence) {
        return Ok(Some(ReportOutcome::Duplicate));
    }
    job.film.check(r)?;
    job.ledger.check(&r.credits)?;
    if let Some(c) = &r.counters {
        metrics::check(c).map_err(|e| Status::invalid_argument(e.to_string()))?;
    }
    Ok(None)
}

/// What applying a report found, for the actor's transitions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Applied {
    /// The worker reported its own failure: the job fails with this message.
    WorkerFailed(String),
    /// Credit came back beyond a tile's start: the job fails with this message.
    Overdrawn(String),
    /// Counted; the job goes on (its transitions depend on its tiles).
    Counted,
}

/// Apply `r`, which [`check`] accepted, to `job`: its sequence, pixels, credit and
/// counters. A worker's failure is recorded (its sequence) and nothing else.
pub fn apply(job: &mut RunningJob, r: &ReportContributionsRequest) -> Applied {
    job.seen.insert(&r.worker_id, r.sequence);
    // Counted once per sequence, as everything else in it is.
    job.stats.count_report(r);
    if !r.failure.is_empty() {
        // Workers often name themselves already ("worker w1: ..."): say it once.
        let failure = r.failure.trim();
        let failure = failure
            .strip_prefix(&format!("worker {}: ", r.worker_id))
            .unwrap_or(failure);
        return Applied::WorkerFailed(format!("worker {} failed: {failure}", r.worker_id));
    }
    // `check` made the sums fit the film; the credits name the job's tiles.
    job.film.add(r);
    let credited = job.ledger.add(&r.credits);
    // The film holds the whole report already: a tile finished by it is final.
    for t in credited.finished {
        job.tile_finished(t);
    }
    job.stats.add(r);
    if let (Some(c), Some(caches)) = (&r.counters, &job.caches) {
        caches.tally.add_worker(c);
    }
    match credited.overdrawn {
        Some(o) => Applied::Overdrawn(format!(
            "credit accounting error: worker {} returned {} credit to tile {}, which already \
             had {} of its {} back; rays were counted twice",
            r.worker_id, o.credit, o.tile, o.back, o.start
        )),
        None => Applied::Counted,
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::job::running::JobPlan;
    use crate::jobs::JobTable;
    use crate::scheduler::Schedule;
    use crate::scheduler::state::{JobSchedule, JobWorker};
    use dray_proto::v1::{JobSetup, JobSpec, Tile, TileCredit};

    /// A 4x2 job of two 2x2 tiles (credit 10 each) on workers w1 and w2.
    fn job() -> RunningJob {
        job_of(2, 1)
    }

    /// A `2 tiles` x 2 job of `tiles` 2x2 tiles side by side (credit 10 each), with `spp`
    /// samples cut in the default (doubling) passes, on workers w1 and w2.
    pub(in crate::job) fn job_of(tiles: u32, spp: u32) -> RunningJob {
        job_with(tiles, spp, JobSetup::default())
    }

    /// [`job_of`] with `setup` as the job's JobSetup.
    pub(in crate::job) fn job_with(tiles: u32, spp: u32, setup: JobSetup) -> RunningJob {
        job_under(tiles, spp, setup, Schedule::Domain)
    }

    /// [`job_with`] under `schedule`.
    pub(in crate::job) fn job_under(
        tiles: u32,
        spp: u32,
        setup: JobSetup,
        schedule: Schedule,
    ) -> RunningJob {
        let table = JobTable::new();
        let record = table.insert(JobSpec {
            width: 2 * tiles,
            height: 2,
            spp,
            ..Default::default()
        });
        let workers = ["w1", "w2"].map(|w| JobWorker {
            endpoint: dray_proto::v1::WorkerEndpoint {
                worker_id: w.into(),
                ..Default::default()
            },
            budget: 0,
        });
        let sched = JobSchedule::new(&record.id, schedule, 2, &workers);
        let tile = |i: u32| Tile {
            index: i,
            x0: 2 * i,
            y0: 0,
            width: 2,
            height: 2,
            credit: 10,
            ..Default::default()
        };
        RunningJob::new(JobPlan {
            record,
            setup,
            sched,
            tiles: (0..tiles).map(tile).collect(),
            owned_package: None,
            caches: None,
            resume: None,
            scene: crate::scheduler::auto::SceneSize::default(),
        })
    }

    pub(in crate::job) fn report(
        worker: &str,
        seq: u64,
        credits: &[(u32, u64)],
    ) -> ReportContributionsRequest {
        ReportContributionsRequest {
            worker_id: worker.into(),
            sequence: seq,
            pixels: vec![1],
            sums: vec![5, 6, 7],
            credits: credits
                .iter()
                .map(|&(tile, credit)| TileCredit { tile, credit })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn check_rejects_strangers_bad_fields_and_answers_duplicates() {
        let mut j = job();
        assert!(
            check(&j, &report("w9", 1, &[])).is_err(),
            "not a worker of the job"
        );
        assert!(check(&j, &report("w1", 0, &[])).is_err(), "sequence 0");
        let mut bad = report("w1", 1, &[]);
        bad.sums.pop();
        assert!(check(&j, &bad).is_err(), "two sums for one pixel");
        let mut outside = report("w1", 1, &[]);
        outside.pixels = vec![8];
        assert!(check(&j, &outside).is_err(), "pixel 8 of a 4x2 image");
        let mut negative = report("w1", 1, &[]);
        negative.sums[1] = -1;
        let e = check(&j, &negative).unwrap_err();
        assert!(
            e.message().contains("pixel 1 is negative"),
            "{}",
            e.message()
        );
        assert!(
            check(&j, &report("w1", 1, &[(2, 1)])).is_err(),
            "tile 2 of 2"
        );
        let mut newer = report("w1", 1, &[]);
        newer.attempt = 1;
        assert!(
            check(&j, &newer).is_err(),
            "an attempt the job has not made"
        );
        let r = report("w1", 1, &[(0, 4)]);
        assert_eq!(check(&j, &r).unwrap(), None);
        assert_eq!(apply(&mut j, &r), Applied::Counted);
        assert_eq!(
            check(&j, &r).unwrap(),
            Some(ReportOutcome::Duplicate),
            "the same sequence again"
        );
        assert_eq!(
            check(&j, &report("w2", 1, &[])).unwrap(),
            None,
            "w2's own sequence"
        );
    }

    #[test]
    fn apply_adds_pixels_and_credit_and_completes_tiles_exactly() {
        let mut j = job();
        assert_eq!(
            apply(&mut j, &report("w1", 1, &[(0, 4), (1, 10)])),
            Applied::Counted
        );
        assert_eq!(j.ledger.done(), 1, "tile 1 has all its credit back");
        assert!(!j.all_complete());
        assert_eq!(apply(&mut j, &report("w2", 1, &[(0, 6)])), Applied::Counted);
        assert!(j.all_complete());
        assert_eq!(
            j.film.film().sum_fixed(1),
            [10, 12, 14],
            "two reports' sums of pixel 1"
        );
        j.clear_tile(0);
        assert_eq!(j.film.film().sum_fixed(1), [0, 0, 0], "cleared exactly");
        assert!(!j.ledger.complete(0));
    }

    #[test]
    fn apply_fails_overdrawn_credit_and_names_worker_failures_once() {
        let mut j = job();
        match apply(&mut j, &report("w1", 1, &[(0, 11)])) {
            Applied::Overdrawn(m) => assert!(m.contains("tile 0"), "{m}"),
            other => panic!("expected overdrawn credit, got {other:?}"),
        }
        let mut failed = report("w2", 1, &[]);
        failed.failure = "worker w2: out of memory".into();
        assert_eq!(
            apply(&mut j, &failed),
            Applied::WorkerFailed("worker w2 failed: out of memory".into())
        );
    }
}
