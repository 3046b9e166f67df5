//! The part of a scene one worker holds: its own domains, every emitter, and the scene's
//! small tables (materials, textures, lights, cameras).
//!
//! A worker traces rays only inside the domains it owns, but shading a hit there needs
//! more than those triangles: next-event estimation samples emissive triangles anywhere
//! in the scene, and the light powers read the whole scene's bounds. So the resident
//! scene is the union of the owned domains and the package's emitters, **in scene order**
//! (ascending global id), with each triangle stored once however many of the loaded
//! domains it overlaps. Scene order matters twice: the light sampler lists emitters in
//! mesh order, so its table equals the whole scene's; and BVH distance ties go to the
//! lower index, which is then the lower global id, as in one BVH over the whole scene.
//! Together with [`dray_core::integrator::Integrator::partial`] this makes a worker's
//! results bit for bit those of the single-process renderer.

use dray_core::bvh::Accel;
use dray_core::scene::{Mesh, Scene};
use glam::Vec3;

use super::DomainMesh;
use super::package::Package;
use crate::error::Result;

/// One owned domain, ready to trace.
pub struct ResidentDomain {
    /// The domain index in the package.
    pub domain: u32,
    /// Its BVH; hits report triangle indices into [`ResidentScene::scene`]'s mesh.
    pub accel: Accel,
    /// Triangles in the domain.
    pub triangles: usize,
}

/// What a worker holds of a scene.
pub struct ResidentScene {
    /// The owned domains' triangles and the emitters, in scene order, with the whole
    /// scene's materials, textures, lights, cameras and environment.
    pub scene: Scene,
    /// Scene-wide id of each triangle of `scene.mesh`, ascending.
    pub global_ids: Vec<u32>,
    /// The whole scene's bounds (not those of the resident triangles).
    pub bounds: (Vec3, Vec3),
    /// The owned domains, in the order they were asked for.
    pub domains: Vec<ResidentDomain>,
}

impl ResidentScene {
    /// The resident domain `d`, if owned here.
    pub fn domain(&self, d: u32) -> Option<&ResidentDomain> {
        self.domains.iter().find(|r| r.domain == d)
    }

    /// Bytes held by triangles and BVHs, roughly: what a memory budget counts.
    pub fn bytes(&self) -> u64 {
        let m = &self.scene.mesh;
        let bvh: u64 = self.domains.iter().map(|d| d.triangles as u64).sum();
        resident_bytes(m.positions.len() as u64, m.indices.len() as u64, bvh)
    }
}

/// Bytes a resident scene of `vertices` and `triangles` (merged mesh) with BVHs over
/// `bvh_triangles` takes, roughly; [`ResidentScene::bytes`] and the estimates a worker
/// makes from a manifest before loading both use it, so they agree.
pub fn resident_bytes(vertices: u64, triangles: u64, bvh_triangles: u64) -> u64 {
    // Position, normal, tangent, uv per vertex; indices, material and global id per
    // triangle; each BVH keeps its own copy of its triangles (three corners) plus nodes.
    let vertex = 12 + 12 + 16 + 8;
    let per_tri = 12 + 4 + 4;
    vertices * vertex + triangles * per_tri + bvh_triangles * 64
}

/// Load `owned` domains and the emitters of `package` (checking every file) and
/// assemble them with [`assemble`].
pub fn load_resident(package: &Package, owned: &[u32]) -> Result<ResidentScene> {
    let parts = owned
        .iter()
        .map(|&d| package.load_domain(d))
        .collect::<Result<Vec<_>>>()?;
    let emitters = package.load_emitters()?;
    let b = package.layout().scene_bounds();
    let scene = package.tables()?;
    Ok(assemble(scene, (b.min, b.max), parts, emitters))
}

