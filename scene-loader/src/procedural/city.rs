//! `city:N`: a procedural city of N x N blocks, in metres, Y up.
//!
//! Modelled on the box-building test cities used for ray-tracing scalability studies:
//! large flat areas (streets), many axis-aligned boxes of very different heights (a dense
//! downtown with towers, low buildings at the edge), so rays are either cheap (hitting the
//! street) or travel far through a deep BVH. Triangles grow with N^2.

use dray_core::camera::Camera;
use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::Vec3;

use super::shapes::{cuboid, quad};
use super::{Generator, Rng, Sink, parse_count};
use crate::error::Result;

const DEFAULT_BLOCKS: &str = "8";
/// 1024^2 blocks of at most 9 buildings is about 100M triangles, within the global cap.
const MAX_BLOCKS: u64 = 1024;
const SEED: u64 = 0x5EED_5EED_0000_0003;
/// Block side and street width, in metres.
const BLOCK: f32 = 80.0;
const STREET: f32 = 16.0;
/// Height of the sidewalk slab each block stands on.
const CURB: f32 = 0.2;
/// Setback from the curb and the gap between neighbouring buildings.
const SETBACK: f32 = 3.0;
const GAP: f32 = 1.5;

/// Material indices, in the order [`City::tables`] lists them.
const ASPHALT: u32 = 0;
const SIDEWALK: u32 = 1;
const FIRST_FACADE: u32 = 2;
const FACADES: [(&str, Vec3); 5] = [
    ("concrete", Vec3::new(0.55, 0.55, 0.52)),
    ("sandstone", Vec3::new(0.7, 0.6, 0.45)),
    ("brick", Vec3::new(0.5, 0.22, 0.15)),
    ("glass-blue", Vec3::new(0.25, 0.35, 0.45)),
    ("white", Vec3::new(0.8, 0.8, 0.78)),
];

/// `city:N`, parsed.
pub(super) struct City {
    blocks: usize,
}

impl City {
    pub(super) fn parse(spec: &str, args: Option<&str>) -> Result<City> {
        let blocks = parse_count(
            spec,
            "block count",
            args.unwrap_or(DEFAULT_BLOCKS),
            1,
            MAX_BLOCKS,
        )? as usize;
        Ok(City { blocks })
    }

    /// The side of the city, street to street.
    fn width(&self) -> f32 {
        self.blocks as f32 * (BLOCK + STREET) + STREET
    }
}

impl Generator for City {
    fn name(&self) -> &'static str {
        "city"
    }

    /// The ground, and per block a sidewalk cuboid and at most 3 x 3 buildings of 12
    /// triangles each: an upper bound (city:32 makes about 40% of it).
    fn triangle_estimate(&self) -> u64 {
        let blocks = (self.blocks as u64).pow(2);
        2 + blocks * 12 * (1 + 9)
    }

    fn tables(&self, spec: &str) -> Scene {
        let mut materials = vec![
            Material::lambert("asphalt", Vec3::splat(0.08)),
            Material::lambert("sidewalk", Vec3::splat(0.45)),
        ];
        materials.extend(FACADES.map(|(name, c)| Material::lambert(name, c)));
        Scene {
            name: spec.to_string(),
            materials,
            // Low afternoon sun, so buildings cast long shadows across the streets.
            lights: vec![Light::Directional {
                direction: Vec3::new(-0.5, -0.8, -0.35).normalize(),
                irradiance: Vec3::new(3.0, 2.85, 2.6),
            }],
            // Sky light fills the shadows; without it shadowed streets would be black.
            environment: Some(Vec3::new(0.3, 0.38, 0.5)),
            ..Scene::default()
        }
    }

    /// The ground, then block by block (row by row) its sidewalk and buildings, each box
    /// one primitive; one generator seeded afresh draws the same city on every call.
    fn emit(&self, _spec: &str, sink: &mut dyn Sink) -> Result<()> {
        let n = self.blocks;
        let mut rng = Rng::new(SEED);
        let pitch = BLOCK + STREET;
        let width = self.width();
        let half = width * 0.5;
        // The ground extends a little past the city so its edge is not a cliff into the void.
        let g = half * 1.5;
        sink.add_mesh(
            &quad(
                [
                    Vec3::new(-g, 0.0, -g),
                    Vec3::new(-g, 0.0, g),
                    Vec3::new(g, 0.0, g),
                    Vec3::new(g, 0.0, -g),
                ],
                Vec3::Y,
            ),
            ASPHALT,
        )?;

        for bz in 0..n {
            for bx in 0..n {
                let x0 = -half + STREET + bx as f32 * pitch;
                let z0 = -half + STREET + bz as f32 * pitch;
                let lo = Vec3::new(x0, 0.0, z0);
                sink.add_mesh(
                    &cuboid(lo, lo + Vec3::new(BLOCK, CURB, BLOCK), false),
                    SIDEWALK,
                )?;
                // 1 for the centre, falling to ~0 at the edge: downtown is taller and denser.
                let centre = Vec3::new(x0 + BLOCK * 0.5, 0.0, z0 + BLOCK * 0.5);
                let downtown = (-(centre.length() / (0.35 * width)).powi(2)).exp();
                let lots_x = 1 + rng.below(3) as usize;
                let lots_z = 1 + rng.below(3) as usize;
                let inner = BLOCK - 2.0 * SETBACK;
                let lot_w = (inner - GAP * (lots_x - 1) as f32) / lots_x as f32;
                let lot_d = (inner - GAP * (lots_z - 1) as f32) / lots_z as f32;
                for lz in 0..lots_z {
                    for lx in 0..lots_x {
                        if rng.f32() < 0.08 {
                            continue; // an empty lot (a plaza) now and then
                        }
                        let lot_x = x0 + SETBACK + lx as f32 * (lot_w + GAP);
                        let lot_z = z0 + SETBACK + lz as f32 * (lot_d + GAP);
                        let w = lot_w * rng.range(0.6, 1.0);
                        let d = lot_d * rng.range(0.6, 1.0);
                        let ox = lot_x + rng.range(0.0, lot_w - w);
                        let oz = lot_z + rng.range(0.0, lot_d - d);
                        let tower = rng.f32() < 0.03 + 0.15 * downtown;
                        let height = if tower {
                            rng.range(80.0, 120.0 + 130.0 * downtown)
                        } else {
                            rng.range(6.0, 15.0 + 35.0 * downtown)
                        };
                        let facade = rng.below(FACADES.len() as u64) as u32;
                        let base = Vec3::new(ox, CURB, oz);
                        sink.add_mesh(
                            &cuboid(base, base + Vec3::new(w, height, d), false),
                            FIRST_FACADE + facade,
                        )?;
                    }
                }
            }
        }
        Ok(())
    }

    /// Elevated oblique view from beyond one corner, looking at the centre. The distance
    /// follows the city width (not the bounds, whose ground apron is mostly empty) or the
    /// tallest tower, whichever is larger, so small cities still show their skyline.
    fn cameras(&self, _lo: Vec3, hi: Vec3) -> Vec<Camera> {
        let target = Vec3::new(0.0, 10.0, 0.0);
        let eye = Vec3::new(0.75, 0.65, 1.0).normalize() * (1.6 * self.width().max(hi.y) + 60.0);
        vec![Camera::look_at(
            "city",
            eye,
            target,
            Vec3::Y,
            45f32.to_radians(),
        )]
    }
}
