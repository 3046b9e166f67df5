//! `dray render`: load, analyse, build, trace, write — all in this process.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::render::{self, RenderOutput};
use dray_core::scene::Scene;
use dray_core::trace::{DomainSet, Trace};
use dray_scene::partition::{DomainLayout, LayoutSpec, partition_in_memory};

use crate::options::{apply_effects, parse_vec3};
use crate::summary::{Summary, print_summary};

/// Largest image side accepted.
pub const MAX_SIDE: u32 = 16384;
/// Largest samples per pixel accepted.
pub const MAX_SPP: u32 = 1 << 16;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// A .gltf, .glb, .ply or .obj file, or a procedural scene: cornell, cornell:mirror,
    /// cornell:glass, spheres:N, soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>.
    pub scene: String,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// raycast | whitted | path | ao
    #[arg(long, default_value = "path")]
    pub integrator: String,
    /// Maximum number of surface interactions along a path.
    #[arg(long, default_value_t = 5)]
    pub max_depth: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// A camera of the scene, by name or index (default: the first, or one framing the bounds).
    #[arg(long)]
    pub camera: Option<String>,
    /// Constant environment radiance "R,G,B" (default: black with lights or emitters, 1.0 otherwise).
    #[arg(long)]
    pub env: Option<String>,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    #[arg(long, default_value = "dray.png")]
    pub output: PathBuf,
    /// Also write linear radiance as OpenEXR.
    #[arg(long)]
    pub exr: Option<PathBuf>,
    /// Write run statistics as JSON.
    #[arg(long)]
    pub stats: Option<PathBuf>,
    /// Force effects on or off, e.g. "+specular,-transmission" (names: direct_light,
    /// specular, transmission, emission, textures, alpha, environment).
    #[arg(long, allow_hyphen_values = true)]
    pub effects: Option<String>,
    /// Rays per hit for the ao integrator.
    #[arg(long, default_value_t = 16)]
    pub ao_samples: u32,
    /// Occlusion distance for the ao integrator (default: unlimited).
    #[arg(long)]
    pub ao_distance: Option<f32>,
    /// Exposure in stops for the PNG (radiance is scaled by 2^EV; the EXR stays linear).
    /// Scenes in photometric units, such as a 68000-lux sun, want about -16.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub exposure: f32,
    /// Move the whole scene by "X,Y,Z" before rendering (tests precision far from the origin).
    #[arg(long)]
    pub translate: Option<String>,
    /// Cut the scene into N spatial domains, each with its own BVH, and walk every ray
    /// through them as workers will (the image is bit-identical to 1 domain).
    #[arg(long, default_value_t = 1)]
    pub domains: u32,
    /// Domain layout for --domains: a uniform grid or a kd split balanced by triangle count.
    #[arg(long, default_value = "kd")]
    pub layout: String,
    /// No progress bar or summary table.
    #[arg(long, short)]
    pub quiet: bool,
}

fn check_args(a: &RenderArgs) -> Result<IntegratorKind> {
    if a.width == 0 || a.height == 0 || a.width > MAX_SIDE || a.height > MAX_SIDE {
        bail!(
            "image size {}x{} is out of range (1..={MAX_SIDE} per side)",
            a.width,
            a.height
        );
    }
    if a.spp == 0 || a.spp > MAX_SPP {
        bail!("--spp {} is out of range (1..={MAX_SPP})", a.spp);
    }
    if a.max_depth == 0 || a.max_depth > 1024 {
        bail!("--max-depth {} is out of range (1..=1024)", a.max_depth);
    }
    if !a.exposure.is_finite() || a.exposure.abs() > 64.0 {
        bail!("--exposure {} is out of range (-64..=64 stops)", a.exposure);
    }
    if a.domains == 0 || a.domains > 65536 {
        bail!("--domains {} is out of range (1..=65536)", a.domains);
    }
    if a.ao_samples == 0 || a.ao_samples > 4096 {
        bail!("--ao-samples {} is out of range (1..=4096)", a.ao_samples);
    }
    if let Some(d) = a.ao_distance
        && (d.is_nan() || d <= 0.0)
    {
        bail!("--ao-distance must be positive, got {d}");
    }
    IntegratorKind::from_name(&a.integrator).with_context(|| {
        format!(
            "unknown integrator {:?} (expected raycast, whitted, path or ao)",
            a.integrator
        )
    })
}

/// Pick the camera named by `--camera`, the scene's first, or one framing the bounds.
pub fn choose_camera(scene: &Scene, which: Option<&str>, aspect: f32) -> Result<Camera> {
    let cam = match which {
        Some(w) => {
            let by_index = w.parse::<usize>().ok().and_then(|i| scene.cameras.get(i));
            let found = by_index.or_else(|| scene.cameras.iter().find(|c| c.name == w));
            match found {
                Some(c) => c.clone(),
                None => {
                    let names: Vec<String> = scene
                        .cameras
                        .iter()
                        .enumerate()
                        .map(|(i, c)| format!("{i}:{}", c.name))
                        .collect();
                    bail!(
                        "camera {w:?} not found in the scene (cameras: {})",
                        if names.is_empty() {
                            "none".to_string()
                        } else {
                            names.join(", ")
                        }
                    );
                }
            }
        }
        None => match scene.cameras.first() {
            Some(c) => c.clone(),
            None => {
                let (lo, hi) = scene.bounds();
                Camera::framing(lo, hi, aspect)
            }
        },
    };
    if !cam.is_valid() {
        bail!(
            "camera {:?} is malformed (non-finite or degenerate transform or projection)",
            cam.name
        );
    }
    Ok(cam)
}

