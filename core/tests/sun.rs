//! The sun (`--sun`) against its analytic answer: a diffuse plane under a sun at
//! elevation EL receives irradiance E sin(EL) and so shows radiance albedo / pi times
//! that; a bar above the plane casts a shadow, black where the whole disk is hidden and
//! graded across a penumbra as wide as the disk's angle makes it.

mod support;

use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::lighting::Lighting;
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::scene::Scene;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun};
use glam::Vec3;
use support::quad;

const ALBEDO: f32 = 0.5;
const ELEVATION: f32 = 40.0;
const IRRADIANCE: f32 = 2.0;
/// The bar: y = BAR_Y, x in [-BAR_HALF, BAR_HALF], all along z.
const BAR_Y: f32 = 1.0;
const BAR_HALF: f32 = 0.25;
const SIZE: u32 = 96;

/// A ground plane y = 0 and a bar above it, both grey Lambert.
fn scene() -> Scene {
    let mut scene = Scene::default();
    let g = 10.0;
    quad(
        &mut scene,
        [
            Vec3::new(-g, 0.0, -g),
            Vec3::new(-g, 0.0, g),
            Vec3::new(g, 0.0, g),
            Vec3::new(g, 0.0, -g),
        ],
        0,
    );
    let (b, y) = (BAR_HALF, BAR_Y);
    quad(
        &mut scene,
        [
            Vec3::new(-b, y, -g),
            Vec3::new(-b, y, g),
            Vec3::new(b, y, g),
            Vec3::new(b, y, -g),
        ],
        0,
    );
    scene
        .materials
        .push(Material::lambert("grey", Vec3::splat(ALBEDO)));
    scene
}

/// Per pixel: where its centre's camera ray meets the ground (x), and its radiance.
fn render_sun(integrator: IntegratorKind, diameter: f32, spp: u32) -> Vec<(f32, Vec3)> {
    let scene = scene();
    // Azimuth 90: the sun stands over +x, so the bar's shadow falls toward -x.
    let sun = Sun::new(90.0, ELEVATION, IRRADIANCE, diameter).expect("sun");
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp,
        integrator,
        max_depth: 1,
        seed: 7,
        environment: Vec3::ZERO,
        effects: Effects::NONE.with(Effect::DirectLight).with(Effect::Sun),
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Lighting {
            sun: Some(sun),
            ..Lighting::default()
        },
        clamp_indirect: None,
        aovs: Default::default(),
    };
    // Straight down from high above, seeing x in about [-3, 3].
    let camera = Camera::look_at(
        "down",
        Vec3::new(0.0, 40.0, 0.0),
        Vec3::ZERO,
        -Vec3::Z,
        2.0 * (3.0f32 / 40.0).atan(),
    );
    let accel = Accel::build(&scene.mesh);
    let it = Integrator::new(&scene, camera, settings);
    let out = render(&it, &accel, 1, &|_, _| {}).expect("render");
    let image = out.film.linear(spp);
    (0..SIZE * SIZE)
        .map(|p| {
            let r = it.camera_ray(p, 0);
            let t = -r.origin.y / r.dir.y;
            (r.origin.x + t * r.dir.x, image[p as usize])
        })
        .collect()
}

/// The shadow of the bar's edges on the ground, for the sun's centre: x in [lo, hi].
fn umbra_centre() -> (f32, f32) {
    let run = BAR_Y / ELEVATION.to_radians().tan();
    (-BAR_HALF - run, BAR_HALF - run)
}

#[test]
fn a_lit_diffuse_plane_shows_albedo_over_pi_times_e_sin_el() {
    let expected = ALBEDO / std::f32::consts::PI * IRRADIANCE * ELEVATION.to_radians().sin();
    let (lo, hi) = umbra_centre();
    for integrator in [IntegratorKind::Path, IntegratorKind::Raycast] {
        let pixels = render_sun(integrator, SUN_DIAMETER_DEG, 16);
        let (mut lit, mut shadow, mut sum) = (0, 0, 0.0f64);
        for &(x, v) in &pixels {
            // Lit ground: away from the bar (seen from above) and from its shadow.
            if x > BAR_HALF + 0.2 || (x < -BAR_HALF - 0.2 && (x > hi + 0.2 || x < lo - 0.2)) {
                lit += 1;
                sum += f64::from(v.x);
                // The noise: cos(theta) to the normal varies over the disk by about
                // 0.27% (one sigma) per sample here, 0.07% at 16 samples.
                for c in v.to_array() {
                    assert!(
                        (c - expected).abs() < 5e-3 * expected,
                        "{integrator:?}: lit ground at x = {x}: {v}, expected {expected}"
                    );
                }
            } else if x > lo + 0.1 && x < hi - 0.1 {
                // The disk is 0.53 degrees: its penumbra here is about 0.02 wide.
                shadow += 1;
                assert_eq!(v, Vec3::ZERO, "{integrator:?}: shadow at x = {x}");
            }
        }
        assert!(
            lit > SIZE as usize * 40 && shadow > SIZE as usize * 3,
            "{lit} {shadow}"
        );
        // Over thousands of pixels the noise averages out to a few parts in 10^5.
        let mean = sum / lit as f64;
        assert!(
            (mean - f64::from(expected)).abs() < 3e-4 * f64::from(expected),
            "{integrator:?}: mean {mean}, expected {expected}"
        );
    }
}

#[test]
fn a_wider_sun_grades_the_shadow_edge_and_a_point_sun_would_not() {
    let expected = ALBEDO / std::f32::consts::PI * IRRADIANCE * ELEVATION.to_radians().sin();
    let (_, hi) = umbra_centre();
    let partial = |diameter: f32| {
        render_sun(IntegratorKind::Path, diameter, 16)
            .iter()
            .filter(|(x, v)| (x - hi).abs() < 0.4 && v.x > 0.1 * expected && v.x < 0.9 * expected)
            .count()
    };
    // A 10-degree disk seen from the ground beside the shadow's edge spreads the edge
    // over 1.56 / sin(40) * tan(10) = 0.43 units: several columns of pixels in between.
    let wide = partial(10.0);
    // The real sun's edge is about 0.02 wide, narrower than a pixel (0.06).
    let real = partial(SUN_DIAMETER_DEG);
    assert!(
        wide > 4 * SIZE as usize,
        "wide sun: {wide} pixels in the penumbra"
    );
    assert!(
        real < 2 * SIZE as usize,
        "real sun: {real} pixels in the penumbra"
    );
}