/// Merge `parts` (owned domains) and `emitters` into `tables` (a scene with no mesh) and
/// build one BVH per part. `bounds` are the whole scene's.
pub fn assemble(
    tables: Scene,
    bounds: (Vec3, Vec3),
    parts: Vec<DomainMesh>,
    emitters: DomainMesh,
) -> ResidentScene {
    let sources: Vec<&DomainMesh> = parts.iter().chain(std::iter::once(&emitters)).collect();
    // (global id, source, triangle in source), sorted by global id, each id once.
    let mut order: Vec<(u32, u32, u32)> = sources
        .iter()
        .enumerate()
        .flat_map(|(s, m)| {
            m.global_ids
                .iter()
                .enumerate()
                .map(move |(t, &g)| (g, s as u32, t as u32))
        })
        .collect();
    order.sort_unstable();
    order.dedup_by_key(|e| e.0);

    let mut mesh = Mesh::default();
    let mut global_ids = Vec::with_capacity(order.len());
    // Per source, its vertices' indices in the merged mesh (u32::MAX: not copied yet).
    let mut remap: Vec<Vec<u32>> = sources
        .iter()
        .map(|m| vec![u32::MAX; m.mesh.positions.len()])
        .collect();
    mesh.indices.reserve_exact(order.len());
    mesh.material.reserve_exact(order.len());
    for &(g, s, t) in &order {
        let src = &sources[s as usize].mesh;
        let map = &mut remap[s as usize];
        let tri = src.indices[t as usize].map(|v| {
            let slot = &mut map[v as usize];
            if *slot == u32::MAX {
                *slot = mesh.positions.len() as u32;
                mesh.positions.push(src.positions[v as usize]);
                mesh.normals.push(src.normals[v as usize]);
                mesh.tangents.push(src.tangents[v as usize]);
                mesh.uvs.push(src.uvs[v as usize]);
            }
            *slot
        });
        mesh.indices.push(tri);
        mesh.material.push(src.material[t as usize]);
        global_ids.push(g);
    }
    drop(remap);

    let domains = parts
        .iter()
        .map(|p| {
            // Every global id of the part is in the merged list, by construction.
            let local: Vec<u32> = p
                .global_ids
                .iter()
                .map(|g| global_ids.binary_search(g).map_or(u32::MAX, |i| i as u32))
                .collect();
            ResidentDomain {
                domain: p.domain,
                accel: Accel::build_with_ids(&p.mesh, Some(&local)),
                triangles: p.triangle_count(),
            }
        })
        .collect();
    ResidentScene {
        scene: Scene { mesh, ..tables },
        global_ids,
        bounds,
        domains,
    }
}

/// The resident scene a worker owning `owned` would load from a package of `scene` cut
/// by `layout`, made in memory: for tests, with the same bits as [`load_resident`] gives.
pub fn resident_in_memory(
    scene: &Scene,
    layout: &super::DomainLayout,
    owned: &[u32],
) -> Result<ResidentScene> {
    super::memory::MemoryPackage::with_layout(scene.clone(), layout.clone())?.resident(owned)
}

/// All domains of `scene` cut by `spec`, each with its own BVH over scene-wide triangle
/// ids, walked front to back: the embedded stand-in for workers owning domains, with the
/// same answers as one BVH over the whole scene.
pub fn domain_set(scene: &Scene, spec: &super::LayoutSpec) -> Result<dray_core::trace::DomainSet> {
    let layout = super::DomainLayout::for_source(scene, spec)?;
    let parts = super::partition_in_memory(scene, &layout)?;
    let mut accels: Vec<Option<Accel>> = (0..layout.domain_count()).map(|_| None).collect();
    for part in &parts {
        if let Some(slot) = accels.get_mut(part.domain as usize) {
            *slot = Some(Accel::build_with_ids(&part.mesh, Some(&part.global_ids)));
        }
    }
    Ok(dray_core::trace::DomainSet {
        tree: layout.to_domain_tree(),
        accels: accels
            .into_iter()
            .map(|a| a.unwrap_or_else(|| Accel::build(&Mesh::default())))
            .collect(),
        pad: layout.epsilon(),
    })
}
