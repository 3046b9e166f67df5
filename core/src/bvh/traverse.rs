//! The traversal loop over [`WideNode`]s, with the node test of `node_test` and the leaf
//! test of `leaf4` inlined into one function per instruction set.
//!
//! Nearest child first, as Embree's single-ray traversal does: a node's test gives each
//! hit child's entry distance; its hit leaves are tested first (they may lower the far
//! limit), then the nearest internal child is visited next and the
//! others wait on a stack with their distances, nearest on top. An entry the far limit no
//! longer reaches is dropped when it comes off the stack, without loading its node. (The
//! first traversal was obvhs's: children in a fixed order by the ray's octant, Ylitie et
//! al. 2017, and node groups on the stack; it visited more nodes and could not drop them
//! unread.) The answers do not depend on the order: see `super`'s doc.

use super::leaf4::Tri4;
use super::node_test::{NodeHits, NodeRay};
use super::wide::{INTERNAL, WideNode};

/// Which build of the node test runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Simd {
    /// Plain Rust, eight children one by one (non-x86-64 targets; tests).
    Portable,
    /// SSE2, four children at a time: every x86-64 CPU.
    Sse2,
    /// AVX2 and FMA, eight children at a time, chosen at run time when the CPU has them.
    Avx2,
    /// The AVX2 node test and the whole loop compiled for AVX-512 (F, VL, BW, DQ) and
    /// BMI1/2, chosen at run time when the CPU has them: the same operations on the same
    /// values (so the same answers, bit for bit), with 32 vector registers instead of
    /// 16, mask registers for the compares and three-operand bit logic. 3-5% more
    /// incoherent rays a second and 7% more primary ones than [`Simd::Avx2`] on Lucy
    /// (one core of an AMD EPYC with AVX-512, 2026-11-27).
    Avx512,
}

