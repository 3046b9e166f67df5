//! The flags that describe a job's image, shared by `dray render` (which renders it here)
//! and `dray submit` (which sends it to a coordinator), so the two take the same words
//! and turn them into the same `dray.v1.JobSpec`.

use anyhow::{Result, bail};
use clap::Args;
use dray_coordinator::scheduler::ScheduleRequest;
use dray_coordinator::scheduler::policy::{SCHEDULE_NAMES, ScheduleError};
use dray_coordinator::validate::{DEFAULT_AO_SAMPLES, DEFAULT_INTEGRATOR, DEFAULT_MAX_DEPTH};
use dray_core::display::Display;
use dray_core::exposure::Exposure;
use dray_core::integrator::IntegratorKind;
use dray_core::tonemap::{Tonemap, UnknownTonemap};
use dray_proto::v1::{JobSpec, PhmSettings, Rgb, Vec3};

use crate::options::parse_vec3;

#[derive(Args, Debug, Clone)]
pub struct JobFlags {
    /// A .gltf, .glb, .ply or .obj file, or a procedural scene: cornell, cornell:mirror,
    /// cornell:glass, spheres:N, soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>.
    /// With `dray submit`, paths are relative to the coordinator's --scene-root, and a
    /// scene package directory works too.
    pub scene: String,
    #[arg(long, default_value_t = 640)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub spp: u32,
    /// raycast | primary | whitted | path | ao (primary: camera rays only, first hits
    /// lit without shadows, Little 2011's ray caster)
    #[arg(long, default_value = DEFAULT_INTEGRATOR.name(), value_name = "NAME", value_parser = parse_integrator)]
    #[arg(help_heading = crate::help_heading::INTEGRATOR)]
    pub integrator: String,
    /// Maximum number of surface interactions along a path.
    #[arg(long, default_value_t = DEFAULT_MAX_DEPTH)]
    #[arg(help_heading = crate::help_heading::INTEGRATOR)]
    pub max_depth: u32,
    #[arg(long, default_value_t = 0)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub seed: u64,
    /// A camera of the scene, by name or index (default: the first, or one framing the bounds).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::CAMERA)]
    pub camera: Option<String>,
    /// Constant environment radiance "R,G,B" (default: black with lights or emitters, 1.0 otherwise).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::LIGHTS)]
    pub env: Option<String>,
    /// Force effects on or off, e.g. "+specular,-transmission" (names: direct_light,
    /// specular, transmission, emission, textures, alpha, environment, unlit, clearcoat,
    /// sheen, anisotropy, volume, iridescence, dispersion, sun, env_map).
    #[arg(long, allow_hyphen_values = true)]
    #[arg(help_heading = crate::help_heading::INTEGRATOR)]
    pub effects: Option<String>,
    /// Rays per hit for the ao integrator.
    #[arg(long, default_value_t = DEFAULT_AO_SAMPLES)]
    #[arg(help_heading = crate::help_heading::INTEGRATOR)]
    pub ao_samples: u32,
    /// Occlusion distance for the ao integrator (default: unlimited).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::INTEGRATOR)]
    pub ao_distance: Option<f32>,
    /// Move the whole scene by "X,Y,Z" before rendering (tests precision far from the origin).
    #[arg(long, allow_hyphen_values = true)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub translate: Option<String>,
    /// Progressive passes: "doubling" (1, 1, 2, 4, ... samples per pixel; GetImage and
    /// `dray submit --preview` show the image after each), "one" (every sample in one
    /// pass), or N samples per pass. No effect on the final image. Default: "doubling"
    /// for a job others can watch (`dray submit`), "one" for `dray render`, which shows
    /// nothing before the end (each pass waits for its slowest tile).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::IMAGE)]
    pub passes: Option<String>,
    /// Exposure of the PNG: `auto` maps the image's log-average luminance (robust to a
    /// few very bright pixels) to mid-grey, so scenes in photometric units (a 68000-lux
    /// sun) come out well exposed; a number is stops (radiance times 2^EV, -64..=64).
    /// The EXR stays linear.
    #[arg(
        long,
        default_value = "auto",
        value_name = "auto|EV",
        allow_hyphen_values = true,
        value_parser = parse_exposure
    )]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub exposure: Exposure,
    /// Tone curve of the PNG: clamp (none: values above 1 clip; with --exposure 0 the
    /// encoding of dray before curves), reinhard, aces (ACES filmic) or agx (AgX, as
    /// Blender; the default: 6.5 stops of highlights above mid-grey, bright colours go
    /// to white). The EXR stays linear.
    #[arg(
        long,
        default_value = Tonemap::DEFAULT.name(),
        value_name = "NAME",
        value_parser = parse_tonemap
    )]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub tonemap: Tonemap,
    /// 8-bit sRGB PNG to write.
    #[arg(long, default_value = "dray.png")]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub output: std::path::PathBuf,
    /// Also write linear radiance as OpenEXR.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub exr: Option<std::path::PathBuf>,
    /// No progress bar or summary.
    #[arg(long, short)]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub quiet: bool,
    /// How the job's domains and rays are scheduled on workers: auto (the default:
    /// replicated when the scene fits every worker's --memory-budget, else dynamic;
    /// `--stats` says which and why), replicated (every worker holds the whole scene and
    /// traces whole paths for its tiles; no rays exchanged), image-plane (each worker
    /// traces its own block of tiles and every ray they lead to, loading the domains it
    /// needs; no rays exchanged), domain (static round-robin ownership, rays sent to
    /// owners), dynamic (ray-weighted: domains move to where the rays wait) or
    /// dynamic-from-image-plane (dynamic, started from image-plane as Navrátil et al.
    /// 2012 start it: no routing until every worker has reported its queues, then each
    /// domain owned where it is resident, then dynamic rounds). The image
    /// is the same under every schedule. No effect with `dray render --workers 0` (the
    /// reference renderer has no workers to schedule).
    #[arg(long, default_value = default_schedule(), value_name = "NAME", value_parser = parse_schedule)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub schedule: String,
    /// With --schedule dynamic or dynamic-from-image-plane (or auto, when it chooses
    /// dynamic): also replicate the most-wanted domains on idle workers.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub replicate: bool,
    /// Ray caches on domain walls, e.g. radius=0.005,kinds=camera+diffuse, or `on` (keys:
    /// radius, angle-deg, retrieve, coarse, kinds, fill, placement, coarse-sampling;
    /// --help says more).
    #[arg(
        long,
        value_name = "KEY=VALUE,...",
        long_help = crate::ray_cache_flag::help(),
        value_parser = crate::ray_cache_flag::parse_ray_cache
    )]
    #[arg(help_heading = crate::help_heading::APPROXIMATIONS)]
    pub ray_cache: Option<crate::ray_cache_flag::RayCacheFlag>,
    /// Probability hit maps on domain walls, e.g. miss=0.1,hit=0.9,kinds=shadow, or `on`
    /// (keys: res, dirs, prior, miss, hit, mode, reprobe, kinds; --help says more).
    #[arg(
        long,
        value_name = "KEY=VALUE,...",
        long_help = crate::phm_flag::help(),
        value_parser = crate::phm_flag::parse_phm
    )]
    #[arg(help_heading = crate::help_heading::APPROXIMATIONS)]
    pub phm: Option<PhmSettings>,
    /// Camera placement and lens (`JobSpec.view`).
    #[command(flatten)]
    pub view: crate::view_flags::ViewFlags,
    #[command(flatten)]
    pub lights: crate::light_flags::LightFlags,
    /// Noise controls (`JobSpec.clamp_indirect`, `noise_threshold`, `aovs`).
    #[command(flatten)]
    pub noise: crate::noise_flags::NoiseFlags,
    /// The moment of the animation, or a range of frames (`JobSpec.time`, `frames`).
    #[command(flatten)]
    pub anim: crate::animation_flags::AnimationFlags,
}

