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
        resident_bytes(
            m.positions.len() as u64,
            m.indices.len() as u64,
            bvh,
            !m.uvs2.is_empty(),
        )
    }
}

/// Bytes a resident scene of `vertices` and `triangles` (merged mesh) with BVHs over
/// `bvh_triangles` takes, roughly, `uvs2` when its mesh keeps a second UV set;
/// [`ResidentScene::bytes`] and the estimates a worker makes from a manifest before
/// loading both use it, so they agree.
pub fn resident_bytes(vertices: u64, triangles: u64, bvh_triangles: u64, uvs2: bool) -> u64 {
    // Position, normal, tangent, uv (and the second uv) per vertex; indices, material
    // and global id per triangle; each BVH keeps its own copy of its triangles (three
    // corners, 48 bytes), their ids (4) and its 256-byte nodes (about 26 bytes a
    // triangle: `Accel::bytes` measured 77-79 bytes a triangle on Lucy and a
    // 1.3M-triangle gyroid).
    let vertex = 12 + 12 + 16 + 8 + if uvs2 { 8 } else { 0 };
    let per_tri = 12 + 4 + 4;
    vertices * vertex + triangles * per_tri + bvh_triangles * 80
}

/// What a domain's load holds at its peak, in hundredths of the domain's resident size
/// ([`resident_bytes`]): the resident domain itself plus what its BVH build holds beside
/// it for a moment. The peak is the 8-wide collapse: the binary tree (two 48-byte nodes a
/// triangle) and the collapse's decisions (8 bytes a node) beside the mesh, 1.53 times
/// the resident size at most on benches/passes.sh's gyroid (1.51 on the regression
/// guard's), measured by `worker/tests/load_peak.rs`, which fails if a load peaks above
/// it (docs/history/2026-11-29-passes-under-a-budget.md). Reading the domain file holds
/// less (its bytes and the mesh decoded from them).
pub const LOAD_PEAK_PERCENT: u64 = 155;

/// Bytes to make room for before loading a domain of `resident` bytes (see
/// [`LOAD_PEAK_PERCENT`]): the worker's store reserves it, and the scheduler's count of
/// the domains a worker can hold leaves room for one such load beside the others.
pub fn load_reserve(resident: u64) -> u64 {
    (resident / 100)
        .saturating_mul(LOAD_PEAK_PERCENT)
        .saturating_add(resident % 100 * LOAD_PEAK_PERCENT / 100)
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
    mut parts: Vec<DomainMesh>,
    emitters: DomainMesh,
) -> ResidentScene {
    if merged_is_the_part(&parts, &emitters)
        && let Some(part) = parts.pop()
    {
        return whole_part(tables, bounds, part);
    }
    merge(tables, bounds, parts, emitters)
}

