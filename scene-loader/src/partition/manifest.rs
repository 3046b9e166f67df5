//! The package manifest: everything about a partitioned scene except the triangles.
//!
//! `manifest.json` is an envelope around the body:
//!
//! ```json
//! {
//!   "format": "dray-scene-package",
//!   "version": 1,
//!   "body_xxh3": "0123456789abcdef",
//!   "body": { "scene_name": ..., "layout": ..., "materials": ..., "domains": [...] }
//! }
//! ```
//!
//! The version sits outside the body so a reader can refuse another version before it
//! tries to understand the rest, and `body_xxh3` is the checksum of the body's exact bytes
//! as written (kept verbatim with serde_json's `RawValue`), so a flipped digit in a
//! material or a wall is caught as corruption rather than rendered. The body names each
//! domain file with its triangle and vertex counts, size and checksum, so the domain files
//! are covered too.
//!
//! Materials are written by the serde derives of `dray-core`'s own types
//! (`dray_core::material`, with the field helpers of `dray_core::material_serde`), so
//! one type holds a material on both sides of a package; their JSON is pinned byte for
//! byte by this module's `material_json_is_pinned` test, because the on-disk format is
//! this module's promise, versioned here. Lights, cameras and samplers go through mirror
//! structs here (`LightDesc` for `Light`, …).
//!
//! Every `f32` is written through [`Real`], exactly: see there.

use std::path::Path;

use dray_core::camera::{Camera, Projection};
use dray_core::light::Light;
use dray_core::material::Material;
pub use dray_core::material_serde::Real;
use dray_core::texture::{Filter, Sampler, Wrap};
use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

use super::checksum::{checksum, from_hex, to_hex};
use super::layout::{BoxDesc, DomainLayout};
use crate::error::{Result, SceneError};

/// The `format` field of every manifest.
pub const FORMAT_NAME: &str = "dray-scene-package";
/// The newest package format version this code reads and writes (manifest and binary
/// files). Bump it on any change a reader of the previous version would misread.
///
/// Version 3 added a second UV set (a `uvs2` section in domain files, and texture
/// references that read it). A package is written with the lowest version that holds it
/// ([`Manifest::version`]): one without a second set is a version 2 package, bit for bit
/// what earlier dray wrote, and one with it is refused by earlier dray by its version
/// rather than rendered with textures on the wrong UVs.
pub const FORMAT_VERSION: u32 = 3;
/// The oldest package format version this code reads: version 2 packages are version 3
/// packages without a second UV set.
pub const MIN_FORMAT_VERSION: u32 = 2;
/// The version that introduced the second UV set.
pub const UVS2_VERSION: u32 = 3;
/// The manifest's file name inside a package directory.
pub const MANIFEST_FILE: &str = "manifest.json";

fn v3(v: Vec3) -> [Real; 3] {
    v.to_array().map(Real)
}

