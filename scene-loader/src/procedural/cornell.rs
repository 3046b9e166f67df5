//! The Cornell box, from the original Cornell University measurements.
//!
//! Units are the measurement's (about 555 units across, nominally millimetres), Y up, the
//! open side facing -Z, +X to the viewer's left. The numbers are kept verbatim (including
//! the slightly non-rectangular walls) so renders can be compared with the published
//! reference images and with other renderers' copies of the same data. The camera is the
//! measured one: at (278, 273, -800) looking down +Z with a 35 mm lens on a 25 mm film
//! (39.3° field of view); the reference is square, so render square images to match.
//!
//! Lighting is only the emissive quad under the ceiling (no punctual lights), so the scene
//! exercises area-light sampling and indirect light the way the original does.

use dray_core::camera::Camera;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::{Affine3A, Vec3};

use super::shapes::{MeshData, icosphere, quad};
use super::{Builder, Sink, spec_error};
use crate::error::Result;

/// Reflectances of the white, red and green paints (the RGB values renderers commonly
/// derive from the measured spectra).
const WHITE: Vec3 = Vec3::new(0.725, 0.71, 0.68);
const RED: Vec3 = Vec3::new(0.63, 0.065, 0.05);
const GREEN: Vec3 = Vec3::new(0.14, 0.45, 0.091);
/// The warm light's radiance, in the usual RGB approximation of its spectrum.
const LIGHT: Vec3 = Vec3::new(17.0, 12.0, 4.0);
/// How far the light sits below the ceiling: enough that the two never overlap in a
/// depth test or an intersection tie, small enough to look flush.
const LIGHT_DROP: f32 = 0.5;

#[derive(Clone, Copy, PartialEq)]
enum Variant {
    Plain,
    /// The tall box is a perfect mirror.
    Mirror,
    /// A glass sphere replaces the short box.
    Glass,
}

fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}

/// The short block's top corners and the tall block's top corners (the blocks are prisms
/// standing on the floor).
const SHORT_TOP: [[f32; 2]; 4] = [[130.0, 65.0], [82.0, 225.0], [240.0, 272.0], [290.0, 114.0]];
const SHORT_HEIGHT: f32 = 165.0;
const TALL_TOP: [[f32; 2]; 4] = [
    [423.0, 247.0],
    [265.0, 296.0],
    [314.0, 456.0],
    [472.0, 406.0],
];
const TALL_HEIGHT: f32 = 330.0;

/// A block standing on the floor with footprint `top` (x, z corners in order) and height
/// `h`: four sides and a top, no bottom (it would never be seen), all facing outward.
fn block(top: [[f32; 2]; 4], h: f32) -> MeshData {
    let corners = top.map(|[x, z]| v(x, 0.0, z));
    let center = corners.iter().copied().sum::<Vec3>() / 4.0 + v(0.0, h * 0.5, 0.0);
    let up = v(0.0, h, 0.0);
    let mut mesh = quad(corners.map(|c| c + up), Vec3::Y);
    for i in 0..4 {
        let (a, b) = (corners[i], corners[(i + 1) % 4]);
        let face = [a, b, b + up, a + up];
        let facing = (a + b) * 0.5 + up * 0.5 - center;
        mesh.append(&quad(face, facing));
    }
    mesh
}

/// More triangles than any Cornell variant has (walls, light and two boxes: about 36).
pub(super) const TRIANGLE_ESTIMATE: u64 = 64;

pub(super) fn generate(spec: &str, args: Option<&str>) -> Result<Scene> {
    let variant = match args {
        None => Variant::Plain,
        Some("mirror") => Variant::Mirror,
        Some("glass") => Variant::Glass,
        Some(other) => {
            return Err(spec_error(
                spec,
                format!("unknown Cornell box variant {other:?} (expected `mirror` or `glass`)"),
            ));
        }
    };
    let mut b = Builder::new(spec, "cornell");
    let white = b.material(Material::lambert("cornell white", WHITE));
    let red = b.material(Material::lambert("cornell red", RED));
    let green = b.material(Material::lambert("cornell green", GREEN));
    let light = b.material(Material::emitter("cornell light", LIGHT));

    let walls = [
        // Floor.
        (
            [
                v(552.8, 0.0, 0.0),
                v(0.0, 0.0, 0.0),
                v(0.0, 0.0, 559.2),
                v(549.6, 0.0, 559.2),
            ],
            Vec3::Y,
            white,
        ),
        // Ceiling.
        (
            [
                v(556.0, 548.8, 0.0),
                v(556.0, 548.8, 559.2),
                v(0.0, 548.8, 559.2),
                v(0.0, 548.8, 0.0),
            ],
            Vec3::NEG_Y,
            white,
        ),
        // Back wall.
        (
            [
                v(549.6, 0.0, 559.2),
                v(0.0, 0.0, 559.2),
                v(0.0, 548.8, 559.2),
                v(556.0, 548.8, 559.2),
            ],
            Vec3::NEG_Z,
            white,
        ),
        // Right wall (x = 0, green).
        (
            [
                v(0.0, 0.0, 559.2),
                v(0.0, 0.0, 0.0),
                v(0.0, 548.8, 0.0),
                v(0.0, 548.8, 559.2),
            ],
            Vec3::X,
            green,
        ),
        // Left wall (x = 556, red).
        (
            [
                v(552.8, 0.0, 0.0),
                v(549.6, 0.0, 559.2),
                v(556.0, 548.8, 559.2),
                v(556.0, 548.8, 0.0),
            ],
            Vec3::NEG_X,
            red,
        ),
        // The light, facing down into the box.
        (
            [
                v(343.0, 548.8 - LIGHT_DROP, 227.0),
                v(343.0, 548.8 - LIGHT_DROP, 332.0),
                v(213.0, 548.8 - LIGHT_DROP, 332.0),
                v(213.0, 548.8 - LIGHT_DROP, 227.0),
            ],
            Vec3::NEG_Y,
            light,
        ),
    ];
    for (corners, facing, material) in walls {
        b.add_mesh(&quad(corners, facing), material)?;
    }

    if variant == Variant::Glass {
        // Same footprint centre and height as the short block it replaces, so the
        // composition (and the caustic on the floor) stays where the box was.
        let glass = b.material(Material::glass("cornell glass", 1.5));
        let radius = SHORT_HEIGHT * 0.5;
        let center =
            SHORT_TOP.iter().map(|&[x, z]| v(x, 0.0, z)).sum::<Vec3>() / 4.0 + v(0.0, radius, 0.0);
        let sphere = icosphere(4).transformed(Affine3A::from_scale_rotation_translation(
            Vec3::splat(radius),
            glam::Quat::IDENTITY,
            center,
        ));
        b.add_mesh(&sphere, glass)?;
    } else {
        b.add_mesh(&block(SHORT_TOP, SHORT_HEIGHT), white)?;
    }

    let tall = if variant == Variant::Mirror {
        b.material(Material::metal("cornell mirror", Vec3::splat(0.95), 0.0))
    } else {
        white
    };
    b.add_mesh(&block(TALL_TOP, TALL_HEIGHT), tall)?;

    let yfov = 2.0 * (12.5f32 / 35.0).atan();
    b.camera(Camera::look_at(
        "cornell",
        v(278.0, 273.0, -800.0),
        v(278.0, 273.0, 0.0),
        Vec3::Y,
        yfov,
    ));
    b.finish()
}
