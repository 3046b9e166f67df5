//! The ray/8-box test of one [`WideNode`], all children at once.
//!
//! Per child and axis, with `n` and `f` the child's near and far planes on that axis
//! (the lower and upper plane, swapped where the direction is negative):
//! - `tn = (n - origin) * inv_dir - pad`, `tf = (f - origin) * inv_dir + pad`;
//! - `tmin = max(tn_x, max(tn_y, tn_z))`, then `max(tmin, 0)`;
//!   `tmax = min(tf_x, min(tf_y, tf_z))`, then `min(tmax, ray.tmax)`;
//! - hit when `tmin <= tmax`.
//!
//! The difference `n - origin` comes first, so its rounding is relative to the distance
//! from the origin to the plane, never to the coordinates' magnitude (a ray far from the
//! world's origin is tested as exactly as one near it).
//!
//! Conservative: `pad[a]` is the ray's spatial margin `m` (in accelerator units) times
//! `|inv_dir[a]|`, so every child box is tested grown by `m` on each side. `Accel` sets
//! `m` to 2^-17 of the largest distance from the ray's origin to the scene's box, which
//! exceeds every rounding that could make the test miss a box whose triangle the leaf
//! test hits: this test's own arithmetic (a subtraction and a multiply, or one fused
//! multiply-add, each rounding relative to the distance from the origin to the plane)
//! and the leaf test's shear (relative to the distance from the origin to the corners).
//! None of these depends on the coordinates' magnitude, so boxes stay tight far from the
//! origin (docs/numerics.md "Far from the origin"). The planes themselves are exact.
//!
//! Builds: portable Rust (one child at a time), SSE2 (four at a time, every x86-64) and
//! AVX2 with FMA (eight at a time, picked at run time). The FMA build rounds once where
//! the others round twice, so a box within a rounding of the margin's edge may be visited
//! by one build and not another; all are conservative, and the closest hit does not depend
//! on which boxes are visited or in which order (ties go to the lower triangle id), so
//! every build returns the same answers (tested).

use glam::Vec3A;

use super::wide::{INTERNAL, WideNode};

/// Per-ray constants of the node test.
#[derive(Clone, Copy, Debug)]
pub(crate) struct NodeRay {
    /// Origin and inverse direction (x, y, z, 0), accelerator space.
    pub origin: [f32; 4],
    pub inv_dir: [f32; 4],
    /// Per axis: the ray's spatial margin times `|inv_dir|` (x, y, z, 0), finite.
    pub pad: [f32; 4],
    /// Float offset of the near planes in each axis row of `WideNode::planes` (0 or 8).
    pub near: [usize; 3],
}

/// What the node test found: the hit children, their entry distances and the primitives
/// of the hit leaves.
#[derive(Clone, Copy, Debug)]
pub(crate) struct NodeHits {
    /// Bit `s` set when child slot `s` is an internal node whose box is hit.
    pub mask: u32,
    /// The OR of the hit leaf children's words: leaf offsets from `leaf_base`.
    pub leaves: u32,
    /// Entry distance of each child's box (meaningful where `mask` has the slot).
    pub tnear: [f32; 8],
}

impl NodeRay {
    /// `dir` must already have its signed zeros folded to +0.0; `margin` (non-negative)
    /// grows every box by that much on each side.
    #[inline(always)]
    pub fn new(origin: Vec3A, dir: Vec3A, inv_dir: Vec3A, margin: f32) -> NodeRay {
        // Bit a set when dir[a] < 0.
        let negative = dir.cmplt(Vec3A::ZERO).bitmask();
        // Capped below infinity: an infinite pad would meet an infinite distance (an
        // empty slot's plane) as inf - inf = NaN. f32::MAX keeps every box it grows hit.
        let pad = (inv_dir.abs() * margin).min(Vec3A::splat(f32::MAX));
        NodeRay {
            origin: origin.extend(0.0).to_array(),
            inv_dir: inv_dir.extend(0.0).to_array(),
            pad: pad.extend(0.0).to_array(),
            near: [0, 1, 2].map(|a| ((negative >> a) & 1) as usize * 8),
        }
    }
}

