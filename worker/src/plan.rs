//! Turning the coordinator's `JobSetup` into a [`JobPlan`]: open the package, check it
//! is the one the coordinator partitioned, read what every domain shares (the emitters,
//! materials and textures), rebuild the render settings from the resolved spec, and say
//! how to load each domain on demand ([`DomainSource`]).
//!
//! The coordinator resolves every default before it sends the setup, so this file only
//! reads fields; any disagreement (another manifest, an unknown integrator or effect) is
//! an error that fails the job rather than a different image. The cache knobs are
//! parsed by [`dray_cache::settings`], as the coordinator and the cache hosts parse
//! them.

use std::path::Path;
use std::sync::Arc;

use dray_cache::settings::{CoarseSampling, DEFAULT_PHM_MERGE, WallSettings};
use dray_core::aov::AovSet;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{IntegratorKind, RenderSettings};
use dray_core::light_samples::LightSamples;
use dray_core::lighting::Lighting;
use dray_core::sun::Sun;
use dray_core::wall::PhmBins;
use dray_proto::v1::JobSetup;
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::memory::{MemoryPackages, is_memory_package};
use dray_scene::partition::{Aabb, DomainLayout, Package, open_package};
use glam::Vec3;

use crate::domain_sources::domains_of;
pub use crate::domain_sources::{memory_domains, package_domains};
use crate::domain_store::{Content, Contents, DomainSource};
pub use crate::job_error::JobError;
use crate::package_fetch::PackageFetcher;
use crate::tracer::JobTracer;

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
        lighting: lighting(spec)?,
        clamp_indirect: spec
            .clamp_indirect
            .map(dray_core::clamp::check_limit)
            .transpose()
            .map_err(|e| JobError::Invalid(format!("clamp_indirect: {e}")))?,
        aovs: AovSet::parse(&spec.aovs).map_err(|e| JobError::Invalid(format!("aovs: {e}")))?,
    })
}

/// The lights the spec adds, as the coordinator resolved them (every default filled
/// in, so nothing here can pick another value than the coordinator's renderer did),
/// and the samples each light takes per hit (`spec.light_samples`, absent meaning 1 as
/// for the coordinator). The environment map, which needs its file, is added by
/// [`plan_job_with`] (`crate::env_map`).
fn lighting(spec: &dray_proto::v1::JobSpec) -> Result<Lighting, JobError> {
    let samples = LightSamples::from_spec(spec.light_samples)
        .map_err(|e| JobError::Invalid(format!("light_samples: {e}")))?;
    let Some(sun) = spec.lighting.as_ref().and_then(|l| l.sun.as_ref()) else {
        return Ok(Lighting {
            samples,
            ..Lighting::default()
        });
    };
    let sun = Sun::new(
        sun.azimuth_deg,
        sun.elevation_deg,
        sun.irradiance
            .ok_or(JobError::Missing("spec.lighting.sun.irradiance"))?,
        sun.angular_diameter_deg
            .ok_or(JobError::Missing("spec.lighting.sun.angular_diameter_deg"))?,
    )
    .map_err(|e| JobError::Invalid(format!("lighting.sun: {e}")))?;
    // The coordinator fills in the colour with the sun; absent means white (as the
    // spec says), so a coordinator from before colours existed renders the same.
    let color = spec
        .sun_color
        .as_ref()
        .map_or(glam::Vec3::ONE, |c| glam::Vec3::new(c.r, c.g, c.b));
    let sun = sun
        .with_color(color)
        .map_err(|e| JobError::Invalid(format!("sun_color: {e}")))?;
    Ok(Lighting {
        sun: Some(sun),
        env_map: None,
        samples,
    })
}

/// A job's tracer and where its domains come from, made from its setup. Reads the
/// manifest (and, for a package on disk, the emitters and textures, which every domain
/// shares) but no domain: those are loaded on demand by the domain store.
pub struct JobPlan {
    pub tracer: JobTracer,
    pub source: Arc<dyn DomainSource>,
    /// What its loaded domains are made of ([`DomainStore::open`]), domain by domain:
    /// jobs with equal content share resident domains, and a domain equal in two
    /// packages (the frames of an animation, where it does not move) is loaded once.
    ///
    /// [`DomainStore::open`]: crate::DomainStore::open
    pub content: Contents,
    /// Sender placement: outcomes gathered before a hit-map merge (`PhmSettings.merge`,
    /// see [`crate::map_merge`]).
    pub merge_every: u32,
}

