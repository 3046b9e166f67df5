//! The binary BVH that [`super::Accel`] hands to obvhs's CWBVH conversion: top-down
//! binned SAH, built with an explicit work stack and a bounded depth.
//!
//! obvhs's own builder (PLOC) is not used: on degenerate input it degrades badly. With
//! many coincident triangles every merge cost ties, PLOC merges one pair per pass
//! (quadratic time: minutes for 100k triangles) into a chain as deep as the triangle
//! count, and the recursive BVH2-to-CWBVH conversion then overflows the thread's stack.
//! Nested triangles sharing a centroid do the same with distinct costs. This builder
//! cannot: a node whose subtree could end deeper than [`MAX_DEPTH`] is cut at the
//! median (by index when every centroid is the same point), so the tree is at most
//! [`MAX_DEPTH`] deep whatever the input, the conversion's recursion is bounded, the
//! build is O(n log n), and the CWBVH stays within obvhs's fixed traversal stack.

use glam::Vec3A;
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::node::Bvh2Node;

/// Deepest leaf (the root is depth 0). At least 32 (a balanced tree over 2^32
/// primitives); the rest is room for SAH's unbalanced cuts.
pub const MAX_DEPTH: u32 = 64;

/// SAH bins per axis.
const BINS: usize = 16;

/// Subtrees over at least this many primitives are built on two threads (rayon's
/// pool); smaller ones on the calling thread.
const PARALLEL_MIN: usize = 4096;

struct Task {
    node: usize,
    start: usize,
    end: usize,
    depth: u32,
    /// The bounds of the range's centroids (from the partition that made the range).
    centroids: Centroids,
}

/// The bounds of a set of centroids: (lower, upper) corners.
type Centroids = (Vec3A, Vec3A);

const NO_CENTROIDS: Centroids = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);

/// A cut: the left side's length, the two sides' boxes and their centroids' bounds.
struct Cut {
    mid: usize,
    boxes: (Aabb, Aabb),
    centroids: (Centroids, Centroids),
}

/// The primitives of one range, side by side: `order[j]` is the index (into the whole
/// input) of the primitive whose box is `boxes[j]`. Every cut reorders both alike.
///
/// The boxes travel with the order so that binning and partitioning read them in
/// sequence, not through the indices (scattered reads, which were most of the cut's
/// time on a large mesh).
struct Range<'a> {
    order: &'a mut [u32],
    boxes: &'a mut [Aabb],
}

impl Range<'_> {
    fn len(&self) -> usize {
        self.order.len()
    }

    fn sub(&mut self, start: usize, end: usize) -> Range<'_> {
        Range {
            order: &mut self.order[start..end],
            boxes: &mut self.boxes[start..end],
        }
    }

    fn split_at(self, mid: usize) -> (Self, Self) {
        let (lo, ro) = self.order.split_at_mut(mid);
        let (lb, rb) = self.boxes.split_at_mut(mid);
        (
            Range {
                order: lo,
                boxes: lb,
            },
            Range {
                order: ro,
                boxes: rb,
            },
        )
    }
}

/// A BVH2 over `aabbs` with one primitive per leaf (what the CWBVH conversion expects),
/// at most [`MAX_DEPTH`] deep. Every box must be finite; `aabbs` must not be empty and
/// must have fewer than 2^31 entries. The boxes are reordered in place (into leaf
/// order) rather than copied: on a large mesh every fresh page costs a fault.
///
/// The top of the tree is built in parallel (the two sides of a cut are independent),
/// and the nodes are numbered as one thread working through a stack, left side first,
/// would number them: the tree is the same, node for node, on any number of threads.
pub fn build(mut boxes: Vec<Aabb>) -> Bvh2 {
    let n = boxes.len();
    let mut order: Vec<u32> = (0..n as u32).collect();
    let root = boxes.iter().fold(Aabb::empty(), |a, b| a.union(b));
    let centroids = centroid_bounds(&boxes);
    // Every node is written by the build; zeroed memory (a `Bvh2Node` of zero bits is its
    // default) spares a pass writing defaults over the whole list first.
    let mut nodes: Vec<Bvh2Node> = bytemuck::zeroed_vec(2 * n - 1);
    let (top, rest) = nodes.split_at_mut(1);
    let range = Range {
        order: &mut order,
        boxes: &mut boxes,
    };
    top[0] = subtree(range, 0, 0, (root, centroids), rest, 1);
    Bvh2 {
        nodes,
        primitive_indices: order,
        max_depth: MAX_DEPTH as usize + 1,
        ..Bvh2::default()
    }
}