/// The children of `node` a ray whose current far limit is `tmax` enters. Portable
/// version.
#[inline(always)]
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
pub(crate) fn hits_portable(node: &WideNode, ray: &NodeRay, tmax: f32) -> NodeHits {
    // SSE's max/min: the second operand unless the first is strictly greater/less.
    let max = |a: f32, b: f32| if a > b { a } else { b };
    let min = |a: f32, b: f32| if a < b { a } else { b };
    let mut out = NodeHits {
        mask: 0,
        leaves: 0,
        tnear: [0.0; 8],
    };
    for slot in 0..8 {
        let mut tn = [0f32; 3];
        let mut tf = [0f32; 3];
        for a in 0..3 {
            let near = ray.near[a];
            let n = node.planes[a][near + slot];
            let f = node.planes[a][8 - near + slot];
            tn[a] = (n - ray.origin[a]) * ray.inv_dir[a] - ray.pad[a];
            tf[a] = (f - ray.origin[a]) * ray.inv_dir[a] + ray.pad[a];
        }
        let tmin = max(max(tn[0], max(tn[1], tn[2])), 0.0);
        let tmax_c = min(min(tf[0], min(tf[1], tf[2])), tmax);
        out.tnear[slot] = tmin;
        if tmin <= tmax_c {
            if node.slot[slot] & INTERNAL != 0 {
                out.mask |= 1 << slot;
            } else {
                out.leaves |= node.slot[slot];
            }
        }
    }
    out
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use super::{NodeHits, NodeRay, WideNode};
    use std::arch::x86_64::*;

    /// The primitive mask of the hit leaves: the OR of the words of hit slots whose top
    /// bit (the internal flag) is clear, over one vector of four slots' words.
    #[inline(always)]
    unsafe fn leaf_words(hit: __m128i, words: __m128i) -> __m128i {
        unsafe { _mm_andnot_si128(_mm_srai_epi32::<31>(words), _mm_and_si128(hit, words)) }
    }

    /// [`super::hits_portable`] with SSE2, four children at a time.
    ///
    /// # Safety
    /// SSE2 is part of x86-64, so always safe to call; `unsafe` only for the intrinsics.
    #[inline(always)]
    pub(crate) unsafe fn hits_sse2(node: &WideNode, ray: &NodeRay, tmax: f32) -> NodeHits {
        unsafe {
            let mut tn = [[_mm_setzero_ps(); 2]; 3];
            let mut tf = [[_mm_setzero_ps(); 2]; 3];
            for a in 0..3 {
                let near = *ray.near.get_unchecked(a);
                let row = node.planes.get_unchecked(a).as_ptr();
                let o = _mm_set1_ps(*ray.origin.get_unchecked(a));
                let inv = _mm_set1_ps(*ray.inv_dir.get_unchecked(a));
                let pad = _mm_set1_ps(*ray.pad.get_unchecked(a));
                for h in 0..2 {
                    let n = _mm_load_ps(row.add(near + 4 * h));
                    let f = _mm_load_ps(row.add(8 - near + 4 * h));
                    tn[a][h] = _mm_sub_ps(_mm_mul_ps(_mm_sub_ps(n, o), inv), pad);
                    tf[a][h] = _mm_add_ps(_mm_mul_ps(_mm_sub_ps(f, o), inv), pad);
                }
            }
            let zero = _mm_setzero_ps();
            let tm = _mm_set1_ps(tmax);
            let mut out = NodeHits {
                mask: 0,
                leaves: 0,
                tnear: [0.0; 8],
            };
            let mut acc = _mm_setzero_si128();
            for h in 0..2 {
                let tmin = _mm_max_ps(tn[0][h], _mm_max_ps(tn[1][h], tn[2][h]));
                let tmax4 = _mm_min_ps(tf[0][h], _mm_min_ps(tf[1][h], tf[2][h]));
                let tmin = _mm_max_ps(tmin, zero);
                let tmax4 = _mm_min_ps(tmax4, tm);
                let hit = _mm_cmple_ps(tmin, tmax4);
                _mm_storeu_ps(out.tnear.as_mut_ptr().add(4 * h), tmin);
                let words = _mm_load_si128(node.slot.as_ptr().add(4 * h) as *const __m128i);
                let internal = _mm_movemask_ps(_mm_castsi128_ps(words)) as u32;
                out.mask |= ((_mm_movemask_ps(hit) as u32) & internal) << (4 * h);
                acc = _mm_or_si128(acc, leaf_words(_mm_castps_si128(hit), words));
            }
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0x4e>(acc));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0xb1>(acc));
            out.leaves = _mm_cvtsi128_si32(acc) as u32;
            out
        }
    }

    /// [`hits_sse2`] with AVX2 and FMA, all eight children in one vector.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) unsafe fn hits_avx2(node: &WideNode, ray: &NodeRay, tmax: f32) -> NodeHits {
        unsafe {
            let mut tn = [_mm256_setzero_ps(); 3];
            let mut tf = [_mm256_setzero_ps(); 3];
            for a in 0..3 {
                let near = *ray.near.get_unchecked(a);
                let row = node.planes.get_unchecked(a).as_ptr();
                let o = _mm256_broadcast_ss(ray.origin.get_unchecked(a));
                let inv = _mm256_broadcast_ss(ray.inv_dir.get_unchecked(a));
                let pad = _mm256_broadcast_ss(ray.pad.get_unchecked(a));
                let n = _mm256_load_ps(row.add(near));
                let f = _mm256_load_ps(row.add(8 - near));
                tn[a] = _mm256_fmsub_ps(_mm256_sub_ps(n, o), inv, pad);
                tf[a] = _mm256_fmadd_ps(_mm256_sub_ps(f, o), inv, pad);
            }
            let tmin = _mm256_max_ps(tn[0], _mm256_max_ps(tn[1], tn[2]));
            let tmax8 = _mm256_min_ps(tf[0], _mm256_min_ps(tf[1], tf[2]));
            let tmin = _mm256_max_ps(tmin, _mm256_setzero_ps());
            let tmax8 = _mm256_min_ps(tmax8, _mm256_set1_ps(tmax));
            let hit = _mm256_cmp_ps::<_CMP_LE_OS>(tmin, tmax8);
            let words = _mm256_load_si256(node.slot.as_ptr() as *const __m256i);
            // The words' top bits are the internal flags.
            let internal = _mm256_movemask_ps(_mm256_castsi256_ps(words)) as u32;
            let mut out = NodeHits {
                mask: _mm256_movemask_ps(hit) as u32 & internal,
                leaves: 0,
                tnear: [0.0; 8],
            };
            _mm256_storeu_ps(out.tnear.as_mut_ptr(), tmin);
            let hit = _mm256_castps_si256(hit);
            let v =
                _mm256_andnot_si256(_mm256_srai_epi32::<31>(words), _mm256_and_si256(hit, words));
            let mut acc = _mm_or_si128(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0x4e>(acc));
            acc = _mm_or_si128(acc, _mm_shuffle_epi32::<0xb1>(acc));
            out.leaves = _mm_cvtsi128_si32(acc) as u32;
            out
        }
    }
}