fn from_v3(v: [Real; 3]) -> Vec3 {
    Vec3::from_array(v.map(|r| r.0))
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WrapDesc {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FilterDesc {
    Nearest,
    Linear,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SamplerDesc {
    pub wrap_s: WrapDesc,
    pub wrap_t: WrapDesc,
    pub filter: FilterDesc,
}

fn wrap_out(w: Wrap) -> WrapDesc {
    match w {
        Wrap::Repeat => WrapDesc::Repeat,
        Wrap::ClampToEdge => WrapDesc::ClampToEdge,
        Wrap::MirroredRepeat => WrapDesc::MirroredRepeat,
    }
}

fn wrap_in(w: WrapDesc) -> Wrap {
    match w {
        WrapDesc::Repeat => Wrap::Repeat,
        WrapDesc::ClampToEdge => Wrap::ClampToEdge,
        WrapDesc::MirroredRepeat => Wrap::MirroredRepeat,
    }
}

impl From<Sampler> for SamplerDesc {
    fn from(s: Sampler) -> Self {
        SamplerDesc {
            wrap_s: wrap_out(s.wrap_s),
            wrap_t: wrap_out(s.wrap_t),
            filter: match s.filter {
                Filter::Nearest => FilterDesc::Nearest,
                Filter::Linear => FilterDesc::Linear,
            },
        }
    }
}

impl From<SamplerDesc> for Sampler {
    fn from(s: SamplerDesc) -> Self {
        Sampler {
            wrap_s: wrap_in(s.wrap_s),
            wrap_t: wrap_in(s.wrap_t),
            filter: match s.filter {
                FilterDesc::Nearest => Filter::Nearest,
                FilterDesc::Linear => Filter::Linear,
            },
        }
    }
}

/// A texture's description; its RGBA8 texels are `bytes` bytes at `offset` in
/// `textures.bin`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextureDesc {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub sampler: SamplerDesc,
    pub offset: u64,
    pub bytes: u64,
}

/// Mirror of [`Light`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum LightDesc {
    Point {
        position: [Real; 3],
        intensity: [Real; 3],
    },
    Spot {
        position: [Real; 3],
        direction: [Real; 3],
        intensity: [Real; 3],
        inner_cone: Real,
        outer_cone: Real,
    },
    Directional {
        direction: [Real; 3],
        irradiance: [Real; 3],
    },
}

impl From<&Light> for LightDesc {
    fn from(l: &Light) -> Self {
        match *l {
            Light::Point {
                position,
                intensity,
            } => LightDesc::Point {
                position: v3(position),
                intensity: v3(intensity),
            },
            Light::Spot {
                position,
                direction,
                intensity,
                inner_cone,
                outer_cone,
            } => LightDesc::Spot {
                position: v3(position),
                direction: v3(direction),
                intensity: v3(intensity),
                inner_cone: Real(inner_cone),
                outer_cone: Real(outer_cone),
            },
            Light::Directional {
                direction,
                irradiance,
            } => LightDesc::Directional {
                direction: v3(direction),
                irradiance: v3(irradiance),
            },
        }
    }
}

impl LightDesc {
    pub fn to_core(&self) -> Light {
        match *self {
            LightDesc::Point {
                position,
                intensity,
            } => Light::Point {
                position: from_v3(position),
                intensity: from_v3(intensity),
            },
            LightDesc::Spot {
                position,
                direction,
                intensity,
                inner_cone,
                outer_cone,
            } => Light::Spot {
                position: from_v3(position),
                direction: from_v3(direction),
                intensity: from_v3(intensity),
                inner_cone: inner_cone.0,
                outer_cone: outer_cone.0,
            },
            LightDesc::Directional {
                direction,
                irradiance,
            } => Light::Directional {
                direction: from_v3(direction),
                irradiance: from_v3(irradiance),
            },
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ProjectionDesc {
    Perspective { yfov: Real, aspect: Option<Real> },
    Orthographic { xmag: Real, ymag: Real },
}

/// Mirror of [`Camera`]; `transform` is column-major, as glam and glTF store it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraDesc {
    pub name: String,
    pub transform: [Real; 16],
    pub projection: ProjectionDesc,
    pub znear: Real,
}

impl From<&Camera> for CameraDesc {
    fn from(c: &Camera) -> Self {
        CameraDesc {
            name: c.name.clone(),
            transform: c.transform.to_cols_array().map(Real),
            projection: match c.projection {
                Projection::Perspective { yfov, aspect } => ProjectionDesc::Perspective {
                    yfov: Real(yfov),
                    aspect: aspect.map(Real),
                },
                Projection::Orthographic { xmag, ymag } => ProjectionDesc::Orthographic {
                    xmag: Real(xmag),
                    ymag: Real(ymag),
                },
            },
            znear: Real(c.znear),
        }
    }
}

impl CameraDesc {
    pub fn to_core(&self) -> Camera {
        Camera {
            name: self.name.clone(),
            transform: Mat4::from_cols_array(&self.transform.map(|r| r.0)),
            projection: match self.projection {
                ProjectionDesc::Perspective { yfov, aspect } => Projection::Perspective {
                    yfov: yfov.0,
                    aspect: aspect.map(|a| a.0),
                },
                ProjectionDesc::Orthographic { xmag, ymag } => Projection::Orthographic {
                    xmag: xmag.0,
                    ymag: ymag.0,
                },
            },
            znear: self.znear.0,
            // A package's cameras are the scene file's, which have no lens; a job's
            // lens travels in its spec (`JobSpec.view`), not in the package.
            lens: None,
        }
    }
}

/// A file of the package with its size and checksum.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    pub file: String,
    pub bytes: u64,
    /// XXH3-64 of the whole file, 16 hex digits.
    pub xxh3: String,
}

/// One domain's file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DomainEntry {
    pub file: String,
    pub triangles: u64,
    pub vertices: u64,
    /// Whether the file carries a vertex colour section. Written only when true, so the
    /// manifests of scenes without vertex colours (nearly all) are what they were.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub colors: bool,
    /// Whether the file leaves out the tangent section because every tangent of the
    /// domain is zero ("absent"; procedural meshes and most scans have none): the reader
    /// puts the zeros back. A billion triangles of such a mesh save 16 bytes a vertex on
    /// disk this way (docs/history/2026-11-26-billion-triangles.md). Written only when
    /// true, so other manifests are what they were.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub no_tangents: bool,
    /// The same for the uv section (8 bytes a vertex).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub no_uvs: bool,
    /// Whether the file carries a second UV set section (8 bytes a vertex; format
    /// version 3), present only when some vertex of the domain has a nonzero one. Written
    /// only when true.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub uvs2: bool,
    pub bytes: u64,
    pub xxh3: String,
}

/// What the loader reported (kept so a package tells the same story as its source).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StatsDesc {
    pub degenerate_triangles: u64,
    pub warnings: Vec<String>,
}

