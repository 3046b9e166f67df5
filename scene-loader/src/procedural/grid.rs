//! `grid:SPEC:XxYxZ`: any scene replicated on a regular grid.
//!
//! The way to turn one model into a scene of chosen size with real spatial structure
//! (like the bunny grids of ray-cache studies): copies are spaced 1.2x the model's extent
//! per axis, so they never touch and rays cross many copies.

use dray_core::light::Light;
use dray_core::scene::{Mesh, Scene};

use crate::partition::{SourceTriangle, TriangleLookup, TriangleSource};
use glam::Vec3;

use super::{MAX_STREAMED_TRIANGLES, MAX_TRIANGLES, frame, parse_count, spec_error};
use crate::error::Result;

/// At most a million copies, whatever the model: beyond that the per-copy overhead alone
/// is unreasonable and the spec is almost certainly a typo.
const MAX_COPIES: u64 = 1_000_000;
/// How many grids may be nested (`grid:grid:...`). The inner scene is loaded through the
/// caller's recursive `load`, so without a bound a long enough spec would overflow the
/// stack; two or three levels are all anyone needs.
const MAX_NESTING: usize = 4;
/// Gap factor between copies.
const SPACING: f32 = 1.2;

/// Parse `XxYxZ`.
fn parse_dims(spec: &str, text: &str) -> Result<[u64; 3]> {
    let parts: Vec<&str> = text.split('x').collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(spec_error(
            spec,
            format!("grid size must be XxYxZ (e.g. 3x3x3), got {text:?}"),
        ));
    };
    let mut dims = [0; 3];
    for (d, (part, axis)) in dims.iter_mut().zip([(x, "X"), (y, "Y"), (z, "Z")]) {
        *d = parse_count(spec, &format!("grid size {axis}"), part, 1, MAX_COPIES)?;
    }
    Ok(dims)
}

/// The number of copies `XxYxZ` asks for, within [`MAX_COPIES`].
pub(super) fn copies(spec: &str, dims: &str) -> Result<u64> {
    let dims = parse_dims(spec, dims)?;
    dims.iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d))
        .filter(|&c| c <= MAX_COPIES)
        .ok_or_else(|| {
            spec_error(
                spec,
                format!(
                    "{}x{}x{} copies exceed the cap of {MAX_COPIES}",
                    dims[0], dims[1], dims[2]
                ),
            )
        })
}

/// Where a grid's triangles will live, which decides its limits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Residence {
    /// Made whole ([`GridSource::into_scene`]): at most [`MAX_TRIANGLES`], and the copies'
    /// vertices must be numbered by the mesh's u32 indices.
    InMemory,
    /// Read copy by copy ([`GridSource`] as a [`TriangleSource`]): only the base model is
    /// in memory, so the one limit is [`MAX_STREAMED_TRIANGLES`], the 32-bit global ids.
    Streamed,
}

/// Check the spec, load the base scene, and describe the grid without making it.
pub(super) fn plan(
    spec: &str,
    args: Option<&str>,
    load: &dyn Fn(&str) -> Result<Scene>,
    residence: Residence,
) -> Result<GridSource> {
    let usage = "expected grid:<scene>:XxYxZ, e.g. grid:cornell:3x3x3";
    let mut nesting = 0;
    let mut rest = spec;
    while let Some(inner) = rest.strip_prefix("grid:") {
        nesting += 1;
        rest = inner;
        if nesting > MAX_NESTING {
            return Err(spec_error(
                spec,
                format!("grids nest at most {MAX_NESTING} deep"),
            ));
        }
    }
    let Some((inner, dims)) = args.and_then(|a| a.rsplit_once(':')) else {
        return Err(spec_error(spec, usage));
    };
    if inner.is_empty() {
        return Err(spec_error(
            spec,
            format!("missing scene to replicate; {usage}"),
        ));
    }
    let copies = copies(spec, dims)?;
    let dims = parse_dims(spec, dims)?;

    let base = load(inner)?;
    let tris = base.mesh.triangle_count() as u64;
    if tris == 0 {
        return Err(spec_error(
            spec,
            format!("scene {inner:?} has no triangles"),
        ));
    }
    let total = copies.saturating_mul(tris);
    let cap = match residence {
        Residence::InMemory => MAX_TRIANGLES,
        Residence::Streamed => MAX_STREAMED_TRIANGLES,
    };
    if total > cap {
        return Err(spec_error(
            spec,
            format!("{copies} copies of {tris} triangles is {total}, over the cap of {cap}"),
        ));
    }
    let verts = base.mesh.positions.len() as u64;
    if residence == Residence::InMemory && copies.saturating_mul(verts) > u32::MAX as u64 {
        return Err(spec_error(
            spec,
            format!("{copies} copies of {verts} vertices exceed 2^32 vertices"),
        ));
    }

    let (lo, hi) = base.bounds();
    // A flat model (a single quad) would otherwise get zero spacing on its thin axis.
    let extent = (hi - lo).max(Vec3::splat((hi - lo).max_element() * 0.1));
    let step = extent * SPACING;
    let offsets: Vec<Vec3> = (0..dims[2])
        .flat_map(|iz| {
            (0..dims[1]).flat_map(move |iy| {
                (0..dims[0]).map(move |ix| Vec3::new(ix as f32, iy as f32, iz as f32) * step)
            })
        })
        .collect();
    // The grid's bounds without making it: rounding is monotonic, so the least p + o over
    // a copy is exactly (least p) + o, and these are the bounds of the made mesh, bit for
    // bit.
    let (glo, ghi) = offsets.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(a, b), o| (a.min(lo + *o), b.max(hi + *o)),
    );

    let mut tables = Scene {
        name: spec.to_string(),
        materials: base.materials,
        textures: base.textures,
        lights: base.lights,
        environment: base.environment,
        stats: base.stats,
        ..Scene::default()
    };
    // Lights are kept once (at the first copy): replicating them would multiply the light
    // count with the grid and change the lighting problem, not just its size.
    if tables.lights.is_empty() {
        tables.lights.push(Light::Directional {
            direction: Vec3::new(-0.4, -1.0, -0.5).normalize(),
            irradiance: Vec3::splat(3.0),
        });
    }
    tables
        .cameras
        .push(frame("grid", glo, ghi, Vec3::new(0.55, 0.45, 1.0), 40.0));
    Ok(GridSource {
        base: base.mesh,
        offsets,
        tables,
    })
}

