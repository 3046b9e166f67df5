//! Where a job's domains come from ([`DomainSource`]): a package on disk (its domain
//! files fetched from the coordinator first when it is not on this disk) or a package
//! in this process's memory. Both share what every domain of the job needs, read once
//! per job, and build a domain ready to trace when the domain store loads it.
//!
//! Apart from [`crate::plan`] so that the tracer's tests can make domains without
//! planning a job (the plan builds the tracer: the two would import each other).

use std::sync::Arc;

use dray_core::effects::Effect;
use dray_core::integrator::RenderSettings;
use dray_core::light_sampler::LightSampler;
use dray_core::scene::Scene;
use dray_scene::partition::memory::MemoryPackage;
use dray_scene::partition::resident::{assemble, resident_bytes};
use dray_scene::partition::{Aabb, DomainMesh, Package};

use crate::domain_store::{DomainSource, LoadedDomain};
use crate::package_fetch::RemotePackage;

/// The domains of `package` on disk, loaded one at a time for `settings` (the
/// emitters and textures are read now, once).
pub fn package_domains(
    package: Package,
    settings: &RenderSettings,
) -> dray_scene::error::Result<Arc<dyn DomainSource>> {
    domains_of(package, settings, None)
}

/// [`package_domains`], each domain file fetched into `remote` before it is read when
/// the package is fetched from the coordinator.
pub(crate) fn domains_of(
    package: Package,
    settings: &RenderSettings,
    remote: Option<RemotePackage>,
) -> dray_scene::error::Result<Arc<dyn DomainSource>> {
    let bounds = package.layout().scene_bounds();
    let emitters = package.load_emitters()?;
    let tables = package.tables()?;
    Ok(Arc::new(PackageDomains {
        sizes: package
            .manifest()
            .domains
            .iter()
            .map(|d| (d.vertices, d.triangles, d.uvs2))
            .collect(),
        package,
        shared: SharedParts::new(tables, emitters, bounds, settings),
        remote,
    }))
}

/// The domains of an in-memory `package`, copied out one at a time for `settings`.
pub fn memory_domains(
    package: Arc<MemoryPackage>,
    settings: &RenderSettings,
) -> Arc<dyn DomainSource> {
    let b = package.layout().scene_bounds();
    let shared = SharedParts::new(
        package.tables().clone(),
        package.emitters().clone(),
        b,
        settings,
    );
    Arc::new(MemoryDomains { package, shared })
}

/// What every domain of a job shares: the scene's tables (materials, textures, lights,
/// cameras) and its emitters, read once per job.
struct SharedParts {
    tables: Scene,
    emitters: DomainMesh,
    bounds: (glam::Vec3, glam::Vec3),
    emission: bool,
}

impl SharedParts {
    fn new(tables: Scene, emitters: DomainMesh, bounds: Aabb, settings: &RenderSettings) -> Self {
        SharedParts {
            tables,
            emitters,
            bounds: (bounds.min, bounds.max),
            emission: settings.effects.contains(Effect::Emission),
        }
    }

    /// Domain `part` ready to trace: merged with the emitters in scene order, its BVH
    /// built, its light table made.
    fn finish(&self, part: DomainMesh) -> LoadedDomain {
        let domain = part.domain;
        let resident = assemble(
            self.tables.clone(),
            self.bounds,
            vec![part],
            self.emitters.clone(),
        );
        let lights = Arc::new(LightSampler::with_bounds(
            &resident.scene,
            self.emission,
            resident.bounds,
        ));
        LoadedDomain {
            domain,
            bytes: resident.bytes(),
            resident,
            lights,
        }
    }

    /// [`SharedParts::finish`]'s size for a domain of `vertices` and `triangles`, `uvs2`
    /// when its file has a second UV set.
    fn estimate(&self, vertices: u64, triangles: u64, uvs2: bool) -> u64 {
        let e = &self.emitters.mesh;
        resident_bytes(
            vertices + e.positions.len() as u64,
            triangles + e.indices.len() as u64,
            triangles,
            uvs2 || !e.uvs2.is_empty(),
        )
    }
}

/// A job's domains in a package directory.
struct PackageDomains {
    package: Package,
    /// (vertices, triangles, second UV set) per domain, from the manifest.
    sizes: Vec<(u64, u64, bool)>,
    shared: SharedParts,
    /// Where the files come from when the package is fetched from the coordinator.
    remote: Option<RemotePackage>,
}

impl DomainSource for PackageDomains {
    fn estimate_bytes(&self, d: u32) -> u64 {
        let (v, t, uvs2) = self.sizes.get(d as usize).copied().unwrap_or_default();
        self.shared.estimate(v, t, uvs2)
    }

    fn load(&self, d: u32) -> Result<LoadedDomain, String> {
        if let Some(r) = &self.remote {
            // Fetched when first loaded: a worker downloads only the domains it traces.
            r.fetch_domain(&self.package, d)
                .map_err(|e| e.to_string())?;
        }
        let part = self.package.load_domain(d).map_err(|e| e.to_string())?;
        Ok(self.shared.finish(part))
    }
}

/// A job's domains in an in-memory package of this process.
struct MemoryDomains {
    package: Arc<MemoryPackage>,
    shared: SharedParts,
}

impl DomainSource for MemoryDomains {
    fn estimate_bytes(&self, d: u32) -> u64 {
        self.package.domain_mesh(d).map_or(0, |m| {
            self.shared.estimate(
                m.mesh.positions.len() as u64,
                m.triangle_count() as u64,
                !m.mesh.uvs2.is_empty(),
            )
        })
    }

    fn load(&self, d: u32) -> Result<LoadedDomain, String> {
        let part = self.package.domain_mesh(d).cloned().ok_or_else(|| {
            format!(
                "domain {d} is not in the package ({} domains)",
                self.package.domain_count()
            )
        })?;
        Ok(self.shared.finish(part))
    }
}
