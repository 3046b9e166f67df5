//! The leaf test on triangles stored for it: the watertight test of
//! [`crate::intersect::WatertightRay::intersect`], with the same operations in the same
//! order (so the same bits), on a layout that needs no runtime axis indexing of a `Vec3`.
//!
//! Each triangle is stored in BVH leaf order as three rows, one per axis, holding that
//! coordinate of its three corners (`[v0, v1, v2, 0]`). The ray's axis permutation picks
//! three rows, and the three corners are then transformed side by side in one SSE
//! vector: `a = v - o`, `x = a[kx] - sx * a[kz]`, `y = a[ky] - sy * a[kz]`, and the three
//! edge functions `u, v, w` as lane-wise products of rotated vectors. The double-precision
//! recomputation on a zero edge function and the sign test are the reference's
//! expressions; the determinant, the distance, its error bound and the barycentrics are
//! the reference's own function (`intersect::finish_hit`).

use glam::Vec3;

#[cfg(target_arch = "x86_64")]
use crate::intersect::finish_hit;
use crate::intersect::{TriangleHit, WatertightRay};

/// One triangle in accelerator space: `rows[axis] = [v0[axis], v1[axis], v2[axis], 0]`.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(16))]
pub(crate) struct PackedTri {
    pub rows: [[f32; 4]; 3],
}

impl PackedTri {
    pub fn new([a, b, c]: [Vec3; 3]) -> PackedTri {
        PackedTri {
            rows: [
                [a.x, b.x, c.x, 0.0],
                [a.y, b.y, c.y, 0.0],
                [a.z, b.z, c.z, 0.0],
            ],
        }
    }