impl Simd {
    /// The best this CPU runs.
    pub fn detect() -> Simd {
        #[cfg(target_arch = "x86_64")]
        {
            let avx2 = std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
                && std::arch::is_x86_feature_detected!("popcnt")
                && std::arch::is_x86_feature_detected!("lzcnt");
            let avx512 = std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512dq")
                && std::arch::is_x86_feature_detected!("bmi1")
                && std::arch::is_x86_feature_detected!("bmi2");
            if avx2 && avx512 {
                Simd::Avx512
            } else if avx2 {
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
            Simd::Avx2 => matches!(Simd::detect(), Simd::Avx2 | Simd::Avx512),
            #[cfg(target_arch = "x86_64")]
            Simd::Avx512 => Simd::detect() == Simd::Avx512,
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }
}

/// The node-test builds this CPU can run, for tests that compare them; the others are
/// named on stderr (uncaptured), so a run on a CPU without AVX-512 (or AVX2) says what it
/// did not test.
#[cfg(test)]
pub(crate) fn testable_levels() -> Vec<Simd> {
    let all = [Simd::Portable, Simd::Sse2, Simd::Avx2, Simd::Avx512];
    let (here, absent): (Vec<Simd>, Vec<Simd>) = all.into_iter().partition(|s| s.supported());
    if !absent.is_empty() {
        // Straight to stderr, past the test harness's capture: a passing run says so too.
        use std::io::Write;
        let _ = writeln!(
            std::io::stderr(),
            "NOTE: this CPU cannot run the {absent:?} node-test builds: not tested here"
        );
    }
    here
}

/// Counts of one traversal, for profiles (`Accel::closest_counted`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalCounts {
    /// Nodes whose eight children were tested.
    pub nodes: u64,
    /// Triangles tested (the triangles of the leaves tested).
    pub triangles: u64,
    /// Leaves tested (each up to four triangles, tested together).
    pub leaves: u64,
}

/// Something that counts node and leaf tests; the `()` counter compiles to nothing.
pub(crate) trait Counter {
    fn node(&mut self);
    /// The test of `leaf`.
    fn leaf(&mut self, leaf: &Tri4);
}

impl Counter for () {
    #[inline(always)]
    fn node(&mut self) {}
    #[inline(always)]
    fn leaf(&mut self, _: &Tri4) {}
}

impl Counter for TraversalCounts {
    #[inline(always)]
    fn node(&mut self) {
        self.nodes += 1;
    }
    #[inline(always)]
    fn leaf(&mut self, leaf: &Tri4) {
        self.leaves += 1;
        self.triangles += u64::from(leaf.count());
    }
}

/// What the leaf callback tells the loop.
pub(crate) enum Leaf {
    Continue,
    Stop,
}

/// Walk `nodes` for `ray`, calling `leaf(leaf, &mut tmax, counter)` for every hit leaf
/// (an index into the accelerator's `Tri4`s). `tmax` is the far limit of the node test;
/// the callback may lower it.
///
/// # Safety
/// `hits` must be runnable on this CPU; `nodes` must be well formed (every child index
/// in range), which [`super::Accel`] guarantees by building them.
#[inline(always)]
pub(crate) unsafe fn walk<C: Counter>(
    nodes: &[WideNode],
    ray: &NodeRay,
    mut tmax: f32,
    counter: &mut C,
    mut hits: impl FnMut(&WideNode, &NodeRay, f32) -> NodeHits,
    mut leaf: impl FnMut(u32, &mut f32, &mut C) -> Leaf,
) {
    if nodes.is_empty() {
        return;
    }
    let mut stack = Stack::new();
    let mut index = 0usize;
    loop {
        // SAFETY: child indices of built nodes are in range.
        let node = unsafe { nodes.get_unchecked(index) };
        counter.node();
        let h = hits(node, ray, tmax);
        // Start loading every hit child now: the nearest is next, the others come off
        // the stack later, and their leaf tests run meanwhile.
        let mut children = h.mask;
        while children != 0 {
            let s = children.trailing_zeros() as usize;
            children &= children - 1;
            // SAFETY: `s < 8`.
            let word = unsafe { *node.slot.get_unchecked(s) };
            if let Some(child) = nodes.get((word & !INTERNAL) as usize) {
                prefetch(child, std::mem::size_of::<WideNode>());
            }
        }
        let mut leaves = h.leaves;
        while leaves != 0 {
            let i = leaves.trailing_zeros();
            leaves &= leaves - 1;
            if let Leaf::Stop = leaf(node.leaf_base + i, &mut tmax, counter) {
                return;
            }
        }
        // The nearest hit child next, the others on the stack; else the nearest entry
        // of the stack that the (possibly lowered) far limit still reaches.
        let next = match stack.push_children(node, &h, tmax) {
            Some((child, _)) => Some(child),
            None => stack.pop(tmax),
        };
        match next {
            Some(child) => index = child,
            None => return,
        }
    }
}

/// Ask the processor to start loading `bytes` from `p` into the first-level cache.
#[inline(always)]
pub(crate) fn prefetch<T>(p: *const T, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let p = p as *const i8;
        let mut off = 0;
        while off < bytes {
            // SAFETY: prefetching never faults.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(off)) };
            off += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (p, bytes);
}

/// Entries of the node stack: a node pushes at most seven (its hit children but the
/// nearest) and holds them while its subtree is walked, and no leaf is deeper than
/// [`super::build::MAX_DEPTH`], so the stack never fills.
const STACK_SIZE: usize = 7 * super::build::MAX_DEPTH as usize + 1;

/// Nodes waiting to be visited, each with its box's entry distance.
pub(crate) struct Stack {
    /// Only entries below `sp` are ever read.
    entries: [std::mem::MaybeUninit<(u32, f32)>; STACK_SIZE],
    sp: usize,
}

impl Stack {
    #[inline(always)]
    pub(crate) fn new() -> Stack {
        Stack {
            // SAFETY: an array of `MaybeUninit` needs no initialisation (the idiom of
            // `MaybeUninit`'s docs; `[MaybeUninit::uninit(); N]` compiled to a memset of
            // the whole stack per ray here).
            entries: unsafe { std::mem::MaybeUninit::uninit().assume_init() },
            sp: 0,
        }
    }

    /// Push the internal children `h` found whose boxes the ray enters before `tmax`,
    /// farthest first, all but the nearest, which is returned.
    #[inline(always)]
    pub(crate) fn push_children(
        &mut self,
        node: &WideNode,
        h: &NodeHits,
        tmax: f32,
    ) -> Option<(usize, f32)> {
        let base = self.sp;
        let mut nearest: Option<(u32, f32)> = None;
        let mut mask = h.mask;
        while mask != 0 {
            let s = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            // SAFETY: `s < 8`.
            let (word, t) = unsafe { (*node.slot.get_unchecked(s), *h.tnear.get_unchecked(s)) };
            debug_assert!(word & INTERNAL != 0);
            if t > tmax {
                continue;
            }
            let child = (word & !INTERNAL, t);
            match nearest {
                None => nearest = Some(child),
                Some(n) => {
                    // The farther of the two waits on the stack, kept sorted near the
                    // top so the nearer of the waiting ones comes off first.
                    let (keep, wait) = if t < n.1 { (child, n) } else { (n, child) };
                    self.push_sorted(wait, base);
                    nearest = Some(keep);
                }
            }
        }
        nearest.map(|(i, t)| (i as usize, t))
    }

    /// Push `e`, moving it below the entries just pushed for the same node that are
    /// nearer (at most six), so that a node's children come off nearest first.
    #[inline(always)]
    fn push_sorted(&mut self, e: (u32, f32), base: usize) {
        debug_assert!(self.sp < STACK_SIZE);
        // SAFETY: `sp < STACK_SIZE` (see `STACK_SIZE`); entries below `sp` are written,
        // and `base <= j <= sp`.
        unsafe {
            let mut j = self.sp;
            while j > base {
                let below = self.entries.get_unchecked(j - 1).assume_init();
                if below.1 >= e.1 {
                    break;
                }
                self.entries.get_unchecked_mut(j).write(below);
                j -= 1;
            }
            self.entries.get_unchecked_mut(j).write(e);
            self.sp += 1;
        }
    }

    /// The nearest remaining entry whose distance `tmax` still reaches (farther ones
    /// are dropped: the far limit only ever decreases).
    #[inline(always)]
    pub(crate) fn pop(&mut self, tmax: f32) -> Option<usize> {
        while self.sp > 0 {
            self.sp -= 1;
            // SAFETY: every entry below the old `sp` was written.
            let (i, t) = unsafe { self.entries.get_unchecked(self.sp).assume_init() };
            if t <= tmax {
                return Some(i as usize);
            }
        }
        None
    }
}

/// One ray's walk, paused between choosing a node and testing it, so that a caller can
/// start loading the node and turn to other rays meanwhile (`super::batch`).
pub(crate) struct Walk {
    stack: Stack,
    /// The node chosen to be tested next.
    next: usize,
    /// Whether `next` holds a node (false when the walk is over or not started).
    has_next: bool,
    /// The last tested node's hit leaves, waiting for `step`: the first leaf and a mask
    /// of offsets from it.
    leaves: (u32, u32),
    /// The last tested node's nearest hit child, to be visited after its leaves
    /// (which may lower the far limit below it).
    near_child: Option<(usize, f32)>,
}

impl Walk {
    /// A walk that starts at the root (none if `nodes` is empty).
    #[inline(always)]
    pub(crate) fn new(nodes: &[WideNode]) -> Walk {
        Walk {
            stack: Stack::new(),
            next: 0,
            has_next: !nodes.is_empty(),
            leaves: (0, 0),
            near_child: None,
        }
    }

    /// Test the leaves waiting from the last node, then choose the next node to test
    /// (`self.next`). False when the walk is over (nothing left, or `leaf` said stop).
    ///
    /// # Safety
    /// As for [`walk`].
    #[inline(always)]
    pub(crate) unsafe fn step<C: Counter>(
        &mut self,
        tmax: &mut f32,
        counter: &mut C,
        leaf: &mut impl FnMut(u32, &mut f32, &mut C) -> Leaf,
    ) -> bool {
        if self.has_next {
            // The root, before anything was tested.
            return true;
        }
        while self.leaves.1 != 0 {
            let i = self.leaves.1.trailing_zeros();
            self.leaves.1 &= self.leaves.1 - 1;
            if let Leaf::Stop = leaf(self.leaves.0 + i, tmax, counter) {
                return false;
            }
        }
        let next = match self.near_child.take() {
            Some((i, t)) if t <= *tmax => Some(i),
            _ => self.stack.pop(*tmax),
        };
        match next {
            Some(i) => {
                self.next = i;
                self.has_next = true;
                true
            }
            None => false,
        }
    }

    /// The node `step` chose.
    #[inline(always)]
    pub(crate) fn next(&self) -> usize {
        self.next
    }

    /// Test the node `step` chose: its hit children go on the stack (the nearest kept
    /// aside), its hit leaves wait for the next `step`.
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
        hits: &mut impl FnMut(&WideNode, &NodeRay, f32) -> NodeHits,
    ) {
        // SAFETY: child indices of built nodes are in range.
        let node = unsafe { nodes.get_unchecked(self.next) };
        self.has_next = false;
        counter.node();
        let h = hits(node, ray, tmax);
        self.leaves = (node.leaf_base, h.leaves);
        self.near_child = self.stack.push_children(node, &h, tmax);
    }

    /// The leaves waiting to be tested: the first leaf and a mask of offsets.
    #[inline(always)]
    pub(crate) fn leaves(&self) -> (u32, u32) {
        self.leaves
    }
}

#[cfg(test)]
mod tests {
    use glam::{UVec2, Vec3, Vec3A};
    use obvhs::cwbvh::CwBvh;
    use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;
    use obvhs::{aabb::Aabb, ray::Ray, traverse};