/// The subtree over `range` (the primitives `start..start + range.len()` of the whole
/// order), whose root has box `bounds.0` (and centroids within `bounds.1`) and sits at
/// `depth`, numbered as one thread would number it: a cut's two children side by side
/// when the cut is made, the left side's subtree before the right's. A subtree over `k`
/// primitives has `2k - 1` nodes; its root is returned (its parent places it), the other
/// `2k - 2` are written into `rest`, which the whole tree numbers from `offset`. Leaves
/// point into the whole order.
///
/// Large subtrees cut in parallel: the two sides' nodes go to the two halves of `rest`
/// after the children's pair, each written once, in place.
fn subtree(
    mut range: Range,
    start: usize,
    depth: u32,
    bounds: (Aabb, Centroids),
    rest: &mut [Bvh2Node],
    offset: usize,
) -> Bvh2Node {
    let count = range.len();
    debug_assert_eq!(rest.len(), 2 * count - 2);
    let (aabb, centroids) = bounds;
    if count < PARALLEL_MIN {
        return sequential(range, start, depth, bounds, rest, offset);
    }
    let cut = cut(&mut range, depth, centroids);
    let mid = cut.mid;
    let (left, right) = range.split_at(mid);
    // The children's pair, then the rest of the left subtree, then the right's.
    let (pair, sides) = rest.split_at_mut(2);
    let (left_rest, right_rest) = sides.split_at_mut(2 * mid - 2);
    let (l_offset, r_offset) = (offset + 2, offset + 2 + left_rest.len());
    let l_bounds = (cut.boxes.0, cut.centroids.0);
    let r_bounds = (cut.boxes.1, cut.centroids.1);
    let (l, r) = rayon::join(
        || subtree(left, start, depth + 1, l_bounds, left_rest, l_offset),
        || {
            subtree(
                right,
                start + mid,
                depth + 1,
                r_bounds,
                right_rest,
                r_offset,
            )
        },
    );
    pair[0] = l;
    pair[1] = r;
    Bvh2Node::new(aabb, 0, offset as u32)
}

/// [`subtree`] on one thread, with an explicit work stack: the same numbering, each
/// node written once, in place. A side of one primitive is made a leaf when its cut's
/// pair is written (a leaf numbers no nodes, so when does not matter).
fn sequential(
    mut range: Range,
    start: usize,
    depth: u32,
    bounds: (Aabb, Centroids),
    rest: &mut [Bvh2Node],
    offset: usize,
) -> Bvh2Node {
    let n = range.len();
    if n <= 1 {
        return Bvh2Node::new(bounds.0, 1, start as u32);
    }
    // Node `k` of the subtree: its root for 0, else `rest[k - 1]` (`offset + k - 1` in
    // the whole tree).
    let mut root = Bvh2Node::new(bounds.0, 0, 0);
    let mut next = 1;
    let mut stack = vec![Task {
        node: 0,
        start: 0,
        end: n,
        depth,
        centroids: bounds.1,
    }];
    while let Some(task) = stack.pop() {
        let mut sub = range.sub(task.start, task.end);
        let cut = cut(&mut sub, task.depth, task.centroids);
        let first = next;
        next += 2;
        let node = if task.node == 0 {
            &mut root
        } else {
            &mut rest[task.node - 1]
        };
        node.first_index = (offset + first - 1) as u32;
        let sides = [
            (
                task.start,
                task.start + cut.mid,
                cut.boxes.0,
                cut.centroids.0,
            ),
            (task.start + cut.mid, task.end, cut.boxes.1, cut.centroids.1),
        ];
        for (k, (begin, end, aabb, _)) in sides.into_iter().enumerate() {
            rest[first + k - 1] = if end - begin == 1 {
                Bvh2Node::new(aabb, 1, (start + begin) as u32)
            } else {
                Bvh2Node::new(aabb, 0, 0)
            };
        }
        // Right side below the left on the stack: the left is cut first.
        for (k, (begin, end, _, centroids)) in sides.into_iter().enumerate().rev() {
            if end - begin > 1 {
                stack.push(Task {
                    node: first + k,
                    start: begin,
                    end,
                    depth: task.depth + 1,
                    centroids,
                });
            }
        }
    }
    root
}