/// The manifest body.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub scene_name: String,
    /// The scene bounds (the same as the layout's).
    pub bounds: BoxDesc,
    pub layout: DomainLayout,
    /// Triangles in the unpartitioned scene; global ids are below this.
    pub source_triangles: u64,
    /// Sum of the domains' triangle counts (triangles on walls count once per domain).
    pub assigned_triangles: u64,
    /// Per material, how many source triangles use it (effect analysis ignores unused
    /// materials, and a package has no single mesh to count them in).
    pub material_triangles: Vec<u64>,
    pub materials: Vec<Material>,
    pub textures: Vec<TextureDesc>,
    /// `textures.bin`, present when there are textures.
    pub textures_file: Option<FileEntry>,
    pub lights: Vec<LightDesc>,
    pub cameras: Vec<CameraDesc>,
    pub environment: Option<[Real; 3]>,
    pub stats: StatsDesc,
    pub domains: Vec<DomainEntry>,
    /// [`EMITTERS_FILE`], present when some triangle has an emissive material.
    pub emitters: Option<DomainEntry>,
}

impl Manifest {
    /// What each domain of the package is, for a worker that keeps loaded domains
    /// between jobs: the checksum of everything a loaded domain holds besides its own
    /// triangles (this manifest without its per-domain entries and counts: the layout
    /// with every domain's box, the bounds, materials, textures, lights, cameras and the
    /// emitters' checksum), then the domain file's checksum. The packages of two frames
    /// of an animation, cut with one layout, give a domain no moving mesh touches the
    /// same content; anything else that differs gives every domain another.
    pub fn domain_contents(&self) -> Result<Vec<String>> {
        let mut shared = self.clone();
        let files = std::mem::take(&mut shared.domains);
        shared.source_triangles = 0;
        shared.assigned_triangles = 0;
        shared.material_triangles.clear();
        shared.stats = StatsDesc::default();
        let bytes = serde_json::to_vec(&shared).map_err(|e| SceneError::Format {
            path: Path::new(MANIFEST_FILE).to_path_buf(),
            message: format!("cannot encode the manifest: {e}"),
        })?;
        let shared = to_hex(checksum(&bytes));
        Ok(files
            .iter()
            .map(|f| format!("{shared}:{}", f.xxh3))
            .collect())
    }
}

/// The file name of domain `d`'s triangles.
pub fn domain_file_name(d: u32) -> String {
    format!("domain-{d:05}.bin")
}

/// The file name of the texture blob.
pub const TEXTURES_FILE: &str = "textures.bin";

/// The file name of the emitters: every triangle with an emissive material, in the domain
/// file format. A worker shades with light samples on emitters anywhere in the scene, so
/// it loads them beside its own domains.
pub const EMITTERS_FILE: &str = "emitters.bin";

