//! The flags that describe a job's image, shared by `dray render` (which renders it here)
//! and `dray submit` (which sends it to a coordinator), so the two take the same words
//! and turn them into the same `dray.v1.JobSpec`.

use anyhow::{Result, bail};
use clap::Args;
use dray_coordinator::scheduler::Schedule;
use dray_coordinator::scheduler::policy::{SCHEDULE_NAMES, ScheduleError};
use dray_coordinator::service::MAX_EXPOSURE_STOPS;
use dray_coordinator::validate::{DEFAULT_AO_SAMPLES, DEFAULT_INTEGRATOR, DEFAULT_MAX_DEPTH};
use dray_proto::v1::{JobSpec, PhmSettings, RayCacheSettings, Rgb, Vec3};

use crate::options::parse_vec3;

#[derive(Args, Debug, Clone)]
pub struct JobFlags {
    /// A .gltf, .glb, .ply or .obj file, or a procedural scene: cornell, cornell:mirror,
    /// cornell:glass, spheres:N, soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>.
    /// With `dray submit`, paths are relative to the coordinator's --scene-root, and a
    /// scene package directory works too.
    pub scene: String,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// raycast | whitted | path | ao
    #[arg(long, default_value = DEFAULT_INTEGRATOR.name())]
    pub integrator: String,
    /// Maximum number of surface interactions along a path.
    #[arg(long, default_value_t = DEFAULT_MAX_DEPTH)]
    pub max_depth: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// A camera of the scene, by name or index (default: the first, or one framing the bounds).
    #[arg(long)]
    pub camera: Option<String>,
    /// Constant environment radiance "R,G,B" (default: black with lights or emitters, 1.0 otherwise).
    #[arg(long)]
    pub env: Option<String>,
    /// Force effects on or off, e.g. "+specular,-transmission" (names: direct_light,
    /// specular, transmission, emission, textures, alpha, environment, unlit, clearcoat,
    /// sheen, anisotropy, volume).
    #[arg(long, allow_hyphen_values = true)]
    pub effects: Option<String>,
    /// Rays per hit for the ao integrator.
    #[arg(long, default_value_t = DEFAULT_AO_SAMPLES)]
    pub ao_samples: u32,
    /// Occlusion distance for the ao integrator (default: unlimited).
    #[arg(long)]
    pub ao_distance: Option<f32>,
    /// Move the whole scene by "X,Y,Z" before rendering (tests precision far from the origin).
    #[arg(long, allow_hyphen_values = true)]
    pub translate: Option<String>,
    /// Progressive passes: "doubling" (1, 1, 2, 4, ... samples per pixel; GetImage and
    /// `dray submit --preview` show the image after each), "one" (every sample in one
    /// pass), or N samples per pass. No effect on the final image.
    #[arg(long, default_value = dray_core::passes::DEFAULT)]
    pub passes: String,
    /// Exposure in stops for the PNG (radiance is scaled by 2^EV; the EXR stays linear).
    /// Scenes in photometric units, such as a 68000-lux sun, want about -16.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub exposure: f32,
    /// 8-bit sRGB PNG to write.
    #[arg(long, default_value = "dray.png")]
    pub output: std::path::PathBuf,
    /// Also write linear radiance as OpenEXR.
    #[arg(long)]
    pub exr: Option<std::path::PathBuf>,
    /// No progress bar or summary.
    #[arg(long, short)]
    pub quiet: bool,
    /// How the job's domains and rays are scheduled on workers: image-plane (each worker
    /// traces its own block of tiles and every ray they lead to, loading the domains it
    /// needs; no rays exchanged), domain (static round-robin ownership, rays sent to
    /// owners) or dynamic (ray-weighted: domains move to where the rays wait). The image
    /// is the same under every schedule. No effect with `dray render --workers 0` (the
    /// reference renderer has no workers to schedule).
    #[arg(long, default_value = default_schedule(), value_name = "NAME", value_parser = parse_schedule)]
    pub schedule: String,
    /// With --schedule dynamic: also replicate the most-wanted domains on idle workers.
    #[arg(long)]
    pub replicate: bool,
    /// Ray caches on domain walls, e.g. radius=0.005,kinds=camera+diffuse, or `on` (keys:
    /// radius, angle-deg, retrieve, coarse, kinds, fill; --help says more).
    #[arg(
        long,
        value_name = "KEY=VALUE,...",
        long_help = crate::ray_cache_flag::help(),
        value_parser = crate::ray_cache_flag::parse_ray_cache
    )]
    pub ray_cache: Option<RayCacheSettings>,
    /// Probability hit maps on domain walls, e.g. miss=0.1,hit=0.9,kinds=shadow, or `on`
    /// (keys: res, dirs, prior, miss, hit, mode, reprobe, kinds; --help says more).
    #[arg(
        long,
        value_name = "KEY=VALUE,...",
        long_help = crate::phm_flag::help(),
        value_parser = crate::phm_flag::parse_phm
    )]
    pub phm: Option<PhmSettings>,
}

/// The schedule of a job that names none: the coordinator's choice for an empty
/// `JobSpec.schedule`.
fn default_schedule() -> &'static str {
    Schedule::parse("", false).map_or("", |s| s.name())
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
            Schedule::parse(&self.schedule, self.replicate)
        {
            bail!("--replicate with --schedule {}: {e}", self.schedule);
        }
        Ok(())
    }

    /// `--passes`: a cut of `--spp` the coordinator accepts.
    pub fn check_passes(&self) -> Result<()> {
        dray_core::passes::Passes::parse(&self.passes, self.spp)
            .map(drop)
            .map_err(|e| anyhow::anyhow!("--passes: {e}"))
    }

    /// `--exposure`: finite, within the coordinator's GetImage range.
    pub fn check_exposure(&self) -> Result<()> {
        if !self.exposure.is_finite() || self.exposure.abs() > MAX_EXPOSURE_STOPS {
            bail!(
                "--exposure {} is out of range (-{MAX_EXPOSURE_STOPS}..={MAX_EXPOSURE_STOPS} \
                 stops)",
                self.exposure
            );
        }
        Ok(())
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
            ray_cache: self.ray_cache.clone(),
            phm: self.phm.clone(),
            passes: self.passes.clone(),
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
            e.contains("\"bogus\"") && e.contains("image-plane, domain or dynamic"),
            "{e}"
        );
        assert!(parse_schedule("Dynamic").is_err());
        assert_eq!(parse_schedule(default_schedule()).as_deref(), Ok("dynamic"));
    }
}
