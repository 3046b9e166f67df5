//! Spatial partitioning and the on-disk scene package.
//!
//! dray renders scenes larger than one machine by cutting them into **domains**: an
//! axis-aligned box and every triangle that overlaps it (docs/architecture.md "Words"). This
//! module decides the boxes ([`DomainLayout`]: a uniform grid or a kd split balanced by
//! triangle count), assigns triangles to them, and stores the result as a **scene
//! package**: a directory with a checksummed, versioned manifest and one binary file per
//! domain (format in [`package`]).
//!
//! # Assignment
//! A triangle belongs to *every* domain whose box, grown by the layout's small epsilon
//! (see [`layout`]), it overlaps by an exact separating-axis test ([`overlap`]). So a
//! triangle touching a wall, or within rounding distance of it, is in both neighbours, and
//! a worker that clips a ray to its domain's interval finds the same closest hit (same t,
//! same triangle) as the single-BVH trace. Each stored triangle keeps its **global id**,
//! its index in the unpartitioned mesh, so tie-breaks and per-triangle hashes (stochastic
//! alpha) do not depend on the partition.
//!
//! # Bounded memory
//! [`write_package`] streams over a [`TriangleSource`] twice: pass 1 finds the bounds and
//! a bounded sample of centroids (for the kd quantiles); pass 2 appends each triangle to
//! per-domain spill buffers that are flushed to disk when full. Each domain is then
//! compacted (vertices shared by content) into its final file, a few domains at a time
//! ([`WriteOptions::threads`]). Memory is O(domains x buffer + sample + threads x largest
//! domain) plus whatever the source holds, so a scene larger than RAM can be partitioned
//! from a streaming source. (Domains are the unit a worker holds in memory, so "the
//! largest domain fits" is the premise of the whole design, not an extra assumption.)
//!
//! [`partition_in_memory`] does the same assignment without a disk, for the embedded mode
//! and tests, and yields exactly the meshes a package round trip gives.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use dray_core::scene::{Mesh, Scene};
use glam::{Vec2, Vec3, Vec4};

use crate::error::Result;

pub mod checksum;
pub mod grid;
pub mod kd;
pub mod layout;
pub mod manifest;
pub mod memory;
pub mod overlap;
pub mod package;
pub mod resident;

pub use layout::{Aabb, DomainLayout, LayoutSpec, MAX_DOMAINS};
pub use manifest::{FORMAT_VERSION, Manifest};
pub use package::{
    Package, PackageSummary, SceneParts, WriteOptions, open_package, write_package,
    write_scene_package, write_scene_package_with,
};
pub use resident::{ResidentDomain, ResidentScene, load_resident};

/// One triangle as a source hands it over: corners with all attributes, its material and
/// its global id.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SourceTriangle {
    /// Index of the triangle in the unpartitioned scene.
    pub id: u32,
    pub material: u32,
    pub positions: [Vec3; 3],
    pub normals: [Vec3; 3],
    pub tangents: [Vec4; 3],
    pub uvs: [Vec2; 3],
    /// The second UV set ([`Mesh::uvs2`]; zero where the source has none).
    pub uvs2: [Vec2; 3],
    /// Vertex colours (white where the source has none).
    pub colors: [Vec4; 3],
}

impl Default for SourceTriangle {
    /// Zero attributes ("absent"), and white corners: white is "no vertex colour".
    fn default() -> Self {
        SourceTriangle {
            id: 0,
            material: 0,
            positions: [Vec3::ZERO; 3],
            normals: [Vec3::ZERO; 3],
            tangents: [Vec4::ZERO; 3],
            uvs: [Vec2::ZERO; 3],
            uvs2: [Vec2::ZERO; 3],
            colors: [Vec4::ONE; 3],
        }
    }
}

