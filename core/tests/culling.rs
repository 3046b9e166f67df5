//! Back faces of single-sided materials (glTF `doubleSided: false`): camera rays pass
//! through them, every other ray sees both sides.

use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::effects::Effects;
use dray_core::integrator::{Integrator, IntegratorKind, RayKind, RayState, RenderSettings};
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::Vec3;

/// Two triangles under a ray looking down -Z: the near one (0) turns its back to the
/// ray (clockwise from above), the far one (1) faces it.
fn scene(near_double_sided: bool) -> Scene {
    let mut scene = Scene::default();
    let near = [Vec3::ZERO, Vec3::Y, Vec3::X];
    let far = [
        Vec3::new(0.0, 0.0, -1.0),
        Vec3::new(1.0, 0.0, -1.0),
        Vec3::new(0.0, 1.0, -1.0),
    ];
    for (m, tri) in [near, far].into_iter().enumerate() {
        let base = scene.mesh.push_vertices(&tri);
        scene.mesh.indices.push([base, base + 1, base + 2]);
        scene.mesh.material.push(m as u32);
    }
    scene.materials = vec![
        Material {
            double_sided: near_double_sided,
            ..Material::lambert("near", Vec3::ONE)
        },
        Material::lambert("far", Vec3::ONE),
    ];
    scene
}

fn settings() -> RenderSettings {
    RenderSettings {
        width: 1,
        height: 1,
        spp: 1,
        integrator: IntegratorKind::Path,
        max_depth: 4,
        seed: 0,
        environment: Vec3::ZERO,
        effects: Effects::NONE,
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    }
}

fn ray(kind: RayKind) -> RayState {
    RayState {
        origin: Vec3::new(0.25, 0.25, 1.0),
        dir: Vec3::NEG_Z,
        tmax: f32::INFINITY,
        pixel: 0,
        sample: 0,
        depth: u32::from(kind != RayKind::Camera),
        kind,
        weight: Vec3::ONE,
        bsdf_pdf: 0.0,
    }
}

fn first_hit(scene: &Scene, kind: RayKind) -> Option<u32> {
    let accel = Accel::build(&scene.mesh);
    let cam = Camera::look_at("c", Vec3::Z, Vec3::ZERO, Vec3::Y, 0.5);
    let integrator = Integrator::new(scene, cam, settings());
    integrator.intersect(&accel, &ray(kind)).map(|h| h.tri)
}

#[test]
fn camera_rays_skip_back_faces_of_single_sided_materials_only() {
    let single = scene(false);
    assert_eq!(first_hit(&single, RayKind::Camera), Some(1));
    // Light transport sees both sides: a bounce, and a shadow ray, meet the back face.
    assert_eq!(first_hit(&single, RayKind::Reflection), Some(0));
    let accel = Accel::build(&single.mesh);
    let cam = Camera::look_at("c", Vec3::Z, Vec3::ZERO, Vec3::Y, 0.5);
    let integrator = Integrator::new(&single, cam, settings());
    let mut shadow = ray(RayKind::Shadow);
    shadow.tmax = 1.5;
    assert!(integrator.occluded(&accel, &shadow));

    // Double-sided: the camera sees the back face.
    assert_eq!(first_hit(&scene(true), RayKind::Camera), Some(0));
}