/// Cut `range` (at least two primitives, at `depth`, centroids within `centroids`) in
/// two: reorders it so the left side comes first and returns the cut.
fn cut(range: &mut Range, depth: u32, centroids: Centroids) -> Cut {
    // Two primitives have one cut, one each side: no bins needed (a third of all cuts,
    // each of which would clear and sweep 48 bins). The sides are leaves, which read
    // no centroid bounds.
    if let [a, b] = *range.boxes {
        return Cut {
            mid: 1,
            boxes: (a, b),
            centroids: (NO_CENTROIDS, NO_CENTROIDS),
        };
    }
    // A median cut from here ends at depth + ceil(log2(count)); once that reaches
    // the limit, only median cuts keep the promise.
    let force_median = depth + ceil_log2(range.len()) >= MAX_DEPTH;
    let sah = if force_median {
        None
    } else {
        sah_cut(range, centroids)
    };
    match sah {
        Some(cut) => cut,
        None => {
            let mid = median_cut(range, centroids);
            let (left, right) = range.boxes.split_at(mid);
            let whole = |b: &[Aabb]| b.iter().fold(Aabb::empty(), |a, b| a.union(b));
            Cut {
                mid,
                boxes: (whole(left), whole(right)),
                centroids: (centroid_bounds(left), centroid_bounds(right)),
            }
        }
    }
}

fn ceil_log2(n: usize) -> u32 {
    n.next_power_of_two().trailing_zeros()
}

fn centroid_bounds(boxes: &[Aabb]) -> Centroids {
    let (mut lo, mut hi) = NO_CENTROIDS;
    for b in boxes {
        let c = b.center();
        lo = lo.min(c);
        hi = hi.max(c);
    }
    (lo, hi)
}

/// Reorder `range` about its median on the centroids' longest axis and return the cut
/// (`len / 2`). With every centroid at one point the order is left as it is.
///
/// The selection runs on the range's positions, each compared by what it holds
/// (centroid, then primitive index): `select_nth_unstable_by` on `u32`s reorders by the
/// comparisons alone, so the positions end as the indices themselves would (as the
/// build always selected them); the order and the boxes then follow. Median cuts are
/// rare (degenerate input, the depth limit), so the two scratch lists cost little.
fn median_cut(range: &mut Range, centroids: Centroids) -> usize {
    let mid = range.len() / 2;
    let (lo, hi) = centroids;
    let extent = hi - lo;
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    if extent[axis] > 0.0 {
        let (order, boxes) = (&mut *range.order, &mut *range.boxes);
        let mut at: Vec<u32> = (0..order.len() as u32).collect();
        at.select_nth_unstable_by(mid, |&a, &b| {
            let (a, b) = (a as usize, b as usize);
            let ca = boxes[a].center_axis(axis);
            let cb = boxes[b].center_axis(axis);
            ca.total_cmp(&cb).then(order[a].cmp(&order[b]))
        });
        let moved: Vec<(u32, Aabb)> = at
            .iter()
            .map(|&p| (order[p as usize], boxes[p as usize]))
            .collect();
        for ((o, b), (i, aabb)) in order.iter_mut().zip(boxes.iter_mut()).zip(moved) {
            (*o, *b) = (i, aabb);
        }
    }
    mid
}

