//! Environment maps read from files (`dray_core::env_map_file`) light a scene as the
//! analytic answer says: a map of radiance `L` over the upper hemisphere and black
//! below gives an upward-facing Lambert plane of albedo `rho` the radiance `rho * L`
//! (irradiance `pi * L`, times `rho / pi`), whether the map is read from a Radiance
//! `.hdr` or an OpenEXR `.exr`, turned about +Y or not, and scaled by its intensity.
//! The maps are written here, by the same crates a user's tools would use.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::env_map_file::read_env_map;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::lighting::Lighting;
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::scene::Scene;
use glam::Vec3;

const SIZE: u32 = 24;
const SPP: u32 = 64;
const ALBEDO: f32 = 0.5;
/// A power of two, so RGBE stores it exactly.
const SKY: f32 = 2.0;
const W: usize = 32;
const H: usize = 16;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dray-envfile-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

/// Radiance of map pixel (x, y): `SKY` in the upper half (the rows above the horizon:
/// row y covers polar angles [y, y + 1) * pi / H), black below.
fn sky(_x: usize, y: usize) -> [f32; 3] {
    if y < H / 2 { [SKY; 3] } else { [0.0; 3] }
}

fn write_hdr(path: &Path) {
    let px: Vec<image::Rgb<f32>> = (0..W * H).map(|i| image::Rgb(sky(i % W, i / W))).collect();
    let out = std::io::BufWriter::new(std::fs::File::create(path).expect("create hdr"));
    image::codecs::hdr::HdrEncoder::new(out)
        .encode(&px, W, H)
        .expect("write hdr");
}

fn write_exr(path: &Path) {
    exr::prelude::write_rgb_file(path, W, H, |x, y| {
        let [r, g, b] = sky(x, y);
        (r, g, b)
    })
    .expect("write exr");
}

/// A large upward-facing plane, seen from straight above: every pixel sees the plane.
fn image(lighting: Lighting) -> Vec<Vec3> {
    let mut scene = Scene::default();
    let base = scene.mesh.push_vertices(&[
        Vec3::new(-50.0, 0.0, -50.0),
        Vec3::new(-50.0, 0.0, 50.0),
        Vec3::new(50.0, 0.0, 50.0),
        Vec3::new(50.0, 0.0, -50.0),
    ]);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.indices.push([base, base + 2, base + 3]);
    scene.mesh.material.extend([0, 0]);
    scene
        .materials
        .push(Material::lambert("grey", Vec3::splat(ALBEDO)));
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: SPP,
        integrator: IntegratorKind::Path,
        max_depth: 3,
        seed: 9,
        environment: Vec3::ZERO,
        effects: Effects::NONE.with(Effect::DirectLight).with(Effect::EnvMap),
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting,
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let camera = Camera::look_at(
        "down",
        Vec3::new(0.0, 5.0, 0.0),
        Vec3::ZERO,
        Vec3::new(0.0, 0.0, -1.0),
        0.5,
    );
    let accel = Accel::build(&scene.mesh);
    let it = Integrator::new(&scene, camera, settings);
    render(&it, &accel, 1, &|_, _| {})
        .expect("render")
        .film
        .linear(SPP)
}

fn mean(im: &[Vec3]) -> Vec3 {
    im.iter().copied().sum::<Vec3>() / im.len() as f32
}

#[test]
fn a_bright_upper_hemisphere_lights_an_upward_plane_as_the_analytic_answer() {
    let hdr = tmp("upper.hdr");
    let exr = tmp("upper.exr");
    write_hdr(&hdr);
    write_exr(&exr);
    for (path, rotation, intensity) in [(&hdr, 0.0, 1.0), (&exr, 70.0, 1.0), (&exr, 0.0, 3.0)] {
        let map = read_env_map(path, rotation, intensity).expect("read map");
        let im = image(Lighting {
            env_map: Some(Arc::new(map)),
            ..Lighting::default()
        });
        let want = ALBEDO * SKY * intensity;
        let m = mean(&im);
        // A plane under a uniform hemisphere: the light sample and the BSDF sample each
        // see the sky or not exactly as the cosine says; the noise left is that of
        // MIS between two good estimators, far below 2% over 576 pixels x 64 samples.
        for c in [m.x, m.y, m.z] {
            assert!(
                (c - want).abs() < 0.02 * want,
                "{} rotation {rotation} intensity {intensity}: mean {m}, want {want}",
                path.display()
            );
        }
        // Every pixel, within the noise of 64 samples.
        for (i, p) in im.iter().enumerate() {
            assert!(
                (p.x - want).abs() < 0.25 * want,
                "{}: pixel {i} is {p}, want {want}",
                path.display()
            );
        }
    }
    // Without the map the plane is black: it is the only light.
    let dark = image(Lighting::default());
    assert_eq!(mean(&dark), Vec3::ZERO);
    let _ = std::fs::remove_file(hdr);
    let _ = std::fs::remove_file(exr);
}