/// The content key of a package's domains loaded for `settings`: the package's
/// identity (the manifest checksum for a package on disk, which covers every domain
/// file; the process-unique name of an in-memory one) and the one setting that
/// changes a loaded domain (whether emitters are lights).
fn content(identity: &str, settings: &RenderSettings) -> Content {
    let emission = settings.effects.contains(Effect::Emission);
    format!("{identity} emission={emission}").into()
}

/// The contents of the domains of a package on disk, one per domain
/// ([`dray_scene::partition::Manifest::domain_contents`]): two packages cut from frames
/// where a domain's triangles did not move give it the same content.
fn disk_contents(package: &Package, found: &str, settings: &RenderSettings) -> Contents {
    let whole = content(found, settings);
    match package.manifest().domain_contents() {
        Ok(domains) => Contents::per_domain(
            whole,
            domains
                .iter()
                .map(|c| content(&format!("domain {c}"), settings))
                .collect(),
        ),
        // Not per domain, then: the package's domains are its own.
        Err(_) => Contents::package(whole),
    }
}

/// Open the job's package (a directory, or an in-memory package of this process in
/// `memory`) and make its tracer. Blocking (reads files).
pub fn plan_job(setup: &JobSetup, memory: Option<&MemoryPackages>) -> Result<JobPlan, JobError> {
    plan_job_with(setup, memory, None)
}

/// [`plan_job`], fetching the package from the coordinator with `fetcher` when it is
/// not on this disk ([`PackageFetcher::should_fetch`]): the manifest and the files every
/// domain shares now, each domain file when the domain is first loaded. Blocking (reads
/// files, waits for the coordinator).
pub fn plan_job_with(
    setup: &JobSetup,
    memory: Option<&MemoryPackages>,
    fetcher: Option<&Arc<PackageFetcher>>,
) -> Result<JobPlan, JobError> {
    let mut settings = settings(setup)?;
    let walls = walls(setup)?;
    settings.lighting.env_map = crate::env_map::job_env_map(setup, memory, fetcher)?;
    if is_memory_package(&setup.package_path) {
        return memory_plan(setup, settings, &walls, memory);
    }
    let pkg_err = |message: String| JobError::Package {
        path: setup.package_path.clone(),
        message,
    };
    let remote = match fetcher {
        Some(f) if f.should_fetch(Path::new(&setup.package_path), &setup.package_checksum) => {
            let r = f
                .open(&setup.job_id, &setup.package_checksum)
                .map_err(|e| pkg_err(e.to_string()))?;
            tracing::info!(job = %setup.job_id, cache = %r.dir().display(), "fetching the package from the coordinator");
            Some(r)
        }
        _ => None,
    };
    let dir = remote
        .as_ref()
        .map_or(Path::new(&setup.package_path), |r| r.dir());
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
    if let Some(r) = &remote {
        r.fetch_shared(&package)
            .map_err(|e| pkg_err(e.to_string()))?;
    }
    check_domain_count(package.domain_count(), setup)?;
    let bounds = package.layout().scene_bounds();
    let camera = job_camera(setup, &settings, package.cameras(), bounds)?;
    let counts: Vec<u64> = package
        .manifest()
        .domains
        .iter()
        .map(|d| d.triangles)
        .collect();
    let tracer = tracer(
        settings.clone(),
        camera,
        package.layout(),
        &counts,
        setup,
        &walls,
    )?;
    let contents = disk_contents(&package, &found, &settings);
    let source = domains_of(package, &settings, remote).map_err(|e| pkg_err(e.to_string()))?;
    Ok(JobPlan {
        content: contents,
        tracer,
        source,
        merge_every: merge_every(&walls),
    })
}

