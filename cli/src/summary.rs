//! The end-of-run summary: a table on the terminal and the `--stats` JSON.

use std::collections::BTreeMap;
use std::time::Duration;

use dray_core::integrator::{RayKind, RenderSettings};
use dray_core::render::{RayCounts, RenderOutput};
use dray_core::scene::Scene;
use dray_proto::v1::JobStats;
use serde::Serialize;

#[derive(Serialize, Debug)]
pub struct Summary {
    pub scene: String,
    pub triangles: usize,
    pub degenerate_triangles_dropped: u64,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub integrator: &'static str,
    pub max_depth: u32,
    pub seed: u64,
    pub environment: [f32; 3],
    pub effects: Vec<&'static str>,
    pub rays: BTreeMap<&'static str, u64>,
    pub rays_total: u64,
    pub threads: usize,
    /// Spatial domains the scene was cut into (1 = one BVH).
    pub domains: u32,
    pub load_time_s: f64,
    pub build_time_s: f64,
    pub render_time_s: f64,
    pub wall_time_s: f64,
    pub mrays_per_s: f64,
    pub nonfinite_contributions: u64,
    pub warnings: Vec<String>,
    /// How the job was scheduled on workers, and what that cost.
    #[serde(flatten)]
    pub scheduling: Scheduling,
}

/// The scheduling metrics of a job on workers (GetJob's `JobStats`), as the `--stats`
/// JSON of `dray render` and `dray submit` spells them.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Scheduling {
    /// "image-plane", "domain" or "dynamic"; "none" when no worker took part (the
    /// reference renderer, or a coordinator rendering in its own process).
    pub schedule: String,
    /// Domain loads by workers (a domain loaded twice counts twice).
    pub domain_loads: u64,
    /// Seconds workers spent loading domains, summed over workers.
    pub domain_load_seconds: f64,
    /// Domains evicted to stay within workers' memory budgets.
    pub evictions: u64,
    /// Rays sent from one worker to another (each hop counts).
    pub rays_exchanged: u64,
    /// Rays a worker forwarded because it no longer owned their domain.
    pub rays_forwarded: u64,
    /// Ray batches' payload bytes sent between actors.
    pub ray_bytes_sent: u64,
    /// Most rays queued at one worker at any moment.
    pub queue_peak: u64,
    /// Rounds of the scheduler.
    pub scheduler_rounds: u32,
    /// The routing table's last version (1: never changed).
    pub routing_version: u64,
    /// Tiles traced again after a worker was lost.
    pub tiles_retraced: u32,
    /// Per worker of the job.
    pub workers: Vec<WorkerSummary>,
    /// Workers that took part (0: no actors).
    #[serde(skip)]
    pub worker_count: u32,
}

/// One worker's share of a job.
#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct WorkerSummary {
    pub worker_id: String,
    pub domain_loads: u64,
    pub domain_load_seconds: f64,
    pub evictions: u64,
    pub idle_seconds: f64,
    pub queue_peak: u64,
    pub rays_traced: u64,
}

impl Scheduling {
    /// No workers, no scheduling: every count zero.
    pub fn none() -> Scheduling {
        Scheduling {
            schedule: "none".into(),
            domain_loads: 0,
            domain_load_seconds: 0.0,
            evictions: 0,
            rays_exchanged: 0,
            rays_forwarded: 0,
            ray_bytes_sent: 0,
            queue_peak: 0,
            scheduler_rounds: 0,
            routing_version: 0,
            tiles_retraced: 0,
            workers: Vec::new(),
            worker_count: 0,
        }
    }

    /// The metrics of a job from its statistics.
    pub fn of(s: &JobStats) -> Scheduling {
        let schedule = if s.workers == 0 || s.schedule.is_empty() {
            "none".to_string()
        } else {
            s.schedule.clone()
        };
        Scheduling {
            schedule,
            domain_loads: s.domain_loads,
            domain_load_seconds: s.domain_load_seconds,
            evictions: s.evictions,
            rays_exchanged: s.rays_exchanged,
            rays_forwarded: s.rays_forwarded,
            ray_bytes_sent: s.ray_bytes_sent,
            queue_peak: s.queue_peak,
            scheduler_rounds: s.scheduler_rounds,
            routing_version: s.routing_version,
            tiles_retraced: s.tiles_retried,
            workers: s
                .workers_detail
                .iter()
                .map(|w| WorkerSummary {
                    worker_id: w.worker_id.clone(),
                    domain_loads: w.domain_loads,
                    domain_load_seconds: w.domain_load_seconds,
                    evictions: w.evictions,
                    idle_seconds: w.idle_seconds,
                    queue_peak: w.queue_peak,
                    rays_traced: w.rays_traced,
                })
                .collect(),
            worker_count: s.workers,
        }
    }

    /// One line for the human summary, when the job ran on workers.
    pub fn line(&self) -> Option<String> {
        (self.worker_count > 0).then(|| {
            format!(
                "{} on {} worker{}: domain loads {} ({:.3} s), evictions {}, rays exchanged {}, \
                 tiles re-traced {}",
                self.schedule,
                self.worker_count,
                if self.worker_count == 1 { "" } else { "s" },
                self.domain_loads,
                self.domain_load_seconds,
                self.evictions,
                self.rays_exchanged,
                self.tiles_retraced
            )
        })
    }
}

