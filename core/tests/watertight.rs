//! Watertightness of the BVH + leaf test on a closed mesh: no ray from inside escapes, and
//! rays aimed exactly at shared vertices and edges cross the surface exactly once.

use std::collections::HashMap;

use dray_core::bvh::{Accel, QueryRay};
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Mesh;
use glam::Vec3;

/// A closed icosphere with shared vertices, `level` subdivisions, radius `r`, centre `c`.
fn icosphere(level: u32, r: f32, c: Vec3) -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut get = |a: u32, b: u32, v: &mut Vec<Vec3>| {
            let k = (a.min(b), a.max(b));
            *mid.entry(k).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                v.len() as u32 - 1
            })
        };
        let mut nf = Vec::new();
        for [a, b, cc] in f {
            let ab = get(a, b, &mut v);
            let bc = get(b, cc, &mut v);
            let ca = get(cc, a, &mut v);
            nf.extend([[a, ab, ca], [b, bc, ab], [cc, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    let mut m = Mesh::default();
    m.push_vertices(&v.iter().map(|p| *p * r + c).collect::<Vec<_>>());
    m.material = vec![0; f.len()];
    m.indices = f;
    m
}

fn count_crossings(accel: &Accel, origin: Vec3, dir: Vec3) -> usize {
    let mut n = 0;
    let mut tmin = 0.0;
    while let Some(h) = accel.closest(
        &QueryRay {
            origin,
            dir,
            tmin,
            tmax: f32::INFINITY,
        },
        |_, _| true,
    ) {
        n += 1;
        // Hits on the triangles around one vertex or edge compute t from different planes
        // and may differ in the last bits: they are one crossing.
        tmin = h.t * (1.0 + 1e-5);
        assert!(n < 10, "runaway crossings");
    }
    n
}

#[test]
fn a_million_rays_from_inside_never_escape() {
    for (scale, centre) in [
        (1.0f32, Vec3::ZERO),
        (1e-3, Vec3::splat(0.01)),
        (100.0, Vec3::new(1e5, 0.0, 0.0)),
    ] {
        let mesh = icosphere(4, scale, centre);
        let accel = Accel::build(&mesh);
        let mut misses = 0u32;
        let n = if scale == 1.0 { 1_000_000 } else { 200_000 };
        for i in 0..n {
            let k = PathKey {
                seed: 3,
                pixel: i,
                sample: 0,
            };
            let o = uniform_sphere(k.uniform2(0, Purpose::Film, 0))
                * k.uniform(0, Purpose::Film, 1)
                * 0.9
                * scale
                + centre;
            let d = uniform_sphere(k.uniform2(0, Purpose::Film, 2));
            let q = QueryRay {
                origin: o,
                dir: d,
                tmin: 0.0,
                tmax: f32::INFINITY,
            };
            if accel.closest(&q, |_, _| true).is_none() {
                misses += 1;
            }
        }
        assert_eq!(misses, 0, "rays escaped the closed sphere at scale {scale}");
    }
}

#[test]
fn rays_through_shared_vertices_and_edges_cross_once() {
    let mesh = icosphere(3, 1.0, Vec3::ZERO);
    let accel = Accel::build(&mesh);
    // From the centre, dir = the vertex itself: the ray passes exactly through it at t = 1.
    for v in &mesh.positions {
        assert_eq!(count_crossings(&accel, Vec3::ZERO, *v), 1, "vertex {v}");
    }
    // Through edge midpoints (shared by exactly two triangles) and along axis-aligned rays.
    for tri in &mesh.indices {
        for e in 0..3 {
            let a = mesh.positions[tri[e] as usize];
            let b = mesh.positions[tri[(e + 1) % 3] as usize];
            let m = (a + b) * 0.5;
            assert_eq!(count_crossings(&accel, Vec3::ZERO, m), 1, "edge {a} {b}");
            // From outside, the ray enters and leaves: exactly two crossings.
            assert_eq!(
                count_crossings(&accel, m * 3.0, -m),
                2,
                "edge {a} {b} from outside"
            );
        }
    }
    for d in [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z] {
        assert_eq!(count_crossings(&accel, Vec3::ZERO, d), 1, "axis {d}");
    }
}

#[test]
fn closest_hit_ties_go_to_the_lower_triangle() {
    // Two coincident triangles: the lower index must win whatever the build order.
    let mut m = Mesh::default();
    m.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
    m.indices = vec![[0, 1, 2], [0, 2, 1], [0, 1, 2]];
    m.material = vec![0; 3];
    let accel = Accel::build(&m);
    let q = QueryRay {
        origin: Vec3::new(0.2, 0.2, 1.0),
        dir: -Vec3::Z,
        tmin: 0.0,
        tmax: f32::INFINITY,
    };
    assert_eq!(accel.closest(&q, |_, _| true).map(|h| h.tri), Some(0));
    assert_eq!(accel.closest(&q, |t, _| t != 0).map(|h| h.tri), Some(1));
}