/// The domain index written in the header of [`EMITTERS_FILE`].
pub const EMITTERS_DOMAIN: u32 = u32::MAX;

#[derive(Serialize)]
struct EnvelopeOut<'a> {
    format: &'static str,
    version: u32,
    body_xxh3: String,
    body: &'a RawValue,
}

/// Just the fields every version shares, read first so a version mismatch is reported as
/// such however different the rest is.
#[derive(Deserialize)]
struct Head {
    format: Option<String>,
    version: Option<serde_json::Value>,
}

#[derive(Deserialize)]
struct EnvelopeIn<'a> {
    body_xxh3: String,
    #[serde(borrow)]
    body: &'a RawValue,
}

/// The text of `manifest.json` for `m`.
pub fn encode(m: &Manifest) -> std::result::Result<String, serde_json::Error> {
    // Compact: every worker parses it, and a kd layout of thousands of domains in
    // pretty JSON is mostly whitespace. `jq` makes it readable.
    let body = serde_json::to_string(m)?;
    let body_xxh3 = to_hex(checksum(body.as_bytes()));
    let raw = RawValue::from_string(body)?;
    let mut text = serde_json::to_string_pretty(&EnvelopeOut {
        format: FORMAT_NAME,
        version: m.version(),
        body_xxh3,
        body: &raw,
    })?;
    text.push('\n');
    Ok(text)
}

/// Parse and check `manifest.json`'s text (`path` is for messages): format name, version,
/// body checksum, then the body itself, then its internal consistency.
pub fn decode(text: &str, path: &Path) -> Result<Manifest> {
    let err = |message: String| SceneError::Format {
        path: path.to_path_buf(),
        message,
    };
    let head: Head = serde_json::from_str(text).map_err(|e| {
        err(format!(
            "not a dray scene package manifest (invalid JSON: {e})"
        ))
    })?;
    if head.format.as_deref() != Some(FORMAT_NAME) {
        return Err(err(format!(
            "not a dray scene package manifest (format is {:?}, expected {FORMAT_NAME:?})",
            head.format.unwrap_or_default()
        )));
    }
    let version = match head.version.as_ref().and_then(|v| v.as_u64()) {
        Some(v) if (MIN_FORMAT_VERSION as u64..=FORMAT_VERSION as u64).contains(&v) => v as u32,
        Some(v) => {
            return Err(err(format!(
                "package format version {v} is not supported (this dray reads versions \
                 {MIN_FORMAT_VERSION} to {FORMAT_VERSION}); partition the scene again with \
                 this dray"
            )));
        }
        None => {
            return Err(err(format!(
                "package format version is missing or not a number (got {}); expected {FORMAT_VERSION}",
                head.version
                    .map_or("nothing".to_string(), |v| v.to_string())
            )));
        }
    };
    let env: EnvelopeIn =
        serde_json::from_str(text).map_err(|e| err(format!("malformed manifest: {e}")))?;
    let expected = from_hex(&env.body_xxh3)
        .ok_or_else(|| err(format!("malformed body checksum {:?}", env.body_xxh3)))?;
    let actual = checksum(env.body.get().as_bytes());
    if actual != expected {
        return Err(err(format!(
            "checksum mismatch: the manifest body hashes to {} but the manifest records {}; \
             the manifest is corrupt or was edited",
            to_hex(actual),
            to_hex(expected)
        )));
    }
    let m: Manifest = serde_json::from_str(env.body.get())
        .map_err(|e| err(format!("malformed manifest body: {e}")))?;
    m.check().map_err(err)?;
    if m.version() > version {
        return Err(err(format!(
            "the manifest says format version {version} but uses a second UV set, which \
             version {UVS2_VERSION} introduced; the manifest is corrupt"
        )));
    }
    Ok(m)
}

impl Manifest {
    /// The lowest format version that holds this manifest and its files: 3 when a domain
    /// file has a second UV set or a texture reads one, else 2.
    pub fn version(&self) -> u32 {
        let uvs2 = self.domains.iter().chain(&self.emitters).any(|e| e.uvs2)
            || self
                .materials
                .iter()
                .any(|m| m.texture_refs().any(|t| t.second_uv));
        if uvs2 {
            UVS2_VERSION
        } else {
            MIN_FORMAT_VERSION
        }
    }