/// The binned-SAH cut of `range` (centroids within `centroids`): reorders it so the
/// left side comes first and returns the cut, or `None` when no bin boundary separates
/// the centroids (or the costs are not finite), for the caller to cut at the median
/// instead.
///
/// One pass bins every axis, and the sides' bounds are the unions of their bins' boxes:
/// min and max are exact, so they are the very boxes a pass over each side would give.
/// The partition's pass takes the sides' centroid bounds on the way (for their cuts).
fn sah_cut(range: &mut Range, centroids: Centroids) -> Option<Cut> {
    let (lo, hi) = centroids;
    let extent = hi - lo;
    // Zero, NaN and infinite extents have no bins to place (one bit an axis).
    let binned = (extent.is_finite_mask() & extent.cmpgt(Vec3A::ZERO)).bitmask();
    let to_bin = bin_scale(extent);
    let mut count = [[0u32; BINS]; 3];
    let mut boxes = [[Aabb::empty(); BINS]; 3];
    // Every axis is binned, also one with no bins to place (its lanes land in bins the
    // sweep below never reads): no branch per axis. `k & (BINS - 1)` is `k` (bins_of
    // clamps to the last bin) and lets the compiler drop the bounds checks.
    const _: () = assert!(BINS.is_power_of_two());
    for b in range.boxes.iter() {
        let bins = bins_of(b.center(), lo, to_bin);
        for axis in 0..3 {
            let k = bins[axis] & (BINS - 1);
            count[axis][k] += 1;
            boxes[axis][k] = boxes[axis][k].union(b);
        }
    }
    let mut best: Option<(f32, usize, usize)> = None; // (cost, axis, first right bin)
    for axis in (0..3).filter(|&a| binned >> a & 1 != 0) {
        sweep(&count[axis], &boxes[axis], axis, &mut best);
    }
    let (_, axis, split) = best?;
    // Two-pointer partition: left of `mid` the bins below `split`. A centroid's bin is
    // below `split` exactly when its scaled offset is not at least `split` (bins_of
    // clamps, then truncates; `split` is a whole number in 1..BINS, and a NaN offset
    // goes to bin 0), so no bin index is needed: one compare of all three lanes.
    //
    // Without a branch per primitive (which side it goes is a coin toss to the branch
    // predictor): a left primitive is swapped with the one at `mid`, a right one with
    // itself. The sides' centroid bounds are taken after, a pass over each (selecting
    // per primitive which side's bounds to grow cost more than the passes).
    let edge = Vec3A::splat(split as f32);
    let axis_bit = 1u32 << axis;
    let mut mid = 0;
    let (prims, order) = (&mut *range.boxes, &mut *range.order);
    for j in 0..prims.len() {
        let b = prims[j];
        let goes_right = ((b.center() - lo) * to_bin).cmpge(edge).bitmask() & axis_bit != 0;
        // The swap partner: `mid` for a left primitive, `j` itself for a right one.
        let to = if goes_right { j } else { mid };
        prims[j] = prims[to];
        prims[to] = b;
        order.swap(j, to);
        mid += usize::from(!goes_right);
    }
    if !(mid > 0 && mid < range.len()) {
        return None;
    }
    let union = |bins: &[Aabb]| bins.iter().fold(Aabb::empty(), |a, b| a.union(b));
    let sides = (union(&boxes[axis][..split]), union(&boxes[axis][split..]));
    let (left, right) = range.boxes.split_at(mid);
    Some(Cut {
        mid,
        boxes: sides,
        centroids: (centroid_bounds(left), centroid_bounds(right)),
    })
}

