//! What the geometry tests share: a mesh from a list of triangles, a quad added to a
//! scene, and cutting a mesh into per-domain BVHs. Each test crate uses part of it.
#![allow(dead_code)]

use dray_core::bvh::Accel;
use dray_core::domain::DomainTree;
use dray_core::scene::{Mesh, Scene};
use glam::Vec3;

/// Per-domain BVHs with scene-wide ids: each triangle goes to every domain whose box,
/// grown by `pad`, overlaps the triangle's bounds (what the partitioner does).
pub fn split(mesh: &Mesh, tree: &DomainTree, pad: f32) -> Vec<Accel> {
    tree.domain_bounds()
        .iter()
        .map(|&(lo, hi)| {
            let (lo, hi) = (lo - Vec3::splat(pad), hi + Vec3::splat(pad));
            let mut part = Mesh::default();
            let mut ids = Vec::new();
            for t in 0..mesh.indices.len() {
                let c = mesh.corners(t);
                let (tlo, thi) = (c[0].min(c[1]).min(c[2]), c[0].max(c[1]).max(c[2]));
                if tlo.cmple(hi).all() && thi.cmpge(lo).all() {
                    let base = part.push_vertices(&c);
                    part.indices.push([base, base + 1, base + 2]);
                    part.material.push(0);
                    ids.push(t as u32);
                }
            }
            Accel::build_with_ids(&part, Some(&ids))
        })
        .collect()
}

/// A mesh of separate triangles (no shared corners), material 0, in the given order:
/// triangle `i` of the list is triangle `i` of the mesh.
pub fn mesh(tris: &[[Vec3; 3]]) -> Mesh {
    let mut m = Mesh::default();
    for t in tris {
        let base = m.push_vertices(t);
        m.indices.push([base, base + 1, base + 2]);
        m.material.push(0);
    }
    m
}

/// Add a quad of `material` to `scene`, corners in order (counter-clockwise seen from
/// its front), as two triangles.
pub fn quad(scene: &mut Scene, corners: [Vec3; 4], material: u32) {
    let base = scene.mesh.push_vertices(&corners);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.indices.push([base, base + 2, base + 3]);
    scene.mesh.material.extend([material, material]);
}