    /// One listed binary file (`what` names it in messages): its name, checksum and counts.
    fn check_entry(
        &self,
        what: &str,
        e: &DomainEntry,
        name: &str,
    ) -> std::result::Result<(), String> {
        if e.file != name {
            return Err(format!(
                "{what} is stored as {:?}, expected {name:?}",
                e.file
            ));
        }
        if from_hex(&e.xxh3).is_none() {
            return Err(format!("{what}: malformed checksum {:?}", e.xxh3));
        }
        if e.triangles > self.source_triangles || e.vertices > 3 * e.triangles {
            return Err(format!(
                "{what}: {} triangles and {} vertices are impossible for a scene of {} triangles",
                e.triangles, e.vertices, self.source_triangles
            ));
        }
        Ok(())
    }

    /// Internal consistency: every count, name and reference a reader will index with.
    pub fn check(&self) -> std::result::Result<(), String> {
        let n = self.layout.domain_count() as usize;
        if self.domains.len() != n {
            return Err(format!(
                "the layout has {n} domains but {} domain files are listed",
                self.domains.len()
            ));
        }
        let lb = self.layout.scene_bounds();
        let mb: super::layout::Aabb = self.bounds.into();
        if lb.min.to_array().map(f32::to_bits) != mb.min.to_array().map(f32::to_bits)
            || lb.max.to_array().map(f32::to_bits) != mb.max.to_array().map(f32::to_bits)
        {
            return Err("the scene bounds differ from the layout's".into());
        }
        if self.source_triangles > u32::MAX as u64 + 1 {
            return Err(format!(
                "{} source triangles is too many",
                self.source_triangles
            ));
        }
        if let Some(e) = &self.emitters {
            self.check_entry("the emitters", e, EMITTERS_FILE)?;
        }
        let mut sum = 0u64;
        for (d, e) in self.domains.iter().enumerate() {
            self.check_entry(&format!("domain {d}"), e, &domain_file_name(d as u32))?;
            sum += e.triangles;
        }
        if sum != self.assigned_triangles {
            return Err(format!(
                "domains hold {sum} triangles but the manifest says {}",
                self.assigned_triangles
            ));
        }
        if self.material_triangles.len() != self.materials.len() {
            return Err("material_triangles does not have one count per material".into());
        }
        let tex_count = self.textures.len();
        for (i, m) in self.materials.iter().enumerate() {
            if let Some(t) = m.texture_refs().find(|t| t.texture as usize >= tex_count) {
                return Err(format!(
                    "material {i} ({:?}) refers to texture {} but there are {tex_count}",
                    m.name, t.texture
                ));
            }
        }
        match (&self.textures_file, tex_count) {
            (None, 0) => {}
            (None, _) => return Err("textures are listed but textures.bin is not".into()),
            (Some(f), _) => {
                if f.file != TEXTURES_FILE || from_hex(&f.xxh3).is_none() {
                    return Err(format!("malformed texture file entry {:?}", f.file));
                }
                for (i, t) in self.textures.iter().enumerate() {
                    let texels = (t.width as u64)
                        .checked_mul(t.height as u64)
                        .and_then(|n| n.checked_mul(4));
                    let end = t.offset.checked_add(t.bytes);
                    if texels != Some(t.bytes) || end.is_none_or(|e| e > f.bytes) {
                        return Err(format!(
                            "texture {i} ({:?}): {}x{} texels do not fit {} bytes at offset {} of {}",
                            t.name, t.width, t.height, t.bytes, t.offset, f.bytes
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    pub fn materials(&self) -> Vec<Material> {
        self.materials.clone()
    }

    pub fn lights(&self) -> Vec<Light> {
        self.lights.iter().map(LightDesc::to_core).collect()
    }

    pub fn cameras(&self) -> Vec<Camera> {
        self.cameras.iter().map(CameraDesc::to_core).collect()
    }

    pub fn environment(&self) -> Option<Vec3> {
        self.environment.map(from_v3)
    }
}

#[cfg(test)]
mod tests {
    use dray_core::material::{
        AlphaMode, Anisotropy, Clearcoat, Iridescence, Sheen, TexRef, Volume,
    };
    use glam::{Affine2, Vec4};

    use super::*;

    #[test]
    fn reals_round_trip_exactly() {
        let mut x = 0x1234_5678u32;
        let mut values = vec![
            0.0,
            -0.0,
            1.0,
            0.1,
            f32::MAX,
            f32::MIN_POSITIVE,
            1.0e-45,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ];
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let v = f32::from_bits(x);
            if !v.is_nan() {
                values.push(v);
            }
        }
        let reals: Vec<Real> = values.iter().map(|&v| Real(v)).collect();
        let json = serde_json::to_string(&reals).unwrap();
        let back: Vec<Real> = serde_json::from_str(&json).unwrap();
        for (a, b) in values.iter().zip(&back) {
            assert_eq!(a.to_bits(), b.0.to_bits(), "{a}");
        }
        let nan: Real =
            serde_json::from_str(&serde_json::to_string(&Real(f32::NAN)).unwrap()).unwrap();
        assert!(nan.0.is_nan());
        assert!(serde_json::from_str::<Real>("1e300").is_err());
        assert!(serde_json::from_str::<Real>("\"lots\"").is_err());
    }

    /// The JSON of a material as a manifest stores it: the function the pinned bytes
    /// below go through.
    fn material_json(m: &Material) -> String {
        serde_json::to_string(m).unwrap()
    }

    fn material_from_json(json: &str) -> Material {
        serde_json::from_str::<Material>(json).unwrap()
    }

    /// A material with every field set away from its default: textures on both UV sets
    /// with and without transforms, every extension, a masked alpha, and the non-finite
    /// factors only `Real` can write.
    fn everything_material() -> Material {
        let tex = |texture: u32, second: bool, transform: Option<Affine2>| TexRef {
            texture,
            tex_coord: u32::from(second),
            second_uv: second,
            transform,
        };
        let turned = Affine2::from_scale_angle_translation(
            glam::Vec2::new(2.0, 0.5),
            0.3,
            glam::Vec2::new(0.25, -1.0),
        );
        Material {
            name: "every \"field\"".to_string(),
            base_color: Vec4::new(0.1, 0.2, 0.3, 0.4),
            base_color_tex: Some(tex(0, false, Some(turned))),
            metallic: 0.7,
            roughness: 0.35,
            metallic_roughness_tex: Some(tex(1, true, None)),
            normal_tex: Some(tex(2, false, None)),
            normal_scale: 0.9,
            emissive: Vec3::new(1.5, 2.5, f32::INFINITY),
            emissive_tex: Some(tex(3, true, Some(Affine2::from_translation(glam::Vec2::X)))),
            transmission: 0.6,
            transmission_tex: Some(tex(4, false, None)),
            ior: 1.45,
            specular: 0.8,
            specular_tex: Some(tex(5, false, None)),
            specular_color: Vec3::new(0.9, 0.8, 0.7),
            specular_color_tex: Some(tex(6, false, None)),
            alpha_mode: AlphaMode::Mask { cutoff: 0.33 },
            double_sided: true,
            unlit: true,
            clearcoat: Some(Clearcoat {
                factor: 0.5,
                tex: Some(tex(7, false, None)),
                roughness: 0.125,
                roughness_tex: Some(tex(8, false, None)),
                normal_tex: Some(tex(9, false, Some(turned))),
                normal_scale: 0.75,
            }),
            sheen: Some(Sheen {
                color: Vec3::new(0.5, 0.25, 1.0),
                color_tex: Some(tex(10, false, None)),
                roughness: 0.6,
                roughness_tex: Some(tex(11, false, None)),
            }),
            anisotropy: Some(Anisotropy {
                strength: 0.4,
                rotation: f32::NAN,
                tex: Some(tex(12, false, None)),
            }),
            volume: Some(Volume {
                attenuation_color: Vec3::new(0.5, 0.9, 1.0),
                attenuation_distance: f32::NEG_INFINITY,
            }),
            iridescence: Some(Iridescence {
                factor: 0.75,
                tex: Some(tex(13, false, None)),
                ior: 1.8,
                thickness_min: 120.0,
                thickness_max: 650.0,
                thickness_tex: Some(tex(14, true, None)),
            }),
            dispersion: 0.05,
        }
    }

    const EVERYTHING_JSON: &str = concat!(
        r#"{"name":"every \"field\"","#,
        r#""base_color":[0.10000000149011612,0.20000000298023224,0.30000001192092896,"#,
        r#"0.4000000059604645],"#,
        r#""base_color_tex":{"texture":0,"tex_coord":0,"transform":[1.9106730222702026,"#,
        r#"0.5910404324531555,-0.14776010811328888,0.47766825556755066,0.25,"#,
        r#"-1.0]},"#,
        r#""metallic":0.699999988079071,"#,
        r#""roughness":0.3499999940395355,"#,
        r#""metallic_roughness_tex":{"texture":1,"tex_coord":1,"second_uv":true},"#,
        r#""normal_tex":{"texture":2,"tex_coord":0},"#,
        r#""normal_scale":0.8999999761581421,"#,
        r#""emissive":[1.5,2.5,"inf"],"#,
        r#""emissive_tex":{"texture":3,"tex_coord":1,"second_uv":true,"transform":[1.0,"#,
        r#"0.0,0.0,1.0,1.0,0.0]},"#,
        r#""transmission":0.6000000238418579,"#,
        r#""transmission_tex":{"texture":4,"tex_coord":0},"#,
        r#""ior":1.4500000476837158,"#,
        r#""specular":0.800000011920929,"#,
        r#""specular_tex":{"texture":5,"tex_coord":0},"#,
        r#""specular_color":[0.8999999761581421,0.800000011920929,0.699999988079071],"#,
        r#""specular_color_tex":{"texture":6,"tex_coord":0},"#,
        r#""alpha_mode":{"mode":"mask","cutoff":0.33000001311302185},"#,
        r#""double_sided":true,"#,
        r#""unlit":true,"#,
        r#""clearcoat":{"factor":0.5,"tex":{"texture":7,"tex_coord":0},"roughness":0.125,"#,
        r#""roughness_tex":{"texture":8,"tex_coord":0},"normal_tex":{"texture":9,"#,
        r#""tex_coord":0,"transform":[1.9106730222702026,0.5910404324531555,"#,
        r#"-0.14776010811328888,0.47766825556755066,0.25,-1.0]},"normal_scale":0.75},"#,
        r#""sheen":{"color":[0.5,0.25,1.0],"color_tex":{"texture":10,"tex_coord":0},"#,
        r#""roughness":0.6000000238418579,"roughness_tex":{"texture":11,"#,
        r#""tex_coord":0}},"#,
        r#""anisotropy":{"strength":0.4000000059604645,"rotation":"nan","#,
        r#""tex":{"texture":12,"tex_coord":0}},"#,
        r#""volume":{"attenuation_color":[0.5,0.8999999761581421,1.0],"#,
        r#""attenuation_distance":"-inf"},"#,
        r#""iridescence":{"factor":0.75,"tex":{"texture":13,"tex_coord":0},"#,
        r#""ior":1.7999999523162842,"thickness_min":120.0,"thickness_max":650.0,"#,
        r#""thickness_tex":{"texture":14,"tex_coord":1,"second_uv":true}},"#,
        r#""dispersion":0.05000000074505806}"#,
    );

    const DEFAULT_JSON: &str = concat!(
        r#"{"name":"default","#,
        r#""base_color":[1.0,1.0,1.0,1.0],"#,
        r#""base_color_tex":null,"#,
        r#""metallic":1.0,"#,
        r#""roughness":1.0,"#,
        r#""metallic_roughness_tex":null,"#,
        r#""normal_tex":null,"#,
        r#""normal_scale":1.0,"#,
        r#""emissive":[0.0,0.0,0.0],"#,
        r#""emissive_tex":null,"#,
        r#""transmission":0.0,"#,
        r#""transmission_tex":null,"#,
        r#""ior":1.5,"#,
        r#""specular":1.0,"#,
        r#""specular_tex":null,"#,
        r#""specular_color":[1.0,1.0,1.0],"#,
        r#""specular_color_tex":null,"#,
        r#""alpha_mode":{"mode":"opaque"},"#,
        r#""double_sided":false}"#,
    );

    /// The bytes a manifest stores for a material are pinned: the package checksums of
    /// scenes already partitioned depend on them.
    #[test]
    fn material_json_is_pinned() {
        let every = everything_material();
        let json = material_json(&every);
        assert_eq!(json, EVERYTHING_JSON);
        // Read back, it writes the same bytes (NaN has no equality to compare with).
        assert_eq!(material_json(&material_from_json(&json)), EVERYTHING_JSON);
        assert!(
            material_from_json(&json)
                .anisotropy
                .unwrap()
                .rotation
                .is_nan()
        );
        let mut finite = every.clone();
        finite.anisotropy = finite.anisotropy.map(|a| Anisotropy {
            rotation: 1.25,
            ..a
        });
        assert_eq!(material_from_json(&material_json(&finite)), finite);
        assert_eq!(material_json(&Material::default()), DEFAULT_JSON);
        // A manifest from before the extensions (the default material's JSON has none of
        // their fields) loads with every extension absent.
        assert_eq!(material_from_json(DEFAULT_JSON), Material::default());
    }

    #[test]
    fn core_types_round_trip() {
        let mut m = Material::glass("g", 1.33);
        m.alpha_mode = AlphaMode::Mask { cutoff: 0.25 };
        m.normal_tex = Some(TexRef::new(2));
        assert_eq!(material_from_json(&material_json(&m)), m);
        // Without glTF extensions the JSON has no field for them (old manifests keep
        // their bytes); with them, they round-trip.
        let plain = material_json(&m);
        for absent in [
            "unlit",
            "clearcoat",
            "sheen",
            "anisotropy",
            "volume",
            "iridescence",
            "dispersion",
            "transform",
        ] {
            assert!(!plain.contains(absent), "{absent} in {plain}");
        }
        m.unlit = true;
        m.normal_tex = Some(TexRef {
            transform: Some(glam::Affine2::from_scale_angle_translation(
                glam::Vec2::new(2.0, 0.5),
                0.3,
                glam::Vec2::new(0.25, -1.0),
            )),
            ..TexRef::new(2)
        });
        m.clearcoat = Some(Clearcoat {
            factor: 0.5,
            tex: Some(TexRef::new(1)),
            roughness: 0.25,
            roughness_tex: None,
            normal_tex: Some(TexRef::new(2)),
            normal_scale: 0.5,
        });
        m.sheen = Some(Sheen {
            color: Vec3::new(0.5, 0.25, 1.0),
            color_tex: None,
            roughness: 0.75,
            roughness_tex: Some(TexRef::new(0)),
        });
        m.anisotropy = Some(Anisotropy {
            strength: 0.5,
            rotation: 1.25,
            tex: Some(TexRef::new(1)),
        });
        m.volume = Some(Volume {
            attenuation_color: Vec3::new(0.5, 0.9, 1.0),
            attenuation_distance: f32::INFINITY,
        });
        m.iridescence = Some(Iridescence {
            factor: 0.75,
            tex: Some(TexRef::new(0)),
            ior: 1.8,
            thickness_min: 120.0,
            thickness_max: 650.0,
            thickness_tex: Some(TexRef::new(1)),
        });
        m.dispersion = 0.5;
        // A coat without a normal map writes what it wrote before coat normals existed.
        let bare = Clearcoat {
            normal_tex: None,
            normal_scale: 1.0,
            ..m.clearcoat.unwrap()
        };
        let bare = serde_json::to_string(&bare).unwrap();
        assert!(!bare.contains("normal"), "{bare}");
        assert_eq!(material_from_json(&material_json(&m)), m);
        let c = Camera::look_at("c", Vec3::new(1.0, 2.0, 3.0), Vec3::ZERO, Vec3::Y, 0.7);
        assert_eq!(CameraDesc::from(&c).to_core(), c);
        let l = Light::Spot {
            position: Vec3::ONE,
            direction: -Vec3::Y,
            intensity: Vec3::splat(5.0),
            inner_cone: 0.1,
            outer_cone: 0.5,
        };
        assert_eq!(LightDesc::from(&l).to_core(), l);
        let s = Sampler {
            wrap_s: Wrap::MirroredRepeat,
            wrap_t: Wrap::ClampToEdge,
            filter: Filter::Nearest,
        };
        assert_eq!(Sampler::from(SamplerDesc::from(s)), s);
    }
}
