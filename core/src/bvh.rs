//! The acceleration structure: an obvhs compressed wide BVH (CWBVH) over the scene's
//! triangles, with the watertight test of [`crate::intersect`] as the only leaf test.
//!
//! obvhs's node test clamps the entry distance to an absolute epsilon of 1e-4, which would
//! lose hits near a ray's origin in small scenes. The accelerator therefore works in its
//! own space: world coordinates scaled by a power of two `s` chosen so the scene spans
//! about 2^20 units. Scaling by a power of two is exact, so hits, barycentrics and
//! watertightness are unchanged, and the node epsilon becomes ~1e-10 of the scene.
//!
//! Node boxes are padded by a few ulps of the scene's magnitude so that rounding in the
//! slab test can never cull a box whose triangle the leaf test would hit.

use std::time::Duration;

use glam::{UVec2, Vec3, Vec3A};
use obvhs::{Boundable, BvhBuildParams, aabb::Aabb, cwbvh::CwBvh, ray::Ray, traverse};

use crate::intersect::{TriangleHit, WatertightRay};
use crate::scene::Mesh;

/// A closest hit: world-space distance, the triangle's index in the mesh, barycentrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub tri: u32,
    pub b0: f32,
    pub b1: f32,
    pub b2: f32,
}

/// A query ray in world space. `dir` should be unit length; distances are world units.
#[derive(Clone, Copy, Debug)]
pub struct QueryRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub tmin: f32,
    pub tmax: f32,
}

struct PaddedTri {
    v: [Vec3; 3],
    pad: f32,
}

impl Boundable for PaddedTri {
    fn aabb(&self) -> Aabb {
        let lo = self.v[0].min(self.v[1]).min(self.v[2]) - Vec3::splat(self.pad);
        let hi = self.v[0].max(self.v[1]).max(self.v[2]) + Vec3::splat(self.pad);
        Aabb::new(Vec3A::from(lo), Vec3A::from(hi))
    }
}

pub struct Accel {
    bvh: CwBvh,
    /// Triangle corners in accelerator space, in BVH leaf order.
    tris: Vec<[Vec3; 3]>,
    /// Mesh triangle index of each leaf slot.
    ids: Vec<u32>,
    /// World to accelerator scale (a power of two).
    scale: f32,
    inv_scale: f32,
    /// Wall time of the BVH build.
    pub build_time: Duration,
}

impl Accel {
    /// Build over every triangle of `mesh`; hits report the mesh's triangle indices.
    pub fn build(mesh: &Mesh) -> Accel {
        Accel::build_with_ids(mesh, None)
    }

