//! The traversal loop over [`WideNode`]s: obvhs's `traverse!` (Ylitie et al. 2017's
//! node groups), step for step, with the node test of `node_test` and the leaf test of
//! `leaf` inlined into one function per instruction set.
//!
//! The stack holds node groups (a first-child index and the hit children left to visit,
//! in traversal order in the top byte, the node's internal-child mask in the low byte),
//! as in obvhs, saturating at the top like obvhs's `StackStack` (but never full: see
//! [`STACK_SIZE`]). Children are
//! taken highest traversal-order bit first and a node's primitives highest offset first,
//! as obvhs does; with exact boxes (`wide`) a ray visits fewer of them than with obvhs's
//! quantised ones, in the same order.

use super::node_test::NodeRay;
use super::wide::WideNode;

/// Entries of the group stack: one per level at most, and no leaf is deeper than
/// [`super::build::MAX_DEPTH`] (obvhs's `TRAVERSAL_STACK_SIZE` is 32, which a deep tree
/// could overflow; the stack saturates rather than overrun, but would then lose nodes).
const STACK_SIZE: usize = super::build::MAX_DEPTH as usize;

/// Which build of the node test runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Simd {
    /// Plain Rust, eight children one by one (non-x86-64 targets; tests).
    Portable,
    /// SSE2, four children at a time: every x86-64 CPU.
    Sse2,
    /// AVX2 and FMA, eight children at a time, chosen at run time when the CPU has them.
    Avx2,
}

impl Simd {
    /// The best this CPU runs.
    pub fn detect() -> Simd {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
                && std::arch::is_x86_feature_detected!("popcnt")
                && std::arch::is_x86_feature_detected!("lzcnt")
            {
                Simd::Avx2
            } else {
                Simd::Sse2
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            Simd::Portable
        }
    }

    /// Whether this CPU can run `self`.
    pub fn supported(self) -> bool {
        match self {
            Simd::Portable => true,
            #[cfg(target_arch = "x86_64")]
            Simd::Sse2 => true,
            #[cfg(target_arch = "x86_64")]
            Simd::Avx2 => Simd::detect() == Simd::Avx2,
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }
}

/// Counts of one traversal, for profiles (`Accel::closest_counted`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalCounts {
    /// Nodes whose eight children were tested.
    pub nodes: u64,
    /// Triangles tested.
    pub triangles: u64,
}

/// Something that counts node and triangle tests; the `()` counter compiles to nothing.
pub(crate) trait Counter {
    fn node(&mut self);
    fn triangle(&mut self);
}

impl Counter for () {
    #[inline(always)]
    fn node(&mut self) {}
    #[inline(always)]
    fn triangle(&mut self) {}
}

impl Counter for TraversalCounts {
    #[inline(always)]
    fn node(&mut self) {
        self.nodes += 1;
    }
    #[inline(always)]
    fn triangle(&mut self) {
        self.triangles += 1;
    }
}

/// What the leaf callback tells the loop.
pub(crate) enum Leaf {
    Continue,
    Stop,
}

/// Walk `nodes` for `ray`, calling `leaf(slot, &mut tmax)` for every primitive slot of
/// every hit leaf. `tmax` is the far limit of the node test; the callback may lower it.
///
/// # Safety
/// `hits` must be runnable on this CPU; `nodes` must be a well-formed CWBVH (every child
/// index in range), which [`super::Accel`] guarantees by building it.
#[inline(always)]
pub(crate) unsafe fn walk<C: Counter>(
    nodes: &[WideNode],
    ray: &NodeRay,
    mut tmax: f32,
    counter: &mut C,
    mut hits: impl FnMut(&WideNode, &NodeRay, f32) -> u32,
    mut leaf: impl FnMut(u32, &mut f32, &mut C) -> Leaf,
) {
    if nodes.is_empty() {
        return;
    }
    // Only entries below `sp` are ever read.
    let mut stack = [std::mem::MaybeUninit::<(u32, u32)>::uninit(); STACK_SIZE];
    let mut sp = 0usize;
    // The root as a group of one: bit 31 with an empty internal mask finds node 0.
    let mut group = (0u32, 0x8000_0000u32);
    let mut prims = (0u32, 0u32);
    loop {
        while prims.1 != 0 {
            let i = 31 - prims.1.leading_zeros();
            prims.1 &= !(1u32 << i);
            counter.triangle();
            if let Leaf::Stop = leaf(prims.0 + i, &mut tmax, counter) {
                return;
            }
        }
        if group.1 & 0xff00_0000 != 0 {
            // SAFETY: `sp < STACK_SIZE` always.
            let index = unsafe { take_child(&mut group, &mut stack, &mut sp, ray.oct_inv) };
            debug_assert!(index < nodes.len());
            // SAFETY: child indices of a built CWBVH are in range.
            let node = unsafe { nodes.get_unchecked(index) };
            counter.node();
            let h = hits(node, ray, tmax);
            prefetch_children(nodes, node, ray.oct_inv, h);
            group = (node.child_base, (h & 0xff00_0000) | node.imask);
            prims = (node.prim_base, h & 0x00ff_ffff);
        } else {
            group = (0, 0);
        }
        if prims.1 == 0 && group.1 & 0xff00_0000 == 0 {
            if sp == 0 {
                return;
            }
            sp -= 1;
            // SAFETY: `sp < STACK_SIZE`, and every entry below the top was written.
            group = unsafe { stack.get_unchecked(sp).assume_init() };
        }
    }
}

