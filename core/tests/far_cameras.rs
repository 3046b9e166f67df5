//! Split renders with cameras far from the scene give the one-domain image bit for bit
//! (docs/numerics.md "Far cameras"): perspective and orthographic cameras 100 to 100,000
//! times the scene's size away, geometry lying on the scene's bounds and near the split
//! planes, on grid and kd layouts. Far from the scene, rounding in `bound - origin` is
//! larger than any margin relative to the scene; camera rays therefore start at the
//! scene's box, where every configuration computes the same origin.

use dray_core::bvh::Accel;
use dray_core::camera::{Camera, Projection};
use dray_core::domain::{DomainNode, DomainTree};
use dray_core::effects::{Effect, Effects};
use dray_core::film::to_fixed;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Scene;
use dray_core::trace::{DomainSet, Trace};
use glam::Vec3;

mod support;
use support::split;

const SIZE: u32 = 40;

/// A quad (two triangles) with corners `a`, `a + u`, `a + u + v`, `a + v`.
fn quad(pts: &mut Vec<Vec3>, a: Vec3, u: Vec3, v: Vec3) {
    pts.extend([a, a + u, a + u + v, a, a + u + v, a + v]);
}

/// A box of side 1 at `offset`: half of each face covered by a quad lying exactly on the
/// scene's bounds (so the inside shows through), and small random triangles inside,
/// many within rounding distance of the split planes at 0.5 and 0.25.
fn scene(offset: Vec3) -> Scene {
    let mut pts = Vec::new();
    let o = offset;
    let (x, y, z) = (Vec3::X, Vec3::Y, Vec3::Z);
    quad(&mut pts, o, x * 0.5, y);
    quad(&mut pts, o + z, x, y * 0.5);
    quad(&mut pts, o, y * 0.5, z);
    quad(&mut pts, o + x, y, z * 0.5);
    quad(&mut pts, o, z * 0.5, x);
    quad(&mut pts, o + y, z, x * 0.5);
    for i in 0..1500u32 {
        let k = PathKey {
            seed: 11,
            pixel: i,
            sample: 0,
        };
        let mut c = Vec3::new(
            k.uniform(0, Purpose::Film, 0),
            k.uniform(0, Purpose::Film, 1),
            k.uniform(0, Purpose::Film, 2),
        ) * 0.9
            + Vec3::splat(0.05);
        if i % 3 == 0 {
            // Just beside a split plane.
            let a = (i / 3 % 3) as usize;
            c[a] =
                [0.5, 0.25][(i / 9 % 2) as usize] + (k.uniform(1, Purpose::Film, 0) - 0.5) * 1e-4;
        }
        for j in 0..3 {
            pts.push(o + c + uniform_sphere(k.uniform2(2, Purpose::Film, j)) * 0.03);
        }
    }
    let n = pts.len() as u32 / 3;
    let mut s = Scene::default();
    s.mesh.push_vertices(&pts);
    s.mesh.indices = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    // The quads on the bounds are darker than the triangles inside, so both show.
    s.mesh.material = (0..n).map(|i| u32::from(i >= 12)).collect();
    s.materials = vec![
        Material::lambert("bounds", Vec3::splat(0.3)),
        Material::lambert("inside", Vec3::new(0.9, 0.6, 0.2)),
    ];
    s
}

fn layouts(lo: Vec3, hi: Vec3) -> Vec<DomainTree> {
    let mid = (lo + hi) * 0.5;
    let q = lo + (hi - lo) * 0.25;
    vec![
        DomainTree::grid(lo, hi, [2, 2, 2]),
        DomainTree::grid(lo, hi, [3, 1, 4]),
        DomainTree {
            lo,
            hi,
            nodes: vec![
                DomainNode::Split {
                    axis: 0,
                    pos: mid.x,
                    below: 1,
                    above: 2,
                },
                DomainNode::Leaf { domain: 0 },
                DomainNode::Split {
                    axis: 1,
                    pos: q.y,
                    below: 3,
                    above: 4,
                },
                DomainNode::Leaf { domain: 1 },
                DomainNode::Leaf { domain: 2 },
            ],
        },
    ]
}

