//! The wording of `dray render`'s refusals, where a user's first mistake meets it: a
//! mistyped scene name is answered once, with the name it probably meant; an EXR name
//! given to the PNG flag names `--exr`; every bad flag value is a usage error with the
//! same exit code; and the summary's build time is the build's, not a constant zero.

use std::path::PathBuf;
use std::process::{Command, Output};

fn dray(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(args)
        .output()
        .expect("run dray")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("dray-cli-errtext-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn a_mistyped_scene_name_is_answered_once_with_a_suggestion() {
    let d = tmp("cornel");
    let png = d.join("x.png");
    let o = dray(&[
        "render",
        "cornel",
        "-q",
        "--output",
        png.to_str().expect("utf-8"),
    ]);
    let e = stderr(&o);
    assert!(!o.status.success(), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert_eq!(e.matches("procedural scene name").count(), 1, "{e}");
    assert!(e.contains("did you mean \"cornell\"?"), "{e}");
    assert!(!png.exists());
}

#[test]
fn a_mistyped_file_name_suggests_the_file_beside_it() {
    let d = tmp("file");
    std::fs::write(d.join("bunny.ply"), b"").expect("write");
    let typo = d.join("buny.ply");
    let o = dray(&["render", typo.to_str().expect("utf-8"), "-q"]);
    let e = stderr(&o);
    assert!(!o.status.success(), "{e}");
    let want = format!(
        "did you mean {:?}?",
        d.join("bunny.ply").to_str().expect("utf-8")
    );
    assert!(e.contains(&want), "{e} lacks {want}");
}

#[test]
fn an_exr_name_for_the_png_names_the_exr_flag() {
    let d = tmp("exr");
    let out = d.join("x.exr");
    let out = out.to_str().expect("utf-8");
    let o = dray(&["render", "cornell", "-q", "--output", out]);
    let e = stderr(&o);
    assert!(!o.status.success(), "{e}");
    assert!(e.contains(&format!("--exr {out}")), "{e}");
}

#[test]
fn bad_integrator_and_bad_tonemap_are_the_same_kind_of_error() {
    let a = dray(&["render", "cornell", "-q", "--integrator", "photon"]);
    let b = dray(&["render", "cornell", "-q", "--tonemap", "filmic"]);
    assert!(
        stderr(&a).contains("unknown integrator \"photon\""),
        "{}",
        stderr(&a)
    );
    assert!(stderr(&b).contains("unknown tone curve"), "{}", stderr(&b));
    assert_eq!(a.status.code(), b.status.code());
    // Usage errors exit 2 (clap's convention, as every other bad flag value).
    assert_eq!(a.status.code(), Some(2));
}

#[test]
fn the_summary_reports_the_build_time_on_workers_and_in_one_process() {
    let d = tmp("build");
    for workers in ["0", "1"] {
        let stats = d.join(format!("stats-{workers}.json"));
        let png = d.join(format!("x-{workers}.png"));
        let o = dray(&[
            "render",
            "soup:200000",
            "--width",
            "16",
            "--height",
            "16",
            "--spp",
            "1",
            "--workers",
            workers,
            "--output",
            png.to_str().expect("utf-8"),
            "--stats",
            stats.to_str().expect("utf-8"),
        ]);
        let e = stderr(&o);
        assert!(o.status.success(), "{e}");
        let s: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&stats).expect("stats")).expect("json");
        let build = s["build_time_s"].as_f64().expect("build_time_s");
        // Building a BVH over 200,000 triangles takes time on any machine.
        assert!(build > 0.0, "workers {workers}: build_time_s {build}");
        assert_eq!(
            s["build_summed_over_workers"].as_bool(),
            Some(workers != "0"),
            "{s}"
        );
        let line = e
            .lines()
            .find(|l| l.starts_with("time "))
            .expect("time line");
        assert!(!line.contains("bvh 0.000s"), "{line}");
    }
}
