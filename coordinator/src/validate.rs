//! Job validation: a [`JobSpec`] is checked against the server's limits and scene root
//! before it is accepted. Every rejection is `INVALID_ARGUMENT` with a message that starts
//! with the offending field's name, and leaves the server as it was.
//!
//! Checks that need no scene run in [`validate`] (cheap, on the request task); checks that
//! need the loaded scene (the scene spec itself, the camera, the effect analysis) run in
//! [`prepare`], which the server calls on a blocking thread before it answers SubmitJob.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use dray_cache::bounds;
use dray_cache::settings::{CoarseSampling, WallSettings};
use dray_core::aov::AovSet;
use dray_core::camera::Camera;
use dray_core::effects::Effect;
use dray_core::integrator::{IntegratorKind, RenderSettings};
use dray_core::light_samples::LightSamples;
use dray_core::lighting::Lighting;
use dray_core::scene::{Mesh, Scene};
use dray_proto::v1::JobSpec;
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::open_package;
use glam::Vec3;
use tonic::Status;

use crate::scheduler::ScheduleRequest;

/// Limits a job must respect. The defaults are those of `dray render`.
#[derive(Clone, Debug)]
pub struct Limits {
    /// Largest image side in pixels.
    pub max_side: u32,
    /// Largest samples per pixel.
    pub max_spp: u32,
    /// Largest `max_depth`.
    pub max_depth: u32,
    /// Largest `ao_samples`.
    pub max_ao_samples: u32,
    /// Largest number of domains.
    pub max_domains: u32,
    /// Longest label, in bytes.
    pub max_label: usize,
    /// Jobs queued, preparing or running at once; more are refused.
    pub max_jobs: usize,
    /// Largest memory a job may need at the coordinator, by the estimate of
    /// [`crate::admission`]; larger jobs are refused.
    pub max_job_bytes: u64,
}

impl Limits {
    /// The default [`Limits::max_side`], and `dray render`'s: the bound workers hold
    /// jobs to ([`dray_cache::bounds`]), which also caps a configured limit.
    pub const MAX_SIDE: u32 = bounds::MAX_SIDE;
    /// The default [`Limits::max_spp`], and `dray render`'s.
    /// The film is sized for it (`dray_core::film::MAX_SPP`).
    pub const MAX_SPP: u32 = bounds::MAX_SPP;
    /// The default [`Limits::max_depth`], and `dray render`'s.
    /// Tiles' credit is sized for it (`dray_core::integrator::MAX_DEPTH`).
    pub const MAX_DEPTH: u32 = bounds::MAX_DEPTH;
    /// The default [`Limits::max_ao_samples`], and `dray render`'s.
    pub const MAX_AO_SAMPLES: u32 = bounds::MAX_AO_SAMPLES;
    /// The default [`Limits::max_domains`], and `dray render`'s.
    pub const MAX_DOMAINS: u32 = bounds::MAX_DOMAINS;
    /// The default [`Limits::max_label`].
    pub const MAX_LABEL: usize = 256;
    /// The default [`Limits::max_jobs`] (`dray coordinator --max-jobs`), within
    /// [`bounds::MAX_COORDINATOR_JOBS`].
    pub const MAX_JOBS: usize = 64;

    /// These limits, each capped by the bound the workers hold jobs to
    /// ([`dray_cache::bounds`]): a coordinator configured beyond them could otherwise
    /// admit jobs every worker refuses.
    pub fn capped(&self) -> Limits {
        Limits {
            max_side: self.max_side.min(bounds::MAX_SIDE),
            max_spp: self.max_spp.min(bounds::MAX_SPP),
            max_depth: self.max_depth.min(bounds::MAX_DEPTH),
            max_ao_samples: self.max_ao_samples.min(bounds::MAX_AO_SAMPLES),
            max_domains: self.max_domains.min(bounds::MAX_DOMAINS),
            max_jobs: self.max_jobs.min(bounds::MAX_COORDINATOR_JOBS),
            ..self.clone()
        }
    }
}

// Tiles are never larger than a worker accepts (`dray_worker::setup_bounds`).
const _: () = assert!(dray_core::tiles::TILE_SIZE <= bounds::MAX_SIDE);
const _: () = assert!(Limits::MAX_JOBS <= bounds::MAX_COORDINATOR_JOBS);

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_side: Limits::MAX_SIDE,
            max_spp: Limits::MAX_SPP,
            max_depth: Limits::MAX_DEPTH,
            max_ao_samples: Limits::MAX_AO_SAMPLES,
            max_domains: Limits::MAX_DOMAINS,
            max_label: Limits::MAX_LABEL,
            max_jobs: Limits::MAX_JOBS,
            max_job_bytes: default_max_job_bytes(),
        }
    }
}

/// Default `integrator` (as `dray render`).
pub const DEFAULT_INTEGRATOR: IntegratorKind = IntegratorKind::Path;

/// Default `max_depth` (as `dray render`).
pub const DEFAULT_MAX_DEPTH: u32 = 5;
/// Default `ao_samples` (as `dray render`).
pub const DEFAULT_AO_SAMPLES: u32 = 16;
/// Default domain layout.
pub const DEFAULT_LAYOUT: &str = "kd";

