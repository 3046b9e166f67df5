//! Exact triangle/box overlap: the separating-axis test of Akenine-Möller (2001).
//!
//! Assigning a triangle to every domain its bounding box touches would duplicate long
//! diagonal triangles into domains they only pass near; the separating-axis test keeps
//! only the domains the triangle itself touches. The test runs in f64 on f32 inputs:
//! every coordinate difference and edge product is then (nearly) exact, so the answer is
//! the true geometric one to within ~1e-16 relative, which the overlap epsilon (about
//! 4e-6 of the scene scale, applied by growing the box) dwarfs. The test is therefore
//! conservative: a triangle within epsilon of a box counts as overlapping it.

use glam::{DVec3, Vec3};

use super::layout::Aabb;

/// True when triangle `tri` and the closed box `b` share a point. Touching counts.
/// Degenerate triangles (zero area) are handled: they overlap when their segment or point
/// does.
pub fn triangle_overlaps_box(tri: &[Vec3; 3], b: &Aabb) -> bool {
    let lo = b.min.as_dvec3();
    let hi = b.max.as_dvec3();
    let c = (lo + hi) * 0.5;
    let h = (hi - lo) * 0.5;
    let v = tri.map(|p| p.as_dvec3() - c);

    // The box's face normals: the triangle's bounds against the box.
    for a in 0..3 {
        let min = v[0][a].min(v[1][a]).min(v[2][a]);
        let max = v[0][a].max(v[1][a]).max(v[2][a]);
        if min > h[a] || max < -h[a] {
            return false;
        }
    }

    let e = [v[1] - v[0], v[2] - v[1], v[0] - v[2]];

    // The nine cross products of triangle edges with box axes.
    let units = [DVec3::X, DVec3::Y, DVec3::Z];
    for edge in &e {
        for u in &units {
            let axis = u.cross(*edge);
            if separates(&v, axis, h) {
                return false;
            }
        }
    }

    // The triangle's plane.
    let n = e[0].cross(e[1]);
    !separates(&v, n, h)
}

/// True when `axis` separates the triangle `v` from the box of half-size `h` at the origin.
#[inline]
fn separates(v: &[DVec3; 3], axis: DVec3, h: DVec3) -> bool {
    let p = [axis.dot(v[0]), axis.dot(v[1]), axis.dot(v[2])];
    let r = h.dot(axis.abs());
    let min = p[0].min(p[1]).min(p[2]);
    let max = p[0].max(p[1]).max(p[2]);
    min > r || max < -r
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference: clip the triangle polygon by the six box planes (Sutherland-Hodgman,
    /// in f64); they overlap when anything is left.
    fn clip_overlaps(tri: &[Vec3; 3], b: &Aabb) -> bool {
        let mut poly: Vec<DVec3> = tri.iter().map(|p| p.as_dvec3()).collect();
        for a in 0..3 {
            for (sign, bound) in [(1.0, b.max[a] as f64), (-1.0, b.min[a] as f64)] {
                // Keep points with sign * (p[a] - bound) <= 0.
                let inside = |p: &DVec3| sign * (p[a] - bound) <= 0.0;
                let mut out = Vec::new();
                for i in 0..poly.len() {
                    let (p, q) = (poly[i], poly[(i + 1) % poly.len()]);
                    match (inside(&p), inside(&q)) {
                        (true, true) => out.push(q),
                        (true, false) | (false, true) => {
                            let t = (bound - p[a]) / (q[a] - p[a]);
                            let mut x = p + (q - p) * t;
                            x[a] = bound;
                            out.push(x);
                            if !inside(&p) {
                                out.push(q);
                            }
                        }
                        (false, false) => {}
                    }
                }
                poly = out;
                if poly.is_empty() {
                    return false;
                }
            }
        }
        true
    }

    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        fn v(&mut self) -> Vec3 {
            Vec3::new(self.f(), self.f(), self.f())
        }
    }

    #[test]
    fn agrees_with_clipping() {
        let mut rng = Rng(7);
        let (mut yes, mut no) = (0, 0);
        for _ in 0..20_000 {
            let c = rng.v() * 1.2 - 0.1;
            let s = 0.02 + rng.f() * 0.6;
            let tri = [
                c + (rng.v() - 0.5) * s,
                c + (rng.v() - 0.5) * s,
                c + (rng.v() - 0.5) * s,
            ];
            let b = Aabb::new(Vec3::splat(0.25), Vec3::new(0.75, 0.6, 0.9));
            let sat = triangle_overlaps_box(&tri, &b);
            // Away from the boundary the two must agree exactly; within 1e-5 of it the
            // SAT may only err on the side of overlap.
            if clip_overlaps(&tri, &b.expanded(-1e-5)) {
                assert!(sat, "{tri:?} misses a box it overlaps");
            }
            if !clip_overlaps(&tri, &b.expanded(1e-5)) {
                assert!(!sat, "{tri:?} overlaps a box it misses");
            }
            if sat { yes += 1 } else { no += 1 }
        }
        assert!(yes > 1000 && no > 1000, "{yes} {no}");
    }

    #[test]
    fn diagonal_triangle_skips_the_corner_its_bounds_touch() {
        // A big triangle cutting diagonally past a small box at the corner of its bounds.
        let tri = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 2.0, 0.0),
        ];
        let corner = Aabb::new(Vec3::new(1.5, 1.5, -0.1), Vec3::new(2.0, 2.0, 0.1));
        assert!(corner.overlaps(&Aabb::of_triangle(&tri)));
        assert!(!triangle_overlaps_box(&tri, &corner));
        // Touching counts: a box whose face contains the triangle's edge.
        let touching = Aabb::new(Vec3::new(0.5, -1.0, -0.1), Vec3::new(1.0, 0.0, 0.1));
        assert!(triangle_overlaps_box(&tri, &touching));
        // A point-like triangle and a flat box.
        let p = Vec3::new(0.5, 0.5, 0.0);
        let flat = Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0));
        assert!(triangle_overlaps_box(&[p, p, p], &flat));
    }
}
