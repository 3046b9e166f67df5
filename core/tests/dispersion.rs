//! `KHR_materials_dispersion`: a path through a dispersive glass follows one colour
//! channel, refracted with that channel's index, and carries the path's whole weight
//! in it (core/src/dispersion.rs).

use dray_core::bvh::Hit;
use dray_core::camera::Camera;
use dray_core::dispersion::channel_ior;
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{Integrator, IntegratorKind, RayKind, RayState, RenderSettings, Sink};
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::Vec3;

#[derive(Default)]
struct Record {
    contributions: Vec<Vec3>,
    spawned: Vec<RayState>,
}

impl Sink for Record {
    fn contribute(&mut self, _pixel: u32, value: Vec3) {
        self.contributions.push(value);
    }

    fn spawn(&mut self, ray: RayState) {
        self.spawned.push(ray);
    }
}

/// One smooth glass triangle (ior 1.5) in the z = 0 plane, front face +z.
fn scene(dispersion: Option<f32>) -> Scene {
    let mut scene = Scene::default();
    let base = scene.mesh.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.material.push(0);
    let mut glass = Material::glass("glass", 1.5);
    if let Some(d) = dispersion {
        glass.dispersion = d;
    }
    scene.materials.push(glass);
    scene
}

const INCIDENCE_DEG: f32 = 50.0;

/// The rays spawned when `samples` camera paths of weight `weight` meet the glass at
/// 50 degrees from the normal.
fn bounces(scene: &Scene, effects: Effects, samples: u32, weight: Vec3) -> Vec<RayState> {
    let settings = RenderSettings {
        width: 1,
        height: 1,
        spp: samples,
        integrator: IntegratorKind::Path,
        max_depth: 8,
        seed: 3,
        environment: Vec3::ZERO,
        effects,
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let t = INCIDENCE_DEG.to_radians();
    let dir = Vec3::new(t.sin(), 0.0, -t.cos());
    let hit_p = Vec3::new(0.2, 0.2, 0.0);
    let origin = hit_p - dir * 2.0;
    let camera = Camera::look_at("c", origin, hit_p, Vec3::Y, 1.0);
    let integrator = Integrator::new(scene, camera, settings);
    let hit = Hit {
        t: 2.0,
        tri: 0,
        b0: 0.6,
        b1: 0.2,
        b2: 0.2,
    };
    let mut sink = Record::default();
    for sample in 0..samples {
        let ray = RayState {
            origin,
            dir,
            tmax: f32::INFINITY,
            pixel: 0,
            sample,
            depth: 1,
            kind: RayKind::Camera,
            weight,
            bsdf_pdf: 0.0,
        };
        integrator.shade_hit(&ray, &hit, &mut sink);
    }
    assert!(sink.contributions.is_empty());
    sink.spawned
}

fn effects() -> Effects {
    Effects::NONE
        .with(Effect::Specular)
        .with(Effect::Transmission)
        .with(Effect::Dispersion)
}

/// White furnace: smooth white glass reflects or transmits everything, so the spawned
/// weights average to the incoming weight in every channel, no more.
#[test]
fn dispersive_glass_conserves_energy() {
    let n = 30_000;
    for weight in [Vec3::ONE, Vec3::new(0.2, 0.7, 0.4)] {
        let rays = bounces(&scene(Some(1.0)), effects(), n, weight);
        assert_eq!(rays.len(), n as usize);
        let mut mean = Vec3::ZERO;
        for r in &rays {
            assert!(r.weight.is_finite() && r.dir.is_finite());
            // Each path now carries one channel.
            assert_eq!(r.weight.to_array().iter().filter(|&&c| c > 0.0).count(), 1);
            mean += r.weight / n as f32;
        }
        assert!(
            (mean - weight).abs().max_element() < 0.03 * weight.max_element(),
            "{weight}: {mean}"
        );
    }
}

/// Dispersion 0, or the effect switched off, is the glass without the extension, to the
/// bit.
#[test]
fn no_dispersion_keeps_the_bits() {
    let plain = bounces(&scene(None), effects(), 500, Vec3::ONE);
    assert_eq!(bounces(&scene(Some(0.0)), effects(), 500, Vec3::ONE), plain);
    let mut off = effects();
    off.set(Effect::Dispersion, false);
    assert_eq!(bounces(&scene(Some(1.0)), off, 500, Vec3::ONE), plain);
    // Without dispersion every refracted path keeps its three channels.
    assert!(plain.iter().all(|r| r.weight.min_element() > 0.0));
}

/// Red, green and blue refract by their own indices: blue bends most.
#[test]
fn channels_refract_differently() {
    let rays = bounces(&scene(Some(1.0)), effects(), 3_000, Vec3::ONE);
    let sin_i = INCIDENCE_DEG.to_radians().sin();
    let mut sin_t = [None; 3];
    for r in rays.iter().filter(|r| r.dir.z < 0.0) {
        let c = (0..3).find(|&c| r.weight[c] > 0.0).unwrap();
        let s = (1.0 - r.dir.z * r.dir.z).sqrt();
        // Snell's law with the channel's index.
        let n = channel_ior(1.5, 1.0, c);
        assert!(
            (sin_i - n * s).abs() < 1e-4,
            "channel {c}: {sin_i} vs {n} x {s}"
        );
        sin_t[c] = Some(s);
    }
    let [r, g, b] = sin_t.map(|s| s.expect("every channel refracted"));
    assert!(r > g && g > b, "{r} {g} {b}");
    assert!(r - b > 1e-3, "{r} {b}");
}
