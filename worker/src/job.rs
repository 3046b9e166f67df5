//! Turning the coordinator's `JobSetup` into a [`JobTracer`]: open the package, check it
//! is the one the coordinator partitioned, load the owned domains and the emitters, and
//! rebuild the render settings from the resolved spec.
//!
//! The coordinator resolves every default before it sends the setup, so this file only
//! reads fields; any disagreement (another manifest, an unknown integrator or effect) is
//! an error that fails the job rather than a different image.

use std::path::Path;

use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{IntegratorKind, RenderSettings};
use dray_proto::v1::{JobSetup, RoutingTable};
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::{load_resident, open_package};
use glam::Vec3;

use crate::tracer::JobTracer;

/// Why a job could not be set up on this worker.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("job setup is missing {0}")]
    Missing(&'static str),
    #[error("cannot read the package {path}: {message}")]
    Package { path: String, message: String },
    #[error(
        "the package at {path} is not the one the coordinator wrote (manifest checksum {found}, expected {expected}); is the work directory shared?"
    )]
    Checksum {
        path: String,
        found: String,
        expected: String,
    },
    #[error("job setup: {0}")]
    Invalid(String),
}

/// The domains `worker_id` owns in `routing`, ascending.
pub fn owned_domains(routing: &RoutingTable, worker_id: &str) -> Vec<u32> {
    let mut owned: Vec<u32> = routing
        .routes
        .iter()
        .filter(|r| r.worker_id == worker_id)
        .map(|r| r.domain)
        .collect();
    owned.sort_unstable();
    owned.dedup();
    owned
}

/// The render settings a setup describes.
pub fn settings(setup: &JobSetup) -> Result<RenderSettings, JobError> {
    let spec = setup.spec.as_ref().ok_or(JobError::Missing("spec"))?;
    let env = setup
        .environment
        .as_ref()
        .ok_or(JobError::Missing("environment"))?;
    let integrator = if spec.integrator.is_empty() {
        IntegratorKind::Path
    } else {
        IntegratorKind::from_name(&spec.integrator)
            .ok_or_else(|| JobError::Invalid(format!("unknown integrator {:?}", spec.integrator)))?
    };
    let mut effects = Effects::NONE;
    for name in &setup.effects {
        let e = Effect::from_name(name)
            .ok_or_else(|| JobError::Invalid(format!("unknown effect {name:?}")))?;
        effects.set(e, true);
    }
    if spec.width == 0 || spec.height == 0 || spec.spp == 0 {
        return Err(JobError::Invalid(format!(
            "image {}x{} at {} spp is empty",
            spec.width, spec.height, spec.spp
        )));
    }
    Ok(RenderSettings {
        width: spec.width,
        height: spec.height,
        spp: spec.spp,
        integrator,
        max_depth: spec.max_depth.ok_or(JobError::Missing("spec.max_depth"))?,
        seed: spec.seed,
        environment: Vec3::new(env.r, env.g, env.b),
        effects,
        ao_samples: spec
            .ao_samples
            .ok_or(JobError::Missing("spec.ao_samples"))?,
        ao_distance: spec.ao_distance.unwrap_or(f32::INFINITY),
    })
}

/// Load what `worker_id` needs of the job and make its tracer. Blocking (reads files
/// and builds BVHs).
pub fn build_tracer(setup: &JobSetup, worker_id: &str) -> Result<JobTracer, JobError> {
    let settings = settings(setup)?;
    let routing = setup.routing.as_ref().ok_or(JobError::Missing("routing"))?;
    let owned = owned_domains(routing, worker_id);
    let dir = Path::new(&setup.package_path);
    let pkg_err = |message: String| JobError::Package {
        path: setup.package_path.clone(),
        message,
    };
    let manifest_bytes =
        std::fs::read(dir.join(MANIFEST_FILE)).map_err(|e| pkg_err(e.to_string()))?;
    let found = to_hex(checksum(&manifest_bytes));
    if found != setup.package_checksum {
        return Err(JobError::Checksum {
            path: setup.package_path.clone(),
            found,
            expected: setup.package_checksum.clone(),
        });
    }
    let package = open_package(dir).map_err(|e| pkg_err(e.to_string()))?;
    if package.domain_count() != setup.domain_count {
        return Err(JobError::Invalid(format!(
            "the package has {} domains, the setup says {}",
            package.domain_count(),
            setup.domain_count
        )));
    }
    let spec = setup.spec.as_ref().ok_or(JobError::Missing("spec"))?;
    let aspect = settings.width as f32 / settings.height as f32;
    let bounds = package.layout().scene_bounds();
    let camera = match spec.camera.as_deref() {
        Some(c) => {
            let i: usize = c.parse().map_err(|_| {
                JobError::Invalid(format!("camera {c:?} is not an index into the package"))
            })?;
            package.cameras().get(i).cloned().ok_or_else(|| {
                JobError::Invalid(format!(
                    "camera {i} does not exist (the package has {})",
                    package.cameras().len()
                ))
            })?
        }
        None => Camera::framing(bounds.min, bounds.max, aspect),
    };
    let counts: Vec<u64> = package
        .manifest()
        .domains
        .iter()
        .map(|d| d.triangles)
        .collect();
    let layout = package.layout().clone();
    let resident = load_resident(&package, &owned).map_err(|e| pkg_err(e.to_string()))?;
    Ok(JobTracer::new(
        resident,
        settings,
        camera,
        layout.to_domain_tree(),
        layout.epsilon(),
        &counts,
        setup.tile_size,
    ))
}