/// [`assemble`] in general: the union of the parts and the emitters, copied in scene
/// order.
fn merge(
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
                let uv2 = src.uvs2.get(v as usize).map(std::slice::from_ref);
                mesh.extend_uvs2(*slot as usize, uv2);
                let colour = src.colors.get(v as usize).map(std::slice::from_ref);
                mesh.extend_colors(*slot as usize, colour);
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

/// Whether [`assemble`]'s merge of `parts` and `emitters` would give back the one part's
/// triangles, in its order: one part whose global ids ascend strictly, with every emitter
/// among them. Then the part itself can be the resident scene, and a one-domain layout
/// (every embedded `dray render`) takes it as it is instead of copying the scene. Only
/// the vertex numbering may differ from the merge's (which numbers vertices by first
/// use), and no result depends on it: hits, shading and light sampling read a
/// triangle's corners, never its vertex indices. Every index must be in range, as the
/// merge (which would panic) requires too.
fn merged_is_the_part(parts: &[DomainMesh], emitters: &DomainMesh) -> bool {
    let [part] = parts else {
        return false;
    };
    let (ids, m) = (&part.global_ids, &part.mesh);
    let n = m.positions.len();
    ids.len() == m.indices.len()
        && m.material.len() == m.indices.len()
        && m.normals.len() == n
        && m.tangents.len() == n
        && m.uvs.len() == n
        && (m.colors.is_empty() || m.colors.len() == n)
        && (m.uvs2.is_empty() || m.uvs2.len() == n)
        && ids.windows(2).all(|w| w[0] < w[1])
        && emitters
            .global_ids
            .iter()
            .all(|g| ids.binary_search(g).is_ok())
        && m.indices.iter().flatten().all(|&v| (v as usize) < n)
}

/// [`assemble`] when [`merged_is_the_part`] holds: the part's mesh moves into the scene.
fn whole_part(tables: Scene, bounds: (Vec3, Vec3), part: DomainMesh) -> ResidentScene {
    // Every triangle's merged index is its index in the part: the ids are the defaults.
    let accel = Accel::build_with_ids(&part.mesh, None);
    let triangles = part.triangle_count();
    ResidentScene {
        scene: Scene {
            mesh: part.mesh,
            ..tables
        },
        global_ids: part.global_ids,
        bounds,
        domains: vec![ResidentDomain {
            domain: part.domain,
            accel,
            triangles,
        }],
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

#[cfg(test)]
mod tests {
    use dray_core::bvh::QueryRay;

    use super::*;
    use crate::partition::LayoutSpec;
    use crate::partition::memory::MemoryPackage;

    /// Per triangle, in order: its material and, per corner, the bits of its position,
    /// normal, tangent and uv (what rendering reads; not the vertex numbering).
    fn triangle_bits(m: &Mesh) -> Vec<u32> {
        let mut out = Vec::new();
        for (t, tri) in m.indices.iter().enumerate() {
            out.push(m.material[t]);
            for &v in tri {
                let v = v as usize;
                let p = m.positions[v].to_array();
                let n = m.normals[v].to_array();
                let g = m.tangents[v].to_array();
                let u = m.uvs[v].to_array();
                let u2 = m
                    .uvs2
                    .get(v)
                    .copied()
                    .unwrap_or(glam::Vec2::ZERO)
                    .to_array();
                let c = m
                    .colors
                    .get(v)
                    .copied()
                    .unwrap_or(glam::Vec4::ONE)
                    .to_array();
                let all = p.iter().chain(&n).chain(&g).chain(&u).chain(&u2).chain(&c);
                out.extend(all.map(|x| x.to_bits()));
            }
        }
        out
    }

    /// Vertex colours survive the merge of several domains: each triangle of the resident
    /// scene has its source triangle's corner colours, white ones included.
    #[test]
    fn the_merge_keeps_vertex_colours() {
        let mut scene = crate::load("soup:400").unwrap();
        let n = scene.mesh.positions.len();
        scene.mesh.colors = (0..n)
            .map(|i| glam::Vec4::new((i % 7) as f32 / 7.0, 0.5, 0.25, 1.0))
            .collect();
        let source = scene.clone();
        let pkg = MemoryPackage::new(scene, &LayoutSpec::Kd(4)).unwrap();
        let parts: Vec<_> = (0..pkg.domain_count())
            .filter_map(|d| pkg.domain_mesh(d).cloned())
            .collect();
        assert!(parts.len() > 1);
        let b = pkg.layout().scene_bounds();
        let merged = merge(
            pkg.tables().clone(),
            (b.min, b.max),
            parts,
            pkg.emitters().clone(),
        );
        let m = &merged.scene.mesh;
        assert_eq!(m.colors.len(), m.positions.len());
        for (t, &g) in merged.global_ids.iter().enumerate() {
            let want = source.mesh.indices[g as usize].map(|v| source.mesh.colors[v as usize]);
            let have = m.indices[t].map(|v| m.colors[v as usize]);
            assert_eq!(have, want, "triangle {g}");
        }
    }

    /// One-domain packages (the embedded `dray render`) take the part as it is, and that
    /// is what the general merge gives: the same triangles in the same order to the bit,
    /// the same global ids, the same hits. Scenes with emitters (which the merge adds),
    /// shared vertices, and vertices not numbered in first-use order (the sphere).
    #[test]
    fn a_whole_part_is_what_the_merge_gives() {
        for spec in [
            "cornell",
            "cornell:glass",
            "spheres:40",
            "soup:3000",
            "city:3",
        ] {
            let scene = crate::load(spec).unwrap_or_else(|e| panic!("{spec}: {e}"));
            let pkg = MemoryPackage::new(scene, &LayoutSpec::Kd(1)).unwrap();
            let part = pkg.domain_mesh(0).cloned().unwrap();
            let emitters = pkg.emitters().clone();
            let one = std::slice::from_ref(&part);
            assert!(merged_is_the_part(one, &emitters), "{spec}");
            let b = pkg.layout().scene_bounds();
            let bounds = (b.min, b.max);
            let tables = || pkg.tables().clone();
            let fast = assemble(tables(), bounds, vec![part.clone()], emitters.clone());
            let slow = merge(tables(), bounds, vec![part], emitters);
            let (fm, sm) = (&fast.scene.mesh, &slow.scene.mesh);
            assert_eq!(triangle_bits(fm), triangle_bits(sm), "{spec}");
            assert_eq!(fast.global_ids, slow.global_ids, "{spec}");
            let (lo, hi) = fast.bounds;
            let (fa, sa) = (&fast.domains[0].accel, &slow.domains[0].accel);
            let mut hits = 0;
            for i in 0..2000u32 {
                let u = |k: u32| {
                    let h = i.wrapping_mul(2_654_435_761).wrapping_add(k * 40_503);
                    (h % 1000) as f32 / 1000.0
                };
                let target = lo + (hi - lo) * Vec3::new(u(1), u(2), u(3));
                let origin = lo + (hi - lo) * (Vec3::new(u(4), u(5), u(6)) * 3.0 - 1.0);
                let ray = QueryRay {
                    origin,
                    dir: (target - origin).normalize(),
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                };
                let key = |h: Option<dray_core::bvh::Hit>| {
                    h.map(|h| (h.t.to_bits(), h.tri, h.b0.to_bits(), h.b1.to_bits()))
                };
                let a = fa.closest(&ray, |_, _: &_| true);
                let s = sa.closest(&ray, |_, _: &_| true);
                assert_eq!(key(a), key(s), "{spec} ray {i}");
                hits += a.is_some() as u32;
            }
            assert!(hits > 100, "{spec}: {hits} hits");
        }
    }

    /// Two parts, an emitter outside the part, ids out of order or an index out of range
    /// take the general merge.
    #[test]
    fn other_inputs_take_the_merge() {
        let scene = crate::load("cornell").unwrap();
        let pkg = MemoryPackage::new(scene.clone(), &LayoutSpec::Kd(2)).unwrap();
        let (a, b) = (
            pkg.domain_mesh(0).cloned().unwrap(),
            pkg.domain_mesh(1).cloned().unwrap(),
        );
        assert!(!merged_is_the_part(&[a, b], pkg.emitters()));
        let whole = MemoryPackage::new(scene, &LayoutSpec::Kd(1)).unwrap();
        let part = whole.domain_mesh(0).cloned().unwrap();
        let mut emitters = whole.emitters().clone();
        emitters.global_ids.push(u32::MAX);
        assert!(!merged_is_the_part(std::slice::from_ref(&part), &emitters));
        let mut swapped = part.clone();
        swapped.global_ids.swap(0, 1);
        assert!(!merged_is_the_part(&[swapped], whole.emitters()));
        let mut outside = part.clone();
        outside.mesh.indices[3][1] = outside.mesh.positions.len() as u32;
        assert!(!merged_is_the_part(&[outside], whole.emitters()));
        assert!(merged_is_the_part(&[part], whole.emitters()));
    }
}
