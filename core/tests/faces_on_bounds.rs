//! A closed cube whose faces are the scene's bounds, seen from every side: every camera
//! ray that passes through the cube hits the face it enters by, at the distance the
//! slab test gives (issue 38: the Khronos sample `BoxVertexColors` showed curved holes
//! along the edges of its near faces).
//!
//! Camera rays start just outside the scene's box (`camera::advance_to_box`, so that a
//! far camera's rays can be clipped to domains exactly). They used to start about 2^-17
//! of the scene away from it, and a face lying on the box was then hit below the
//! watertight test's error bound on the distance, which refuses such hits as possibly
//! behind the origin: the ray went through the face. Single-sided faces (glTF's
//! default) let such a ray out again through the far side's back face, so it is a miss.

use dray_core::bvh::Accel;
use dray_core::camera::{Camera, Projection};
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::material::Material;
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Scene;
use glam::{Mat4, Vec3};

const SIZE: u32 = 48;

/// A cube `[lo, hi]` of 12 triangles wound counter-clockwise seen from outside, with a
/// single-sided material, as a glTF exporter writes it.
fn cube(lo: Vec3, hi: Vec3) -> Scene {
    let c = |i: u32| {
        Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    };
    // Faces as corner quads, counter-clockwise from outside.
    let faces = [
        [0, 4, 6, 2], // -x
        [1, 3, 7, 5], // +x
        [0, 1, 5, 4], // -y
        [2, 6, 7, 3], // +y
        [0, 2, 3, 1], // -z
        [4, 5, 7, 6], // +z
    ];
    let mut pts = Vec::new();
    for [a, b, cc, d] in faces {
        pts.extend([c(a), c(b), c(cc), c(a), c(cc), c(d)]);
    }
    let mut s = Scene::default();
    s.mesh.push_vertices(&pts);
    s.mesh.indices = (0..12).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    s.mesh.material = vec![0; 12];
    let mut m = Material::lambert("cube", Vec3::splat(0.8));
    m.double_sided = false;
    s.materials = vec![m];
    s
}

/// Where the line `o + t d` enters the box `[lo, hi]` (t > 0), if it passes through it.
fn entry(o: Vec3, d: Vec3, lo: Vec3, hi: Vec3) -> Option<f64> {
    let (mut t0, mut t1) = (0f64, f64::INFINITY);
    for a in 0..3 {
        let (o, d) = (f64::from(o[a]), f64::from(d[a]));
        let (l, h) = (f64::from(lo[a]), f64::from(hi[a]));
        if d == 0.0 {
            if o <= l || o >= h {
                return None;
            }
            continue;
        }
        let (ta, tb) = ((l - o) / d, (h - o) / d);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 < t1).then_some(t0)
}

/// The camera directions: the 26 axis, edge and corner directions and 40 random ones.
fn directions() -> Vec<Vec3> {
    let mut dirs = Vec::new();
    for x in -1..=1 {
        for y in -1..=1 {
            for z in -1..=1 {
                if (x, y, z) != (0, 0, 0) {
                    dirs.push(Vec3::new(x as f32, y as f32, z as f32).normalize());
                }
            }
        }
    }
    for i in 0..40 {
        let k = PathKey {
            seed: 38,
            pixel: i,
            sample: 0,
        };
        dirs.push(uniform_sphere(k.uniform2(0, Purpose::Film, 0)));
    }
    dirs
}

/// A camera on `dir` from the cube's centre, `dist` half-diagonals away, looking at it;
/// perspective or orthographic, with an up vector that is never parallel to `dir`.
fn camera(lo: Vec3, hi: Vec3, dir: Vec3, dist: f32, ortho: bool) -> Camera {
    let centre = (lo + hi) * 0.5;
    let radius = (hi - lo).length() * 0.5;
    let up = if dir.cross(Vec3::Y).length() > 0.1 {
        Vec3::Y
    } else {
        Vec3::X
    };
    let mut cam = Camera::look_at("c", centre + dir * radius * dist, centre, up, 0.9);
    if ortho {
        cam.projection = Projection::Orthographic {
            xmag: radius * 1.2,
            ymag: radius * 1.2,
        };
    }
    cam
}

/// For each cube, camera direction and projection (and the framing camera `dray render`
/// gives a file without one, which showed the holes): every pixel whose ray passes
/// through the cube (away from its edges by a thousandth of its side, where the hit
/// could honestly go to either face) hits a front face where the ray enters.
fn check(lo: Vec3, hi: Vec3, dists: &[f32]) {
    let scene = cube(lo, hi);
    let accel = Accel::build(&scene.mesh);
    let side = (hi - lo).max_element();
    let inner = (lo + Vec3::splat(side * 1e-3), hi - Vec3::splat(side * 1e-3));
    let mut misses = Vec::new();
    let mut checked = 0usize;
    let mut cameras = vec![("framing".to_string(), Camera::framing(lo, hi, 1.0))];
    for dir in directions() {
        for &dist in dists {
            for ortho in [false, true] {
                let what = format!("dir {dir} dist {dist} ortho {ortho}");
                cameras.push((what, camera(lo, hi, dir, dist, ortho)));
            }
        }
    }
    for (what, cam) in cameras {
        let settings = RenderSettings {
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
        };
        let integ = Integrator::new(&scene, cam, settings);
        for y in 0..SIZE {
            for x in 0..SIZE {
                let ray = integ.camera_ray_xy(x, y, 0);
                let Some(t_in) = entry(ray.origin, ray.dir, inner.0, inner.1) else {
                    continue;
                };
                checked += 1;
                let hit = integ.intersect(&accel, &ray);
                let ok = hit.is_some_and(|h| {
                    let [a, b, c] = scene.mesh.corners(h.tri as usize);
                    let front = (b - a).cross(c - a).dot(ray.dir) < 0.0;
                    // The outer face is at most a thousandth of the side nearer.
                    front && f64::from(h.t) <= t_in + f64::from(side) * 1e-5
                });
                if !ok && misses.len() < 8 {
                    misses.push(format!("{what} pixel ({x}, {y}): {hit:?}"));
                }
            }
        }
    }
    assert!(
        checked > 10_000,
        "too few rays went through the cube: {checked}"
    );
    assert!(
        misses.is_empty(),
        "cube [{lo}, {hi}]: rays through the cube missed its near face:\n{}",
        misses.join("\n")
    );
}

#[test]
fn a_unit_cube_on_the_bounds_has_no_holes_from_any_side() {
    check(Vec3::splat(-0.5), Vec3::splat(0.5), &[1.5, 3.0, 30.0]);
}

#[test]
fn a_cube_far_from_the_origin_has_no_holes_from_any_side() {
    let o = Vec3::new(1.0e4, -3.0e3, 2.5e4);
    check(
        o - Vec3::splat(0.5),
        o + Vec3::splat(0.5),
        &[1.5, 30.0, 1.0e4],
    );
}

#[test]
fn a_flat_box_has_no_holes_from_any_side() {
    check(
        Vec3::new(-4.0, -0.05, -2.0),
        Vec3::new(4.0, 0.05, 2.0),
        &[1.2, 5.0],
    );
}

/// The transform `look_at` builds is a rotation: a guard on the test's own camera.
#[test]
fn the_test_cameras_are_rigid() {
    for dir in directions() {
        let cam = camera(Vec3::ZERO, Vec3::ONE, dir, 3.0, false);
        let m: Mat4 = cam.transform;
        assert!(
            (m.determinant() - 1.0).abs() < 1e-4,
            "{dir}: {}",
            m.determinant()
        );
    }
}