/// A spec that passed [`validate`]: the spec with defaults filled in, plus parsed values.
#[derive(Clone, Debug)]
pub struct Validated {
    /// The spec as submitted, with defaults filled in (what GetJob shows).
    pub spec: JobSpec,
    /// What to hand to `dray_scene::load`: a procedural spec, or a canonical path inside
    /// the scene root.
    pub scene_spec: String,
    /// The integrator.
    pub integrator: IntegratorKind,
    /// Effect overrides, in order.
    pub effects: Vec<(Effect, bool)>,
    /// Explicit environment radiance.
    pub env: Option<Vec3>,
    /// The lights the spec adds (`spec.lighting`, defaults filled in), without the
    /// environment map, which [`prepare`] reads.
    pub lighting: Lighting,
    /// The AOVs the job writes (`spec.aovs`).
    pub aovs: AovSet,
    /// `spec.lighting.env_map.path` resolved under the scene root (canonical).
    pub env_map_path: Option<PathBuf>,
    /// Scene offset.
    pub translate: Option<Vec3>,
    /// The scene is a scene package at this (canonical) directory.
    pub package: Option<PathBuf>,
    /// The spec left `domains` at 0: in process that means one BVH (`spec.domains` is
    /// 1); on workers the coordinator chooses the count.
    pub domains_auto: bool,
    /// The schedule asked for on workers (`spec.schedule` holds its name; `auto` is
    /// resolved when the job starts; the in-process path ignores it).
    pub schedule: ScheduleRequest,
    /// The moment of the scene's animation to load (`spec.time`, `spec.animation`).
    pub time: Option<dray_scene::animation::AnimationTime>,
}

fn bad(msg: String) -> Status {
    Status::invalid_argument(msg)
}

/// `light_samples` (`dray render --light-samples`): 1..=[`MAX_LIGHT_SAMPLES`], absent
/// meaning 1. Left absent in the spec when absent, so a job that does not ask reads as
/// it did before the field existed. The bound is core's, not a configurable limit: tiles'
/// credit is sized for it.
///
/// [`MAX_LIGHT_SAMPLES`]: dray_core::light_samples::MAX_LIGHT_SAMPLES
pub fn light_samples(n: Option<u32>) -> Result<LightSamples, Status> {
    LightSamples::from_spec(n).map_err(|e| bad(format!("light_samples: {e}")))
}

/// The default `--max-job-bytes` ([`crate::admission`]): half the machine's memory (or
/// 8 GiB when it cannot be read).
pub fn default_max_job_bytes() -> u64 {
    physical_memory().map_or(8 << 30, |m| m / 2)
}

/// Total memory from /proc/meminfo.
fn physical_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// The longest `scene` (a path or a procedural spec): Linux's PATH_MAX.
pub const MAX_SCENE_BYTES: usize = 4096;
pub use crate::text::{MAX_NAME_BYTES, as_given, bounded};

/// Refuse a text field longer than `max` bytes, without echoing it: every later error
/// may quote a field, so bounding the fields here bounds every message.
fn check_text(field: &str, v: &str, max: usize) -> Result<(), Status> {
    if v.len() > max {
        return Err(bad(format!(
            "{field}: {} bytes is longer than {max}",
            v.len()
        )));
    }
    Ok(())
}

fn check_range(field: &str, v: u32, max: u32) -> Result<(), Status> {
    if v == 0 || v > max {
        return Err(bad(format!("{field}: {v} is out of range (1..={max})")));
    }
    Ok(())
}

/// Check `spec` against `limits` and resolve its scene against `scene_root` (which must
/// be canonical). Procedural scene names are accepted as they are; a path must name an
/// existing file inside the root.
pub fn validate(spec: &JobSpec, limits: &Limits, scene_root: &Path) -> Result<Validated, Status> {
    check_texts(spec)?;
    let mut spec = spec.clone();
    let limits = &limits.capped();
    let integrator = check_sampling(&mut spec, limits)?;
    if let Some(v) = &spec.view {
        crate::view::check(v, spec.camera.as_deref())?;
    }
    if let Some(c) = &spec.camera
        && c.trim().is_empty()
    {
        return Err(bad(
            "camera: empty camera name (omit the field for the scene's first camera)".into(),
        ));
    }
    let env = env_of(&spec)?;
    let translate = translate_of(&spec)?;
    let effects = parse_effects(&spec.effects)?;
    let lighting = crate::lighting::check_lighting(&mut spec.lighting, &mut spec.sun_color)?;
    let lighting = Lighting {
        samples: light_samples(spec.light_samples)?,
        ..lighting
    };
    check_noise(&spec)?;
    let aovs = AovSet::parse(&spec.aovs).map_err(|e| bad(format!("aovs: {e}")))?;
    // In one order, so equal sets read alike in GetJob.
    spec.aovs = aovs.names();
    let env_map_path = spec
        .lighting
        .as_ref()
        .and_then(|l| l.env_map.as_ref())
        .map(|e| crate::lighting::resolve_env_map_path(&e.path, scene_root))
        .transpose()?;
    let (domains_auto, schedule) = check_layout(&mut spec, limits)?;
    check_caches(&mut spec)?;
    if spec.label.len() > limits.max_label {
        return Err(bad(format!(
            "label: {} bytes is longer than {}",
            spec.label.len(),
            limits.max_label
        )));
    }
    let time = crate::animation_time::check(&spec)?;
    let scene_spec = resolve_scene(&spec.scene, scene_root)?;
    crate::animation_time::check_named(time.as_ref(), &scene_spec, &spec.scene)?;
    let package = Some(PathBuf::from(&scene_spec)).filter(|p| p.is_dir());
    check_package(package.is_some(), time.is_some(), translate.is_some())?;
    Ok(Validated {
        package,
        spec,
        scene_spec,
        integrator,
        effects,
        env,
        lighting,
        aovs,
        env_map_path,
        translate,
        domains_auto,
        schedule,
        time,
    })
}