/// The best SAH cut among `axis`'s bins, kept in `best` (cost, axis, first right bin)
/// when cheaper than what it holds (of equal costs the first found stays).
///
/// Only cuts just above an occupied bin are looked at: a run of empty bins leaves both
/// sides and the cost as they were, and of equal costs the first (that one) wins, so
/// the cut is the one a sweep over every bin finds (a test holds the two together).
/// Near the leaves most bins are empty.
fn sweep(
    count: &[u32; BINS],
    boxes: &[Aabb; BINS],
    axis: usize,
    best: &mut Option<(f32, usize, usize)>,
) {
    // The occupied bins in order, from a mask of them (no branch per bin).
    let mut bits = count
        .iter()
        .enumerate()
        .fold(0u32, |m, (k, &c)| m | u32::from(c > 0) << k);
    let mut occupied = [0usize; BINS];
    let mut m = 0;
    while bits != 0 {
        occupied[m] = bits.trailing_zeros() as usize;
        m += 1;
        bits &= bits - 1;
    }
    // Right-hand sweep: area and count of occupied bins j.. for every j >= 1.
    let mut right_area = [0f32; BINS];
    let mut right_count = [0u32; BINS];
    let mut acc = Aabb::empty();
    let mut acc_count = 0;
    for j in (1..m).rev() {
        acc = acc.union(&boxes[occupied[j]]);
        acc_count += count[occupied[j]];
        right_area[j] = acc.half_area();
        right_count[j] = acc_count;
    }
    let mut acc = Aabb::empty();
    let mut acc_count = 0;
    for j in 1..m {
        let below = occupied[j - 1];
        acc = acc.union(&boxes[below]);
        acc_count += count[below];
        let cost = acc.half_area() * acc_count as f32 + right_area[j] * right_count[j] as f32;
        if cost.is_finite() && best.is_none_or(|(c, _, _)| cost < c) {
            *best = Some((cost, axis, below + 1));
        }
    }
}

/// Per lane, slightly under `BINS / extent`, so the largest centroid lands in the last
/// bin (one SSE division for the three axes, each lane the scalar quotient).
#[inline]
fn bin_scale(extent: Vec3A) -> Vec3A {
    Vec3A::splat(BINS as f32 * (1.0 - 1e-5)) / extent
}

