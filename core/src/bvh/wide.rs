//! The traversal's node: obvhs's compressed 8-wide node (Ylitie et al. 2017), re-laid out
//! so that all eight children are tested at once with no per-child branch or byte
//! shuffling.
//!
//! The quantised child planes are obvhs's own bytes, moved so that one axis's lower and
//! upper planes sit in one 16-byte row; the node origin and the grid step (obvhs stores an
//! exponent byte) are plain floats; and each child slot carries the bits it adds to the
//! node's hit mask when its box is hit, precomputed from obvhs's `child_meta`:
//! - a leaf child: its primitives' unary count shifted to their offset from `prim_base`
//!   (what obvhs's `get_child_and_index_bits` computes per visit),
//! - an internal child: `0xff00_0000`, narrowed per ray to the child's traversal-order
//!   bit `1 << (24 + (slot ^ oct_inv))` by one AND (see `node_test`),
//! - an empty slot: 0.
//!
//! The arithmetic of the box test is unchanged (see `node_test`), so every ray visits the
//! same nodes in the same order as with obvhs's `traverse!` and `intersect_ray`.

use obvhs::cwbvh::CwBvh;
use rayon::prelude::*;

/// One 8-wide node, 128 bytes (two cache lines, aligned).
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(64))]
pub(crate) struct WideNode {
    /// Per axis (x, y, z): bytes 0..8 the children's quantised lower planes, 8..16 the upper.
    pub q: [[u8; 16]; 3],
    /// Node grid origin (x, y, z, 0).
    pub p: [f32; 4],
    /// Grid step per axis (x, y, z, 0): `2^(e - 127)`, obvhs's `compute_extent`.
    pub extent: [f32; 4],
    /// Hit-mask bits contributed by each child slot when its box is hit.
    pub bits: [u32; 8],
    /// Index of the first internal child (the others follow in slot order).
    pub child_base: u32,
    /// Leaf slot of the first primitive of the node's leaf children.
    pub prim_base: u32,
    /// Bit `s` set when slot `s` is an internal node.
    pub imask: u32,
    _pad: u32,
}

/// The wide nodes of `bvh`, index for index (child indices keep their meaning).
pub(crate) fn from_cwbvh(bvh: &CwBvh) -> Vec<WideNode> {
    bvh.nodes
        .par_iter()
        .map(|n| {
            let mut q = [[0u8; 16]; 3];
            for (row, (lo, hi)) in q.iter_mut().zip([
                (&n.child_min_x, &n.child_max_x),
                (&n.child_min_y, &n.child_max_y),
                (&n.child_min_z, &n.child_max_z),
            ]) {
                row[..8].copy_from_slice(lo);
                row[8..].copy_from_slice(hi);
            }
            let extent = n.e.map(|e| f32::from_bits(u32::from(e) << 23));
            let mut bits = [0u32; 8];
            for (slot, b) in bits.iter_mut().enumerate() {
                let meta = u32::from(n.child_meta[slot]);
                *b = if n.imask & (1 << slot) != 0 {
                    0xff00_0000
                } else {
                    // Unary primitive count (high 3 bits) at the primitive offset (low 5).
                    (meta >> 5) << (meta & 0x1f)
                };
            }
            WideNode {
                q,
                p: [n.p.x, n.p.y, n.p.z, 0.0],
                extent: [extent[0], extent[1], extent[2], 0.0],
                bits,
                child_base: n.child_base_idx,
                prim_base: n.primitive_base_idx,
                imask: u32::from(n.imask),
                _pad: 0,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_is_two_cache_lines() {
        assert_eq!(std::mem::size_of::<WideNode>(), 128);
        assert_eq!(std::mem::align_of::<WideNode>(), 64);
    }
}