    #[cfg_attr(target_arch = "x86_64", allow(dead_code))]
    pub fn corners(&self) -> [Vec3; 3] {
        let r = &self.rows;
        [0, 1, 2].map(|i| Vec3::new(r[0][i], r[1][i], r[2][i]))
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

/// `ray.intersect(v0, v1, v2, tmin, tmax)` for the triangle stored in `tri`.
#[inline(always)]
pub(crate) fn intersect(
    ray: &WatertightRay,
    tri: &PackedTri,
    tmin: f32,
    tmax: f32,
) -> Option<TriangleHit> {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: SSE2 is part of x86-64; `kx`, `ky`, `kz` are below 3 by construction.
        unsafe { intersect_sse(ray, tri, tmin, tmax) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let [a, b, c] = tri.corners();
        ray.intersect(a, b, c, tmin, tmax)
    }
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn intersect_sse(
    ray: &WatertightRay,
    tri: &PackedTri,
    tmin: f32,
    tmax: f32,
) -> Option<TriangleHit> {
    use std::arch::x86_64::*;
    unsafe {
        debug_assert!(ray.kx < 3 && ray.ky < 3 && ray.kz < 3);
        let o = ray.origin;
        let row = |k: usize| _mm_load_ps(tri.rows.get_unchecked(k).as_ptr());
        let coord = |k: usize| match k {
            0 => o.x,
            1 => o.y,
            _ => o.z,
        };
        // a = v - origin, corner by corner, for the three permuted axes.
        let px = _mm_sub_ps(row(ray.kx), _mm_set1_ps(coord(ray.kx)));
        let py = _mm_sub_ps(row(ray.ky), _mm_set1_ps(coord(ray.ky)));
        let pz = _mm_sub_ps(row(ray.kz), _mm_set1_ps(coord(ray.kz)));
        // (ax, bx, cx) = a[kx] - sx * a[kz]; likewise y.
        let x = _mm_sub_ps(px, _mm_mul_ps(_mm_set1_ps(ray.sx), pz));
        let y = _mm_sub_ps(py, _mm_mul_ps(_mm_set1_ps(ray.sy), pz));
        // u = cx*by - cy*bx, v = ax*cy - ay*cx, w = bx*ay - by*ax, in lanes 0, 1, 2.
        let x1 = _mm_shuffle_ps::<0b11_01_00_10>(x, x); // (cx, ax, bx)
        let y2 = _mm_shuffle_ps::<0b11_00_10_01>(y, y); // (by, cy, ay)
        let y1 = _mm_shuffle_ps::<0b11_01_00_10>(y, y); // (cy, ay, by)
        let x2 = _mm_shuffle_ps::<0b11_00_10_01>(x, x); // (bx, cx, ax)
        let mut uvw = _mm_sub_ps(_mm_mul_ps(x1, y2), _mm_mul_ps(y1, x2));
        let zero = _mm_setzero_ps();
        if _mm_movemask_ps(_mm_cmpeq_ps(uvw, zero)) & 7 != 0 {
            let mut xs = [0f32; 4];
            let mut ys = [0f32; 4];
            _mm_storeu_ps(xs.as_mut_ptr(), x);
            _mm_storeu_ps(ys.as_mut_ptr(), y);
            let [u, v, w] = edges_f64([xs[0], xs[1], xs[2]], [ys[0], ys[1], ys[2]]);
            uvw = _mm_setr_ps(u, v, w, 0.0);
        }
        let neg = _mm_movemask_ps(_mm_cmplt_ps(uvw, zero)) & 7;
        let pos = _mm_movemask_ps(_mm_cmpgt_ps(uvw, zero)) & 7;
        if neg != 0 && pos != 0 {
            return None;
        }
        let mut e = [0f32; 4];
        _mm_storeu_ps(e.as_mut_ptr(), uvw);
        // The corners' scaled depths sz * a[kz], and their sheared x and y for the
        // distance's error bound; the rest is the reference's own code.
        let mut z = [0f32; 4];
        _mm_storeu_ps(z.as_mut_ptr(), _mm_mul_ps(_mm_set1_ps(ray.sz), pz));
        let mut xs = [0f32; 4];
        let mut ys = [0f32; 4];
        _mm_storeu_ps(xs.as_mut_ptr(), x);
        _mm_storeu_ps(ys.as_mut_ptr(), y);
        finish_hit(
            [e[0], e[1], e[2]],
            [z[0], z[1], z[2]],
            [xs[0], xs[1], xs[2]],
            [ys[0], ys[1], ys[2]],
            tmin,
            tmax,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{PathKey, Purpose, uniform_sphere};

    fn same(a: Option<TriangleHit>, b: Option<TriangleHit>) -> bool {
        match (a, b) {
            (None, None) => true,
            (Some(a), Some(b)) => {
                a.t.to_bits() == b.t.to_bits()
                    && a.b0.to_bits() == b.b0.to_bits()
                    && a.b1.to_bits() == b.b1.to_bits()
                    && a.b2.to_bits() == b.b2.to_bits()
            }
            _ => false,
        }
    }

    /// Random rays against random triangles, and rays through shared vertices and edges
    /// on a grid (where edge functions are exactly zero): the packed test returns the
    /// reference's bits every time.
    #[test]
    fn packed_test_is_the_reference_bit_for_bit() {
        let mut checked = 0;
        let mut hits = 0;
        let mut zeros = 0;
        for i in 0..200_000u32 {
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
            let tri = if i % 4 == 0 {
                // Grid corners: integer coordinates, axis-aligned rays hit edges exactly.
                [0, 1, 2].map(|j| (corner(j) * 2.0).round())
            } else {
                [corner(0), corner(1), corner(2)]
            };
            let o = if i % 4 == 0 {
                (corner(3) * 2.0).round() + Vec3::new(0.0, 0.0, 9.0)
            } else {
                corner(3) * 3.0
            };
            let d = if i % 8 == 0 {
                Vec3::new(0.0, 0.0, -1.0)
            } else {
                uniform_sphere(k.uniform2(2, Purpose::Film, 0))
            };
            let wt = WatertightRay::new(o, d);
            let packed = PackedTri::new(tri);
            for (tmin, tmax) in [(0.0, f32::INFINITY), (0.5, 3.0)] {
                let want = wt.intersect(tri[0], tri[1], tri[2], tmin, tmax);
                let got = intersect(&wt, &packed, tmin, tmax);
                assert!(same(want, got), "{tri:?} {o} {d}: {want:?} vs {got:?}");
                checked += 1;
                hits += want.is_some() as u32;
            }
            let a = tri.map(|v| v - o);
            if (0..3).any(|j| {
                let (p, q) = (a[(j + 1) % 3], a[(j + 2) % 3]);
                p.x * q.y - p.y * q.x == 0.0
            }) {
                zeros += 1;
            }
        }
        assert!(hits > 5_000 && zeros > 100, "{checked} {hits} {zeros}");
    }
}
