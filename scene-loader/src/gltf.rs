//! glTF 2.0 import (`.gltf` with external or embedded resources, and `.glb`).
//!
//! The `gltf` crate parses and validates the JSON, but dray resolves buffers and images
//! and decodes accessors itself: the crate's importer and accessor readers give generic
//! messages and can panic or silently stop on malformed data (short buffers, bad strides,
//! zero counts), while a renderer fed arbitrary files must answer with an error that
//! names the file, the URI, the mesh and the primitive at fault.
//!
//! The node hierarchy of the chosen scene is flattened into one world-space mesh with
//! instancing expanded; every primitive passes through [`crate::validate::add_primitive`].

use std::borrow::Cow;
use std::panic::AssertUnwindSafe;
use std::path::Path;

use dray_core::camera::{Camera, Projection};
use dray_core::light::Light;
use dray_core::material::{
    AlphaMode, Anisotropy, Clearcoat, Iridescence, Material, Sheen, TexRef, Volume,
};
use dray_core::scene::Scene;
use dray_core::texture::{Filter, Sampler, Texture, Wrap};
use glam::{DMat3, DMat4, DQuat, DVec3, Vec2, Vec3, Vec4};
use gltf::json;
use gltf::json::validation::Checked;

use crate::animation::{AnimationTime, Channel, Interpolation, NodePose, Pose, Target};
use crate::error::{Result, SceneError};
use crate::gltf_ext::{self, SlotJson, TextureTransform};
use crate::validate::{self, Origin, Primitive};

/// Extensions dray understands. A file that *requires* anything else is refused; a file
/// that merely *uses* something else loads with a warning (the extension is ignored).
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_emissive_strength",
    "KHR_materials_transmission",
    "KHR_materials_ior",
    "KHR_materials_specular",
    "KHR_materials_unlit",
    "KHR_materials_clearcoat",
    "KHR_materials_sheen",
    "KHR_materials_anisotropy",
    "KHR_materials_volume",
    "KHR_materials_iridescence",
    "KHR_materials_dispersion",
    "KHR_texture_transform",
    "KHR_mesh_quantization",
    "EXT_meshopt_compression",
];

/// Deeper hierarchies than this are treated as cycles (the JSON validator does not
/// detect a node that is its own ancestor, and walking one would never end).
const MAX_NODE_DEPTH: usize = 1024;

/// Upper bound on node visits while expanding instances, so a small file whose nodes
/// share children exponentially cannot make the loader run out of memory.
const MAX_NODE_VISITS: usize = 1 << 22;

/// Upper bound on components of an accessor with no buffer view (all zeros, possibly
/// patched by sparse values); without it a tiny file could ask for a huge allocation.
const MAX_ZERO_FILLED_COMPONENTS: usize = 1 << 28;

/// Load a glTF 2.0 file (`.gltf` or `.glb`) into a flattened world-space [`Scene`].
///
/// The default scene is used (or the first scene; with no scenes, every root node).
/// Buffers and images are relative paths that must resolve inside the file's folder, to
/// regular files (see [`crate::reference`]; a buffer is read no further than its
/// `byteLength`); `data:` URIs and the GLB binary chunk are supported, other schemes
/// (`file:` included) and absolute paths are refused. Problems in the file are errors that name the file and,
/// where they apply, the URI, mesh and primitive; ignored features are listed in
/// `scene.stats.warnings`.
pub fn load_gltf(path: &Path) -> Result<Scene> {
    load_gltf_at(path, None)
}

/// [`load_gltf`] with the file's animation sampled at `time` (node transforms and morph
/// weights as they are at that moment; see [`crate::animation`]); `None` is the rest
/// pose the file shows.
pub fn load_gltf_at(path: &Path, time: Option<&AnimationTime>) -> Result<Scene> {
    // The loader checks every offset itself, but it still calls into the `gltf` crate,
    // whose validator and wrappers index and unwrap internally. A panic there on some
    // input we did not foresee must not take down a render node: it becomes an error
    // naming the file.
    match std::panic::catch_unwind(AssertUnwindSafe(|| load_unguarded(path, time))) {
        Ok(result) => result,
        Err(payload) => {
            let what = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".to_string());
            Err(format_error(
                path,
                format!("internal error while reading the glTF file: {what}"),
            ))
        }
    }
}

/// The bytes loading the glTF file at `path` decodes beyond the file itself: what its
/// `EXT_meshopt_compression` views declare (see [`crate::meshopt::declared_decoded_bytes`]).
/// Only the JSON is read (a GLB's first chunk), so admission can count a decompression
/// bomb before anything is decoded. 0 for a file that is not glTF or cannot be read: the
/// load itself reports those.
pub fn declared_expansion(path: &Path) -> u64 {
    json_only(path)
        .map(|root| crate::meshopt::declared_decoded_bytes(&root))
        .unwrap_or(0)
}

/// The names of the animations of the glTF file at `path` (`None` for an unnamed one), in
/// file order, from its JSON alone (a GLB's first chunk), so SubmitJob can refuse an
/// animation the file lacks before it answers, without loading the scene. `None` for a
/// file that is not glTF or cannot be read: the load itself reports those.
pub fn animation_names(path: &Path) -> Option<Vec<Option<String>>> {
    let root = json_only(path)?;
    let Some(list) = root.get("animations") else {
        return Some(Vec::new());
    };
    let list = list.as_array()?;
    Some(
        list.iter()
            .map(|a| a.get("name").and_then(|n| n.as_str()).map(str::to_string))
            .collect(),
    )
}

/// The JSON of the glTF file at `path` (a GLB's first chunk), parsed but not checked;
/// `None` when it cannot be read or parsed.
fn json_only(path: &Path) -> Option<serde_json::Value> {
    use std::io::Read;
    let Ok(opened) = crate::reference::open_scene_file(path) else {
        return None;
    };
    let mut file = opened.file;
    let mut head = [0u8; 20];
    let json = match file.read_exact(&mut head) {
        Ok(()) if &head[..4] == b"glTF" => {
            let len = u32::from_le_bytes([head[12], head[13], head[14], head[15]]);
            let mut json = Vec::new();
            if (&mut file)
                .take(u64::from(len))
                .read_to_end(&mut json)
                .is_err()
            {
                return None;
            }
            json
        }
        _ => crate::reference::read_scene_file(path).ok()?,
    };
    let text = json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(&json);
    serde_json::from_slice::<serde_json::Value>(text).ok()
}