/// Anything that can hand over a scene's triangles one at a time.
///
/// Partitioning calls [`for_each_triangle`](Self::for_each_triangle) twice and relies on
/// getting the same triangles in the same order both times (it checks the count and that
/// every triangle lies in the bounds found the first time). In-memory scenes implement it
/// directly; a procedural generator or a file reader can implement it to stream a scene
/// that never exists in memory whole.
pub trait TriangleSource {
    /// Call `f` once per triangle, stopping at the first error `f` returns.
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()>;

    /// Call `f(id, positions, material)` once per triangle, in `for_each_triangle`'s
    /// order with its values: all that pass 1 ([`survey`]) reads. A source that can give
    /// them without making whole triangles (normals, tangents, uvs) overrides it.
    fn for_each_position(
        &self,
        f: &mut dyn FnMut(u32, [Vec3; 3], u32) -> Result<()>,
    ) -> Result<()> {
        self.for_each_triangle(&mut |t| f(t.id, t.positions, t.material))
    }

    /// Whether any triangle may have a vertex colour other than white. Sources without
    /// them (the default) are partitioned without a colour section anywhere.
    fn has_colors(&self) -> bool {
        false
    }

    /// Whether any triangle may have a nonzero second UV set. Sources without one (the
    /// default) spill and store none.
    fn has_uvs2(&self) -> bool {
        false
    }

    /// Random access by global id, for sources that can make any of their triangles
    /// cheaply from its id alone (a mesh in memory, a grid of copies of one). The package
    /// writer then spills 4-byte ids in pass 2 instead of whole triangles (152 bytes or
    /// more), and makes each domain's triangles again while compacting it: the spill is
    /// what bounds the disk a package needs while it is written, and whole triangles made
    /// it about three times the finished package
    /// (docs/history/2026-11-22-distributed-runtime.md, "`dray partition`
    /// of 104 million triangles").
    fn lookup(&self) -> Option<&dyn TriangleLookup> {
        None
    }
}

/// A [`TriangleSource`]'s triangles by global id (see [`TriangleSource::lookup`]).
///
/// `Sync` because the package writer compacts several domains at once.
pub trait TriangleLookup: Sync {
    /// The triangle with global id `id`, bit for bit as `for_each_triangle` hands it
    /// over; `None` when the source has no such triangle.
    fn triangle(&self, id: u32) -> Option<SourceTriangle>;
}

/// Every triangle of `mesh` can be given a 32-bit global id.
fn ids_fit(mesh: &Mesh) -> Result<()> {
    if mesh.indices.len() > u32::MAX as usize {
        return Err(layout::layout_error(
            "more than 4 billion triangles cannot be given 32-bit global ids",
        ));
    }
    Ok(())
}

/// Triangle `i` of `mesh` as a source hands it over (absent attributes zero, absent
/// colours white). The caller has checked `i` is in range and fits a u32.
fn mesh_triangle(mesh: &Mesh, i: usize) -> SourceTriangle {
    let tri = mesh.indices[i];
    let at = |k: usize| tri[k] as usize;
    SourceTriangle {
        id: i as u32,
        material: mesh.material.get(i).copied().unwrap_or(0),
        positions: std::array::from_fn(|k| mesh.positions[at(k)]),
        normals: std::array::from_fn(|k| mesh.normals.get(at(k)).copied().unwrap_or(Vec3::ZERO)),
        tangents: std::array::from_fn(|k| mesh.tangents.get(at(k)).copied().unwrap_or(Vec4::ZERO)),
        uvs: std::array::from_fn(|k| mesh.uvs.get(at(k)).copied().unwrap_or(Vec2::ZERO)),
        uvs2: std::array::from_fn(|k| mesh.uvs2.get(at(k)).copied().unwrap_or(Vec2::ZERO)),
        colors: std::array::from_fn(|k| mesh.colors.get(at(k)).copied().unwrap_or(Vec4::ONE)),
    }
}

