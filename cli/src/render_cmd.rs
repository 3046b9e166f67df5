//! `dray render`: load, analyse, build, trace, write — all in this process.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use dray_coordinator::validate::{DEFAULT_LAYOUT, Limits};
use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::film::Film;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::render::{self, RenderOutput};
use dray_core::scene::Scene;
use dray_core::trace::Trace;
use dray_scene::partition::LayoutSpec;

use crate::options::{apply_effects, parse_vec3};
use crate::summary::{
    DisplaySummary, PhmSummary, RayCacheSummary, SceneFacts, Scheduling, Summary, print_summary,
};

/// Most in-process worker actors: each has its own threads, queues and loopback server.
pub const MAX_WORKERS: usize = 64;
/// Most tracing threads: far more than any machine's cores (threads beyond the cores
/// only add stacks and scheduling), and few enough that asking cannot exhaust memory or
/// the process's thread limit.
pub const MAX_THREADS: usize = 4096;

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub job: crate::job_flags::JobFlags,
    #[command(flatten, next_help_heading = crate::help_heading::PERFORMANCE)]
    pub otlp: crate::telemetry::OtlpArgs,
    /// Worker threads (0 = all cores; at most 4096).
    #[arg(
        long,
        default_value_t = 0,
        value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=MAX_THREADS as u64)
    )]
    #[arg(help_heading = crate::help_heading::PERFORMANCE)]
    pub threads: usize,
    /// Write run statistics as JSON.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub stats: Option<PathBuf>,
    /// Cut the scene into N spatial domains, each with its own BVH, and walk every ray
    /// through them (the image is bit-identical to 1 domain). Default: 1 domain on one
    /// worker; with several workers, the coordinator's choice (4 per worker).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub domains: Option<u32>,
    /// Domain layout for --domains: a uniform grid or a kd split balanced by triangle count.
    #[arg(long, default_value = DEFAULT_LAYOUT)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub layout: String,
    /// Worker actors to run the job on, all in this process with a coordinator, talking
    /// over loopback gRPC exactly as `dray cluster` does. 0: the reference renderer,
    /// which traces tiles straight through the domains with no actors (the image is the
    /// same, bit for bit).
    #[arg(long, default_value_t = 1)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub workers: usize,
    /// Memory of each in-process worker for resident domains and queued rays, in bytes
    /// (suffixes K, M, G, T are powers of 1024: 512M, 2GiB; 0 = unlimited), as
    /// `dray worker --memory-budget`. No effect with --workers 0.
    #[arg(long, default_value = "0", value_name = "BYTES", value_parser = crate::bytes::parse_bytes)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub memory_budget: u64,
    /// Milliseconds added to every domain load of the in-process workers, to emulate slow
    /// shared storage. No effect with --workers 0.
    #[arg(long, default_value_t = 0, value_name = "MS")]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub load_delay_ms: u64,
    /// Record the job's traffic to FILE as JSON lines: every worker's traced steps
    /// (rays in, CPU, rays out per domain, bytes), domain loads and forwards, after a
    /// line with the job's wall time, settings and totals (docs/caches.md "The trace's
    /// schema"), for `benches/sim/replay.py`. Needs --workers 1 or more.
    #[arg(long, value_name = "FILE")]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub trace_out: Option<PathBuf>,
}

