//! Occlusion close to a surface is found at every scale and distance from the origin
//! (docs/numerics.md "Spawned rays"): rays leave a hit point from just outside the
//! point's own rounding-error bound, and the leaf test refuses only distances within
//! their own error bound, so a gap between two plates of 2^-17 of the coordinates'
//! magnitude (or 2^-15 of the plates' size, where that is larger: the bound on a hit
//! distance grows with the triangle hit) reads as closed from scale 1e-6 to 1e6 and
//! translation 0 to 1e6, for rays up to 60 degrees off the normal, and a plate alone
//! never shadows itself. The fixed offsets these bounds replace (256 ulps of each
//! coordinate, or 2^-16 below 1/32) were 2 to 4 times the first gap far from the origin,
//! and 10^5 times the gap at scale 1e-6.
//!
//! Each case is checked against the same f32 geometry moved to the origin: the corners
//! lie on a grid fine enough to hold both exactly, so the two scenes differ only in
//! where they are, and every ray's answer must agree.

use dray_core::bvh::{Accel, Hit, QueryRay};
use dray_core::camera::Camera;
use dray_core::effects::Effects;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::intersect::offset_ray_origin;
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::scene::Scene;
use dray_core::surface::Surface;
use glam::{DVec3, Vec3};

const SCALES: [f64; 5] = [1e-6, 1e-3, 1.0, 1e3, 1e6];
const SHIFTS: [f64; 6] = [0.0, 1.0, 1e2, 1e4, 1e5, 1e6];

/// One configuration: the plates' size, the gap between them, the grid their corners
/// are rounded to, and where the scene sits.
struct Case {
    half: f64,
    gap: f64,
    grid: f64,
    shift: DVec3,
}

impl Case {
    /// Plates of half-size `scale` (at least 2^-11 of the magnitude) `shift_len` from
    /// the origin along `dir`, with a gap of 2^-17 of the coordinates' magnitude or
    /// 2^-15 of the plates' half-size, whichever is larger (both rounded up to a power
    /// of two).
    fn new(scale: f64, shift_len: f64, dir: DVec3) -> Case {
        let magnitude = shift_len + scale;
        let e = magnitude.log2().floor();
        // Corners and shift are multiples of 2^(e - 20): below the f32 spacing at twice
        // the magnitude, so every sum and difference below is exact in f32.
        let grid = (e - 20.0).exp2();
        let half = scale.max((e - 11.0).exp2());
        let gap = (e - 17.0).exp2().max((half.log2().ceil() - 15.0).exp2());
        let snap = |v: DVec3| (v / grid).round() * grid;
        Case {
            half,
            gap,
            grid,
            shift: snap(dir * shift_len),
        }
    }

    fn snap(&self, v: DVec3) -> DVec3 {
        (v / self.grid).round() * self.grid
    }

    /// A corner given in plate coordinates (rotated by `frame`), in the scene at its
    /// place and at the origin: the same f32 point but for the shift.
    fn corner(&self, frame: &[DVec3; 3], local: DVec3) -> (Vec3, Vec3) {
        let l = self.snap(frame[0] * local.x + frame[1] * local.y + frame[2] * local.z);
        let at = (l + self.shift).as_vec3();
        let home = l.as_vec3();
        // Exact: both sums are on the grid and within f32's 24 bits of it.
        assert_eq!(at.as_dvec3(), l + self.shift, "corner off the grid");
        assert_eq!(home.as_dvec3(), l, "corner off the grid");
        (at, home)
    }
}

/// An axis-aligned frame, or one tilted so no plate is parallel to an axis.
fn frames() -> [[DVec3; 3]; 2] {
    let z = DVec3::new(0.3, -0.5, 0.81).normalize();
    let x = DVec3::new(1.0, 0.2, 0.0).cross(z).normalize();
    [[DVec3::X, DVec3::Y, DVec3::Z], [x, z.cross(x), z]]
}

/// Two square plates (two triangles each) at heights 0 and `gap`, in the scene at its
/// place and at the origin; `with_ceiling: false` keeps only the floor.
fn plates(case: &Case, frame: &[DVec3; 3], with_ceiling: bool) -> (Scene, Scene) {
    let h = case.half;
    let mut at = Vec::new();
    let mut home = Vec::new();
    let heights: &[f64] = if with_ceiling {
        &[0.0, case.gap]
    } else {
        &[0.0]
    };
    for &z in heights {
        let quad = [(-h, -h), (h, -h), (h, h), (-h, -h), (h, h), (-h, h)];
        for (x, y) in quad {
            let (a, b) = case.corner(frame, DVec3::new(x, y, z));
            at.push(a);
            home.push(b);
        }
    }
    (triangles(&at), triangles(&home))
}

fn triangles(pts: &[Vec3]) -> Scene {
    let n = pts.len() as u32 / 3;
    let mut s = Scene::default();
    s.mesh.push_vertices(pts);
    s.mesh.indices = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    s.mesh.material = vec![0; n as usize];
    s.materials = vec![Material::lambert("grey", Vec3::splat(0.5))];
    s
}