impl TriangleSource for Mesh {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        ids_fit(self)?;
        for i in 0..self.indices.len() {
            f(&mesh_triangle(self, i))?;
        }
        Ok(())
    }

    fn for_each_position(
        &self,
        f: &mut dyn FnMut(u32, [Vec3; 3], u32) -> Result<()>,
    ) -> Result<()> {
        ids_fit(self)?;
        for (i, tri) in self.indices.iter().enumerate() {
            let material = self.material.get(i).copied().unwrap_or(0);
            f(i as u32, tri.map(|v| self.positions[v as usize]), material)?;
        }
        Ok(())
    }

    fn has_colors(&self) -> bool {
        !self.colors.is_empty()
    }

    fn has_uvs2(&self) -> bool {
        !self.uvs2.is_empty()
    }

    fn lookup(&self) -> Option<&dyn TriangleLookup> {
        Some(self)
    }
}

impl TriangleLookup for Mesh {
    fn triangle(&self, id: u32) -> Option<SourceTriangle> {
        let i = id as usize;
        (i < self.indices.len()).then(|| mesh_triangle(self, i))
    }
}

impl TriangleSource for Scene {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        self.mesh.for_each_triangle(f)
    }

    fn for_each_position(
        &self,
        f: &mut dyn FnMut(u32, [Vec3; 3], u32) -> Result<()>,
    ) -> Result<()> {
        self.mesh.for_each_position(f)
    }

    fn has_colors(&self) -> bool {
        self.mesh.has_colors()
    }

    fn has_uvs2(&self) -> bool {
        self.mesh.has_uvs2()
    }

    fn lookup(&self) -> Option<&dyn TriangleLookup> {
        self.mesh.lookup()
    }
}

/// The triangles of one domain, ready for a BVH.
#[derive(Clone, Debug, PartialEq)]
pub struct DomainMesh {
    pub domain: u32,
    /// The domain's box (not grown by the epsilon).
    pub bounds: Aabb,
    /// The triangles with local vertex indices; `mesh.material` holds scene material ids.
    pub mesh: Mesh,
    /// Per triangle, its index in the unpartitioned scene. Ascending for sources that
    /// number triangles in order, as in-memory scenes do.
    pub global_ids: Vec<u32>,
}

impl DomainMesh {
    pub fn triangle_count(&self) -> usize {
        self.mesh.indices.len()
    }
}

/// A vertex's identity: the bits of all its attributes (position, normal, tangent, uv,
/// colour, and in [`VertexKey2`] the second uv, as little-endian f32). Vertices are
/// shared within a domain when they are bitwise identical, which loses nothing (shading
/// reads only the attributes) and needs no global vertex ids from the source.
#[derive(Clone, Copy, PartialEq, Eq)]
struct VertexKey([u8; 64]);

/// [`VertexKey`] with the second UV set: used only once a domain meets a triangle that
/// has one, so the vertex map of every other domain keeps its size.
#[derive(Clone, Copy, PartialEq, Eq)]
struct VertexKey2([u8; 72]);

impl std::hash::Hash for VertexKey {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        // One-shot XXH3 of the first 48 bytes: several times faster than feeding a
        // streaming hasher, and the map hashes every corner of every triangle. The
        // colour (the last 16) is left out of the hash, which costs colourless scenes
        // nothing; equality still compares it, so vertices that differ only in colour
        // stay apart (they merely share a hash).
        state.write_u64(xxhash_rust::xxh3::xxh3_64(&self.0[..48]));
    }
}

impl std::hash::Hash for VertexKey2 {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        // As VertexKey's; the second uv (the last 8) is compared, not hashed.
        state.write_u64(xxhash_rust::xxh3::xxh3_64(&self.0[..48]));
    }
}

/// Passes through the one u64 [`VertexKey`] writes.
#[derive(Default)]
struct PassThrough(u64);

impl std::hash::Hasher for PassThrough {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        // Not reached for VertexKey; fold anything else in rather than drop it.
        self.0 = xxhash_rust::xxh3::xxh3_64_with_seed(bytes, self.0);
    }
    fn write_u64(&mut self, v: u64) {
        self.0 ^= v;
    }
}