fn format_error(path: &Path, message: impl Into<String>) -> SceneError {
    SceneError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn load_unguarded(path: &Path, time: Option<&AnimationTime>) -> Result<Scene> {
    let bytes = crate::reference::read_scene_file(path)?;
    // serde_json refuses a UTF-8 byte order mark, which some exporters write. The GLB
    // check comes after, on what the crate will see (a mark before "glTF" must not
    // smuggle a bad header past it).
    let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(&bytes);
    check_glb_header(text).map_err(|m| format_error(path, m))?;
    let gltf::Gltf { document, blob } = gltf::Gltf::from_slice_without_validation(text)
        .map_err(|e| format_error(path, format!("not a valid glTF file: {}", bounded(&e))))?;
    let mut root = document.into_json();

    for ext in &root.extensions_required {
        if !SUPPORTED_EXTENSIONS.contains(&ext.as_str()) {
            return Err(SceneError::UnsupportedExtension {
                path: path.to_path_buf(),
                extension: ext.clone(),
            });
        }
    }
    let mut warnings = Vec::new();
    for ext in &root.extensions_used {
        if !SUPPORTED_EXTENSIONS.contains(&ext.as_str()) {
            warnings.push(format!(
                "{}: extension {ext} is used but not supported; it is ignored",
                path.display()
            ));
        }
    }
    precheck(&root).map_err(|m| format_error(path, m))?;
    // The crate's validator rejects required extensions it does not know itself (such as
    // KHR_materials_specular, which it parses but does not list); dray has already
    // checked the required list against what it supports, so hide the rest from it.
    root.extensions_required
        .retain(|e| json::extensions::ENABLED_EXTENSIONS.contains(&e.as_str()));
    let document = gltf::Document::from_json(root)
        .map_err(|e| format_error(path, format!("invalid glTF: {}", bounded(&e))))?;

    let buffers = load_buffers(path, document.as_json(), blob)?;
    let decoded_views = decode_meshopt_views(path, document.as_json(), &buffers)?;

    let mut loader = Loader {
        path,
        doc: &document,
        root: document.as_json(),
        buffers,
        decoded_views,
        scene: Scene {
            name: path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            ..Scene::default()
        },
        default_material: None,
        uv_sets: Vec::new(),
        pose: Pose::default(),
    };
    for w in warnings {
        loader.warn(w);
    }
    if let Some(time) = time {
        loader.pose = loader.pose_at(time)?;
    }
    loader.load()?;
    if loader.scene.mesh.triangle_count() == 0 {
        return Err(SceneError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(loader.scene)
}

/// Reject GLB headers the `gltf` crate would mishandle: it subtracts the header size
/// from the declared length without checking, which panics (debug) or wraps (release).
fn check_glb_header(bytes: &[u8]) -> std::result::Result<(), String> {
    if !bytes.starts_with(b"glTF") {
        return Ok(());
    }
    let word = |at: usize| -> Option<u32> {
        let b: [u8; 4] = bytes.get(at..at + 4)?.try_into().ok()?;
        Some(u32::from_le_bytes(b))
    };
    let (Some(version), Some(length)) = (word(4), word(8)) else {
        return Err("GLB file is shorter than its 12-byte header".into());
    };
    if version != 2 {
        return Err(format!(
            "GLB version {version} is not supported (expected 2)"
        ));
    }
    // Header (12 bytes) plus at least the JSON chunk header (8 bytes).
    if length < 20 || length as usize > bytes.len() {
        return Err(format!(
            "GLB header declares {length} bytes but the file has {} (truncated or corrupt)",
            bytes.len()
        ));
    }
    Ok(())
}

/// Checks the crate's validator relies on without making them itself: it indexes the
/// accessor list with each primitive's POSITION index before checking that index.
fn precheck(root: &json::Root) -> std::result::Result<(), String> {
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            for (semantic, index) in &prim.attributes {
                if index.value() >= root.accessors.len() {
                    let name = match semantic {
                        Checked::Valid(s) => s.to_string(),
                        Checked::Invalid => "attribute".to_string(),
                    };
                    return Err(format!(
                        "mesh {m} primitive {p}: {name} refers to accessor {} but there are \
                         only {} accessors",
                        index.value(),
                        root.accessors.len()
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Read every buffer: the GLB binary chunk, a `data:` URI or a file in the glTF's folder,
/// no further than its `byteLength`.
fn load_buffers(path: &Path, root: &json::Root, mut blob: Option<Vec<u8>>) -> Result<Vec<Vec<u8>>> {
    let mut out = Vec::with_capacity(root.buffers.len());
    for (i, buffer) in root.buffers.iter().enumerate() {
        let what = match &buffer.uri {
            Some(uri) => format!("buffer {i} ({})", display_uri(uri)),
            None => format!("buffer {i} (GLB binary chunk)"),
        };
        let declared = usize::try_from(buffer.byte_length.0).map_err(|_| {
            format_error(
                path,
                format!("{what}: byteLength {} is too large", buffer.byte_length.0),
            )
        })?;
        let meshopt_ext = buffer
            .extensions
            .as_ref()
            .and_then(|e| e.others.get("EXT_meshopt_compression"));
        if buffer.uri.is_none() && crate::meshopt::is_fallback(meshopt_ext) {
            // Its views are all compressed elsewhere: nothing to read.
            out.push(Vec::new());
            continue;
        }
        let mut data = match &buffer.uri {
            Some(uri) => read_uri(path, uri, Some(buffer.byte_length.0))
                .map_err(|m| format_error(path, format!("{what}: {m}")))?,
            // Only the first buffer may refer to the GLB binary chunk.
            None => match (i, blob.take()) {
                (0, Some(b)) => b,
                _ => {
                    return Err(format_error(
                        path,
                        format!("{what}: buffer has no uri and the file has no GLB binary chunk"),
                    ));
                }
            },
        };
        if data.len() < declared {
            return Err(format_error(
                path,
                format!(
                    "{what}: has {} bytes but its byteLength is {declared} (truncated file?)",
                    data.len()
                ),
            ));
        }
        // Accessors may only read within byteLength; anything past it (GLB padding) goes.
        data.truncate(declared);
        out.push(data);
    }
    Ok(out)
}

/// Decode every buffer view stored with `EXT_meshopt_compression` (see
/// [`crate::meshopt`]); `None` for the views stored plainly.
fn decode_meshopt_views(
    path: &Path,
    root: &json::Root,
    buffers: &[Vec<u8>],
) -> Result<Vec<Option<Vec<u8>>>> {
    let mut out = Vec::with_capacity(root.buffer_views.len());
    let buffer_bytes = buffers
        .iter()
        .map(Vec::len)
        .fold(0usize, usize::saturating_add);
    let mut budget = crate::meshopt::DecodeBudget::for_buffers(buffer_bytes);
    for (i, view) in root.buffer_views.iter().enumerate() {
        let Some(ext) = view
            .extensions
            .as_ref()
            .and_then(|e| e.others.get("EXT_meshopt_compression"))
        else {
            out.push(None);
            continue;
        };
        crate::cancel::check()?;
        let what = format!("buffer view {i} (EXT_meshopt_compression)");
        let fail = |m: String| format_error(path, format!("{what}: {m}"));
        let c = crate::meshopt::Compressed::from_json(ext).map_err(fail)?;
        let source = buffers.get(c.buffer).ok_or_else(|| {
            fail(format!(
                "refers to buffer {}, which does not exist",
                c.buffer
            ))
        })?;
        let data = c
            .byte_offset
            .checked_add(c.byte_length)
            .and_then(|end| source.get(c.byte_offset..end))
            .ok_or_else(|| {
                fail(format!(
                    "bytes {}..+{} lie outside buffer {} ({} bytes)",
                    c.byte_offset,
                    c.byte_length,
                    c.buffer,
                    source.len()
                ))
            })?;
        out.push(Some(c.decode(data, &mut budget).map_err(fail)?));
    }
    Ok(out)
}

/// A URI shortened for messages.
fn display_uri(uri: &str) -> String {
    crate::reference::display_reference(uri)
}

/// An error from a parser, at most a few hundred characters: serde's messages quote the
/// values they reject, which can be as long as the file.
fn bounded(e: &dyn std::fmt::Display) -> String {
    const MAX: usize = 300;
    let text = e.to_string().replace(['\n', '\r'], " ");
    if text.chars().count() <= MAX {
        text
    } else {
        let head: String = text.chars().take(MAX).collect();
        format!("{head}…")
    }
}

/// Resolve a buffer or image URI: a `data:` URI, or a relative path that must stay
/// inside the folder of the scene file `scene` and name a regular file, read no further
/// than `limit` bytes when given (a buffer's byteLength). Other schemes (`file:`,
/// `http:`, ...) and absolute paths are refused. Messages never quote file contents.
fn read_uri(scene: &Path, uri: &str, limit: Option<u64>) -> std::result::Result<Vec<u8>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (header, payload) = rest
            .split_once(',')
            .ok_or_else(|| "data URI has no ',' before its payload".to_string())?;
        return if header.ends_with(";base64") {
            decode_base64(payload).map_err(|m| format!("data URI: {m}"))
        } else {
            percent_decode(payload).map_err(|m| format!("data URI: {m}"))
        };
    }
    match uri_scheme(uri) {
        Some(scheme) if scheme.eq_ignore_ascii_case("file") => {
            return Err(
                "file: URIs are not allowed (a scene may only refer to files in its own \
                 folder, by relative path)"
                    .to_string(),
            );
        }
        Some(scheme) => {
            return Err(format!(
                "URI scheme {} is not supported (only relative paths and data: URIs)",
                display_uri(scheme)
            ));
        }
        None => {}
    }
    let relative = utf8(percent_decode(uri)?)?;
    let opened =
        crate::reference::open_in_scene_folder(scene, &relative).map_err(|e| e.message())?;
    let len = opened.len;
    if let Some(declared) = limit
        && len < declared
    {
        return Err(format!(
            "file has {len} bytes but the buffer's byteLength is {declared} (truncated file?)"
        ));
    }
    opened
        .read_at_most(limit.unwrap_or(len))
        .map_err(|e| format!("cannot read: {}", e.kind()))
}

fn utf8(bytes: Vec<u8>) -> std::result::Result<String, String> {
    String::from_utf8(bytes).map_err(|_| "URI is not valid UTF-8 after percent-decoding".into())
}

/// The scheme of an absolute URI (RFC 3986: a letter, then letters, digits, `+-.`),
/// or `None` for a relative reference. One-letter schemes are taken as Windows drives.
fn uri_scheme(uri: &str) -> Option<&str> {
    let (scheme, _) = uri.split_once(':')?;
    let mut chars = scheme.chars();
    let first = chars.next()?;
    let ok = first.is_ascii_alphabetic()
        && chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'));
    (ok && scheme.len() > 1).then_some(scheme)
}

fn percent_decode(s: &str) -> std::result::Result<Vec<u8>, String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        if b == b'%' {
            let hex = |at: usize| bytes.get(at).and_then(|&c| (c as char).to_digit(16));
            match (hex(i + 1), hex(i + 2)) {
                (Some(h), Some(l)) => out.push((h * 16 + l) as u8),
                _ => return Err(format!("malformed percent-encoding at byte {i}")),
            }
            i += 3;
        } else {
            out.push(b);
            i += 1;
        }
    }
    Ok(out)
}

/// Standard (and URL-safe) base64, padding optional, ASCII whitespace ignored. Written
/// here rather than adding a dependency for one small function.
fn decode_base64(s: &str) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(s.len() / 4 * 3 + 3);
    let mut acc: u32 = 0;
    let mut bits = 0u32;
    let mut digits = 0usize;
    for (i, c) in s.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => break,
            c if c.is_ascii_whitespace() => continue,
            _ => return Err(format!("invalid base64 character {:?} at {i}", c as char)),
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        digits += 1;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if digits % 4 == 1 {
        return Err("base64 payload is truncated".into());
    }
    Ok(out)
}

/// Conversion from a decoded accessor component.
trait FromComponent: Copy + Default {
    fn from_component(v: f64) -> Self;
}

impl FromComponent for f32 {
    fn from_component(v: f64) -> Self {
        v as f32
    }
}

impl FromComponent for u32 {
    fn from_component(v: f64) -> Self {
        // Only reached with integer component types, whose values f64 holds exactly.
        v as u32
    }
}

/// One component at the start of `bytes`, normalised to [0,1] / [-1,1] if asked.
fn read_component(
    bytes: &[u8],
    ty: json::accessor::ComponentType,
    normalized: bool,
) -> Option<f64> {
    use json::accessor::ComponentType as C;
    fn arr<const N: usize>(b: &[u8]) -> Option<[u8; N]> {
        b.get(..N)?.try_into().ok()
    }
    let norm = |v: f64, max: f64| {
        if normalized { (v / max).max(-1.0) } else { v }
    };
    Some(match ty {
        C::I8 => norm(f64::from(i8::from_le_bytes(arr(bytes)?)), 127.0),
        C::U8 => norm(f64::from(u8::from_le_bytes(arr(bytes)?)), 255.0),
        C::I16 => norm(f64::from(i16::from_le_bytes(arr(bytes)?)), 32767.0),
        C::U16 => norm(f64::from(u16::from_le_bytes(arr(bytes)?)), 65535.0),
        C::U32 => f64::from(u32::from_le_bytes(arr(bytes)?)),
        C::F32 => f64::from(f32::from_le_bytes(arr(bytes)?)),
    })
}

/// One mesh primitive decoded into local-space arrays, ready to be instanced.
struct DecodedPrimitive {
    index: usize,
    positions: Vec<Vec3>,
    normals: Option<Vec<Vec3>>,
    tangents: Option<Vec<Vec4>>,
    uvs: Option<Vec<Vec2>>,
    /// The second UV set, read only when the material's textures name two.
    uvs2: Option<Vec<Vec2>>,
    /// The source's numbers of `uvs` and `uvs2` (`TEXCOORD_n`).
    uv_sets: [u32; 2],
    /// `COLOR_0` as linear RGBA.
    colors: Option<Vec<Vec4>>,
    /// Triangle list (strips and fans already converted).
    indices: Vec<u32>,
    material: u32,
}

/// The UV sets a material's textures read: every slot reads `first` except those marked
/// [`TexRef::second_uv`], which read `second`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct UvSets {
    first: u32,
    second: Option<u32>,
}

/// Every texture slot of `m` in use, named as in glTF, in [`Material::texture_refs`]'s
/// order.
fn named_slots(m: &mut Material) -> Vec<(&'static str, &mut TexRef)> {
    let Material {
        base_color_tex,
        metallic_roughness_tex,
        normal_tex,
        emissive_tex,
        transmission_tex,
        specular_tex,
        specular_color_tex,
        clearcoat,
        sheen,
        anisotropy,
        iridescence,
        ..
    } = m;
    let mut slots = vec![
        ("baseColorTexture", base_color_tex.as_mut()),
        ("metallicRoughnessTexture", metallic_roughness_tex.as_mut()),
        ("normalTexture", normal_tex.as_mut()),
        ("emissiveTexture", emissive_tex.as_mut()),
        ("transmissionTexture", transmission_tex.as_mut()),
        ("specularTexture", specular_tex.as_mut()),
        ("specularColorTexture", specular_color_tex.as_mut()),
    ];
    if let Some(c) = clearcoat {
        slots.push(("clearcoatTexture", c.tex.as_mut()));
        slots.push(("clearcoatRoughnessTexture", c.roughness_tex.as_mut()));
        slots.push(("clearcoatNormalTexture", c.normal_tex.as_mut()));
    }
    if let Some(sh) = sheen {
        slots.push(("sheenColorTexture", sh.color_tex.as_mut()));
        slots.push(("sheenRoughnessTexture", sh.roughness_tex.as_mut()));
    }
    if let Some(a) = anisotropy {
        slots.push(("anisotropyTexture", a.tex.as_mut()));
    }
    if let Some(ir) = iridescence {
        slots.push(("iridescenceTexture", ir.tex.as_mut()));
        slots.push(("iridescenceThicknessTexture", ir.thickness_tex.as_mut()));
    }
    slots
        .into_iter()
        .filter_map(|(name, t)| Some((name, t?)))
        .collect()
}

/// An image decoded to RGBA8, shared by the textures that use it.
#[derive(Clone)]
struct DecodedImage {
    width: u32,
    height: u32,
    texels: std::sync::Arc<[[u8; 4]]>,
}

/// Everything the node walk found.
#[derive(Default)]
struct Placements {
    /// Per mesh instance: mesh index, world matrix, and the node's morph weights (which
    /// override the mesh's).
    meshes: Vec<(usize, DMat4, Option<Vec<f32>>)>,
    /// Per skinned mesh instance: its node, mesh, skin and morph weights (the node's
    /// transform does not apply to a skin).
    skinned: Vec<SkinnedInstance>,
    /// Every visited node's world matrix, for the joints of the skins.
    node_world: std::collections::HashMap<usize, DMat4>,
}

/// A mesh placed by a skin ([`crate::skin`]).
struct SkinnedInstance {
    node_name: String,
    mesh: usize,
    skin: usize,
    weights: Option<Vec<f32>>,
}

struct Loader<'a> {
    path: &'a Path,
    doc: &'a gltf::Document,
    root: &'a json::Root,
    buffers: Vec<Vec<u8>>,
    /// Per buffer view, its bytes when `EXT_meshopt_compression` stored it compressed.
    decoded_views: Vec<Option<Vec<u8>>>,
    scene: Scene,
    /// Index of the default material once a primitive without one has needed it.
    default_material: Option<u32>,
    /// Per glTF material, the UV sets its triangles store ([`Loader::choose_uv_sets`]).
    uv_sets: Vec<UvSets>,
    /// The animated nodes' transforms and weights at the requested time (empty: the
    /// file's rest pose).
    pose: Pose,
}

impl Loader<'_> {
    /// Record a warning in `scene.stats.warnings`, once: the same problem met again (in
    /// another material, primitive or instance) adds nothing. The loader does not log
    /// it; whoever loads the scene prints the list (the CLI) or forwards it (the
    /// coordinator's job summary), so each warning reaches the user exactly once.
    fn warn(&mut self, message: String) {
        if !self.scene.stats.warnings.contains(&message) {
            self.scene.stats.warnings.push(message);
        }
    }

    fn error(&self, message: impl Into<String>) -> SceneError {
        format_error(self.path, message)
    }

    fn load(&mut self) -> Result<()> {
        self.load_textures()?;
        self.load_materials();
        let mut placements = self.walk_nodes()?;
        let skinned = std::mem::take(&mut placements.skinned);
        let node_world = std::mem::take(&mut placements.node_world);
        self.load_meshes(placements)?;
        for instance in &skinned {
            self.load_skinned(instance, &node_world)?;
        }
        Ok(())
    }

    // ----- textures --------------------------------------------------------------------

    /// One [`Texture`] per glTF texture, in order, so a material's texture index can be
    /// used as is. Each image is decoded once even when several textures share it.
    fn load_textures(&mut self) -> Result<()> {
        let mut images: Vec<Option<DecodedImage>> = vec![None; self.root.images.len()];
        let mut textures = Vec::with_capacity(self.root.textures.len());
        for (t, texture) in self.root.textures.iter().enumerate() {
            let image_index = texture.source.value();
            let slot = images.get_mut(image_index).ok_or_else(|| {
                self.error(format!(
                    "texture {t} refers to image {image_index}, which does not exist"
                ))
            })?;
            if slot.is_none() {
                *slot = Some(self.decode_image(image_index)?);
            }
            let Some(DecodedImage {
                width,
                height,
                texels,
            }) = slot.clone()
            else {
                return Err(self.error(format!("texture {t}: image {image_index} was not decoded")));
            };
            let image = self.root.images.get(image_index);
            let name = texture
                .name
                .clone()
                .or_else(|| image.and_then(|i| i.name.clone()))
                .or_else(|| {
                    image
                        .and_then(|i| i.uri.as_deref())
                        .filter(|u| !u.starts_with("data:"))
                        .map(str::to_string)
                })
                .unwrap_or_else(|| format!("texture #{t}"));
            let sampler = texture
                .sampler
                .and_then(|s| self.root.samplers.get(s.value()))
                .map(convert_sampler)
                .unwrap_or_default();
            textures.push(Texture {
                name,
                width,
                height,
                texels,
                sampler,
            });
        }
        self.scene.textures = textures;
        Ok(())
    }

    fn decode_image(&self, index: usize) -> Result<DecodedImage> {
        crate::cancel::check()?;
        let image = self
            .root
            .images
            .get(index)
            .ok_or_else(|| self.error(format!("image {index} does not exist")))?;
        let (what, bytes): (String, Cow<'_, [u8]>) = match (&image.uri, image.buffer_view) {
            (Some(uri), _) => {
                let what = format!("image {index} ({})", display_uri(uri));
                let bytes = read_uri(self.path, uri, None)
                    .map_err(|m| self.error(format!("{what}: {m}")))?;
                (what, Cow::Owned(bytes))
            }
            (None, Some(view)) => {
                let what = format!("image {index} (buffer view {})", view.value());
                let (bytes, _) = self
                    .view_bytes(view.value())
                    .map_err(|m| self.error(format!("{what}: {m}")))?;
                (what, Cow::Borrowed(bytes))
            }
            (None, None) => {
                return Err(self.error(format!("image {index} has neither a uri nor a bufferView")));
            }
        };
        let decoded = image::load_from_memory(&bytes)
            .map_err(|e| self.error(format!("{what}: cannot decode image: {e}")))?
            .into_rgba8();
        let (width, height) = decoded.dimensions();
        let texels = decoded
            .into_raw()
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        Ok(DecodedImage {
            width,
            height,
            texels,
        })
    }

    // ----- materials -------------------------------------------------------------------

    /// Convert every glTF material, in order, so glTF material `i` is scene material `i`.
    fn load_materials(&mut self) {
        let doc = self.doc;
        for m in doc.materials() {
            let name = m
                .name()
                .map(str::to_string)
                .unwrap_or_else(|| format!("material #{}", m.index().unwrap_or(0)));
            let pbr = m.pbr_metallic_roughness();
            let mut mat = Material {
                name: name.clone(),
                base_color: Vec4::from(pbr.base_color_factor()),
                metallic: pbr.metallic_factor(),
                roughness: pbr.roughness_factor(),
                emissive: Vec3::from(m.emissive_factor()) * m.emissive_strength().unwrap_or(1.0),
                alpha_mode: match m.alpha_mode() {
                    gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
                    gltf::material::AlphaMode::Mask => AlphaMode::Mask {
                        cutoff: m.alpha_cutoff().unwrap_or(0.5),
                    },
                    gltf::material::AlphaMode::Blend => AlphaMode::Blend,
                },
                double_sided: m.double_sided(),
                ..Material::default()
            };
            mat.base_color_tex = self.tex_ref(&name, "baseColorTexture", pbr.base_color_texture());
            mat.metallic_roughness_tex = self.tex_ref(
                &name,
                "metallicRoughnessTexture",
                pbr.metallic_roughness_texture(),
            );
            if let Some(normal) = m.normal_texture() {
                mat.normal_scale = normal.scale();
                mat.normal_tex = self.tex_slot(
                    &name,
                    "normalTexture",
                    normal.texture().index(),
                    normal.tex_coord(),
                    TextureTransform::from_extensions(normal.extensions()),
                );
            }
            mat.emissive_tex = self.tex_ref(&name, "emissiveTexture", m.emissive_texture());
            if let Some(t) = m.transmission() {
                mat.transmission = t.transmission_factor();
                mat.transmission_tex =
                    self.tex_ref(&name, "transmissionTexture", t.transmission_texture());
            }
            if let Some(ior) = m.ior() {
                mat.ior = ior;
            }
            if let Some(s) = m.specular() {
                mat.specular = s.specular_factor();
                mat.specular_tex = self.tex_ref(&name, "specularTexture", s.specular_texture());
                mat.specular_color = Vec3::from(s.specular_color_factor());
                mat.specular_color_tex =
                    self.tex_ref(&name, "specularColorTexture", s.specular_color_texture());
            }
            if let Some(v) = m.volume() {
                mat.volume = Some(Volume {
                    attenuation_color: Vec3::from(v.attenuation_color()),
                    attenuation_distance: v.attenuation_distance(),
                });
            }
            if let Some(c) = m.extension_value("KHR_materials_clearcoat") {
                let c = gltf_ext::clearcoat(c);
                mat.clearcoat = Some(Clearcoat {
                    factor: c.factor,
                    tex: self.tex_json(&name, "clearcoatTexture", c.texture),
                    roughness: c.roughness,
                    roughness_tex: self.tex_json(
                        &name,
                        "clearcoatRoughnessTexture",
                        c.roughness_texture,
                    ),
                    normal_tex: self.tex_json(&name, "clearcoatNormalTexture", c.normal_texture),
                    normal_scale: c.normal_scale,
                });
            }
            if let Some(sh) = m.extension_value("KHR_materials_sheen") {
                let sh = gltf_ext::sheen(sh);
                mat.sheen = Some(Sheen {
                    color: sh.color,
                    color_tex: self.tex_json(&name, "sheenColorTexture", sh.color_texture),
                    roughness: sh.roughness,
                    roughness_tex: self.tex_json(
                        &name,
                        "sheenRoughnessTexture",
                        sh.roughness_texture,
                    ),
                });
            }
            if let Some(a) = m.extension_value("KHR_materials_anisotropy") {
                let a = gltf_ext::anisotropy(a);
                mat.anisotropy = Some(Anisotropy {
                    strength: a.strength,
                    rotation: a.rotation,
                    tex: self.tex_json(&name, "anisotropyTexture", a.texture),
                });
            }
            if let Some(ir) = m.extension_value("KHR_materials_iridescence") {
                let ir = gltf_ext::iridescence(ir);
                mat.iridescence = Some(Iridescence {
                    factor: ir.factor,
                    tex: self.tex_json(&name, "iridescenceTexture", ir.texture),
                    ior: ir.ior,
                    thickness_min: ir.thickness_min,
                    thickness_max: ir.thickness_max,
                    thickness_tex: self.tex_json(
                        &name,
                        "iridescenceThicknessTexture",
                        ir.thickness_texture,
                    ),
                });
            }
            if let Some(d) = m.extension_value("KHR_materials_dispersion") {
                mat.dispersion = gltf_ext::dispersion(d);
            }
            mat.unlit = m.unlit();
            let sets = self.choose_uv_sets(&mut mat);
            self.uv_sets.push(sets);
            self.scene.materials.push(mat);
        }
    }

    fn tex_ref(
        &mut self,
        material: &str,
        slot: &str,
        info: Option<gltf::texture::Info<'_>>,
    ) -> Option<TexRef> {
        let info = info?;
        let transform = info.texture_transform().map(|t| TextureTransform {
            offset: t.offset(),
            rotation: t.rotation(),
            scale: t.scale(),
            tex_coord: t.tex_coord(),
        });
        self.tex_slot(
            material,
            slot,
            info.texture().index(),
            info.tex_coord(),
            transform,
        )
    }

    /// A texture slot the `gltf` crate does not type (an extension's), from its JSON.
    fn tex_json(&mut self, material: &str, slot: &str, json: Option<SlotJson>) -> Option<TexRef> {
        let s = json?;
        if s.index >= self.scene.textures.len() {
            self.warn(format!(
                "{}: material {material:?} {slot} refers to texture {}, which does not exist; \
                 the slot is ignored",
                self.path.display(),
                s.index
            ));
            return None;
        }
        self.tex_slot(material, slot, s.index, s.tex_coord, s.transform)
    }

    /// A texture reference with `KHR_texture_transform` applied (its `texCoord`
    /// overrides the slot's, as the extension says).
    fn tex_slot(
        &mut self,
        material: &str,
        slot: &str,
        texture: usize,
        tex_coord: u32,
        transform: Option<TextureTransform>,
    ) -> Option<TexRef> {
        if transform.is_some_and(|t| t.is_malformed()) {
            self.warn(format!(
                "{}: material {material:?} {slot}: KHR_texture_transform has a value that \
                 is not finite; the transform is ignored",
                self.path.display()
            ));
        }
        Some(TexRef {
            texture: u32::try_from(texture).ok()?,
            tex_coord: transform.and_then(|t| t.tex_coord).unwrap_or(tex_coord),
            // Set by `choose_uv_sets` once every slot is known.
            second_uv: false,
            transform: transform.and_then(|t| t.affine()),
        })
    }

    /// The UV sets the mesh stores for triangles of `material`: the one its base colour
    /// reads (else its first slot's), and the first other set a slot names, if any. Each
    /// slot is marked with the one it reads ([`TexRef::second_uv`]). A slot naming a
    /// third set reads the first, with a warning: a vertex keeps at most two sets, which
    /// covers the files seen in practice (a second set serves light maps or ambient
    /// occlusion, and the Sample Models use at most two).
    fn choose_uv_sets(&mut self, material: &mut Material) -> UvSets {
        let first = material
            .base_color_tex
            .or_else(|| material.texture_refs().next())
            .map_or(0, |t| t.tex_coord);
        let mut second = None;
        let mut ignored = Vec::new();
        for (slot, t) in named_slots(material) {
            let k = t.tex_coord;
            if k == first {
                continue;
            }
            if second.is_none_or(|s| s == k) {
                second = Some(k);
                t.second_uv = true;
            } else {
                ignored.push((slot, k));
                t.tex_coord = first;
            }
        }
        for (slot, k) in ignored {
            self.warn(format!(
                "{}: material {:?} {slot} reads TEXCOORD_{k}, a third UV set after \
                 TEXCOORD_{first} and TEXCOORD_{}; dray keeps at most two per vertex, so it \
                 reads TEXCOORD_{first}",
                self.path.display(),
                material.name,
                second.unwrap_or(first),
            ));
        }
        UvSets { first, second }
    }

    fn default_material(&mut self) -> u32 {
        if let Some(i) = self.default_material {
            return i;
        }
        let i = self.scene.materials.len() as u32;
        self.scene.materials.push(Material::default());
        self.default_material = Some(i);
        i
    }

    // ----- animation -------------------------------------------------------------------

    /// The pose of the animation `time` names at `time.seconds`: its channels decoded,
    /// checked and sampled. A file without animations renders its rest pose (warned); an
    /// animation asked for by a name or index the file does not have is an error.
    fn pose_at(&mut self, time: &AnimationTime) -> Result<Pose> {
        if !time.seconds.is_finite() {
            return Err(self.error(format!(
                "animation time {} s is not a finite number",
                time.seconds
            )));
        }
        let doc = self.doc;
        let animations: Vec<gltf::Animation<'_>> = doc.animations().collect();
        if animations.is_empty() {
            if time.animation.is_some() {
                return Err(self.error("has no animations to choose from"));
            }
            self.warn(format!(
                "{}: has no animations; every time shows the rest pose",
                self.path.display()
            ));
            return Ok(Pose::default());
        }
        let label = |a: &gltf::Animation<'_>| {
            a.name()
                .map(|n| format!("{n:?}"))
                .unwrap_or_else(|| format!("#{}", a.index()))
        };
        let chosen = match time.animation.as_deref() {
            None => &animations[0],
            Some(want) => {
                let names: Vec<Option<String>> = animations
                    .iter()
                    .map(|a| a.name().map(str::to_string))
                    .collect();
                &animations[crate::animation::choose(&names, want).map_err(|m| self.error(m))?]
            }
        };
        let name = label(chosen);
        let mut channels = Vec::new();
        for channel in chosen.channels() {
            let sampler = channel.sampler();
            let target = match channel.target().property() {
                gltf::animation::Property::Translation => Target::Translation,
                gltf::animation::Property::Rotation => Target::Rotation,
                gltf::animation::Property::Scale => Target::Scale,
                gltf::animation::Property::MorphTargetWeights => Target::Weights,
            };
            let interpolation = match sampler.interpolation() {
                gltf::animation::Interpolation::Linear => Interpolation::Linear,
                gltf::animation::Interpolation::Step => Interpolation::Step,
                gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
            };
            let at = |m: String| {
                format_error(
                    self.path,
                    format!("animation {name} channel {}: {m}", channel.index()),
                )
            };
            let times: Vec<f32> = self.read_accessor(sampler.input().index(), 1).map_err(at)?;
            let dims = match target {
                Target::Translation | Target::Scale => 3,
                Target::Rotation => 4,
                Target::Weights => 1,
            };
            let values: Vec<f32> = self
                .read_accessor(sampler.output().index(), dims)
                .map_err(at)?;
            let per_key = if interpolation == Interpolation::CubicSpline {
                3
            } else {
                1
            };
            let width = match target {
                // One scalar per morph target per element.
                Target::Weights => values.len() / (times.len() * per_key).max(1),
                _ => dims,
            };
            let c = Channel {
                node: channel.target().node().index(),
                target,
                interpolation,
                times,
                values,
                width,
            };
            c.check().map_err(|e| at(e.to_string()))?;
            channels.push(c);
        }
        Ok(Pose::sample(&channels, time.seconds))
    }

    // ----- skins -----------------------------------------------------------------------

    /// Decode one skinned instance's mesh and move its vertices by its skin's joints
    /// ([`crate::skin`]): joint matrices from the joints' world transforms (as the walk,
    /// and any animation, left them) and the inverse bind matrices (identity when
    /// absent).
    fn load_skinned(
        &mut self,
        instance: &SkinnedInstance,
        node_world: &std::collections::HashMap<usize, DMat4>,
    ) -> Result<()> {
        crate::cancel::check()?;
        let doc = self.doc;
        let node = &instance.node_name;
        let skin = doc.skins().nth(instance.skin).ok_or_else(|| {
            self.error(format!(
                "node {node}: skin {} does not exist",
                instance.skin
            ))
        })?;
        let mesh = doc
            .meshes()
            .nth(instance.mesh)
            .ok_or_else(|| self.error(format!("mesh {} does not exist", instance.mesh)))?;
        let joints: Vec<gltf::Node<'_>> = skin.joints().collect();
        let inverse_bind: Vec<f32> = match skin.inverse_bind_matrices() {
            Some(acc) => self.read_accessor(acc.index(), 16).map_err(|m| {
                self.error(format!("skin {}: inverseBindMatrices: {m}", skin.index()))
            })?,
            None => Vec::new(),
        };
        if !inverse_bind.is_empty() && inverse_bind.len() < joints.len() * 16 {
            return Err(self.error(format!(
                "skin {}: {} inverse bind matrices for {} joints",
                skin.index(),
                inverse_bind.len() / 16,
                joints.len()
            )));
        }
        let mut matrices = Vec::with_capacity(joints.len());
        for (j, joint) in joints.iter().enumerate() {
            let Some(world) = node_world.get(&joint.index()) else {
                return Err(self.error(format!(
                    "skin {}: joint node {} is not in the scene",
                    skin.index(),
                    joint.index()
                )));
            };
            let ibm = inverse_bind
                .get(j * 16..j * 16 + 16)
                .map_or(DMat4::IDENTITY, |m| {
                    DMat4::from_cols_array(&std::array::from_fn(|k| f64::from(m[k])))
                });
            let m = *world * ibm;
            if !m.is_finite() {
                return Err(self.error(format!(
                    "skin {}: joint {j} has a matrix that is not finite",
                    skin.index()
                )));
            }
            matrices.push(m);
        }
        let name = mesh
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("mesh #{}", instance.mesh));
        let weights = instance.weights.as_deref().or(mesh.weights());
        let prims = self.decode_mesh(&mesh, &name, weights)?;
        for mut prim in prims {
            let Some(source) = mesh.primitives().nth(prim.index) else {
                continue;
            };
            let at = |m: String| {
                format_error(
                    self.path,
                    format!("mesh {name:?} primitive {}: {m}", prim.index),
                )
            };
            let mut influences: Vec<crate::skin::Influences> =
                vec![Vec::new(); prim.positions.len()];
            for set in 0..2 {
                let joints_acc = source.get(&gltf::mesh::Semantic::Joints(set));
                let weights_acc = source.get(&gltf::mesh::Semantic::Weights(set));
                let (Some(ja), Some(wa)) = (joints_acc, weights_acc) else {
                    if set == 0 {
                        return Err(at("skinned, but has no JOINTS_0 and WEIGHTS_0".into()));
                    }
                    break;
                };
                let js: Vec<u32> = self.read_accessor(ja.index(), 4).map_err(at)?;
                let ws: Vec<f32> = self.read_accessor(wa.index(), 4).map_err(at)?;
                if js.len() != prim.positions.len() * 4 || ws.len() != js.len() {
                    return Err(at(format!(
                        "JOINTS_{set}/WEIGHTS_{set} have {}/{} elements for {} vertices",
                        js.len() / 4,
                        ws.len() / 4,
                        prim.positions.len()
                    )));
                }
                for (v, inf) in influences.iter_mut().enumerate() {
                    for k in 0..4 {
                        inf.push((js[v * 4 + k], ws[v * 4 + k]));
                    }
                }
            }
            crate::skin::skin(
                &matrices,
                &influences,
                &mut prim.positions,
                prim.normals.as_deref_mut(),
                prim.tangents.as_deref_mut(),
            )
            .map_err(|e| at(e.to_string()))?;
            self.emit(&name, &prim, DMat4::IDENTITY)?;
        }
        Ok(())
    }

    // ----- node hierarchy --------------------------------------------------------------

    /// Walk the chosen scene, composing transforms in f64, and collect mesh instances,
    /// cameras and lights.
    fn walk_nodes(&mut self) -> Result<Placements> {
        let doc = self.doc;
        let roots: Vec<gltf::Node<'_>> = match doc.default_scene().or_else(|| doc.scenes().next()) {
            Some(scene) => scene.nodes().collect(),
            None => {
                let mut is_child = vec![false; self.root.nodes.len()];
                for node in doc.nodes() {
                    for child in node.children() {
                        if let Some(c) = is_child.get_mut(child.index()) {
                            *c = true;
                        }
                    }
                }
                doc.nodes()
                    .filter(|n| !is_child.get(n.index()).copied().unwrap_or(false))
                    .collect()
            }
        };

        let mut placements = Placements::default();
        let mut visits = 0usize;
        // Reverse so that popping visits nodes in document order.
        let mut stack: Vec<(gltf::Node<'_>, DMat4, usize)> = roots
            .into_iter()
            .rev()
            .map(|n| (n, DMat4::IDENTITY, 0))
            .collect();
        while let Some((node, parent, depth)) = stack.pop() {
            visits += 1;
            let node_name = node
                .name()
                .map(|n| format!("{n:?}"))
                .unwrap_or_else(|| format!("#{}", node.index()));
            if depth > MAX_NODE_DEPTH {
                return Err(self.error(format!(
                    "node {node_name}: hierarchy is deeper than {MAX_NODE_DEPTH} levels (does it \
                     contain a cycle?)"
                )));
            }
            if visits > MAX_NODE_VISITS {
                return Err(self.error(format!(
                    "node hierarchy expands to more than {MAX_NODE_VISITS} node instances"
                )));
            }
            let posed = self.pose.nodes.get(&node.index());
            let world = parent * local_matrix(&node, posed);
            if !world.is_finite() {
                return Err(self.error(format!(
                    "node {node_name}: transform is not finite (check matrix, rotation, scale)"
                )));
            }
            placements.node_world.entry(node.index()).or_insert(world);
            if let Some(mesh) = node.mesh() {
                match node.skin() {
                    Some(skin) => placements.skinned.push(SkinnedInstance {
                        node_name: node_name.clone(),
                        mesh: mesh.index(),
                        skin: skin.index(),
                        weights: node_weights(&node, posed),
                    }),
                    None => {
                        placements
                            .meshes
                            .push((mesh.index(), world, node_weights(&node, posed)))
                    }
                }
            }
            if let Some(camera) = node.camera() {
                self.add_camera(&camera, world);
            }
            if let Some(light) = node.light() {
                self.add_light(&light, &node_name, world);
            }
            let children: Vec<_> = node.children().collect();
            stack.extend(children.into_iter().rev().map(|c| (c, world, depth + 1)));
        }
        Ok(placements)
    }

    fn add_camera(&mut self, camera: &gltf::Camera<'_>, world: DMat4) {
        let name = camera
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("camera #{}", camera.index()));
        let (projection, znear) = match camera.projection() {
            gltf::camera::Projection::Perspective(p) => (
                Projection::Perspective {
                    yfov: p.yfov(),
                    aspect: p.aspect_ratio(),
                },
                p.znear(),
            ),
            gltf::camera::Projection::Orthographic(o) => (
                Projection::Orthographic {
                    xmag: o.xmag(),
                    ymag: o.ymag(),
                },
                o.znear(),
            ),
        };
        self.scene.cameras.push(Camera {
            name,
            transform: world.as_mat4(),
            projection,
            znear,
            lens: None,
        });
    }

    fn add_light(
        &mut self,
        light: &gltf::khr_lights_punctual::Light<'_>,
        node_name: &str,
        world: DMat4,
    ) {
        use gltf::khr_lights_punctual::Kind;
        let power = Vec3::from(light.color()) * light.intensity();
        let position = world.transform_point3(DVec3::ZERO).as_vec3();
        let direction = world
            .transform_vector3(DVec3::NEG_Z)
            .normalize_or_zero()
            .as_vec3();
        let needs_direction = !matches!(light.kind(), Kind::Point);
        if needs_direction && direction == Vec3::ZERO {
            self.warn(format!(
                "{}: light on node {node_name} has a degenerate orientation; skipped",
                self.path.display()
            ));
            return;
        }
        let light = match light.kind() {
            Kind::Directional => Light::Directional {
                direction,
                irradiance: power,
            },
            Kind::Point => Light::Point {
                position,
                intensity: power,
            },
            Kind::Spot {
                inner_cone_angle,
                outer_cone_angle,
            } => Light::Spot {
                position,
                direction,
                intensity: power,
                inner_cone: inner_cone_angle,
                outer_cone: outer_cone_angle,
            },
        };
        self.scene.lights.push(light);
    }

    // ----- meshes ----------------------------------------------------------------------

    /// Decode each instanced mesh once and emit it for each of its instances.
    fn load_meshes(&mut self, mut placements: Placements) -> Result<()> {
        // Group instances by mesh (stable, so instances keep their walk order) so each
        // mesh is decoded once and dropped before the next.
        placements.meshes.sort_by_key(|&(mesh, _, _)| mesh);
        let doc = self.doc;
        let mut start = 0;
        while let Some(&(mesh_index, _, _)) = placements.meshes.get(start) {
            let end = placements
                .meshes
                .get(start..)
                .unwrap_or_default()
                .iter()
                .position(|&(m, _, _)| m != mesh_index)
                .map_or(placements.meshes.len(), |n| start + n);
            let mesh = doc
                .meshes()
                .nth(mesh_index)
                .ok_or_else(|| self.error(format!("mesh {mesh_index} does not exist")))?;
            let name = mesh
                .name()
                .map(str::to_string)
                .unwrap_or_else(|| format!("mesh #{mesh_index}"));
            let group = placements.meshes.get(start..end).unwrap_or_default();
            // Instances whose nodes give the same morph weights (nearly always all of
            // them: node weights are rare) share one decoded copy.
            let mut emitted = vec![false; group.len()];
            for (first, (_, _, node_weights)) in group.iter().enumerate() {
                if emitted.get(first).copied().unwrap_or(true) {
                    continue;
                }
                crate::cancel::check()?;
                let weights = node_weights.as_deref().or(mesh.weights());
                let prims = self.decode_mesh(&mesh, &name, weights)?;
                for (k, (_, world, w)) in group.iter().enumerate().skip(first) {
                    if w != node_weights || emitted.get(k).copied().unwrap_or(true) {
                        continue;
                    }
                    if let Some(e) = emitted.get_mut(k) {
                        *e = true;
                    }
                    for prim in &prims {
                        self.emit(&name, prim, *world)?;
                    }
                }
            }
            start = end;
        }
        Ok(())
    }

    /// Decode every triangle primitive of `mesh` in its local space, with the morph
    /// `weights` applied (the rest pose the file shows), and tangents generated where a
    /// normal map needs them and the file gives none.
    fn decode_mesh(
        &mut self,
        mesh: &gltf::Mesh<'_>,
        name: &str,
        weights: Option<&[f32]>,
    ) -> Result<Vec<DecodedPrimitive>> {
        use gltf::mesh::{Mode, Semantic};
        let mut out = Vec::new();
        for prim in mesh.primitives() {
            let origin = Origin {
                path: self.path,
                mesh: name,
                primitive: prim.index(),
            };
            let mode = prim.mode();
            if !matches!(
                mode,
                Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
            ) {
                self.warn(format!(
                    "{}: mesh {name:?} primitive {}: mode {mode:?} is not triangles; skipped",
                    self.path.display(),
                    prim.index()
                ));
                continue;
            }
            let attr = |semantic: Semantic| prim.get(&semantic).map(|a| a.index());
            let err = |what: &str, m: String| origin.error(format!("{what}: {m}"));

            let pos_acc = attr(Semantic::Positions)
                .ok_or_else(|| origin.error("primitive has no POSITION attribute"))?;
            let mut positions: Vec<Vec3> = self
                .read_accessor::<f32>(pos_acc, 3)
                .map_err(|m| err("POSITION", m))?
                .chunks_exact(3)
                .map(Vec3::from_slice)
                .collect();
            let mut normals = match attr(Semantic::Normals) {
                Some(a) => Some(
                    self.read_accessor::<f32>(a, 3)
                        .map_err(|m| err("NORMAL", m))?
                        .chunks_exact(3)
                        .map(Vec3::from_slice)
                        .collect::<Vec<_>>(),
                ),
                None => None,
            };
            let mut tangents = match attr(Semantic::Tangents) {
                Some(a) => Some(
                    self.read_accessor::<f32>(a, 4)
                        .map_err(|m| err("TANGENT", m))?
                        .chunks_exact(4)
                        .map(Vec4::from_slice)
                        .collect::<Vec<_>>(),
                ),
                None => None,
            };
            let targets = self
                .root
                .meshes
                .get(mesh.index())
                .and_then(|m| m.primitives.get(prim.index()))
                .and_then(|p| p.targets.as_deref());
            if let (Some(targets), Some(weights)) = (targets, weights) {
                self.apply_morph_targets(
                    origin,
                    targets,
                    weights,
                    &mut positions,
                    &mut normals,
                    &mut tangents,
                )?;
            }
            let material = match prim.material().index() {
                Some(i) => u32::try_from(i)
                    .ok()
                    .filter(|&i| (i as usize) < self.root.materials.len())
                    .ok_or_else(|| origin.error(format!("material {i} does not exist")))?,
                None => self.default_material(),
            };
            // The UV sets this primitive's material reads (TEXCOORD_0 unless its
            // textures ask for another, and a second only when they name two).
            let sets = self
                .uv_sets
                .get(material as usize)
                .copied()
                .unwrap_or_default();
            let read_uvs = |set: u32| -> Result<Option<Vec<Vec2>>> {
                match attr(Semantic::TexCoords(set)) {
                    Some(a) => Ok(Some(
                        self.read_accessor::<f32>(a, 2)
                            .map_err(|m| err(&format!("TEXCOORD_{set}"), m))?
                            .chunks_exact(2)
                            .map(Vec2::from_slice)
                            .collect::<Vec<_>>(),
                    )),
                    None => Ok(None),
                }
            };
            let mut uvs = read_uvs(sets.first)?;
            let mut uvs2 = match sets.second {
                Some(set) => read_uvs(set)?,
                None => None,
            };
            let mut colors = match attr(Semantic::Colors(0)) {
                Some(a) => Some(self.read_colors(a).map_err(|m| err("COLOR_0", m))?),
                None => None,
            };
            let raw_indices = match prim.indices() {
                Some(acc) => self
                    .read_indices(acc.index())
                    .map_err(|m| err("indices", m))?,
                None => {
                    let n = u32::try_from(positions.len())
                        .map_err(|_| origin.error("too many vertices for 32-bit indices"))?;
                    (0..n).collect()
                }
            };
            let mut indices = match mode {
                Mode::TriangleStrip => validate::strip_to_list(&raw_indices),
                Mode::TriangleFan => validate::fan_to_list(&raw_indices),
                _ => raw_indices,
            };
            // Tangents are made for a normal map (the material's or its clear coat's),
            // from the UV set that map reads, and for an anisotropic lobe (its direction
            // is given in tangent space) from the first set.
            let normal_map = self.scene.materials.get(material as usize).and_then(|m| {
                m.normal_tex.or(m.clearcoat.and_then(|c| c.normal_tex)).or(m
                    .has_anisotropy()
                    .then_some(TexRef {
                        tex_coord: sets.first,
                        ..TexRef::new(0)
                    }))
            });
            if let (Some(map), None) = (normal_map, &tangents) {
                let frame_uvs = if map.second_uv { &uvs2 } else { &uvs };
                match (&mut normals, frame_uvs) {
                    (Some(ns), Some(us)) => {
                        // MikkTSpace reads what shading will read (cleaned values),
                        // with V pointing up as in the tools that bake normal maps:
                        // glTF's V points down the image, and a normal map's green
                        // channel points up it ("+Y is up", glTF 2.0 normalTexture).
                        // Without the flip every bitangent sign would be inverted
                        // (three.js negates w after MikkTSpace for the same reason).
                        let clean_ns: Vec<Vec3> =
                            ns.iter().map(|&n| validate::clean_normal(n)).collect();
                        let clean_us: Vec<Vec2> = us
                            .iter()
                            .map(|&u| {
                                let c = validate::clean_uv(u);
                                Vec2::new(c.x, 1.0 - c.y)
                            })
                            .collect();
                        let (generated, split) = crate::tangents::generate(
                            &positions,
                            &clean_ns,
                            &clean_us,
                            &mut indices,
                        );
                        split.apply(&mut positions);
                        split.apply(ns);
                        if let Some(us) = uvs.as_mut() {
                            split.apply(us);
                        }
                        if let Some(us) = uvs2.as_mut() {
                            split.apply(us);
                        }
                        if let Some(cs) = colors.as_mut() {
                            split.apply(cs);
                        }
                        tangents = Some(generated);
                    }
                    _ => self.warn(format!(
                        "{}: mesh {name:?} primitive {}: its material has a normal map or an \
                         anisotropic lobe but the primitive has no TANGENT, and no NORMAL or \
                         TEXCOORD_{} to generate tangents from; its normal map is ignored there, \
                         and so is its anisotropy",
                        self.path.display(),
                        prim.index(),
                        map.tex_coord
                    )),
                }
            }
            out.push(DecodedPrimitive {
                index: prim.index(),
                positions,
                normals,
                tangents,
                uvs,
                uvs2,
                uv_sets: [sets.first, sets.second.unwrap_or(sets.first)],
                colors,
                indices,
                material,
            });
        }
        Ok(out)
    }

    /// Add the morph targets' displacements, each times its weight, to the base
    /// attributes: a file's rest pose is its mesh at the default weights (glTF 2.0,
    /// "Morph Targets"), and an animation dray does not play would start from it. A
    /// weight of zero adds nothing, so an unweighted mesh keeps its bits.
    #[allow(clippy::too_many_arguments)] // the one primitive's attributes being moved
    fn apply_morph_targets(
        &mut self,
        origin: Origin<'_>,
        targets: &[json::mesh::MorphTarget],
        weights: &[f32],
        positions: &mut [Vec3],
        normals: &mut Option<Vec<Vec3>>,
        tangents: &mut Option<Vec<Vec4>>,
    ) -> Result<()> {
        if weights.len() != targets.len() {
            self.warn(format!(
                "{}: mesh {:?} primitive {}: {} morph weights for {} morph targets; the \
                 missing ones are taken as 0 and the extra ones ignored",
                self.path.display(),
                origin.mesh,
                origin.primitive,
                weights.len(),
                targets.len()
            ));
        }
        let n = positions.len();
        for (t, (target, &weight)) in targets.iter().zip(weights).enumerate() {
            if weight == 0.0 {
                continue;
            }
            // One mesh may have hundreds of thousands of targets (issue 45: 200,000 of
            // them ran on for 20 s of CPU after CancelJob): look at the flag each time.
            crate::cancel::check()?;
            let read = |acc: Option<json::Index<json::Accessor>>, what: &str| {
                let Some(acc) = acc else {
                    return Ok(None);
                };
                let what = format!("morph target {t} {what}");
                let deltas: Vec<Vec3> = self
                    .read_accessor::<f32>(acc.value(), 3)
                    .map_err(|m| origin.error(format!("{what}: {m}")))?
                    .chunks_exact(3)
                    .map(Vec3::from_slice)
                    .collect();
                if deltas.len() != n {
                    return Err(origin.error(format!(
                        "{what} has {} entries but POSITION has {n}",
                        deltas.len()
                    )));
                }
                Ok(Some(deltas))
            };
            if let Some(d) = read(target.positions, "POSITION")? {
                for (p, d) in positions.iter_mut().zip(d) {
                    *p += weight * d;
                }
            }
            if let (Some(d), Some(ns)) = (read(target.normals, "NORMAL")?, normals.as_mut()) {
                for (v, d) in ns.iter_mut().zip(d) {
                    *v += weight * d;
                }
            }
            if let (Some(d), Some(ts)) = (read(target.tangents, "TANGENT")?, tangents.as_mut()) {
                for (v, d) in ts.iter_mut().zip(d) {
                    *v += (weight * d).extend(0.0);
                }
            }
        }
        Ok(())
    }

    /// Transform one decoded primitive by `world` and push it through the validation gate.
    fn emit(&mut self, mesh_name: &str, prim: &DecodedPrimitive, world: DMat4) -> Result<()> {
        // Most instances sit under identity transforms; keep their data bit for bit.
        let identity = world == DMat4::IDENTITY;
        let linear = DMat3::from_mat4(world);
        let det = linear.determinant();
        // Normals follow the inverse transpose; a singular matrix gives non-finite
        // normals, which the gate turns into "absent".
        let normal_matrix = linear.inverse().transpose();
        let positions: Cow<'_, [Vec3]> = if identity {
            Cow::Borrowed(&prim.positions)
        } else {
            prim.positions
                .iter()
                .map(|p| world.transform_point3(p.as_dvec3()).as_vec3())
                .collect()
        };
        let normals: Option<Cow<'_, [Vec3]>> = prim.normals.as_ref().map(|ns| {
            if identity {
                Cow::Borrowed(ns.as_slice())
            } else {
                ns.iter()
                    .map(|n| (normal_matrix * n.as_dvec3()).as_vec3())
                    .collect()
            }
        });
        // A mirroring transform flips handedness, so the bitangent sign flips with it.
        let w_sign = if det < 0.0 { -1.0 } else { 1.0 };
        let tangents: Option<Cow<'_, [Vec4]>> = prim.tangents.as_ref().map(|ts| {
            if identity {
                Cow::Borrowed(ts.as_slice())
            } else {
                ts.iter()
                    .map(|t| {
                        let xyz = (linear * t.truncate().as_dvec3())
                            .normalize_or_zero()
                            .as_vec3();
                        xyz.extend(t.w * w_sign)
                    })
                    .collect()
            }
        });
        // Mirroring also turns counter-clockwise triangles clockwise; swap two corners
        // so front faces stay front faces.
        let indices: Cow<'_, [u32]> = if det < 0.0 {
            let mut flipped = prim.indices.clone();
            for tri in flipped.chunks_exact_mut(3) {
                tri.swap(1, 2);
            }
            Cow::Owned(flipped)
        } else {
            Cow::Borrowed(&prim.indices)
        };
        let origin = Origin {
            path: self.path,
            mesh: mesh_name,
            primitive: prim.index,
        };
        validate::add_primitive(
            &mut self.scene.mesh,
            &mut self.scene.stats,
            origin,
            Primitive {
                positions: &positions,
                normals: normals.as_deref(),
                tangents: tangents.as_deref(),
                uvs: prim.uvs.as_deref(),
                uvs2: prim.uvs2.as_deref(),
                uv_sets: prim.uv_sets,
                colors: prim.colors.as_deref(),
                indices: &indices,
                material: prim.material,
            },
        )
    }

    // ----- accessors -------------------------------------------------------------------

    /// The bytes of buffer view `index` and its stride, bounds-checked against its buffer.
    fn view_bytes(&self, index: usize) -> std::result::Result<(&[u8], Option<usize>), String> {
        let view = self
            .root
            .buffer_views
            .get(index)
            .ok_or_else(|| format!("buffer view {index} does not exist"))?;
        let stride = view.byte_stride.map(|s| s.0).filter(|&s| s > 0);
        if let Some(Some(decoded)) = self.decoded_views.get(index) {
            return Ok((decoded, stride));
        }
        let b = view.buffer.value();
        let buffer = self
            .buffers
            .get(b)
            .ok_or_else(|| format!("buffer view {index} refers to missing buffer {b}"))?;
        let offset = view.byte_offset.map_or(0, |o| o.0);
        let end = offset.checked_add(view.byte_length.0);
        let slice = end
            .and_then(|end| buffer.get(usize::try_from(offset).ok()?..usize::try_from(end).ok()?));
        let slice = slice.ok_or_else(|| {
            format!(
                "buffer view {index} covers bytes {offset}..{} but buffer {b} has only {} bytes",
                end.map_or_else(|| "overflow".to_string(), |e| e.to_string()),
                buffer.len()
            )
        })?;
        Ok((slice, stride))
    }

    /// Decode accessor `index`, which must have `dims` components per element, into a
    /// flat array. Every offset is checked, so a bad file gives a message, never a panic.
    fn read_accessor<T: FromComponent>(
        &self,
        index: usize,
        dims: usize,
    ) -> std::result::Result<Vec<T>, String> {
        let acc = self.accessor(index)?;
        let Checked::Valid(json::accessor::GenericComponentType(ty)) = acc.component_type else {
            return Err(format!("accessor {index} has an invalid componentType"));
        };
        let Checked::Valid(kind) = acc.type_ else {
            return Err(format!("accessor {index} has an invalid type"));
        };
        if kind.multiplicity() != dims {
            return Err(format!(
                "accessor {index} has type {kind:?} but {dims} components per element are required"
            ));
        }
        let count = usize::try_from(acc.count.0)
            .map_err(|_| format!("accessor {index}: count {} is too large", acc.count.0))?;
        let comp_size = ty.size();
        let elem_size = comp_size * dims;
        let total = count
            .checked_mul(dims)
            .ok_or_else(|| format!("accessor {index}: count {count} is too large"))?;

        let mut out: Vec<T> = Vec::new();
        match acc.buffer_view {
            Some(view) => {
                let (bytes, stride) = self
                    .view_bytes(view.value())
                    .map_err(|m| format!("accessor {index}: {m}"))?;
                let stride = stride.unwrap_or(elem_size);
                if stride < elem_size {
                    return Err(format!(
                        "accessor {index}: byteStride {stride} is smaller than the element size \
                         {elem_size}"
                    ));
                }
                let offset = usize::try_from(acc.byte_offset.map_or(0, |o| o.0))
                    .map_err(|_| format!("accessor {index}: byteOffset is too large"))?;
                if count > 0 {
                    let end = (count - 1)
                        .checked_mul(stride)
                        .and_then(|x| x.checked_add(offset))
                        .and_then(|x| x.checked_add(elem_size));
                    match end {
                        Some(end) if end <= bytes.len() => {}
                        _ => {
                            return Err(format!(
                                "accessor {index} ({count} elements of {elem_size} bytes, stride \
                                 {stride}, offset {offset}) reads past the end of buffer view {} \
                                 ({} bytes)",
                                view.value(),
                                bytes.len()
                            ));
                        }
                    }
                }
                out.reserve_exact(total);
                for e in 0..count {
                    let at = offset + e * stride;
                    for c in 0..dims {
                        let v = bytes
                            .get(at + c * comp_size..)
                            .and_then(|b| read_component(b, ty, acc.normalized))
                            .ok_or_else(|| {
                                format!("accessor {index}: element {e} is out of range")
                            })?;
                        out.push(T::from_component(v));
                    }
                }
            }
            None => {
                if total > MAX_ZERO_FILLED_COMPONENTS {
                    return Err(format!(
                        "accessor {index} has no buffer view and {count} elements (too many)"
                    ));
                }
                out.resize(total, T::default());
            }
        }
        if let Some(sparse) = &acc.sparse {
            self.apply_sparse(index, sparse, ty, acc.normalized, dims, count, &mut out)?;
        }
        Ok(out)
    }

    #[allow(clippy::too_many_arguments)] // all describe the one accessor being patched
    fn apply_sparse<T: FromComponent>(
        &self,
        index: usize,
        sparse: &json::accessor::sparse::Sparse,
        ty: json::accessor::ComponentType,
        normalized: bool,
        dims: usize,
        count: usize,
        out: &mut [T],
    ) -> std::result::Result<(), String> {
        let n = usize::try_from(sparse.count.0)
            .map_err(|_| format!("accessor {index}: sparse count is too large"))?;
        let Checked::Valid(json::accessor::IndexComponentType(ity)) = sparse.indices.component_type
        else {
            return Err(format!(
                "accessor {index}: sparse indices have an invalid componentType"
            ));
        };
        let isize_ = ity.size();
        let elem_size = ty.size() * dims;
        let region = |view: usize, offset: u64, elem: usize, what: &str| {
            let (bytes, _) = self
                .view_bytes(view)
                .map_err(|m| format!("accessor {index}: sparse {what}: {m}"))?;
            let offset = usize::try_from(offset).ok();
            let end = offset.and_then(|o| n.checked_mul(elem)?.checked_add(o));
            match (offset, end) {
                (Some(o), Some(e)) if e <= bytes.len() => Ok(bytes.get(o..e).unwrap_or_default()),
                _ => Err(format!(
                    "accessor {index}: sparse {what} ({n} x {elem} bytes) read past the end of \
                     buffer view {view} ({} bytes)",
                    bytes.len()
                )),
            }
        };
        let ibytes = region(
            sparse.indices.buffer_view.value(),
            sparse.indices.byte_offset.0,
            isize_,
            "indices",
        )?;
        let vbytes = region(
            sparse.values.buffer_view.value(),
            sparse.values.byte_offset.0,
            elem_size,
            "values",
        )?;
        for k in 0..n {
            let target = ibytes
                .get(k * isize_..)
                .and_then(|b| read_component(b, ity, false))
                .ok_or_else(|| format!("accessor {index}: sparse index {k} is out of range"))?;
            let target = target as usize;
            if target >= count {
                return Err(format!(
                    "accessor {index}: sparse index {k} targets element {target} but the accessor \
                     has {count}"
                ));
            }
            for c in 0..dims {
                let v = vbytes
                    .get(k * elem_size + c * ty.size()..)
                    .and_then(|b| read_component(b, ty, normalized))
                    .ok_or_else(|| format!("accessor {index}: sparse value {k} is out of range"))?;
                if let Some(slot) = out.get_mut(target * dims + c) {
                    *slot = T::from_component(v);
                }
            }
        }
        Ok(())
    }

    /// Accessor `index`, or a message saying it does not exist.
    fn accessor(&self, index: usize) -> std::result::Result<&json::Accessor, String> {
        self.root
            .accessors
            .get(index)
            .ok_or_else(|| format!("accessor {index} does not exist"))
    }

    /// Read a `COLOR_0` accessor: VEC3 (alpha 1) or VEC4, float or normalized unsigned
    /// 8/16-bit, as the glTF specification allows.
    fn read_colors(&self, index: usize) -> std::result::Result<Vec<Vec4>, String> {
        use json::accessor::ComponentType as C;
        let acc = self.accessor(index)?;
        let dims = match acc.type_ {
            Checked::Valid(json::accessor::Type::Vec3) => 3,
            Checked::Valid(json::accessor::Type::Vec4) => 4,
            _ => return Err(format!("accessor {index} must be VEC3 or VEC4")),
        };
        match acc.component_type {
            Checked::Valid(json::accessor::GenericComponentType(C::F32)) => {}
            Checked::Valid(json::accessor::GenericComponentType(C::U8 | C::U16))
                if acc.normalized => {}
            _ => {
                return Err(format!(
                    "accessor {index} must hold floats or normalized unsigned 8 or 16-bit \
                     integers"
                ));
            }
        }
        let values = self.read_accessor::<f32>(index, dims)?;
        Ok(values
            .chunks_exact(dims)
            .map(|c| match c {
                [r, g, b] => Vec4::new(*r, *g, *b, 1.0),
                _ => Vec4::from_slice(c),
            })
            .collect())
    }

    /// Read an index accessor (unsigned 8, 16 or 32-bit scalars).
    fn read_indices(&self, index: usize) -> std::result::Result<Vec<u32>, String> {
        use json::accessor::ComponentType as C;
        let acc = self.accessor(index)?;
        match acc.component_type {
            Checked::Valid(json::accessor::GenericComponentType(C::U8 | C::U16 | C::U32)) => {}
            _ => {
                return Err(format!(
                    "accessor {index} must hold unsigned 8, 16 or 32-bit integers to be used as \
                     indices"
                ));
            }
        }
        self.read_accessor::<u32>(index, 1)
    }
}

