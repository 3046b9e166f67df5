//! BVH2 to CWBVH: obvhs 0.4's `bvh2_to_cwbvh` (Ylitie et al. 2017's cost-based collapse
//! into 8-wide nodes, children ordered by octant), step for step, with the large
//! subtrees converted on rayon's pool.
//!
//! The collapse is where the tree stops splitting: the binary build goes down to one
//! triangle a leaf, and the collapse's SAH costs (each node one unit per half-area, each
//! leaf its test's cost per half-area) choose which subtrees become leaves. obvhs prices
//! a leaf per triangle, at most three; dray's leaves ([`Leaves::Four`]) hold up to four
//! triangles tested together (`leaf4`), priced as one test.
//!
//! obvhs converts on one thread; on a 1.7M-triangle scene that is a third of a second
//! with the other core idle, as long as the parallel binned-SAH build before it. The
//! result here is obvhs's own tree, node for node and primitive for primitive (a test
//! compares the two), less the 8-bit quantised child boxes (each node's `p`, `e` and
//! `child_min_*`/`child_max_*`, left at zero): dray's wide nodes (`wide`) take exact
//! planes from the triangles and never read them, and quantising every child was a
//! tenth of the conversion's instructions.
//! - **Costs** (bottom up): each node's seven decisions need only its children's, so
//!   the two sides of the top levels are costed in parallel (`rayon::join`). Each
//!   node's decisions are written once, by the task that owns the node, into atomics
//!   (relaxed: the join orders a child's writes before its parent's reads).
//! - **Nodes** (top down): obvhs numbers a node's children as one block at the end of
//!   the node list when it visits the node, then visits the internal children in slot
//!   order, and appends a leaf child's primitives when it visits the leaf's parent. So
//!   what one internal child's visit appends (its subtree's nodes less itself, and its
//!   subtree's primitives) is one contiguous run of each list. A large subtree is
//!   converted on its own, into lists numbered from its own start, and its runs are
//!   appended with its indices moved by where they land.

use std::sync::atomic::{AtomicU64, Ordering};

use glam::{Vec3A, vec3a};
use obvhs::bvh2::Bvh2;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::cwbvh::{BRANCHING, CwBvh};

/// obvhs's `PRIM_COST`: one triangle test, in units of one node visit.
const PRIM_COST: f32 = 0.3;
/// One test of a leaf of up to four triangles (`leaf4`, the four in SSE lanes), in units
/// of one node visit: about two single-triangle tests (the edge functions and the rest of
/// the watertight test for four lanes, against one 8-wide node test).
const LEAF4_COST: f32 = 2.0 * PRIM_COST;
/// Directions of the child-ordering table (octants).
const DIRECTIONS: usize = 8;
/// Decisions per BVH2 node: one per number of CWBVH child slots it may fill (1..=7).
const SLOTS: usize = 7;
const INVALID: u8 = u8::MAX;
const INVALID32: u32 = u32::MAX;
/// BVH2 levels whose two sides are costed in parallel.
const PARALLEL_COST_DEPTH: u32 = 8;
/// Subtrees over at least this many primitives are converted on their own, in parallel
/// with their siblings.
const PARALLEL_MIN: u32 = 4096;

/// How the collapse prices a leaf, which decides (with each node's cost) where the tree
/// stops splitting: SAH, each cost weighted by the box's half-area.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Leaves {
    /// obvhs's: [`PRIM_COST`] per triangle, at most this many (1 to 3) a leaf. Only the
    /// tests build it, to hold the conversion to obvhs's own.
    #[cfg_attr(not(test), allow(dead_code))]
    PerTriangle(u32),
    /// dray's: up to four triangles a leaf, tested together for [`LEAF4_COST`] whatever
    /// their number (as Embree prices its four-triangle leaves by block, not by
    /// triangle). A subtree of up to four is then always cheaper as one leaf than as a
    /// node over smaller ones; the sweep decides whether its slots are better spent on
    /// one leaf of four or on smaller leaves with tighter boxes.
    Four,
}

impl Leaves {
    fn max(self) -> u32 {
        match self {
            Leaves::PerTriangle(n) => n,
            Leaves::Four => 4,
        }
    }

    /// The cost of a leaf of `n` triangles (at most [`Leaves::max`]) whose box has
    /// `half_area` (obvhs's products in obvhs's order, so the same roundings).
    fn cost(self, half_area: f32, n: u32) -> f32 {
        match self {
            Leaves::PerTriangle(_) => half_area * n as f32 * PRIM_COST,
            Leaves::Four => half_area * LEAF4_COST,
        }
    }
}