/// Take the next child (highest traversal-order bit) out of `group`, which must have one,
/// pushing what is left of the group when anything is; returns the child's node index.
///
/// # Safety
/// `*sp < STACK_SIZE`.
#[inline(always)]
unsafe fn take_child(
    group: &mut (u32, u32),
    stack: &mut [std::mem::MaybeUninit<(u32, u32)>; STACK_SIZE],
    sp: &mut usize,
    oct_inv: u32,
) -> usize {
    let hits_imask = group.1;
    let bit = 31 - hits_imask.leading_zeros();
    group.1 &= !(1u32 << bit);
    if group.1 & 0xff00_0000 != 0 {
        // SAFETY: as the caller promises; `sp` saturates below.
        unsafe { stack.get_unchecked_mut(*sp).write(*group) };
        *sp = (*sp + 1).min(STACK_SIZE - 1);
    }
    let slot = (bit - 24) ^ oct_inv;
    let rel = (hits_imask & !(u32::MAX << slot)).count_ones();
    (group.0 + rel) as usize
}

/// One ray's walk, paused between choosing a node and testing it, so that a caller can
/// start loading the node and turn to other rays meanwhile (`super::batch`).
///
/// The stack holds node groups as described above; `next` is the node chosen to be
/// tested next.
pub(crate) struct Walk {
    /// Only entries below `sp` are ever read.
    stack: [std::mem::MaybeUninit<(u32, u32)>; STACK_SIZE],
    sp: usize,
    group: (u32, u32),
    prims: (u32, u32),
    next: usize,
}

impl Walk {
    /// A walk that starts at the root (none if `nodes` is empty).
    #[inline(always)]
    pub(crate) fn new(nodes: &[WideNode]) -> Walk {
        Walk {
            stack: [std::mem::MaybeUninit::uninit(); STACK_SIZE],
            sp: 0,
            // The root as a group of one: bit 31 with an empty internal mask finds node
            // 0; an empty tree as an empty group.
            group: if nodes.is_empty() {
                (0, 0)
            } else {
                (0, 0x8000_0000)
            },
            prims: (0, 0),
            next: 0,
        }
    }

    /// Test the primitives waiting from the last node, then choose the next node to test
    /// (`self.next`). False when the walk is over (nothing left, or `leaf` said stop).
    ///
    /// # Safety
    /// As for [`walk`].
    #[inline(always)]
    pub(crate) unsafe fn step<C: Counter>(
        &mut self,
        nodes: &[WideNode],
        ray: &NodeRay,
        tmax: &mut f32,
        counter: &mut C,
        leaf: &mut impl FnMut(u32, &mut f32, &mut C) -> Leaf,
    ) -> bool {
        while self.prims.1 != 0 {
            let i = 31 - self.prims.1.leading_zeros();
            self.prims.1 &= !(1u32 << i);
            counter.triangle();
            if let Leaf::Stop = leaf(self.prims.0 + i, tmax, counter) {
                return false;
            }
        }
        loop {
            if self.group.1 & 0xff00_0000 != 0 {
                // SAFETY: `sp < STACK_SIZE` always.
                self.next = unsafe {
                    take_child(&mut self.group, &mut self.stack, &mut self.sp, ray.oct_inv)
                };
                debug_assert!(self.next < nodes.len());
                return true;
            }
            if self.sp == 0 {
                return false;
            }
            self.sp -= 1;
            // SAFETY: `sp < STACK_SIZE`, and every entry below the top was written.
            self.group = unsafe { self.stack.get_unchecked(self.sp).assume_init() };
        }
    }

    /// The node `step` chose.
    #[inline(always)]
    pub(crate) fn next(&self) -> usize {
        self.next
    }

