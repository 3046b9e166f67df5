//! Shared helpers of dray's fuzz targets (see `docs/fuzzing.md`).
//!
//! - [`init`]: the panic policy and the per-process scratch directory.
//! - [`Scratch`]: path-only loaders (`load_ply`, `load_obj`, `load_gltf`,
//!   `open_package`) read files, so each input is written to a directory of this process's
//!   own (`$TMPDIR/dray-fuzz-<target>-<pid>`), emptied before every input and removed at
//!   exit. Directories of processes that are gone are removed on start.
//! - [`Sections`]: a tiny framing for targets that need several files from one input.
//! - [`check_scene`]: invariants every loader promises its callers (indices in range,
//!   attribute arrays as long as the positions, material and texture references valid,
//!   finite positions); a violation panics, i.e. is a finding.
//!
//! # Panics
//! libFuzzer-sys aborts on *every* panic, even one the code under test catches on purpose
//! (`load_gltf` and `load_obj` wrap third-party parsers in `catch_unwind` so that a bug
//! there becomes a load error instead of a dead render node). By default those contained
//! panics are allowed, as in production, but each distinct location is printed once with
//! a backtrace (`dray-fuzz: contained panic ...`), so a run's log lists them. A panic
//! that escapes the target still aborts and is a crash. `DRAY_FUZZ_STRICT=1` makes
//! every panic, contained or not, a crash (to minimise a contained one).

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use dray_core::scene::Scene;
use glam::Vec2;

static SCRATCH: OnceLock<PathBuf> = OnceLock::new();

