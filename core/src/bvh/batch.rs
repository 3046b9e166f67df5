//! Many rays traced together, so that one ray's wait for memory is spent on the others.
//!
//! An incoherent ray in a scene larger than the caches misses at nearly every node: on a
//! 1.3M-triangle mesh a single ray spends most of its time waiting for node lines from
//! memory, one node at a time, because which node comes next depends on the last one's
//! test. [`Accel::closest_batch`] keeps [`LANES`] rays in flight, each a paused walk
//! (`traverse::Walk`): a ray chooses its next node, starts loading it (a prefetch), and
//! the loop turns to the next ray; by the time it comes back the node is (often) in
//! cache. A hit leaf's triangles are prefetched the same way before their test.
//!
//! Every ray's answer is what [`Accel::closest`] finds for it, bit for bit: the same node
//! test, leaf test and tie rule (smaller distance, then lower triangle id), which do not
//! depend on the order of visits.

use super::node_test::NodeHits;
use super::traverse::{Leaf, Walk, prefetch};
use super::{Accel, Hit, NodeRay, Simd, Tri4, WideNode, node_test};
use crate::bvh::QueryRay;
use crate::intersect::{TriangleHit, WatertightRay};

/// Rays in flight at once: enough to cover a memory access with the other rays' node
/// tests (about a dozen independent misses can be outstanding per core), few enough that
/// the lanes' stacks stay in the first-level cache.
pub const LANES: usize = 16;

/// One ray in flight.
struct Lane {
    /// Index of the ray in the batch.
    index: usize,
    node_ray: NodeRay,
    wt: WatertightRay,
    tmin: f32,
    tmax: f32,
    best: Option<(TriangleHit, u32)>,
    walk: Walk,
    /// `walk` has chosen a node (being loaded) that is not tested yet.
    node_pending: bool,
}

impl Accel {
    /// The closest hit of every ray of `rays` in its (tmin, tmax) that `accept(i, tri,
    /// hit)` agrees to, written to `out[i]`: the same answers as [`Accel::closest`] ray
    /// by ray, traced [`LANES`] at a time (see the module's doc).
    ///
    /// # Panics
    /// If `out` is not as long as `rays`.
    pub fn closest_batch(
        &self,
        rays: &[QueryRay],
        mut accept: impl FnMut(usize, u32, &TriangleHit) -> bool,
        out: &mut [Option<Hit>],
    ) {
        assert_eq!(rays.len(), out.len(), "one answer per ray");
        // SAFETY: `self.simd` is only ever a level this CPU supports, and the nodes were
        // built by `wide::from_cwbvh`.
        unsafe {
            match self.simd {
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => batch_avx2(self, rays, &mut accept, out),
                #[cfg(target_arch = "x86_64")]
                Simd::Avx512 => batch_avx512(self, rays, &mut accept, out),
                #[cfg(target_arch = "x86_64")]
                Simd::Sse2 => self.batch(rays, &mut accept, out, |n, r, t| {
                    node_test::x86::hits_sse2(n, r, t)
                }),
                _ => self.batch(rays, &mut accept, out, node_test::hits_portable),
            }
        }
    }

    /// Start ray `index` in a lane, or answer it at once (`None`) when it cannot hit.
    #[inline(always)]
    fn lane(&self, rays: &[QueryRay], index: usize) -> Option<Lane> {
        let ray = &rays[index];
        if self.leaves.is_empty() || !ray.origin.is_finite() || !ray.dir.is_finite() {
            return None;
        }
        let (node_ray, wt, tmin, tmax) = self.prepare(ray);
        Some(Lane {
            index,
            node_ray,
            wt,
            tmin,
            tmax,
            best: None,
            walk: Walk::new(&self.nodes),
            node_pending: false,
        })
    }

