//! Writing and reading scene packages.
//!
//! # Layout on disk
//! A package is a directory:
//!
//! ```text
//! manifest.json        envelope + body (see `manifest`): layout, materials, lights,
//!                      cameras, environment, textures, per-domain counts/size/checksum
//! domain-00000.bin     one file per domain, format below
//! domain-00001.bin
//! ...
//! textures.bin         present when the scene has textures
//! emitters.bin         present when some material is emissive: every emissive triangle,
//!                      in the domain file format (domain index u32::MAX)
//! ```
//!
//! Domain file, all little-endian, no padding:
//!
//! ```text
//! offset  size      field
//! 0       8         magic "DRAYDOM\0"
//! 8       4         u32 format version (3 with a uvs2 section, else 2)
//! 12      4         u32 domain index
//! 16      8         u64 vertex count V
//! 24      8         u64 triangle count T
//! 32      12 V      positions   [f32; 3]
//!         12 V      normals     [f32; 3]   (zero = absent)
//!         16 V      tangents    [f32; 4]   (zero = absent; left out, all zero, when the
//!                                          manifest entry says `no_tangents`)
//!          8 V      uvs         [f32; 2]   (left out, all zero, when it says `no_uvs`)
//!          8 V      uvs2        [f32; 2]   (only when it says `uvs2`: the second UV set)
//!         16 V      colours     [f32; 4]   (only when the manifest entry says `colors`)
//!         12 T      indices     [u32; 3]   (into this file's vertices)
//!          4 T      material    u32        (into the manifest's materials)
//!          4 T      global id   u32        (index in the unpartitioned scene)
//! ```
//!
//! so a domain file is exactly `32 + 48 V + 20 T` bytes, `+ 16 V` with colours, `+ 8 V`
//! with a second UV set, `- 16 V` without tangents and `- 8 V` without uvs (see
//! [`Sections`]). Sections rather than records keep each attribute contiguous, as the BVH
//! builder and shading want them.
//!
//! `textures.bin`: magic `"DRAYTEX\0"`, u32 version (2), u32 texture count, then each
//! texture's RGBA8 texels at the offset the manifest gives.
//!
//! # Reading safely
//! Nothing read from a file is trusted before it is checked: the manifest's body checksum
//! and consistency first ([`open_package`]), then for each domain the file size against
//! the manifest (which fixes every count, so no allocation exceeds the file), the header
//! against the manifest, the checksum of every byte, and finally every index. A bad
//! package is a [`SceneError`] naming the file and what is wrong, never a panic.

use std::fs::{self, File, OpenOptions};
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;

use dray_core::camera::Camera;
use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::{LoadStats, Mesh, Scene};
use dray_core::texture::Texture;
use glam::{Vec2, Vec3, Vec4};

use super::checksum::{HashingReader, HashingWriter, from_hex, to_hex};
use super::layout::{Aabb, DomainLayout, LayoutSpec};
use super::manifest::{
    self, DomainEntry, EMITTERS_DOMAIN, EMITTERS_FILE, FORMAT_VERSION, FileEntry, MANIFEST_FILE,
    MIN_FORMAT_VERSION, Manifest, StatsDesc, TEXTURES_FILE, TextureDesc, UVS2_VERSION,
    domain_file_name,
};
use super::{
    DEFAULT_SAMPLE_CAPACITY, DomainBuilder, DomainMesh, SourceTriangle, Survey, TriangleLookup,
    TriangleSource, survey, unassigned_error,
};
use crate::error::{Result, SceneError};

const DOMAIN_MAGIC: [u8; 8] = *b"DRAYDOM\0";
const TEXTURE_MAGIC: [u8; 8] = *b"DRAYTEX\0";
const DOMAIN_HEADER_BYTES: u64 = 32;
const TEXTURE_HEADER_BYTES: u64 = 16;
const VERTEX_BYTES: u64 = 48;
const TRIANGLE_BYTES: u64 = 20;
/// A triangle in a spill file: id, material, then per corner position, normal, tangent
/// and uv (12 f32), the second uv (2 f32) when the source has a second UV set, and the
/// colour (4 f32) when it has vertex colours, so scenes without them do not spill more.
fn record_bytes(colors: bool, uvs2: bool) -> usize {
    8 + 3 * corner_bytes(colors, uvs2)
}

fn corner_bytes(colors: bool, uvs2: bool) -> usize {
    48 + if uvs2 { 8 } else { 0 } + if colors { 16 } else { 0 }
}

/// What pass 2 writes to a domain's spill file for each of its triangles.
#[derive(Clone, Copy)]
enum SpillFormat<'a> {
    /// Whole triangles ([`encode_record`]), for sources that can only be streamed.
    Records { colors: bool, uvs2: bool },
    /// The global id alone (u32, little-endian): compaction makes the triangle again
    /// from the source's [`TriangleLookup`], so the spill is 4 bytes a triangle instead
    /// of 152 or more.
    Ids(&'a dyn TriangleLookup),
}

impl SpillFormat<'_> {
    fn bytes(self) -> usize {
        match self {
            SpillFormat::Records { colors, uvs2 } => record_bytes(colors, uvs2),
            SpillFormat::Ids(_) => 4,
        }
    }

    fn encode(self, t: &SourceTriangle, out: &mut Vec<u8>) {
        match self {
            SpillFormat::Records { colors, uvs2 } => encode_record(t, colors, uvs2, out),
            SpillFormat::Ids(_) => out.extend_from_slice(&t.id.to_le_bytes()),
        }
    }
}
const IO_BUFFER: usize = 1 << 20;

/// Bytes per vertex of the optional colour and second UV set sections.
const COLOR_BYTES: u64 = 16;
const UVS2_BYTES: u64 = 8;
/// Bytes per vertex of the tangent and uv sections, which are left out when all zero.
const TANGENT_BYTES: u64 = 16;
const UV_BYTES: u64 = 8;

/// Which optional vertex sections a domain file carries. Tangents and uvs are left out
/// when every one of the domain's is zero (bit for bit, so nothing is lost): a mesh
/// without them (any isosurface) then costs about 34 bytes a triangle on disk instead of
/// 46, which is what let a package of a billion triangles fit the disk of the machine
/// that wrote it (docs/history/2026-11-26-billion-triangles.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sections {
    pub tangents: bool,
    pub uvs: bool,
    pub colors: bool,
    /// The second UV set: present only when some vertex has a nonzero one (then the
    /// file is format version 3).
    pub uvs2: bool,
}

impl Sections {
    /// Every section (colours and the second UV set too): the fullest file.
    pub const ALL: Sections = Sections {
        tangents: true,
        uvs: true,
        colors: true,
        uvs2: true,
    };