/// Rays by kind from the protocol's counts.
pub fn ray_counts(r: &dray_proto::v1::RayCounts) -> RayCounts {
    let mut rays = RayCounts::default();
    rays.0[RayKind::Camera as usize] = r.camera;
    rays.0[RayKind::Shadow as usize] = r.shadow;
    rays.0[RayKind::Reflection as usize] = r.reflection;
    rays.0[RayKind::Refraction as usize] = r.refraction;
    rays.0[RayKind::Diffuse as usize] = r.diffuse;
    rays.0[RayKind::AmbientOcclusion as usize] = r.ambient_occlusion;
    rays
}

/// Rays by kind under the names the `--stats` JSON uses.
pub fn rays_by_name(rays: &RayCounts) -> BTreeMap<&'static str, u64> {
    RayKind::ALL
        .iter()
        .map(|k| (k.name(), rays.get(*k)))
        .collect()
}

/// What the summary says about the scene, taken before the scene is handed to the
/// in-process coordinator.
#[derive(Clone, Debug)]
pub struct SceneFacts {
    pub triangles: usize,
    pub degenerate_triangles: u64,
    pub warnings: Vec<String>,
}

impl SceneFacts {
    pub fn of(scene: &Scene) -> SceneFacts {
        SceneFacts {
            triangles: scene.mesh.triangle_count(),
            degenerate_triangles: scene.stats.degenerate_triangles,
            warnings: scene.stats.warnings.clone(),
        }
    }
}

impl Summary {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        spec: &str,
        scene: &SceneFacts,
        s: &RenderSettings,
        out: &RenderOutput,
        threads: usize,
        load: Duration,
        build: Duration,
        wall: Duration,
    ) -> Summary {
        let rays = rays_by_name(&out.rays);
        let secs = out.render_time.as_secs_f64();
        Summary {
            scene: spec.to_string(),
            triangles: scene.triangles,
            degenerate_triangles_dropped: scene.degenerate_triangles,
            width: s.width,
            height: s.height,
            spp: s.spp,
            integrator: s.integrator.name(),
            max_depth: s.max_depth,
            seed: s.seed,
            environment: s.environment.to_array(),
            effects: s.effects.names(),
            rays,
            rays_total: out.rays.total(),
            threads,
            domains: 1,
            load_time_s: load.as_secs_f64(),
            build_time_s: build.as_secs_f64(),
            render_time_s: secs,
            wall_time_s: wall.as_secs_f64(),
            mrays_per_s: if secs > 0.0 {
                out.rays.total() as f64 / secs / 1e6
            } else {
                0.0
            },
            nonfinite_contributions: out.film.nonfinite,
            warnings: scene.warnings.clone(),
            scheduling: Scheduling::none(),
        }
    }
}

pub fn print_summary(s: &Summary) {
    let effects = if s.effects.is_empty() {
        "none".to_string()
    } else {
        s.effects.join(", ")
    };
    eprintln!("scene        {}", s.scene);
    eprintln!(
        "triangles    {} ({} degenerate dropped)",
        s.triangles, s.degenerate_triangles_dropped
    );
    eprintln!(
        "image        {}x{}, {} spp, {} (max depth {})",
        s.width, s.height, s.spp, s.integrator, s.max_depth
    );
    eprintln!("effects      {effects}");
    eprintln!("rays         {} total", s.rays_total);
    for (k, n) in &s.rays {
        if *n > 0 {
            eprintln!("  {k:<18} {n}");
        }
    }
    eprintln!(
        "time         load {:.3}s, bvh {:.3}s, render {:.3}s, wall {:.3}s",
        s.load_time_s, s.build_time_s, s.render_time_s, s.wall_time_s
    );
    eprintln!(
        "throughput   {:.2} Mrays/s on {} threads",
        s.mrays_per_s, s.threads
    );
    if let Some(line) = s.scheduling.line() {
        eprintln!("schedule     {line}");
    }
    if s.nonfinite_contributions > 0 {
        eprintln!(
            "non-finite   {} contributions dropped",
            s.nonfinite_contributions
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::WorkerJobStats;

    #[test]
    fn scheduling_from_job_stats() {
        let stats = JobStats {
            workers: 2,
            schedule: "domain".into(),
            domain_loads: 9,
            domain_load_seconds: 0.5,
            evictions: 1,
            rays_exchanged: 40,
            tiles_retried: 3,
            routing_version: 2,
            workers_detail: vec![WorkerJobStats {
                worker_id: "w1".into(),
                domain_loads: 9,
                ..WorkerJobStats::default()
            }],
            ..JobStats::default()
        };
        let s = Scheduling::of(&stats);
        assert_eq!(s.schedule, "domain");
        assert_eq!(s.tiles_retraced, 3);
        assert_eq!(s.workers[0].worker_id, "w1");
        let json = serde_json::to_value(&s).expect("json");
        assert_eq!(json["tiles_retraced"], 3);
        assert_eq!(json["workers"][0]["domain_loads"], 9);
        assert!(json.get("worker_count").is_none());
        assert_eq!(
            s.line().as_deref(),
            Some(
                "domain on 2 workers: domain loads 9 (0.500 s), evictions 1, rays exchanged 40, \
                 tiles re-traced 3"
            )
        );
        // A job the coordinator rendered itself, and the reference renderer.
        let alone = Scheduling::of(&JobStats::default());
        assert_eq!(alone.schedule, "none");
        assert_eq!(alone.line(), None);
        assert_eq!(Scheduling::none(), alone);
    }
}