/// A node's local transform in f64. Rotations are renormalised: exporters write
/// quaternions rounded to a few digits.
/// The node's local transform, with what an animation sets at the requested time in
/// place of the file's values (glTF animates only nodes with decomposed transforms).
fn local_matrix(node: &gltf::Node<'_>, posed: Option<&NodePose>) -> DMat4 {
    match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => {
            DMat4::from_cols_array_2d(&matrix.map(|col| col.map(f64::from)))
        }
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            let [x, y, z, w] = rotation.map(f64::from);
            let pose = posed.cloned().unwrap_or_default();
            DMat4::from_scale_rotation_translation(
                pose.scale.unwrap_or(DVec3::from(scale.map(f64::from))),
                pose.rotation
                    .unwrap_or(DQuat::from_xyzw(x, y, z, w))
                    .normalize(),
                pose.translation
                    .unwrap_or(DVec3::from(translation.map(f64::from))),
            )
        }
    }
}

/// The node's morph weights: the animation's at the requested time, else the node's own
/// (either overrides the mesh's).
fn node_weights(node: &gltf::Node<'_>, posed: Option<&NodePose>) -> Option<Vec<f32>> {
    posed
        .and_then(|p| p.weights.clone())
        .or_else(|| node.weights().map(<[f32]>::to_vec))
}