    /// The sections a manifest entry says its file has.
    pub fn of_entry(e: &DomainEntry) -> Sections {
        Sections {
            tangents: !e.no_tangents,
            uvs: !e.no_uvs,
            colors: e.colors,
            uvs2: e.uvs2,
        }
    }

    /// The sections `mesh` needs.
    pub fn of_mesh(mesh: &Mesh) -> Sections {
        let zero = |x: &[f32]| x.iter().all(|v| v.to_bits() == 0);
        Sections {
            tangents: !mesh.tangents.iter().all(|t| zero(&t.to_array())),
            uvs: !mesh.uvs.iter().all(|u| zero(&u.to_array())),
            colors: !mesh.colors.is_empty(),
            uvs2: !mesh.uvs2.iter().all(|u| zero(&u.to_array())),
        }
    }

    /// The format version of a file with these sections.
    fn version(self) -> u32 {
        if self.uvs2 {
            UVS2_VERSION
        } else {
            MIN_FORMAT_VERSION
        }
    }

    fn vertex_bytes(self) -> u64 {
        let optional = |present: bool, bytes: u64| if present { bytes } else { 0 };
        VERTEX_BYTES - TANGENT_BYTES - UV_BYTES
            + optional(self.tangents, TANGENT_BYTES)
            + optional(self.uvs, UV_BYTES)
            + optional(self.colors, COLOR_BYTES)
            + optional(self.uvs2, UVS2_BYTES)
    }
}

/// The size of a domain file with `vertices` and `triangles` and the optional
/// `sections`, or `None` on overflow.
pub fn domain_file_bytes(vertices: u64, triangles: u64, sections: Sections) -> Option<u64> {
    let per_vertex = sections.vertex_bytes();
    vertices
        .checked_mul(per_vertex)?
        .checked_add(triangles.checked_mul(TRIANGLE_BYTES)?)?
        .checked_add(DOMAIN_HEADER_BYTES)
}

fn format_error(path: &Path, message: impl Into<String>) -> SceneError {
    SceneError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn io_error(path: &Path) -> impl FnOnce(io::Error) -> SceneError + '_ {
    move |error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    }
}

/// Knobs for [`write_package`].
#[derive(Clone, Debug)]
pub struct WriteOptions {
    /// Total memory for the per-domain spill buffers of pass 2. Each domain gets an equal
    /// share, at least 4 KiB and at most 1 MiB.
    pub buffer_bytes: usize,
    /// Centroids kept for the kd quantiles.
    pub sample_capacity: usize,
    /// Threads compacting domains into their files; each holds one domain in memory, so
    /// peak memory grows with this.
    pub threads: usize,
    /// Cut with this layout instead of one made for `spec`, when the source's bounds are
    /// its bounds (the frames of an animation, cut alike so that a domain no moving
    /// mesh touches has the same file in each; domains never change the image). Another
    /// bounds: a layout made for `spec`, as without it.
    pub layout: Option<DomainLayout>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        WriteOptions {
            buffer_bytes: 64 << 20,
            sample_capacity: DEFAULT_SAMPLE_CAPACITY,
            // Compaction is hash-map bound; a few threads help, many would only
            // multiply the memory of the largest domain.
            threads: std::thread::available_parallelism().map_or(1, |n| n.get().min(4)),
            layout: None,
        }
    }
}

/// Everything but the triangles: what the manifest stores. Borrowed, so writing a package
/// from a loaded scene copies nothing.
#[derive(Clone, Copy, Debug)]
pub struct SceneParts<'a> {
    pub name: &'a str,
    pub materials: &'a [Material],
    pub textures: &'a [Texture],
    pub lights: &'a [Light],
    pub cameras: &'a [Camera],
    pub environment: Option<Vec3>,
    pub stats: &'a LoadStats,
}

impl<'a> SceneParts<'a> {
    pub fn of(scene: &'a Scene) -> Self {
        SceneParts {
            name: &scene.name,
            materials: &scene.materials,
            textures: &scene.textures,
            lights: &scene.lights,
            cameras: &scene.cameras,
            environment: scene.environment,
            stats: &scene.stats,
        }
    }
}

/// What [`write_package`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct PackageSummary {
    pub domains: u32,
    /// `"grid"` or `"kd"`.
    pub layout: &'static str,
    pub source_triangles: u64,
    /// Sum over domains; larger than `source_triangles` by the triangles on walls.
    pub assigned_triangles: u64,
    pub min_domain_triangles: u64,
    pub max_domain_triangles: u64,
    /// All files of the package.
    pub bytes: u64,
    pub seconds: f64,
}

impl PackageSummary {
    /// The share of stored triangles that are copies: `(assigned - source) / source`.
    pub fn duplicated_share(&self) -> f64 {
        if self.source_triangles == 0 {
            0.0
        } else {
            (self.assigned_triangles - self.source_triangles) as f64 / self.source_triangles as f64
        }
    }
}

/// Partition an in-memory scene into a package at `dir` with default options.
pub fn write_scene_package(dir: &Path, scene: &Scene, spec: &LayoutSpec) -> Result<PackageSummary> {
    write_scene_package_with(dir, scene, spec, None)
}

/// [`write_scene_package`], cut with `layout` when the scene has its bounds
/// ([`WriteOptions::layout`]).
pub fn write_scene_package_with(
    dir: &Path,
    scene: &Scene,
    spec: &LayoutSpec,
    layout: Option<DomainLayout>,
) -> Result<PackageSummary> {
    let options = WriteOptions {
        layout,
        ..WriteOptions::default()
    };
    write_package(dir, SceneParts::of(scene), scene, spec, &options)
}

/// Pass 1: bounds, material use and the centroid sample; the layout (the one given
/// when it fits these bounds). Refuses a scene with no triangles, too many, or
/// triangles whose material the scene lacks.
fn first_pass(
    dir: &Path,
    parts: &SceneParts<'_>,
    source: &dyn TriangleSource,
    spec: &LayoutSpec,
    options: &WriteOptions,
) -> Result<(Survey, DomainLayout)> {
    let capacity = if spec.needs_centroids() {
        options.sample_capacity
    } else {
        0
    };
    let mut s = survey(source, capacity)?;
    if s.triangles == 0 {
        return Err(format_error(dir, "the scene has no triangles to partition"));
    }
    if s.triangles > u32::MAX as u64 {
        return Err(format_error(dir, "more than 4 billion triangles"));
    }
    if s.material_triangles.len() > parts.materials.len() {
        return Err(format_error(
            dir,
            format!(
                "triangles use material {} but the scene has {} materials",
                s.material_triangles.len() - 1,
                parts.materials.len()
            ),
        ));
    }
    s.material_triangles.resize(parts.materials.len(), 0);
    let layout = match &options.layout {
        Some(given) if given.scene_bounds() == s.bounds => given.clone(),
        _ => DomainLayout::build(s.bounds, spec, &mut s.centroids)?,
    };
    drop(std::mem::take(&mut s.centroids));
    tracing::info!(%layout, triangles = s.triangles, "pass 1 done");
    Ok((s, layout))
}

