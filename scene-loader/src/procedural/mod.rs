//! Procedural scenes, addressed by name instead of a file path.
//!
//! Benchmarks and tests need scenes that exist everywhere, cost nothing to ship and can be
//! scaled from a handful of triangles to hundreds of millions with one number. A scene
//! spec is either one of the names below or a path; [`generate`] answers `Ok(None)` for
//! anything that is not procedural so the caller falls back to loading a file.
//!
//! # Spec grammar
//!
//! ```text
//! cornell[:mirror|:glass]      the Cornell box (original 555-unit measurements, Y up)
//! spheres[:N[:mirror]]         N icospheres (320 triangles each) on a ground quad; N = 100;
//!                              `mirror`: every third colour a perfect mirror
//! soup[:N]                     N random triangles in the unit cube;                N = 10000
//! city[:N]                     N x N blocks of box buildings;                      N = 8
//! iso[:FIELD[:RES]]            marching-cubes isosurface on a RES^3 cell grid,
//!                              FIELD = sphere|torus|gyroid|metaballs|heart;  sphere, 64
//! grid:SPEC:XxYxZ              the scene SPEC (any spec or path) replicated X*Y*Z times;
//!                              SPEC is everything up to the last ':'
//! ```
//!
//! The first `:`-separated word selects the generator, so a file literally called
//! `city` must be given as `./city`. Sizes are capped (see [`MAX_TRIANGLES`], the
//! per-generator limits, and [`MAX_STREAMED_TRIANGLES`] for grids that are streamed into a
//! package) so a typo cannot ask for terabytes; an out-of-range or malformed argument is a
//! [`SceneError::Procedural`] naming the spec, never a panic.
//!
//! Every scene is deterministic: each generator seeds its own [`Rng`] (splitmix64) with a
//! fixed constant, so the same spec gives bit-identical scenes on every machine, which
//! distributed rendering and reference comparisons rely on.
//!
//! Generators emit triangles primitive by primitive into a [`Sink`]: a [`Builder`] that
//! makes the [`Scene`] in memory, or a [`StreamSink`] that hands each primitive's
//! triangles to the partitioner and forgets them. Both push every primitive through the
//! same validation gate, so a scene streamed by [`stream`] is the scene [`generate`]
//! makes, triangle for triangle; `dray partition` streams, so a scene larger than memory
//! can be cut into a package.

use std::path::Path;

use dray_core::camera::Camera;
use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::Vec3;

use crate::error::{Result, SceneError};
use crate::validate::{Origin, Primitive, add_primitive};

mod city;
mod cornell;
mod generated;
pub mod grid;
mod iso;
pub mod shapes;
mod soup;
mod source;
mod spheres;
mod stream_sink;

pub use generated::GeneratedSource;
use generated::Generator;
use shapes::MeshData;
pub use source::ProceduralSource;
use stream_sink::StreamSink;

/// The largest scene any generator will build. 200M triangles is about 10 GB of mesh in
/// memory: large enough for the streaming experiments, small enough that a stray zero in
/// a spec fails fast with a message instead of exhausting the machine.
pub const MAX_TRIANGLES: u64 = 200_000_000;

/// The largest grid [`stream`] hands over: every triangle needs a 32-bit global id (see
/// `partition`). A streamed grid holds only its base model in memory (which
/// [`MAX_TRIANGLES`] still bounds), so it may be far larger than the machine; what it
/// costs is disk: 34 to 46 bytes a triangle in the package, the less when the model has
/// no tangents or uvs (docs/history/2026-11-26-billion-triangles.md).
pub const MAX_STREAMED_TRIANGLES: u64 = u32::MAX as u64;

/// The names that select a generator (the first `:`-separated word of a spec).
pub const NAMES: [&str; 6] = ["cornell", "spheres", "soup", "grid", "city", "iso"];

/// True when `spec` names a procedural scene (well-formed or not).
pub fn is_procedural(spec: &str) -> bool {
    let head = spec.split_once(':').map_or(spec, |(h, _)| h);
    NAMES.contains(&head)
}

/// Build the procedural scene `spec`, or return `Ok(None)` when `spec` is not procedural
/// (the caller then treats it as a file path). `load` loads any other spec, file or
/// procedural; `grid` uses it for the scene it replicates.
pub fn generate(spec: &str, load: &dyn Fn(&str) -> Result<Scene>) -> Result<Option<Scene>> {
    let (head, args) = match spec.split_once(':') {
        Some((h, a)) => (h, Some(a)),
        None => (spec, None),
    };
    if let Some(g) = generator(spec, head, args)? {
        return Ok(Some(generated::make(spec, g.as_ref())?));
    }
    let scene = match head {
        "cornell" => cornell::generate(spec, args)?,
        "spheres" => spheres::generate(spec, args)?,
        "grid" => grid::generate(spec, args, load)?,
        _ => return Ok(None),
    };
    Ok(Some(scene))
}

