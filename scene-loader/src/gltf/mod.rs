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
//!
//! One file per part of the format: `buffers.rs` (buffers, URIs, meshopt views),
//! `accessors.rs` (typed reads of accessors), `textures.rs` and `materials.rs`,
//! `nodes.rs` (the scene graph: instances, cameras, lights), `mesh.rs` (primitives
//! decoded and emitted), `pose.rs` (an animation's pose) and `skinned.rs` (skins). This
//! file holds the entry points and the [`Loader`] they share.

mod accessors;
mod buffers;
mod materials;
mod mesh;
mod nodes;
mod pose;
mod skinned;
mod textures;

use std::panic::AssertUnwindSafe;
use std::path::Path;

use dray_core::scene::Scene;
use gltf::json;
use gltf::json::validation::Checked;

use crate::animation::{AnimationTime, Pose};
use crate::error::{Result, SceneError};
use buffers::{decode_meshopt_views, load_buffers};
use materials::UvSets;

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
}

#[cfg(test)]
mod tests {
    use super::buffers::{decode_base64, percent_decode, uri_scheme};
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