    /// Build over every triangle of `mesh`, reporting triangle `i` as `ids[i]`. A domain's
    /// mesh holds part of a scene; with the scene-wide ids, hits and distance ties resolve
    /// exactly as in one BVH over the whole scene.
    pub fn build_with_ids(mesh: &Mesh, global_ids: Option<&[u32]>) -> Accel {
        let start = std::time::Instant::now();
        let (lo, hi) = mesh.bounds();
        let extent = (hi - lo).max_element().max(f32::MIN_POSITIVE);
        let magnitude = lo.abs().max(hi.abs()).max_element().max(extent);
        // s = 2^(20 - floor(log2(extent))), limited so that coordinates stay far from overflow.
        let e = extent.log2().floor() as i32;
        let mut exp = 20 - e;
        let max_exp = 100 - magnitude.log2().ceil() as i32;
        exp = exp.min(max_exp).clamp(-120, 120);
        let scale = 2f32.powi(exp);
        let inv_scale = 2f32.powi(-exp);
        let pad = magnitude * scale * (1.0 / (1u32 << 21) as f32);

        let prims: Vec<PaddedTri> = (0..mesh.indices.len())
            .map(|i| PaddedTri {
                v: mesh.corners(i).map(|p| p * scale),
                pad,
            })
            .collect();
        if prims.is_empty() {
            return Accel {
                bvh: CwBvh::default(),
                tris: Vec::new(),
                ids: Vec::new(),
                scale,
                inv_scale,
                build_time: start.elapsed(),
            };
        }
        let mut core = Duration::default();
        let bvh =
            obvhs::cwbvh::builder::build_cwbvh(&prims, BvhBuildParams::medium_build(), &mut core);
        let ids = match global_ids {
            Some(g) => bvh
                .primitive_indices
                .iter()
                .map(|&i| g.get(i as usize).copied().unwrap_or(i))
                .collect(),
            None => bvh.primitive_indices.clone(),
        };
        let tris = bvh
            .primitive_indices
            .iter()
            .map(|&i| prims[i as usize].v)
            .collect();
        Accel {
            bvh,
            tris,
            ids,
            scale,
            inv_scale,
            build_time: start.elapsed(),
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.ids.len()
    }

    #[inline]
    fn prepare(&self, ray: &QueryRay) -> (Ray, WatertightRay) {
        let o = ray.origin * self.scale;
        let tmax = if ray.tmax.is_finite() {
            ray.tmax * self.scale
        } else {
            f32::INFINITY
        };
        // obvhs picks slab order from `direction < 0` but its own inverse uses the sign
        // bit, so -0.0 would flip a slab and lose the box: fold signed zeros to +0.0.
        // Its inverse also caps at 1/f32::EPSILON, which under-estimates slab distances
        // for nearly axis-parallel rays; use the true inverse, capped far beyond any
        // distance in accelerator space (and far from f32 overflow after quantisation).
        let dir = ray.dir + Vec3::ZERO;
        let inv = |d: f32| {
            if d.abs() >= 1e-28 {
                1.0 / d
            } else if d < 0.0 {
                -1e28
            } else {
                1e28
            }
        };
        let r = Ray {
            origin: Vec3A::from(o),
            direction: Vec3A::from(dir),
            inv_direction: Vec3A::new(inv(dir.x), inv(dir.y), inv(dir.z)),
            tmin: ray.tmin * self.scale,
            tmax,
        };
        (r, WatertightRay::new(o, dir))
    }

    /// The closest hit in (tmin, tmax) that `accept` agrees to. Ties in distance go to the
    /// lower triangle index, so the answer does not depend on traversal order.
    pub fn closest(
        &self,
        ray: &QueryRay,
        mut accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit> {
        if self.ids.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return None;
        }
        let (mut trav, wt) = self.prepare(ray);
        let mut best: Option<(TriangleHit, u32)> = None;
        let mut state = self.bvh.new_traversal(trav.direction);
        let mut node;
        traverse!(
            self.bvh,
            node,
            state,
            node.intersect_ray(&trav, state.oct_inv4),
            {
                let slot = state.primitive_id as usize;
                let [a, b, c] = self.tris[slot];
                // Inclusive upper bound so that equal-distance hits reach the tie-break.
                if let Some(h) = wt.intersect(a, b, c, trav.tmin, next_up(trav.tmax)) {
                    let id = self.ids[slot];
                    let better = match &best {
                        None => true,
                        Some((bh, bid)) => h.t < bh.t || (h.t == bh.t && id < *bid),
                    };
                    if better && accept(id, &h) {
                        trav.tmax = h.t;
                        best = Some((h, id));
                    }
                }
            }
        );
        best.map(|(h, id)| Hit {
            t: h.t * self.inv_scale,
            tri: id,
            b0: h.b0,
            b1: h.b1,
            b2: h.b2,
        })
    }

    /// True if any hit in (tmin, tmax) is accepted by `accept` (shadow and AO rays).
    pub fn occluded(
        &self,
        ray: &QueryRay,
        mut accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> bool {
        if self.ids.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return false;
        }
        let (trav, wt) = self.prepare(ray);
        let mut hit = false;
        let mut state = self.bvh.new_traversal(trav.direction);
        let mut node;
        'outer: {
            traverse!(
                self.bvh,
                node,
                state,
                node.intersect_ray(&trav, state.oct_inv4),
                {
                    let slot = state.primitive_id as usize;
                    let [a, b, c] = self.tris[slot];
                    if let Some(h) = wt.intersect(a, b, c, trav.tmin, trav.tmax)
                        && accept(self.ids[slot], &h)
                    {
                        hit = true;
                        break 'outer;
                    }
                }
            );
        }
        hit
    }
}

/// The next float above `x` (for positive finite `x`; infinity stays infinity).
#[inline]
fn next_up(x: f32) -> f32 {
    if x.is_finite() && x >= 0.0 {
        f32::from_bits(x.to_bits() + 1)
    } else {
        x
    }
}
