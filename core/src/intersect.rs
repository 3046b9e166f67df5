//! The one leaf test: watertight ray/triangle intersection (Woop, Benthin & Wald,
//! "Watertight Ray/Triangle Intersection", JCGT 2013) with a conservative bound on the
//! hit distance's rounding error, and spawn points offset by the hit point's own error
//! bound (Pharr, Jakob & Humphreys, pbrt-v4 §6.8, "Managing Rounding Error").
//!
//! Watertight means a ray through a shared edge or vertex of a closed mesh can never slip
//! between the triangles: edge functions are evaluated on the same operands for both
//! triangles, and a zero edge function is recomputed in double precision.
//!
//! Robust spawning is two bounds that work together (docs/numerics.md "Spawned rays"):
//! a hit point interpolated from barycentrics carries an error bound
//! ([`interpolate_with_error`]); a new ray starts just outside that bound along the normal
//! ([`offset_ray_origin`]); and the leaf test only accepts a hit whose distance exceeds
//! the bound on its own rounding error ([`t_error_bound`]), so a ray never re-hits the
//! surface it leaves, and occlusion farther than those bounds is never lost: both scale
//! with the hit point and the triangles, not with fixed constants.

use glam::Vec3;

/// pbrt's γ(n) = n·u / (1 - n·u) with u = 2^-24 (half an f32 ulp at 1): a bound on the
/// relative error of n rounded operations.
pub const fn gamma(n: u32) -> f32 {
    let nu = n as f32 * (1.0 / 16_777_216.0);
    nu / (1.0 - nu)
}

/// Per-ray constants of the watertight test: the axis permutation and shear that map the
/// ray direction to +Z.
#[derive(Clone, Copy, Debug)]
pub struct WatertightRay {
    pub origin: Vec3,
    pub(crate) kx: usize,
    pub(crate) ky: usize,
    pub(crate) kz: usize,
    pub(crate) sx: f32,
    pub(crate) sy: f32,
    pub(crate) sz: f32,
}

/// A hit on one triangle: distance along the ray and barycentric weights of the three
/// corners (they sum to one).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleHit {
    pub t: f32,
    pub b0: f32,
    pub b1: f32,
    pub b2: f32,
}

impl WatertightRay {
    /// `dir` need not be unit length; hit distances are in units of `dir`.
    pub fn new(origin: Vec3, dir: Vec3) -> WatertightRay {
        // kz: the axis of the largest |dir| (ties to the later axis, as `a.x > a.y ?
        // (a.x > a.z ? x : z) : (a.y > a.z ? y : z)`), looked up from the three
        // comparisons rather than branched on: an incoherent ray's axis is a coin toss
        // that a branch predictor loses.
        const KZ: [u8; 8] = {
            let mut t = [0u8; 8];
            let mut c = 0;
            while c < 8 {
                let (xy, xz, yz) = (c & 1 != 0, c & 2 != 0, c & 4 != 0);
                t[c] = if xy {
                    if xz { 0 } else { 2 }
                } else if yz {
                    1
                } else {
                    2
                };
                c += 1;
            }
            t
        };
        let a = dir.abs();
        let c = usize::from(a.x > a.y) | usize::from(a.x > a.z) << 1 | usize::from(a.y > a.z) << 2;
        let kz = usize::from(KZ[c]);
        let d = dir.to_array();
        let dz = d[kz];
        // The next two axes in cyclic order, swapped when dir[kz] < 0 to keep the
        // triangle's winding.
        let (next, after) = ((kz + 1) % 3, (kz + 2) % 3);
        let (kx, ky) = if dz < 0.0 {
            (after, next)
        } else {
            (next, after)
        };
        let sz = 1.0 / dz;
        WatertightRay {
            origin,
            kx,
            ky,
            kz,
            sx: d[kx] * sz,
            sy: d[ky] * sz,
            sz,
        }
    }

    /// Intersect the triangle (v0, v1, v2); hits with `tmin < t < tmax` and `t` above
    /// its error bound are returned. Both faces are hit (culling is a material decision).
    #[inline]
    pub fn intersect(
        &self,
        v0: Vec3,
        v1: Vec3,
        v2: Vec3,
        tmin: f32,
        tmax: f32,
    ) -> Option<TriangleHit> {
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let a = v0 - self.origin;
        let b = v1 - self.origin;
        let c = v2 - self.origin;
        let ax = a[kx] - self.sx * a[kz];
        let ay = a[ky] - self.sy * a[kz];
        let bx = b[kx] - self.sx * b[kz];
        let by = b[ky] - self.sy * b[kz];
        let cx = c[kx] - self.sx * c[kz];
        let cy = c[ky] - self.sy * c[kz];
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        if u == 0.0 || v == 0.0 || w == 0.0 {
            // Fall back to double precision on the edge so that the sign is exact.
            let (ax, ay, bx, by, cx, cy) = (
                ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64,
            );
            u = (cx * by - cy * bx) as f32;
            v = (ax * cy - ay * cx) as f32;
            w = (bx * ay - by * ax) as f32;
        }
        if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
            return None;
        }
        let z = [self.sz * a[kz], self.sz * b[kz], self.sz * c[kz]];
        finish_hit([u, v, w], z, [ax, bx, cx], [ay, by, cy], tmin, tmax)
    }
}

