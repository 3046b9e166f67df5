//! The realistic tier: every glTF, PLY and OBJ model in the shared scenes folder
//! (`DRAY_SCENES`, default `../shared/scenes` beside the repository) renders to a finite,
//! non-blank image with every integrator's default settings.

mod common;

use std::path::{Path, PathBuf};

use common::{render, rgb, tmp};

fn scenes_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("DRAY_SCENES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes"));
    if dir.is_dir() {
        Some(dir)
    } else {
        common::dependency_missing(&format!(
            "realistic tier: no scenes folder at {} (set DRAY_SCENES to the shared scenes)",
            dir.display()
        ));
        None
    }
}

fn models(dir: &Path) -> Vec<PathBuf> {
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
                && ["gltf", "glb", "ply", "obj"].contains(&ext.to_ascii_lowercase().as_str())
            {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn every_shared_model_renders_finite_and_not_blank() {
    let Some(dir) = scenes_dir() else { return };
    let list = models(&dir);
    assert!(!list.is_empty(), "no models found under {}", dir.display());
    let out = tmp("realistic");
    for (i, model) in list.iter().enumerate() {
        for integ in ["path", "raycast"] {
            let r = render(
                &out,
                &format!("m{i}-{integ}"),
                model.to_str().unwrap(),
                &[
                    "--width",
                    "96",
                    "--height",
                    "72",
                    "--spp",
                    "4",
                    "--integrator",
                    integ,
                ],
            );
            assert!(r.ok, "{}: {}", model.display(), r.stderr);
            let stats = r.stats.unwrap();
            assert_eq!(stats["nonfinite_contributions"], 0, "{}", model.display());
            let img = rgb(r.png.as_ref().unwrap());
            let raw = img.as_raw();
            let (lo, hi) = (raw.iter().min().unwrap(), raw.iter().max().unwrap());
            assert!(
                hi > lo,
                "{} ({integ}) rendered a constant image",
                model.display()
            );
            assert!(*hi > 8, "{} ({integ}) rendered black", model.display());
            eprintln!(
                "{} ({integ}): {} triangles, effects {}, {:.2}s",
                model.display(),
                stats["triangles"],
                stats["effects"],
                stats["wall_time_s"].as_f64().unwrap_or(0.0)
            );
        }
    }
}