/// What pass 2 leaves: every domain's spill file (flushed), the emitting triangles
/// (kept in memory: they are lights, few next to the scene) and the spills' format.
struct Spilled<'a> {
    spills: Vec<Spill>,
    emitters: DomainBuilder,
    format: SpillFormat<'a>,
}

/// Pass 2: every triangle to the spill buffers of its domains (at `paths`), a buffer
/// flushed when full. Refuses a source that changed since pass 1.
fn second_pass<'a>(
    dir: &Path,
    parts: &SceneParts<'_>,
    source: &'a dyn TriangleSource,
    layout: &DomainLayout,
    triangles: u64,
    paths: &[PathBuf],
    buffer_bytes: usize,
) -> Result<Spilled<'a>> {
    let domain_count = layout.domain_count() as usize;
    let per_domain = (buffer_bytes / domain_count).clamp(4096, 1 << 20);
    let format = match source.lookup() {
        Some(lookup) => SpillFormat::Ids(lookup),
        None => SpillFormat::Records {
            colors: source.has_colors(),
            uvs2: source.has_uvs2(),
        },
    };
    let record_len = format.bytes();
    let per_domain = per_domain.div_ceil(record_len) * record_len;
    let mut spills: Vec<Spill> = paths
        .iter()
        .map(|p| Spill {
            path: p.clone(),
            buf: Vec::new(),
            triangles: 0,
        })
        .collect();
    let mut seen = 0u64;
    let mut domains = Vec::new();
    let mut emitters = DomainBuilder::new();
    let mut record = Vec::with_capacity(record_len);
    source.for_each_triangle(&mut |t| {
        crate::cancel::check_at(seen as usize)?;
        seen += 1;
        if seen > triangles || t.id as u64 >= triangles {
            return Err(format_error(
                dir,
                format!(
                    "the source changed between passes (triangle id {} of {})",
                    t.id, triangles
                ),
            ));
        }
        layout.assign(&t.positions, &mut domains);
        if domains.is_empty() {
            return Err(unassigned_error(t));
        }
        if parts
            .materials
            .get(t.material as usize)
            .is_some_and(|m| m.has_emission())
        {
            emitters.push(t);
        }
        record.clear();
        format.encode(t, &mut record);
        for &d in &domains {
            let spill = &mut spills[d as usize];
            if spill.buf.capacity() == 0 {
                // Exactly one buffer's worth, not a doubling Vec's overshoot.
                spill.buf.reserve_exact(per_domain);
            }
            spill.buf.extend_from_slice(&record);
            spill.triangles += 1;
            if spill.buf.len() >= per_domain {
                spill.flush()?;
            }
        }
        Ok(())
    })?;
    if seen != triangles {
        return Err(format_error(
            dir,
            format!("the source changed between passes ({triangles} triangles, then {seen})"),
        ));
    }
    for spill in &mut spills {
        spill.flush()?;
        spill.buf = Vec::new();
    }
    tracing::info!("pass 2 done");
    Ok(Spilled {
        spills,
        emitters,
        format,
    })
}

/// Write the manifest last, atomically (a temporary file renamed), after checking that
/// what we write we can read; its length in bytes.
fn write_manifest(dir: &Path, m: &Manifest) -> Result<u64> {
    m.check()
        .map_err(|e| format_error(dir, format!("internal error: inconsistent manifest: {e}")))?;
    let text = manifest::encode(m)
        .map_err(|e| format_error(dir, format!("cannot encode the manifest: {e}")))?;
    let tmp = dir.join(format!("{MANIFEST_FILE}.tmp"));
    // No write follows a symlink planted in the package directory (see private_fs).
    crate::private_fs::create_truncate(&tmp)
        .and_then(|mut f| f.write_all(text.as_bytes()))
        .map_err(io_error(&tmp))?;
    let final_path = dir.join(MANIFEST_FILE);
    fs::rename(&tmp, &final_path).map_err(io_error(&final_path))?;
    Ok(text.len() as u64)
}

