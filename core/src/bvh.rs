//! The acceleration structure: an 8-wide BVH over the scene's triangles, with the
//! watertight test of [`crate::intersect`] as the only leaf test.
//!
//! What is obvhs's and what is dray's own:
//! - the binary tree is dray's (`build`): a binned-SAH build with a bounded depth,
//!   because obvhs's PLOC builder goes quadratic and arbitrarily deep on coincident
//!   triangles; it produces obvhs's `Bvh2` type;
//! - the collapse to 8-wide nodes is obvhs's algorithm (Ylitie et al. 2017's cost-based
//!   collapse, children ordered by octant), run in parallel by `convert` with the same
//!   result node for node as obvhs's `bvh2_to_cwbvh` (tested);
//! - the node layout is dray's (`wide`): exact f32 child planes, as Embree's BVH8,
//!   instead of obvhs's 8-bit quantised ones; the node test (`node_test`: SSE2 on every
//!   x86-64, AVX2 with FMA picked at run time, portable elsewhere), the traversal loop
//!   (`traverse`: nearest child first, far entries dropped unread) and the leaves
//!   (`leaf4`: up to four triangles, tested together in SSE lanes) are dray's. Where the
//!   tree stops splitting is SAH's decision, taken in the collapse (`convert`, which
//!   prices a leaf of up to four as one test).
//!
//! Before the binary build, pre-splitting (`presplit`, Embree's method; off by default,
//! see [`AccelOptions`]) can cut the triangles whose boxes fit them worst into fragments with
//! tighter boxes, each a reference to its triangle; a leaf holds a triangle once however
//! many of its fragments it was built for, and its box is their union. A triangle can then
//! sit in several leaves: harmless to the answers (below), which never depend on where a
//! triangle is, only on the node test letting through some leaf of every triangle the
//! leaf test hits (the fragments' boxes cover their triangle).
//!
//! The accelerator works in its own space: world coordinates scaled by a power of two
//! `s` chosen so the scene spans about 2^20 units. Scaling by a power of two is exact,
//! so hits, barycentrics and watertightness are unchanged.
//!
//! Node boxes are exactly the bounds of their triangles; the node test instead grows
//! every box, per ray, by 2^-17 of the largest distance from the ray's origin to the
//! scene's box ([`BOX_MARGIN`]), so that rounding in the slab test or in the leaf test
//! can never cull a box whose triangle the leaf test would hit (see `node_test`). The
//! margin scales with the distances the arithmetic works with, never with the
//! coordinates' magnitude, so a scene far from the origin is traversed as fast as at the
//! origin. Triangles with a non-finite corner are left out (nothing can hit them), and
//! the scene's bounds are taken in f64 so that coordinates near the f32 range cannot
//! make the scale or a box infinite.
//!
//! The closest hit is the smallest distance the leaf test finds, ties going to the lower
//! triangle id (the scene-wide id, not the place in a leaf or the order of leaves): it
//! does not depend on which boxes the node test lets through (as long as it is
//! conservative), on the order of visits, nor on which triangles share a leaf, so every
//! build of the node test, every tree (a domain's or the whole scene's) and any future
//! layout gives the same answers. Each lane of the leaf test gives the reference test's
//! bits for its triangle (`leaf4`), so the distances compared are the same everywhere.

use std::time::Duration;

use glam::{DVec3, Vec3, Vec3A};
use obvhs::{Boundable, aabb::Aabb};
use rayon::prelude::*;

use crate::intersect::{TriangleHit, WatertightRay};
use crate::scene::Mesh;

mod batch;
mod build;
mod convert;
mod leaf4;
mod node_test;
mod presplit;
mod traverse;
mod wide;

pub use batch::LANES;
use leaf4::Tri4;
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

/// The part of the largest distance from a ray's origin to the scene's box by which the
/// node test grows every box (see `node_test`, "Conservative"). The roundings it covers
/// add up to well under 2^-19 of that distance (about 50 units of 2^-24: the slab
/// arithmetic and the leaf test's shear and edge functions; it was sized when child
/// planes were also quantised, which they no longer are); 2^-17 leaves a factor of at
/// least 2.5, and is still 10^-5 of the scene.
pub const BOX_MARGIN: f32 = 1.0 / (1u32 << 17) as f32;