/// One BVH over the scene, or with `domains > 1` a BVH per spatial domain walked front to
/// back (the embedded stand-in for workers owning domains).
fn build_geometry(scene: &Scene, domains: u32, layout: &str) -> Result<Box<dyn Trace>> {
    if domains <= 1 {
        return Ok(Box::new(Accel::build(&scene.mesh)));
    }
    let spec = match layout {
        "grid" => LayoutSpec::GridCount(domains),
        "kd" => LayoutSpec::Kd(domains),
        other => bail!("unknown --layout {other:?} (expected grid or kd)"),
    };
    let layout = DomainLayout::for_source(scene, &spec).context("cannot lay out the domains")?;
    let parts = partition_in_memory(scene, &layout).context("cannot partition the scene")?;
    let mut accels: Vec<Option<Accel>> = (0..layout.domain_count()).map(|_| None).collect();
    for part in &parts {
        if let Some(slot) = accels.get_mut(part.domain as usize) {
            *slot = Some(Accel::build_with_ids(&part.mesh, Some(&part.global_ids)));
        }
    }
    Ok(Box::new(DomainSet {
        tree: layout.to_domain_tree(),
        accels: accels
            .into_iter()
            .map(|a| a.unwrap_or_else(|| Accel::build(&Default::default())))
            .collect(),
        pad: layout.epsilon(),
    }))
}

pub fn run(a: RenderArgs) -> Result<()> {
    let start = Instant::now();
    let integrator_kind = check_args(&a)?;
    let env_arg = a
        .env
        .as_deref()
        .map(|s| parse_vec3("--env", s))
        .transpose()?;
    let translate = a
        .translate
        .as_deref()
        .map(|s| parse_vec3("--translate", s))
        .transpose()?;

    let mut scene =
        dray_scene::load(&a.scene).with_context(|| format!("cannot load scene {:?}", a.scene))?;
    if let Some(t) = translate {
        scene.translate(t);
    }
    for w in &scene.stats.warnings {
        tracing::warn!("{w}");
    }
    let load_time = start.elapsed();
    let environment = env_arg.unwrap_or_else(|| dray_scene::effects::default_environment(&scene));
    let mut effects = dray_scene::effects::analyze(&scene, environment);
    if let Some(spec) = &a.effects {
        effects = apply_effects(effects, spec)?;
    }
    let aspect = a.width as f32 / a.height as f32;
    let camera = choose_camera(&scene, a.camera.as_deref(), aspect)?;

    let build_start = Instant::now();
    let geometry = build_geometry(&scene, a.domains, &a.layout)?;
    let build_time = build_start.elapsed();

    let settings = RenderSettings {
        width: a.width,
        height: a.height,
        spp: a.spp,
        integrator: integrator_kind,
        max_depth: a.max_depth,
        seed: a.seed,
        environment,
        effects,
        ao_samples: a.ao_samples,
        ao_distance: a.ao_distance.unwrap_or(f32::INFINITY),
    };
    let integrator = Integrator::new(&scene, camera, settings);
    let bar = (!a.quiet && std::io::IsTerminal::is_terminal(&std::io::stderr())).then(|| {
        let b = indicatif::ProgressBar::new(render::tiles(a.width, a.height).len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} rendering [{bar:40}] {pos}/{len} tiles {elapsed} eta {eta}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        b
    });
    let progress = |done: usize, _total: usize| {
        if let Some(b) = &bar {
            b.set_position(done as u64);
        }
    };
    let out: RenderOutput = {
        let _span = tracing::info_span!("job", scene = %a.scene).entered();
        render::render(&integrator, geometry.as_ref(), a.threads, &progress)
            .context("cannot start the thread pool")?
    };
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    out.film
        .write_png(&a.output, a.spp, 2f32.powf(a.exposure))
        .with_context(|| format!("cannot write {}", a.output.display()))?;
    if let Some(p) = &a.exr {
        out.film
            .write_exr(p, a.spp)
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    let threads = if a.threads == 0 {
        rayon::current_num_threads()
    } else {
        a.threads
    };
    let mut summary = Summary::new(
        &a.scene,
        &scene,
        &integrator.settings,
        &out,
        threads,
        load_time,
        build_time,
        start.elapsed(),
    );
    summary.domains = a.domains;
    if let Some(p) = &a.stats {
        let json = serde_json::to_string_pretty(&summary).context("cannot encode statistics")?;
        std::fs::write(p, json + "\n").with_context(|| format!("cannot write {}", p.display()))?;
    }
    if !a.quiet {
        print_summary(&summary);
    }
    Ok(())
}
