//! An environment map lights a scene as the constant environment of the same radiance
//! does: the map is importance-sampled and MIS-weighted against BSDF sampling, the
//! constant environment is found by bounces alone, and the two estimators agree within
//! their noise.

use std::sync::Arc;

use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::env_map::EnvMap;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::lighting::Lighting;
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::scene::Scene;
use glam::Vec3;

const SKY: f32 = 0.7;
const SIZE: u32 = 32;
const SPP: u32 = 64;

/// A ground quad and a box-like wall on it, grey Lambert, seen from above at an angle.
fn scene() -> Scene {
    let mut scene = Scene::default();
    let mut quad = |c: [Vec3; 4]| {
        let base = scene.mesh.push_vertices(&c);
        scene.mesh.indices.push([base, base + 1, base + 2]);
        scene.mesh.indices.push([base, base + 2, base + 3]);
        scene.mesh.material.extend([0, 0]);
    };
    quad([
        Vec3::new(-3.0, 0.0, -3.0),
        Vec3::new(-3.0, 0.0, 3.0),
        Vec3::new(3.0, 0.0, 3.0),
        Vec3::new(3.0, 0.0, -3.0),
    ]);
    quad([
        Vec3::new(-1.0, 0.0, 0.0),
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(1.0, 1.5, 0.0),
        Vec3::new(-1.0, 1.5, 0.0),
    ]);
    scene
        .materials
        .push(Material::lambert("grey", Vec3::splat(0.6)));
    scene
}

fn image(environment: Vec3, effects: Effects, lighting: Lighting) -> Vec<Vec3> {
    let scene = scene();
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: SPP,
        integrator: IntegratorKind::Path,
        max_depth: 3,
        seed: 3,
        environment,
        effects,
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting,
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let camera = Camera::look_at("c", Vec3::new(3.0, 4.0, 5.0), Vec3::ZERO, Vec3::Y, 0.9);
    let accel = Accel::build(&scene.mesh);
    let it = Integrator::new(&scene, camera, settings);
    render(&it, &accel, 1, &|_, _| {})
        .expect("render")
        .film
        .linear(SPP)
}

#[test]
fn a_constant_map_lights_the_scene_as_the_constant_environment_does() {
    let constant = image(
        Vec3::splat(SKY),
        Effects::NONE.with(Effect::Environment),
        Lighting::default(),
    );
    // 16 x 8 pixels of the same radiance, turned: its samples follow sin(theta).
    let map = EnvMap::new(16, 8, vec![Vec3::splat(SKY); 128], 33.0, 1.0).expect("map");
    let mapped = image(
        Vec3::ZERO,
        Effects::NONE.with(Effect::DirectLight).with(Effect::EnvMap),
        Lighting {
            env_map: Some(Arc::new(map)),
            ..Lighting::default()
        },
    );
    // Pixels that see the sky see the same radiance; the image means agree to well
    // within the noise of 64 samples over 1024 pixels, and so do 8 x 8 blocks.
    let mean = |im: &[Vec3]| im.iter().map(|v| f64::from(v.x)).sum::<f64>() / im.len() as f64;
    let (a, b) = (mean(&constant), mean(&mapped));
    assert!((a - b).abs() < 0.01 * a, "means: constant {a}, map {b}");
    let mut sky = 0;
    for (p, (c, m)) in constant.iter().zip(&mapped).enumerate() {
        if *c == Vec3::splat(SKY) {
            sky += 1;
            assert_eq!(*m, Vec3::splat(SKY), "pixel {p} sees the sky");
        }
    }
    assert!(sky > 0, "no pixel sees the sky");
    for by in 0..SIZE / 8 {
        for bx in 0..SIZE / 8 {
            let block = |im: &[Vec3]| {
                (0..64)
                    .map(|k| {
                        let (x, y) = (bx * 8 + k % 8, by * 8 + k / 8);
                        f64::from(im[(y * SIZE + x) as usize].x)
                    })
                    .sum::<f64>()
                    / 64.0
            };
            let (a, b) = (block(&constant), block(&mapped));
            assert!(
                (a - b).abs() < 0.04 * a.max(0.05),
                "block {bx},{by}: {a} vs {b}"
            );
        }
    }
    // And the map is the effect: without it, only what the camera sees directly of the
    // sky remains (nothing here: the environment is black).
    let off = image(
        Vec3::ZERO,
        Effects::NONE.with(Effect::DirectLight),
        Lighting {
            env_map: Some(Arc::new(
                EnvMap::new(1, 1, vec![Vec3::splat(SKY)], 0.0, 1.0).expect("map"),
            )),
            ..Lighting::default()
        },
    );
    assert!(off.iter().all(|v| *v == Vec3::ZERO));
}
