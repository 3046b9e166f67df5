//! The traversal's node: the topology of obvhs's compressed 8-wide node (Ylitie et al.
//! 2017: children ordered by octant, leaf primitives contiguous), with every child's box
//! stored as exact f32 planes, so that all eight children are tested at once with no
//! decoding (as Embree's BVH8 does).
//!
//! obvhs quantises each child's planes to 8 bits on its parent's grid, which a ray must
//! decode per visit (`u8 -> f32`, then the grid's scale and origin) and which grows every
//! box by up to 1/255 of its parent's size. Here the planes are the exact bounds of each
//! child's triangles (computed bottom up from the leaves), so the node test is two
//! operations per plane and culls more. The cost is memory: 256 bytes per node instead
//! of obvhs's 80 (four cache lines, all read per visit).
//!
//! Each child slot also carries one word, `slot[s]`:
//! - an internal child: its node index with the top bit set ([`INTERNAL`]), so the
//!   traversal reads the child's index directly;
//! - a leaf child: one bit, its place among the node's leaf children (slot order), whose
//!   leaves (`leaf4::Tri4`, up to four triangles each) are numbered from `leaf_base`, so
//!   the node test ORs the words of its hit leaves into one mask of leaves to test;
//! - an empty slot: 0 (its planes are an empty box, +inf below and -inf above).

use obvhs::cwbvh::CwBvh;

use super::convert::leaf_size;
use super::leaf4::{PAD, Tri4};

/// One 8-wide node, 256 bytes (four cache lines, aligned).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub(crate) struct WideNode {
    /// Per axis (x, y, z): floats 0..8 the children's lower planes, 8..16 the upper.
    pub planes: [[f32; 16]; 3],
    /// Per child slot: an internal child's node index | [`INTERNAL`], or a leaf child's
    /// bit (its leaf's offset from `leaf_base`), or 0 for an empty slot.
    pub slot: [u32; 8],
    /// Index of the leaf of the node's first leaf child (the others follow it).
    pub leaf_base: u32,
    _pad: [u32; 7],
}

/// The flag of an internal child's word in [`WideNode::slot`].
pub(crate) const INTERNAL: u32 = 0x8000_0000;

impl Default for WideNode {
    fn default() -> WideNode {
        let mut planes = [[0f32; 16]; 3];
        for row in &mut planes {
            row[..8].fill(f32::INFINITY);
            row[8..].fill(f32::NEG_INFINITY);
        }
        WideNode {
            planes,
            slot: [0; 8],
            leaf_base: 0,
            _pad: [0; 7],
        }
    }
}

/// An axis-aligned box as (lower, upper) corners.
pub(crate) type Bounds = ([f32; 3], [f32; 3]);

pub(crate) const EMPTY: Bounds = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);

pub(crate) fn union(a: Bounds, b: Bounds) -> Bounds {
    (
        [0, 1, 2].map(|k| a.0[k].min(b.0[k])),
        [0, 1, 2].map(|k| a.1[k].max(b.1[k])),
    )
}

/// The bounds of a leaf's triangles (padding lanes left out).
fn leaf_bounds(t: &Tri4) -> Bounds {
    (0..4)
        .filter(|&l| t.ids[l] != PAD)
        .map(|l| {
            let [a, b, c] = t.corners(l);
            (a.min(b).min(c).to_array(), a.max(b).max(c).to_array())
        })
        .fold(EMPTY, union)
}

/// The leaf children of `bvh`, node by node in node order, slot by slot: each as the run
/// `(first, count)` of `bvh.primitive_indices` it holds. Leaf `k` of this list is the
/// one [`from_cwbvh`] numbers `k`.
pub(crate) fn leaves(bvh: &CwBvh) -> Vec<(u32, u32)> {
    let mut out = Vec::with_capacity(bvh.nodes.len() * 4);
    for cw in &bvh.nodes {
        for slot in 0..8 {
            let meta = cw.child_meta[slot];
            let size = leaf_size(meta);
            if cw.imask & (1 << slot) == 0 && size != 0 {
                out.push((cw.primitive_base_idx + u32::from(meta & 0x1f), size));
            }
        }
    }
    out
}

/// The wide nodes of `bvh`, index for index (child indices keep their meaning), with
/// each child's box the exact bounds of its triangles, or, with `leaf_boxes`, each leaf
/// child's box its entry there (a pre-split leaf's: the bounds of its triangles' parts it
/// was built for). `leaves` (and `leaf_boxes`) are `bvh`'s leaves in the order of
/// [`leaves`].
///
/// A node's children always come after it in obvhs's numbering (and in `convert`'s), so
/// one pass from the last node to the first sees every child's box before its parent.
pub(crate) fn from_cwbvh(
    bvh: &CwBvh,
    leaves: &[Tri4],
    leaf_boxes: Option<&[Bounds]>,
) -> Vec<WideNode> {
    let n = bvh.nodes.len();
    let mut out = vec![WideNode::default(); n];
    let mut node_bounds = vec![EMPTY; n];
    // Each node's first leaf: the leaf children of the nodes before it.
    let is_leaf = |cw: &obvhs::cwbvh::node::CwBvhNode, slot: usize| {
        cw.imask & (1 << slot) == 0 && leaf_size(cw.child_meta[slot]) != 0
    };
    let mut leaf_base = Vec::with_capacity(n);
    let mut next = 0u32;
    for cw in &bvh.nodes {
        leaf_base.push(next);
        next += (0..8).filter(|&s| is_leaf(cw, s)).count() as u32;
    }
    assert_eq!(next as usize, leaves.len(), "one Tri4 per leaf child");
    assert!(leaf_boxes.is_none_or(|b| b.len() == leaves.len()));
    for i in (0..n).rev() {
        let cw = &bvh.nodes[i];
        let node = &mut out[i];
        let mut whole = EMPTY;
        let mut internal = 0u32;
        let mut leaf = 0u32;
        for slot in 0..8 {
            let (b, word) = if cw.imask & (1 << slot) != 0 {
                let c = (cw.child_base_idx + internal) as usize;
                internal += 1;
                assert!(
                    c > i && c < n && (c as u32) < INTERNAL,
                    "CWBVH child {c} of node {i} out of order"
                );
                (node_bounds[c], c as u32 | INTERNAL)
            } else if is_leaf(cw, slot) {
                let k = (leaf_base[i] + leaf) as usize;
                let b = leaf_boxes.map_or_else(|| leaf_bounds(&leaves[k]), |b| b[k]);
                leaf += 1;
                (b, 1 << (leaf - 1))
            } else {
                (EMPTY, 0)
            };
            for a in 0..3 {
                node.planes[a][slot] = b.0[a];
                node.planes[a][8 + slot] = b.1[a];
            }
            node.slot[slot] = word;
            whole = union(whole, b);
        }
        node.leaf_base = leaf_base[i];
        node_bounds[i] = whole;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_is_four_cache_lines() {
        assert_eq!(std::mem::size_of::<WideNode>(), 256);
        assert_eq!(std::mem::align_of::<WideNode>(), 64);
    }
}