    /// The loop of [`Accel::closest_batch`] with the node test `hits`.
    ///
    /// # Safety
    /// `hits` must be runnable on this CPU.
    #[inline(always)]
    unsafe fn batch(
        &self,
        rays: &[QueryRay],
        accept: &mut impl FnMut(usize, u32, &TriangleHit) -> bool,
        out: &mut [Option<Hit>],
        mut hits: impl FnMut(&WideNode, &NodeRay, f32) -> NodeHits,
    ) {
        let mut lanes: [Option<Lane>; LANES] = std::array::from_fn(|_| None);
        let mut next = 0usize;
        let mut active = 0usize;
        let leaves: &[Tri4] = &self.leaves;
        loop {
            for slot in lanes.iter_mut() {
                // A free lane takes the next ray (rays that cannot hit are answered here).
                while slot.is_none() && next < rays.len() {
                    *slot = self.lane(rays, next);
                    if slot.is_none() {
                        out[next] = None;
                    } else {
                        active += 1;
                    }
                    next += 1;
                }
                let Some(lane) = slot else { continue };
                if lane.node_pending {
                    lane.node_pending = false;
                    // SAFETY: the node was chosen by `step`; `hits` as the caller promises.
                    unsafe {
                        lane.walk
                            .test(&self.nodes, &lane.node_ray, lane.tmax, &mut (), &mut hits)
                    };
                    let (first, mut mask) = lane.walk.leaves();
                    if mask != 0 {
                        // Load the leaves now, test them on the next turn.
                        while mask != 0 {
                            let i = mask.trailing_zeros();
                            mask &= mask - 1;
                            if let Some(t) = leaves.get((first + i) as usize) {
                                prefetch(t, std::mem::size_of::<Tri4>());
                            }
                        }
                        continue;
                    }
                }
                let (wt, tmin, best, index) = (&lane.wt, lane.tmin, &mut lane.best, lane.index);
                let mut accept_here = |id: u32, h: &TriangleHit| accept(index, id, h);
                let mut leaf_test = |leaf: u32, tmax: &mut f32, c: &mut ()| {
                    self.closer(wt, leaf, tmin, tmax, best, &mut accept_here, c);
                    Leaf::Continue
                };
                // SAFETY: as for `walk`.
                let more = unsafe { lane.walk.step(&mut lane.tmax, &mut (), &mut leaf_test) };
                if more {
                    prefetch(
                        &self.nodes[lane.walk.next()],
                        std::mem::size_of::<WideNode>(),
                    );
                    lane.node_pending = true;
                } else {
                    out[lane.index] = self.world_hit(lane.best);
                    *slot = None;
                    active -= 1;
                }
            }
            if active == 0 && next >= rays.len() {
                return;
            }
        }
    }
}