/// [`plan_job`] for a package in this process's memory.
fn memory_plan(
    setup: &JobSetup,
    settings: RenderSettings,
    walls: &WallSettings,
    memory: Option<&MemoryPackages>,
) -> Result<JobPlan, JobError> {
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
    let counts = package.triangle_counts();
    let tracer = tracer(settings.clone(), camera, layout, &counts, setup, walls)?;
    let domains = package
        .domain_contents()
        .iter()
        .map(|c| content(&format!("memory domain {c}"), &settings))
        .collect();
    Ok(JobPlan {
        content: Contents::per_domain(content(&setup.package_path, &settings), domains),
        tracer,
        source: memory_domains(package, &settings),
        merge_every: merge_every(walls),
    })
}

/// The job's tracer, walking rays with `layout` (`counts`: triangles per domain).
fn tracer(
    settings: RenderSettings,
    camera: Camera,
    layout: &DomainLayout,
    counts: &[u64],
    setup: &JobSetup,
    walls: &WallSettings,
) -> Result<JobTracer, JobError> {
    let tracer = plain_tracer(settings, camera, layout, counts, setup, walls)?;
    if setup.passes_ahead == 0 {
        return Ok(tracer);
    }
    let tags = pass_tags(setup)?;
    if tracer.tile_count() >= crate::tracer::pass_tag::MAX_TAGGED_TILES {
        return Err(JobError::Invalid(format!(
            "passes_ahead with {} tiles: a job tracing passes ahead has fewer than {}",
            tracer.tile_count(),
            crate::tracer::pass_tag::MAX_TAGGED_TILES
        )));
    }
    Ok(tracer.with_pass_tags(tags))
}

/// The passes of a job tracing them ahead (`JobSetup.passes_ahead`): at least two, at
/// most 256.
fn pass_tags(setup: &JobSetup) -> Result<crate::tracer::pass_tag::PassTags, JobError> {
    let spec = setup.spec.as_ref();
    let spp = spec.map_or(1, |s| s.spp);
    let passes = spec.map_or("", |s| s.passes.as_str());
    let cut = dray_core::passes::Passes::parse(passes, spp)
        .map_err(|e| JobError::Invalid(format!("passes: {e}")))?;
    crate::tracer::pass_tag::PassTags::new(cut.ranges(spp)).ok_or_else(|| {
        JobError::Invalid(format!(
            "passes_ahead {} with passes {passes:?} at {spp} spp: tracing ahead needs 2 to \
             256 passes",
            setup.passes_ahead
        ))
    })
}

fn plain_tracer(
    settings: RenderSettings,
    camera: Camera,
    layout: &DomainLayout,
    counts: &[u64],
    setup: &JobSetup,
    walls: &WallSettings,
) -> Result<JobTracer, JobError> {
    let sampling = CoarseSampling::from_proto(
        setup
            .spec
            .as_ref()
            .map_or("", |s| s.coarse_sampling.as_str()),
    )
    .map_err(|e| JobError::Invalid(e.to_string()))?;
    // Without hit maps no ray consults one, and the binning is the default's.
    let bins = walls.phm.as_ref().map_or(
        PhmBins::new(
            dray_cache::settings::DEFAULT_PHM_RES,
            dray_cache::settings::DEFAULT_PHM_DIRS,
        ),
        |p| p.bins,
    );
    Ok(JobTracer::new(
        settings,
        camera,
        layout.to_domain_tree(),
        layout.epsilon(),
        counts,
        setup.tile_size,
    )
    .with_cached_kinds(walls.cached_kinds())
    .with_phm(walls.phm_kinds(), bins)
    .with_fill(walls.ray_cache.as_ref().is_none_or(|c| c.fill))
    .with_coarse(walls.coarse(), sampling == CoarseSampling::Random))
}

/// The job's ray-cache and hit-map knobs (none without walls), as the coordinator
/// resolved them.
fn walls(setup: &JobSetup) -> Result<WallSettings, JobError> {
    let spec = setup.spec.as_ref();
    WallSettings::from_proto(
        spec.and_then(|s| s.ray_cache.as_ref()),
        spec.and_then(|s| s.phm.as_ref()),
    )
    .map_err(|e| JobError::Invalid(e.to_string()))
}

