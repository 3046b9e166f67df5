//! `soup:N`: N unconnected random triangles in the unit cube.
//!
//! The adversarial case for a BVH and for watertight intersection: overlapping triangles
//! of wildly different sizes (log-uniform), with a share of slivers (apex near the middle
//! of a long edge) and needles (apex near one end), and no shared vertices at all.

use dray_core::camera::Camera;
use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::Vec3;

use super::{Generator, MAX_TRIANGLES, Rng, Sink, frame, parse_count};
use crate::error::Result;

const DEFAULT_COUNT: &str = "10000";
const SEED: u64 = 0x5EED_5EED_0000_0002;
/// Triangles per emitted primitive: what a streaming sink holds at once (9 MiB of
/// vertices), and bounded staging buffers in memory too.
const CHUNK: u64 = 1 << 16;

/// One random triangle: a centre, a log-uniform size between 0.005 and 0.2, and a shape.
fn triangle(rng: &mut Rng) -> [Vec3; 3] {
    let center = Vec3::new(rng.f32(), rng.f32(), rng.f32());
    let size = 0.005 * 40f32.powf(rng.f32());
    let kind = rng.f32();
    let corners = if kind < 0.7 {
        [
            center + rng.in_ball() * size,
            center + rng.in_ball() * size,
            center + rng.in_ball() * size,
        ]
    } else {
        // A long edge a-b and an apex a tiny distance off it.
        let axis = rng.unit_vector();
        let (a, b) = (center - axis * size, center + axis * size);
        let off = axis.any_orthonormal_vector() * (size * rng.range(0.001, 0.02));
        let apex = if kind < 0.85 {
            // Sliver: apex near the middle of the long edge.
            center + off
        } else {
            // Needle: apex near one end, giving one very short edge.
            a + axis * (size * 0.02) + off
        };
        [a, b, apex]
    };
    corners.map(|p| p.clamp(Vec3::ZERO, Vec3::ONE))
}

/// `soup:N`, parsed.
pub(super) struct Soup {
    triangles: u64,
}

/// The one material; triangles refer to it by this index.
const MATERIAL: u32 = 0;

impl Soup {
    pub(super) fn parse(spec: &str, args: Option<&str>) -> Result<Soup> {
        let triangles = parse_count(
            spec,
            "triangle count",
            args.unwrap_or(DEFAULT_COUNT),
            1,
            MAX_TRIANGLES,
        )?;
        Ok(Soup { triangles })
    }
}

impl Generator for Soup {
    fn name(&self) -> &'static str {
        "soup"
    }

    fn triangle_estimate(&self) -> u64 {
        self.triangles
    }

    fn tables(&self, spec: &str) -> Scene {
        Scene {
            name: spec.to_string(),
            materials: vec![Material::lambert("soup", Vec3::new(0.7, 0.6, 0.5))],
            lights: vec![Light::Directional {
                direction: Vec3::new(-0.3, -1.0, -0.5).normalize(),
                irradiance: Vec3::splat(3.0),
            }],
            environment: Some(Vec3::new(0.12, 0.14, 0.18)),
            ..Scene::default()
        }
    }

    /// The triangles in chunks of [`CHUNK`], all from one generator seeded afresh, so
    /// every call draws the same sequence.
    fn emit(&self, _spec: &str, sink: &mut dyn Sink) -> Result<()> {
        let mut rng = Rng::new(SEED);
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        let mut done = 0;
        while done < self.triangles {
            let count = CHUNK.min(self.triangles - done);
            positions.clear();
            indices.clear();
            for _ in 0..count {
                positions.extend_from_slice(&triangle(&mut rng));
            }
            indices.extend(0..positions.len() as u32);
            sink.add_triangles(&positions, None, &indices, MATERIAL)?;
            done += count;
        }
        Ok(())
    }

    /// Framed on the unit cube the triangles are drawn in, not on their bounds.
    fn cameras(&self, _lo: Vec3, _hi: Vec3) -> Vec<Camera> {
        vec![frame(
            "soup",
            Vec3::ZERO,
            Vec3::ONE,
            Vec3::new(0.55, 0.45, 1.0),
            40.0,
        )]
    }
}
