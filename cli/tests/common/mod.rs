//! Shared helpers for the CLI tests: run the real `dray` binary, read what it wrote.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

pub struct Run {
    pub ok: bool,
    pub stderr: String,
    pub stats: Option<serde_json::Value>,
    pub png: Option<PathBuf>,
}

/// A fresh directory for one test.
pub fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("dray-cli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// `dray render SCENE ARGS… --output DIR/TAG.png --stats DIR/TAG.json -q`.
pub fn render(dir: &Path, tag: &str, scene: &str, args: &[&str]) -> Run {
    let png = dir.join(format!("{tag}.png"));
    let stats = dir.join(format!("{tag}.json"));
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .arg("render")
        .arg(scene)
        .args(args)
        .arg("--output")
        .arg(&png)
        .arg("--stats")
        .arg(&stats)
        .arg("-q")
        .output()
        .expect("run dray");
    let ok = out.status.success();
    Run {
        ok,
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        stats: ok
            .then(|| std::fs::read_to_string(&stats).ok())
            .flatten()
            .and_then(|s| serde_json::from_str(&s).ok()),
        png: ok.then_some(png),
    }
}

pub fn rgb(path: &Path) -> image::RgbImage {
    image::open(path).expect("decode png").to_rgb8()
}

pub fn rays(stats: &serde_json::Value, kind: &str) -> u64 {
    stats["rays"][kind]
        .as_u64()
        .unwrap_or_else(|| panic!("no ray count {kind} in {stats}"))
}

/// An ASCII PLY of a closed box with a ground quad (no lights, no materials).
pub fn write_box_ply(path: &Path) {
    let v = [
        (-1.0, 0.0, -1.0),
        (1.0, 0.0, -1.0),
        (1.0, 2.0, -1.0),
        (-1.0, 2.0, -1.0),
        (-1.0, 0.0, 1.0),
        (1.0, 0.0, 1.0),
        (1.0, 2.0, 1.0),
        (-1.0, 2.0, 1.0),
        (-5.0, 0.0, -5.0),
        (5.0, 0.0, -5.0),
        (5.0, 0.0, 5.0),
        (-5.0, 0.0, 5.0),
    ];
    let f = [
        [0, 3, 2, 1],
        [4, 5, 6, 7],
        [0, 4, 7, 3],
        [1, 2, 6, 5],
        [3, 7, 6, 2],
        [8, 11, 10, 9],
    ];
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        v.len(),
        f.len()
    );
    for (x, y, z) in v {
        s += &format!("{x} {y} {z}\n");
    }
    for q in f {
        s += &format!("4 {} {} {} {}\n", q[0], q[1], q[2], q[3]);
    }
    std::fs::write(path, s).expect("write ply");
}

/// A test's real dependency (grpcurl, the Python venv, the shared scenes, SimGrid, root
/// and setpriv for a second local user) is missing: on a developer's machine the test
/// says so loudly and passes; under CI (`CI=true`, as .ci/run is run) it fails, so a
/// missing install step cannot pass silently. Every skip in cli/tests goes through here.
pub fn dependency_missing(why: &str) {
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("CI=true but this test's dependency is missing: {why}");
    }
    eprintln!("SKIPPED (not under CI): {why}");
}

/// The shared scenes folder of the realistic tier: `DRAY_SCENES`, else `../shared/scenes`
/// beside the repository; `None` (after [`dependency_missing`] says so) when absent.
pub fn scenes_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("DRAY_SCENES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes"));
    if dir.is_dir() {
        Some(dir)
    } else {
        dependency_missing(&format!(
            "realistic tier: no scenes folder at {} (set DRAY_SCENES to the shared scenes)",
            dir.display()
        ));
        None
    }
}

/// Every model file under `dir` whose extension (lower-cased) is one of `extensions`,
/// sorted.
pub fn model_files(dir: &Path, extensions: &[&str]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if let Some(ext) = p.extension().and_then(|e| e.to_str())
                && extensions.contains(&ext.to_ascii_lowercase().as_str())
            {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The effects a `--stats` JSON lists.
pub fn effects(stats: &serde_json::Value) -> Vec<String> {
    stats["effects"]
        .as_array()
        .unwrap_or_else(|| panic!("no effects in {stats}"))
        .iter()
        .filter_map(|e| e.as_str().map(str::to_string))
        .collect()
}

/// Every channel of an EXR by name.
pub fn exr_channels(bytes: &[u8]) -> Vec<(String, Vec<f32>)> {
    use exr::prelude::{ReadChannels, ReadLayers};
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes.to_vec()))
        .expect("read exr");
    image.layer_data[0]
        .channel_data
        .list
        .iter()
        .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect()))
        .collect()
}