/// The schedule of a job that names none: the coordinator's choice for an empty
/// `JobSpec.schedule`.
fn default_schedule() -> &'static str {
    ScheduleRequest::parse("", false).map_or("", |s| s.name())
}

/// `--exposure auto|EV`.
fn parse_exposure(s: &str) -> Result<Exposure, String> {
    Exposure::parse(s).map_err(|e| e.to_string())
}

/// `--tonemap NAME`: one of [`Tonemap::NAMES`] (the empty name is not one here: on the
/// command line the default is spelt out).
fn parse_tonemap(s: &str) -> Result<Tonemap, String> {
    if s.is_empty() {
        return Err(UnknownTonemap(String::new()).to_string());
    }
    Tonemap::parse(s).map_err(|e| e.to_string())
}

/// `--integrator NAME`: refused here, as every other bad flag value is (a usage error,
/// exit code 2), rather than after the scene has loaded.
fn parse_integrator(s: &str) -> Result<String, String> {
    match IntegratorKind::from_name(s) {
        Some(_) => Ok(s.to_string()),
        None => Err(format!(
            "unknown integrator {s:?} (expected {})",
            IntegratorKind::choices()
        )),
    }
}

/// `--schedule NAME`: one of the coordinator's [`SCHEDULE_NAMES`], or a one-line error
/// naming them.
fn parse_schedule(s: &str) -> Result<String, String> {
    if SCHEDULE_NAMES.contains(&s) {
        Ok(s.to_string())
    } else {
        // "a, b or c", as the coordinator words it.
        let (last, rest) = SCHEDULE_NAMES.split_last().unwrap_or((&"", &[]));
        Err(format!(
            "unknown schedule {s:?} (expected {} or {last})",
            rest.join(", ")
        ))
    }
}

