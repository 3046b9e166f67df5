//! Beer-Lambert attenuation inside absorbing transmissive objects
//! (`KHR_materials_volume`): a ray that reaches a back face has crossed the medium.

use dray_core::bvh::Hit;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::integrator::{Integrator, IntegratorKind, RayKind, RayState, RenderSettings, Sink};
use dray_core::material::{Material, Volume};
use dray_core::scene::Scene;
use glam::Vec3;

#[derive(Default)]
struct Record {
    contributions: Vec<Vec3>,
}

impl Sink for Record {
    fn contribute(&mut self, _pixel: u32, value: Vec3) {
        self.contributions.push(value);
    }

    fn spawn(&mut self, _ray: RayState) {}
}

/// One glowing glass triangle in the z = 0 plane, front face +z, whose medium turns
/// white light to 0.5 per unit of distance.
fn scene() -> Scene {
    let mut scene = Scene::default();
    let base = scene.mesh.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.material.push(0);
    scene.materials.push(Material {
        emissive: Vec3::ONE,
        volume: Some(Volume {
            attenuation_color: Vec3::splat(0.5),
            attenuation_distance: 1.0,
        }),
        ..Material::glass("absorbing", 1.5)
    });
    scene
}

/// What a ray from `origin` straight along `dir` sees first at the triangle.
fn first_contribution(scene: &Scene, effects: Effects, origin: Vec3, dir: Vec3) -> Vec3 {
    let settings = RenderSettings {
        width: 1,
        height: 1,
        spp: 1,
        integrator: IntegratorKind::Path,
        max_depth: 4,
        seed: 1,
        environment: Vec3::ZERO,
        effects,
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let camera = Camera::look_at("c", origin, origin + dir, Vec3::Y, 1.0);
    let integrator = Integrator::new(scene, camera, settings);
    let ray = RayState {
        origin,
        dir,
        tmax: f32::INFINITY,
        pixel: 0,
        sample: 0,
        depth: 1,
        kind: RayKind::Refraction,
        weight: Vec3::ONE,
        bsdf_pdf: 0.0,
    };
    let hit = Hit {
        t: origin.z.abs(),
        tri: 0,
        b0: 0.6,
        b1: 0.2,
        b2: 0.2,
    };
    let mut sink = Record::default();
    integrator.shade_hit(&ray, &hit, &mut sink);
    sink.contributions[0]
}

#[test]
fn a_path_inside_the_medium_is_attenuated_by_its_length() {
    let scene = scene();
    let fx = Effects::NONE
        .with(Effect::Emission)
        .with(Effect::Transmission)
        .with(Effect::Volume);
    // From 2 units inside (below the front face), up to the back of the surface:
    // 0.5^2 of the emission arrives.
    let inside = first_contribution(&scene, fx, Vec3::new(0.2, 0.2, -2.0), Vec3::Z);
    assert!(
        (inside - Vec3::splat(0.25)).abs().max_element() < 1e-6,
        "{inside}"
    );
    // From outside (a front-face hit) nothing is absorbed.
    let outside = first_contribution(&scene, fx, Vec3::new(0.2, 0.2, 2.0), -Vec3::Z);
    assert_eq!(outside, Vec3::ONE);
    // Without the effect the medium is clear.
    let off = first_contribution(
        &scene,
        Effects::NONE
            .with(Effect::Emission)
            .with(Effect::Transmission),
        Vec3::new(0.2, 0.2, -2.0),
        Vec3::Z,
    );
    assert_eq!(off, Vec3::ONE);
}