/// Call once from the target's `init:` block.
pub fn init(target: &str) {
    // One thread for rayon (BVH builds): the machine is shared and libFuzzer measures
    // one input at a time anyway.
    // SAFETY: called from LLVMFuzzerInitialize, before any other thread exists.
    unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    if std::env::var_os("DRAY_FUZZ_STRICT").is_none_or(|v| v.is_empty() || v == "0") {
        let seen: Mutex<HashSet<String>> = Mutex::new(HashSet::new());
        std::panic::set_hook(Box::new(move |info| {
            let at = info
                .location()
                .map(|l| format!("{}:{}:{}", l.file(), l.line(), l.column()))
                .unwrap_or_else(|| "unknown location".into());
            let first = seen
                .lock()
                .map(|mut s| s.insert(at.clone()))
                .unwrap_or(false);
            if first {
                let msg = info
                    .payload()
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| info.payload().downcast_ref::<String>().cloned())
                    .unwrap_or_default();
                eprintln!(
                    "dray-fuzz: contained panic at {at}: {msg}\n(a panic that escapes the \
                     target aborts next and is a crash)\n{}",
                    std::backtrace::Backtrace::force_capture()
                );
            }
        }));
    }
    let base = std::env::temp_dir();
    remove_stale(&base);
    let dir = base.join(format!("dray-fuzz-{target}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("create the fuzz scratch directory");
    SCRATCH.set(dir).expect("init is called once");
    // libFuzzer ends with exit(), which runs atexit handlers.
    unsafe { libc::atexit(remove_scratch) };
}

extern "C" fn remove_scratch() {
    if let Some(dir) = SCRATCH.get() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// Remove `dray-fuzz-*-<pid>` directories whose process is gone (killed runs).
fn remove_stale(base: &Path) {
    let Ok(entries) = std::fs::read_dir(base) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(name) = name.to_str() else { continue };
        if !name.starts_with("dray-fuzz-") {
            continue;
        }
        let Some(pid) = name.rsplit('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// This process's scratch directory, emptied.
pub struct Scratch {
    dir: PathBuf,
}

impl Scratch {
    /// The scratch directory with every file of the previous input removed.
    pub fn fresh() -> Scratch {
        let dir = SCRATCH.get().expect("dray_fuzz::init was called").clone();
        if let Ok(entries) = std::fs::read_dir(&dir) {
            for e in entries.flatten() {
                let p = e.path();
                if p.is_dir() {
                    let _ = std::fs::remove_dir_all(&p);
                } else {
                    let _ = std::fs::remove_file(&p);
                }
            }
        }
        Scratch { dir }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Write `bytes` to `name` inside the directory and return the file's path.
    pub fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.dir.join(name);
        std::fs::write(&p, bytes).expect("write into the fuzz scratch directory");
        p
    }
}

/// Several named parts in one input: `[u8 id][u32 LE length][bytes]...`; the last part
/// may be shorter than its length says (it takes what is left). Built by
/// `fuzz/seeds.py` for the seeds; mutations of the lengths and ids are fine (anything
/// unparsable simply ends the list).
pub struct Sections<'a> {
    rest: &'a [u8],
}

impl<'a> Sections<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Sections { rest: data }
    }
}

impl<'a> Iterator for Sections<'a> {
    type Item = (u8, &'a [u8]);
    fn next(&mut self) -> Option<(u8, &'a [u8])> {
        if self.rest.len() < 5 {
            return None;
        }
        let id = self.rest[0];
        let len = u32::from_le_bytes(self.rest[1..5].try_into().unwrap()) as usize;
        let body = &self.rest[5..];
        let take = len.min(body.len());
        self.rest = &body[take..];
        Some((id, &body[..take]))
    }
}

/// What every caller of a loader relies on; panics (a finding) when violated.
pub fn check_scene(scene: &Scene) {
    check_scene_with(scene, true);
}

/// [`check_scene`], with the finite-position check optional (`finite_positions`): the
/// scene package reader does not promise it yet (docs/fuzzing.md, finding P1).
pub fn check_scene_with(scene: &Scene, finite_positions: bool) {
    let m = &scene.mesh;
    let n = m.positions.len();
    assert_eq!(m.normals.len(), n, "normals per vertex");
    assert_eq!(m.tangents.len(), n, "tangents per vertex");
    assert_eq!(m.uvs.len(), n, "uvs per vertex");
    assert!(
        m.uvs2.is_empty() || m.uvs2.len() == n,
        "second uvs: none or one per vertex"
    );
    assert_eq!(m.material.len(), m.indices.len(), "material per triangle");
    if finite_positions {
        for (i, p) in m.positions.iter().enumerate() {
            assert!(p.is_finite(), "vertex {i} position {p} is not finite");
        }
    }
    for (t, tri) in m.indices.iter().enumerate() {
        for &v in tri {
            assert!((v as usize) < n, "triangle {t} index {v} >= {n} vertices");
        }
    }
    for (t, &mat) in m.material.iter().enumerate() {
        assert!(
            (mat as usize) < scene.materials.len(),
            "triangle {t} material {mat} >= {} materials",
            scene.materials.len()
        );
    }
    for (i, mat) in scene.materials.iter().enumerate() {
        for t in [
            mat.base_color_tex,
            mat.metallic_roughness_tex,
            mat.normal_tex,
            mat.emissive_tex,
            mat.transmission_tex,
            mat.specular_tex,
            mat.specular_color_tex,
        ]
        .into_iter()
        .flatten()
        {
            assert!(
                (t.texture as usize) < scene.textures.len(),
                "material {i} refers to texture {} of {}",
                t.texture,
                scene.textures.len()
            );
        }
    }
    for tex in &scene.textures {
        assert_eq!(
            tex.texels.len() as u64,
            u64::from(tex.width) * u64::from(tex.height),
            "texture {:?} texel count",
            tex.name
        );
        // Sampling is what shading does with a texture; it must not index out of range.
        for uv in [
            Vec2::ZERO,
            Vec2::ONE,
            Vec2::new(0.5, -0.25),
            Vec2::new(-3.7, 12.2),
            Vec2::splat(f32::NAN),
        ] {
            let _ = tex.sample(uv, true);
        }
    }
    let _ = scene.bounds();
}

/// A valid 2x2 RGBA PNG, written as `tex.png` beside OBJ and glTF inputs that bring no
/// texture of their own, so `map_Kd tex.png` and image URIs `tex.png` resolve.
pub const TEX_PNG: &[u8] = &[
    0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44, 0x52,
    0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x02, 0x08, 0x06, 0x00, 0x00, 0x00, 0x72, 0xb6, 0x0d,
    0x24, 0x00, 0x00, 0x00, 0x13, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0xf8, 0xcf, 0xc0, 0xf0,
    0x1f, 0x0c, 0x81, 0x34, 0x08, 0x34, 0x00, 0x00, 0x49, 0x49, 0x09, 0x78, 0x28, 0xa0, 0xdb, 0x77,
    0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
];

/// Split `data` at the first `marker`: (before, Some(after)) or (data, None).
pub fn split_at_marker<'a>(data: &'a [u8], marker: &[u8]) -> (&'a [u8], Option<&'a [u8]>) {
    match data.windows(marker.len()).position(|w| w == marker) {
        Some(i) => (&data[..i], Some(&data[i + marker.len()..])),
        None => (data, None),
    }
}