impl JobFlags {
    /// Flags that clap cannot check one at a time, by the coordinator's rules.
    pub fn check_schedule(&self) -> Result<()> {
        if let Err(e @ ScheduleError::ReplicateNeedsDynamic(_)) =
            ScheduleRequest::parse(&self.schedule, self.replicate)
        {
            bail!("--replicate with --schedule {}: {e}", self.schedule);
        }
        Ok(())
    }

    /// `--passes`: a cut of `--spp` the coordinator accepts; with `--noise-threshold`,
    /// one of more than one pass (tiles stop between passes).
    pub fn check_passes(&self) -> Result<()> {
        let cut = dray_core::passes::Passes::parse(self.passes_or_default(), self.spp)
            .map_err(|e| anyhow::anyhow!("--passes: {e}"))?;
        if self.noise.noise_threshold.is_some()
            && self.spp > dray_core::adaptive::MIN_SAMPLES
            && cut.ranges(self.spp).len() < 2
        {
            bail!(
                "--noise-threshold stops tiles between passes, but --passes {} traces all {} \
                 samples in one: leave --passes out (doubling) or give a number of samples \
                 per pass",
                self.passes_or_default(),
                self.spp
            );
        }
        Ok(())
    }

    /// The passes `dray render --workers 0` traces: one pass unless asked, or doubling
    /// for adaptive sampling (which stops tiles between passes).
    pub fn local_passes(&self) -> dray_core::passes::Passes {
        let spp = self.spp;
        match self.passes.as_deref() {
            Some(p) => dray_core::passes::Passes::parse(p, spp)
                .unwrap_or(dray_core::passes::Passes::Every(spp.max(1))),
            None if self.noise.noise_threshold.is_some() => dray_core::passes::Passes::Doubling,
            None => dray_core::passes::Passes::Every(spp.max(1)),
        }
    }

    /// `--aov`: known names, each once, and an `--exr` file to hold them.
    pub fn check_aovs(&self) -> Result<()> {
        if self.noise.aovs()?.is_empty() {
            return Ok(());
        }
        if self.exr.is_none() {
            bail!("--aov writes its channels into the EXR image: give --exr FILE too");
        }
        Ok(())
    }

    /// `--passes`, or the coordinator's default (`doubling`) when not given.
    pub fn passes_or_default(&self) -> &str {
        self.passes.as_deref().unwrap_or(dray_core::passes::DEFAULT)
    }

