//! The ray/8-box test of one [`WideNode`], all children at once.
//!
//! The arithmetic is obvhs's `CwBvhNode::intersect_ray_simd`, operation for operation, so
//! the same boxes are hit to the bit:
//! - per node, `adj_inv = extent * inv_dir` and `adj_orig = (p - origin) * inv_dir`;
//! - per child and axis, `t = q * adj_inv + adj_orig` (a multiply, then an add: no FMA),
//!   with `q` the child's lower plane on that axis for the entry distance and the upper
//!   one for the exit, swapped where the direction is negative (`dir < 0`), and
//!   `adj_orig` lowered by the ray's slack `pad` for entry distances and raised by it for
//!   exit distances (dray's addition: see "Conservative" below);
//! - `tmin = max(tx, max(ty, tz))`, then `max(tmin, 1e-4)`; `tmax = min(tx, min(ty, tz))`,
//!   then `min(tmax, ray.tmax)` (same operand order, so NaNs fall the same way);
//! - hit when `tmin <= tmax`.
//!
//! Conservative: `pad[a]` is the ray's spatial margin `m` (in accelerator units) divided
//! by `|dir[a]|`, so every child box is tested grown by `m` on each side. `Accel` sets
//! `m` to 2^-17 of the largest distance from the ray's origin to the scene's box, which
//! exceeds every rounding that could make the test miss a box whose triangle the leaf
//! test hits: this test's own arithmetic (relative to the distances from the origin to
//! the node's planes and to the node's size), the 8-bit quantisation of child planes
//! (relative to the parent's size), and the leaf test's shear (relative to the distance
//! from the origin to the corners). None of these depends on the coordinates' magnitude,
//! so boxes stay tight far from the origin (docs/numerics.md "Far from the origin").
//! With a zero `pad` the test is obvhs's, bit for bit.
//!
//! What changes is the decoding: a child's planes are converted eight at a time
//! (`u8 -> i32 -> f32`, exact), the near/far choice is a per-ray byte offset instead of a
//! branch, and the hit mask is the OR of the hit children's precomputed bits instead of a
//! loop over the children. Two builds of the same code: SSE2 (every x86-64) and AVX2,
//! picked at run time; elsewhere a portable scalar version with the same semantics.

use super::wide::WideNode;

/// obvhs's lower bound on a box's entry distance (`cwbvh::node::EPSILON`).
pub(crate) const NODE_EPSILON: f32 = 0.0001;

/// `NodeRay::order_bits` for each `oct_inv`.
const ORDER_BITS: [[u32; 8]; 8] = {
    let mut t = [[0u32; 8]; 8];
    let mut oct = 0;
    while oct < 8 {
        let mut slot = 0;
        while slot < 8 {
            t[oct][slot] = (1u32 << (24 + (slot ^ oct))) | 0x00ff_ffff;
            slot += 1;
        }
        oct += 1;
    }
    t
};

/// Per-ray constants of the node test.
#[derive(Clone, Copy, Debug)]
pub(crate) struct NodeRay {
    /// Origin and inverse direction (x, y, z, 0), accelerator space.
    pub origin: [f32; 4],
    pub inv_dir: [f32; 4],
    /// Per axis: the ray's spatial margin divided by `|dir|`, `m * |inv_dir|` (x, y, z, 0).
    pub pad: [f32; 4],
    /// Byte offset of the near planes in each axis row of `WideNode::q` (0 or 8).
    pub near: [usize; 3],
    /// Per slot: the traversal-order bit of an internal child, `1 << (24 + (slot ^
    /// oct_inv))`, with the low 24 bits set so that leaf bits pass unchanged.
    pub order_bits: [u32; 8],
    /// obvhs's `ray_get_octant_inv4` byte: bit 2 set when `dir.x >= 0`, bit 1 for y,
    /// bit 0 for z.
    pub oct_inv: u32,
}

impl NodeRay {
    /// `dir` must already have its signed zeros folded to +0.0; `margin` (non-negative)
    /// grows every box by that much on each side.
    pub fn new(origin: [f32; 3], dir: [f32; 3], inv_dir: [f32; 3], margin: f32) -> NodeRay {
        let oct_inv = (if dir[0] < 0.0 { 0 } else { 4 })
            | (if dir[1] < 0.0 { 0 } else { 2 })
            | (if dir[2] < 0.0 { 0 } else { 1 });
        NodeRay {
            origin: [origin[0], origin[1], origin[2], 0.0],
            inv_dir: [inv_dir[0], inv_dir[1], inv_dir[2], 0.0],
            pad: [
                margin * inv_dir[0].abs(),
                margin * inv_dir[1].abs(),
                margin * inv_dir[2].abs(),
                0.0,
            ],
            near: dir.map(|d| if d < 0.0 { 8 } else { 0 }),
            order_bits: ORDER_BITS[oct_inv as usize],
            oct_inv,
        }
    }
}