/// The meta bits (the high three) of a leaf of `n` triangles: obvhs's unary count for one
/// to three, and `0b100`, which no unary count uses, for four.
fn leaf_code(n: u32) -> u8 {
    match n {
        1 => 0b001,
        2 => 0b011,
        3 => 0b111,
        4 => 0b100,
        _ => panic!("a CWBVH leaf of {n} primitives (at most 4)"),
    }
}

/// The number of triangles of a leaf child whose meta byte is `meta` (0 for an empty
/// slot): the inverse of the encoding the conversion writes.
pub(crate) fn leaf_size(meta: u8) -> u32 {
    match meta >> 5 {
        0b100 => 4,
        code => code.count_ones(),
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Kind {
    Leaf,
    Internal,
    Distribute,
}

/// obvhs's `Decision` less its cost: what a node becomes when it may fill `i + 1` child
/// slots, and how it splits them between its two children. Packed in one byte: the kind
/// in bits 0..2, `left` in 2..5 and `right` in 5..8 (both at most 6).
#[derive(Clone, Copy, Debug)]
struct Decision {
    kind: Kind,
    left: u8,
    right: u8,
}

impl Decision {
    fn pack(self) -> u8 {
        let kind = match self.kind {
            Kind::Leaf => 0u8,
            Kind::Internal => 1,
            Kind::Distribute => 2,
        };
        kind | self.left << 2 | self.right << 5
    }

    fn unpack(v: u8) -> Decision {
        Decision {
            kind: match v & 3 {
                0 => Kind::Leaf,
                1 => Kind::Internal,
                _ => Kind::Distribute,
            },
            left: v >> 2 & 7,
            right: v >> 5,
        }
    }
}

/// A leaf's decisions: a leaf whatever the slots (obvhs leaves `left` and `right` at
/// their defaults, 0; nothing reads them).
const LEAF: Decision = Decision {
    kind: Kind::Leaf,
    left: 0,
    right: 0,
};

struct Converter<'a> {
    bvh2: &'a Bvh2,
    /// Each BVH2 node's `SLOTS` decisions, one byte each (slot `i` in bits `8i..8i + 8`).
    /// Their costs are not kept: a node's are needed only by its parent's, which the
    /// cost pass hands up on the stack.
    decisions: Vec<AtomicU64>,
    directions: [Vec3A; DIRECTIONS],
}

/// What converting one subtree appends: its nodes (the subtree's root first, then the
/// blocks its visit numbers) and its primitives, numbered from 0.
#[derive(Default)]
struct Part {
    nodes: Vec<CwBvhNode>,
    primitive_indices: Vec<u32>,
}

/// With [`Leaves::PerTriangle`]`(n)`, obvhs's `bvh2_to_cwbvh(bvh2, n, true, false)`, the
/// same to the bit but for the quantised child boxes, which are not computed (zero): the
/// same nodes, children, child order, leaves and primitive order, which is all
/// `wide::from_cwbvh` reads. With [`Leaves::Four`], the same algorithm with leaves of up
/// to four priced as one test each (a leaf of four is coded as [`leaf_size`] reads).
/// `bvh2` must have one primitive per leaf (as obvhs requires).
pub(crate) fn to_cwbvh(bvh2: &Bvh2, leaves: Leaves) -> CwBvh {
    if bvh2.nodes.is_empty() {
        return CwBvh::default();
    }
    let n = bvh2.nodes.len();
    let c = Converter {
        bvh2,
        // Zeroed memory: the cost pass writes every node's entries once.
        decisions: bytemuck::zeroed_vec(n),
        directions: std::array::from_fn(|s| {
            vec3a(
                if (s & 0b100) != 0 { -1.0 } else { 1.0 },
                if (s & 0b010) != 0 { -1.0 } else { 1.0 },
                if (s & 0b001) != 0 { -1.0 } else { 1.0 },
            )
        }),
    };
    c.cost(0, leaves, 0, &mut [0.0; SLOTS]);
    let mut part = Part::default();
    // Every primitive lands once; the nodes are far fewer than the primitives (a tenth
    // or so: up to 3 primitives a leaf, 8 children a node), so they grow as they come
    // instead of reserving a node per primitive (80 bytes a triangle held through the
    // build, more than the whole 8-wide tree).
    part.primitive_indices.reserve(bvh2.primitive_indices.len());
    part.nodes.push(CwBvhNode::default());
    c.convert(&mut part, 0, 0);
    CwBvh {
        nodes: part.nodes,
        primitive_indices: part.primitive_indices,
        total_aabb: *bvh2.nodes[0].aabb(),
        exact_node_aabbs: None,
        uses_spatial_splits: bvh2.uses_spatial_splits,
    }
}

impl Converter<'_> {
    /// Node `index`'s decision for `slot`.
    fn decision(&self, index: usize, slot: usize) -> Decision {
        let word = self.decisions[index].load(Ordering::Relaxed);
        Decision::unpack((word >> (8 * slot)) as u8)
    }

    /// obvhs's `calculate_cost_impl`: fill node `index`'s decisions, its children's
    /// first, and its seven costs into `costs`; returns the primitives under it.
    ///
    /// The same costs, compared in the same order, as obvhs's: each slot's best split
    /// is the first strictly cheaper one, and a slot with none copies the slot before.
    fn cost(&self, index: usize, leaves: Leaves, depth: u32, costs: &mut [f32; SLOTS]) -> u32 {
        let node = &self.bvh2.nodes[index];
        let half_area = node.aabb().half_area();
        let first = node.first_index as usize;
        let num_primitives;
        let word;
        if node.prim_count != 0 {
            num_primitives = node.prim_count;
            assert!(
                num_primitives == 1,
                "the CWBVH conversion expects one primitive per BVH2 leaf"
            );
            *costs = [leaves.cost(half_area, num_primitives); SLOTS];
            word = u64::from_le_bytes([LEAF.pack(); 8]);
        } else {
            let (mut cl, mut cr) = ([0f32; SLOTS], [0f32; SLOTS]);
            let (l, r) = if depth < PARALLEL_COST_DEPTH {
                rayon::join(
                    || self.cost(first, leaves, depth + 1, &mut cl),
                    || self.cost(first + 1, leaves, depth + 1, &mut cr),
                )
            } else {
                (
                    self.cost(first, leaves, depth + 1, &mut cl),
                    self.cost(first + 1, leaves, depth + 1, &mut cr),
                )
            };
            num_primitives = l + r;
            let cost_leaf = if num_primitives <= leaves.max() {
                leaves.cost(half_area, num_primitives)
            } else {
                f32::INFINITY
            };
            let mut cost_distribute = f32::INFINITY;
            let (mut left, mut right) = (INVALID, INVALID);
            // The minimum by selects, not branches (which way each compare goes is
            // data, and the branches were mispredicted).
            for k in 0..SLOTS {
                let c = cl[k] + cr[6 - k];
                let better = c < cost_distribute;
                cost_distribute = if better { c } else { cost_distribute };
                left = if better { k as u8 } else { left };
                right = if better { 6 - k as u8 } else { right };
            }
            if left == INVALID {
                // Every split costs infinity or NaN: boxes whose half-areas overflow
                // f32 (coordinates far beyond the import bound, moved there). obvhs
                // leaves the slots unset and the conversion then indexes slot 255;
                // any split gives a valid tree, so take the first.
                (left, right) = (0, 6);
            }
            let cost_internal = cost_distribute + half_area;
            let (kind, cost) = if cost_leaf < cost_internal {
                (Kind::Leaf, cost_leaf)
            } else {
                (Kind::Internal, cost_internal)
            };
            costs[0] = cost;
            let mut byte = Decision { kind, left, right }.pack();
            let mut slots = u64::from(byte);
            for i in 1..SLOTS {
                let mut cost_distribute = costs[i - 1];
                let mut split = INVALID;
                for k in 0..i {
                    let c = cl[k] + cr[i - k - 1];
                    let better = c < cost_distribute;
                    cost_distribute = if better { c } else { cost_distribute };
                    split = if better { k as u8 } else { split };
                }
                let split = (split != INVALID).then_some(split);
                // Without a cheaper split, obvhs copies the previous decision (its
                // cost too).
                if let Some(left) = split {
                    let right = i as u8 - left - 1;
                    byte = Decision {
                        kind: Kind::Distribute,
                        left,
                        right,
                    }
                    .pack();
                }
                costs[i] = cost_distribute;
                slots |= u64::from(byte) << (8 * i);
            }
            word = slots;
        }
        self.decisions[index].store(word, Ordering::Relaxed);
        num_primitives
    }

    /// Primitives under BVH2 node `index`, from its leftmost and rightmost leaves: the
    /// build numbers the primitives of every subtree as one run of the order (see
    /// `build`), so this walks two paths instead of keeping a count per node (4 bytes a
    /// node, 8 a triangle, held through the conversion, whose peak is what a domain load
    /// reserves). Only a hint (which subtrees convert in parallel, what a part reserves):
    /// the tree converted does not depend on it.
    fn primitives_under(&self, index: usize) -> u32 {
        let nodes = &self.bvh2.nodes;
        let leaf = |right: usize| {
            let mut i = index;
            while let Some(node) = nodes.get(i)
                && !node.is_leaf()
            {
                i = node.first_index as usize + right;
            }
            nodes.get(i).map_or(0, |n| n.first_index)
        };
        leaf(1).saturating_sub(leaf(0)).saturating_add(1)
    }

    /// obvhs's `get_children`.
    fn children(&self, index: usize, out: &mut [u32; 8], count: &mut usize, i: usize) {
        let node = &self.bvh2.nodes[index];
        if node.is_leaf() {
            out[*count] = index as u32;
            *count += 1;
            return;
        }
        let d = self.decision(index, i);
        let first = node.first_index as usize;
        for (child, slot) in [(first, d.left), (first + 1, d.right)] {
            if self.decision(child, slot as usize).kind == Kind::Distribute {
                self.children(child, out, count, slot as usize);
            } else {
                out[*count] = child as u32;
                *count += 1;
            }
        }
    }

    /// obvhs's `order_children`: children in octant order (greedy assignment).
    fn order(&self, index: usize, children: &mut [u32; 8], count: usize) {
        let p = self.bvh2.nodes[index].aabb().center();
        let mut cost = [[f32::MAX; DIRECTIONS]; BRANCHING];
        for (s, d) in self.directions.iter().enumerate() {
            for c in 0..count {
                let v = self.bvh2.nodes[children[c] as usize].aabb().center() - p;
                cost[c][s] = d.dot(v);
            }
        }
        let mut assignment = [usize::MAX; BRANCHING];
        let mut filled = [false; DIRECTIONS];
        loop {
            let mut min_cost = f32::MAX;
            let (mut min_slot, mut min_index) = (usize::MAX, usize::MAX);
            for c in 0..count {
                if assignment[c] == usize::MAX {
                    for (s, &f) in filled.iter().enumerate() {
                        if !f && cost[c][s] < min_cost {
                            min_cost = cost[c][s];
                            min_slot = s;
                            min_index = c;
                        }
                    }
                }
            }
            if min_slot == usize::MAX {
                break;
            }
            filled[min_slot] = true;
            assignment[min_index] = min_slot;
        }
        let original = std::mem::replace(children, [INVALID32; 8]);
        for i in 0..count {
            children[assignment[i]] = original[i];
        }
    }

    /// obvhs's `count_primitives`: append the primitives under `index`, left first.
    fn push_primitives(&self, index: usize, out: &mut Vec<u32>) -> u32 {
        let node = &self.bvh2.nodes[index];
        if node.is_leaf() {
            out.push(self.bvh2.primitive_indices[node.first_index as usize]);
            return node.prim_count;
        }
        let first = node.first_index as usize;
        self.push_primitives(first, out) + self.push_primitives(first + 1, out)
    }

    /// obvhs's `convert_to_cwbvh_impl`: fill `part.nodes[at]` from BVH2 node `index`,
    /// appending its children's block and primitives, then convert its internal
    /// children; large ones on their own, in parallel, appended in slot order.
    fn convert(&self, part: &mut Part, at: usize, index: usize) {
        let mut node = part.nodes[at];
        let mut children = [INVALID32; 8];
        let mut count = 0;
        self.children(index, &mut children, &mut count, 0);
        self.order(index, &mut children, count);

        node.imask = 0;
        node.primitive_base_idx = part.primitive_indices.len() as u32;
        node.child_base_idx = part.nodes.len() as u32;
        let mut internal = 0;
        let mut num_primitives = 0u32;
        for (i, &child) in children.iter().enumerate() {
            if child == INVALID32 {
                continue;
            }
            match self.decision(child as usize, 0).kind {
                Kind::Leaf => {
                    let n = self.push_primitives(child as usize, &mut part.primitive_indices);
                    node.child_meta[i] = num_primitives as u8 | leaf_code(n) << 5;
                    num_primitives += n;
                }
                Kind::Internal => {
                    node.imask |= 1u8 << i;
                    node.child_meta[i] = (24 + i as u8) | 0b0010_0000;
                    internal += 1;
                }
                Kind::Distribute => unreachable!("a child slot never distributes"),
            }
        }
        let block = part.nodes.len();
        part.nodes.resize(block + internal, CwBvhNode::default());
        part.nodes[at] = node;

        // The internal children in slot order (on the stack: this runs once per node).
        let mut slots = [0usize; 8];
        let mut n = 0;
        for (i, &c) in children.iter().enumerate() {
            if c != INVALID32 && node.imask & (1 << i) != 0 {
                slots[n] = c as usize;
                n += 1;
            }
        }
        let inner = &slots[..n];
        let large = |c: usize| self.primitives_under(c) >= PARALLEL_MIN;
        if inner.iter().filter(|&&c| large(c)).count() < 2 {
            for (offset, &child) in inner.iter().enumerate() {
                self.convert(part, block + offset, child);
            }
            return;
        }
        // Each large child converted on its own (numbered from 0), small ones in place
        // when their turn comes, so that every run lands where one thread puts it.
        let mut parts: Vec<Option<Part>> = inner.iter().map(|_| None).collect();
        rayon::scope(|s| {
            for (slot, &child) in parts.iter_mut().zip(inner) {
                if large(child) {
                    s.spawn(move |_| {
                        let mut sub = Part::default();
                        // Exactly the subtree's primitives land here: no slack.
                        let prims = self.primitives_under(child) as usize;
                        sub.primitive_indices.reserve_exact(prims);
                        sub.nodes.push(CwBvhNode::default());
                        self.convert(&mut sub, 0, child);
                        *slot = Some(sub);
                    });
                }
            }
        });
        for (offset, (&child, sub)) in inner.iter().zip(parts).enumerate() {
            match sub {
                None => self.convert(part, block + offset, child),
                Some(sub) => append(part, block + offset, sub),
            }
        }
    }
}