/// The bin of centroid `c` on each axis, in one SSE step: per lane `(c - lo) * to_bin`,
/// clamped to `[0, BINS - 1]` (a NaN to 0, as `max` with zero second returns zero), then
/// truncated, which equals a saturating `as usize` followed by `min(BINS - 1)` (the
/// per-axis form it replaced, whose conversions took a third of the build's
/// instructions; the tests keep it as the reference).
#[inline(always)]
fn bins_of(c: Vec3A, lo: Vec3A, to_bin: Vec3A) -> [usize; 3] {
    let k = ((c - lo) * to_bin)
        .max(Vec3A::ZERO)
        .min(Vec3A::splat((BINS - 1) as f32));
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__m128, _mm_cvttps_epi32, _mm_storeu_si128};
        let mut lanes = [0i32; 4];
        // SAFETY: SSE2 is part of x86-64; the store writes exactly the four lanes.
        unsafe {
            let v: __m128 = k.into();
            _mm_storeu_si128(lanes.as_mut_ptr().cast(), _mm_cvttps_epi32(v));
        }
        [lanes[0] as usize, lanes[1] as usize, lanes[2] as usize]
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        [k.x as usize, k.y as usize, k.z as usize]
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// One axis's bin with `as`, which saturates and maps NaN to 0 (the form `bins_of`
    /// replaced, kept as its reference).
    fn bin_of(c: f32, lo: f32, to_bin: f32) -> usize {
        (((c - lo) * to_bin) as usize).min(BINS - 1)
    }

    /// Uniform floats in [0, 1) from a xorshift generator.
    pub(in crate::bvh) fn uniforms(mut seed: u64) -> impl FnMut() -> f32 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// The three-lane bin index is `bin_of`'s on every axis: in range, at the last bin's
    /// edge, below the low end, beyond the top, for NaN and infinite positions.
    #[test]
    fn bins_of_is_bin_of_per_axis() {
        let mut next = uniforms(0x2545_F491_4F6C_DD1Du64);
        let special = [
            0.0,
            -0.0,
            1e-30,
            -1e-30,
            -1.0,
            15.999_999,
            16.0,
            17.5,
            1e30,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let mut checked = 0;
        for round in 0..20_000 {
            let lo = Vec3A::new(next(), next(), next()) * 10.0 - 5.0;
            let extent = Vec3A::new(next(), next(), next()) * 8.0;
            let to_bin = bin_scale(extent);
            let mut c = lo + Vec3A::new(next(), next(), next()) * extent * 1.2 - 0.1 * extent;
            if round % 4 == 0 {
                let s = special[round / 4 % special.len()];
                c[round % 3] = s;
            }
            let want = [0, 1, 2].map(|a| bin_of(c[a], lo[a], to_bin[a]));
            assert_eq!(bins_of(c, lo, to_bin), want, "{c} {lo} {to_bin}");
            checked += 1;
        }
        assert_eq!(checked, 20_000);
    }

    /// The deepest leaf's depth (the root's is 0).
    pub(in crate::bvh) fn depth(bvh: &Bvh2) -> u32 {
        let mut deepest = 0;
        let mut stack = vec![(0usize, 0u32)];
        while let Some((i, d)) = stack.pop() {
            deepest = deepest.max(d);
            let node = &bvh.nodes[i];
            if node.prim_count == 0 {
                stack.push((node.first_index as usize, d + 1));
                stack.push((node.first_index as usize + 1, d + 1));
            }
        }
        deepest
    }

    /// The primitive of every leaf, sorted.
    pub(in crate::bvh) fn leaves(bvh: &Bvh2) -> Vec<u32> {
        let mut out: Vec<u32> = bvh
            .nodes
            .iter()
            .filter(|n| n.prim_count == 1)
            .map(|n| bvh.primitive_indices[n.first_index as usize])
            .collect();
        out.sort_unstable();
        out
    }

    /// The sweep over every bin that [`sweep`] shortens.
    fn full_sweep(
        count: &[u32; BINS],
        boxes: &[Aabb; BINS],
        axis: usize,
        best: &mut Option<(f32, usize, usize)>,
    ) {
        let mut right_area = [0f32; BINS];
        let mut right_count = [0u32; BINS];
        let mut acc = Aabb::empty();
        let mut acc_count = 0;
        for k in (1..BINS).rev() {
            acc = acc.union(&boxes[k]);
            acc_count += count[k];
            right_area[k] = acc.half_area();
            right_count[k] = acc_count;
        }
        let mut acc = Aabb::empty();
        let mut acc_count = 0;
        for k in 1..BINS {
            acc = acc.union(&boxes[k - 1]);
            acc_count += count[k - 1];
            if acc_count == 0 || right_count[k] == 0 {
                continue;
            }
            let cost = acc.half_area() * acc_count as f32 + right_area[k] * right_count[k] as f32;
            if cost.is_finite() && best.is_none_or(|(c, _, _)| cost < c) {
                *best = Some((cost, axis, k));
            }
        }
    }

    #[test]
    fn skipping_empty_bins_finds_the_cut_a_full_sweep_finds() {
        let mut seed = 0x2545_F491_4F6C_DD1Du64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for round in 0..20_000 {
            let mut count = [0u32; BINS];
            let mut boxes = [Aabb::empty(); BINS];
            // Few occupied bins (as near the leaves), some with equal boxes (ties).
            let occupied = 1 + (next() % if round % 2 == 0 { 4 } else { BINS as u64 });
            for _ in 0..occupied {
                let k = (next() % BINS as u64) as usize;
                let f = |r: u64| (r % 8) as f32 * 0.5;
                let lo = Vec3A::new(f(next()), f(next()), f(next()));
                count[k] += 1 + (next() % 3) as u32;
                boxes[k] = boxes[k].union(&Aabb::new(lo, lo + 0.5 + f(next())));
            }
            let (mut a, mut b) = (None, None);
            for axis in 0..3 {
                sweep(&count, &boxes, axis, &mut a);
                full_sweep(&count, &boxes, axis, &mut b);
            }
            assert_eq!(
                a.map(|(c, x, k)| (c.to_bits(), x, k)),
                b.map(|(c, x, k)| (c.to_bits(), x, k)),
                "round {round}: {count:?}"
            );
        }
    }

    #[test]
    fn coincident_boxes_give_a_balanced_tree() {
        let b = Aabb::new(Vec3A::ZERO, Vec3A::ONE);
        let bvh = build(vec![b; 100_000]);
        assert_eq!(bvh.nodes.len(), 2 * 100_000 - 1);
        assert_eq!(depth(&bvh), 17);
        assert_eq!(leaves(&bvh), (0..100_000).collect::<Vec<_>>());
    }

    #[test]
    fn nested_boxes_stay_within_the_depth_limit() {
        // Every box contains the previous one and shares its centre: the input that
        // turns a greedy agglomerative build into a chain.
        let boxes: Vec<Aabb> = (1..=50_000)
            .map(|i| {
                let r = i as f32;
                Aabb::new(Vec3A::splat(-r), Vec3A::splat(r))
            })
            .collect();
        let bvh = build(boxes.clone());
        assert!(depth(&bvh) <= MAX_DEPTH, "{}", depth(&bvh));
        assert_eq!(leaves(&bvh).len(), 50_000);
        // Geometric growth: SAH alone would peel one box per level.
        let boxes: Vec<Aabb> = (0..2_000)
            .map(|i| {
                let r = 1.01f32.powi(i);
                Aabb::new(Vec3A::new(-r, 0.0, 0.0), Vec3A::new(r, 1.0, 1.0))
            })
            .collect();
        assert!(depth(&build(boxes.clone())) <= MAX_DEPTH);
    }

    #[test]
    fn distinct_boxes_cover_every_primitive_once() {
        let boxes: Vec<Aabb> = (0..1000)
            .map(|i| {
                let p = Vec3A::new((i % 10) as f32, (i / 10 % 10) as f32, (i / 100) as f32);
                Aabb::new(p, p + 0.5)
            })
            .collect();
        let bvh = build(boxes.clone());
        assert_eq!(leaves(&bvh), (0..1000).collect::<Vec<_>>());
        for node in &bvh.nodes {
            if node.prim_count == 0 {
                let l = bvh.nodes[node.first_index as usize].aabb();
                let r = bvh.nodes[node.first_index as usize + 1].aabb();
                assert_eq!(l.union(r), *node.aabb());
            }
        }
        assert!(depth(&bvh) < 20, "{}", depth(&bvh));
    }

    /// The parallel build gives the very tree one thread gives: every node, in the same
    /// place, and the same primitive order. Random boxes, coincident boxes (median cuts
    /// by index) and nested ones (the depth limit's forced median cuts).
    #[test]
    fn the_parallel_build_is_the_one_thread_build() {
        let mut next = uniforms(0x9E37_79B9_7F4A_7C15u64);
        let random: Vec<Aabb> = (0..60_000)
            .map(|_| {
                let p = Vec3A::new(next(), next(), next()) * 100.0;
                Aabb::new(p, p + Vec3A::new(next(), next(), next()))
            })
            .collect();
        let coincident = vec![Aabb::new(Vec3A::ZERO, Vec3A::ONE); 20_000];
        let nested: Vec<Aabb> = (1..=20_000)
            .map(|i| Aabb::new(Vec3A::splat(-(i as f32)), Vec3A::splat(i as f32)))
            .collect();
        for boxes in [random, coincident, nested] {
            assert!(
                boxes.len() >= 4 * PARALLEL_MIN,
                "the top levels must run in parallel"
            );
            let parallel = build(boxes.clone());
            let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
            let mut copy = boxes.clone();
            let root = copy.iter().fold(Aabb::empty(), |a, b| a.union(b));
            let bounds = (root, centroid_bounds(&copy));
            let range = Range {
                order: &mut order,
                boxes: &mut copy,
            };
            let mut one = vec![Bvh2Node::default(); 2 * boxes.len() - 1];
            let (top, rest) = one.split_at_mut(1);
            top[0] = sequential(range, 0, 0, bounds, rest, 1);
            assert_eq!(parallel.primitive_indices, order);
            assert_eq!(parallel.nodes.len(), one.len());
            for (i, (a, b)) in parallel.nodes.iter().zip(&one).enumerate() {
                assert_eq!(
                    (a.aabb(), a.prim_count, a.first_index),
                    (b.aabb(), b.prim_count, b.first_index),
                    "node {i}"
                );
            }
        }
    }

    /// FNV-1a over a tree's every node (box bits, count, index) and its primitive order.
    fn tree_hash(bvh: &Bvh2) -> u64 {
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        let mut word = |w: u32| {
            h ^= u64::from(w);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        };
        for n in &bvh.nodes {
            let b = n.aabb();
            for v in [b.min, b.max] {
                v.to_array().iter().for_each(|x| word(x.to_bits()));
            }
            word(n.prim_count);
            word(n.first_index);
        }
        bvh.primitive_indices.iter().for_each(|&i| word(i));
        h
    }

    /// The build makes the very trees it made before its cuts were reworked for speed
    /// (hashes taken from that build): random boxes (SAH cuts, some clustered with
    /// ties), coincident and nested ones (median cuts by index, the depth limit), boxes
    /// too large for finite costs (median cuts by centroid), large enough for the
    /// parallel top. A change that alters any tree must say so here.
    #[test]
    fn the_trees_are_the_ones_the_build_always_made() {
        let mut next = uniforms(0x1234_5678_9ABC_DEF1u64);
        let random: Vec<Aabb> = (0..30_000)
            .map(|_| {
                let p = Vec3A::new(next(), next(), next()) * 100.0;
                Aabb::new(p, p + Vec3A::new(next(), next(), next()))
            })
            .collect();
        let clustered: Vec<Aabb> = (0..20_000)
            .map(|i| {
                let p = Vec3A::new((i % 7) as f32, (i % 3) as f32 * 0.5, (i % 11) as f32);
                Aabb::new(p, p + next())
            })
            .collect();
        let coincident = vec![Aabb::new(Vec3A::ZERO, Vec3A::ONE); 9_000];
        let nested: Vec<Aabb> = (1..=9_000)
            .map(|i| Aabb::new(Vec3A::splat(-(i as f32)), Vec3A::splat(i as f32)))
            .collect();
        // Boxes whose half-areas overflow f32: every SAH cost is infinite, so every cut
        // is a median cut over distinct centroids.
        let huge: Vec<Aabb> = (0..5_000)
            .map(|_| {
                let c = Vec3A::new(next(), next(), next()) * 1e24;
                Aabb::new(c - 1e21, c + 1e21)
            })
            .collect();
        let got: Vec<String> = [random, clustered, coincident, nested, huge]
            .iter()
            .map(|b| format!("{:016x}", tree_hash(&build(b.clone()))))
            .collect();
        assert_eq!(
            got,
            [
                "90ddfb00a3311ba0",
                "5e287189d4fbe836",
                "16f256c37ee431d0",
                "183c005f432bd1d0",
                "27684802bef11a03",
            ]
        );
    }
}
