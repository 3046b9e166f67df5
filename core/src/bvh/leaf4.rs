//! The leaf: up to four triangles stored together and tested together, one per SSE
//! lane, with the watertight test of [`crate::intersect::WatertightRay::intersect`] in
//! every lane: the same operations in the same order, so each lane's answer is the
//! reference's, bit for bit.
//!
//! Why four at once: a leaf of one triangle costs a node slot and a node visit per
//! triangle; a leaf of up to four (what the 8-wide collapse makes when SAH finds it
//! cheaper, see `convert`) is tested for the price of about one, and the tree over it has
//! fewer, fuller nodes (Embree's BVH8 with its four-triangle leaves does the same).
//!
//! Layout ([`Tri4`]): per axis, per corner, the four triangles' coordinates side by side
//! (`v[axis][corner] = [lane 0, lane 1, lane 2, lane 3]`), so the ray's axis permutation
//! picks three rows of three vectors and every step of the test is one vector operation
//! over the four triangles: `a = v - o`; `x = a[kx] - sx * a[kz]`,
//! `y = a[ky] - sy * a[kz]`; the edge functions `u = cx*by - cy*bx`,
//! `v = ax*cy - ay*cx`, `w = bx*ay - by*ax`; the sign test; then `finish_hit`'s
//! determinant ([`crate::intersect::sum3`] as compares and selects), distance, range,
//! error bound ([`crate::intersect::t_error_bound`]) and barycentrics. A lane with an edge function exactly zero has its three recomputed in
//! double precision, as the reference does (rare: taken lane by lane, out of line).
//!
//! Padding: a leaf of fewer than four triangles fills its other lanes with NaN corners
//! and the id [`PAD`]. NaN propagates through every subtraction and product, so a padding
//! lane's edge functions and determinant are NaN, and the determinant test (`finite and
//! non-zero`, the reference's) rejects it: a padding lane never hits, and no mask is
//! needed. (Real triangles are finite: `Accel` leaves out triangles with a non-finite
//! corner.)
//!
//! Which of several hits wins is not decided here: every lane's hit is returned and the
//! caller applies the one rule of the whole accelerator (smaller distance, then lower
//! triangle id), which depends neither on the order of lanes nor of leaves.

use glam::Vec3;

#[cfg(target_arch = "x86_64")]
use crate::intersect::gamma;
use crate::intersect::{TriangleHit, WatertightRay};

/// The id of a padding lane.
pub(crate) const PAD: u32 = u32::MAX;

/// Up to four triangles in accelerator space: `v[axis][corner][lane]`, and the triangle
/// id of each lane ([`PAD`] for padding, whose corners are NaN). 160 bytes, aligned to 32
/// so that each leaf spans three cache lines, never four.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub(crate) struct Tri4 {
    pub v: [[[f32; 4]; 3]; 3],
    pub ids: [u32; 4],
}

impl Tri4 {
    /// A leaf of `tris` (one to four, with their ids), in lane order.
    pub fn new(tris: &[([Vec3; 3], u32)]) -> Tri4 {
        debug_assert!(!tris.is_empty() && tris.len() <= 4);
        let mut out = Tri4 {
            v: [[[f32::NAN; 4]; 3]; 3],
            ids: [PAD; 4],
        };
        for (lane, (corners, id)) in tris.iter().take(4).enumerate() {
            for (c, p) in corners.iter().enumerate() {
                for axis in 0..3 {
                    out.v[axis][c][lane] = p[axis];
                }
            }
            out.ids[lane] = *id;
        }
        out
    }

    /// The corners of lane `lane`.
    pub fn corners(&self, lane: usize) -> [Vec3; 3] {
        let v = &self.v;
        [0, 1, 2].map(|c| Vec3::new(v[0][c][lane], v[1][c][lane], v[2][c][lane]))
    }

    /// Lanes holding a triangle.
    pub fn count(&self) -> u32 {
        self.ids.iter().filter(|&&i| i != PAD).count() as u32
    }
}