/// Whether rays spawned from triangle `tri` at barycentrics `b`, leaving toward the side
/// the ray `incoming` came from, are blocked, in each of `dirs` (given in the frame of
/// the surface's normal: x and y along the plate, z along the normal).
fn spawned_answers(
    scene: &Scene,
    accel: &Accel,
    tri: u32,
    b: [f32; 3],
    incoming: Vec3,
    dirs: &[Vec3],
) -> Vec<bool> {
    let hit = Hit {
        t: 1.0,
        tri,
        b0: b[0],
        b1: b[1],
        b2: b[2],
    };
    let surf = Surface::new(scene, &hit, incoming, Effects::NONE);
    let origin = offset_ray_origin(surf.p, surf.p_err, surf.ng);
    let [a, c, _] = scene.mesh.corners(tri as usize);
    let tx = (c - a).normalize();
    let ty = surf.ng.cross(tx);
    dirs.iter()
        .map(|d| {
            let dir = (tx * d.x + ty * d.y + surf.ng * d.z).normalize();
            accel.occluded(
                &QueryRay {
                    origin,
                    dir,
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                },
                |_, _| true,
            )
        })
        .collect()
}

/// Directions up to 60 degrees from the normal (they all reach the other plate), and
/// grazing ones (0.6 degrees above the plate) for the self-shadowing check.
fn directions() -> (Vec<Vec3>, Vec<Vec3>) {
    let mut steep = vec![Vec3::Z];
    let mut grazing = Vec::new();
    for k in 0..8 {
        let a = k as f32 * std::f32::consts::FRAC_PI_4 + 0.1;
        for tan in [0.3f32, 1.0, 1.7] {
            steep.push(Vec3::new(a.cos() * tan, a.sin() * tan, 1.0));
        }
        grazing.push(Vec3::new(a.cos(), a.sin(), 0.01));
    }
    (steep, grazing)
}

const BARYCENTRICS: [[f32; 3]; 5] = [
    [0.2, 0.3, 0.5],
    [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0],
    [0.6, 0.25, 0.15],
    [0.1, 0.45, 0.45],
    [0.45, 0.1, 0.45],
];

#[test]
fn a_narrow_gap_is_closed_at_every_scale_and_translation() {
    let (steep, grazing) = directions();
    let shift_dirs = [
        DVec3::new(1.0, -1.0, 0.0).normalize(),
        DVec3::new(0.6, 0.7, -0.8).normalize(),
    ];
    let mut cases = 0;
    for scale in SCALES {
        for shift in SHIFTS {
            for dir in shift_dirs {
                for (f, frame) in frames().iter().enumerate() {
                    let case = Case::new(scale, shift, dir);
                    let what = format!("scale {scale} shift {shift} along {dir} frame {f}");
                    let (both, both_home) = plates(&case, frame, true);
                    let (floor, floor_home) = plates(&case, frame, false);
                    let [accel, accel_home] = [&both, &both_home].map(|s| Accel::build(&s.mesh));
                    let [floor_accel, floor_accel_home] =
                        [&floor, &floor_home].map(|s| Accel::build(&s.mesh));
                    let up = frame[2].as_vec3();
                    for tri in 0..2u32 {
                        for b in BARYCENTRICS {
                            // From the floor, up: the ceiling blocks every steep ray.
                            let a = spawned_answers(&both, &accel, tri, b, -up, &steep);
                            let h = spawned_answers(&both_home, &accel_home, tri, b, -up, &steep);
                            assert!(a.iter().all(|&o| o), "{what}: floor {tri} {b:?} {a:?}");
                            assert_eq!(a, h, "{what}: floor {tri} {b:?} against the origin");
                            // From the ceiling, down: the floor blocks them.
                            let a = spawned_answers(&both, &accel, tri + 2, b, up, &steep);
                            let h =
                                spawned_answers(&both_home, &accel_home, tri + 2, b, up, &steep);
                            assert!(a.iter().all(|&o| o), "{what}: ceiling {tri} {b:?} {a:?}");
                            assert_eq!(a, h, "{what}: ceiling {tri} {b:?} against the origin");
                            // A plate alone never blocks a ray leaving it, even grazing, on
                            // either side.
                            for side in [up, -up] {
                                let all = [steep.as_slice(), grazing.as_slice()].concat();
                                let a = spawned_answers(&floor, &floor_accel, tri, b, -side, &all);
                                let h = spawned_answers(
                                    &floor_home,
                                    &floor_accel_home,
                                    tri,
                                    b,
                                    -side,
                                    &all,
                                );
                                assert!(
                                    a.iter().all(|&o| !o),
                                    "{what}: floor {tri} {b:?} shadows itself: {a:?}"
                                );
                                assert_eq!(a, h, "{what}: floor alone against the origin");
                            }
                        }
                    }
                    cases += 1;
                }
            }
        }
    }
    assert_eq!(cases, 120);
}