/// A grid scene as a stream: the base mesh once and the copies' offsets. Partitioning
/// reads it as a [`TriangleSource`], so a grid far larger than memory can be cut into a
/// package; [`GridSource::into_scene`] makes the same scene in memory.
pub struct GridSource {
    base: Mesh,
    /// One per copy, x fastest, then y, then z.
    offsets: Vec<Vec3>,
    /// Everything but the mesh: materials, textures, lights, the framing camera.
    tables: Scene,
}

impl GridSource {
    /// The scene without its triangles.
    pub fn tables(&self) -> &Scene {
        &self.tables
    }

    /// The whole grid in memory: copy `c` of base triangle `i` is triangle
    /// `c * base_triangles + i`, as the stream numbers it.
    pub fn into_scene(self) -> Scene {
        let mut scene = self.tables;
        let mesh = &mut scene.mesh;
        let copies = self.offsets.len();
        let n = self.base.positions.len();
        mesh.positions.reserve(n * copies);
        mesh.normals.reserve(n * copies);
        mesh.tangents.reserve(n * copies);
        mesh.uvs.reserve(n * copies);
        mesh.indices.reserve(self.base.indices.len() * copies);
        mesh.material.reserve(self.base.material.len() * copies);
        for offset in &self.offsets {
            let start = mesh.positions.len();
            // All copies share the model's materials, hence offset 0.
            mesh.append(&self.base, 0);
            for p in &mut mesh.positions[start..] {
                *p += *offset;
            }
        }
        scene
    }
}

impl TriangleSource for GridSource {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        let per_copy = self.base.indices.len() as u64;
        for (c, offset) in self.offsets.iter().enumerate() {
            let first = c as u64 * per_copy;
            self.base.for_each_triangle(&mut |t| {
                let mut t = *t;
                t.id = (first + t.id as u64) as u32;
                for p in &mut t.positions {
                    *p += *offset;
                }
                f(&t)
            })?;
        }
        Ok(())
    }

    fn has_colors(&self) -> bool {
        self.base.has_colors()
    }

    /// Any copy's triangle is the base model's moved by the copy's offset, so a grid far
    /// larger than memory is still randomly accessible.
    fn lookup(&self) -> Option<&dyn TriangleLookup> {
        Some(self)
    }
}

impl TriangleLookup for GridSource {
    fn triangle(&self, id: u32) -> Option<SourceTriangle> {
        let per_copy = self.base.indices.len() as u64;
        if per_copy == 0 {
            return None;
        }
        let (copy, i) = (id as u64 / per_copy, id as u64 % per_copy);
        let offset = *self.offsets.get(copy as usize)?;
        // `i` is below the base's triangle count, which fits a u32 when `id` does.
        let mut t = self.base.triangle(i as u32)?;
        t.id = id;
        // The same additions as `for_each_triangle`, so the same bits.
        for p in &mut t.positions {
            *p += offset;
        }
        Some(t)
    }
}

/// `grid:SPEC:XxYxZ` in memory.
pub(super) fn generate(
    spec: &str,
    args: Option<&str>,
    load: &dyn Fn(&str) -> Result<Scene>,
) -> Result<Scene> {
    Ok(plan(spec, args, load, Residence::InMemory)?.into_scene())
}