/// Put a subtree converted on its own into `part`: its root at `at`, the rest of its
/// nodes and its primitives appended, with their indices moved to where they land
/// (node `k >= 1` of the subtree lands at `nodes.len() + k - 1`).
fn append(part: &mut Part, at: usize, sub: Part) {
    let node_shift = part.nodes.len() as u32;
    let prim_shift = part.primitive_indices.len() as u32;
    let moved = |mut n: CwBvhNode| {
        // Every child block of the subtree starts at its index 1 or later.
        n.child_base_idx = n.child_base_idx + node_shift - 1;
        n.primitive_base_idx += prim_shift;
        n
    };
    let mut nodes = sub.nodes.into_iter();
    if let Some(root) = nodes.next() {
        part.nodes[at] = moved(root);
    }
    part.nodes.extend(nodes.map(moved));
    part.primitive_indices.extend(sub.primitive_indices);
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;
    use obvhs::aabb::Aabb;
    use obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh;

    use super::*;
    use crate::bvh::build;
    use crate::sampling::{PathKey, Purpose};

    fn boxes(n: u32, seed: u32, kind: u32) -> Vec<Aabb> {
        (0..n)
            .map(|i| {
                let k = PathKey {
                    seed: u64::from(seed),
                    pixel: i,
                    sample: 0,
                };
                let u = |d: u32| k.uniform(0, Purpose::Film, d);
                let c = match kind {
                    // Everything at one point: median cuts, deep chains.
                    0 => Vec3A::splat(1.0),
                    // A few clusters far apart, with coincident boxes.
                    1 => Vec3A::new((i % 7) as f32 * 1000.0, (i % 3) as f32, 5.0),
                    _ => Vec3A::new(u(0), u(1), u(2)) * 100.0,
                };
                let h = Vec3A::new(u(3), u(4), u(5)) * if kind == 2 { 2.0 } else { 0.0 };
                Aabb::new(c - h, c + h)
            })
            .collect()
    }

    /// The parallel conversion is obvhs's, node for node (every field but the quantised
    /// child boxes, which it leaves at zero) and primitive for primitive, on random,
    /// clustered and coincident boxes, small (one thread) and large (parallel
    /// subtrees), and with 1, 2 or 3 primitives per leaf.
    #[test]
    fn same_tree_as_obvhs() {
        for (n, kind) in [
            (1, 2),
            (2, 2),
            (9, 2),
            (700, 2),
            (50_000, 2),
            (30_000, 1),
            (20_000, 0),
        ] {
            let bvh2 = build::build(boxes(n, 7 + n, kind));
            for leaf in 1..=3 {
                let want = bvh2_to_cwbvh(&bvh2, leaf, true, false);
                let got = to_cwbvh(&bvh2, Leaves::PerTriangle(leaf));
                assert_eq!(got.nodes.len(), want.nodes.len(), "{n} {kind} {leaf}");
                for (i, (g, w)) in got.nodes.iter().zip(&want.nodes).enumerate() {
                    // obvhs's node with its quantised boxes taken out.
                    let w = CwBvhNode {
                        p: Default::default(),
                        e: [0; 3],
                        child_min_x: [0; 8],
                        child_min_y: [0; 8],
                        child_min_z: [0; 8],
                        child_max_x: [0; 8],
                        child_max_y: [0; 8],
                        child_max_z: [0; 8],
                        ..*w
                    };
                    assert!(
                        *g == w,
                        "{n} boxes, kind {kind}, leaf {leaf}: node {i} differs"
                    );
                }
                assert_eq!(got.primitive_indices, want.primitive_indices);
                assert_eq!(got.total_aabb, want.total_aabb);
            }
        }
    }

    /// Boxes whose half-areas overflow f32 (sides of 1e22 and more, as a scene moved to
    /// 1e25 gives in accelerator space) make every split cost infinity; the conversion
    /// indexed decision slot 255 then ("index out of bounds: the len is 441 but the
    /// index is 444"). Now it gives a tree holding every primitive once.
    #[test]
    fn boxes_with_infinite_half_areas_convert() {
        for side in [1e22f32, 1e25, 3e38] {
            let aabbs: Vec<Aabb> = (0..64u32)
                .map(|i| {
                    let c = Vec3A::new(1e25, i as f32 * 1e20, (i % 5) as f32 * 1e20);
                    Aabb::new(c - Vec3A::splat(side), c + Vec3A::splat(side))
                })
                .collect();
            assert!(!aabbs[0].half_area().is_finite(), "{side}");
            let bvh2 = build::build(aabbs.clone());
            for leaves in [1, 2, 3]
                .map(Leaves::PerTriangle)
                .into_iter()
                .chain([Leaves::Four])
            {
                let got = to_cwbvh(&bvh2, leaves);
                let mut prims = got.primitive_indices.clone();
                prims.sort_unstable();
                assert_eq!(prims, (0..64).collect::<Vec<u32>>(), "{side} {leaves:?}");
            }
        }
    }

    /// Leaves of up to four: every primitive in exactly one leaf, the leaves' runs tiling
    /// the primitive order node by node, sizes 1 to 4 as `leaf_size` reads them back,
    /// on random, clustered and coincident boxes; on boxes with areas, some leaves of four
    /// and fewer nodes than with obvhs's leaves of up to three.
    #[test]
    fn leaves_of_four_cover_every_primitive_once() {
        for (n, kind) in [
            (1, 2),
            (5, 2),
            (700, 2),
            (50_000, 2),
            (30_000, 1),
            (20_000, 0),
        ] {
            let bvh2 = build::build(boxes(n, 11 + n, kind));
            let got = to_cwbvh(&bvh2, Leaves::Four);
            let three = to_cwbvh(&bvh2, Leaves::PerTriangle(3));
            let mut seen = vec![0u32; n as usize];
            let mut sizes = [0u32; 5];
            for node in &got.nodes {
                let mut offset = 0;
                for slot in 0..8 {
                    let meta = node.child_meta[slot];
                    if node.imask & (1 << slot) != 0 || meta == 0 {
                        continue;
                    }
                    let size = leaf_size(meta);
                    assert!((1..=4).contains(&size), "{n} {kind}: {meta:08b}");
                    assert_eq!(u32::from(meta & 0x1f), offset, "{n} {kind}");
                    for p in 0..size {
                        let at = (node.primitive_base_idx + offset + p) as usize;
                        seen[got.primitive_indices[at] as usize] += 1;
                    }
                    offset += size;
                    sizes[size as usize] += size;
                }
            }
            assert!(seen.iter().all(|&c| c == 1), "{n} {kind}");
            // Boxes of kinds 0 and 1 are points: every cost is zero, nothing to prefer.
            if n >= 700 && kind == 2 {
                assert!(
                    sizes[4] > 0 && got.nodes.len() < three.nodes.len(),
                    "{n} {kind}: {sizes:?}, {} nodes against {}",
                    got.nodes.len(),
                    three.nodes.len()
                );
            }
        }
    }
}