/// The length of every free-text field, before anything else reads them.
fn check_texts(spec: &JobSpec) -> Result<(), Status> {
    check_text("scene", &spec.scene, MAX_SCENE_BYTES)?;
    let names = [
        ("integrator", &spec.integrator),
        ("layout", &spec.layout),
        ("schedule", &spec.schedule),
        ("effects", &spec.effects),
        ("passes", &spec.passes),
        ("animation", &spec.animation),
        ("frames", &spec.frames),
        ("coarse_sampling", &spec.coarse_sampling),
    ];
    for (field, v) in names {
        check_text(field, v, MAX_NAME_BYTES)?;
    }
    if let Some(c) = &spec.camera {
        check_text("camera", c, MAX_NAME_BYTES)?;
    }
    if let Some(p) = &spec.phm {
        check_text("phm.mode", &p.mode, MAX_NAME_BYTES)?;
        check_text("phm.kinds", &p.kinds, MAX_NAME_BYTES)?;
    }
    if let Some(rc) = &spec.ray_cache {
        check_text("ray_cache.retrieve", &rc.retrieve, MAX_NAME_BYTES)?;
        check_text("ray_cache.kinds", &rc.kinds, MAX_NAME_BYTES)?;
    }
    Ok(())
}

/// The image's size and samples, the passes, the integrator and its depth and AO knobs;
/// defaults written into `spec`.
fn check_sampling(spec: &mut JobSpec, limits: &Limits) -> Result<IntegratorKind, Status> {
    check_range("width", spec.width, limits.max_side)?;
    check_range("height", spec.height, limits.max_side)?;
    check_range("spp", spec.spp, limits.max_spp)?;
    if spec.passes.is_empty() {
        spec.passes = dray_core::passes::DEFAULT.into();
    }
    dray_core::passes::Passes::parse(&spec.passes, spec.spp)
        .map_err(|e| bad(format!("passes: {e}")))?;
    if spec.integrator.is_empty() {
        spec.integrator = DEFAULT_INTEGRATOR.name().into();
    }
    let integrator = IntegratorKind::from_name(&spec.integrator).ok_or_else(|| {
        bad(format!(
            "integrator: unknown integrator {:?} (expected {})",
            spec.integrator,
            IntegratorKind::choices()
        ))
    })?;
    let max_depth = *spec.max_depth.get_or_insert(DEFAULT_MAX_DEPTH);
    check_range("max_depth", max_depth, limits.max_depth)?;
    let ao = *spec.ao_samples.get_or_insert(DEFAULT_AO_SAMPLES);
    check_range("ao_samples", ao, limits.max_ao_samples)?;
    if let Some(d) = spec.ao_distance
        && (d.is_nan() || d <= 0.0)
    {
        return Err(bad(format!("ao_distance: must be positive, got {d}")));
    }
    Ok(integrator)
}

/// The constant environment's radiance: finite and non-negative.
fn env_of(spec: &JobSpec) -> Result<Option<Vec3>, Status> {
    spec.env
        .map(|e| {
            let v = Vec3::new(e.r, e.g, e.b);
            if !v.is_finite() || v.min_element() < 0.0 {
                Err(bad(format!(
                    "env: radiance must be finite and non-negative, got ({}, {}, {})",
                    e.r, e.g, e.b
                )))
            } else {
                Ok(v)
            }
        })
        .transpose()
}

/// The scene's translation: finite.
fn translate_of(spec: &JobSpec) -> Result<Option<Vec3>, Status> {
    spec.translate
        .map(|t| {
            let v = Vec3::new(t.x, t.y, t.z);
            if v.is_finite() {
                Ok(v)
            } else {
                Err(bad(format!(
                    "translate: must be finite, got ({}, {}, {})",
                    t.x, t.y, t.z
                )))
            }
        })
        .transpose()
}

/// `clamp_indirect` and `noise_threshold`: adaptive sampling decides between passes, so
/// it needs more than one.
fn check_noise(spec: &JobSpec) -> Result<(), Status> {
    if let Some(c) = spec.clamp_indirect {
        dray_core::clamp::check_limit(c).map_err(|e| bad(format!("clamp_indirect: {e}")))?;
    }
    if let Some(x) = spec.noise_threshold {
        dray_core::adaptive::check_threshold(x)
            .map_err(|e| bad(format!("noise_threshold: {e}")))?;
        // Decisions are taken between passes: one pass of every sample leaves none.
        let cut = dray_core::passes::Passes::parse(&spec.passes, spec.spp)
            .map_err(|e| bad(format!("passes: {e}")))?;
        if spec.spp > dray_core::adaptive::MIN_SAMPLES && cut.ranges(spec.spp).len() < 2 {
            return Err(bad(format!(
                "noise_threshold: needs more than one pass to stop tiles between them, but \
                 passes {:?} traces all {} samples in one (use \"doubling\")",
                spec.passes, spec.spp
            )));
        }
    }
    Ok(())
}