/// The hits of one leaf test: lane `l` hit when bit `l` of `mask` is set, at `t[l]` with
/// barycentrics `b0[l], b1[l], b2[l]` (other lanes' values are meaningless).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Hits4 {
    pub mask: u32,
    pub t: [f32; 4],
    pub b0: [f32; 4],
    pub b1: [f32; 4],
    pub b2: [f32; 4],
}

impl Hits4 {
    /// Lane `l`'s hit (meaningful where `mask` has the lane).
    #[inline(always)]
    pub fn lane(&self, l: usize) -> TriangleHit {
        TriangleHit {
            t: self.t[l],
            b0: self.b0[l],
            b1: self.b1[l],
            b2: self.b2[l],
        }
    }
}

/// The edge functions in double precision, rounded to f32: the reference's fallback when
/// one of them is exactly zero in single precision.
#[inline(never)]
#[cold]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
fn edges_f64(x: [f32; 3], y: [f32; 3]) -> [f32; 3] {
    let (ax, ay, bx, by, cx, cy) = (
        x[0] as f64,
        y[0] as f64,
        x[1] as f64,
        y[1] as f64,
        x[2] as f64,
        y[2] as f64,
    );
    [
        (cx * by - cy * bx) as f32,
        (ax * cy - ay * cx) as f32,
        (bx * ay - by * ax) as f32,
    ]
}

/// `ray.intersect(v0, v1, v2, tmin, tmax)` for every lane of `leaf` at once. Inlined
/// into the traversal: out of line, the call cost 9% more instructions per ray.
#[inline(always)]
pub(crate) fn intersect(ray: &WatertightRay, leaf: &Tri4, tmin: f32, tmax: f32) -> Hits4 {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: SSE2 is part of x86-64; `kx`, `ky`, `kz` are below 3 by construction.
        unsafe { x86::intersect_sse(ray, leaf, tmin, tmax) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        intersect_portable(ray, leaf, tmin, tmax)
    }
}

