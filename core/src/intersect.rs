//! The one leaf test: watertight ray/triangle intersection (Woop, Benthin & Wald,
//! "Watertight Ray/Triangle Intersection", JCGT 2013), and robust spawn-point offsets
//! (Wächter & Binder, "A Fast and Robust Method for Avoiding Self-Intersection",
//! Ray Tracing Gems 2019).
//!
//! Watertight means a ray through a shared edge or vertex of a closed mesh can never slip
//! between the triangles: edge functions are evaluated on the same operands for both
//! triangles, and a zero edge function is recomputed in double precision.

use glam::Vec3;

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
        let a = dir.abs();
        let kz = if a.x > a.y {
            if a.x > a.z { 0 } else { 2 }
        } else if a.y > a.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sz = 1.0 / dir[kz];
        WatertightRay {
            origin,
            kx,
            ky,
            kz,
            sx: dir[kx] * sz,
            sy: dir[ky] * sz,
            sz,
        }
    }

    /// Intersect the triangle (v0, v1, v2); hits with `tmin < t < tmax` are returned.
    /// Both faces are hit (culling is a material decision).
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
        let det = u + v + w;
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let az = self.sz * a[kz];
        let bz = self.sz * b[kz];
        let cz = self.sz * c[kz];
        let tt = u * az + v * bz + w * cz;
        let inv = 1.0 / det;
        let t = tt * inv;
        if !(t > tmin && t < tmax) {
            return None;
        }
        Some(TriangleHit {
            t,
            b0: u * inv,
            b1: v * inv,
            b2: w * inv,
        })
    }
}

/// Move a surface point `p` off the surface along the unit normal `n` (which must point to
/// the side the new ray leaves from), by a few ulps of `p`'s own magnitude: the offset
/// scales with the distance from the origin, so it works at 1e6 as well as at 1.
#[inline]
pub fn offset_ray_origin(p: Vec3, n: Vec3) -> Vec3 {
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 256.0;
    let mut out = p;
    for i in 0..3 {
        let of_i = (INT_SCALE * n[i]) as i32;
        let pi = p[i];
        let moved =
            f32::from_bits(
                (pi.to_bits() as i32).wrapping_add(if pi < 0.0 { -of_i } else { of_i }) as u32,
            );
        out[i] = if pi.abs() < ORIGIN {
            pi + FLOAT_SCALE * n[i]
        } else {
            moved
        };
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
    fn offset_leaves_the_plane_at_any_scale() {
        for scale in [1e-3f32, 1.0, 1e5, 1e6] {
            let p = Vec3::new(scale, -scale, scale * 0.5);
            let n = Vec3::Z;
            let q = offset_ray_origin(p, n);
            assert!(q.z > p.z, "scale {scale}");
            assert!(q.x == p.x);
        }
    }
}