/// The domain count (0: chosen for the job; returned as `domains_auto`), the layout and
/// the schedule, written back resolved.
fn check_layout(spec: &mut JobSpec, limits: &Limits) -> Result<(bool, ScheduleRequest), Status> {
    let domains_auto = spec.domains == 0;
    if spec.domains == 0 {
        spec.domains = 1;
    }
    check_range("domains", spec.domains, limits.max_domains)?;
    if spec.layout.is_empty() {
        spec.layout = DEFAULT_LAYOUT.into();
    }
    if spec.layout != "grid" && spec.layout != "kd" {
        return Err(bad(format!(
            "layout: unknown layout {:?} (expected grid or kd)",
            spec.layout
        )));
    }
    let schedule =
        ScheduleRequest::parse(&spec.schedule, spec.replicate).map_err(|e| bad(e.to_string()))?;
    spec.schedule = schedule.name().to_string();
    Ok((domains_auto, schedule))
}

/// A scene package's geometry is cut already: it can be neither posed nor moved.
fn check_package(package: bool, time: bool, translate: bool) -> Result<(), Status> {
    if package && time {
        return Err(bad(
            "time: a scene package has no animation (its geometry is cut already): \
             partition the posed scene, or submit the glTF file"
                .into(),
        ));
    }
    if package && translate {
        return Err(bad(
            "translate: a scene package cannot be moved (partition the moved scene instead)".into(),
        ));
    }
    Ok(())
}

/// Check the ray-cache and hit-map knobs and `coarse_sampling`, and write them back
/// resolved (every default filled in, kinds in canonical order), so the workers, the
/// cache hosts and GetJob all read the same settings. The parsing, the defaults, the
/// bounds and the messages are [`dray_cache::settings`]'s, which the workers and the
/// cache hosts parse the spec with too.
pub fn check_caches(spec: &mut JobSpec) -> Result<WallSettings, Status> {
    let walls = WallSettings::from_proto(spec.ray_cache.as_ref(), spec.phm.as_ref())
        .map_err(|e| bad(e.to_string()))?;
    (spec.ray_cache, spec.phm) = walls.to_proto();
    check_coarse_sampling(spec, walls.coarse())?;
    Ok(walls)
}

/// Check `coarse_sampling` and fill in its default ([`CoarseSampling::DEFAULT`]) for a
/// job with a coarse pass (`coarse` > 0). It places the coarse pass's rays, so without
/// one it changes nothing (it is still checked, and kept: `dray sweep` checks each
/// varied value on its own, and a sweep over samplings and coarse sizes includes
/// coarse 0).
fn check_coarse_sampling(spec: &mut JobSpec, coarse: u32) -> Result<(), Status> {
    let sampling =
        CoarseSampling::from_proto(&spec.coarse_sampling).map_err(|e| bad(e.to_string()))?;
    if !spec.coarse_sampling.is_empty() || coarse > 0 {
        spec.coarse_sampling = sampling.name().into();
    }
    Ok(())
}

/// Parse effect overrides such as "+specular,-transmission" (a bare name means on).
pub fn parse_effects(spec: &str) -> Result<Vec<(Effect, bool)>, Status> {
    let mut out = Vec::new();
    for item in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (on, name) = if let Some(n) = item.strip_prefix('+') {
            (true, n)
        } else if let Some(n) = item.strip_prefix('-') {
            (false, n)
        } else {
            (true, item)
        };
        let Some(e) = Effect::from_name(name) else {
            let known: Vec<&str> = Effect::ALL.iter().map(|e| e.name()).collect();
            return Err(bad(format!(
                "effects: unknown effect {name:?} (known: {})",
                known.join(", ")
            )));
        };
        out.push((e, on));
    }
    Ok(out)
}

/// Resolve a scene spec: procedural names pass (a `grid:` spec has its inner scene
/// resolved too); a path, relative to `root` or absolute, must exist and lie inside
/// `root` once symlinks and `..` are resolved. A path may name a scene file or a scene
/// package directory (one with a manifest).
pub fn resolve_scene(scene: &str, root: &Path) -> Result<String, Status> {
    if scene.trim().is_empty() {
        return Err(bad("scene: empty scene".into()));
    }
    if dray_scene::procedural::is_procedural(scene) {
        // What its generator would refuse is refused now, not when the job loads it.
        dray_scene::procedural::check(scene).map_err(|e| bad(format!("scene: {e}")))?;
        if let Some(rest) = scene.strip_prefix("grid:")
            && let Some((inner, dims)) = rest.rsplit_once(':')
            && !inner.is_empty()
        {
            return Ok(format!("grid:{}:{dims}", resolve_scene(inner, root)?));
        }
        return Ok(scene.to_string());
    }
    let joined: PathBuf = root.join(scene);
    let canon = joined.canonicalize().map_err(|e| {
        bad(format!(
            "scene: {scene:?} is not a procedural scene name (cornell, cornell:mirror, \
             cornell:glass, spheres:N, soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>) \
             nor a file under the scene root ({e}){}",
            dray_scene::suggest::suggest_procedural(scene)
                .map(|s| format!("; did you mean {s:?}?"))
                .unwrap_or_default()
        ))
    })?;
    if !canon.starts_with(root) {
        return Err(bad(format!(
            "scene: path {scene:?} is outside the scene root"
        )));
    }
    if canon.is_dir() {
        if !canon.join(MANIFEST_FILE).is_file() {
            return Err(bad(format!(
                "scene: {scene:?} is a directory but not a scene package (no {MANIFEST_FILE}; \
                 make one with `dray partition`)"
            )));
        }
    } else if !canon.is_file() {
        return Err(bad(format!("scene: {scene:?} is not a file")));
    }
    canon
        .to_str()
        .map(str::to_string)
        .ok_or_else(|| bad(format!("scene: path {scene:?} is not valid UTF-8")))
}