/// Outcomes gathered before a hit-map merge (the default without maps, where none is
/// ever gathered).
fn merge_every(walls: &WallSettings) -> u32 {
    walls.phm.as_ref().map_or(DEFAULT_PHM_MERGE, |p| p.merge)
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

/// The camera of a resolved `JobSpec.view` (the coordinator resolved it:
/// `dray_coordinator::view::resolve`), read as the coordinator reads it
/// (`dray_coordinator::view::camera_of_resolved`), so both build the same camera.
fn view_camera(v: &dray_proto::v1::CameraSpec) -> Result<Camera, String> {
    let get = |name: &str, p: Option<&dray_proto::v1::Vec3>| {
        p.map(|p| Vec3::new(p.x, p.y, p.z))
            .ok_or(format!("{name}: not resolved"))
    };
    let view = dray_core::view::View::from_resolved(
        get("look_from", v.look_from.as_ref())?,
        get("look_at", v.look_at.as_ref())?,
        get("up", v.up.as_ref())?,
        v.fov.ok_or("fov: not resolved")?,
        v.orthographic,
        &v.aperture,
        v.focus_distance,
    )
    .map_err(|e| e.to_string())?;
    Ok(view.camera())
}

/// The job's camera: from the spec's resolved view, by index into the package's
/// cameras, or framing its bounds.
fn job_camera(
    setup: &JobSetup,
    settings: &RenderSettings,
    cameras: &[Camera],
    bounds: Aabb,
) -> Result<Camera, JobError> {
    let spec = setup.spec.as_ref().ok_or(JobError::Missing("spec"))?;
    let aspect = settings.width as f32 / settings.height as f32;
    if let Some(v) = &spec.view {
        return view_camera(v).map_err(|e| JobError::Invalid(format!("view.{e}")));
    }
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
    use dray_proto::v1::{DomainRoute, JobSpec, Rgb, RoutingTable};
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
        let plan = plan_job(&s, Some(&store)).expect("plans from the store");
        let d = plan.source.load(1).expect("loads a domain");
        assert_eq!(d.domain, 1);
        assert_eq!(d.resident.domains.len(), 1);
        assert!(d.bytes > 0 && d.bytes <= plan.source.estimate_bytes(1));
        assert!(plan.source.load(3).is_err(), "no domain 3");
        drop(plan);
        let err = plan_job(&s, None).err().expect("no store").to_string();
        assert!(err.contains(&name) && err.contains("another"), "{err}");
        let wrong = plan_job(&setup(&name, 4), Some(&store))
            .err()
            .expect("domain count mismatch")
            .to_string();
        assert!(wrong.contains("3 domains"), "{wrong}");
        store.remove(&name);
        assert!(plan_job(&s, Some(&store)).is_err());
    }

    /// `spec.light_samples` reaches the settings with and without a sun; absent means
    /// one sample; out of range fails the job naming the field.
    #[test]
    fn light_samples_reach_the_settings_and_absent_means_one() {
        use dray_proto::v1::{LightingSpec, SunSpec};
        let samples = |n: Option<u32>, sun: bool| {
            let mut s = setup("", 1);
            let spec = s.spec.as_mut().expect("spec");
            spec.light_samples = n;
            if sun {
                spec.lighting = Some(LightingSpec {
                    sun: Some(SunSpec {
                        azimuth_deg: 10.0,
                        elevation_deg: 30.0,
                        irradiance: Some(1.0),
                        angular_diameter_deg: Some(0.53),
                    }),
                    ..LightingSpec::default()
                });
            }
            settings(&s).map(|st| (st.lighting.samples.get(), st.lighting.sun.is_some()))
        };
        for sun in [false, true] {
            assert_eq!(samples(None, sun).expect("absent"), (1, sun));
            assert_eq!(samples(Some(8), sun).expect("8"), (8, sun));
            let e = samples(Some(0), sun).expect_err("0").to_string();
            assert!(e.contains("light_samples") && e.contains("1..=256"), "{e}");
        }
    }
}