/// The rest of the watertight test once the ray passes the edge tests: determinant,
/// distance, its error bound and barycentrics. `e` are the edge functions (all of one
/// sign), `z` the corners' scaled depths `sz * (v - o)[kz]`, `x` and `y` their sheared
/// coordinates. The four-lane leaf test (`bvh::leaf4`) repeats these operations in each
/// lane, in this order, so it gives the same bits (tested there).
///
/// Sums are taken in an order fixed by the terms' magnitudes ([`sum3`]), not by the
/// order the corners are stored in: a triangle listed with its corners rotated or
/// reversed gives the same distance to the bit, so two copies of one triangle always
/// tie, and the tie goes to the lower triangle id (docs/numerics.md "Coplanar
/// triangles").
#[inline(always)]
pub(crate) fn finish_hit(
    e: [f32; 3],
    z: [f32; 3],
    x: [f32; 3],
    y: [f32; 3],
    tmin: f32,
    tmax: f32,
) -> Option<TriangleHit> {
    let det = sum3(e);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let tt = sum3([e[0] * z[0], e[1] * z[1], e[2] * z[2]]);
    let inv = 1.0 / det;
    let t = tt * inv;
    if !(t > tmin && t < tmax) {
        return None;
    }
    if t <= t_error_bound(e, z, x, y, inv) {
        return None;
    }
    Some(TriangleHit {
        t,
        b0: e[0] * inv,
        b1: e[1] * inv,
        b2: e[2] * inv,
    })
}

/// pbrt-v4's conservative bound on the rounding error of the watertight test's hit
/// distance (`Triangle::Intersect`, "Ensure that computed triangle t is conservatively
/// greater than zero"), in the ray's units: a computed `t` at or below it may be a
/// surface at or behind the origin, so the hit is refused. It scales with the triangle's
/// extent around the ray (its sheared coordinates), so a ray leaving a surface does not
/// re-hit that surface or its neighbours at any scale or distance from the origin.
#[inline(always)]
pub(crate) fn t_error_bound(e: [f32; 3], z: [f32; 3], x: [f32; 3], y: [f32; 3], inv: f32) -> f32 {
    let max3 = |v: [f32; 3]| v[0].abs().max(v[1].abs()).max(v[2].abs());
    let max_z = max3(z);
    let delta_z = gamma(3) * max_z;
    let (max_x, max_y) = (max3(x), max3(y));
    let delta_x = gamma(5) * (max_x + max_z);
    let delta_y = gamma(5) * (max_y + max_z);
    let delta_e = 2.0 * (gamma(2) * max_x * max_y + delta_y * max_x + delta_x * max_y);
    let max_e = max3(e);
    3.0 * (gamma(3) * max_e * max_z + delta_e * max_z + delta_z * max_e) * inv.abs()
}

/// `a + b + c` summed smallest magnitude first, so that the result depends neither on
/// the order the three terms come in nor on their common sign (negating every term
/// negates the sum exactly, as a triangle with its winding reversed needs).
///
/// Terms of equal magnitude are equal (any order gives the same sum) or opposite: two
/// opposite terms cancel exactly, which the last line makes explicit when they are the
/// two largest (otherwise `(a + b) + c` and `(a + c) + b` could round differently).
#[inline(always)]
pub(crate) fn sum3([a, b, c]: [f32; 3]) -> f32 {
    let (a, b) = if a.abs() <= b.abs() { (a, b) } else { (b, a) };
    let (b, c) = if b.abs() <= c.abs() { (b, c) } else { (c, b) };
    let (a, b) = if a.abs() <= b.abs() { (a, b) } else { (b, a) };
    if b == -c { a } else { (a + b) + c }
}

/// A point interpolated from a triangle's corners with barycentrics `b`, as
/// `c0 * b0 + c1 * b1 + c2 * b2`, and a bound on each coordinate's rounding error
/// (pbrt-v4 §6.8.5: γ(7) times the sum of the terms' magnitudes). The bound is relative
/// to the corners' coordinates, so it grows with the distance from the origin.
#[inline]
pub fn interpolate_with_error(c: [Vec3; 3], b: [f32; 3]) -> (Vec3, Vec3) {
    let p = c[0] * b[0] + c[1] * b[1] + c[2] * b[2];
    let err = ((c[0] * b[0]).abs() + (c[1] * b[1]).abs() + (c[2] * b[2]).abs()) * gamma(7);
    (p, err)
}