/// A job ready to render: the loaded scene, its camera and the render settings.
pub struct Prepared {
    /// The loaded (and translated) scene. For a scene package: everything but the
    /// triangles (materials, lights, cameras, environment), with `mesh.material` listing
    /// the materials some triangle uses, which is all effect analysis reads.
    pub scene: Scene,
    /// Triangles in the scene.
    pub triangles: u64,
    /// For a scene package: the opened package.
    pub package: Option<dray_scene::partition::Package>,
    /// The camera chosen by the spec.
    pub camera: Camera,
    /// The spec's `view` resolved against the scene (`crate::view::resolve`), what
    /// workers build `camera` from.
    pub view: Option<dray_proto::v1::CameraSpec>,
    /// Everything the integrator needs.
    pub settings: RenderSettings,
    /// The environment map's file, for the workers (`JobSetup.env_map`); its decoded
    /// map is `settings.lighting.env_map`.
    pub env_map: Option<crate::lighting::LoadedEnvMap>,
}

/// Load the scene and make the scene-dependent checks (camera, effects), exactly as
/// `dray render` does, so the same spec gives the same image. `loaded` is the scene
/// already in memory (a process hosting the coordinator, as `dray render` does, hands
/// over the scene it loaded instead of having it read twice); it is translated here like
/// a loaded one. Blocking.
///
/// A scene loaded here stops early once `cancel` is set (CancelJob during PREPARING): it
/// then fails with a message saying so, for a job that is already CANCELLED.
pub fn prepare(
    v: &Validated,
    loaded: Option<Scene>,
    cancel: &Arc<AtomicBool>,
) -> Result<Prepared, Status> {
    let s = &v.spec;
    let (mut scene, package) = match (&v.package, loaded) {
        (_, Some(scene)) => (scene, None),
        (Some(dir), None) => {
            let pkg = open_package(dir).map_err(|e| {
                let e = as_given(&e.to_string(), &dir.to_string_lossy(), &s.scene);
                bad(format!("scene: cannot open the package {:?}: {e}", s.scene))
            })?;
            (package_scene(&pkg), Some(pkg))
        }
        (None, None) => {
            let scene = dray_scene::cancel::with_cancel(cancel, || {
                dray_scene::load_at(&v.scene_spec, v.time.as_ref())
            })
            .map_err(|e| {
                let e = as_given(&e.to_string(), &v.scene_spec, &s.scene);
                bad(format!("scene: cannot load {:?}: {e}", s.scene))
            })?;
            (scene, None)
        }
    };
    if let Some(t) = v.translate {
        dray_scene::translate::translate(&mut scene, t)
            .map_err(|e| bad(format!("translate: {e}")))?;
    }
    let triangles = match &package {
        Some(p) => p.manifest().source_triangles,
        None => scene.mesh.triangle_count() as u64,
    };
    let env_map = match (
        &v.env_map_path,
        s.lighting.as_ref().and_then(|l| l.env_map.as_ref()),
    ) {
        (Some(path), Some(spec)) => Some(crate::lighting::load_env_map(
            spec,
            path,
            "lighting.env_map.path",
        )?),
        _ => None,
    };
    let mut lighting = v.lighting.clone();
    lighting.env_map = env_map.as_ref().map(|e| e.map.clone());
    let environment = v
        .env
        .unwrap_or_else(|| dray_scene::effects::default_environment_lit(&scene, &lighting));
    let mut effects = dray_scene::effects::analyze_lit(&scene, environment, &lighting);
    for (e, on) in &v.effects {
        effects.set(*e, *on);
    }
    let aspect = s.width as f32 / s.height as f32;
    // The package has no mesh to take bounds from; its manifest has them.
    let bounds = match &package {
        Some(p) => {
            let b = p.layout().scene_bounds();
            (b.min, b.max)
        }
        None => scene.bounds(),
    };
    let camera = match &package {
        Some(_) if scene.cameras.is_empty() && s.camera.is_none() => {
            Camera::framing(bounds.0, bounds.1, aspect)
        }
        _ => choose_camera(&scene, s.camera.as_deref(), aspect)?,
    };
    let (view, camera) = match &s.view {
        Some(view) => {
            let offset = v.translate.unwrap_or(Vec3::ZERO);
            let (resolved, camera) = crate::view::resolve(view, &camera, bounds, aspect, offset)?;
            (Some(resolved), camera)
        }
        None => (None, camera),
    };
    let settings = RenderSettings {
        width: s.width,
        height: s.height,
        spp: s.spp,
        integrator: v.integrator,
        max_depth: s.max_depth.unwrap_or(DEFAULT_MAX_DEPTH),
        seed: s.seed,
        environment,
        effects,
        ao_samples: s.ao_samples.unwrap_or(DEFAULT_AO_SAMPLES),
        ao_distance: s.ao_distance.unwrap_or(f32::INFINITY),
        lighting,
        clamp_indirect: s.clamp_indirect,
        aovs: v.aovs,
    };
    Ok(Prepared {
        scene,
        triangles,
        package,
        camera,
        view,
        settings,
        env_map,
    })
}

