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

use std::collections::BTreeSet;
use std::time::Instant;

use dray_core::aov::AOV_WORDS;
use dray_core::credit::Credit;
use dray_proto::v1::{RayCounts, ReportContributionsRequest};
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

/// Sequences of one (worker, job) already applied: everything up to `upto`, plus the
/// ones above it that arrived out of order. Stays small when reports arrive in order.
#[derive(Default, Debug)]
pub struct SeqWindow {
    upto: u64,
    above: BTreeSet<u64>,
}

impl SeqWindow {
    /// Whether sequence `s` was applied.
    pub fn contains(&self, s: u64) -> bool {
        s <= self.upto || self.above.contains(&s)
    }

    /// Record sequence `s` as applied.
    pub fn insert(&mut self, s: u64) {
        if s <= self.upto {
            return;
        }
        self.above.insert(s);
        while self.above.remove(&(self.upto + 1)) {
            self.upto += 1;
        }
    }
}

/// Whether `r` may be applied to `job`: `Ok(None)` when it may, `Ok(Some(outcome))` when
/// it is answered without being applied (stale attempt, duplicate sequence), an error
/// naming the field when it is malformed or from a worker that is not the job's.
pub fn check(
    job: &RunningJob,
    r: &ReportContributionsRequest,
) -> Result<Option<ReportOutcome>, Status> {
    if job.entry.is_terminal() {
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
            crate::validate::bounded(&r.worker_id),
            r.job_id
        )));
    }
    if r.sequence == 0 {
        return Err(Status::invalid_argument(
            "sequence: must start at 1 (0 is the unset value)",
        ));
    }
    if job
        .seen
        .get(&r.worker_id)
        .is_some_and(|s| s.contains(r.sequence))
    {
        return Ok(Some(ReportOutcome::Duplicate));
    }
    if r.sums.len() != 3 * r.pixels.len() {
        return Err(Status::invalid_argument(format!(
            "sums: {} values for {} pixels (three per pixel expected)",
            r.sums.len(),
            r.pixels.len()
        )));
    }
    let npix = u64::from(job.film.width) * u64::from(job.film.height);
    if let Some(p) = r.pixels.iter().find(|&&p| u64::from(p) >= npix) {
        return Err(Status::invalid_argument(format!(
            "pixels: {p} is outside the {}x{} image",
            job.film.width, job.film.height
        )));
    }
    // Contributions are non-negative (`dray_core::film::to_fixed`) and every sum of them
    // saturates, which is what makes the film's sums independent of the order reports
    // arrive in; a negative value can only come from a broken or hostile worker.
    if let Some(i) = r.sums.iter().position(|&v| v < 0) {
        return Err(Status::invalid_argument(format!(
            "sums: {} for pixel {} is negative (contributions never are)",
            r.sums[i],
            r.pixels[i / 3]
        )));
    }
    check_aovs(job, r)?;
    if let Some(c) = r
        .credits
        .iter()
        .find(|c| c.tile as usize >= job.tiles.len())
    {
        return Err(Status::invalid_argument(format!(
            "credits: tile {} does not exist (the job has {} tiles)",
            c.tile,
            job.tiles.len()
        )));
    }
    if let Some(c) = &r.counters {
        metrics::check(c).map_err(|e| Status::invalid_argument(e.to_string()))?;
    }
    Ok(None)
}

