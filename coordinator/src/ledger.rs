//! The ledger: credit accounting and image assembly for jobs running on workers.
//!
//! Every tile starts with a fixed credit (DESIGN.md, "Counting: credit"); workers hand
//! credit back with the contributions of terminated rays. A tile is complete when all of
//! its credit is back, and a job when all its tiles are. Credit beyond a tile's start
//! means something was counted twice, which would silently brighten the image, so it
//! fails the job instead.
//!
//! Pixel sums arrive in fixed point and are added with integer arithmetic into one
//! [`Film`] per job: addition is associative, so the image does not depend on which
//! worker reported what, or in which order. A report is applied at most once per
//! `(worker, job, sequence)`, so a worker may retry a call whose answer it lost.
//!
//! Contract for workers: a ray's contribution must be reported in the same report as the
//! credit it returns, or an earlier one: the job succeeds (and its film is frozen) the
//! moment the last credit arrives.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_core::film::Film;
use dray_proto::v1::{
    Assignment, JobRelease, JobState, RayCounts, ReportContributionsRequest, ReportQueuesRequest,
    RoutingTable, assignment::Command,
};
use tonic::Status;

use crate::jobs::JobEntry;
use crate::membership::Membership;
use crate::owned_package::{OwnedPackage, remove_package};

/// Sequences of one (worker, job) already applied: everything up to `upto`, plus the
/// ones above it that arrived out of order. Stays small when reports arrive in order.
#[derive(Default, Debug)]
struct SeqWindow {
    upto: u64,
    above: BTreeSet<u64>,
}

impl SeqWindow {
    fn contains(&self, s: u64) -> bool {
        s <= self.upto || self.above.contains(&s)
    }

    fn insert(&mut self, s: u64) {
        if s <= self.upto {
            return;
        }
        self.above.insert(s);
        while self.above.remove(&(self.upto + 1)) {
            self.upto += 1;
        }
    }
}

/// A job running on workers.
pub struct DistJob {
    /// The public job record (state, progress, stats, film when done).
    pub entry: Arc<JobEntry>,
    /// Workers of the job, ordered as in the routing table.
    pub workers: Vec<String>,
    /// Current routing table.
    pub routing: RoutingTable,
    /// Package directory to delete when the job is released (None for a package the
    /// user supplied).
    pub owned_package: Option<OwnedPackage>,
    tile_start: Vec<u64>,
    tile_back: Vec<u64>,
    tiles_done: u32,
    film: Film,
    seen: HashMap<String, SeqWindow>,
    rays: RayCounts,
    nonfinite: u64,
    ray_bytes_sent: u64,
    /// Latest queue report per worker (input for a future dynamic scheduler).
    queues: HashMap<String, ReportQueuesRequest>,
}

impl DistJob {
    /// A job whose `tiles` tiles each start with `tile_credit`, on an image of
    /// `width` x `height`.
    pub fn new(
        entry: Arc<JobEntry>,
        routing: RoutingTable,
        tiles: usize,
        tile_credit: u64,
        owned_package: Option<OwnedPackage>,
    ) -> DistJob {
        let (w, h) = (entry.spec.width, entry.spec.height);
        DistJob {
            workers: routing
                .workers
                .iter()
                .map(|w| w.worker_id.clone())
                .collect(),
            entry,
            routing,
            owned_package,
            tile_start: vec![tile_credit; tiles],
            tile_back: vec![0; tiles],
            tiles_done: 0,
            film: Film::new(w, h),
            seen: HashMap::new(),
            rays: RayCounts::default(),
            nonfinite: 0,
            ray_bytes_sent: 0,
            queues: HashMap::new(),
        }
    }
}

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
}

impl ReportOutcome {
    /// `ReportContributionsResponse.job_active`.
    pub fn job_active(self) -> bool {
        matches!(self, ReportOutcome::Applied | ReportOutcome::Duplicate)
    }
}

/// All jobs running on workers.
pub struct Ledger {
    jobs: Mutex<HashMap<String, DistJob>>,
    membership: Arc<Membership>,
}

/// How a job leaves the ledger.
enum Release {
    Finish,
    Cancel,
}

