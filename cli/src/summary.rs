//! The end-of-run summary: a table on the terminal and the `--stats` JSON.

use std::collections::BTreeMap;
use std::time::Duration;

use dray_core::integrator::{RayKind, RenderSettings};
use dray_core::render::RenderOutput;
use dray_core::scene::Scene;
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
        let rays = RayKind::ALL
            .iter()
            .map(|k| (k.name(), out.rays.get(*k)))
            .collect();
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
    if s.nonfinite_contributions > 0 {
        eprintln!(
            "non-finite   {} contributions dropped",
            s.nonfinite_contributions
        );
    }
}