/// The reference test lane by lane (non-x86-64 targets, and the tests' reference).
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
pub(crate) fn intersect_portable(ray: &WatertightRay, leaf: &Tri4, tmin: f32, tmax: f32) -> Hits4 {
    let mut out = Hits4::default();
    for lane in 0..4 {
        let [a, b, c] = leaf.corners(lane);
        if let Some(h) = ray.intersect(a, b, c, tmin, tmax) {
            out.mask |= 1 << lane;
            out.t[lane] = h.t;
            out.b0[lane] = h.b0;
            out.b1[lane] = h.b1;
            out.b2[lane] = h.b2;
        }
    }
    out
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Hits4, Tri4, WatertightRay, edges_f64, gamma};
    use std::arch::x86_64::*;

    /// `m ? a : b`, lane by lane (SSE2 has no blend).
    #[inline(always)]
    unsafe fn select(m: __m128, a: __m128, b: __m128) -> __m128 {
        unsafe { _mm_or_ps(_mm_and_ps(m, a), _mm_andnot_ps(m, b)) }
    }

    #[inline(always)]
    unsafe fn abs(a: __m128) -> __m128 {
        unsafe { _mm_andnot_ps(_mm_set1_ps(-0.0), a) }
    }

    /// `|a|.max(|b|).max(|c|)`, as `t_error_bound`'s `max3`, where no operand is NaN:
    /// then `maxps` is `f32::max` (they differ only on NaN; all operands are `+0.0` or
    /// above after `abs`). The lanes whose bound is used have no NaN among their `x`, `y`,
    /// `z` and edge functions: each of `x` and `y` enters two edge functions and a NaN
    /// edge function makes the determinant NaN (refused), and a NaN `z` makes the
    /// distance NaN (refused). Other lanes' bounds are never read.
    #[inline(always)]
    unsafe fn max3(v: [__m128; 3]) -> __m128 {
        unsafe { _mm_max_ps(_mm_max_ps(abs(v[0]), abs(v[1])), abs(v[2])) }
    }

    /// [`crate::intersect::sum3`] lane by lane: the same compares pick the same order,
    /// and the same additions follow.
    #[inline(always)]
    unsafe fn sum3([a, b, c]: [__m128; 3]) -> __m128 {
        unsafe {
            let m = _mm_cmple_ps(abs(a), abs(b));
            let (a, b) = (select(m, a, b), select(m, b, a));
            let m = _mm_cmple_ps(abs(b), abs(c));
            let (b, c) = (select(m, b, c), select(m, c, b));
            let m = _mm_cmple_ps(abs(a), abs(b));
            let (a, b) = (select(m, a, b), select(m, b, a));
            let cancel = _mm_cmpeq_ps(b, _mm_xor_ps(c, _mm_set1_ps(-0.0)));
            select(cancel, a, _mm_add_ps(_mm_add_ps(a, b), c))
        }
    }

    #[inline(always)]
    unsafe fn lanes(v: __m128) -> [f32; 4] {
        let mut out = [0f32; 4];
        unsafe { _mm_storeu_ps(out.as_mut_ptr(), v) };
        out
    }

    /// [`super::intersect`] with SSE2.
    ///
    /// # Safety
    /// SSE2 is part of x86-64; `ray.kx`, `ray.ky`, `ray.kz` must be below 3.
    #[inline(always)]
    pub(super) unsafe fn intersect_sse(
        ray: &WatertightRay,
        leaf: &Tri4,
        tmin: f32,
        tmax: f32,
    ) -> Hits4 {
        unsafe {
            debug_assert!(ray.kx < 3 && ray.ky < 3 && ray.kz < 3);
            let o = ray.origin.to_array();
            // a = v - origin for the three permuted axes, corner by corner.
            let rows = |k: usize| {
                let row = leaf.v.get_unchecked(k);
                let ok = _mm_set1_ps(*o.get_unchecked(k));
                [0, 1, 2].map(|c| _mm_sub_ps(_mm_load_ps(row.get_unchecked(c).as_ptr()), ok))
            };
            let (px, py, pz) = (rows(ray.kx), rows(ray.ky), rows(ray.kz));
            // x = a[kx] - sx * a[kz], y = a[ky] - sy * a[kz], per corner.
            let (sx, sy) = (_mm_set1_ps(ray.sx), _mm_set1_ps(ray.sy));
            let x = [0, 1, 2].map(|c| _mm_sub_ps(px[c], _mm_mul_ps(sx, pz[c])));
            let y = [0, 1, 2].map(|c| _mm_sub_ps(py[c], _mm_mul_ps(sy, pz[c])));
            let edge =
                |i: usize, j: usize| _mm_sub_ps(_mm_mul_ps(x[i], y[j]), _mm_mul_ps(y[i], x[j]));
            // u = cx*by - cy*bx, v = ax*cy - ay*cx, w = bx*ay - by*ax.
            let mut e = [edge(2, 1), edge(0, 2), edge(1, 0)];
            let zero = _mm_setzero_ps();
            let zeros = _mm_or_ps(
                _mm_or_ps(_mm_cmpeq_ps(e[0], zero), _mm_cmpeq_ps(e[1], zero)),
                _mm_cmpeq_ps(e[2], zero),
            );
            let mut fallback = _mm_movemask_ps(zeros) as u32;
            if fallback != 0 {
                let (xs, ys) = (x.map(|v| lanes(v)), y.map(|v| lanes(v)));
                let mut es = e.map(|v| lanes(v));
                while fallback != 0 {
                    let l = fallback.trailing_zeros() as usize;
                    fallback &= fallback - 1;
                    let f = edges_f64(xs.map(|v| v[l]), ys.map(|v| v[l]));
                    for k in 0..3 {
                        es[k][l] = f[k];
                    }
                }
                e = es.map(|v| _mm_loadu_ps(v.as_ptr()));
            }
            // Rejected where some edge function is negative and some positive.
            let neg = _mm_or_ps(
                _mm_or_ps(_mm_cmplt_ps(e[0], zero), _mm_cmplt_ps(e[1], zero)),
                _mm_cmplt_ps(e[2], zero),
            );
            let pos = _mm_or_ps(
                _mm_or_ps(_mm_cmpgt_ps(e[0], zero), _mm_cmpgt_ps(e[1], zero)),
                _mm_cmpgt_ps(e[2], zero),
            );
            let mut ok = _mm_andnot_ps(_mm_and_ps(neg, pos), _mm_castsi128_ps(_mm_set1_epi32(-1)));
            if _mm_movemask_ps(ok) == 0 {
                return Hits4::default();
            }
            // finish_hit: the determinant, finite and non-zero.
            let det = sum3(e);
            ok = _mm_and_ps(ok, _mm_cmpneq_ps(det, zero));
            ok = _mm_and_ps(ok, _mm_cmplt_ps(abs(det), _mm_set1_ps(f32::INFINITY)));
            let sz = _mm_set1_ps(ray.sz);
            let z = [0, 1, 2].map(|c| _mm_mul_ps(sz, pz[c]));
            let tt = sum3([0, 1, 2].map(|c| _mm_mul_ps(e[c], z[c])));
            let inv = _mm_div_ps(_mm_set1_ps(1.0), det);
            let t = _mm_mul_ps(tt, inv);
            ok = _mm_and_ps(ok, _mm_cmpgt_ps(t, _mm_set1_ps(tmin)));
            ok = _mm_and_ps(ok, _mm_cmplt_ps(t, _mm_set1_ps(tmax)));
            // t_error_bound, operation for operation.
            let max_z = max3(z);
            let delta_z = _mm_mul_ps(_mm_set1_ps(gamma(3)), max_z);
            let (max_x, max_y) = (max3(x), max3(y));
            let g5 = _mm_set1_ps(gamma(5));
            let delta_x = _mm_mul_ps(g5, _mm_add_ps(max_x, max_z));
            let delta_y = _mm_mul_ps(g5, _mm_add_ps(max_y, max_z));
            let delta_e = _mm_mul_ps(
                _mm_set1_ps(2.0),
                _mm_add_ps(
                    _mm_add_ps(
                        _mm_mul_ps(_mm_mul_ps(_mm_set1_ps(gamma(2)), max_x), max_y),
                        _mm_mul_ps(delta_y, max_x),
                    ),
                    _mm_mul_ps(delta_x, max_y),
                ),
            );
            let max_e = max3(e);
            let inner = _mm_add_ps(
                _mm_add_ps(
                    _mm_mul_ps(_mm_mul_ps(_mm_set1_ps(gamma(3)), max_e), max_z),
                    _mm_mul_ps(delta_e, max_z),
                ),
                _mm_mul_ps(delta_z, max_e),
            );
            let bound = _mm_mul_ps(_mm_mul_ps(_mm_set1_ps(3.0), inner), abs(inv));
            // Refused where `t <= bound` (a NaN bound refuses nothing, as in the reference).
            ok = _mm_and_ps(ok, _mm_cmpnle_ps(t, bound));
            let mask = _mm_movemask_ps(ok) as u32;
            if mask == 0 {
                return Hits4::default();
            }
            Hits4 {
                mask,
                t: lanes(t),
                b0: lanes(_mm_mul_ps(e[0], inv)),
                b1: lanes(_mm_mul_ps(e[1], inv)),
                b2: lanes(_mm_mul_ps(e[2], inv)),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{PathKey, Purpose, uniform_sphere};

    fn lane_hit(h: &Hits4, l: usize) -> Option<TriangleHit> {
        (h.mask >> l & 1 != 0).then(|| h.lane(l))
    }

    fn bits(h: Option<TriangleHit>) -> Option<[u32; 4]> {
        h.map(|h| [h.t, h.b0, h.b1, h.b2].map(f32::to_bits))
    }

    /// Random rays against leaves of one to four random triangles, and rays through
    /// shared vertices and edges on a grid (where edge functions are exactly zero, the
    /// double-precision fallback): every lane answers what the reference answers for its
    /// triangle, bit for bit, and padding lanes never hit.
    #[test]
    fn every_lane_is_the_reference_bit_for_bit() {
        let (mut checked, mut hits, mut zeros, mut multi) = (0u32, 0u32, 0u32, 0u32);
        for i in 0..60_000u32 {
            let k = PathKey {
                seed: 3,
                pixel: i,
                sample: 0,
            };
            let corner = |j: u32| {
                let u = k.uniform2(0, Purpose::Film, j);
                let r = k.uniform(1, Purpose::Film, j);
                uniform_sphere(u) * r * 4.0
            };
            let grid = i % 4 == 0;
            let n = 1 + (i % 4) as usize;
            let tris: Vec<([Vec3; 3], u32)> = (0..n as u32)
                .map(|t| {
                    let c = [0, 1, 2].map(|j| corner(3 * t + j));
                    let c = if grid {
                        c.map(|v| (v * 2.0).round())
                    } else {
                        c
                    };
                    (c, 1000 + t)
                })
                .collect();
            let o = if grid {
                (corner(20) * 2.0).round() + Vec3::new(0.0, 0.0, 9.0)
            } else {
                corner(20) * 3.0
            };
            let d = if i % 8 == 0 {
                Vec3::new(0.0, 0.0, -1.0)
            } else {
                uniform_sphere(k.uniform2(2, Purpose::Film, 0))
            };
            let wt = WatertightRay::new(o, d);
            let leaf = Tri4::new(&tris);
            assert_eq!(leaf.count(), n as u32);
            for (tmin, tmax) in [(0.0, f32::INFINITY), (0.5, 3.0)] {
                let got = intersect(&wt, &leaf, tmin, tmax);
                assert_eq!(got.mask >> n, 0, "a padding lane hit");
                for (l, (c, _)) in tris.iter().enumerate() {
                    let want = wt.intersect(c[0], c[1], c[2], tmin, tmax);
                    assert_eq!(
                        bits(want),
                        bits(lane_hit(&got, l)),
                        "{c:?} {o} {d}: {want:?} vs {got:?}"
                    );
                    checked += 1;
                    hits += want.is_some() as u32;
                    let a = c.map(|v| v - o);
                    if grid
                        && (0..3).any(|j| {
                            let (p, q) = (a[(j + 1) % 3], a[(j + 2) % 3]);
                            p.x * q.y - p.y * q.x == 0.0
                        })
                    {
                        zeros += 1;
                    }
                }
                multi += (got.mask.count_ones() > 1) as u32;
            }
        }
        assert!(
            hits > 4_000 && zeros > 100 && multi > 100,
            "{checked} {hits} {zeros} {multi}"
        );
    }

    /// Padding lanes (NaN corners) stay out whatever the ray: from the origin, along the
    /// axes, with infinite and zero limits.
    #[test]
    fn padding_never_hits() {
        assert_eq!(std::mem::size_of::<Tri4>(), 160);
        let tri = [
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::Y,
        ];
        let leaf = Tri4::new(&[(tri, 7)]);
        let mut hits = 0;
        for i in 0..2_000u32 {
            let k = PathKey {
                seed: 9,
                pixel: i,
                sample: 0,
            };
            let o = uniform_sphere(k.uniform2(0, Purpose::Film, 0)) * 3.0;
            let d = match i % 4 {
                0 => -o,
                1 => Vec3::Z,
                2 => Vec3::new(0.0, 0.0, -1.0),
                _ => uniform_sphere(k.uniform2(1, Purpose::Film, 0)),
            };
            let wt = WatertightRay::new(o, d);
            for (tmin, tmax) in [
                (0.0, f32::INFINITY),
                (f32::NEG_INFINITY, f32::INFINITY),
                (0.0, 0.0),
            ] {
                let got = intersect(&wt, &leaf, tmin, tmax);
                assert_eq!(got.mask & !1, 0);
                hits += got.mask;
            }
        }
        assert!(hits > 500, "{hits}");
    }
}