fn vertex_key(t: &SourceTriangle, k: usize) -> VertexKey {
    let (p, n, g, u, c) = (
        t.positions[k],
        t.normals[k],
        t.tangents[k],
        t.uvs[k],
        t.colors[k],
    );
    let mut key = [0u8; 64];
    let values = [
        p.x, p.y, p.z, n.x, n.y, n.z, g.x, g.y, g.z, g.w, u.x, u.y, c.x, c.y, c.z, c.w,
    ];
    for (chunk, v) in key.chunks_exact_mut(4).zip(values) {
        chunk.copy_from_slice(&v.to_le_bytes());
    }
    VertexKey(key)
}

/// `key` with the second uv `uv2` appended.
fn with_uv2(key: VertexKey, uv2: Vec2) -> VertexKey2 {
    let mut k = [0u8; 72];
    k[..64].copy_from_slice(&key.0);
    k[64..68].copy_from_slice(&uv2.x.to_le_bytes());
    k[68..].copy_from_slice(&uv2.y.to_le_bytes());
    VertexKey2(k)
}

type VertexMap<K> = HashMap<K, u32, BuildHasherDefault<PassThrough>>;

/// A domain's vertices by content: without second uvs until the first triangle that has
/// a nonzero one, then with them (the vertices so far keep their index, their second uv
/// being zero).
enum Vertices {
    OneSet(VertexMap<VertexKey>),
    TwoSets(VertexMap<VertexKey2>),
}

/// Builds one domain's indexed mesh from its triangles in arrival order. The in-memory
/// partition and the package writer both use it, so they give identical meshes.
pub(crate) struct DomainBuilder {
    mesh: Mesh,
    global_ids: Vec<u32>,
    vertices: Vertices,
}

impl DomainBuilder {
    pub(crate) fn new() -> Self {
        Self::with_capacity(0)
    }

    /// A builder expecting about `triangles` triangles (sizes the vertex map so it does
    /// not rehash as it grows; meshes with shared vertices use fewer than this).
    pub(crate) fn with_capacity(triangles: usize) -> Self {
        let mut mesh = Mesh::default();
        mesh.indices.reserve_exact(triangles);
        mesh.material.reserve_exact(triangles);
        DomainBuilder {
            mesh,
            global_ids: Vec::with_capacity(triangles),
            vertices: Vertices::OneSet(HashMap::with_capacity_and_hasher(
                triangles,
                Default::default(),
            )),
        }
    }

    pub(crate) fn push(&mut self, t: &SourceTriangle) {
        let zero = |u: &Vec2| u.x.to_bits() == 0 && u.y.to_bits() == 0;
        if let Vertices::OneSet(map) = &mut self.vertices
            && !t.uvs2.iter().all(zero)
        {
            let two = std::mem::take(map)
                .into_iter()
                .map(|(key, i)| (with_uv2(key, Vec2::ZERO), i))
                .collect();
            self.vertices = Vertices::TwoSets(two);
        }
        let idx = std::array::from_fn(|k| {
            let next = self.mesh.positions.len() as u32;
            let key = vertex_key(t, k);
            let i = match &mut self.vertices {
                Vertices::OneSet(map) => *map.entry(key).or_insert(next),
                Vertices::TwoSets(map) => *map.entry(with_uv2(key, t.uvs2[k])).or_insert(next),
            };
            if i == next {
                self.mesh.positions.push(t.positions[k]);
                self.mesh.normals.push(t.normals[k]);
                self.mesh.tangents.push(t.tangents[k]);
                self.mesh.uvs.push(t.uvs[k]);
                // Both stay empty while every second uv is zero and every colour white.
                let uv2 = t.uvs2[k];
                self.mesh
                    .extend_uvs2(i as usize, Some(std::slice::from_ref(&uv2)));
                let colour = t.colors[k];
                self.mesh
                    .extend_colors(i as usize, Some(std::slice::from_ref(&colour)));
            }
            i
        });
        self.mesh.indices.push(idx);
        self.mesh.material.push(t.material);
        self.global_ids.push(t.id);
    }