/// The node's hit mask for a ray whose current far limit is `tmax`: internal children
/// hit in the top byte (traversal-order bits), primitives of hit leaves in the low 24
/// bits (offsets from `prim_base`). Portable version.
#[inline(always)]
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
pub(crate) fn hits_portable(node: &WideNode, ray: &NodeRay, tmax: f32) -> u32 {
    let mut adj_inv = [0f32; 3];
    let mut orig_near = [0f32; 3];
    let mut orig_far = [0f32; 3];
    for a in 0..3 {
        adj_inv[a] = node.extent[a] * ray.inv_dir[a];
        let adj_orig = (node.p[a] - ray.origin[a]) * ray.inv_dir[a];
        orig_near[a] = adj_orig - ray.pad[a];
        orig_far[a] = adj_orig + ray.pad[a];
    }
    // SSE's max/min: the second operand unless the first is strictly greater/less.
    let max = |a: f32, b: f32| if a > b { a } else { b };
    let min = |a: f32, b: f32| if a < b { a } else { b };
    let mut mask = 0u32;
    for slot in 0..8 {
        let mut tn = [0f32; 3];
        let mut tf = [0f32; 3];
        for a in 0..3 {
            let near = ray.near[a];
            let qn = f32::from(node.q[a][near + slot]);
            let qf = f32::from(node.q[a][8 - near + slot]);
            tn[a] = qn * adj_inv[a] + orig_near[a];
            tf[a] = qf * adj_inv[a] + orig_far[a];
        }
        let tmin = max(max(tn[0], max(tn[1], tn[2])), NODE_EPSILON);
        let tmax_c = min(min(tf[0], min(tf[1], tf[2])), tmax);
        if tmin <= tmax_c {
            mask |= node.bits[slot] & ray.order_bits[slot];
        }
    }
    mask
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use super::{NODE_EPSILON, NodeRay, WideNode};
    use std::arch::x86_64::*;

    /// [`super::hits_portable`] with SSE2, four children at a time.
    ///
    /// # Safety
    /// SSE2 is part of x86-64, so always safe to call; `unsafe` only for the intrinsics.
    #[inline(always)]
    pub(crate) unsafe fn hits_sse2(node: &WideNode, ray: &NodeRay, tmax: f32) -> u32 {
        unsafe {
            let inv = _mm_loadu_ps(ray.inv_dir.as_ptr());
            let adj_inv = _mm_mul_ps(_mm_loadu_ps(node.extent.as_ptr()), inv);
            let adj_orig = _mm_mul_ps(
                _mm_sub_ps(
                    _mm_loadu_ps(node.p.as_ptr()),
                    _mm_loadu_ps(ray.origin.as_ptr()),
                ),
                inv,
            );
            let pad = _mm_loadu_ps(ray.pad.as_ptr());
            let (near_orig, far_orig) = (_mm_sub_ps(adj_orig, pad), _mm_add_ps(adj_orig, pad));
            let zero = _mm_setzero_si128();
            // Eight bytes to two vectors of four floats (exact).
            let planes = |row: &[u8; 16], off: usize| -> (__m128, __m128) {
                let b = _mm_loadl_epi64(row.as_ptr().add(off) as *const __m128i);
                let w = _mm_unpacklo_epi8(b, zero);
                (
                    _mm_cvtepi32_ps(_mm_unpacklo_epi16(w, zero)),
                    _mm_cvtepi32_ps(_mm_unpackhi_epi16(w, zero)),
                )
            };
            let mut tn = [[_mm_setzero_ps(); 2]; 3];
            let mut tf = [[_mm_setzero_ps(); 2]; 3];
            // Per axis: the node's grid step, and its origin for entry and exit distances.
            let lanes = [
                (
                    _mm_shuffle_ps::<0x00>(adj_inv, adj_inv),
                    _mm_shuffle_ps::<0x00>(near_orig, near_orig),
                    _mm_shuffle_ps::<0x00>(far_orig, far_orig),
                ),
                (
                    _mm_shuffle_ps::<0x55>(adj_inv, adj_inv),
                    _mm_shuffle_ps::<0x55>(near_orig, near_orig),
                    _mm_shuffle_ps::<0x55>(far_orig, far_orig),
                ),
                (
                    _mm_shuffle_ps::<0xaa>(adj_inv, adj_inv),
                    _mm_shuffle_ps::<0xaa>(near_orig, near_orig),
                    _mm_shuffle_ps::<0xaa>(far_orig, far_orig),
                ),
            ];
            for a in 0..3 {
                let near = *ray.near.get_unchecked(a);
                let row = node.q.get_unchecked(a);
                let (n0, n1) = planes(row, near);
                let (f0, f1) = planes(row, 8 - near);
                let (s, on, of) = lanes[a];
                tn[a] = [
                    _mm_add_ps(_mm_mul_ps(n0, s), on),
                    _mm_add_ps(_mm_mul_ps(n1, s), on),
                ];
                tf[a] = [
                    _mm_add_ps(_mm_mul_ps(f0, s), of),
                    _mm_add_ps(_mm_mul_ps(f1, s), of),
                ];
            }
            let eps = _mm_set1_ps(NODE_EPSILON);
            let tm = _mm_set1_ps(tmax);
            let mut acc = _mm_setzero_si128();
            for h in 0..2 {
                let tmin = _mm_max_ps(tn[0][h], _mm_max_ps(tn[1][h], tn[2][h]));
                let tmax4 = _mm_min_ps(tf[0][h], _mm_min_ps(tf[1][h], tf[2][h]));
                let tmin = _mm_max_ps(tmin, eps);
                let tmax4 = _mm_min_ps(tmax4, tm);
                let hit = _mm_castps_si128(_mm_cmple_ps(tmin, tmax4));
                let bits = _mm_and_si128(
                    _mm_loadu_si128(node.bits.as_ptr().add(4 * h) as *const __m128i),
                    _mm_loadu_si128(ray.order_bits.as_ptr().add(4 * h) as *const __m128i),
                );
                acc = _mm_or_si128(acc, _mm_and_si128(hit, bits));
            }
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0x4e>(acc));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0xb1>(acc));
            _mm_cvtsi128_si32(acc) as u32
        }
    }

    /// [`hits_sse2`] with AVX2, all eight children in one vector.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) unsafe fn hits_avx2(node: &WideNode, ray: &NodeRay, tmax: f32) -> u32 {
        unsafe {
            let inv = _mm_loadu_ps(ray.inv_dir.as_ptr());
            let adj_inv = _mm_mul_ps(_mm_loadu_ps(node.extent.as_ptr()), inv);
            let adj_orig = _mm_mul_ps(
                _mm_sub_ps(
                    _mm_loadu_ps(node.p.as_ptr()),
                    _mm_loadu_ps(ray.origin.as_ptr()),
                ),
                inv,
            );
            let pad = _mm_loadu_ps(ray.pad.as_ptr());
            let (near_orig, far_orig) = (_mm_sub_ps(adj_orig, pad), _mm_add_ps(adj_orig, pad));
            let planes = |row: &[u8; 16], off: usize| -> __m256 {
                let b = _mm_loadl_epi64(row.as_ptr().add(off) as *const __m128i);
                _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(b))
            };
            let s = [
                _mm256_broadcastss_ps(adj_inv),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0x55>(adj_inv, adj_inv)),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0xaa>(adj_inv, adj_inv)),
            ];
            let on = [
                _mm256_broadcastss_ps(near_orig),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0x55>(near_orig, near_orig)),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0xaa>(near_orig, near_orig)),
            ];
            let of = [
                _mm256_broadcastss_ps(far_orig),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0x55>(far_orig, far_orig)),
                _mm256_broadcastss_ps(_mm_shuffle_ps::<0xaa>(far_orig, far_orig)),
            ];
            let mut tn = [_mm256_setzero_ps(); 3];
            let mut tf = [_mm256_setzero_ps(); 3];
            for a in 0..3 {
                let near = *ray.near.get_unchecked(a);
                let row = node.q.get_unchecked(a);
                tn[a] = _mm256_add_ps(_mm256_mul_ps(planes(row, near), s[a]), on[a]);
                tf[a] = _mm256_add_ps(_mm256_mul_ps(planes(row, 8 - near), s[a]), of[a]);
            }
            let tmin = _mm256_max_ps(tn[0], _mm256_max_ps(tn[1], tn[2]));
            let tmax8 = _mm256_min_ps(tf[0], _mm256_min_ps(tf[1], tf[2]));
            let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(NODE_EPSILON));
            let tmax8 = _mm256_min_ps(tmax8, _mm256_set1_ps(tmax));
            let hit = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OS>(tmin, tmax8));
            let bits = _mm256_and_si256(
                _mm256_loadu_si256(node.bits.as_ptr() as *const __m256i),
                _mm256_loadu_si256(ray.order_bits.as_ptr() as *const __m256i),
            );
            let v = _mm256_and_si256(hit, bits);
            let mut acc = _mm_or_si128(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0x4e>(acc));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0xb1>(acc));
            _mm_cvtsi128_si32(acc) as u32
        }
    }
}