/// How [`Accel::build_with`] builds the tree. Every choice gives the same hits, bit for
/// bit (the closest-hit rule does not depend on the tree, see above); they trade build
/// time and memory for traversal work.
///
/// The default is no pre-splitting: measured with `dray bench-rays --count` (issue 41),
/// Embree's budget splits almost nothing on meshes of even triangles (one reference on
/// the bunny: its share rule gives no triangle a whole reference), and larger budgets
/// that do split add node visits on the bunny (4.59 per incoherent ray to 4.71 at +48%
/// references) for fewer leaf tests (0.911 to 0.893), more than they save, with a larger
/// tree and a slower build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AccelOptions {
    /// Pre-splitting's budget (`presplit`): at most this many extra references per
    /// triangle, given to the triangles whose boxes fit them worst; 0 turns it off.
    pub presplit: f32,
}

impl AccelOptions {
    /// Embree's default budget (`max_spatial_split_replications` = 1.2).
    pub const PRESPLIT: f32 = 0.2;

    /// No pre-splitting: one reference per triangle (the tree dray always built; the
    /// default).
    pub const UNSPLIT: AccelOptions = AccelOptions { presplit: 0.0 };

    /// Pre-splitting with Embree's budget.
    pub const SPLIT: AccelOptions = AccelOptions {
        presplit: AccelOptions::PRESPLIT,
    };
}

impl Default for AccelOptions {
    fn default() -> AccelOptions {
        AccelOptions::UNSPLIT
    }
}

struct Tri {
    v: [Vec3; 3],
}

impl Boundable for Tri {
    fn aabb(&self) -> Aabb {
        let lo = self.v[0].min(self.v[1]).min(self.v[2]);
        let hi = self.v[0].max(self.v[1]).max(self.v[2]);
        Aabb::new(Vec3A::from(lo), Vec3A::from(hi))
    }
}