/// The origin of a ray leaving the surface point `p`, whose coordinates are within `err`
/// of the true point, to the side of the unit normal `n` (pbrt-v4's `OffsetRayOrigin`):
/// `p` moved along `n` by the largest distance the error box reaches along it, each
/// moved coordinate then rounded one float further away. The true surface is then
/// strictly behind the new origin, and the offset is as small as the point's error allows
/// (a few ulps of the corners' coordinates), so nearby occluders are still found.
#[inline]
pub fn offset_ray_origin(p: Vec3, err: Vec3, n: Vec3) -> Vec3 {
    let d = n.abs().dot(err);
    let offset = n * d;
    let mut out = p + offset;
    for i in 0..3 {
        if offset[i] > 0.0 {
            out[i] = out[i].next_up();
        } else if offset[i] < 0.0 {
            out[i] = out[i].next_down();
        }
    }
    if out.is_finite() { out } else { p }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hits_inside_misses_outside() {
        let r = WatertightRay::new(Vec3::new(0.25, 0.25, 1.0), Vec3::new(0.0, 0.0, -1.0));
        let h = r
            .intersect(Vec3::ZERO, Vec3::X, Vec3::Y, 0.0, f32::INFINITY)
            .expect("hit");
        assert!((h.t - 1.0).abs() < 1e-6);
        assert!((h.b0 + h.b1 + h.b2 - 1.0).abs() < 1e-6);
        assert!((h.b1 - 0.25).abs() < 1e-6 && (h.b2 - 0.25).abs() < 1e-6);
        let r = WatertightRay::new(Vec3::new(0.75, 0.75, 1.0), Vec3::new(0.0, 0.0, -1.0));
        assert!(
            r.intersect(Vec3::ZERO, Vec3::X, Vec3::Y, 0.0, f32::INFINITY)
                .is_none()
        );
        // tmax excludes.
        let r = WatertightRay::new(Vec3::new(0.25, 0.25, 1.0), Vec3::new(0.0, 0.0, -1.0));
        assert!(
            r.intersect(Vec3::ZERO, Vec3::X, Vec3::Y, 0.0, 0.5)
                .is_none()
        );
    }

    #[test]
    fn shared_edge_is_hit_by_both_sides() {
        // Two triangles sharing the diagonal; a ray exactly on the diagonal hits.
        let (a, b, c, d) = (Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y);
        for i in 0..=16 {
            let s = i as f32 / 16.0;
            let r = WatertightRay::new(Vec3::new(s, s, 1.0), Vec3::new(0.0, 0.0, -1.0));
            let h1 = r.intersect(a, b, c, 0.0, f32::INFINITY);
            let h2 = r.intersect(a, c, d, 0.0, f32::INFINITY);
            assert!(h1.is_some() || h2.is_some(), "leak at s={s}");
        }
    }

    #[test]
    fn offset_leaves_the_error_box_at_any_scale() {
        for scale in [1e-6f32, 1e-3, 1.0, 1e5, 1e6] {
            let corners = [
                Vec3::new(scale, -scale, scale * 0.5),
                Vec3::new(-scale, scale * 0.25, scale * 0.5),
                Vec3::new(scale * 0.75, scale, scale * 0.5),
            ];
            let (p, err) = interpolate_with_error(corners, [0.2, 0.3, 0.5]);
            assert!(err.z > 0.0 && err.z <= scale * 1e-6, "scale {scale}: {err}");
            let q = offset_ray_origin(p, err, Vec3::Z);
            assert!(q.z > p.z + err.z, "scale {scale}");
            assert_eq!((q.x, q.y), (p.x, p.y));
            // The offset is a few ulps of the coordinates, not a fixed fraction.
            assert!(q.z - p.z <= scale * 2e-6, "scale {scale}: {}", q.z - p.z);
            let q = offset_ray_origin(p, err, -Vec3::Z);
            assert!(q.z < p.z - err.z, "scale {scale}");
        }
        // A point known exactly (all corners on z = 0) moves by nothing along z: the
        // leaf test's distance bound keeps its ray off the plane instead.
        let (p, err) = interpolate_with_error([Vec3::ZERO, Vec3::X, Vec3::Y], [0.2, 0.3, 0.5]);
        assert_eq!(err.z, 0.0);
        assert_eq!(offset_ray_origin(p, err, Vec3::Z), p);
    }

    /// A ray leaving a triangle from an offset point never re-hits it, at any scale and
    /// distance from the origin, in any direction away from it.
    #[test]
    fn a_ray_leaving_a_triangle_does_not_hit_it_again() {
        let mut n_rays = 0;
        for scale in [1e-6f32, 1e-2, 1.0, 1e3, 1e6] {
            for shift in [0.0f32, 1.0, 1e3, 1e6] {
                let at = |v: Vec3| v * scale + Vec3::new(shift, -shift, 0.5 * shift);
                let tri = [
                    at(Vec3::new(0.0, 0.0, 0.3)),
                    at(Vec3::new(1.0, 0.1, -0.2)),
                    at(Vec3::new(0.2, 1.0, 0.9)),
                ];
                let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]).normalize();
                for i in 1..20 {
                    let b1 = i as f32 / 23.0;
                    let b2 = (i * 7 % 19) as f32 / 40.0;
                    let (p, err) = interpolate_with_error(tri, [1.0 - b1 - b2, b1, b2]);
                    for side in [n, -n] {
                        let o = offset_ray_origin(p, err, side);
                        for j in 0..16 {
                            let a = j as f32 * 0.4;
                            // Directions from grazing (0.01 above the plane) to normal.
                            let tangent = (tri[1] - tri[0]).normalize();
                            let bi = side.cross(tangent);
                            let lift = [0.01, 0.1, 0.5, 1.0][j % 4];
                            let d = (tangent * a.cos() + bi * a.sin() + side * lift).normalize();
                            let r = WatertightRay::new(o, d);
                            let h = r.intersect(tri[0], tri[1], tri[2], 0.0, f32::INFINITY);
                            assert!(h.is_none(), "scale {scale} shift {shift}: {h:?}");
                            n_rays += 1;
                        }
                    }
                }
            }
        }
        assert!(n_rays > 10_000);
    }

    #[test]
    fn sums_do_not_depend_on_order_or_sign() {
        let vals = [
            [1.0f32, 1e-8, -3.0],
            [0.1, 0.2, 0.3],
            [5.0, -5.0, 1e-3],
            [1e-3, 5.0, -5.0],
            [2.0, 2.0, 2.0],
            [7.0, -7.0, 7.0],
            [0.0, -0.0, 1.5],
        ];
        for v in vals {
            let want = sum3(v);
            for p in [
                [0, 1, 2],
                [0, 2, 1],
                [1, 0, 2],
                [1, 2, 0],
                [2, 0, 1],
                [2, 1, 0],
            ] {
                let w = [v[p[0]], v[p[1]], v[p[2]]];
                assert_eq!(sum3(w).to_bits(), want.to_bits(), "{w:?}");
                assert_eq!(sum3(w.map(|x| -x)), -want, "{w:?}");
            }
        }
    }

    /// The same triangle with its corners in any order or winding gives the same
    /// distance to the bit, so two copies always tie (and the tie-break applies).
    #[test]
    fn corner_order_does_not_change_the_distance() {
        let mut hits = 0;
        for i in 0..2000u32 {
            let key = crate::sampling::PathKey {
                seed: 29,
                pixel: i,
                sample: 0,
            };
            let f = |k: u32| key.uniform(0, crate::sampling::Purpose::Film, k);
            let tri = [
                Vec3::new(f(0), f(1), f(2)) * 3.0 + Vec3::splat(1e3),
                Vec3::new(f(3), f(4), f(5)) * 3.0 + Vec3::splat(1e3),
                Vec3::new(f(6), f(7), f(8)) * 3.0 + Vec3::splat(1e3),
            ];
            let o = Vec3::new(f(9), f(10), f(11)) * 3.0 + Vec3::new(1e3, 1e3, 1e3 + 5.0);
            let target = (tri[0] + tri[1] + tri[2]) / 3.0 + (tri[1] - tri[0]) * (f(12) - 0.5) * 0.3;
            let r = WatertightRay::new(o, (target - o).normalize());
            let want = r.intersect(tri[0], tri[1], tri[2], 0.0, f32::INFINITY);
            for p in [
                [0, 1, 2],
                [1, 2, 0],
                [2, 0, 1],
                [0, 2, 1],
                [2, 1, 0],
                [1, 0, 2],
            ] {
                let got = r.intersect(tri[p[0]], tri[p[1]], tri[p[2]], 0.0, f32::INFINITY);
                assert_eq!(
                    want.map(|h| h.t.to_bits()),
                    got.map(|h| h.t.to_bits()),
                    "{tri:?} {p:?}"
                );
            }
            hits += want.is_some() as u32;
        }
        assert!(hits > 500, "{hits}");
    }
}