/// The checks clap cannot make, shared with `dray sweep` (which runs them on every
/// setting before rendering any).
pub fn check_args(a: &RenderArgs) -> Result<IntegratorKind> {
    // The coordinator's default limits (a job on workers is checked against them too).
    const MAX_SIDE: u32 = Limits::MAX_SIDE;
    if a.job.anim.frames.is_some() {
        bail!("--frames renders one image per frame: `dray render --frames`, not here");
    }
    if a.job.width == 0 || a.job.height == 0 || a.job.width > MAX_SIDE || a.job.height > MAX_SIDE {
        bail!(
            "image size {}x{} is out of range (1..={MAX_SIDE} per side)",
            a.job.width,
            a.job.height
        );
    }
    if a.job.spp == 0 || a.job.spp > Limits::MAX_SPP {
        bail!(
            "--spp {} is out of range (1..={})",
            a.job.spp,
            Limits::MAX_SPP
        );
    }
    if a.job.max_depth == 0 || a.job.max_depth > Limits::MAX_DEPTH {
        bail!(
            "--max-depth {} is out of range (1..={})",
            a.job.max_depth,
            Limits::MAX_DEPTH
        );
    }
    if let Some(d) = a.domains
        && (d == 0 || d > Limits::MAX_DOMAINS)
    {
        bail!(
            "--domains {d} is out of range (1..={})",
            Limits::MAX_DOMAINS
        );
    }
    if a.workers > MAX_WORKERS {
        bail!(
            "--workers {} is out of range (0..={MAX_WORKERS})",
            a.workers
        );
    }
    a.job.check_schedule()?;
    if a.job.ray_cache.is_some() && a.workers == 0 {
        bail!(
            "--ray-cache needs worker actors: --workers 0 is the exact reference renderer, \
             which has no cache hosts"
        );
    }
    if a.trace_out.is_some() && a.workers == 0 {
        bail!(
            "--trace-out records the workers' traffic: --workers 0 is the reference renderer, \
             which has none"
        );
    }
    if a.job.phm.is_some() && a.workers == 0 {
        bail!(
            "--phm needs worker actors: --workers 0 is the exact reference renderer, which \
             has no cache hosts"
        );
    }
    if a.job.ao_samples == 0 || a.job.ao_samples > Limits::MAX_AO_SAMPLES {
        bail!(
            "--ao-samples {} is out of range (1..={})",
            a.job.ao_samples,
            Limits::MAX_AO_SAMPLES
        );
    }
    if let Some(d) = a.job.ao_distance
        && (d.is_nan() || d <= 0.0)
    {
        bail!("--ao-distance must be positive, got {d}");
    }
    IntegratorKind::from_name(&a.job.integrator).with_context(|| {
        format!(
            "unknown integrator {:?} (expected {})",
            a.job.integrator,
            IntegratorKind::choices()
        )
    })
}

/// Pick the camera named by `--camera`, the scene's first, or one framing the bounds.
pub fn choose_camera(scene: &Scene, which: Option<&str>, aspect: f32) -> Result<Camera> {
    scene
        .choose_camera(which, scene.bounds(), aspect)
        .map_err(|e| anyhow::anyhow!("camera {e}"))
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
    let set = dray_scene::partition::resident::domain_set(scene, &spec)
        .context("cannot cut the scene into domains")?;
    Ok(Box::new(set))
}

/// A finished render before anything is written or printed: what `dray render` writes,
/// and what `dray sweep` compares against its exact render.
pub struct Rendered {
    pub film: Film,
    /// The run's statistics; `wall_time_s` is as of the end of the render (`dray render`
    /// sets it again once the files are written, from `start`).
    pub summary: Summary,
    pub start: Instant,
}

/// Check that `path` can be written as a file with one of `extensions` (lower case,
/// without the dot), without writing it: its folder exists, it is not a folder, and it
/// can be opened for writing (a file made only to find out is removed again). Called
/// before rendering, so a typo costs nothing instead of the whole render.
pub fn check_output(flag: &str, path: &Path, extensions: &[&str]) -> Result<()> {
    let shown = path.display();
    if !extensions.is_empty() {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if !ext.as_deref().is_some_and(|e| extensions.contains(&e)) {
            let expected: Vec<String> = extensions.iter().map(|e| format!(".{e}")).collect();
            // The one mix-up worth naming: the PNG flag given an EXR name.
            let hint = if flag == "--output" && ext.as_deref() == Some("exr") {
                format!("; linear OpenEXR is written with --exr {shown}")
            } else {
                String::new()
            };
            bail!(
                "{flag} {shown}: unsupported file type (expected {}){hint}",
                expected.join(" or ")
            );
        }
    }
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    match std::fs::metadata(folder) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => bail!("{flag} {shown}: {} is not a folder", folder.display()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("{flag} {shown}: folder {} does not exist", folder.display())
        }
        Err(e) => bail!(
            "{flag} {shown}: cannot use folder {}: {e}",
            folder.display()
        ),
    }
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.is_dir() => bail!("{flag} {shown}: is a folder"),
        Ok(_) => {
            // Exists: open for writing without truncating, so nothing changes yet.
            std::fs::OpenOptions::new()
                .write(true)
                .open(path)
                .map(drop)
                .map_err(|e| anyhow::anyhow!("{flag} {shown}: cannot be written: {e}"))?;
            if !std::fs::metadata(path).is_ok_and(|m| m.is_file()) {
                bail!("{flag} {shown}: is not a regular file");
            }
        }
        Err(_) => {
            std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(path)
                .map(drop)
                .map_err(|e| anyhow::anyhow!("{flag} {shown}: cannot be written: {e}"))?;
            let _ = std::fs::remove_file(path);
        }
    }
    Ok(())
}