fn settings() -> RenderSettings {
    RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: 1,
        integrator: IntegratorKind::Raycast,
        max_depth: 1,
        seed: 3,
        environment: Vec3::ONE,
        effects: Effects::NONE.with(Effect::Environment),
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    }
}

/// A camera `dist` scene sizes from the box's centre along `dir`, framing the box.
fn camera(centre: Vec3, dir: Vec3, dist: f32, ortho: bool) -> Camera {
    let eye = centre + dir * dist;
    let mut c = Camera::look_at("far", eye, centre, Vec3::Y, 2.0 * (0.9 / dist).atan());
    if ortho {
        c.projection = Projection::Orthographic {
            xmag: 0.9,
            ymag: 0.9,
        };
    }
    c
}

/// The image, as fixed-point sums, of `scene` through `geometry`.
fn image(scene: &Scene, cam: &Camera, geometry: &dyn Trace) -> Vec<[i64; 3]> {
    let integrator = Integrator::new(scene, cam.clone(), settings());
    let out = render(&integrator, geometry, 1, &|_, _| {}).expect("thread pool");
    (0..SIZE * SIZE).map(|p| out.film.sum_fixed(p)).collect()
}

fn check(offset: Vec3) {
    let scene = scene(offset);
    let (lo, hi) = scene.bounds();
    let pad = (hi - lo)
        .max_element()
        .max(lo.abs().max(hi.abs()).max_element())
        / (1 << 18) as f32;
    let whole = Accel::build(&scene.mesh);
    let sets: Vec<DomainSet> = layouts(lo, hi)
        .into_iter()
        .map(|tree| DomainSet {
            accels: split(&scene.mesh, &tree, pad),
            tree,
            pad,
        })
        .collect();
    let centre = (lo + hi) * 0.5;
    let dirs = [
        Vec3::Z,
        -Vec3::X,
        Vec3::new(0.3, 0.5, 1.0).normalize(),
        Vec3::new(-1.0, -0.7, -0.4).normalize(),
    ];
    // What a pixel that sees only the sky holds (raycast: the environment, 1).
    let background = to_fixed(Vec3::ONE).expect("finite");
    for dist in [1.0e2f32, 1.0e3, 1.0e4, 1.0e5] {
        for (d, &dir) in dirs.iter().enumerate() {
            for ortho in [false, true] {
                let cam = camera(centre, dir, dist, ortho);
                let one = image(&scene, &cam, &whole);
                let bounds_seen = one
                    .iter()
                    .filter(|s| s[2] < background[2] && s[0] < background[0] / 2)
                    .count();
                let inside_seen = one.iter().filter(|s| s[0] > s[2] * 3).count();
                assert!(
                    bounds_seen > 20 && inside_seen > 20,
                    "offset {offset} dist {dist} dir {d} ortho {ortho}: the image shows \
                     the quads on the bounds ({bounds_seen}) and the inside ({inside_seen})"
                );
                for (l, set) in sets.iter().enumerate() {
                    let split = image(&scene, &cam, set);
                    let differ = one.iter().zip(&split).filter(|(a, b)| a != b).count();
                    assert_eq!(
                        differ, 0,
                        "offset {offset} dist {dist} dir {d} ortho {ortho} layout {l}: \
                         {differ} pixels differ from one domain"
                    );
                }
            }
        }
    }
}

#[test]
fn far_cameras_give_the_one_domain_image_on_every_layout() {
    check(Vec3::ZERO);
}

#[test]
fn far_cameras_give_the_one_domain_image_away_from_the_origin() {
    check(Vec3::new(-37.25, 1000.0, 5.5));
}