pub struct Accel {
    /// The CWBVH's nodes, laid out for the wide node test.
    nodes: Vec<WideNode>,
    /// The leaves (up to four triangles each, in accelerator space, with the ids hits
    /// report), in the order the nodes number them.
    leaves: Vec<Tri4>,
    /// Triangles in the leaves.
    count: usize,
    /// References the build placed: the triangles and their pre-split fragments.
    references: usize,
    /// The bounds of every triangle, accelerator space (for the node test's margin).
    lo: Vec3,
    hi: Vec3,
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
        Accel::build_with(mesh, global_ids, AccelOptions::default())
    }

    /// [`Accel::build_with_ids`] with `options`.
    pub fn build_with(mesh: &Mesh, global_ids: Option<&[u32]>, options: AccelOptions) -> Accel {
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
        // minus -3e38), which would make the scale infinite.
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
        // Exact: the corners are f32 and the scale a power of two.
        let (box_lo, box_hi) = (lo.as_vec3() * scale, hi.as_vec3() * scale);

        // What a domain load holds at its peak is mostly this build (the worker reserves
        // room for it before loading: `resident::load_reserve`), so each array lives only
        // as long as it is needed: the accelerator-space corners are made from the mesh
        // where they are used (scaling by a power of two is exact, so every copy is the
        // same bits) instead of being kept beside the tree, the list of kept triangles
        // is dropped when it keeps them all (the usual case), and the binary tree is
        // dropped as soon as the 8-wide one is made.
        let count = kept.len() as u32;
        let kept = (kept.len() < mesh.indices.len()).then_some(kept);
        // The mesh index of the build's primitive `p`.
        let index = |p: u32| kept.as_ref().map_or(p, |k| k[p as usize]);
        let corners = |p: u32| mesh.corners(index(p) as usize).map(|c| c * scale);
        if count == 0 {
            return Accel {
                nodes: Vec::new(),
                leaves: Vec::new(),
                count: 0,
                references: 0,
                lo: box_lo,
                hi: box_hi,
                scale,
                inv_scale,
                simd: Simd::detect(),
                build_time: start.elapsed(),
            };
        }
        let aabbs: Vec<Aabb> = (0..count)
            .into_par_iter()
            .map(|p| Tri { v: corners(p) }.aabb())
            .collect();
        // The build's primitives are references: each triangle's own, and, pre-split,
        // the further fragments of some (`refs.primitive`).
        let mut refs = presplit::presplit(aabbs, corners, options.presplit);
        let references = refs.boxes.len();
        let split = !refs.extra.is_empty();
        let bvh2 = build::build(std::mem::take(&mut refs.boxes));
        // Leaves of up to four, where SAH prefers them; obvhs's conversion otherwise,
        // with large subtrees on rayon's pool.
        let bvh = convert::to_cwbvh(&bvh2, convert::Leaves::Four);
        let runs = wide::leaves(&bvh);
        // A fragment's box is not its triangle's: pre-split, a leaf's box is the union of
        // its references' boxes, each a BVH2 leaf's, read while the binary tree is here
        // (through a 4-byte index a reference, not a copy of the boxes: the build's peak
        // is what a domain load reserves).
        let leaf_boxes: Option<Vec<wide::Bounds>> = split.then(|| {
            let mut node_of = vec![0u32; references];
            for (k, node) in bvh2.nodes.iter().enumerate() {
                if node.prim_count != 0 {
                    node_of[bvh2.primitive_indices[node.first_index as usize] as usize] = k as u32;
                }
            }
            runs.par_iter()
                .map(|&(first, n)| {
                    let run = &bvh.primitive_indices[first as usize..(first + n) as usize];
                    run.iter().fold(wide::EMPTY, |acc, &r| {
                        let b = bvh2.nodes[node_of[r as usize] as usize].aabb();
                        wide::union(acc, (b.min.to_array(), b.max.to_array()))
                    })
                })
                .collect()
        });
        drop(bvh2);
        let id = |p: u32| {
            let i = index(p);
            match global_ids {
                Some(g) => g.get(i as usize).copied().unwrap_or(i),
                None => i,
            }
        };
        // Each leaf holds a triangle once, however many of its fragments the leaf's run
        // refers to.
        let leaves: Vec<Tri4> = runs
            .par_iter()
            .map(|&(first, n)| {
                let mut tris = [([Vec3::ZERO; 3], 0u32); 4];
                let mut prims = [u32::MAX; 4];
                let mut held = 0;
                let run = &bvh.primitive_indices[first as usize..(first + n) as usize];
                for &r in run {
                    let p = refs.primitive(r, count);
                    if !prims[..held].contains(&p) {
                        prims[held] = p;
                        tris[held] = (corners(p), id(p));
                        held += 1;
                    }
                }
                Tri4::new(&tris[..held])
            })
            .collect();
        drop(runs);
        Accel {
            nodes: wide::from_cwbvh(&bvh, &leaves, leaf_boxes.as_deref()),
            leaves,
            count: count as usize,
            references,
            lo: box_lo,
            hi: box_hi,
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
        self.count
    }

    /// References the tree was built over: one per triangle, and one per further
    /// fragment of a pre-split triangle.
    pub fn reference_count(&self) -> usize {
        self.references
    }

    /// A hash of everything the traversal reads (every node's planes, slot words and
    /// first leaf, the leaves' corners and ids, the scene box and the scale), bit for
    /// bit: two builds with the same digest are, but for a hash collision, the same
    /// tree, and give the same answer to every ray. For checking that
    /// a change to the build leaves the tree as it was (`examples/build_time.rs`).
    pub fn digest(&self) -> u64 {
        // FNV-1a over 32-bit words: stable across runs and platforms, unlike std's
        // randomly keyed hasher.
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        let mut word = |w: u32| {
            h ^= u64::from(w);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        };
        for node in &self.nodes {
            node.planes.iter().flatten().for_each(|p| word(p.to_bits()));
            node.slot.iter().for_each(|&s| word(s));
            word(node.leaf_base);
        }
        for t in &self.leaves {
            t.v.iter()
                .flatten()
                .flatten()
                .for_each(|p| word(p.to_bits()));
            t.ids.iter().for_each(|&i| word(i));
        }
        let box_bits = self.lo.to_array().into_iter().chain(self.hi.to_array());
        box_bits.for_each(|p| word(p.to_bits()));
        word(self.scale.to_bits());
        word(self.nodes.len() as u32);
        h
    }

    /// Bytes held by the nodes and the leaves (triangles and their ids).
    pub fn bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<WideNode>()
            + self.leaves.len() * std::mem::size_of::<Tri4>()
    }

    #[inline(always)]
    fn prepare(&self, ray: &QueryRay) -> (NodeRay, WatertightRay, f32, f32) {
        let o = Vec3A::from(ray.origin) * self.scale;
        let tmax = if ray.tmax.is_finite() {
            ray.tmax * self.scale
        } else {
            f32::INFINITY
        };
        // obvhs picks slab order from `direction < 0` but its own inverse uses the sign
        // bit, so -0.0 would flip a slab and lose the box: fold signed zeros to +0.0.
        // Its inverse also caps at 1/f32::EPSILON, which under-estimates slab distances
        // for nearly axis-parallel rays; use the true inverse, capped far beyond any
        // distance in accelerator space (and far from f32 overflow after quantisation),
        // with the direction's sign.
        let dir = Vec3A::from(ray.dir) + Vec3A::ZERO;
        let inv = Vec3A::select(
            dir.abs().cmpge(Vec3A::splat(1e-28)),
            Vec3A::ONE / dir,
            Vec3A::splat(1e28).copysign(dir),
        );
        // The node test's margin: 2^-17 of the farthest the scene's box reaches from
        // the origin along any axis (exact but for one rounding of each difference).
        let reach = (Vec3A::from(self.hi) - o)
            .abs()
            .max((Vec3A::from(self.lo) - o).abs())
            .max_element();
        let node_ray = NodeRay::new(o, dir, inv, reach * BOX_MARGIN);
        (
            node_ray,
            WatertightRay::new(o.into(), dir.into()),
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
                Simd::Avx512 => walk_avx512(&self.nodes, ray, tmax, counter, leaf),
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
        if self.leaves.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return None;
        }
        let (node_ray, wt, tmin, tmax) = self.prepare(ray);
        let mut best: Option<(TriangleHit, u32)> = None;
        self.walk(
            &node_ray,
            tmax,
            counter,
            #[inline(always)]
            |leaf, tmax, counter| {
                self.closer(&wt, leaf, tmin, tmax, &mut best, &mut accept, counter);
                Leaf::Continue
            },
        );
        self.world_hit(best)
    }

    /// The leaf step of a closest-hit query: test the triangles of leaf `leaf`, and keep
    /// each hit in `best` (lowering `tmax` to it) when it is nearer than `best`, or as
    /// near with a lower triangle id, and `accept` agrees. Shared by [`Accel::closest`]
    /// and [`Accel::closest_batch`], so both answer alike.
    ///
    /// The lanes' hits are taken in lane order, each against the best so far: what
    /// testing the triangles one by one would keep, and `accept` is asked about the same
    /// hits. The answer is the least accepted (distance, id) whatever the order.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn closer<C: Counter>(
        &self,
        wt: &WatertightRay,
        leaf: u32,
        tmin: f32,
        tmax: &mut f32,
        best: &mut Option<(TriangleHit, u32)>,
        accept: &mut impl FnMut(u32, &TriangleHit) -> bool,
        counter: &mut C,
    ) {
        let Some(tris) = self.leaves.get(leaf as usize) else {
            return;
        };
        counter.leaf(tris);
        // Inclusive upper bound so that equal-distance hits reach the tie-break.
        let hits = leaf4::intersect(wt, tris, tmin, next_up(*tmax));
        let mut mask = hits.mask;
        while mask != 0 {
            let lane = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            let h = hits.lane(lane);
            let id = tris.ids[lane];
            let better = match best {
                None => true,
                Some((bh, bid)) => h.t < bh.t || (h.t == bh.t && id < *bid),
            };
            if better && accept(id, &h) {
                *tmax = h.t;
                *best = Some((h, id));
            }
        }
    }

    /// A closest hit in accelerator units as the world-space answer.
    #[inline(always)]
    fn world_hit(&self, best: Option<(TriangleHit, u32)>) -> Option<Hit> {
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
        if self.leaves.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return false;
        }
        let (node_ray, wt, tmin, tmax) = self.prepare(ray);
        let mut hit = false;
        self.walk(
            &node_ray,
            tmax,
            counter,
            #[inline(always)]
            |leaf, tmax, counter| {
                let Some(tris) = self.leaves.get(leaf as usize) else {
                    return Leaf::Continue;
                };
                counter.leaf(tris);
                let hits = leaf4::intersect(&wt, tris, tmin, *tmax);
                let mut mask = hits.mask;
                while mask != 0 {
                    let lane = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    if accept(tris.ids[lane], &hits.lane(lane)) {
                        hit = true;
                        return Leaf::Stop;
                    }
                }
                Leaf::Continue
            },
        );
        hit
    }
}

