//! Vertex colours (glTF `COLOR_0`) multiply the base colour, alpha included, and a mesh
//! without them shades exactly as before.

use dray_core::bvh::Hit;
use dray_core::effects::Effects;
use dray_core::material::{AlphaMode, Material};
use dray_core::scene::Scene;
use dray_core::surface::{Surface, alpha_passes};
use glam::{Vec3, Vec4};

fn scene(colors: Option<[Vec4; 3]>) -> Scene {
    let mut scene = Scene::default();
    let base = scene.mesh.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
    scene.mesh.indices.push([base, base + 1, base + 2]);
    scene.mesh.material.push(0);
    if let Some(c) = colors {
        scene.mesh.colors = c.to_vec();
    }
    scene.materials.push(Material {
        base_color: Vec4::new(0.8, 0.6, 0.4, 0.5),
        alpha_mode: AlphaMode::Mask { cutoff: 0.3 },
        ..Material::lambert("m", Vec3::ONE)
    });
    scene
}

/// Shading at barycentrics `b` of the one triangle, seen from above.
fn base_color_at(scene: &Scene, b: [f32; 3]) -> (Vec3, f32) {
    let hit = Hit {
        t: 1.0,
        tri: 0,
        b0: b[0],
        b1: b[1],
        b2: b[2],
    };
    let effects = Effects::NONE;
    let s = Surface::new(scene, &hit, Vec3::NEG_Z, effects).shading(scene, effects);
    (s.base_color, s.alpha)
}

#[test]
fn vertex_colours_multiply_the_base_colour_and_alpha() {
    let red = Vec4::new(1.0, 0.0, 0.0, 1.0);
    let blue_half = Vec4::new(0.0, 0.0, 1.0, 0.5);
    let coloured = scene(Some([red, blue_half, Vec4::ONE]));
    let (c, a) = base_color_at(&coloured, [1.0, 0.0, 0.0]);
    assert_eq!((c, a), (Vec3::new(0.8, 0.0, 0.0), 0.5));
    let (c, a) = base_color_at(&coloured, [0.0, 1.0, 0.0]);
    assert_eq!((c, a), (Vec3::new(0.0, 0.0, 0.4), 0.25));
    let (c, _) = base_color_at(&coloured, [0.5, 0.5, 0.0]);
    assert!((c - Vec3::new(0.4, 0.0, 0.2)).length() < 1e-6, "{c}");
    // The alpha cut-out reads the vertex alpha too: 0.5 x 0.5 < 0.3 at the blue corner.
    assert!(alpha_passes(&coloured, 0, [1.0, 0.0, 0.0], 0.0));
    assert!(!alpha_passes(&coloured, 0, [0.0, 1.0, 0.0], 0.0));

    // Without colours: the material's own colour, to the bit.
    let plain = scene(None);
    let (c, a) = base_color_at(&plain, [0.2, 0.3, 0.5]);
    assert_eq!((c, a), (Vec3::new(0.8, 0.6, 0.4), 0.5));
}