/// A procedural scene that can be streamed instead of made, for partitioning scenes
/// larger than memory: `grid:` (copy by copy), `soup:`, `city:` and `iso:` (primitive by
/// primitive); `None` for every other spec, which is small or a file and is loaded whole.
///
/// Planning a generated scene runs its generator once without keeping the triangles,
/// because the manifest needs the degenerate count and the camera framed on the bounds
/// before the partitioner's own passes.
pub fn stream(
    spec: &str,
    load: &dyn Fn(&str) -> Result<Scene>,
) -> Result<Option<ProceduralSource>> {
    let (head, args) = match spec.split_once(':') {
        Some((h, a)) => (h, Some(a)),
        None => (spec, None),
    };
    if head == "grid" {
        let plan = grid::plan(spec, args, load, grid::Residence::Streamed)?;
        return Ok(Some(ProceduralSource::Grid(plan)));
    }
    Ok(match generator(spec, head, args)? {
        Some(g) => Some(ProceduralSource::Generated(GeneratedSource::plan(spec, g)?)),
        None => None,
    })
}

/// Check the procedural scene `spec`'s arguments without making it, so a request for
/// one its generator would refuse (`spheres:4294967296`, `iso:sphere:100000`,
/// `city:1e9`) is refused when submitted, not when loaded (issue 45, item 13). A `grid:`
/// of a file checks only the copies (the file is checked where it is resolved). Specs
/// that are not procedural pass.
pub fn check(spec: &str) -> Result<()> {
    let (head, args) = match spec.split_once(':') {
        Some((h, a)) => (h, Some(a)),
        None => (spec, None),
    };
    match head {
        // 36 triangles: made, which checks the variant exactly as a load would.
        "cornell" => cornell::generate(spec, args).map(|_| ()),
        "spheres" => spheres::check(spec, args),
        "grid" => {
            let Some((inner, dims)) = args.and_then(|a| a.rsplit_once(':')) else {
                return Err(spec_error(spec, "expected grid:<scene>:XxYxZ"));
            };
            grid::copies(spec, dims)?;
            check(inner)
        }
        _ => generator(spec, head, args).map(|_| ()),
    }
}

/// About how many triangles the procedural scene `spec` has, without making it: what
/// admission control needs to refuse a scene too large for the machine before anything
/// is built. `None` when `spec` is not procedural, is malformed (making it reports why),
/// or replicates a file (whose size the caller knows better).
pub fn triangle_estimate(spec: &str) -> Option<u64> {
    let (head, args) = match spec.split_once(':') {
        Some((h, a)) => (h, Some(a)),
        None => (spec, None),
    };
    match head {
        "cornell" => Some(cornell::TRIANGLE_ESTIMATE),
        "spheres" => spheres::triangle_estimate(spec, args),
        "grid" => {
            let (inner, dims) = args?.rsplit_once(':')?;
            let copies = grid::copies(spec, dims).ok()?;
            triangle_estimate(inner).map(|t| t.saturating_mul(copies))
        }
        _ => generator(spec, head, args)
            .ok()
            .flatten()
            .map(|g| g.triangle_estimate()),
    }
}

/// The generators that can stream, parsed from their arguments; `None` for any other head.
fn generator(spec: &str, head: &str, args: Option<&str>) -> Result<Option<Box<dyn Generator>>> {
    Ok(Some(match head {
        "soup" => Box::new(soup::Soup::parse(spec, args)?),
        "city" => Box::new(city::City::parse(spec, args)?),
        "iso" => Box::new(iso::Iso::parse(spec, args)?),
        _ => return Ok(None),
    }))
}

/// A [`SceneError::Procedural`] for `spec`.
pub(crate) fn spec_error(spec: &str, message: impl Into<String>) -> SceneError {
    SceneError::Procedural {
        spec: spec.to_string(),
        message: message.into(),
    }
}

/// Parse a whole-number argument `text` and check it lies in `min..=max`.
pub(crate) fn parse_count(spec: &str, what: &str, text: &str, min: u64, max: u64) -> Result<u64> {
    let n: u64 = text
        .parse()
        .map_err(|_| spec_error(spec, format!("{what} must be a whole number, got {text:?}")))?;
    if n < min || n > max {
        return Err(spec_error(
            spec,
            format!("{what} must be between {min} and {max}, got {n}"),
        ));
    }
    Ok(n)
}

/// Where generators put their triangles, one primitive (triangle list) at a time.
pub(crate) trait Sink {
    /// Emit one primitive with optional per-vertex normals; degenerate triangles are
    /// dropped and counted, so ids number only the triangles kept.
    fn add_triangles(
        &mut self,
        positions: &[Vec3],
        normals: Option<&[Vec3]>,
        indices: &[u32],
        material: u32,
    ) -> Result<()>;