impl Ledger {
    /// No jobs; releases go out through `membership`.
    pub fn new(membership: Arc<Membership>) -> Ledger {
        Ledger {
            jobs: Mutex::new(HashMap::new()),
            membership,
        }
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<String, DistJob>> {
        self.jobs.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Start accounting `job` and, under the same lock, queue `commands` for its workers
    /// (worker id, command), so that a cancel racing with the start either sees the job
    /// or is seen by it. Fails (sending nothing) when the job was cancelled meanwhile,
    /// or names the first worker that is gone.
    pub fn start(&self, job: DistJob, commands: Vec<(String, Assignment)>) -> Result<(), String> {
        let mut g = self.lock();
        if job.entry.is_terminal() {
            return Err(format!("job {} ended before it started", job.entry.id));
        }
        if let Some(w) = job
            .workers
            .iter()
            .find(|w| self.membership.get(w).is_none())
        {
            return Err(format!(
                "worker {w} left the cluster while the job was being prepared"
            ));
        }
        for (w, a) in commands {
            if !self.membership.send(&w, a) {
                // Cannot happen while we hold the ledger lock unless the worker expired
                // between the check above and here; the job cannot run without it.
                let id = job.entry.id.clone();
                drop(g);
                self.release_workers(&job, Release::Cancel, "a worker left during setup");
                return Err(format!(
                    "worker {w} left the cluster while job {id} was being set up"
                ));
            }
        }
        job.entry.set_state(JobState::Running);
        g.insert(job.entry.id.clone(), job);
        Ok(())
    }

    /// Apply one ReportContributions call.
    pub fn report(&self, r: &ReportContributionsRequest) -> Result<ReportOutcome, Status> {
        let mut g = self.lock();
        let Some(job) = g.get_mut(&r.job_id) else {
            return Ok(ReportOutcome::Inactive);
        };
        if job.entry.is_terminal() {
            return Ok(ReportOutcome::Inactive);
        }
        if !job.workers.contains(&r.worker_id) {
            return Err(Status::permission_denied(format!(
                "worker_id: {:?} is not a worker of job {:?}",
                r.worker_id, r.job_id
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
            return Ok(ReportOutcome::Duplicate);
        }
        let _span = tracing::info_span!("job", id = %r.job_id).entered();
        // Check everything before changing anything, so a malformed report leaves the
        // ledger as it was (and may be sent again, fixed, under the same sequence).
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
        if let Some(c) = r
            .credits
            .iter()
            .find(|c| c.tile as usize >= job.tile_start.len())
        {
            return Err(Status::invalid_argument(format!(
                "credits: tile {} does not exist (the job has {} tiles)",
                c.tile,
                job.tile_start.len()
            )));
        }
        job.seen
            .entry(r.worker_id.clone())
            .or_default()
            .insert(r.sequence);
        if !r.failure.is_empty() {
            let msg = format!("worker {} failed: {}", r.worker_id, r.failure.trim());
            tracing::warn!(worker = %r.worker_id, "{msg}");
            let job = g.remove(&r.job_id);
            drop(g);
            if let Some(job) = job {
                self.fail(job, msg);
            }
            return Ok(ReportOutcome::Failed);
        }
        for (i, &p) in r.pixels.iter().enumerate() {
            let s = &r.sums[3 * i..3 * i + 3];
            job.film.add_fixed(p, [s[0], s[1], s[2]]);
        }
        let mut overdrawn = None;
        for c in &r.credits {
            let t = c.tile as usize;
            let back = job.tile_back[t].checked_add(c.credit);
            match back {
                Some(b) if b <= job.tile_start[t] => {
                    let was = job.tile_back[t] == job.tile_start[t];
                    job.tile_back[t] = b;
                    if !was && b == job.tile_start[t] {
                        job.tiles_done += 1;
                    }
                }
                _ => {
                    overdrawn = Some((c.tile, c.credit));
                    break;
                }
            }
        }
        if let Some(t) = &r.traced {
            let k = &mut job.rays;
            k.camera += t.camera;
            k.shadow += t.shadow;
            k.reflection += t.reflection;
            k.refraction += t.refraction;
            k.diffuse += t.diffuse;
            k.ambient_occlusion += t.ambient_occlusion;
        }
        job.nonfinite += r.nonfinite;
        job.ray_bytes_sent += r.ray_bytes_sent;
        job.entry.set_tiles_done(job.tiles_done);
        let (rays, nonfinite, bytes) = (job.rays, job.nonfinite, job.ray_bytes_sent);
        job.entry.update_stats(|s| {
            s.rays = Some(rays);
            s.nonfinite = nonfinite;
            s.ray_bytes_sent = bytes;
        });
        if let Some((tile, credit)) = overdrawn {
            let t = tile as usize;
            let msg = format!(
                "credit accounting error: worker {} returned {credit} credit to tile {tile}, \
                 which already had {} of its {} back; rays were counted twice",
                r.worker_id, job.tile_back[t], job.tile_start[t]
            );
            tracing::error!("{msg}");
            let job = g.remove(&r.job_id);
            drop(g);
            if let Some(job) = job {
                self.fail(job, msg);
            }
            return Ok(ReportOutcome::Failed);
        }
        if job.tiles_done as usize == job.tile_start.len() {
            let Some(job) = g.remove(&r.job_id) else {
                return Ok(ReportOutcome::Inactive);
            };
            drop(g);
            tracing::info!(tiles = job.tile_start.len(), "job complete");
            self.release_workers(&job, Release::Finish, "completed");
            job.entry.update_stats(|s| s.nonfinite = job.nonfinite);
            let mut film = job.film;
            film.nonfinite = job.nonfinite;
            job.entry
                .finish(JobState::Succeeded, String::new(), Some(film));
            remove_package(job.owned_package.as_ref());
            return Ok(ReportOutcome::Completed);
        }
        Ok(ReportOutcome::Applied)
    }

    fn fail(&self, job: DistJob, msg: String) {
        self.release_workers(&job, Release::Cancel, &msg);
        job.entry.finish(JobState::Failed, msg, None);
        remove_package(job.owned_package.as_ref());
    }

    fn release_workers(&self, job: &DistJob, how: Release, reason: &str) {
        for w in &job.workers {
            let release = JobRelease {
                job_id: job.entry.id.clone(),
                reason: reason.to_string(),
            };
            let command = match how {
                Release::Finish => Command::Finish(release),
                Release::Cancel => Command::Cancel(release),
            };
            self.membership.send(
                w,
                Assignment {
                    command: Some(command),
                },
            );
        }
    }

    /// Stop job `id` on its workers (CancelJob). False when it is not running here.
    /// The caller marks the job CANCELLED first.
    pub fn cancel(&self, id: &str) -> bool {
        let job = self.lock().remove(id);
        match job {
            Some(job) => {
                tracing::info!(job = %id, "job cancelled on its workers");
                self.release_workers(&job, Release::Cancel, "cancelled by user");
                job.entry.finish(JobState::Cancelled, String::new(), None);
                remove_package(job.owned_package.as_ref());
                true
            }
            None => false,
        }
    }

    /// A worker was dropped: fail every job it was part of, naming it. (Tracing its lost
    /// tiles again is a later issue.)
    pub fn worker_lost(&self, id: &str, endpoint: &str, silent_for: std::time::Duration) {
        let lost: Vec<DistJob> = {
            let mut g = self.lock();
            let ids: Vec<String> = g
                .iter()
                .filter(|(_, j)| j.workers.iter().any(|w| w == id))
                .map(|(k, _)| k.clone())
                .collect();
            ids.iter().filter_map(|k| g.remove(k)).collect()
        };
        for job in lost {
            let msg = format!(
                "worker {id} ({endpoint}) was lost: no heartbeat for {:.1} s; the tiles it \
                 held cannot be traced again yet",
                silent_for.as_secs_f64()
            );
            tracing::warn!(job = %job.entry.id, "{msg}");
            self.fail(job, msg);
        }
    }

    /// Store a queue report; returns the job's routing version, or None when the job is
    /// not running (or the worker is not one of its workers).
    pub fn report_queues(&self, r: ReportQueuesRequest) -> Option<u64> {
        let mut g = self.lock();
        let job = g.get_mut(&r.job_id)?;
        if !job.workers.contains(&r.worker_id) {
            return None;
        }
        let v = job.routing.version;
        job.queues.insert(r.worker_id.clone(), r);
        // Rays queued at the job's workers, as of each one's latest report: what
        // JobProgress.rays_in_flight shows (rays on the wire are not counted).
        let queued: u64 = job
            .queues
            .values()
            .flat_map(|q| &q.queues)
            .map(|d| d.rays_queued)
            .sum();
        job.entry.set_rays_in_flight(queued);
        Some(v)
    }

    /// The latest queue report of `worker` for `job`.
    pub fn queues(&self, job: &str, worker: &str) -> Option<ReportQueuesRequest> {
        self.lock().get(job)?.queues.get(worker).cloned()
    }

    /// The current routing table of `job`.
    pub fn routing(&self, job: &str) -> Option<RoutingTable> {
        self.lock().get(job).map(|j| j.routing.clone())
    }

    /// Whether `job` is running on workers.
    pub fn contains(&self, job: &str) -> bool {
        self.lock().contains_key(job)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