    pub(crate) fn triangle_count(&self) -> usize {
        self.mesh.indices.len()
    }

    pub(crate) fn finish(self, domain: u32, bounds: Aabb) -> DomainMesh {
        DomainMesh {
            domain,
            bounds,
            mesh: self.mesh,
            global_ids: self.global_ids,
        }
    }
}

/// How many centroids pass 1 keeps for the kd quantiles by default: 12 MiB, exact for
/// scenes up to a million triangles and within a fraction of a percent of the true
/// quantile beyond.
pub const DEFAULT_SAMPLE_CAPACITY: usize = 1 << 20;

/// What pass 1 learns about a source.
#[derive(Clone, Debug)]
pub struct Survey {
    pub bounds: Aabb,
    pub triangles: u64,
    /// Per material id seen, how many triangles use it (as long as the largest id + 1).
    pub material_triangles: Vec<u64>,
    /// A uniform sample of triangle centroids (all of them when they fit).
    pub centroids: Vec<Vec3>,
}

/// Pass 1: bounds, counts and a reservoir sample of at most `sample_capacity` centroids
/// (Vitter's algorithm R with a fixed seed, so the same source gives the same layout).
pub fn survey(source: &dyn TriangleSource, sample_capacity: usize) -> Result<Survey> {
    let mut s = Survey {
        bounds: Aabb::EMPTY,
        triangles: 0,
        material_triangles: Vec::new(),
        centroids: Vec::new(),
    };
    let mut rng = 0x9A27_1710_0000_0003u64;
    source.for_each_position(&mut |id, positions, material| {
        crate::cancel::check_at(id as usize)?;
        for p in positions {
            s.bounds.grow(p);
        }
        let m = material as usize;
        if m >= s.material_triangles.len() {
            s.material_triangles.resize(m + 1, 0);
        }
        s.material_triangles[m] += 1;
        let c = (positions[0] + positions[1] + positions[2]) / 3.0;
        if s.centroids.len() < sample_capacity {
            s.centroids.push(c);
        } else if sample_capacity > 0 {
            let j = ((splitmix(&mut rng) as u128 * (s.triangles + 1) as u128) >> 64) as usize;
            if j < sample_capacity {
                s.centroids[j] = c;
            }
        }
        s.triangles += 1;
        Ok(())
    })?;
    Ok(s)
}

fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl DomainLayout {
    /// Pass 1 over `source` and the layout `spec` over its bounds.
    pub fn for_source(source: &dyn TriangleSource, spec: &LayoutSpec) -> Result<DomainLayout> {
        let capacity = if spec.needs_centroids() {
            DEFAULT_SAMPLE_CAPACITY
        } else {
            0
        };
        let mut s = survey(source, capacity)?;
        if s.triangles == 0 {
            return Err(layout::layout_error(
                "the scene has no triangles to partition",
            ));
        }
        DomainLayout::build(s.bounds, spec, &mut s.centroids)
    }
}

/// The error for a triangle that no domain takes: the source gave a triangle outside the
/// bounds it reported in pass 1 (or the layout belongs to another scene).
pub(crate) fn unassigned_error(t: &SourceTriangle) -> crate::SceneError {
    layout::layout_error(format!(
        "triangle {} ({:?}) lies outside the layout's bounds: the source changed between \
         passes, or the layout was made for another scene",
        t.id, t.positions
    ))
}

/// Partition `scene` by `layout` without touching the disk: one mesh per domain, the
/// same (bit for bit) as writing a package and loading each domain back.
///
/// Fails (instead of silently dropping triangles) when a triangle lies outside the
/// layout's bounds, i.e. when the layout was made for another scene.
pub fn partition_in_memory(scene: &Scene, layout: &DomainLayout) -> Result<Vec<DomainMesh>> {
    partition_source_in_memory(scene, layout)
}

