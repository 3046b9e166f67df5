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
use dray_scene::partition::memory::{MemoryPackages, is_memory_package};
use dray_scene::partition::{Aabb, DomainLayout, ResidentScene, load_resident, open_package};
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

/// Load what `worker_id` needs of the job and make its tracer: from the package
/// directory, or from `memory` when the package is an in-memory one of this process.
/// Blocking (reads files and builds BVHs).
pub fn build_tracer(
    setup: &JobSetup,
    worker_id: &str,
    memory: Option<&MemoryPackages>,
) -> Result<JobTracer, JobError> {
    let settings = settings(setup)?;
    let routing = setup.routing.as_ref().ok_or(JobError::Missing("routing"))?;
    let owned = owned_domains(routing, worker_id);
    if is_memory_package(&setup.package_path) {
        return memory_tracer(setup, settings, &owned, memory);
    }
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
    check_domain_count(package.domain_count(), setup)?;
    let bounds = package.layout().scene_bounds();
    let camera = job_camera(setup, &settings, package.cameras(), bounds)?;
    let counts: Vec<u64> = package
        .manifest()
        .domains
        .iter()
        .map(|d| d.triangles)
        .collect();
    let resident = load_resident(&package, &owned).map_err(|e| pkg_err(e.to_string()))?;
    Ok(tracer(
        resident,
        settings,
        camera,
        package.layout(),
        &counts,
        setup,
    ))
}

/// [`build_tracer`] for a package in this process's memory.
fn memory_tracer(
    setup: &JobSetup,
    settings: RenderSettings,
    owned: &[u32],
    memory: Option<&MemoryPackages>,
) -> Result<JobTracer, JobError> {
    let pkg_err = |message: String| JobError::Package {
        path: setup.package_path.clone(),
        message,
    };
    let package = memory
        .and_then(|m| m.get(&setup.package_path))
        .ok_or_else(|| {
            pkg_err(
                "it is held in the memory of the coordinator's process, and this worker runs in \
             another"
                    .into(),
            )
        })?;
    check_domain_count(package.domain_count(), setup)?;
    let layout = package.layout();
    let camera = job_camera(
        setup,
        &settings,
        &package.tables().cameras,
        layout.scene_bounds(),
    )?;
    let resident = package
        .resident(owned)
        .map_err(|e| pkg_err(e.to_string()))?;
    let counts = package.triangle_counts();
    Ok(tracer(resident, settings, camera, layout, &counts, setup))
}

/// The tracer over `resident`, walking rays with `layout` (`counts`: triangles per domain).
fn tracer(
    resident: ResidentScene,
    settings: RenderSettings,
    camera: Camera,
    layout: &DomainLayout,
    counts: &[u64],
    setup: &JobSetup,
) -> JobTracer {
    JobTracer::new(
        resident,
        settings,
        camera,
        layout.to_domain_tree(),
        layout.epsilon(),
        counts,
        setup.tile_size,
    )
}

/// The package must be cut as the coordinator said.
fn check_domain_count(found: u32, setup: &JobSetup) -> Result<(), JobError> {
    if found != setup.domain_count {
        return Err(JobError::Invalid(format!(
            "the package has {found} domains, the setup says {}",
            setup.domain_count
        )));
    }
    Ok(())
}

/// The job's camera: by index into the package's cameras, or framing its bounds.
fn job_camera(
    setup: &JobSetup,
    settings: &RenderSettings,
    cameras: &[Camera],
    bounds: Aabb,
) -> Result<Camera, JobError> {
    let spec = setup.spec.as_ref().ok_or(JobError::Missing("spec"))?;
    let aspect = settings.width as f32 / settings.height as f32;
    match spec.camera.as_deref() {
        Some(c) => {
            let i: usize = c.parse().map_err(|_| {
                JobError::Invalid(format!("camera {c:?} is not an index into the package"))
            })?;
            cameras.get(i).cloned().ok_or_else(|| {
                JobError::Invalid(format!(
                    "camera {i} does not exist (the package has {})",
                    cameras.len()
                ))
            })
        }
        None => Ok(Camera::framing(bounds.min, bounds.max, aspect)),
    }
}

#[cfg(test)]
mod tests {
    use dray_proto::v1::{DomainRoute, JobSpec, Rgb};
    use dray_scene::partition::LayoutSpec;
    use dray_scene::partition::memory::MemoryPackage;

    use super::*;

    fn setup(package_path: &str, domain_count: u32) -> JobSetup {
        JobSetup {
            job_id: "j".into(),
            spec: Some(JobSpec {
                width: 8,
                height: 8,
                spp: 1,
                integrator: "raycast".into(),
                max_depth: Some(2),
                ao_samples: Some(1),
                ..JobSpec::default()
            }),
            environment: Some(Rgb::default()),
            package_path: package_path.into(),
            domain_count,
            tile_size: 32,
            routing: Some(RoutingTable {
                routes: (0..domain_count)
                    .map(|d| DomainRoute {
                        domain: d,
                        worker_id: "w".into(),
                    })
                    .collect(),
                ..RoutingTable::default()
            }),
            ..JobSetup::default()
        }
    }

    #[test]
    fn an_in_memory_package_loads_only_in_its_own_process() {
        let scene = dray_scene::load("cornell").unwrap();
        let store = MemoryPackages::default();
        let name = store.insert(MemoryPackage::new(scene, &LayoutSpec::Kd(3)).unwrap());
        let s = setup(&name, 3);
        let t = build_tracer(&s, "w", Some(&store)).expect("loads from the store");
        drop(t);
        let err = build_tracer(&s, "w", None)
            .err()
            .expect("no store")
            .to_string();
        assert!(err.contains(&name) && err.contains("another"), "{err}");
        let wrong = build_tracer(&setup(&name, 4), "w", Some(&store))
            .err()
            .expect("domain count mismatch")
            .to_string();
        assert!(wrong.contains("3 domains"), "{wrong}");
        store.remove(&name);
        assert!(build_tracer(&s, "w", Some(&store)).is_err());
    }
}