/// A report's AOV sums: only for a job that writes AOVs, eight words per pixel, every
/// pixel inside the film, and the words that cannot be negative (albedo, depth, hits)
/// not negative.
fn check_aovs(job: &RunningJob, r: &ReportContributionsRequest) -> Result<(), Status> {
    if r.aov_pixels.is_empty() && r.aov_sums.is_empty() {
        return Ok(());
    }
    if job.film.aovs.is_none() {
        return Err(Status::invalid_argument(format!(
            "aov_pixels: job {:?} writes no AOVs",
            r.job_id
        )));
    }
    if r.aov_sums.len() != AOV_WORDS * r.aov_pixels.len() {
        return Err(Status::invalid_argument(format!(
            "aov_sums: {} values for {} pixels ({AOV_WORDS} per pixel expected)",
            r.aov_sums.len(),
            r.aov_pixels.len()
        )));
    }
    let npix = u64::from(job.film.width) * u64::from(job.film.height);
    if let Some(p) = r.aov_pixels.iter().find(|&&p| u64::from(p) >= npix) {
        return Err(Status::invalid_argument(format!(
            "aov_pixels: {p} is outside the {}x{} image",
            job.film.width, job.film.height
        )));
    }
    for (i, v) in r.aov_sums.chunks_exact(AOV_WORDS).enumerate() {
        if [0, 1, 2, 6, 7].iter().any(|&w| v[w] < 0) {
            return Err(Status::invalid_argument(format!(
                "aov_sums: pixel {}'s albedo, depth or hit count is negative",
                r.aov_pixels[i]
            )));
        }
    }
    Ok(())
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
    job.seen
        .entry(r.worker_id.clone())
        .or_default()
        .insert(r.sequence);
    // Counted once per sequence, as everything else in it is.
    crate::traffic::add_report(&mut job.reports, r);
    if !r.failure.is_empty() {
        // Workers often name themselves already ("worker w1: ..."): say it once.
        let failure = r.failure.trim();
        let failure = failure
            .strip_prefix(&format!("worker {}: ", r.worker_id))
            .unwrap_or(failure);
        return Applied::WorkerFailed(format!("worker {} failed: {failure}", r.worker_id));
    }
    // `check` made it three sums per pixel, every pixel inside the film.
    job.film.add_fixed_run(&r.pixels, &r.sums);
    // `check_aovs` made them eight words per pixel, every pixel inside the film.
    if let Some(a) = job.film.aovs.as_mut() {
        for (&p, v) in r.aov_pixels.iter().zip(r.aov_sums.chunks_exact(AOV_WORDS)) {
            a.add_fixed(p, &std::array::from_fn(|w| v[w]));
        }
    }
    let mut overdrawn = None;
    for c in &r.credits {
        let t = c.tile as usize;
        // Credit arrives, and is kept per tile, as the wire carries it; the sums are
        // made on [`Credit`] (docs/architecture.md "Credit").
        let start = Credit::from_wire(job.tiles[t].credit);
        let back = Credit::from_wire(job.tile_back[t]);
        let credit = Credit::from_wire(c.credit);
        match back.checked_add(credit) {
            Some(b) if b <= start => {
                if !credit.is_zero() {
                    job.last_progress = Instant::now();
                }
                job.tile_back[t] = b.to_wire();
                if back != start && b == start && t < job.image_tiles {
                    job.tile_finished(t);
                }
            }
            _ => {
                overdrawn = Some((c.tile, credit));
                break;
            }
        }
    }
    if let Some(t) = &r.traced {
        let (sum, add) = (job.rays.by_kind(), t.by_kind());
        job.rays = RayCounts::from_kinds(std::array::from_fn(|k| sum[k] + add[k]));
    }
    job.nonfinite += r.nonfinite;
    job.clamped = job.clamped.saturating_add(r.clamped);
    job.clamped_indirect = job.clamped_indirect.saturating_add(r.clamped_indirect);
    job.ray_bytes_sent += r.ray_bytes_sent;
    if let Some(t) = r.counters.as_ref().and_then(|c| c.traffic.as_ref()) {
        crate::traffic::add(&mut job.traffic, t);
    }
    if let Some(c) = r.counters.as_ref().and_then(|c| c.cpu.as_ref()) {
        job.cpu.note(c);
    }
    job.cpu.note_here();
    job.metrics
        .add(&r.worker_id, r.counters.as_ref(), r.traced.as_ref());
    if let (Some(c), Some(caches)) = (&r.counters, &job.caches) {
        caches.tally.add_worker(c);
    }
    match overdrawn {
        Some((tile, credit)) => {
            let t = tile as usize;
            Applied::Overdrawn(format!(
                "credit accounting error: worker {} returned {credit} credit to tile {tile}, \
                 which already had {} of its {} back; rays were counted twice",
                r.worker_id, job.tile_back[t], job.tiles[t].credit
            ))
        }
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

    #[test]
    fn seq_window_dedupes_in_and_out_of_order() {
        let mut w = SeqWindow::default();
        assert!(!w.contains(1));
        w.insert(1);
        w.insert(3);
        assert!(w.contains(1) && w.contains(3) && !w.contains(2));
        w.insert(2);
        assert_eq!(w.upto, 3);
        assert!(w.above.is_empty());
        assert!(w.contains(2) && !w.contains(4));
    }

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
        let table = JobTable::new(1);
        let entry = table.insert(JobSpec {
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
        let sched = JobSchedule::new(&entry.id, schedule, 2, &workers);
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
            entry,
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
        assert_eq!(j.tiles_done, 1, "tile 1 has all its credit back");
        assert!(!j.all_complete());
        assert_eq!(apply(&mut j, &report("w2", 1, &[(0, 6)])), Applied::Counted);
        assert!(j.all_complete());
        assert_eq!(
            j.film.sum_fixed(1),
            [10, 12, 14],
            "two reports' sums of pixel 1"
        );
        j.clear_tile(0);
        assert_eq!(j.film.sum_fixed(1), [0, 0, 0], "cleared exactly");
        assert_eq!(j.tile_back[0], 0);
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
