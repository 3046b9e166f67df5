//! The BVH on degenerate and extreme geometry: coincident triangles, triangles nested
//! about one centre, coordinates near the f32 range and non-finite corners. Each must
//! build in a bounded depth without a panic, and still find the right hits.

use dray_core::bvh::{Accel, QueryRay};
use glam::Vec3;

mod support;
use support::mesh;

fn down(x: f32, y: f32, z: f32) -> QueryRay {
    QueryRay {
        origin: Vec3::new(x, y, z),
        dir: Vec3::NEG_Z,
        tmin: 0.0,
        tmax: f32::INFINITY,
    }
}

#[test]
fn coincident_triangles_build_and_tie_to_the_lowest_index() {
    // Every triangle the same: obvhs's PLOC builder made this a chain as deep as the
    // triangle count (quadratic time, then a stack overflow in the CWBVH conversion).
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let m = mesh(&vec![t; 50_000]);
    let accel = Accel::build(&m);
    assert_eq!(accel.triangle_count(), 50_000);
    let hit = accel.closest(&down(0.25, 0.25, 1.0), |_, _| true).unwrap();
    assert_eq!(hit.tri, 0);
    assert!((hit.t - 1.0).abs() < 1e-6);
    // A filter that refuses the lowest ids still finds the next one.
    let hit = accel
        .closest(&down(0.25, 0.25, 1.0), |id, _| id >= 7)
        .unwrap();
    assert_eq!(hit.tri, 7);
    assert!(accel.occluded(&down(0.25, 0.25, 1.0), |_, _| true));
    assert!(accel.closest(&down(2.0, 2.0, 1.0), |_, _| true).is_none());
}

#[test]
fn nested_triangles_about_one_centre_build_and_hit_the_nearest() {
    // Growing copies of one triangle around one centroid, each a little lower: distinct
    // boxes that contain each other, the other input that makes a greedy build a chain.
    let tris: Vec<[Vec3; 3]> = (1..=30_000)
        .map(|i| {
            let s = i as f32 * 0.001;
            let z = -(i as f32) * 1e-4;
            [
                Vec3::new(-s, -s, z),
                Vec3::new(2.0 * s, -s, z),
                Vec3::new(-s, 2.0 * s, z),
            ]
        })
        .collect();
    let accel = Accel::build(&mesh(&tris));
    let hit = accel.closest(&down(0.0, 0.0, 1.0), |_, _| true).unwrap();
    assert_eq!(hit.tri, 0, "the top triangle is nearest");
    // Outside the smallest triangles, the first one large enough is hit.
    let hit = accel.closest(&down(0.5, 0.0, 1.0), |_, _| true).unwrap();
    let [a, b, c] = tris[hit.tri as usize];
    assert!(a.x <= 0.5 && b.x > 0.5 && c.x < 0.5, "{hit:?}");
    assert!(hit.tri > 0 && (hit.tri as usize) < tris.len());
}

#[test]
fn coordinates_near_the_float_range_do_not_panic() {
    // The extent (6e38) overflows f32; it used to make the padding infinite and every
    // box non-finite, and obvhs's conversion then panicked ordering children.
    let tris = [
        [Vec3::ZERO, Vec3::X, Vec3::Y],
        [
            Vec3::new(-3e38, -3e38, -5.0),
            Vec3::new(3e38, -3e38, -5.0),
            Vec3::new(0.0, 3e38, -5.0),
        ],
        [
            Vec3::new(3.4e38, 3.4e38, 3.4e38),
            Vec3::new(1e38, 3.4e38, 3.4e38),
            Vec3::new(3.4e38, 1e38, -3.4e38),
        ],
    ];
    let accel = Accel::build(&mesh(&tris));
    assert_eq!(accel.triangle_count(), 3);
    // Nothing panics, and a ray at the scale of the scene finds the giant triangle
    // (features far below that scale are not resolved).
    let _ = accel.closest(&down(5.0, 5.0, 1.0), |_, _| true);
    let far = accel.closest(&down(5.0, 5.0, 1e38), |_, _| true);
    assert_eq!(far.map(|h| h.tri), Some(1), "{far:?}");
}

#[test]
fn scenes_moved_far_beyond_the_import_bound_do_not_panic() {
    // A box of 40 triangles moved to 1e22 or 1e25 on an axis, or to 3e38: the
    // coordinates collapse to a few f32 values, the padded boxes' half-areas overflow
    // f32, and the conversion used to index a decision slot that does not exist
    // (`dray render cornell --translate 1e25,0,0` panicked this way).
    for offset in [
        Vec3::new(1e25, 0.0, 0.0),
        Vec3::new(0.0, 1e22, 0.0),
        Vec3::new(0.0, 0.0, 1e22),
        Vec3::new(3e38, 0.0, 0.0),
    ] {
        let tris: Vec<[Vec3; 3]> = (0..40)
            .map(|i| {
                let o = Vec3::new((i % 4) as f32, (i / 4) as f32, (i % 3) as f32) * 100.0;
                [o, o + Vec3::X * 50.0, o + Vec3::Y * 50.0].map(|p| p + offset)
            })
            .collect();
        let accel = Accel::build(&mesh(&tris));
        assert_eq!(accel.triangle_count(), 40, "{offset}");
        let _ = accel.closest(&down(offset.x, offset.y, offset.z + 1e3), |_, _| true);
    }
}

#[test]
fn non_finite_corners_are_left_out() {
    let tris = [
        [Vec3::ZERO, Vec3::X, Vec3::Y],
        [Vec3::new(f32::NAN, 0.0, 0.0), Vec3::X, Vec3::Y],
        [
            Vec3::new(f32::INFINITY, 0.0, 0.5),
            Vec3::new(0.0, f32::NEG_INFINITY, 0.5),
            Vec3::Y,
        ],
        [
            Vec3::new(0.0, 0.0, 0.5),
            Vec3::new(1.0, 0.0, 0.5),
            Vec3::new(0.0, 1.0, 0.5),
        ],
    ];
    let accel = Accel::build(&mesh(&tris));
    assert_eq!(accel.triangle_count(), 2);
    let hit = accel.closest(&down(0.25, 0.25, 1.0), |_, _| true).unwrap();
    assert_eq!(hit.tri, 3, "mesh indices survive the filtering");
    let hit = accel.closest(&down(0.25, 0.25, 0.25), |_, _| true).unwrap();
    assert_eq!(hit.tri, 0);
    // Nothing but non-finite triangles: an empty accelerator, not a panic.
    let accel = Accel::build(&mesh(&tris[1..3]));
    assert_eq!(accel.triangle_count(), 0);
    assert!(accel.closest(&down(0.25, 0.25, 1.0), |_, _| true).is_none());
}
