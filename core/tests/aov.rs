//! AOVs against analytic answers: a plane at a known distance, seen head on, gives its
//! distance as depth, its normal and its base colour; where the camera sees nothing,
//! albedo and normal are zero and depth is +inf. And the EXR holds every channel.

use dray_core::aov::AovSet;
use dray_core::bvh::Accel;
use dray_core::camera::Camera;
use dray_core::effects::{Effect, Effects};
use dray_core::film::Film;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::material::Material;
use dray_core::render::render;
use dray_core::scene::Scene;
use glam::Vec3;

const SIZE: u32 = 16;
const SPP: u32 = 4;
const DISTANCE: f32 = 5.0;
const BASE: Vec3 = Vec3::new(0.25, 0.5, 0.75);
/// Vertical field of view: narrow, so the distance to the plane varies little over the
/// image (at most 0.03% more than on the axis).
const FOV_DEG: f32 = 2.0;

/// A square at z = -DISTANCE facing +Z, covering the left half of the view only.
fn scene() -> Scene {
    let mut scene = Scene::default();
    let (z, big) = (-DISTANCE, 10.0);
    let base = scene.mesh.push_vertices(&[
        Vec3::new(-big, -big, z),
        Vec3::new(0.0, -big, z),
        Vec3::new(0.0, big, z),
        Vec3::new(-big, big, z),
    ]);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.indices.push([base, base + 2, base + 3]);
    scene.mesh.material.extend([0, 0]);
    scene.materials.push(Material::lambert("plane", BASE));
    scene
}

fn film(aovs: AovSet) -> Film {
    let scene = scene();
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: SPP,
        integrator: IntegratorKind::Path,
        max_depth: 2,
        seed: 1,
        environment: Vec3::splat(0.5),
        effects: Effects::NONE.with(Effect::Environment),
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs,
    };
    let camera = Camera::look_at("c", Vec3::ZERO, Vec3::NEG_Z, Vec3::Y, FOV_DEG.to_radians());
    let bvh = Accel::build(&scene.mesh);
    let integrator = Integrator::new(&scene, camera, settings);
    render(&integrator, &bvh, 2, &|_, _| {})
        .expect("render")
        .film
}

fn all() -> AovSet {
    AovSet::parse(&["albedo", "normal", "depth", "samples"]).expect("names")
}

#[test]
fn a_plane_gives_its_distance_normal_and_base_colour() {
    let f = film(all());
    let aovs = f.aovs.as_ref().expect("a film with AOVs");
    let ch = aovs.channels(SPP, None);
    let get = |name: &str| &ch.iter().find(|c| c.0 == name).expect(name).1;
    let half = SIZE / 2;
    // At the image's corners the ray leaves the axis by the half-diagonal angle.
    let t = (FOV_DEG.to_radians() / 2.0).tan();
    let slack = (1.0 + 2.0 * t * t).sqrt() - 1.0 + 1e-6;
    for y in 0..SIZE {
        for x in 0..SIZE {
            let p = (y * SIZE + x) as usize;
            let (albedo, normal) = (
                Vec3::new(get("albedo.R")[p], get("albedo.G")[p], get("albedo.B")[p]),
                Vec3::new(get("normal.X")[p], get("normal.Y")[p], get("normal.Z")[p]),
            );
            let depth = get("depth.Z")[p];
            assert_eq!(get("samples.Y")[p], SPP as f32);
            // Pixel columns left of the middle see the plane only (its edge x = 0 is
            // the middle of the view); those right of it see nothing.
            if x + 1 < half {
                assert_eq!(albedo, BASE, "pixel {x},{y}");
                assert_eq!(normal, Vec3::Z, "pixel {x},{y}");
                assert!(
                    depth >= DISTANCE * (1.0 - 1e-6) && depth <= DISTANCE * (1.0 + slack),
                    "pixel {x},{y}: depth {depth}"
                );
            } else if x > half {
                assert_eq!(albedo, Vec3::ZERO, "pixel {x},{y}");
                assert_eq!(normal, Vec3::ZERO, "pixel {x},{y}");
                assert_eq!(depth, f32::INFINITY, "pixel {x},{y}");
            }
        }
    }
    // The beauty is the one a render without AOVs makes: recording them changes no
    // contribution.
    let plain = film(AovSet::NONE);
    assert!(plain.aovs.is_none());
    for p in 0..SIZE * SIZE {
        assert_eq!(f.sum_fixed(p), plain.sum_fixed(p), "pixel {p}");
    }
}

#[test]
fn the_exr_holds_the_beauty_and_every_aov_channel() {
    use exr::prelude::{ReadChannels, ReadLayers};
    let f = film(all());
    let bytes = f.encode_exr(SPP).expect("encode");
    assert_eq!(bytes, f.encode_exr(SPP).expect("again"), "the same bytes");
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .expect("read back");
    assert_eq!(image.layer_data.len(), 1, "one part");
    let layer = &image.layer_data[0];
    let names: Vec<String> = layer
        .channel_data
        .list
        .iter()
        .map(|c| c.name.to_string())
        .collect();
    let mut want = vec![
        "B",
        "G",
        "R",
        "albedo.B",
        "albedo.G",
        "albedo.R",
        "depth.Z",
        "normal.X",
        "normal.Y",
        "normal.Z",
        "samples.Y",
    ];
    want.sort_unstable();
    assert_eq!(names, want);
    let channel = |name: &str| {
        layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .expect(name)
            .sample_data
            .values_as_f32()
            .collect::<Vec<f32>>()
    };
    let lin = f.linear(SPP);
    assert_eq!(channel("R"), lin.iter().map(|p| p.x).collect::<Vec<_>>());
    let albedo_g = channel("albedo.G");
    assert_eq!(albedo_g[0], BASE.y);
    let depth = channel("depth.Z");
    assert_eq!(
        depth[(SIZE - 1) as usize],
        f32::INFINITY,
        "top right sees nothing"
    );
    // Without AOVs, the EXR is the plain RGB one.
    let plain = film(AovSet::NONE).encode_exr(SPP).expect("plain");
    assert!(plain.len() < f.encode_exr(SPP).expect("aovs").len());
}
