//! A ray walked through spatial domains, each with its own BVH over the triangles touching
//! its (slightly expanded) box, finds exactly the hit one BVH over the whole scene finds:
//! the same distance, bit for bit, and the same triangle.

use dray_core::bvh::{Accel, QueryRay};
use dray_core::domain::{DomainNode, DomainTree};
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Mesh;
use dray_core::trace::{DomainSet, Trace};
use glam::Vec3;

mod support;
use support::split;

fn key(i: u32) -> PathKey {
    PathKey {
        seed: 5,
        pixel: i,
        sample: 0,
    }
}

/// Random triangles of mixed sizes in [0, 10]^3, some axis-aligned and on grid planes.
fn scene() -> Mesh {
    let mut pts = Vec::new();
    for i in 0..6000u32 {
        let k = key(i);
        let c = Vec3::new(
            k.uniform(0, Purpose::Film, 0),
            k.uniform(0, Purpose::Film, 1),
            k.uniform(0, Purpose::Film, 2),
        ) * 10.0;
        let size = if i % 50 == 0 { 4.0 } else { 0.4 };
        for j in 0..3 {
            pts.push(c + uniform_sphere(k.uniform2(1, Purpose::Film, j)) * size);
        }
    }
    // Triangles lying exactly in the walls of a 2x2x2 grid over [0,10].
    for (a, b, c) in [
        (
            Vec3::new(5.0, 1.0, 1.0),
            Vec3::new(5.0, 9.0, 1.0),
            Vec3::new(5.0, 1.0, 9.0),
        ),
        (
            Vec3::new(1.0, 5.0, 1.0),
            Vec3::new(9.0, 5.0, 1.0),
            Vec3::new(1.0, 5.0, 9.0),
        ),
    ] {
        pts.extend([a, b, c]);
    }
    let n = pts.len() as u32 / 3;
    let mut m = Mesh::default();
    m.push_vertices(&pts);
    m.indices = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    m.material = vec![0; n as usize];
    m
}

fn check(tree: &DomainTree, mesh: &Mesh) {
    let (lo, hi) = mesh.bounds();
    let pad = (hi - lo).max_element() * (1.0 / (1 << 18) as f32);
    let whole = Accel::build(mesh);
    let set = DomainSet {
        tree: tree.clone(),
        accels: split(mesh, tree, pad),
        pad,
    };
    let dirs = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
    let mut hits = 0;
    for i in 0..100_000u32 {
        let k = key(i + 10_000_000);
        let inside = Vec3::new(
            k.uniform(2, Purpose::Film, 0),
            k.uniform(2, Purpose::Film, 1),
            k.uniform(2, Purpose::Film, 2),
        ) * 10.0;
        let (origin, dir) = match i % 4 {
            0 => (inside, uniform_sphere(k.uniform2(3, Purpose::Film, 0))),
            // From outside the bounds.
            1 => (
                inside + uniform_sphere(k.uniform2(4, Purpose::Film, 0)) * 30.0,
                (inside - Vec3::splat(5.0)).normalize(),
            ),
            // Axis-aligned, along grid walls and from points on them.
            2 => (
                Vec3::new(5.0, inside.y, inside.z),
                dirs[(i / 4) as usize % 6],
            ),
            _ => (
                Vec3::new(inside.x.round(), 5.0, inside.z),
                dirs[(i / 4) as usize % 6],
            ),
        };
        let q = QueryRay {
            origin,
            dir,
            tmin: 0.0,
            tmax: f32::INFINITY,
        };
        let a = whole.closest(&q, |_, _| true);
        let b = set.closest(&q, &mut |_, _| true);
        assert_eq!(
            a.map(|h| (h.t.to_bits(), h.tri)),
            b.map(|h| (h.t.to_bits(), h.tri)),
            "ray {i}: {origin} {dir}"
        );
        // Shadow rays of random length agree too.
        let short = QueryRay {
            tmax: k.uniform(5, Purpose::Film, 0) * 12.0,
            ..q
        };
        assert_eq!(
            whole.occluded(&short, |_, _| true),
            set.occluded(&short, &mut |_, _| true),
            "shadow ray {i}"
        );
        hits += a.is_some() as u32;
    }
    assert!(
        hits > 20_000,
        "too few hits ({hits}) for the test to mean much"
    );
}

#[test]
fn grid_domains_find_the_single_bvh_hit() {
    let mesh = scene();
    let (lo, hi) = mesh.bounds();
    for dims in [[2, 2, 2], [3, 1, 4], [5, 5, 5]] {
        check(&DomainTree::grid(lo, hi, dims), &mesh);
    }
}

#[test]
fn kd_domains_find_the_single_bvh_hit() {
    let mesh = scene();
    let (lo, hi) = mesh.bounds();
    // An unbalanced hand-made tree with a plane exactly where wall triangles lie.
    let nodes = vec![
        DomainNode::Split {
            axis: 0,
            pos: 5.0,
            below: 1,
            above: 2,
        },
        DomainNode::Leaf { domain: 0 },
        DomainNode::Split {
            axis: 1,
            pos: 5.0,
            below: 3,
            above: 4,
        },
        DomainNode::Leaf { domain: 1 },
        DomainNode::Split {
            axis: 2,
            pos: 2.5,
            below: 5,
            above: 6,
        },
        DomainNode::Leaf { domain: 2 },
        DomainNode::Leaf { domain: 3 },
    ];
    let tree = DomainTree { lo, hi, nodes };
    assert_eq!(tree.domain_count(), 4);
    assert_eq!(tree.locate(Vec3::new(1.0, 1.0, 1.0)), Some(0));
    assert_eq!(tree.locate(Vec3::new(6.0, 6.0, 6.0)), Some(3));
    check(&tree, &mesh);
}

#[test]
fn grid_numbering_and_locate() {
    let t = DomainTree::grid(Vec3::ZERO, Vec3::splat(3.0), [3, 3, 3]);
    assert_eq!(t.domain_count(), 27);
    assert_eq!(t.locate(Vec3::new(0.5, 0.5, 0.5)), Some(0));
    assert_eq!(t.locate(Vec3::new(2.5, 0.5, 0.5)), Some(2));
    assert_eq!(t.locate(Vec3::new(0.5, 1.5, 0.5)), Some(3));
    assert_eq!(t.locate(Vec3::new(0.5, 0.5, 2.5)), Some(18));
    assert_eq!(t.locate(Vec3::splat(4.0)), None);
    for (d, (lo, hi)) in t.domain_bounds().iter().enumerate() {
        assert_eq!(t.locate((*lo + *hi) * 0.5), Some(d as u32));
    }
}
