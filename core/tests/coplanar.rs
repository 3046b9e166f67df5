//! Which of two coplanar triangles a ray sees (docs/numerics.md "Coplanar triangles"):
//! the hit with the smaller computed distance, and on equal distances the lower
//! triangle id. A triangle's distance does not depend on the order its corners are
//! stored in, so copies of one triangle (any corner order, either winding) always tie
//! and the lower id always wins; triangles that overlap in one plane with different
//! corners compute distances that differ in the last bits, so which one shows varies
//! from ray to ray, but identically on every configuration.

use dray_core::bvh::{Accel, QueryRay};
use dray_core::domain::DomainTree;
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Mesh;
use dray_core::trace::{DomainSet, Trace};
use glam::Vec3;

mod support;
use support::{mesh, split};

fn key(i: u32) -> PathKey {
    PathKey {
        seed: 23,
        pixel: i,
        sample: 0,
    }
}

/// The closest hit's triangle and distance bits, through `geometry`.
fn closest(geometry: &dyn Trace, o: Vec3, d: Vec3) -> Option<(u32, u32)> {
    let ray = QueryRay {
        origin: o,
        dir: d,
        tmin: 0.0,
        tmax: f32::INFINITY,
    };
    geometry
        .closest(&ray, &mut |_, _| true)
        .map(|h| (h.tri, h.t.to_bits()))
}

/// Split layouts over the mesh's bounds, with one BVH per domain.
fn layouts(m: &Mesh) -> Vec<DomainSet> {
    let (lo, hi) = m.bounds();
    let pad = (hi - lo)
        .max_element()
        .max(lo.abs().max(hi.abs()).max_element())
        / (1 << 18) as f32;
    [[2, 2, 2], [3, 1, 2]]
        .into_iter()
        .map(|dims| {
            let tree = DomainTree::grid(lo, hi, dims);
            DomainSet {
                accels: split(m, &tree, pad),
                tree,
                pad,
            }
        })
        .collect()
}

/// Copies of triangles, listed with their corners in every order and both windings,
/// interleaved with other triangles so copies get scattered ids: every ray that hits a
/// copy sees the lowest id among them, with one BVH and with split layouts, at the
/// origin and far from it.
#[test]
fn copies_of_a_triangle_always_resolve_to_the_lowest_id() {
    for shift in [Vec3::ZERO, Vec3::new(1e5, -3e4, 2e5)] {
        let mut tris = Vec::new();
        let mut lowest = Vec::new();
        let mut copies: Vec<Vec<u32>> = Vec::new();
        let orders = [
            [0, 1, 2],
            [1, 2, 0],
            [2, 0, 1],
            [0, 2, 1],
            [2, 1, 0],
            [1, 0, 2],
        ];
        for i in 0..40u32 {
            let k = key(i);
            let c = Vec3::new(
                k.uniform(0, Purpose::Film, 0),
                k.uniform(0, Purpose::Film, 1),
                k.uniform(0, Purpose::Film, 2),
            ) * 8.0;
            let t = [0, 1, 2].map(|j| c + uniform_sphere(k.uniform2(1, Purpose::Film, j)) + shift);
            lowest.push(tris.len() as u32);
            copies.push(Vec::new());
            for (n, o) in orders.iter().enumerate() {
                copies[i as usize].push(tris.len() as u32);
                tris.push([t[o[0]], t[o[1]], t[o[2]]]);
                if n % 2 == 0 {
                    // Something else between the copies, so ids are not consecutive.
                    tris.push(t.map(|v| v + Vec3::new(0.0, 0.0, 20.0)));
                }
            }
        }
        let m = mesh(&tris);
        let whole = Accel::build(&m);
        let sets = layouts(&m);
        let mut hits = 0;
        for i in 0..20_000u32 {
            let k = key(1000 + i);
            let group = (i % 40) as usize;
            let [a, b, c] = tris[lowest[group] as usize];
            // Inside, on an edge, or on a corner of the triangle.
            let target = match i % 4 {
                0 => a,
                1 => a + (b - a) * k.uniform(2, Purpose::Film, 0),
                _ => {
                    let (u, v) = (
                        k.uniform(2, Purpose::Film, 1),
                        k.uniform(2, Purpose::Film, 2),
                    );
                    let (u, v) = if u + v > 1.0 {
                        (1.0 - u, 1.0 - v)
                    } else {
                        (u, v)
                    };
                    a + (b - a) * u + (c - a) * v
                }
            };
            let o = target + uniform_sphere(k.uniform2(3, Purpose::Film, 0)) * 30.0;
            let d = (target - o).normalize();
            let got = closest(&whole, o, d);
            if let Some((tri, _)) = got
                && copies[group].contains(&tri)
            {
                assert_eq!(
                    tri, lowest[group],
                    "shift {shift} ray {i}: a higher copy won"
                );
                hits += 1;
            }
            for (l, set) in sets.iter().enumerate() {
                assert_eq!(closest(set, o, d), got, "shift {shift} ray {i} layout {l}");
            }
        }
        assert!(hits > 10_000, "{hits}");
    }
}

