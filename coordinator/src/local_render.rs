//! Jobs rendered in this process: while no worker is registered, an accepted job is
//! traced here with the single-process path of `dray render` (`dray_core::render` over
//! one BVH, or a `DomainSet` when `domains > 1`), one job at a time, by priority then
//! submission order: a job waits QUEUED (or PAUSED) in the deal queue
//! ([`crate::priority`]), builds its geometry (PREPARING), then traces tiles on a
//! blocking thread (RUNNING). Cancellation is cooperative: a flag the render loop checks
//! before each tile. The image is the same, bit for bit, as `dray render` with the same
//! settings.
//!
//! The job's record ([`crate::job::JobRecord`], handed here by the submission path) is
//! where it publishes its progress, as a job on workers publishes from its actor; the
//! record does not know which of the two runs it.

use std::sync::Arc;

use dray_core::bvh::Accel;
use dray_core::film::Film;
use dray_core::integrator::Integrator;
use dray_core::render;
use dray_core::scene::Scene;
use dray_core::trace::Trace;
use dray_proto::v1::{JobEventKind, JobState, RayCounts};
use dray_scene::partition::LayoutSpec;

use crate::job::JobRecord;
use crate::priority::DealQueue;
use crate::validate::Prepared;

/// The one in-process render slot and the jobs waiting for it.
pub struct LocalRenderer {
    /// Jobs waiting for the slot, by priority.
    queue: Arc<DealQueue>,
    /// Tracing threads (0 = all cores).
    threads: usize,
}

impl LocalRenderer {
    /// One slot, rendering with `threads` threads (0 = all cores).
    pub fn new(threads: usize) -> LocalRenderer {
        LocalRenderer {
            queue: Arc::new(DealQueue::new("process", 1)),
            threads,
        }
    }

    /// The queue of jobs waiting to render in this process.
    pub(crate) fn queue(&self) -> &Arc<DealQueue> {
        &self.queue
    }

    /// Start the in-process render of `entry`, a job already in the table whose scene
    /// has been prepared. Must be called within a tokio runtime.
    pub fn start(&self, entry: &Arc<JobRecord>, prepared: Prepared) {
        let (queue, threads, job) = (self.queue.clone(), self.threads, entry.clone());
        // Waiting for the slot is QUEUED (a scene file was loaded PREPARING).
        let waiting = queue.join(job.entry());
        if job.state() == JobState::Preparing {
            job.set_state(JobState::Queued);
        }
        tokio::spawn(async move {
            let Some(_slot) = waiting.turn().await else {
                return;
            };
            if job.is_cancelled() {
                return;
            }
            job.set_state(JobState::Preparing);
            let worker = job.clone();
            let joined = tokio::task::spawn_blocking(move || run(&worker, prepared, threads)).await;
            if let Err(e) = joined {
                job.finish(JobState::Failed, format!("render task died: {e}"), None);
            }
        });
    }
}

/// Build the geometry, trace the image, and record the outcome. Blocking.
fn run(job: &JobRecord, p: Prepared, threads: usize) {
    let _span = tracing::info_span!("job", id = %job.id, scene = %job.spec.scene).entered();
    let geometry = match build_geometry(&p.scene, job.spec.domains, &job.spec.layout) {
        Ok(g) => g,
        Err(e) => return job.finish(JobState::Failed, e, None),
    };
    job.update_stats(|s| {
        s.triangles = p.scene.mesh.triangle_count() as u64;
        s.domains = job.spec.domains;
        s.effects = p
            .settings
            .effects
            .names()
            .into_iter()
            .map(String::from)
            .collect();
    });
    job.set_state(JobState::Running);
    let integrator = Integrator::new(&p.scene, p.camera, p.settings);
    let progress = |done: usize, _total: usize| {
        job.raise_tiles_done(done as u32);
    };
    let passes = job.passes.ranges();
    let on_pass = |film: &Film, k: usize| {
        // The last pass's image is the job's final one (`finish`).
        if k + 1 < passes.len() {
            job.publish_pass(Arc::new(film.clone()), k as u32 + 1);
            job.note(
                JobEventKind::PassFinished,
                format!("pass {} of {} finished", k + 1, passes.len()),
            );
            job.set_tiles_done(0);
        }
    };
    let out = render::render_passes(
        &integrator,
        geometry.as_ref(),
        threads,
        passes,
        job.spec.noise_threshold,
        &progress,
        &on_pass,
        job.cancel_flag(),
    );
    match out {
        Err(e) => job.finish(
            JobState::Failed,
            format!("cannot start the thread pool: {e}"),
            None,
        ),
        Ok(_) if job.is_cancelled() => job.finish(JobState::Cancelled, String::new(), None),
        Ok(out) => {
            job.update_stats(|s| {
                s.rays = Some(RayCounts::from_kinds(out.rays.0));
                s.nonfinite = out.film.nonfinite;
                s.clamped = out.film.clamped;
                s.clamped_indirect = out.film.clamped_indirect;
                let saved = dray_core::adaptive::Saved::of(&out.film, job.spec.spp);
                s.tiles_stopped = saved.tiles_stopped;
                s.samples_saved = saved.samples_saved;
            });
            job.finish(JobState::Succeeded, String::new(), Some(out.film));
        }
    }
}

/// One BVH over the scene, or with `domains > 1` a BVH per spatial domain walked front to
/// back, as `dray render --domains` does (the image is the same bits either way).
pub fn build_geometry(scene: &Scene, domains: u32, layout: &str) -> Result<Box<dyn Trace>, String> {
    if domains <= 1 {
        return Ok(Box::new(Accel::build(&scene.mesh)));
    }
    let spec = match layout {
        "grid" => LayoutSpec::GridCount(domains),
        _ => LayoutSpec::Kd(domains),
    };
    let set = dray_scene::partition::resident::domain_set(scene, &spec)
        .map_err(|e| format!("cannot cut the scene into domains: {e}"))?;
    Ok(Box::new(set))
}