    use super::*;
    use crate::bvh::leaf4::{self, Tri4};
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

    /// Our walk over `nodes` and their leaves `tris`, leaf `k` holding the primitive slots
    /// `runs[k].0..` (`runs[k].1` of them) in its lanes; a lane's hit is kept when nearer
    /// than the last kept, lane by lane, as the one-triangle-at-a-time loop of obvhs's.
    fn with_walk(
        nodes: &[WideNode],
        tris: &[Tri4],
        runs: &[(u32, u32)],
        simd: Simd,
        o: Vec3,
        d: Vec3,
    ) -> Trace {
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
        let mut leaf = |k: u32, tmax: &mut f32, _: &mut ()| {
            let (first, count) = runs[k as usize];
            slots.extend(first..first + count);
            let h = leaf4::intersect(&wt, &tris[k as usize], 0.0, *tmax);
            for lane in 0..4 {
                if h.mask >> lane & 1 != 0 && h.t[lane] < *tmax {
                    *tmax = h.t[lane];
                    best = Some((h.t[lane].to_bits(), first + lane as u32));
                }
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
                Simd::Avx2 | Simd::Avx512 => walk(
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
        let bvh = bvh2_to_cwbvh(&build::build(aabbs.clone()), 3, true, false);
        let ordered: Vec<[Vec3; 3]> = bvh
            .primitive_indices
            .iter()
            .map(|&i| tris[i as usize])
            .collect();
        let runs = wide::leaves(&bvh);
        let packed: Vec<Tri4> = runs
            .iter()
            .map(|&(first, count)| {
                let tris: Vec<([Vec3; 3], u32)> = (first..first + count)
                    .map(|p| (ordered[p as usize], p))
                    .collect();
                Tri4::new(&tris)
            })
            .collect();
        let nodes = wide::from_cwbvh(&bvh, &packed, None);
        let levels: Vec<Simd> = testable_levels();
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
                let got = with_walk(&nodes, &packed, &runs, s, o, d);
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
