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
//!
//! The binary tree under the CWBVH is dray's own (see `build`): a binned-SAH build with
//! a bounded depth, because obvhs's PLOC builder goes quadratic and arbitrarily deep on
//! coincident triangles. Triangles with a non-finite corner are left out (nothing can
//! hit them), and the scene's bounds are taken in f64 so that coordinates near the f32
//! range cannot make the scale, the padding or a box infinite.
//!
//! Traversal is dray's own loop over obvhs's compressed nodes (`traverse`), with the
//! nodes re-laid out for an eight-children-at-once box test (`wide`, `node_test`: SSE2 on
//! every x86-64, AVX2 picked at run time) and the triangles stored in leaf order for the
//! watertight test (`leaf`). Both tests are obvhs's and [`crate::intersect`]'s arithmetic,
//! operation for operation, and the loop visits nodes and triangles in obvhs's order, so
//! the answers are the same bits as with obvhs's `traverse!`.

use std::time::Duration;

use glam::{DVec3, Vec3, Vec3A};
use obvhs::{Boundable, aabb::Aabb};
use rayon::prelude::*;

use crate::intersect::{TriangleHit, WatertightRay};
use crate::scene::Mesh;

mod build;
mod convert;
mod leaf;
mod node_test;
mod traverse;
mod wide;