/// Coplanar triangles with different corners (a quad split along one diagonal over the
/// same quad split along the other, and a smaller triangle inside): each ray sees the
/// smaller computed distance, which is the same triangle with one BVH and with every
/// split layout; distances equal to the bit go to the lower id.
#[test]
fn overlapping_coplanar_triangles_resolve_the_same_everywhere() {
    for shift in [Vec3::ZERO, Vec3::new(-2e4, 7e3, 1e5)] {
        let (p, q, r, s) = (
            Vec3::new(0.0, 0.0, 0.0) + shift,
            Vec3::new(4.0, 0.3, 0.5) + shift,
            Vec3::new(4.5, 4.0, 1.0) + shift,
            Vec3::new(0.2, 4.2, 0.5) + shift,
        );
        // Make the quad planar: s on the plane of p, q, r.
        let n = (q - p).cross(r - p);
        let s = s - n * (n.dot(s - p) / n.length_squared());
        let inner = [p * 0.6 + r * 0.4, p * 0.3 + q * 0.7, r * 0.5 + s * 0.5];
        let tris = vec![[p, q, r], [p, r, s], [q, r, s], [q, s, p], inner];
        let m = mesh(&tris);
        let whole = Accel::build(&m);
        let sets = layouts(&m);
        let singles: Vec<Accel> = tris.iter().map(|t| Accel::build(&mesh(&[*t]))).collect();
        let mut seen = [0u32; 5];
        for i in 0..20_000u32 {
            let k = key(50_000 + i);
            let (u, v) = (
                k.uniform(0, Purpose::Film, 0),
                k.uniform(0, Purpose::Film, 1),
            );
            let target = p + (q - p) * u + (s - p) * v;
            let o = target + uniform_sphere(k.uniform2(1, Purpose::Film, 0)) * 10.0;
            let d = (target - o).normalize();
            let got = closest(&whole, o, d);
            if let Some((tri, bits)) = got {
                seen[tri as usize] += 1;
                // No other triangle hits at a smaller distance, nor a lower id at the same.
                for (other, one) in singles.iter().enumerate() {
                    if let Some((_, b)) = closest(one, o, d) {
                        let (t0, t1) = (f32::from_bits(b), f32::from_bits(bits));
                        assert!(
                            t0 > t1 || (t0 == t1 && other as u32 >= tri),
                            "shift {shift} ray {i}: {other} at {t0} beats {tri} at {t1}"
                        );
                    }
                }
            }
            for (l, set) in sets.iter().enumerate() {
                assert_eq!(closest(set, o, d), got, "shift {shift} ray {i} layout {l}");
            }
        }
        assert!(seen.iter().filter(|&&n| n > 0).count() >= 3, "{seen:?}");
    }
}