/// [`partition_in_memory`] for any [`TriangleSource`].
pub fn partition_source_in_memory(
    source: &dyn TriangleSource,
    layout: &DomainLayout,
) -> Result<Vec<DomainMesh>> {
    let mut builders: Vec<DomainBuilder> = (0..layout.domain_count())
        .map(|_| DomainBuilder::new())
        .collect();
    let mut domains = Vec::new();
    source.for_each_triangle(&mut |t| {
        layout.assign(&t.positions, &mut domains);
        if domains.is_empty() {
            return Err(unassigned_error(t));
        }
        for &d in &domains {
            builders[d as usize].push(t);
        }
        Ok(())
    })?;
    Ok(builders
        .into_iter()
        .enumerate()
        .map(|(d, b)| b.finish(d as u32, layout.bounds(d as u32)))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mesh's own position pass gives what its whole triangles give: the same ids,
    /// corners and materials in the same order (so pass 1 surveys the same values), and
    /// materials past the table's end read as 0 as before.
    #[test]
    fn a_meshs_position_pass_is_its_triangle_pass() {
        for spec in ["cornell:glass", "city:3", "soup:500"] {
            let mut scene = crate::load(spec).unwrap();
            scene.mesh.material.pop();
            let mut whole = Vec::new();
            scene
                .for_each_triangle(&mut |t| {
                    whole.push((t.id, t.positions.map(|p| p.to_array()), t.material));
                    Ok(())
                })
                .unwrap();
            let mut positions = Vec::new();
            scene
                .for_each_position(&mut |id, p, m| {
                    positions.push((id, p.map(|p| p.to_array()), m));
                    Ok(())
                })
                .unwrap();
            assert!(whole.len() > 10, "{spec}");
            assert_eq!(positions, whole, "{spec}");
        }
    }

    #[test]
    fn reservoir_keeps_everything_below_capacity_and_is_bounded_above() {
        let mut mesh = Mesh::default();
        for i in 0..1000 {
            let o = Vec3::splat(i as f32);
            let b = mesh.push_vertices(&[o, o + Vec3::X, o + Vec3::Y]);
            mesh.indices.push([b, b + 1, b + 2]);
            mesh.material.push((i % 3) as u32);
        }
        let s = survey(&mesh, 2000).unwrap();
        assert_eq!(s.triangles, 1000);
        assert_eq!(s.centroids.len(), 1000);
        assert_eq!(s.material_triangles, vec![334, 333, 333]);
        assert_eq!(
            s.bounds,
            Aabb::new(Vec3::ZERO, Vec3::new(1000.0, 1000.0, 999.0))
        );
        let s = survey(&mesh, 100).unwrap();
        assert_eq!(s.centroids.len(), 100);
        // The sample spreads over the whole range, not just the first triangles.
        assert!(s.centroids.iter().any(|c| c.z > 500.0));
    }

    #[test]
    fn shared_vertices_are_shared_by_content() {
        let mut b = DomainBuilder::new();
        let mut t = SourceTriangle {
            positions: [Vec3::ZERO, Vec3::X, Vec3::Y],
            ..Default::default()
        };
        b.push(&t);
        t.id = 1;
        t.positions = [Vec3::X, Vec3::ONE, Vec3::Y];
        b.push(&t);
        t.id = 2;
        t.uvs[0] = Vec2::ONE; // same position, different uv: a new vertex
        b.push(&t);
        let d = b.finish(0, Aabb::new(Vec3::ZERO, Vec3::ONE));
        assert_eq!(d.mesh.positions.len(), 5);
        assert_eq!(d.mesh.indices, vec![[0, 1, 2], [1, 3, 2], [4, 3, 2]]);
        assert_eq!(d.global_ids, vec![0, 1, 2]);
    }
}