/// Partition `source` by `spec` and write the package to `dir`.
///
/// `dir` is created if needed; an existing package there is replaced, but a directory
/// holding anything else is refused (so a typo cannot clobber a home directory). The old
/// manifest is removed first and the new one written last (atomically, by rename), so an
/// interrupted write never leaves a package that opens.
pub fn write_package(
    dir: &Path,
    parts: SceneParts<'_>,
    source: &dyn TriangleSource,
    spec: &LayoutSpec,
    options: &WriteOptions,
) -> Result<PackageSummary> {
    let start = Instant::now();
    let _span = tracing::info_span!("write_package", dir = %dir.display()).entered();
    spec.check().map_err(|m| format_error(dir, m))?;
    prepare_dir(dir)?;
    let (s, layout) = first_pass(dir, &parts, source, spec, options)?;
    let mut cleanup = SpillCleanup {
        paths: (0..layout.domain_count())
            .map(|d| dir.join(spill_file_name(d)))
            .collect(),
    };
    let spilled = second_pass(
        dir,
        &parts,
        source,
        &layout,
        s.triangles,
        &cleanup.paths,
        options.buffer_bytes,
    )?;

    // Compact each domain into its file, a few at a time.
    crate::cancel::check()?;
    let entries = finalize_domains(
        dir,
        &spilled.spills,
        &layout,
        options.threads,
        spilled.format,
    )?;
    cleanup.paths.clear();
    tracing::info!("domain files written");

    let emitters = if spilled.emitters.triangle_count() > 0 {
        let mesh = spilled
            .emitters
            .finish(EMITTERS_DOMAIN, layout.scene_bounds());
        let written = write_domain_file(&dir.join(EMITTERS_FILE), &mesh)?;
        Some(written.entry(EMITTERS_FILE.to_string(), &mesh))
    } else {
        None
    };
    let (textures, textures_file) = write_textures(dir, parts.textures)?;
    let assigned: u64 = entries.iter().map(|e| e.triangles).sum();
    let data_bytes: u64 = entries.iter().map(|e| e.bytes).sum::<u64>()
        + textures_file.as_ref().map_or(0, |f| f.bytes)
        + emitters.as_ref().map_or(0, |f| f.bytes);
    let summary_counts = entries.iter().map(|e| e.triangles);
    let min_domain = summary_counts.clone().min().unwrap_or(0);
    let max_domain = summary_counts.max().unwrap_or(0);
    let m = Manifest {
        scene_name: parts.name.to_string(),
        bounds: layout.scene_bounds().into(),
        layout,
        source_triangles: s.triangles,
        assigned_triangles: assigned,
        material_triangles: s.material_triangles,
        materials: parts.materials.to_vec(),
        textures,
        textures_file,
        lights: parts.lights.iter().map(Into::into).collect(),
        cameras: parts.cameras.iter().map(Into::into).collect(),
        environment: parts.environment.map(|e| e.to_array().map(manifest::Real)),
        stats: StatsDesc {
            degenerate_triangles: parts.stats.degenerate_triangles,
            warnings: parts.stats.warnings.clone(),
        },
        domains: entries,
        emitters,
    };
    let manifest_bytes = write_manifest(dir, &m)?;

    Ok(PackageSummary {
        domains: m.layout.domain_count(),
        layout: m.layout.kind_name(),
        source_triangles: m.source_triangles,
        assigned_triangles: m.assigned_triangles,
        min_domain_triangles: min_domain,
        max_domain_triangles: max_domain,
        bytes: data_bytes + manifest_bytes,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Turn every spill file into its domain file, on up to `threads` threads (each holds
/// one domain in memory at a time). Domain files do not depend on the thread count.
fn finalize_domains(
    dir: &Path,
    spills: &[Spill],
    layout: &DomainLayout,
    threads: usize,
    format: SpillFormat<'_>,
) -> Result<Vec<DomainEntry>> {
    let threads = threads.clamp(1, spills.len());
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let per_thread: Vec<Result<Vec<(usize, DomainEntry)>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    while !failed.load(Ordering::Relaxed) {
                        let d = next.fetch_add(1, Ordering::Relaxed);
                        let Some(spill) = spills.get(d) else { break };
                        match finalize_domain(dir, d as u32, spill, layout, format) {
                            Ok(e) => done.push((d, e)),
                            Err(e) => {
                                failed.store(true, Ordering::Relaxed);
                                return Err(e);
                            }
                        }
                    }
                    Ok(done)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
            .collect()
    });
    let mut entries: Vec<Option<DomainEntry>> = vec![None; spills.len()];
    for r in per_thread {
        for (d, e) in r? {
            entries[d] = Some(e);
        }
    }
    Ok(entries.into_iter().flatten().collect())
}

/// Read one domain's spill file, share its vertices, write its domain file.
fn finalize_domain(
    dir: &Path,
    d: u32,
    spill: &Spill,
    layout: &DomainLayout,
    format: SpillFormat<'_>,
) -> Result<DomainEntry> {
    let mut builder = DomainBuilder::with_capacity(spill.triangles as usize);
    if spill.triangles > 0 {
        read_spill(&spill.path, format, &mut |t| {
            builder.push(t);
            Ok(())
        })?;
    }
    if builder.triangle_count() as u64 != spill.triangles {
        return Err(format_error(
            &spill.path,
            format!(
                "spill file holds {} triangles, expected {}",
                builder.triangle_count(),
                spill.triangles
            ),
        ));
    }
    let mesh = builder.finish(d, layout.bounds(d));
    let file = domain_file_name(d);
    let written = write_domain_file(&dir.join(&file), &mesh)?;
    let _ = fs::remove_file(&spill.path);
    Ok(written.entry(file, &mesh))
}

fn spill_file_name(d: u32) -> String {
    format!(".domain-{d:05}.spill")
}

/// True for the names a package (or an interrupted write of one) consists of.
fn is_package_file(name: &str) -> bool {
    let numbered = |prefix: &str, suffix: &str| {
        name.strip_prefix(prefix)
            .and_then(|r| r.strip_suffix(suffix))
            .is_some_and(|n| n.len() == 5 && n.bytes().all(|b| b.is_ascii_digit()))
    };
    name == MANIFEST_FILE
        || name == format!("{MANIFEST_FILE}.tmp")
        || name == TEXTURES_FILE
        || name == EMITTERS_FILE
        || numbered("domain-", ".bin")
        || numbered(".domain-", ".spill")
}

/// Create `dir`, or empty it of a previous package; refuse a directory with other files.
fn prepare_dir(dir: &Path) -> Result<()> {
    if !dir.exists() {
        return fs::create_dir_all(dir).map_err(io_error(dir));
    }
    if !dir.is_dir() {
        return Err(format_error(dir, "exists and is not a directory"));
    }
    let mut names = Vec::new();
    for entry in fs::read_dir(dir).map_err(io_error(dir))? {
        let entry = entry.map_err(io_error(dir))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if !is_package_file(&name) {
            return Err(format_error(
                dir,
                format!(
                    "is not empty and holds {name:?}, which is not part of a scene package; \
                     refusing to overwrite (choose an empty or new directory)"
                ),
            ));
        }
        names.push(name);
    }
    // The manifest goes first, so a half-replaced package never opens.
    names.sort_by_key(|n| n != MANIFEST_FILE);
    for name in names {
        let p = dir.join(name);
        fs::remove_file(&p).map_err(io_error(&p))?;
    }
    Ok(())
}

/// Removes spill files left by a write that failed part way.
struct SpillCleanup {
    paths: Vec<PathBuf>,
}

impl Drop for SpillCleanup {
    fn drop(&mut self) {
        for p in &self.paths {
            let _ = fs::remove_file(p);
        }
    }
}

/// One domain's pass-2 buffer; full buffers are appended to the domain's spill file,
/// which is opened only for the append, so thousands of domains never hold thousands of
/// file handles.
struct Spill {
    path: PathBuf,
    buf: Vec<u8>,
    triangles: u64,
}

impl Spill {
    fn flush(&mut self) -> Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let mut f = crate::private_fs::no_follow(OpenOptions::new().create(true).append(true))
            .open(&self.path)
            .map_err(io_error(&self.path))?;
        f.write_all(&self.buf).map_err(io_error(&self.path))?;
        self.buf.clear();
        Ok(())
    }
}

fn encode_record(t: &SourceTriangle, colors: bool, uvs2: bool, out: &mut Vec<u8>) {
    out.extend_from_slice(&t.id.to_le_bytes());
    out.extend_from_slice(&t.material.to_le_bytes());
    for k in 0..3 {
        let (p, n, g, u) = (t.positions[k], t.normals[k], t.tangents[k], t.uvs[k]);
        for x in [p.x, p.y, p.z, n.x, n.y, n.z, g.x, g.y, g.z, g.w, u.x, u.y] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        if uvs2 {
            for x in t.uvs2[k].to_array() {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        if colors {
            for x in t.colors[k].to_array() {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
    }
}

fn decode_record(b: &[u8], colors: bool, uvs2: bool) -> SourceTriangle {
    let u = |i: usize| u32::from_le_bytes(b[i..i + 4].try_into().unwrap());
    let f = |i: usize| f32::from_bits(u(i));
    let stride = corner_bytes(colors, uvs2);
    // The colour follows the second uv when there is one.
    let color_at = if uvs2 { 56 } else { 48 };
    let corner = |k: usize| 8 + stride * k;
    SourceTriangle {
        id: u(0),
        material: u(4),
        positions: std::array::from_fn(|k| {
            let o = corner(k);
            Vec3::new(f(o), f(o + 4), f(o + 8))
        }),
        normals: std::array::from_fn(|k| {
            let o = corner(k) + 12;
            Vec3::new(f(o), f(o + 4), f(o + 8))
        }),
        tangents: std::array::from_fn(|k| {
            let o = corner(k) + 24;
            Vec4::new(f(o), f(o + 4), f(o + 8), f(o + 12))
        }),
        uvs: std::array::from_fn(|k| {
            let o = corner(k) + 40;
            Vec2::new(f(o), f(o + 4))
        }),
        uvs2: std::array::from_fn(|k| {
            let o = corner(k) + 48;
            if uvs2 {
                Vec2::new(f(o), f(o + 4))
            } else {
                Vec2::ZERO
            }
        }),
        colors: std::array::from_fn(|k| {
            let o = corner(k) + color_at;
            if colors {
                Vec4::new(f(o), f(o + 4), f(o + 8), f(o + 12))
            } else {
                Vec4::ONE
            }
        }),
    }
}

fn read_spill(
    path: &Path,
    format: SpillFormat<'_>,
    f: &mut dyn FnMut(&SourceTriangle) -> Result<()>,
) -> Result<()> {
    let mut r = BufReader::with_capacity(IO_BUFFER, File::open(path).map_err(io_error(path))?);
    let record_len = format.bytes();
    let mut chunk = vec![0u8; record_len * 1024];
    loop {
        let n = read_full(&mut r, &mut chunk).map_err(io_error(path))?;
        if n % record_len != 0 {
            return Err(format_error(path, "spill file ends inside a record"));
        }
        for rec in chunk[..n].chunks_exact(record_len) {
            match format {
                SpillFormat::Records { colors, uvs2 } => f(&decode_record(rec, colors, uvs2))?,
                SpillFormat::Ids(lookup) => {
                    let id = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]);
                    let t = lookup.triangle(id).ok_or_else(|| {
                        format_error(
                            path,
                            format!("the source has no triangle {id}: it changed while written"),
                        )
                    })?;
                    f(&t)?;
                }
            }
        }
        if n < chunk.len() {
            return Ok(());
        }
    }
}

/// Read until `buf` is full or the reader ends; the number of bytes read.
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// What [`write_domain_file`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WrittenDomain {
    pub bytes: u64,
    pub xxh3: u64,
    pub sections: Sections,
}

impl WrittenDomain {
    /// The manifest entry of `mesh` written to `file`.
    pub fn entry(self, file: String, mesh: &DomainMesh) -> DomainEntry {
        DomainEntry {
            file,
            triangles: mesh.triangle_count() as u64,
            vertices: mesh.mesh.positions.len() as u64,
            colors: self.sections.colors,
            no_tangents: !self.sections.tangents,
            no_uvs: !self.sections.uvs,
            uvs2: self.sections.uvs2,
            bytes: self.bytes,
            xxh3: to_hex(self.xxh3),
        }
    }
}

/// Write `mesh` as a domain file, with the sections it needs ([`Sections::of_mesh`]).
pub fn write_domain_file(path: &Path, mesh: &DomainMesh) -> Result<WrittenDomain> {
    let sections = Sections::of_mesh(&mesh.mesh);
    let file = crate::private_fs::create_truncate(path).map_err(io_error(path))?;
    // The buffer sits outside the hasher, so the hasher sees large chunks.
    let mut w = BufWriter::with_capacity(IO_BUFFER, HashingWriter::new(file));
    let m = &mesh.mesh;
    let result = (|| -> io::Result<()> {
        w.write_all(&DOMAIN_MAGIC)?;
        w.write_all(&sections.version().to_le_bytes())?;
        w.write_all(&mesh.domain.to_le_bytes())?;
        w.write_all(&(m.positions.len() as u64).to_le_bytes())?;
        w.write_all(&(m.indices.len() as u64).to_le_bytes())?;
        let mut put = |x: u32| w.write_all(&x.to_le_bytes());
        for v in &m.positions {
            v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
        }
        for v in &m.normals {
            v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
        }
        if sections.tangents {
            for v in &m.tangents {
                v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
            }
        }
        if sections.uvs {
            for v in &m.uvs {
                v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
            }
        }
        if sections.uvs2 {
            for v in &m.uvs2 {
                v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
            }
        }
        for v in &m.colors {
            v.to_array().iter().try_for_each(|x| put(x.to_bits()))?;
        }
        for t in &m.indices {
            t.iter().try_for_each(|&i| put(i))?;
        }
        m.material.iter().try_for_each(|&x| put(x))?;
        mesh.global_ids.iter().try_for_each(|&x| put(x))?;
        Ok(())
    })();
    result.map_err(io_error(path))?;
    let hashing = w.into_inner().map_err(|e| io_error(path)(e.into_error()))?;
    let (_, bytes, xxh3) = hashing.finish().map_err(io_error(path))?;
    Ok(WrittenDomain {
        bytes,
        xxh3,
        sections,
    })
}

/// Write `textures.bin` (when there are textures) and describe each texture.
fn write_textures(
    dir: &Path,
    textures: &[Texture],
) -> Result<(Vec<TextureDesc>, Option<FileEntry>)> {
    if textures.is_empty() {
        return Ok((Vec::new(), None));
    }
    let path = dir.join(TEXTURES_FILE);
    let mut descs = Vec::with_capacity(textures.len());
    let file = crate::private_fs::create_truncate(&path).map_err(io_error(&path))?;
    let mut w = BufWriter::with_capacity(IO_BUFFER, HashingWriter::new(file));
    let mut offset = TEXTURE_HEADER_BYTES;
    let result = (|| -> io::Result<()> {
        w.write_all(&TEXTURE_MAGIC)?;
        // Unchanged since version 2, so written as 2 (a version 2 package stays one).
        w.write_all(&MIN_FORMAT_VERSION.to_le_bytes())?;
        w.write_all(&(textures.len() as u32).to_le_bytes())?;
        for t in textures {
            for px in t.texels.iter() {
                w.write_all(px)?;
            }
        }
        Ok(())
    })();
    result.map_err(io_error(&path))?;
    for (i, t) in textures.iter().enumerate() {
        let bytes = t.texels.len() as u64 * 4;
        if t.width as u64 * t.height as u64 != t.texels.len() as u64 {
            return Err(format_error(
                &path,
                format!(
                    "texture {i} ({:?}) is {}x{} but has {} texels",
                    t.name,
                    t.width,
                    t.height,
                    t.texels.len()
                ),
            ));
        }
        descs.push(TextureDesc {
            name: t.name.clone(),
            width: t.width,
            height: t.height,
            sampler: t.sampler.into(),
            offset,
            bytes,
        });
        offset += bytes;
    }
    let hashing = w
        .into_inner()
        .map_err(|e| io_error(&path)(e.into_error()))?;
    let (_, bytes, sum) = hashing.finish().map_err(io_error(&path))?;
    Ok((
        descs,
        Some(FileEntry {
            file: TEXTURES_FILE.to_string(),
            bytes,
            xxh3: to_hex(sum),
        }),
    ))
}

/// An opened scene package: the checked manifest, and domains and textures on demand.
#[derive(Clone, Debug)]
pub struct Package {
    dir: PathBuf,
    manifest: Manifest,
    materials: Vec<Material>,
    lights: Vec<Light>,
    cameras: Vec<Camera>,
}

/// Read and check the manifest of the package at `dir`. Domain files are not touched (a
/// worker reads only its own); [`Package::verify`] checks them all.
pub fn open_package(dir: &Path) -> Result<Package> {
    let path = dir.join(MANIFEST_FILE);
    let opened = crate::reference::open_scene_file(&path)?;
    let (file, len) = (opened.file, opened.len);
    // A manifest is a few bytes per material and domain; anything this large is not one.
    const MAX_MANIFEST: u64 = 1 << 30;
    if len > MAX_MANIFEST {
        return Err(format_error(
            &path,
            format!("{len} bytes is too large for a manifest"),
        ));
    }
    let mut text = String::with_capacity(len as usize);
    file.take(MAX_MANIFEST)
        .read_to_string(&mut text)
        .map_err(|e| match e.kind() {
            io::ErrorKind::InvalidData => format_error(&path, "is not UTF-8 text"),
            _ => io_error(&path)(e),
        })?;
    let manifest = manifest::decode(&text, &path)?;
    let named = manifest
        .domains
        .iter()
        .enumerate()
        .map(|(d, e)| (format!("domain {d}"), e))
        .chain(
            manifest
                .emitters
                .iter()
                .map(|e| ("emitters".to_string(), e)),
        );
    for (what, e) in named {
        if domain_file_bytes(e.vertices, e.triangles, Sections::of_entry(e)) != Some(e.bytes) {
            return Err(format_error(
                &path,
                format!(
                    "{what}: {} bytes cannot hold {} vertices and {} triangles",
                    e.bytes, e.vertices, e.triangles
                ),
            ));
        }
    }
    if let Some(f) = &manifest.textures_file
        && f.bytes < TEXTURE_HEADER_BYTES
    {
        return Err(format_error(
            &path,
            "textures.bin is too small for its header",
        ));
    }
    Ok(Package {
        dir: dir.to_path_buf(),
        materials: manifest.materials(),
        lights: manifest.lights(),
        cameras: manifest.cameras(),
        manifest,
    })
}

impl Package {
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    pub fn layout(&self) -> &DomainLayout {
        &self.manifest.layout
    }

    pub fn domain_count(&self) -> u32 {
        self.manifest.layout.domain_count()
    }

    pub fn name(&self) -> &str {
        &self.manifest.scene_name
    }

    pub fn materials(&self) -> &[Material] {
        &self.materials
    }

    pub fn lights(&self) -> &[Light] {
        &self.lights
    }

    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    pub fn environment(&self) -> Option<Vec3> {
        self.manifest.environment()
    }

    /// The scene's tables with no mesh: materials, textures (read and checked now),
    /// lights, cameras and environment: what every domain of the package shares.
    pub fn tables(&self) -> Result<Scene> {
        Ok(Scene {
            name: self.name().to_string(),
            mesh: Mesh::default(),
            materials: self.materials().to_vec(),
            textures: self.load_textures()?,
            lights: self.lights().to_vec(),
            cameras: self.cameras().to_vec(),
            environment: self.environment(),
            stats: Default::default(),
        })
    }

    /// Load domain `d`, checking its size, header, checksum and indices.
    pub fn load_domain(&self, d: u32) -> Result<DomainMesh> {
        let Some(entry) = self.manifest.domains.get(d as usize) else {
            return Err(format_error(
                &self.dir,
                format!(
                    "domain {d} does not exist (the package has {})",
                    self.domain_count()
                ),
            ));
        };
        self.load_entry(d, entry, self.layout().bounds(d))
    }

    /// Load the emitters (every triangle with an emissive material, in scene order), with
    /// the same checks as a domain; an empty mesh when the scene has none.
    pub fn load_emitters(&self) -> Result<DomainMesh> {
        match &self.manifest.emitters {
            Some(entry) => self.load_entry(EMITTERS_DOMAIN, entry, self.layout().scene_bounds()),
            None => Ok(DomainMesh {
                domain: EMITTERS_DOMAIN,
                bounds: self.layout().scene_bounds(),
                mesh: Mesh::default(),
                global_ids: Vec::new(),
            }),
        }
    }

    fn load_entry(&self, d: u32, entry: &DomainEntry, bounds: Aabb) -> Result<DomainMesh> {
        let path = self.dir.join(&entry.file);
        // A regular file, opened without blocking (a FIFO or device in a package folder
        // must not hang or feed the reader forever).
        let opened = crate::reference::open_scene_file(&path)?;
        let (file, len) = (opened.file, opened.len);
        if len != entry.bytes {
            return Err(format_error(
                &path,
                format!(
                    "{} bytes, but the manifest records {}: the file is {}",
                    len,
                    entry.bytes,
                    if len < entry.bytes {
                        "truncated"
                    } else {
                        "too long"
                    }
                ),
            ));
        }
        let mut r = BufReader::with_capacity(IO_BUFFER, HashingReader::new(file));
        let mesh = decode_domain(&mut r, &path, d, entry)?;
        // Everything was read, so the hasher has seen the whole file.
        let mut probe = [0u8; 1];
        if r.read(&mut probe).map_err(io_error(&path))? != 0 {
            return Err(format_error(&path, "the file grew while it was read"));
        }
        let actual = r.get_ref().digest();
        let expected = from_hex(&entry.xxh3).unwrap_or_default();
        if actual != expected {
            return Err(format_error(
                &path,
                format!(
                    "checksum mismatch: the file hashes to {} but the manifest records {}; \
                     the file is corrupt",
                    to_hex(actual),
                    entry.xxh3
                ),
            ));
        }
        self.check_domain(&mesh, &path)?;
        Ok(DomainMesh {
            domain: d,
            bounds,
            mesh: mesh.0,
            global_ids: mesh.1,
        })
    }

    /// Index checks on a decoded domain (after its checksum matched, so a failure here
    /// means the package was written wrong, not damaged).
    fn check_domain(&self, (mesh, ids): &(Mesh, Vec<u32>), path: &Path) -> Result<()> {
        // Checksums catch damage, not a hostile writer (anyone can recompute them): hold
        // positions to the importers' rule.
        let limit = crate::validate::MAX_COORDINATE;
        if let Some(i) = mesh
            .positions
            .iter()
            .position(|p| !p.is_finite() || p.abs().max_element() > limit)
        {
            return Err(format_error(
                path,
                format!("vertex {i} has a non-finite position or a coordinate beyond ±{limit:e}"),
            ));
        }
        let v = mesh.positions.len() as u32;
        if let Some((i, t)) = mesh
            .indices
            .iter()
            .enumerate()
            .find(|(_, t)| t.iter().any(|&x| x >= v))
        {
            return Err(format_error(
                path,
                format!("triangle {i} refers to vertex {t:?} but there are {v} vertices"),
            ));
        }
        let materials = self.materials.len() as u32;
        if let Some((i, m)) = mesh
            .material
            .iter()
            .enumerate()
            .find(|(_, m)| **m >= materials)
        {
            return Err(format_error(
                path,
                format!("triangle {i} uses material {m} but there are {materials}"),
            ));
        }
        let n = self.manifest.source_triangles;
        if let Some((i, g)) = ids.iter().enumerate().find(|(_, g)| **g as u64 >= n) {
            return Err(format_error(
                path,
                format!("triangle {i} has global id {g} but the scene has {n} triangles"),
            ));
        }
        Ok(())
    }

    /// Load and check all textures.
    pub fn load_textures(&self) -> Result<Vec<Texture>> {
        let Some(entry) = &self.manifest.textures_file else {
            return Ok(Vec::new());
        };
        let path = self.dir.join(&entry.file);
        let bytes = read_checked(&path, entry.bytes, &entry.xxh3)?;
        // The manifest's size is only checked against the file, so a short (but
        // checksummed) file must not be sliced blindly.
        let word = |at: usize| -> Option<u32> {
            Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
        };
        let (Some(version), Some(count)) = (word(8), word(12)) else {
            return Err(format_error(
                &path,
                format!(
                    "{} bytes is too short for a texture file header",
                    bytes.len()
                ),
            ));
        };
        let header_ok = bytes.get(..8) == Some(&TEXTURE_MAGIC[..]);
        if !header_ok {
            return Err(format_error(&path, "not a dray texture file (bad magic)"));
        }
        if !(MIN_FORMAT_VERSION..=FORMAT_VERSION).contains(&version) {
            return Err(format_error(
                &path,
                format!(
                    "texture file format version {version} is not supported (expected \
                     {MIN_FORMAT_VERSION} to {FORMAT_VERSION})"
                ),
            ));
        }
        if count as usize != self.manifest.textures.len() {
            return Err(format_error(
                &path,
                format!(
                    "holds {count} textures, the manifest lists {}",
                    self.manifest.textures.len()
                ),
            ));
        }
        // Offsets and sizes were checked against the file size when the manifest was read.
        Ok(self
            .manifest
            .textures
            .iter()
            .map(|t| {
                let b = usize::try_from(t.offset)
                    .ok()
                    .zip(usize::try_from(t.offset.saturating_add(t.bytes)).ok())
                    .and_then(|(start, end)| bytes.get(start..end))
                    .unwrap_or_default();
                Texture {
                    name: t.name.clone(),
                    width: t.width,
                    height: t.height,
                    texels: b
                        .chunks_exact(4)
                        .map(|p| [p[0], p[1], p[2], p[3]])
                        .collect(),
                    sampler: t.sampler.into(),
                }
            })
            .collect())
    }

    /// Check every file of the package: each domain loads (size, header, checksum,
    /// indices) and the textures load. Reads the whole package.
    pub fn verify(&self) -> Result<()> {
        for d in 0..self.domain_count() {
            self.load_domain(d)?;
        }
        self.load_emitters()?;
        self.load_textures()?;
        Ok(())
    }
}

/// Read a whole file whose size and checksum the manifest gives.
fn read_checked(path: &Path, size: u64, xxh3: &str) -> Result<Vec<u8>> {
    let opened = crate::reference::open_scene_file(path)?;
    let (file, len) = (opened.file, opened.len);
    if len != size {
        return Err(format_error(
            path,
            format!(
                "{len} bytes, but the manifest records {size}: the file is truncated or replaced"
            ),
        ));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(size)
        .read_to_end(&mut bytes)
        .map_err(io_error(path))?;
    if bytes.len() as u64 != size {
        return Err(format_error(path, "the file shrank while it was read"));
    }
    let actual = super::checksum::checksum(&bytes);
    if Some(actual) != from_hex(xxh3) {
        return Err(format_error(
            path,
            format!(
                "checksum mismatch: the file hashes to {} but the manifest records {xxh3}; \
                 the file is corrupt",
                to_hex(actual)
            ),
        ));
    }
    Ok(bytes)
}

/// Decode a domain file whose size already matched `entry`; the caller verifies the
/// checksum afterwards.
fn decode_domain(
    r: &mut impl Read,
    path: &Path,
    d: u32,
    entry: &DomainEntry,
) -> Result<(Mesh, Vec<u32>)> {
    let mut header = [0u8; DOMAIN_HEADER_BYTES as usize];
    read_exact(r, &mut header, path)?;
    if header[..8] != DOMAIN_MAGIC {
        return Err(format_error(
            path,
            "not a dray domain file (bad magic); the file is corrupt",
        ));
    }
    let u32_at = |i: usize| u32::from_le_bytes(header[i..i + 4].try_into().unwrap());
    let u64_at = |i: usize| u64::from_le_bytes(header[i..i + 8].try_into().unwrap());
    let version = u32_at(8);
    if !(MIN_FORMAT_VERSION..=FORMAT_VERSION).contains(&version) {
        return Err(format_error(
            path,
            format!(
                "domain file format version {version} is not supported (expected \
                 {MIN_FORMAT_VERSION} to {FORMAT_VERSION})"
            ),
        ));
    }
    let expected = Sections::of_entry(entry).version();
    if version != expected {
        return Err(format_error(
            path,
            format!(
                "domain file format version {version}, but the manifest entry makes it \
                 version {expected}; the file is corrupt"
            ),
        ));
    }
    let (domain, vertices, triangles) = (u32_at(12), u64_at(16), u64_at(24));
    if domain != d || vertices != entry.vertices || triangles != entry.triangles {
        return Err(format_error(
            path,
            format!(
                "header says domain {domain} with {vertices} vertices and {triangles} triangles, \
                 the manifest says domain {d} with {} and {}; the file is corrupt",
                entry.vertices, entry.triangles
            ),
        ));
    }
    // Counts now equal the manifest's, whose sizes matched the file: allocations are
    // bounded by the file's real size.
    let (v, t) = (vertices as usize, triangles as usize);
    let f = |b: &[u8], i: usize| f32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap());
    let u = |b: &[u8], i: usize| u32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap());
    let positions = read_items(r, v, 12, path, |b| Vec3::new(f(b, 0), f(b, 1), f(b, 2)))?;
    let normals = read_items(r, v, 12, path, |b| Vec3::new(f(b, 0), f(b, 1), f(b, 2)))?;
    let tangents = if entry.no_tangents {
        vec![Vec4::ZERO; v]
    } else {
        read_items(r, v, 16, path, |b| {
            Vec4::new(f(b, 0), f(b, 1), f(b, 2), f(b, 3))
        })?
    };
    let uvs = if entry.no_uvs {
        vec![Vec2::ZERO; v]
    } else {
        read_items(r, v, 8, path, |b| Vec2::new(f(b, 0), f(b, 1)))?
    };
    let uvs2 = if entry.uvs2 {
        read_items(r, v, 8, path, |b| Vec2::new(f(b, 0), f(b, 1)))?
    } else {
        Vec::new()
    };
    let colors = if entry.colors {
        read_items(r, v, 16, path, |b| {
            Vec4::new(f(b, 0), f(b, 1), f(b, 2), f(b, 3))
        })?
    } else {
        Vec::new()
    };
    let indices = read_items(r, t, 12, path, |b| [u(b, 0), u(b, 1), u(b, 2)])?;
    let material = read_items(r, t, 4, path, |b| u(b, 0))?;
    let ids = read_items(r, t, 4, path, |b| u(b, 0))?;
    Ok((
        Mesh {
            positions,
            normals,
            tangents,
            uvs,
            uvs2,
            colors,
            indices,
            material,
        },
        ids,
    ))
}

fn read_exact(r: &mut impl Read, buf: &mut [u8], path: &Path) -> Result<()> {
    r.read_exact(buf).map_err(|e| {
        if e.kind() == io::ErrorKind::UnexpectedEof {
            format_error(path, "the file ends early: it is truncated")
        } else {
            io_error(path)(e)
        }
    })
}

/// Read `count` items of `size` bytes each, decoding with `f`.
fn read_items<T>(
    r: &mut impl Read,
    count: usize,
    size: usize,
    path: &Path,
    f: impl Fn(&[u8]) -> T,
) -> Result<Vec<T>> {
    let mut out = Vec::with_capacity(count);
    let per_chunk = (64 * 1024 / size).max(1);
    let mut buf = vec![0u8; per_chunk * size];
    let mut left = count;
    while left > 0 {
        let k = left.min(per_chunk);
        let b = &mut buf[..k * size];
        read_exact(r, b, path)?;
        out.extend(b.chunks_exact(size).map(&f));
        left -= k;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_round_trip() {
        let t = SourceTriangle {
            id: 77,
            material: 3,
            positions: [Vec3::new(1.0, 2.0, 3.0), Vec3::X, -Vec3::Y],
            normals: [Vec3::Z; 3],
            tangents: [Vec4::new(1.0, 0.0, 0.0, -1.0); 3],
            uvs: [Vec2::new(0.25, 0.75), Vec2::ZERO, Vec2::ONE],
            uvs2: [Vec2::ZERO; 3],
            colors: [Vec4::ONE; 3],
        };
        let mut b = Vec::new();
        encode_record(&t, false, false, &mut b);
        assert_eq!(b.len(), record_bytes(false, false));
        assert_eq!(b.len(), 152, "a one-set record is what it was");
        assert_eq!(decode_record(&b, false, false), t);
        let t = SourceTriangle {
            colors: [Vec4::new(0.5, 0.25, 1.0, 0.75), Vec4::ONE, Vec4::ZERO],
            ..t
        };
        b.clear();
        encode_record(&t, true, false, &mut b);
        assert_eq!(b.len(), record_bytes(true, false));
        assert_eq!(decode_record(&b, true, false), t);
        // The second UV set, alone and with colours.
        let t = SourceTriangle {
            uvs2: [Vec2::new(0.5, 0.125), Vec2::ONE, Vec2::new(-1.0, 2.0)],
            ..t
        };
        for colors in [false, true] {
            let t = SourceTriangle {
                colors: if colors { t.colors } else { [Vec4::ONE; 3] },
                ..t
            };
            b.clear();
            encode_record(&t, colors, true, &mut b);
            assert_eq!(b.len(), record_bytes(colors, true));
            assert_eq!(decode_record(&b, colors, true), t, "colours {colors}");
        }
    }

    #[test]
    fn package_file_names() {
        assert!(is_package_file("manifest.json"));
        assert!(is_package_file("domain-00017.bin"));
        assert!(is_package_file(".domain-00017.spill"));
        assert!(is_package_file("textures.bin"));
        assert!(!is_package_file("domain-17.bin"));
        assert!(!is_package_file("notes.txt"));
    }

    #[test]
    fn file_size_formula_overflows_safely() {
        let plain = Sections {
            colors: false,
            uvs2: false,
            ..Sections::ALL
        };
        let bare = Sections {
            tangents: false,
            uvs: false,
            colors: false,
            uvs2: false,
        };
        assert_eq!(domain_file_bytes(0, 0, plain), Some(32));
        assert_eq!(domain_file_bytes(3, 1, plain), Some(32 + 144 + 20));
        assert_eq!(
            domain_file_bytes(3, 1, Sections::ALL),
            Some(32 + 144 + 48 + 24 + 20)
        );
        assert_eq!(domain_file_bytes(3, 1, bare), Some(32 + 72 + 20));
        assert_eq!(domain_file_bytes(u64::MAX / 2, 1, plain), None);
        assert_eq!(domain_file_bytes(u64::MAX / 24, 1, bare), None);
    }
}
