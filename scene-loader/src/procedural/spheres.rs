//! `spheres:N[:mirror]`: N icospheres resting on a ground quad; with `mirror`, every
//! third colour of the palette is a perfect mirror, so Whitted rays bounce between
//! spheres (the scheduling experiment's scene: two lights' shadows and reflections).
//!
//! A scene of many small, separate, smoothly shaded objects: the BVH sees N tight
//! clusters, shadows and the point light give every sphere distinct shading, and the
//! triangle count grows exactly linearly (320 N + 2), which makes it a clean scaling test.

use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::{Affine3A, Quat, Vec3};

use super::shapes::{icosphere, quad};
use super::{Builder, MAX_TRIANGLES, Rng, Sink, frame, parse_count};
use crate::error::Result;

const DEFAULT_COUNT: &str = "100";
/// Two subdivisions: 320 triangles per sphere, round enough for smooth-normal shading.
const SUBDIVISIONS: u32 = 2;
const TRIANGLES_PER_SPHERE: u64 = 320;
/// Colours are drawn from a palette so huge counts do not create one material each.
const PALETTE: u64 = 24;
const SEED: u64 = 0x5EED_5EED_0000_0001;

/// The triangles of `spheres:N[:mirror]` (the spheres and the ground quad), or `None`
/// when the count does not parse.
pub(super) fn triangle_estimate(spec: &str, args: Option<&str>) -> Option<u64> {
    let count = args.map_or(DEFAULT_COUNT, |a| a.split_once(':').map_or(a, |(n, _)| n));
    let max = (MAX_TRIANGLES - 2) / TRIANGLES_PER_SPHERE;
    let n = parse_count(spec, "sphere count", count, 1, max).ok()?;
    Some(n * TRIANGLES_PER_SPHERE + 2)
}

/// Check `spheres:N[:mirror]`'s arguments without making anything: what
/// [`generate`] would refuse.
pub(super) fn check(spec: &str, args: Option<&str>) -> Result<()> {
    let (count, variant) = match args.map(|a| a.split_once(':')) {
        Some(Some((n, v))) => (n, Some(v)),
        Some(None) => (args.unwrap_or(DEFAULT_COUNT), None),
        None => (DEFAULT_COUNT, None),
    };
    let max = (MAX_TRIANGLES - 2) / TRIANGLES_PER_SPHERE;
    parse_count(spec, "sphere count", count, 1, max)?;
    match variant {
        None | Some("mirror") => Ok(()),
        Some(other) => Err(crate::error::SceneError::Procedural {
            spec: spec.to_string(),
            message: format!("unknown spheres variant {other:?} (expected `mirror`)"),
        }),
    }
}

pub(super) fn generate(spec: &str, args: Option<&str>) -> Result<Scene> {
    let max = (MAX_TRIANGLES - 2) / TRIANGLES_PER_SPHERE;
    let (count, variant) = match args.map(|a| a.split_once(':')) {
        Some(Some((n, v))) => (n, Some(v)),
        Some(None) => (args.unwrap_or(DEFAULT_COUNT), None),
        None => (DEFAULT_COUNT, None),
    };
    let mirrors = match variant {
        None => false,
        Some("mirror") => true,
        Some(other) => {
            return Err(crate::error::SceneError::Procedural {
                spec: spec.to_string(),
                message: format!("unknown spheres variant {other:?} (expected `mirror`)"),
            });
        }
    };
    let n = parse_count(spec, "sphere count", count, 1, max)?;
    let mut rng = Rng::new(SEED);
    let mut b = Builder::new(spec, "spheres");

    // Keep the density constant (about one sphere per 9 square units) so any N looks
    // like the same kind of scene.
    let side = 3.0 * (n as f32).sqrt() + 2.0;
    let half = side * 0.5;
    let ground = b.material(Material::lambert("ground", Vec3::splat(0.5)));
    b.add_mesh(
        &quad(
            [
                Vec3::new(-half, 0.0, -half),
                Vec3::new(-half, 0.0, half),
                Vec3::new(half, 0.0, half),
                Vec3::new(half, 0.0, -half),
            ],
            Vec3::Y,
        ),
        ground,
    )?;
    let palette: Vec<u32> = (0..PALETTE.min(n))
        .map(|i| {
            let color = rng.color(0.1, 0.9);
            if mirrors && i % 3 == 0 {
                b.material(Material::metal(
                    &format!("sphere {i}"),
                    Vec3::splat(0.9),
                    0.0,
                ))
            } else {
                b.material(Material::lambert(&format!("sphere {i}"), color))
            }
        })
        .collect();

    let unit = icosphere(SUBDIVISIONS);
    for _ in 0..n {
        // Mostly small spheres with the occasional large one.
        let u = rng.f32();
        let radius = 0.25 + 0.6 * u * u;
        let x = rng.range(-half + radius, half - radius);
        let z = rng.range(-half + radius, half - radius);
        let material = palette[rng.below(palette.len() as u64) as usize];
        let xf = Affine3A::from_scale_rotation_translation(
            Vec3::splat(radius),
            Quat::IDENTITY,
            Vec3::new(x, radius, z),
        );
        b.add_mesh(&unit.transformed(xf), material)?;
    }

    b.light(Light::Directional {
        direction: Vec3::new(-0.4, -1.0, -0.6).normalize(),
        irradiance: Vec3::new(2.2, 2.1, 1.9),
    });
    // A point light over the middle adds a second, differently shaped shadow and a
    // falloff, so both light types are exercised.
    let height = 0.35 * side + 2.0;
    b.light(Light::Point {
        position: Vec3::new(0.0, height, 0.0),
        intensity: Vec3::new(1.0, 0.95, 0.85) * (1.5 * height * height),
    });
    b.environment(Vec3::new(0.12, 0.14, 0.18));
    let (lo, hi) = b.bounds();
    b.camera(frame("spheres", lo, hi, Vec3::new(0.3, 0.7, 1.0), 40.0));
    b.finish()
}