    /// The display transform of the PNG (`--exposure`, `--tonemap`).
    pub fn display(&self) -> Display {
        Display {
            exposure: self.exposure,
            tonemap: self.tonemap,
        }
    }

    /// The job spec these flags describe, with `scene` as given. `max_depth` and
    /// `ao_samples` are always sent (with `dray render`'s defaults), so the job does not
    /// depend on a server's defaults.
    pub fn job_spec(
        &self,
        scene: String,
        domains: u32,
        layout: &str,
        label: &str,
    ) -> Result<JobSpec> {
        self.check_schedule()?;
        self.anim.check()?;
        let env = self
            .env
            .as_deref()
            .map(|s| parse_vec3("--env", s))
            .transpose()?
            .map(|v| Rgb {
                r: v.x,
                g: v.y,
                b: v.z,
            });
        let translate = self
            .translate
            .as_deref()
            .map(|s| parse_vec3("--translate", s))
            .transpose()?
            .map(|v| Vec3 {
                x: v.x,
                y: v.y,
                z: v.z,
            });
        Ok(JobSpec {
            scene,
            width: self.width,
            height: self.height,
            spp: self.spp,
            integrator: self.integrator.clone(),
            max_depth: Some(self.max_depth),
            seed: self.seed,
            camera: self.camera.clone(),
            env,
            effects: self.effects.clone().unwrap_or_default(),
            ao_samples: Some(self.ao_samples),
            ao_distance: self.ao_distance,
            translate,
            domains,
            layout: layout.to_string(),
            label: label.to_string(),
            schedule: self.schedule.clone(),
            replicate: self.replicate,
            ray_cache: self.ray_cache.as_ref().map(|f| f.settings.clone()),
            coarse_sampling: self
                .ray_cache
                .as_ref()
                .map(|f| f.coarse_sampling.clone())
                .unwrap_or_default(),
            phm: self.phm.clone(),
            passes: self.passes_or_default().to_string(),
            view: self.view.spec()?,
            lighting: self.lights.lighting_spec(),
            sun_color: self.lights.sun_color_spec(),
            light_samples: self.lights.light_samples_spec(),
            clamp_indirect: self.noise.clamp_indirect,
            aovs: self.noise.aov.clone(),
            time: self.anim.time,
            animation: self.anim.animation.clone().unwrap_or_default(),
            frames: self.anim.frames_text(),
            fps: self.anim.fps,
            // `dray submit --priority` sets it (submit_cmd.rs); nothing to queue behind
            // in `dray render`.
            priority: 0,
            noise_threshold: self.noise.noise_threshold,
            // `dray render --trace-out` sets it (embedded.rs).
            trace: false,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedules() {
        for name in SCHEDULE_NAMES {
            assert_eq!(parse_schedule(name).as_deref(), Ok(name));
        }
        let e = parse_schedule("bogus").expect_err("bogus");
        assert!(
            e.contains("\"bogus\"")
                && e.contains(
                    "auto, replicated, image-plane, domain, dynamic or dynamic-from-image-plane"
                ),
            "{e}"
        );
        assert!(parse_schedule("Dynamic").is_err());
        assert_eq!(parse_schedule(default_schedule()).as_deref(), Ok("auto"));
    }

    #[test]
    fn exposure_and_tone_curve_flags() {
        assert_eq!(parse_exposure("auto"), Ok(Exposure::Auto));
        assert_eq!(parse_exposure("-12"), Ok(Exposure::Stops(-12.0)));
        let e = parse_exposure("65").expect_err("out of range");
        assert!(e.contains("65 is out of range (-64..=64 stops)"), "{e}");
        for (t, n) in Tonemap::ALL.into_iter().zip(Tonemap::NAMES) {
            assert_eq!(parse_tonemap(n), Ok(t));
        }
        let e = parse_tonemap("").expect_err("empty");
        assert!(e.contains("expected clamp, reinhard, aces or agx"), "{e}");
        assert!(parse_tonemap("filmic").is_err());
    }
}