fn convert_sampler(s: &json::texture::Sampler) -> Sampler {
    use json::texture::{MagFilter, WrappingMode};
    let wrap = |w: Checked<WrappingMode>| match w {
        Checked::Valid(WrappingMode::ClampToEdge) => Wrap::ClampToEdge,
        Checked::Valid(WrappingMode::MirroredRepeat) => Wrap::MirroredRepeat,
        _ => Wrap::Repeat,
    };
    Sampler {
        wrap_s: wrap(s.wrap_s),
        wrap_t: wrap(s.wrap_t),
        filter: match s.mag_filter {
            Some(Checked::Valid(MagFilter::Nearest)) => Filter::Nearest,
            _ => Filter::Linear,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The morph-target loop looks at the cancel flag once per weighted target, so a
    /// mesh with a great many targets stops soon after CancelJob (issue 45, item 9).
    #[test]
    fn the_morph_target_loop_looks_at_the_cancel_flag() {
        let targets = 2000;
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},
"buffers":[{{"byteLength":72,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAAAAAAAAAAAABvEoM6AAAAAAAAAABvEoM6AAAAAAAAAABvEoM6"}}],
"bufferViews":[{{"buffer":0,"byteLength":36}},{{"buffer":0,"byteOffset":36,"byteLength":36}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
  {{"bufferView":1,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0.001],"max":[0,0,0.001]}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"targets":[{}]}}],"weights":[{}]}}],
"nodes":[{{"mesh":0}}]}}"#,
            vec![r#"{"POSITION":1}"#; targets].join(","),
            vec!["0.5"; targets].join(",")
        );
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("morph.gltf");
        std::fs::write(&path, json).expect("write");
        let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let before = crate::cancel::checks_made();
        let scene = crate::cancel::with_cancel(&flag, || load_gltf(&path)).expect("loads");
        let looks = crate::cancel::checks_made() - before;
        assert!(
            looks >= targets,
            "{looks} looks at the flag for {targets} targets"
        );
        // Every target moved the triangle by 0.5 x 0.001 in z.
        let z = scene.mesh.positions[0].z;
        assert!((z - 1.0).abs() < 1e-3, "{z}");
    }

    #[test]
    fn base64_round_trips() {
        assert_eq!(decode_base64("aGVsbG8=").unwrap(), b"hello");
        assert_eq!(decode_base64("aGVsbG8").unwrap(), b"hello");
        assert_eq!(decode_base64("AAECAw==").unwrap(), [0, 1, 2, 3]);
        assert!(decode_base64("a$b").is_err());
        assert!(decode_base64("aGVsb").is_err());
    }

    #[test]
    fn uri_helpers() {
        assert_eq!(percent_decode("a%20b").unwrap(), b"a b");
        assert!(percent_decode("a%2").is_err());
        assert_eq!(uri_scheme("http://x"), Some("http"));
        assert_eq!(uri_scheme("dir/file.bin"), None);
        assert_eq!(uri_scheme("C:/dir/file.bin"), None);
    }

    #[test]
    fn bad_glb_header_is_an_error() {
        assert!(check_glb_header(b"glTF\x02\0\0\0\x05\0\0\0").is_err());
        assert!(check_glb_header(b"glTF").is_err());
        assert!(check_glb_header(b"{}").is_ok());
    }
}