use leaf::PackedTri;
use node_test::NodeRay;
use traverse::{Counter, Leaf};
pub use traverse::{Simd, TraversalCounts};
use wide::WideNode;

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
    /// The CWBVH's nodes, laid out for the wide node test.
    nodes: Vec<WideNode>,
    /// Triangle corners in accelerator space, in BVH leaf order.
    tris: Vec<PackedTri>,
    /// Mesh triangle index of each leaf slot.
    ids: Vec<u32>,
    /// World to accelerator scale (a power of two).
    scale: f32,
    inv_scale: f32,
    /// The node test's instruction set (detected at build time).
    simd: Simd,
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
        // Only triangles with finite corners go in: nothing can hit the others, and one
        // infinite coordinate would make every box above it (and the conversion's child
        // ordering, which then panics) non-finite.
        // Per-triangle passes run on rayon's pool; each keeps its input's order.
        let kept: Vec<u32> = (0..mesh.indices.len() as u32)
            .into_par_iter()
            .filter(|&i| mesh.corners(i as usize).iter().all(|p| p.is_finite()))
            .collect();
        // Bounds in f64: the extent of finite f32 coordinates can overflow f32 (3e38
        // minus -3e38), which would make the scale and the padding infinite.
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for &i in &kept {
            for p in mesh.corners(i as usize) {
                lo = lo.min(p.as_dvec3());
                hi = hi.max(p.as_dvec3());
            }
        }
        if kept.is_empty() {
            (lo, hi) = (DVec3::ZERO, DVec3::ZERO);
        }
        let extent = (hi - lo).max_element().max(f64::from(f32::MIN_POSITIVE));
        let magnitude = lo.abs().max(hi.abs()).max_element().max(extent);
        // s = 2^(20 - floor(log2(extent))), limited so that coordinates stay far from
        // overflow (below 2^100 in accelerator space).
        let e = extent.log2().floor() as i32;
        let mut exp = 20 - e;
        let max_exp = 100 - magnitude.log2().ceil() as i32;
        exp = exp.min(max_exp).clamp(-120, 120);
        let scale = 2f32.powi(exp);
        let inv_scale = 2f32.powi(-exp);
        let pad = (magnitude * f64::from(scale) / f64::from(1u32 << 21)) as f32;

        let prims: Vec<PaddedTri> = kept
            .par_iter()
            .map(|&i| PaddedTri {
                v: mesh.corners(i as usize).map(|p| p * scale),
                pad,
            })
            .collect();
        if prims.is_empty() {
            return Accel {
                nodes: Vec::new(),
                tris: Vec::new(),
                ids: Vec::new(),
                scale,
                inv_scale,
                simd: Simd::detect(),
                build_time: start.elapsed(),
            };
        }
        let aabbs: Vec<Aabb> = prims.par_iter().map(Boundable::aabb).collect();
        let bvh2 = build::build(&aabbs);
        // At most 3 triangles per leaf, as obvhs's own CWBVH builder converts; obvhs's
        // conversion, with large subtrees on rayon's pool.
        let bvh = convert::to_cwbvh(&bvh2, 3);
        let ids = bvh
            .primitive_indices
            .par_iter()
            .map(|&p| {
                let i = kept[p as usize];
                match global_ids {
                    Some(g) => g.get(i as usize).copied().unwrap_or(i),
                    None => i,
                }
            })
            .collect();
        let tris = bvh
            .primitive_indices
            .par_iter()
            .map(|&i| PackedTri::new(prims[i as usize].v))
            .collect();
        Accel {
            nodes: wide::from_cwbvh(&bvh),
            tris,
            ids,
            scale,
            inv_scale,
            simd: Simd::detect(),
            build_time: start.elapsed(),
        }
    }

    /// The node test's instruction set.
    pub fn simd(&self) -> Simd {
        self.simd
    }

    /// Run the node test with `simd` instead of the detected best (for tests and
    /// benchmarks: every build gives the same answers). Ignored, returning false, when
    /// this CPU cannot run it.
    pub fn set_simd(&mut self, simd: Simd) -> bool {
        if simd.supported() {
            self.simd = simd;
        }
        self.simd == simd
    }

    pub fn triangle_count(&self) -> usize {
        self.ids.len()
    }

    #[inline]
    fn prepare(&self, ray: &QueryRay) -> (NodeRay, WatertightRay, f32, f32) {
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
        let node_ray = NodeRay::new(
            o.to_array(),
            dir.to_array(),
            [inv(dir.x), inv(dir.y), inv(dir.z)],
        );
        (
            node_ray,
            WatertightRay::new(o, dir),
            ray.tmin * self.scale,
            tmax,
        )
    }

    /// Run `walk` with the node test of `self.simd`.
    #[inline(always)]
    fn walk<C: Counter>(
        &self,
        ray: &NodeRay,
        tmax: f32,
        counter: &mut C,
        leaf: impl FnMut(u32, &mut f32, &mut C) -> Leaf,
    ) {
        // SAFETY: `self.simd` is only ever a level this CPU supports (`detect`,
        // `set_simd`), and `self.nodes` was built by `wide::from_cwbvh`.
        unsafe {
            match self.simd {
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => walk_avx2(&self.nodes, ray, tmax, counter, leaf),
                #[cfg(target_arch = "x86_64")]
                Simd::Sse2 => traverse::walk(
                    &self.nodes,
                    ray,
                    tmax,
                    counter,
                    |n, r, t| node_test::x86::hits_sse2(n, r, t),
                    leaf,
                ),
                _ => traverse::walk(
                    &self.nodes,
                    ray,
                    tmax,
                    counter,
                    node_test::hits_portable,
                    leaf,
                ),
            }
        }
    }

    /// The closest hit in (tmin, tmax) that `accept` agrees to. Ties in distance go to the
    /// lower triangle index, so the answer does not depend on traversal order.
    ///
    /// Never inlined: one call per ray costs nothing next to the traversal, and profiles
    /// can then name the whole query.
    #[inline(never)]
    pub fn closest(
        &self,
        ray: &QueryRay,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit> {
        self.closest_with(ray, accept, &mut ())
    }

    /// [`Accel::closest`], adding the nodes and triangles it tested to `counts`.
    pub fn closest_counted(
        &self,
        ray: &QueryRay,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
        counts: &mut TraversalCounts,
    ) -> Option<Hit> {
        self.closest_with(ray, accept, counts)
    }

    #[inline(always)]
    fn closest_with<C: Counter>(
        &self,
        ray: &QueryRay,
        mut accept: impl FnMut(u32, &TriangleHit) -> bool,
        counter: &mut C,
    ) -> Option<Hit> {
        if self.ids.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return None;
        }
        let (node_ray, wt, tmin, tmax) = self.prepare(ray);
        let mut best: Option<(TriangleHit, u32)> = None;
        self.walk(
            &node_ray,
            tmax,
            counter,
            #[inline(always)]
            |slot, tmax, _| {
                let slot = slot as usize;
                // Inclusive upper bound so that equal-distance hits reach the tie-break.
                if let Some(tri) = self.tris.get(slot)
                    && let Some(h) = leaf::intersect(&wt, tri, tmin, next_up(*tmax))
                {
                    let id = self.ids[slot];
                    let better = match &best {
                        None => true,
                        Some((bh, bid)) => h.t < bh.t || (h.t == bh.t && id < *bid),
                    };
                    if better && accept(id, &h) {
                        *tmax = h.t;
                        best = Some((h, id));
                    }
                }
                Leaf::Continue
            },
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
    #[inline(never)]
    pub fn occluded(&self, ray: &QueryRay, accept: impl FnMut(u32, &TriangleHit) -> bool) -> bool {
        self.occluded_with(ray, accept, &mut ())
    }

    /// [`Accel::occluded`], adding the nodes and triangles it tested to `counts`.
    pub fn occluded_counted(
        &self,
        ray: &QueryRay,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
        counts: &mut TraversalCounts,
    ) -> bool {
        self.occluded_with(ray, accept, counts)
    }

    #[inline(always)]
    fn occluded_with<C: Counter>(
        &self,
        ray: &QueryRay,
        mut accept: impl FnMut(u32, &TriangleHit) -> bool,
        counter: &mut C,
    ) -> bool {
        if self.ids.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return false;
        }
        let (node_ray, wt, tmin, tmax) = self.prepare(ray);
        let mut hit = false;
        self.walk(
            &node_ray,
            tmax,
            counter,
            #[inline(always)]
            |slot, tmax, _| {
                let slot = slot as usize;
                if let Some(tri) = self.tris.get(slot)
                    && let Some(h) = leaf::intersect(&wt, tri, tmin, *tmax)
                    && accept(self.ids[slot], &h)
                {
                    hit = true;
                    return Leaf::Stop;
                }
                Leaf::Continue
            },
        );
        hit
    }
}

/// [`traverse::walk`] with the AVX2 node test, compiled for AVX2 (and the POPCNT and
/// LZCNT that come with it) so the whole loop, leaf test included, uses them.
///
/// # Safety
/// The CPU must support AVX2, POPCNT and LZCNT; `nodes` as for [`traverse::walk`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,popcnt,lzcnt")]
unsafe fn walk_avx2<C: Counter>(
    nodes: &[WideNode],
    ray: &NodeRay,
    tmax: f32,
    counter: &mut C,
    leaf: impl FnMut(u32, &mut f32, &mut C) -> Leaf,
) {
    // SAFETY: as the caller promises.
    unsafe {
        traverse::walk(
            nodes,
            ray,
            tmax,
            counter,
            |n, r, t| node_test::x86::hits_avx2(n, r, t),
            leaf,
        )
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