    /// Test the node `step` chose: its hit children become the current group, the
    /// primitives of its hit leaves wait for the next `step`.
    ///
    /// # Safety
    /// As for [`walk`], after a `step` that returned true.
    #[inline(always)]
    pub(crate) unsafe fn test<C: Counter>(
        &mut self,
        nodes: &[WideNode],
        ray: &NodeRay,
        tmax: f32,
        counter: &mut C,
        hits: &mut impl FnMut(&WideNode, &NodeRay, f32) -> u32,
    ) {
        // SAFETY: child indices of a built CWBVH are in range.
        let node = unsafe { nodes.get_unchecked(self.next) };
        counter.node();
        let h = hits(node, ray, tmax);
        self.group = (node.child_base, (h & 0xff00_0000) | node.imask);
        self.prims = (node.prim_base, h & 0x00ff_ffff);
    }

    /// The primitive slots waiting to be tested: the first slot and a mask of offsets.
    #[inline(always)]
    pub(crate) fn prims(&self) -> (u32, u32) {
        self.prims
    }
}

/// Start loading every internal child the node test hit, so that the ones visited
/// later (after the first child's subtree) are in cache by then and the first one's
/// four lines are fetched together.
#[inline(always)]
fn prefetch_children(nodes: &[WideNode], node: &WideNode, oct_inv: u32, h: u32) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let mut order = h >> 24;
        while order != 0 {
            let bit = order.trailing_zeros();
            order &= order - 1;
            let slot = bit ^ oct_inv;
            let rel = (node.imask & !(u32::MAX << slot)).count_ones();
            if let Some(child) = nodes.get((node.child_base + rel) as usize) {
                let p = child as *const WideNode as *const i8;
                // SAFETY: prefetching never faults; the lines are inside `child`.
                unsafe {
                    _mm_prefetch::<_MM_HINT_T0>(p);
                    _mm_prefetch::<_MM_HINT_T0>(p.add(64));
                    _mm_prefetch::<_MM_HINT_T0>(p.add(128));
                    _mm_prefetch::<_MM_HINT_T0>(p.add(192));
                }
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (nodes, node, oct_inv, h);
}

#[cfg(test)]
mod tests {
    use glam::{UVec2, Vec3, Vec3A};
    use obvhs::cwbvh::CwBvh;
    use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
    use obvhs::{aabb::Aabb, ray::Ray, traverse};

    use super::*;
    use crate::bvh::leaf::{self, PackedTri};
    use crate::bvh::{build, node_test, wide};
    use crate::intersect::WatertightRay;
    use crate::sampling::{PathKey, Purpose, uniform_sphere};

    /// Nodes visited (in order), triangle slots tested (in order), closest (t bits, slot).
    type Trace = (Vec<usize>, Vec<u32>, Option<(u32, u32)>);

    fn key(i: u32) -> PathKey {
        PathKey {
            seed: 5,
            pixel: i,
            sample: 0,
        }
    }

    fn soup(n: u32) -> Vec<[Vec3; 3]> {
        let size = 0.6 / (n as f32).cbrt();
        (0..n)
            .map(|i| {
                let k = key(i);
                let c = Vec3::new(
                    k.uniform(0, Purpose::Film, 0),
                    k.uniform(0, Purpose::Film, 1),
                    k.uniform(0, Purpose::Film, 2),
                ) * 1024.0;
                [0, 1, 2]
                    .map(|j| c + uniform_sphere(k.uniform2(1, Purpose::Film, j)) * size * 1024.0)
            })
            .collect()
    }

    fn inv(d: f32) -> f32 {
        if d.abs() >= 1e-28 {
            1.0 / d
        } else if d < 0.0 {
            -1e28
        } else {
            1e28
        }
    }

    /// The traversal as it was: obvhs's `traverse!` and `intersect_ray`.
    fn with_obvhs(bvh: &CwBvh, tris: &[[Vec3; 3]], o: Vec3, d: Vec3) -> Trace {
        let d = d + Vec3::ZERO;
        let mut trav = Ray {
            origin: Vec3A::from(o),
            direction: Vec3A::from(d),
            inv_direction: Vec3A::new(inv(d.x), inv(d.y), inv(d.z)),
            tmin: 0.0,
            tmax: f32::INFINITY,
        };
        let wt = WatertightRay::new(o, d);
        let (mut nodes, mut slots, mut best) = (Vec::new(), Vec::new(), None);
        let mut state = bvh.new_traversal(trav.direction);
        let mut node;
        traverse!(
            bvh,
            node,
            state,
            {
                nodes.push(
                    (node as *const _ as usize - bvh.nodes.as_ptr() as usize)
                        / std::mem::size_of_val(node),
                );
                node.intersect_ray(&trav, state.oct_inv4)
            },
            {
                let slot = state.primitive_id;
                slots.push(slot);
                let [a, b, c] = tris[slot as usize];
                if let Some(h) = wt.intersect(a, b, c, trav.tmin, trav.tmax) {
                    trav.tmax = h.t;
                    best = Some((h.t.to_bits(), slot));
                }
            }
        );
        (nodes, slots, best)
    }

    fn with_walk(nodes: &[WideNode], tris: &[PackedTri], simd: Simd, o: Vec3, d: Vec3) -> Trace {
        let d = d + Vec3::ZERO;
        let ray = NodeRay::new(
            Vec3A::from(o),
            Vec3A::from(d),
            Vec3A::new(inv(d.x), inv(d.y), inv(d.z)),
            0.0,
        );
        let wt = WatertightRay::new(o, d);
        let (mut visited, mut slots, mut best) = (Vec::new(), Vec::new(), None);
        let base = nodes.as_ptr() as usize;
        let mut leaf = |slot: u32, tmax: &mut f32, _: &mut ()| {
            slots.push(slot);
            if let Some(h) = leaf::intersect(&wt, &tris[slot as usize], 0.0, *tmax) {
                *tmax = h.t;
                best = Some((h.t.to_bits(), slot));
            }
            Leaf::Continue
        };
        let mut record = |n: &WideNode| {
            visited.push((n as *const _ as usize - base) / std::mem::size_of::<WideNode>())
        };
        // SAFETY: the nodes come from a built CWBVH; each level is checked as supported.
        unsafe {
            match simd {
                Simd::Portable => walk(
                    nodes,
                    &ray,
                    f32::INFINITY,
                    &mut (),
                    |n, r, t| {
                        record(n);
                        node_test::hits_portable(n, r, t)
                    },
                    &mut leaf,
                ),
                #[cfg(target_arch = "x86_64")]
                Simd::Sse2 => walk(
                    nodes,
                    &ray,
                    f32::INFINITY,
                    &mut (),
                    |n, r, t| {
                        record(n);
                        node_test::x86::hits_sse2(n, r, t)
                    },
                    &mut leaf,
                ),
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => walk(
                    nodes,
                    &ray,
                    f32::INFINITY,
                    &mut (),
                    |n, r, t| {
                        record(n);
                        node_test::x86::hits_avx2(n, r, t)
                    },
                    &mut leaf,
                ),
                #[cfg(not(target_arch = "x86_64"))]
                _ => unreachable!(),
            }
        }
        (visited, slots, best)
    }

    /// Every ray finds the same closest hit with obvhs's traversal (quantised boxes) and
    /// with each build of ours (exact boxes), and ours, with tighter boxes, visit fewer
    /// nodes and test fewer triangles in all.
    #[test]
    fn same_hits_as_obvhs_traverse_with_fewer_visits() {
        let tris = soup(20_000);
        let aabbs: Vec<Aabb> = tris
            .iter()
            .map(|t| {
                let lo = t[0].min(t[1]).min(t[2]);
                let hi = t[0].max(t[1]).max(t[2]);
                Aabb::new(Vec3A::from(lo), Vec3A::from(hi))
            })
            .collect();
        let bvh = bvh2_to_cwbvh(&build::build(&aabbs), 3, true, false);
        let ordered: Vec<[Vec3; 3]> = bvh
            .primitive_indices
            .iter()
            .map(|&i| tris[i as usize])
            .collect();
        let packed: Vec<PackedTri> = ordered.iter().map(|&t| PackedTri::new(t)).collect();
        let nodes = wide::from_cwbvh(&bvh, &packed);
        let levels: Vec<Simd> = [Simd::Portable, Simd::Sse2, Simd::Avx2]
            .into_iter()
            .filter(|s| s.supported())
            .collect();
        let (mut visits, mut hits, mut tested) = (0, 0, 0);
        let mut ours = vec![(0usize, 0usize); levels.len()];
        for i in 0..4_000u32 {
            let k = key(100_000 + i);
            let o = Vec3::new(
                k.uniform(2, Purpose::Film, 0),
                k.uniform(2, Purpose::Film, 1),
                k.uniform(2, Purpose::Film, 2),
            ) * 1400.0
                - 200.0;
            let mut d = uniform_sphere(k.uniform2(3, Purpose::Film, 0));
            // Axis-parallel and signed-zero directions too.
            match i % 5 {
                0 => d = Vec3::new(0.0, -0.0, d.z.signum()),
                1 => d.x = -0.0,
                _ => {}
            }
            let want = with_obvhs(&bvh, &ordered, o, d);
            visits += want.0.len();
            hits += want.2.is_some() as u32;
            for (&s, total) in levels.iter().zip(&mut ours) {
                let got = with_walk(&nodes, &packed, s, o, d);
                assert_eq!(got.2, want.2, "ray {i}, {s:?}");
                total.0 += got.0.len();
                total.1 += got.1.len();
            }
            tested += want.1.len();
        }
        assert!(visits > 10_000 && hits > 500, "{visits} {hits}");
        for (&s, &(v, t)) in levels.iter().zip(&ours) {
            assert!(
                v < visits && t < tested,
                "{s:?}: {v} nodes, {t} triangles; obvhs {visits}, {tested}"
            );
        }
    }
}