    fn add_mesh(&mut self, mesh: &MeshData, material: u32) -> Result<()> {
        let normals = (!mesh.normals.is_empty()).then_some(mesh.normals.as_slice());
        self.add_triangles(&mesh.positions, normals, &mesh.indices, material)
    }
}

/// The sink that makes the scene in memory: it owns the scene under construction and
/// pushes every primitive through [`add_primitive`], so degenerate triangles are dropped
/// and counted exactly as for files.
pub(crate) struct Builder<'a> {
    spec: &'a str,
    generator: &'static str,
    scene: Scene,
    primitives: usize,
}

impl<'a> Builder<'a> {
    pub(crate) fn new(spec: &'a str, generator: &'static str) -> Self {
        Builder {
            spec,
            generator,
            scene: Scene {
                name: spec.to_string(),
                ..Scene::default()
            },
            primitives: 0,
        }
    }

    /// A builder starting from `tables` (materials, lights, ...) made beforehand.
    pub(crate) fn with_tables(spec: &'a str, generator: &'static str, tables: Scene) -> Self {
        Builder {
            spec,
            generator,
            scene: tables,
            primitives: 0,
        }
    }

    /// Add a material and return its index.
    pub(crate) fn material(&mut self, material: Material) -> u32 {
        self.scene.materials.push(material);
        (self.scene.materials.len() - 1) as u32
    }

    pub(crate) fn light(&mut self, light: Light) {
        self.scene.lights.push(light);
    }

    pub(crate) fn camera(&mut self, camera: Camera) {
        self.scene.cameras.push(camera);
    }

    pub(crate) fn environment(&mut self, radiance: Vec3) {
        self.scene.environment = Some(radiance);
    }

    /// Bounds of everything emitted so far (zero when nothing was).
    pub(crate) fn bounds(&self) -> (Vec3, Vec3) {
        self.scene.bounds()
    }

    /// The finished scene; a scene without triangles is an error because every consumer
    /// (BVH, camera framing) needs at least one.
    pub(crate) fn finish(self) -> Result<Scene> {
        if self.scene.mesh.indices.is_empty() {
            return Err(no_triangles(self.spec));
        }
        Ok(self.scene)
    }
}

/// The error for a generator that produced no triangles at all.
pub(crate) fn no_triangles(spec: &str) -> SceneError {
    spec_error(spec, "the generator produced no triangles")
}

impl Sink for Builder<'_> {
    fn add_triangles(
        &mut self,
        positions: &[Vec3],
        normals: Option<&[Vec3]>,
        indices: &[u32],
        material: u32,
    ) -> Result<()> {
        let origin = Origin {
            path: Path::new(self.spec),
            mesh: self.generator,
            primitive: self.primitives,
        };
        self.primitives += 1;
        add_primitive(
            &mut self.scene.mesh,
            &mut self.scene.stats,
            origin,
            Primitive {
                positions,
                normals,
                tangents: None,
                uvs: None,
                uvs2: None,
                uv_sets: [0, 1],
                colors: None,
                indices,
                material,
            },
        )
    }
}

/// A camera at direction `dir` from the centre of the box `lo..hi`, far enough that the
/// box's bounding sphere fits the vertical field of view (and the horizontal one for any
/// image at least as wide as it is tall).
pub(crate) fn frame(name: &str, lo: Vec3, hi: Vec3, dir: Vec3, yfov_degrees: f32) -> Camera {
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-6);
    let yfov = yfov_degrees.to_radians();
    let dist = radius / (yfov * 0.5).sin();
    let eye = center + dir.normalize_or(Vec3::Z) * dist;
    Camera::look_at(name, eye, center, Vec3::Y, yfov)
}

/// splitmix64: a tiny, well-mixed counter-based generator. Procedural scenes only need
/// reproducible variety, not statistical perfection, and owning the generator keeps the
/// scenes identical across crate versions (no `rand` dependency whose streams may change).
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub(crate) fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Uniform in [lo, hi).
    pub(crate) fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }

    /// Uniform integer in 0..n (n > 0).
    pub(crate) fn below(&mut self, n: u64) -> u64 {
        // Multiply-shift: unbiased enough for picking colours and lots.
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// A uniformly distributed unit vector.
    pub(crate) fn unit_vector(&mut self) -> Vec3 {
        let z = self.range(-1.0, 1.0);
        let phi = self.range(0.0, std::f32::consts::TAU);
        let r = (1.0 - z * z).max(0.0).sqrt();
        Vec3::new(r * phi.cos(), r * phi.sin(), z)
    }

    /// A point uniformly distributed in the unit ball.
    pub(crate) fn in_ball(&mut self) -> Vec3 {
        self.unit_vector() * self.f32().cbrt()
    }

    /// A random colour with every channel in [lo, hi).
    pub(crate) fn color(&mut self, lo: f32, hi: f32) -> Vec3 {
        Vec3::new(self.range(lo, hi), self.range(lo, hi), self.range(lo, hi))
    }
}