/// A floor, a block standing on it (contact shadows along its base) and a plate
/// hovering 2^-17 of the magnitude above the floor, lit by ambient occlusion, seen from
/// above at an angle: the scene's triangles (corners in plate coordinates) and the eye.
fn contact_scene(case: &Case) -> (Scene, Scene, [Vec3; 2], [Vec3; 2]) {
    let h = case.half;
    let g = case.gap;
    let frame = [DVec3::X, DVec3::Y, DVec3::Z];
    let mut pts = Vec::new();
    let mut quad = |a: DVec3, u: DVec3, v: DVec3| {
        for p in [a, a + u, a + u + v, a, a + u + v, a + v] {
            pts.push(p);
        }
    };
    let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
    // Floor.
    quad(
        DVec3::new(-4.0 * h, -4.0 * h, 0.0),
        x * 8.0 * h,
        y * 8.0 * h,
    );
    // Block of side 2h standing on the floor: four sides and the top.
    let c = DVec3::new(-2.5 * h, -h, 0.0);
    let s = 2.0 * h;
    quad(c, x * s, z * s);
    quad(c + y * s, z * s, x * s);
    quad(c, z * s, y * s);
    quad(c + x * s, y * s, z * s);
    quad(c + z * s, x * s, y * s);
    // Hovering plate.
    quad(DVec3::new(0.5 * h, -1.5 * h, g), x * 3.0 * h, y * 3.0 * h);
    let (at, home): (Vec<Vec3>, Vec<Vec3>) =
        pts.into_iter().map(|p| case.corner(&frame, p)).unzip();
    let eye = case.corner(&frame, DVec3::new(0.0, -7.0 * h, 6.0 * h));
    let target = case.corner(&frame, DVec3::ZERO);
    (
        triangles(&at),
        triangles(&home),
        [eye.0, target.0],
        [eye.1, target.1],
    )
}

const SIZE: u32 = 32;

/// The ambient-occlusion image (fraction of unblocked rays, as fixed-point sums).
fn ao_image(scene: &Scene, eye: [Vec3; 2]) -> Vec<i64> {
    let cam = Camera::look_at("gap", eye[0], eye[1], Vec3::Z, 0.9);
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: 2,
        integrator: IntegratorKind::Ao,
        max_depth: 1,
        seed: 7,
        environment: Vec3::ZERO,
        effects: Effects::NONE,
        ao_samples: 8,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let integrator = Integrator::new(scene, cam, settings);
    let accel = Accel::build(&scene.mesh);
    let out = render(&integrator, &accel, 1, &|_, _| {}).expect("thread pool");
    (0..SIZE * SIZE).map(|p| out.film.sum_fixed(p)[0]).collect()
}

/// Ambient occlusion of the contact scene: at power-of-two scales from 2^-20 to 2^20
/// (the same geometry scaled exactly) the image is the same to the bit; translated up to
/// 1e6 it matches the same f32 geometry at the origin but for pixels whose camera ray
/// lands on another triangle (the camera's own rounding far away), and the shadow under
/// the hovering plate is there in every image.
#[test]
fn contact_shadows_render_the_same_at_every_scale_and_translation() {
    // Scales: exact powers of two, so the scenes are one scene, scaled.
    let unit = Case::new(1.0, 0.0, DVec3::X);
    let (base, _, eye, _) = contact_scene(&unit);
    let want = ao_image(&base, eye);
    // A pixel fully in the open sees every AO ray through: its sum is the largest.
    let open = *want.iter().max().expect("pixels");
    let dark = want.iter().filter(|&&v| v < open / 4).count();
    assert!(dark > 40, "the plate's shadow shows: {dark} dark pixels");
    for k in [-20i32, -10, 10, 20] {
        let s = 2f64.powi(k);
        let case = Case {
            half: unit.half * s,
            gap: unit.gap * s,
            grid: unit.grid * s,
            shift: DVec3::ZERO,
        };
        let (scene, _, eye, _) = contact_scene(&case);
        let got = ao_image(&scene, eye);
        let differ = want.iter().zip(&got).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "scale 2^{k}: {differ} pixels differ from scale 1"
        );
    }
    // Translations: against the same f32 scene at the origin.
    for shift in SHIFTS {
        for scale in [1e-3, 1.0, 1e3] {
            let case = Case::new(scale, shift, DVec3::new(0.6, 0.7, -0.8).normalize());
            let (at, home, eye_at, eye_home) = contact_scene(&case);
            let a = ao_image(&at, eye_at);
            let h = ao_image(&home, eye_home);
            let open = *h.iter().max().expect("pixels");
            let dark = |img: &[i64]| img.iter().filter(|&&v| v < open / 4).count();
            assert!(
                dark(&h) > 40,
                "scale {scale} shift {shift}: shadow at the origin"
            );
            // Pixels whose value differs by more than one AO ray in eight.
            let far_off = a
                .iter()
                .zip(&h)
                .filter(|(x, y)| (**x - **y).abs() > open / 8)
                .count();
            assert!(
                far_off <= (SIZE * SIZE / 50) as usize,
                "scale {scale} shift {shift}: {far_off} pixels differ from the origin; \
                 dark pixels {} there, {} here",
                dark(&h),
                dark(&a)
            );
            assert!(
                dark(&a).abs_diff(dark(&h)) <= 8,
                "scale {scale} shift {shift}: {} dark pixels, {} at the origin",
                dark(&a),
                dark(&h)
            );
        }
    }
}