pub fn run(a: RenderArgs) -> Result<()> {
    crate::threads::limit_build_threads(a.threads);
    if a.job.anim.frames.is_some() {
        return crate::frames::render_frames(a);
    }
    run_one(&a)
}

/// `dray render` of one image.
pub fn run_one(a: &RenderArgs) -> Result<()> {
    run_one_with(a, None)
}

/// [`run_one`], with the scene and in-process actors of `warm` when given: the frames
/// of `--frames` (`crate::frames`).
pub fn run_one_with(a: &RenderArgs, warm: Option<&mut crate::warm::WarmProcess>) -> Result<()> {
    a.job.check_passes()?;
    // Every file this run will write is checked before the render, not after it.
    check_output("--output", &a.job.output, &["png", "jpg", "jpeg"])?;
    if let Some(p) = &a.job.exr {
        check_output("--exr", p, &["exr"])?;
    }
    a.job.check_aovs()?;
    if let Some(p) = &a.stats {
        check_output("--stats", p, &[])?;
    }
    if let Some(p) = &a.trace_out {
        check_output("--trace-out", p, &[])?;
    }
    // The bar appears with the first progress report, once the scene is loaded.
    let bar = std::sync::OnceLock::new();
    let show = !a.job.quiet && std::io::IsTerminal::is_terminal(&std::io::stderr());
    let progress = |done: usize, total: usize| {
        if show {
            let b = bar.get_or_init(|| {
                let b = indicatif::ProgressBar::new(total as u64);
                b.set_style(
                    indicatif::ProgressStyle::with_template(
                        "{spinner} rendering [{bar:40}] {pos}/{len} tiles {elapsed} eta {eta}",
                    )
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                    .progress_chars("=> "),
                );
                b
            });
            b.set_length(total as u64);
            b.set_position(done as u64);
        }
    };
    let rendered = render_with(a, &progress, warm);
    if let Some(b) = bar.get() {
        b.finish_and_clear();
    }
    let Rendered {
        film,
        mut summary,
        start,
    } = rendered?;
    let display = a.job.display();
    let stops = display
        .write(&film, a.job.spp, &a.job.output)
        .with_context(|| format!("cannot write {}", a.job.output.display()))?;
    summary.display = Some(DisplaySummary::of(display, stops));
    if let Some(p) = &a.job.exr {
        film.write_exr(p, a.job.spp)
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    summary.wall_time_s = start.elapsed().as_secs_f64();
    if let Some(p) = &a.stats {
        let json = serde_json::to_string_pretty(&summary).context("cannot encode statistics")?;
        std::fs::write(p, json + "\n").with_context(|| format!("cannot write {}", p.display()))?;
    }
    if !a.job.quiet {
        print_summary(&summary);
    }
    Ok(())
}

/// The scene of `a`, moved by `--translate` when given.
fn load_scene(a: &RenderArgs, translate: Option<glam::Vec3>) -> Result<Scene> {
    let time = a.job.anim.moment();
    let mut scene = dray_scene::load_at(&a.job.scene, time.as_ref())
        .with_context(|| format!("cannot load scene {:?}", a.job.scene))?;
    if let Some(t) = translate {
        dray_scene::translate::translate(&mut scene, t)
            .with_context(|| format!("--translate {}", a.job.translate.as_deref().unwrap_or("")))?;
    }
    Ok(scene)
}

/// The lights as the coordinator resolves them from the spec, so `--workers 0` and
/// workers render the same lights; an environment map is read from here (no scene
/// root; with workers the in-process coordinator reads it again for them, docs/lights.md).
fn resolve_lighting(a: &RenderArgs) -> Result<dray_core::lighting::Lighting> {
    let mut lighting_spec = a.job.lights.lighting_spec();
    let mut sun_color = a.job.lights.sun_color_spec();
    let flag_err =
        |e: tonic::Status| anyhow::anyhow!("{}", crate::light_flags::flag_error(e.message()));
    let mut lighting =
        dray_coordinator::lighting::check_lighting(&mut lighting_spec, &mut sun_color)
            .map_err(flag_err)?;
    if let Some(e) = lighting_spec.as_ref().and_then(|l| l.env_map.as_ref()) {
        let loaded = dray_coordinator::lighting::load_env_map(
            e,
            std::path::Path::new(&e.path),
            "lighting.env_map.path",
        )
        .map_err(flag_err)?;
        lighting.env_map = Some(loaded.map);
    }
    lighting.samples = a.job.lights.light_samples();
    Ok(lighting)
}

/// The camera `--camera` picks (or the default), then the view flags, checked and
/// resolved by the coordinator's code as a submitted job's.
fn resolve_camera(
    a: &RenderArgs,
    scene: &Scene,
    translate: Option<glam::Vec3>,
) -> Result<dray_core::camera::Camera> {
    let aspect = a.job.width as f32 / a.job.height as f32;
    let camera = choose_camera(scene, a.job.camera.as_deref(), aspect)?;
    let Some(v) = a.job.view.spec()? else {
        return Ok(camera);
    };
    let status = |e: tonic::Status| anyhow::anyhow!("{}", e.message());
    dray_coordinator::view::check(&v, a.job.camera.as_deref()).map_err(status)?;
    let offset = translate.unwrap_or(glam::Vec3::ZERO);
    Ok(
        dray_coordinator::view::resolve(&v, &camera, scene.bounds(), aspect, offset)
            .map_err(status)?
            .1,
    )
}

/// A finished render, from the actors or from this thread pool, with what the summary
/// says of how it ran.
struct Traced {
    out: RenderOutput,
    domains: u32,
    scheduling: Scheduling,
    walls: (Option<RayCacheSummary>, Option<PhmSummary>),
    /// BVH build time; with workers, their domain loads (read plus build) summed.
    build_time: std::time::Duration,
    build_summed: bool,
}

/// `a` on in-process actors (the ones `warm` keeps, when given). The scene goes to the
/// in-process coordinator as it is (translated), so it is not loaded twice; the
/// coordinator repeats the checks `render_with` made.
fn trace_on_actors(
    a: &RenderArgs,
    scene: Scene,
    progress: &(dyn Fn(usize, usize) + Sync),
    warm: Option<&mut crate::warm::WarmProcess>,
) -> Result<Traced> {
    let _span = tracing::info_span!("job", scene = %a.job.scene, workers = a.workers).entered();
    let r = match warm {
        Some(_) if a.trace_out.is_some() => {
            bail!("--trace-out records one render: `dray render`, not `dray sweep`")
        }
        Some(w) => w.actors(a)?.render(a, scene, progress)?,
        None => crate::embedded::render_on_actors(a, a.workers, scene, progress)?,
    };
    Ok(Traced {
        domains: r.stats.domains,
        scheduling: Scheduling::of(&r.stats),
        walls: (RayCacheSummary::of(&r.stats), PhmSummary::of(&r.stats)),
        build_time: std::time::Duration::from_secs_f64(r.stats.domain_load_seconds.max(0.0)),
        build_summed: true,
        out: r.out,
    })
}

/// `a` on the reference renderer, in this process's thread pool.
fn trace_here(
    a: &RenderArgs,
    scene: &Scene,
    camera: dray_core::camera::Camera,
    settings: &RenderSettings,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Traced> {
    let _span = tracing::info_span!("job", scene = %a.job.scene).entered();
    let domains = a.domains.unwrap_or(1);
    let build_start = Instant::now();
    let geometry = build_geometry(scene, domains, &a.layout)?;
    let build_time = build_start.elapsed();
    let integrator = Integrator::new(scene, camera, settings.clone());
    let passes = a.job.local_passes().ranges(a.job.spp);
    let out = render::render_passes(
        &integrator,
        geometry.as_ref(),
        a.threads,
        &passes,
        a.job.noise.noise_threshold,
        &|done, total| progress(done, total),
        &|_, _| {},
        &std::sync::atomic::AtomicBool::new(false),
    )
    .context("cannot start the thread pool")?;
    Ok(Traced {
        out,
        domains,
        scheduling: Scheduling::none(),
        walls: (None, None),
        build_time,
        build_summed: false,
    })
}

/// Render `a` as `dray render` does (reference renderer or in-process actors), writing
/// nothing and printing nothing; `progress` gets (tiles done, total). The scene and the
/// in-process actors come from `warm` when given (and are left there for the next
/// render): `dray sweep`'s and `dray render --frames`'s renders in one process.
pub fn render_with(
    a: &RenderArgs,
    progress: &(dyn Fn(usize, usize) + Sync),
    mut warm: Option<&mut crate::warm::WarmProcess>,
) -> Result<Rendered> {
    let start = Instant::now();
    let integrator_kind = check_args(a)?;
    let env_arg = a
        .job
        .env
        .as_deref()
        .map(|s| parse_vec3("--env", s))
        .transpose()?;
    let translate = a
        .job
        .translate
        .as_deref()
        .map(|s| parse_vec3("--translate", s))
        .transpose()?;

    a.job.anim.check()?;
    let scene = match warm.as_deref_mut() {
        Some(w) => w.scene(a, || load_scene(a, translate))?,
        None => load_scene(a, translate)?,
    };
    for w in &scene.stats.warnings {
        tracing::warn!("{w}");
    }
    let load_time = start.elapsed();
    let lighting = resolve_lighting(a)?;
    let environment =
        env_arg.unwrap_or_else(|| dray_scene::effects::default_environment_lit(&scene, &lighting));
    let mut effects = dray_scene::effects::analyze_lit(&scene, environment, &lighting);
    if let Some(spec) = &a.job.effects {
        effects = apply_effects(effects, spec)?;
    }
    let camera = resolve_camera(a, &scene, translate)?;
    let settings = RenderSettings {
        width: a.job.width,
        height: a.job.height,
        spp: a.job.spp,
        integrator: integrator_kind,
        max_depth: a.job.max_depth,
        seed: a.job.seed,
        environment,
        effects,
        ao_samples: a.job.ao_samples,
        ao_distance: a.job.ao_distance.unwrap_or(f32::INFINITY),
        lighting,
        clamp_indirect: a.job.noise.clamp_indirect,
        aovs: a.job.noise.aovs()?,
    };
    let facts = SceneFacts::of(&scene);
    let traced = if a.workers > 0 {
        trace_on_actors(a, scene, progress, warm)?
    } else {
        trace_here(a, &scene, camera, &settings, progress)?
    };
    let out = traced.out;
    let threads = if a.threads == 0 {
        rayon::current_num_threads()
    } else {
        a.threads
    };
    let mut summary = Summary::new(
        &a.job.scene,
        &facts,
        &settings,
        &out,
        threads,
        load_time,
        traced.build_time,
        start.elapsed(),
    );
    summary.domains = traced.domains;
    summary.build_summed_over_workers = traced.build_summed;
    // Counted by the tile renderer, and by the workers (JobStats.clamped).
    summary.clamped_contributions = Some(out.film.clamped);
    // Counted by the tile renderer, and by the workers (JobStats.clamped_indirect).
    summary.clamped_indirect = out.film.clamped_indirect;
    // Read from the film's per-pixel counts, the same bits on every configuration.
    let saved = dray_core::adaptive::Saved::of(&out.film, a.job.spp);
    (summary.tiles_stopped, summary.samples_saved) = (saved.tiles_stopped, saved.samples_saved);
    summary.scheduling = traced.scheduling;
    (summary.ray_cache, summary.phm) = traced.walls;
    Ok(Rendered {
        film: out.film,
        summary,
        start,
    })
}