/// A package's scene without its triangles, for the checks and the effect analysis
/// `prepare` makes: materials, lights, cameras and environment from the manifest, and
/// `mesh.material` holding each material some triangle uses, once.
fn package_scene(p: &dray_scene::partition::Package) -> Scene {
    let used = p
        .manifest()
        .material_triangles
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(m, _)| m as u32)
        .collect();
    Scene {
        name: p.name().to_string(),
        mesh: Mesh {
            material: used,
            ..Mesh::default()
        },
        materials: p.materials().to_vec(),
        textures: Vec::new(),
        lights: p.lights().to_vec(),
        cameras: p.cameras().to_vec(),
        environment: p.environment(),
        stats: Default::default(),
    }
}

/// The camera named by `which` (a name or an index), the scene's first, or one framing
/// the bounds; the same choice as `dray render --camera`.
pub fn choose_camera(scene: &Scene, which: Option<&str>, aspect: f32) -> Result<Camera, Status> {
    scene
        .choose_camera(which, scene.bounds(), aspect)
        .map_err(|e| bad(format!("camera: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::Schedule;
    use dray_proto::v1::{PhmSettings, RayCacheSettings};

    fn spec() -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            width: 8,
            height: 8,
            spp: 1,
            ..Default::default()
        }
    }

    /// `coarse_sampling`: centres by default with a coarse pass, nothing filled in
    /// without one, unknown values refused naming the field.
    #[test]
    fn coarse_sampling_is_checked_and_defaults_to_centres() {
        let with_coarse = |coarse, sampling: &str| JobSpec {
            ray_cache: Some(RayCacheSettings {
                coarse,
                ..Default::default()
            }),
            coarse_sampling: sampling.into(),
            ..spec()
        };
        let mut s = with_coarse(16, "");
        check_caches(&mut s).unwrap();
        assert_eq!(s.coarse_sampling, "centres");
        let mut s = with_coarse(0, "");
        check_caches(&mut s).unwrap();
        assert_eq!(s.coarse_sampling, "");
        for ok in ["random", "centres"] {
            let mut s = with_coarse(16, ok);
            check_caches(&mut s).unwrap();
            assert_eq!(s.coarse_sampling, ok);
        }
        let e = check_caches(&mut with_coarse(16, "jitter")).unwrap_err();
        assert!(e.message().starts_with("coarse_sampling must be"), "{e:?}");
    }

    /// Procedural specs the generators would refuse are refused at submission (issue
    /// 45, item 13: they were accepted and failed only when loaded).
    #[test]
    fn procedural_specs_beyond_their_generators_are_refused_at_once() {
        let root = std::env::temp_dir().canonicalize().unwrap();
        for bad_scene in [
            "spheres:4294967296",
            "spheres:10:gold",
            "iso:sphere:100000",
            "city:1e9",
            "soup:0",
            "cornell:velvet",
            "grid:spheres:4294967296:2x2x2",
            "grid:cornell:0x1x1",
        ] {
            let s = JobSpec {
                scene: bad_scene.into(),
                ..spec()
            };
            let e = match validate(&s, &Limits::default(), &root) {
                Err(e) => e,
                Ok(_) => panic!("{bad_scene} was accepted"),
            };
            assert_eq!(e.code(), tonic::Code::InvalidArgument, "{bad_scene}: {e:?}");
            assert!(e.message().starts_with("scene: "), "{}", e.message());
        }
        for good in [
            "cornell",
            "cornell:glass",
            "spheres:10:mirror",
            "iso:sphere:64",
            "grid:cornell:2x1x1",
        ] {
            let s = JobSpec {
                scene: good.into(),
                ..spec()
            };
            assert!(validate(&s, &Limits::default(), &root).is_ok(), "{good}");
        }
    }

    /// A scene that fails to load is named as the client gave it, never by the
    /// coordinator's absolute scene root (issue 45, item 11).
    #[test]
    fn load_errors_do_not_show_the_scene_root() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().canonicalize().unwrap();
        std::fs::create_dir(root.join("models")).unwrap();
        std::fs::write(root.join("models/bad.gltf"), b"{ not json").unwrap();
        let s = JobSpec {
            scene: "models/bad.gltf".into(),
            ..spec()
        };
        let v = validate(&s, &Limits::default(), &root).unwrap();
        let never = Arc::new(AtomicBool::new(false));
        let e = match prepare(&v, None, &never) {
            Err(e) => e,
            Ok(_) => panic!("a broken file loaded"),
        };
        let msg = e.message();
        assert!(msg.contains("models/bad.gltf"), "{msg}");
        assert!(!msg.contains(&*root.to_string_lossy()), "{msg}");
    }

    /// docs/security.md "Hardening, second round", item 3: a scene moved beyond the import
    /// bound (±1e18) is refused
    /// like a file with such coordinates; before, it reached the BVH conversion, which
    /// panicked on the workers.
    #[test]
    fn a_translation_beyond_the_coordinate_bound_is_refused() {
        let root = std::env::temp_dir().canonicalize().unwrap();
        let l = Limits::default();
        let never = Arc::new(AtomicBool::new(false));
        for (x, ok) in [(1e25f32, false), (-1e22, false), (1e17, true)] {
            let s = JobSpec {
                translate: Some(dray_proto::v1::Vec3 { x, y: 0.0, z: 0.0 }),
                ..spec()
            };
            let v = validate(&s, &l, &root).unwrap();
            match prepare(&v, None, &never) {
                Ok(_) => assert!(ok, "{x} accepted"),
                Err(e) => {
                    assert!(!ok, "{x}: {}", e.message());
                    assert_eq!(e.code(), tonic::Code::InvalidArgument);
                    assert!(
                        e.message().starts_with("translate: moves vertex"),
                        "{}",
                        e.message()
                    );
                    assert!(e.message().contains("1e18"), "{}", e.message());
                }
            }
        }
    }

    #[test]
    fn defaults_and_rejections() {
        let root = std::env::temp_dir().canonicalize().unwrap();
        let l = Limits::default();
        let v = validate(&spec(), &l, &root).unwrap();
        assert_eq!(v.spec.integrator, "path");
        assert_eq!(v.spec.max_depth, Some(5));
        assert_eq!(v.spec.layout, "kd");
        assert_eq!(v.spec.domains, 1);
        assert_eq!(v.spec.schedule, "auto");
        assert_eq!(v.schedule, ScheduleRequest::Auto { replicate: false });
        let field = |s: JobSpec| validate(&s, &l, &root).unwrap_err().message().to_string();
        assert!(field(JobSpec { width: 0, ..spec() }).starts_with("width:"));
        assert!(
            field(JobSpec {
                height: 20000,
                ..spec()
            })
            .starts_with("height:")
        );
        assert!(field(JobSpec { spp: 0, ..spec() }).starts_with("spp:"));
        let bogus = JobSpec {
            integrator: "bogus".into(),
            ..spec()
        };
        assert!(field(bogus).starts_with("integrator:"));
        let fx = JobSpec {
            effects: "+nope".into(),
            ..spec()
        };
        assert!(field(fx).starts_with("effects:"));
        let esc = JobSpec {
            scene: "../../etc/passwd".into(),
            ..spec()
        };
        assert!(field(esc).starts_with("scene:"));
        let unknown = JobSpec {
            scene: "no-such-scene.glb".into(),
            ..spec()
        };
        assert!(field(unknown).starts_with("scene:"));
        let sched = JobSpec {
            schedule: "round-robin".into(),
            ..spec()
        };
        let msg = field(sched);
        assert!(
            msg.starts_with("schedule:")
                && msg.contains(
                    "auto, replicated, image-plane, domain, dynamic or dynamic-from-image-plane"
                ),
            "{msg}"
        );
        let rep = JobSpec {
            schedule: "image-plane".into(),
            replicate: true,
            ..spec()
        };
        assert!(field(rep).starts_with("replicate:"));
        for (name, want) in [
            ("auto", ScheduleRequest::Auto { replicate: false }),
            ("replicated", ScheduleRequest::Forced(Schedule::Replicated)),
            ("image-plane", ScheduleRequest::Forced(Schedule::ImagePlane)),
            ("domain", ScheduleRequest::Forced(Schedule::Domain)),
            (
                "dynamic",
                ScheduleRequest::Forced(Schedule::Dynamic { replicate: false }),
            ),
        ] {
            let s = JobSpec {
                schedule: name.into(),
                ..spec()
            };
            let v = validate(&s, &l, &root).unwrap();
            assert_eq!((v.schedule, v.spec.schedule.as_str()), (want, name));
        }
        let s = JobSpec {
            replicate: true,
            ..spec()
        };
        let v = validate(&s, &l, &root).unwrap();
        assert_eq!(v.schedule, ScheduleRequest::Auto { replicate: true });
    }

    /// `light_samples`: absent means one sample (and stays absent), 1..=256 reach the
    /// settings, 0 and 257 are refused naming the field and the bound.
    #[test]
    fn light_samples_are_checked_against_their_bound() {
        use dray_core::light_samples::MAX_LIGHT_SAMPLES;
        let root = std::env::temp_dir().canonicalize().unwrap();
        let l = Limits::default();
        let with = |n| JobSpec {
            light_samples: n,
            ..spec()
        };
        let v = validate(&with(None), &l, &root).unwrap();
        assert_eq!((v.lighting.samples.get(), v.spec.light_samples), (1, None));
        for n in [1, 10, MAX_LIGHT_SAMPLES] {
            let v = validate(&with(Some(n)), &l, &root).unwrap();
            assert_eq!(
                (v.lighting.samples.get(), v.spec.light_samples),
                (n, Some(n))
            );
        }
        assert_eq!(MAX_LIGHT_SAMPLES, 256);
        for n in [0, 257, u32::MAX] {
            let e = validate(&with(Some(n)), &l, &root).unwrap_err();
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert_eq!(
                e.message(),
                format!("light_samples: {n} is out of range (1..=256)")
            );
        }
    }

    fn cache(rc: RayCacheSettings) -> Result<RayCacheSettings, String> {
        let root = std::env::temp_dir().canonicalize().unwrap();
        let s = JobSpec {
            ray_cache: Some(rc),
            ..spec()
        };
        validate(&s, &Limits::default(), &root)
            .map(|v| v.spec.ray_cache.expect("ray_cache kept"))
            .map_err(|e| {
                assert_eq!(e.code(), tonic::Code::InvalidArgument);
                e.message().to_string()
            })
    }

    #[test]
    fn ray_cache_defaults_are_filled_in() {
        let root = std::env::temp_dir().canonicalize().unwrap();
        let off = validate(&spec(), &Limits::default(), &root).unwrap();
        assert_eq!(off.spec.ray_cache, None, "absent stays absent (caches off)");
        let rc = cache(RayCacheSettings::default()).unwrap();
        assert_eq!(
            rc,
            RayCacheSettings {
                radius: 0.0,
                angle_deg: Some(10.0),
                retrieve: "nearest".into(),
                coarse: 0,
                kinds: "camera,reflection,refraction,diffuse".into(),
                fill: Some(true),
                placement: "sender".into(),
            }
        );
        let rc = cache(RayCacheSettings {
            radius: 0.005,
            angle_deg: Some(90.0),
            retrieve: "average".into(),
            kinds: " diffuse,camera,,diffuse ".into(),
            fill: Some(false),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(rc.radius, 0.005);
        assert_eq!(rc.angle_deg, Some(90.0));
        assert_eq!(rc.retrieve, "average");
        assert_eq!(rc.kinds, "camera,diffuse", "canonical order, no duplicates");
        assert_eq!(rc.fill, Some(false));
        let frozen = cache(RayCacheSettings {
            coarse: 64,
            ..Default::default()
        })
        .unwrap();
        assert_eq!(frozen.fill, Some(false), "a coarse pass freezes the caches");
        for mode in ["first", "nearest", "average"] {
            let rc = cache(RayCacheSettings {
                retrieve: mode.into(),
                ..Default::default()
            });
            assert_eq!(rc.unwrap().retrieve, mode);
        }
    }

    #[test]
    fn phm_placement_follows_the_ray_cache_and_must_agree_with_it() {
        let root = std::env::temp_dir().canonicalize().unwrap();
        let run = |rc: Option<&str>, phm: &str| {
            let s = JobSpec {
                ray_cache: rc.map(|p| RayCacheSettings {
                    placement: p.into(),
                    ..Default::default()
                }),
                phm: Some(PhmSettings {
                    placement: phm.into(),
                    ..Default::default()
                }),
                ..spec()
            };
            validate(&s, &Limits::default(), &root)
                .map(|v| v.spec.phm.expect("phm kept"))
                .map_err(|e| e.message().to_string())
        };
        let p = run(None, "").unwrap();
        assert_eq!((p.placement.as_str(), p.merge), ("sender", Some(4096)));
        assert_eq!(run(Some("remote"), "").unwrap().placement, "remote");
        assert_eq!(run(Some(""), "").unwrap().placement, "sender");
        assert_eq!(run(None, "remote").unwrap().placement, "remote");
        let e = run(Some("remote"), "sender").unwrap_err();
        assert!(
            e.starts_with("phm.placement \"sender\" and ray_cache.placement \"remote\" must agree"),
            "{e}"
        );
        let e = run(None, "nearby").unwrap_err();
        assert_eq!(e, "phm.placement must be sender or remote, got \"nearby\"");
        let s = JobSpec {
            phm: Some(PhmSettings {
                merge: Some(0),
                ..Default::default()
            }),
            ..spec()
        };
        let e = validate(&s, &Limits::default(), &root).unwrap_err();
        assert!(
            e.message().starts_with("phm.merge must be at least 1"),
            "{}",
            e.message()
        );
    }

    #[test]
    fn ray_cache_bad_values_name_the_field() {
        let base = RayCacheSettings::default;
        let cases = [
            (
                RayCacheSettings {
                    placement: "beside".into(),
                    ..base()
                },
                "ray_cache.placement must be sender or remote, got \"beside\"",
            ),
            (
                RayCacheSettings {
                    radius: -1.0,
                    ..base()
                },
                "ray_cache.radius must be finite and >= 0, got -1",
            ),
            (
                RayCacheSettings {
                    radius: f32::NAN,
                    ..base()
                },
                "ray_cache.radius",
            ),
            (
                RayCacheSettings {
                    radius: f32::INFINITY,
                    ..base()
                },
                "ray_cache.radius",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(0.0),
                    ..base()
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(90.5),
                    ..base()
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(-3.0),
                    ..base()
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(f32::NAN),
                    ..base()
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    retrieve: "best".into(),
                    ..base()
                },
                "ray_cache.retrieve",
            ),
            (
                RayCacheSettings {
                    retrieve: "Nearest".into(),
                    ..base()
                },
                "ray_cache.retrieve",
            ),
            (
                RayCacheSettings {
                    coarse: 4097,
                    ..base()
                },
                "ray_cache.coarse must be in 0..=4096",
            ),
            (
                RayCacheSettings {
                    kinds: "camera,shadow".into(),
                    ..base()
                },
                "ray_cache.kinds: \"shadow\"",
            ),
            (
                RayCacheSettings {
                    kinds: "ao".into(),
                    ..base()
                },
                "ray_cache.kinds: \"ao\"",
            ),
        ];
        for (rc, want) in cases {
            let msg = cache(rc.clone()).expect_err(&format!("{rc:?} accepted"));
            assert!(
                msg.starts_with(want),
                "{msg:?} does not start with {want:?}"
            );
        }
    }
}
