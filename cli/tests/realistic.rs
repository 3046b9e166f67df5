//! The realistic tier: every glTF, PLY and OBJ model in the shared scenes folder
//! (`DRAY_SCENES`, default `../shared/scenes` beside the repository) renders to a finite,
//! non-blank image with every integrator's default settings.

mod common;

use common::{render, rgb, tmp};

#[test]
fn every_shared_model_renders_finite_and_not_blank() {
    let Some(dir) = common::scenes_dir() else {
        return;
    };
    let list = common::model_files(&dir, &["gltf", "glb", "ply", "obj"]);
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