/// Defines an `unsafe fn $name`: [`Accel::batch`] with the AVX2 node test, compiled for
/// `$features` like `super::walk_avx2` and `super::walk_avx512`.
macro_rules! batch_compiled_for {
    ($(#[$doc:meta])* $name:ident, $features:literal) => {
        $(#[$doc])*
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $name(
            accel: &Accel,
            rays: &[QueryRay],
            accept: &mut impl FnMut(usize, u32, &TriangleHit) -> bool,
            out: &mut [Option<Hit>],
        ) {
            // SAFETY: as the caller promises.
            unsafe {
                accel.batch(rays, accept, out, |n, r, t| {
                    node_test::x86::hits_avx2(n, r, t)
                })
            }
        }
    };
}

batch_compiled_for!(
    /// [`Accel::batch`] for [`Simd::Avx2`].
    ///
    /// # Safety
    /// The CPU must support AVX2, FMA, POPCNT and LZCNT.
    batch_avx2,
    "avx2,fma,popcnt,lzcnt"
);

batch_compiled_for!(
    /// [`Accel::batch`] for [`Simd::Avx512`].
    ///
    /// # Safety
    /// The CPU must support what [`Simd::Avx512`] detects.
    batch_avx512,
    "avx2,fma,popcnt,lzcnt,avx512f,avx512vl,avx512bw,avx512dq,bmi1,bmi2"
);

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::sampling::{PathKey, Purpose, uniform_sphere};
    use crate::scene::Mesh;

    fn key(i: u32) -> PathKey {
        PathKey {
            seed: 23,
            pixel: i,
            sample: 0,
        }
    }

    /// `n` random triangles in a box `scale` across.
    fn soup(n: u32, scale: f32) -> Mesh {
        let size = 0.6 / (n as f32).cbrt();
        let mut pts = Vec::new();
        for i in 0..n {
            let k = key(i);
            let c = Vec3::new(
                k.uniform(0, Purpose::Film, 0),
                k.uniform(0, Purpose::Film, 1),
                k.uniform(0, Purpose::Film, 2),
            );
            for j in 0..3 {
                pts.push((c + uniform_sphere(k.uniform2(1, Purpose::Film, j)) * size) * scale);
            }
        }
        let mut m = Mesh::default();
        m.push_vertices(&pts);
        m.indices = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
        m.material = vec![0; n as usize];
        m
    }

    /// Rays from inside and around the box, some with limits, some that cannot hit.
    fn rays(n: u32, scale: f32) -> Vec<QueryRay> {
        (0..n)
            .map(|i| {
                let k = key(1_000_000 + i);
                let o = Vec3::new(
                    k.uniform(2, Purpose::Film, 0),
                    k.uniform(2, Purpose::Film, 1),
                    k.uniform(2, Purpose::Film, 2),
                ) * 1.6
                    - 0.3;
                let mut r = QueryRay {
                    origin: o * scale,
                    dir: uniform_sphere(k.uniform2(3, Purpose::Film, 0)),
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                };
                match i % 11 {
                    0 => r.origin.x = f32::NAN,
                    1 => r.tmax = 0.2 * scale,
                    2 => r.tmin = 0.1 * scale,
                    3 => r.dir = Vec3::new(0.0, -0.0, 1.0),
                    _ => {}
                }
                r
            })
            .collect()
    }

    /// Every ray's answer from `closest_batch` is `closest`'s, bit for bit, with every
    /// build of the node test, with and without a filter, for batches shorter and longer
    /// than the lanes.
    #[test]
    fn batch_answers_are_closest_answers() {
        for (n, scale) in [(3_000u32, 1.0f32), (20_000, 1e-3), (500, 1e4)] {
            let mut accel = Accel::build(&soup(n, scale));
            let rays = rays(4_000, scale);
            let reject = |tri: u32| tri % 7 == 3;
            let levels: Vec<Simd> = crate::bvh::traverse::testable_levels();
            for simd in levels {
                assert!(accel.set_simd(simd));
                for filtered in [false, true] {
                    let want: Vec<Option<Hit>> = rays
                        .iter()
                        .map(|r| accel.closest(r, |tri, _| !(filtered && reject(tri))))
                        .collect();
                    let hits = want.iter().filter(|h| h.is_some()).count();
                    assert!(hits > 300, "{hits}");
                    for len in [1usize, LANES - 1, LANES + 3, rays.len()] {
                        let mut got = vec![None; len];
                        let mut asked = vec![0u32; len];
                        accel.closest_batch(
                            &rays[..len],
                            |i, tri, _| {
                                asked[i] += 1;
                                !(filtered && reject(tri))
                            },
                            &mut got,
                        );
                        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                            assert_eq!(g, w, "{simd:?} n {n} ray {i} of {len}");
                        }
                        // The filter was asked about each ray that found a triangle.
                        for (i, w) in want[..len].iter().enumerate() {
                            if w.is_some() {
                                assert!(asked[i] > 0, "ray {i}");
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn an_empty_scene_answers_none() {
        let accel = Accel::build(&Mesh::default());
        let rays = rays(40, 1.0);
        let mut got = vec![
            Some(Hit {
                t: 1.0,
                tri: 0,
                b0: 1.0,
                b1: 0.0,
                b2: 0.0
            });
            rays.len()
        ];
        accel.closest_batch(&rays, |_, _, _| true, &mut got);
        assert!(got.iter().all(Option::is_none));
    }
}