/// Defines an `unsafe fn $name`: [`traverse::walk`] with the AVX2 node test, the whole
/// loop (leaf test included) compiled for `$features`. One body for every x86 level
/// above SSE2: `#[target_feature]` is per function, so each level is its own copy.
macro_rules! walk_compiled_for {
    ($(#[$doc:meta])* $name:ident, $features:literal) => {
        $(#[$doc])*
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $name<C: Counter>(
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
    };
}

walk_compiled_for!(
    /// [`traverse::walk`] for [`Simd::Avx2`]: AVX2 and FMA (and the POPCNT and LZCNT that
    /// come with them).
    ///
    /// # Safety
    /// The CPU must support AVX2, FMA, POPCNT and LZCNT; `nodes` as for [`traverse::walk`].
    walk_avx2,
    "avx2,fma,popcnt,lzcnt"
);

walk_compiled_for!(
    /// [`traverse::walk`] for [`Simd::Avx512`]: AVX2's code with AVX-512 and BMI too.
    ///
    /// # Safety
    /// The CPU must support what [`Simd::Avx512`] detects; `nodes` as for [`traverse::walk`].
    walk_avx512,
    "avx2,fma,popcnt,lzcnt,avx512f,avx512vl,avx512bw,avx512dq,bmi1,bmi2"
);

/// The next float above `x` (for positive finite `x`; infinity stays infinity).
#[inline]
fn next_up(x: f32) -> f32 {
    if x.is_finite() && x >= 0.0 {
        f32::from_bits(x.to_bits() + 1)
    } else {
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{PathKey, Purpose, uniform_sphere};

    fn key(i: u32) -> PathKey {
        PathKey {
            seed: 17,
            pixel: i,
            sample: 0,
        }
    }

    /// Pre-splitting with a budget that splits many triangles of the test meshes
    /// (Embree's shares it so that few get a whole reference).
    const MANY_SPLITS: AccelOptions = AccelOptions { presplit: 2.0 };

    /// A ray from `o` along `d` with no limits.
    fn unbounded(o: Vec3, d: Vec3) -> QueryRay {
        QueryRay {
            origin: o,
            dir: d,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }

    /// A closed, bumpy grid surface (every edge shared) and a soup of small triangles
    /// over it, `scale` across, `shift` from the origin.
    fn mesh(scale: f32, shift: Vec3) -> Mesh {
        let n = 24;
        let height = |i: u32, j: u32| {
            let k = key(i * 100 + j);
            k.uniform(0, Purpose::Film, 0) * 0.1
        };
        let at = |x: f32, y: f32, z: f32| Vec3::new(x, y, z) * scale + shift;
        let mut pts = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let p = |a: u32, b: u32| at(a as f32 / n as f32, b as f32 / n as f32, height(a, b));
                let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
                pts.extend([a, b, c, a, c, d]);
            }
        }
        for i in 0..600u32 {
            let k = key(10_000 + i);
            let c = Vec3::new(
                k.uniform(1, Purpose::Film, 0),
                k.uniform(1, Purpose::Film, 1),
                k.uniform(1, Purpose::Film, 2) * 0.5 + 0.1,
            );
            for j in 0..3 {
                let v = c + uniform_sphere(k.uniform2(2, Purpose::Film, j)) * 0.02;
                pts.push(at(v.x, v.y, v.z));
            }
        }
        let mut m = Mesh::default();
        m.push_vertices(&pts);
        let t = pts.len() as u32 / 3;
        m.indices = (0..t).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        m.material = vec![0; t as usize];
        m
    }

    /// `m` with `n` long slivers added, each from one side of the scene to the other
    /// (the triangles pre-splitting cuts), `scale` across, `shift` from the origin.
    fn with_slivers(mut m: Mesh, n: u32, scale: f32, shift: Vec3) -> Mesh {
        let mut pts = Vec::new();
        for i in 0..n {
            let k = key(70_000 + i);
            let u = |d: u32| k.uniform(7, Purpose::Film, d);
            let a = Vec3::new(u(0), u(1), u(2) * 0.5);
            let b = Vec3::new(u(3), u(4), u(5) * 0.5);
            let c = a + (Vec3::new(u(6), u(7), u(8)) - a) * 0.02;
            pts.extend([a, b, c].map(|v| v * scale + shift));
        }
        let base = m.push_vertices(&pts);
        m.indices
            .extend((0..n).map(|i| [base + 3 * i, base + 3 * i + 1, base + 3 * i + 2]));
        m.material = vec![0; m.indices.len()];
        m
    }

    /// Every triangle the leaf test hits lies in a box the node test lets through (with
    /// pre-splitting, one of its fragments' leaves): rays aimed exactly at corners and
    /// edges (where the leaf test's rounding matters), from inside the scene, from its
    /// box and from 1,000 scene sizes away, at scales and distances from the origin where
    /// the margin is tiny next to the coordinates, over the grid, the soup and slivers.
    #[test]
    fn the_node_test_never_loses_a_triangle_the_leaf_test_hits() {
        let cases = [
            (1.0f32, Vec3::ZERO),
            (1e-6, Vec3::ZERO),
            (1e6, Vec3::ZERO),
            (1.0, Vec3::new(1e5, -1e5, 3e4)),
            (64.0, Vec3::new(1e6, 0.0, -1e6)),
            (1e-2, Vec3::new(-1e4, 1e4, 0.0)),
        ];
        let mut hits = 0u64;
        let mut fragments = 0;
        for (scale, shift) in cases {
            let m = with_slivers(mesh(scale, shift), 150, scale, shift);
            for options in [AccelOptions::UNSPLIT, MANY_SPLITS] {
                let mut accel = Accel::build_with(&m, None, options);
                fragments += accel.reference_count() - accel.triangle_count();
                let levels: Vec<Simd> = traverse::testable_levels();
                // The triangles the leaf test hits, and those in the leaves each build
                // of the node test visits (the far limit never lowered, so every box the
                // ray crosses).
                let mut tri_hits = |o: Vec3, d: Vec3| -> (Vec<u32>, Vec<Vec<u32>>) {
                    let ray = unbounded(o, d);
                    let (node_ray, wt, tmin, tmax) = accel.prepare(&ray);
                    let mut want: Vec<u32> = accel
                        .leaves
                        .iter()
                        .flat_map(|t| {
                            let h = leaf4::intersect(&wt, t, tmin, tmax);
                            (0..4usize)
                                .filter(move |&l| h.mask >> l & 1 != 0)
                                .map(move |l| t.ids[l])
                        })
                        .collect();
                    want.sort_unstable();
                    want.dedup();
                    let seen = levels
                        .iter()
                        .map(|&simd| {
                            assert!(accel.set_simd(simd));
                            let mut seen = Vec::new();
                            accel.walk(&node_ray, tmax, &mut (), |leaf, _, _| {
                                seen.extend(accel.leaves[leaf as usize].ids);
                                Leaf::Continue
                            });
                            seen
                        })
                        .collect();
                    (want, seen)
                };
                for i in 0..3000u32 {
                    let k = key(20_000 + i);
                    let tri = (k.uniform(3, Purpose::Film, 0) * m.indices.len() as f32) as usize;
                    let [a, b, c] = m.corners(tri.min(m.indices.len() - 1));
                    let target = match i % 3 {
                        0 => a,
                        1 => (a + b) * 0.5,
                        _ => (a + b + c) / 3.0,
                    };
                    let from = uniform_sphere(k.uniform2(4, Purpose::Film, 0));
                    let dist = [0.3, 2.0, 1000.0][(i / 3 % 3) as usize] * scale;
                    let o = target + from * dist;
                    let d = (target - o).normalize();
                    if !d.is_finite() {
                        continue;
                    }
                    let (want, seen_by) = tri_hits(o, d);
                    // Every build of the node test visits a leaf of every triangle the
                    // leaf test hits.
                    for (seen, simd) in seen_by.iter().zip(&levels) {
                        for t in &want {
                            assert!(
                                seen.contains(t),
                                "scale {scale} shift {shift} {options:?} ray {i} {simd:?}: \
                                 triangle {t} is hit but its boxes are culled"
                            );
                        }
                    }
                    hits += want.len() as u64;
                }
            }
        }
        assert!(hits > 20_000, "{hits}");
        assert!(fragments > 1000, "{fragments}");
    }

    /// The closest hit is the least (distance, triangle id) over every triangle the
    /// reference test hits and the filter accepts, found by testing every triangle one
    /// by one; the any-hit query finds a hit exactly when there is one. On the bumpy grid
    /// and soup with every triangle listed twice more (once with its corners rotated,
    /// once reversed: the same distance to the bit, so ties that only the id breaks,
    /// wherever the copies land in the leaves), with and without a filter; slivers
    /// added, built with and without pre-splitting (the slivers' fragments in several
    /// leaves, their copies' fragments sharing some).
    #[test]
    fn closest_is_the_least_distance_then_id_over_all_triangles() {
        let shift = Vec3::new(3.0, -2.0, 0.5);
        let mut m = with_slivers(mesh(1.0, shift), 100, 1.0, shift);
        let n = m.indices.len() as u32;
        let copies: Vec<[u32; 3]> = m.indices.iter().map(|&[a, b, c]| [b, c, a]).collect();
        let reversed: Vec<[u32; 3]> = m.indices.iter().map(|&[a, b, c]| [a, c, b]).collect();
        m.indices.extend(copies);
        m.indices.extend(reversed);
        m.material = vec![0; m.indices.len()];
        let mut accels =
            [AccelOptions::UNSPLIT, MANY_SPLITS].map(|o| Accel::build_with(&m, None, o));
        assert!(accels[1].reference_count() > accels[1].triangle_count() + 300);
        let reject = |tri: u32| tri % 5 == 1;
        let (mut hits, mut ties) = (0, 0);
        for (i, accel) in (0..3000u32).flat_map(|i| [(i, 0), (i, 1)]) {
            let accel = &mut accels[accel];
            let k = key(50_000 + i);
            let u = |d: u32| k.uniform(5, Purpose::Film, d);
            let o = Vec3::new(u(0), u(1), u(2)) * 1.4 + Vec3::new(2.8, -2.2, 0.3);
            let ray = unbounded(o, uniform_sphere(k.uniform2(6, Purpose::Film, 0)));
            let (_, wt, tmin, tmax) = accel.prepare(&ray);
            for filtered in [false, true] {
                let mut want: Option<(u32, u32)> = None;
                let mut at_best = 0;
                for t in 0..m.indices.len() as u32 {
                    if filtered && reject(t) {
                        continue;
                    }
                    let [a, b, c] = m.corners(t as usize).map(|p| p * accel.scale);
                    if let Some(h) = wt.intersect(a, b, c, tmin, tmax) {
                        let key = (h.t.to_bits(), t);
                        if want.is_none_or(|w| h.t < f32::from_bits(w.0)) {
                            at_best = 0;
                        }
                        if want.is_none_or(|w| h.t <= f32::from_bits(w.0)) {
                            at_best += 1;
                        }
                        want = Some(want.map_or(key, |w| {
                            if (h.t, t) < (f32::from_bits(w.0), w.1) {
                                key
                            } else {
                                w
                            }
                        }));
                    }
                }
                for simd in traverse::testable_levels() {
                    assert!(accel.set_simd(simd));
                    let got = accel.closest(&ray, |t, _| !(filtered && reject(t)));
                    let got = got.map(|h| ((h.t * accel.scale).to_bits(), h.tri));
                    assert_eq!(got, want, "ray {i} filtered {filtered} {simd:?}");
                    let any = accel.occluded(&ray, |t, _| !(filtered && reject(t)));
                    assert_eq!(any, want.is_some(), "ray {i} filtered {filtered} {simd:?}");
                }
                hits += want.is_some() as u32;
                ties += (at_best > 1) as u32;
            }
        }
        assert!(n > 1000 && hits > 1200 && ties > 1200, "{hits} {ties}");
    }

    /// A build with pre-splitting answers every query as the build without does, bit
    /// for bit (closest hits with their distances and barycentrics, any-hits), on a soup
    /// of long skinny triangles (most of them split) and small ones, rays from inside
    /// and outside, with a filter too.
    #[test]
    fn presplit_trees_answer_as_unsplit_ones() {
        let mut m = with_slivers(Mesh::default(), 3000, 1.0, Vec3::ZERO);
        let small = mesh(1.0, Vec3::ZERO);
        let base = m.push_vertices(&small.positions);
        m.indices
            .extend(small.indices.iter().map(|t| t.map(|v| v + base)));
        m.material = vec![0; m.indices.len()];
        let plain = Accel::build_with(&m, None, AccelOptions::UNSPLIT);
        let mut split = Accel::build_with(&m, None, MANY_SPLITS);
        assert_eq!(plain.reference_count(), plain.triangle_count());
        assert!(split.reference_count() > split.triangle_count() * 5 / 4);
        assert!(split.digest() != plain.digest());
        let (mut hits, mut fewer) = (0, 0i64);
        for i in 0..20_000u32 {
            let k = key(90_000 + i);
            let u = |d: u32| k.uniform(8, Purpose::Film, d);
            let o = Vec3::new(u(0), u(1), u(2)) * 1.6 - 0.3;
            let ray = unbounded(o, uniform_sphere(k.uniform2(9, Purpose::Film, 0)));
            let filter = |t: u32, _: &TriangleHit| i.is_multiple_of(2) || !t.is_multiple_of(3);
            let (mut a, mut b) = (TraversalCounts::default(), TraversalCounts::default());
            let want = plain.closest_counted(&ray, filter, &mut a);
            for simd in traverse::testable_levels() {
                assert!(split.set_simd(simd));
                let got = split.closest_counted(&ray, filter, &mut b);
                assert_eq!(
                    got.map(|h| (h.t.to_bits(), h.tri, h.b0.to_bits(), h.b1.to_bits())),
                    want.map(|h| (h.t.to_bits(), h.tri, h.b0.to_bits(), h.b1.to_bits())),
                    "ray {i} {simd:?}"
                );
                assert_eq!(
                    split.occluded(&ray, filter),
                    plain.occluded(&ray, filter),
                    "ray {i} {simd:?}"
                );
            }
            hits += u32::from(want.is_some());
            fewer += a.nodes as i64 - (b.nodes / traverse::testable_levels().len() as u64) as i64;
        }
        assert!(hits > 2_000, "{hits}");
        // Not a promise, but what pre-splitting is for: slivers' boxes overlap less.
        assert!(fewer > 0, "{fewer}");
    }
}
