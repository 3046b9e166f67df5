//! Animation frames on a real cluster (issue 42): `dray submit --frames 1..3 --fps 4`
//! to a `dray cluster` makes a job group of three ordinary jobs, each frame's PNG the
//! same bits as `dray render --time frame/fps` in one process; `dray submit --time`
//! renders the posed scene on workers too (the coordinator cuts the posed package); the
//! group shows in GetJob and ListJobs. Bad ranges and frame rates are refused, naming
//! what is wrong.

mod common;
#[path = "../../scene-loader/tests/support/mod.rs"]
mod gltf_support;
mod support;

use std::path::{Path, PathBuf};
use std::process::Command;

/// A ground quad that stays and a triangle that slides along +X from x = -1 to x = 1
/// over one second ("slide"), written with the glTF test builder.
fn write_sliding(dir: &Path) -> PathBuf {
    let mut b = gltf_support::Builder::default();
    let ground = [
        -2.0, 0.0, -2.0, 2.0, 0.0, -2.0, 2.0, 0.0, 2.0, -2.0, 0.0, 2.0,
    ];
    b.floats(&ground, "VEC3"); // 0
    b.indices(&[0, 2, 1, 0, 3, 2]); // 1
    b.floats(&[-0.5, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3"); // 2
    b.floats(&[0.0, 1.0], "SCALAR"); // 3: key times
    b.floats(&[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0], "VEC3"); // 4: key translations
    let rest = r#""materials":[{"doubleSided":true}],
"meshes":[{"name":"ground","primitives":[{"attributes":{"POSITION":0},"indices":1,"material":0}]},
          {"name":"tri","primitives":[{"attributes":{"POSITION":2},"material":0}]}],
"nodes":[{"mesh":0},{"mesh":1,"translation":[-1,0,0]}],
"scenes":[{"nodes":[0,1]}],
"animations":[{"name":"slide","samplers":[{"input":3,"output":4}],
  "channels":[{"sampler":0,"target":{"node":1,"path":"translation"}}]}]"#;
    b.write(dir, "slide", rest)
}

/// The camera, light and image of every render here.
fn view() -> Vec<&'static str> {
    "--width 40 --height 30 --spp 2 --look-from 0,1.5,4 --look-at 0,0.4,0 --sun 30,60 \
     --animation slide"
        .split_whitespace()
        .collect()
}

#[test]
fn a_frame_range_on_a_cluster_is_a_job_group_each_frame_the_bits_of_render_time() {
    let dir = common::tmp("frames-cluster");
    let scene = write_sliding(&dir);
    let cluster = support::WorkerCluster::start(2, 3, &dir, &[]);

    // The group: frames 1, 2, 3 at 4 fps are 0.25, 0.5 and 0.75 s.
    let pattern = dir.join("group.##.png");
    let mut cmd = support::dray();
    cmd.args(["submit", "slide.gltf", "--coordinator", &cluster.addr])
        .args(view())
        .args(["--frames", "1..3", "--fps", "4", "--output"])
        .arg(&pattern);
    let err = support::run_to_success(cmd, "dray submit --frames", 300.0);
    let group = err
        .lines()
        .find_map(|l| l.strip_prefix("dray submit: job group "))
        .and_then(|l| l.split(' ').next())
        .unwrap_or_else(|| panic!("no group in {err}"))
        .to_string();

    // One `dray submit --time` of frame 2's moment: a lone job, the posed scene.
    let lone = dir.join("lone.png");
    let mut cmd = support::dray();
    cmd.args(["submit", "slide.gltf", "--coordinator", &cluster.addr])
        .args(view())
        .args(["--time", "0.5", "--output"])
        .arg(&lone);
    support::run_to_success(cmd, "dray submit --time", 300.0);

    let mut frames = Vec::new();
    for (frame, time) in [(1u32, "0.25"), (2, "0.5"), (3, "0.75")] {
        let reference = common::render(
            &dir,
            &format!("render-{frame}"),
            scene.to_str().expect("utf-8"),
            &[&view()[..], &["--time", time, "--workers", "0"]].concat(),
        );
        assert!(
            reference.ok,
            "dray render --time {time}: {}",
            reference.stderr
        );
        let want = std::fs::read(reference.png.expect("png")).expect("read");
        let got = std::fs::read(dir.join(format!("group.{frame:02}.png")))
            .unwrap_or_else(|e| panic!("frame {frame}'s image: {e}; submit said {err}"));
        assert!(
            got == want,
            "frame {frame}: the cluster's image differs from dray render --time {time}"
        );
        if frame == 2 {
            assert!(
                std::fs::read(&lone).expect("lone") == want,
                "dray submit --time 0.5 differs from dray render --time 0.5"
            );
        }
        frames.push(got);
    }
    assert!(
        frames[0] != frames[1] && frames[1] != frames[2],
        "the triangle did not move between frames"
    );

    // The group as the coordinator lists it: three jobs, one per frame, each its time.
    let mut jobs = support::list_group(&cluster.addr, &group).expect("ListJobs");
    jobs.sort_by_key(|j| j.group.as_ref().map(|g| g.frame));
    let seen: Vec<(u32, Option<f64>)> = jobs
        .iter()
        .map(|j| {
            let g = j.group.as_ref().expect("a frame's job names its group");
            assert_eq!(g.group_id, group);
            (g.frame, j.spec.as_ref().and_then(|s| s.time))
        })
        .collect();
    assert_eq!(
        seen,
        [(1, Some(0.25)), (2, Some(0.5)), (3, Some(0.75))],
        "ListJobs of group {group}"
    );
    let one = support::get_job(&cluster.addr, &jobs[0].job_id).expect("GetJob");
    assert_eq!(one.group, jobs[0].group, "GetJob shows the group too");
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

fn refused(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["render", "cornell", "--width", "8", "--height", "8"])
        .args(args)
        .output()
        .expect("run dray");
    assert!(!out.status.success(), "{args:?} was accepted");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn bad_ranges_and_frame_rates_are_refused_naming_what_is_wrong() {
    for (args, words) in [
        (
            &["--frames", "5..1", "--fps", "24"][..],
            "the range ends before it starts (1 < 5)",
        ),
        (&["--frames", "1..", "--fps", "24"], "is not a frame range"),
        (
            &["--frames", "1..4:0", "--fps", "24"],
            "the step must be at least 1",
        ),
        (
            &["--frames", "1..4", "--fps", "0"],
            "above 0 frames a second, got 0",
        ),
        (&["--frames", "1..4"], "--fps"),
        (
            &["--frames", "1..4", "--fps", "24", "--time", "1"],
            "--time",
        ),
        (
            &["--animation", "walk"],
            "--animation: give --time or --frames",
        ),
    ] {
        let err = refused(args);
        assert!(err.contains(words), "{args:?}: expected {words:?} in {err}");
    }
}

#[test]
fn render_frames_writes_each_frame_under_its_name() {
    let dir = common::tmp("frames-render");
    let scene = write_sliding(&dir);
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .arg("render")
        .arg(&scene)
        .args(view())
        .args(["--frames", "0..4:2", "--fps", "4", "--workers", "0", "-q"])
        .arg("--output")
        .arg(dir.join("f.png"))
        .output()
        .expect("run dray");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for (frame, time) in [(0, "0"), (2, "0.5"), (4, "1")] {
        let reference = common::render(
            &dir,
            &format!("t{frame}"),
            scene.to_str().expect("utf-8"),
            &[&view()[..], &["--time", time, "--workers", "0"]].concat(),
        );
        assert!(reference.ok, "{}", reference.stderr);
        let got = std::fs::read(dir.join(format!("f.{frame:04}.png")))
            .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
        assert!(
            got == std::fs::read(reference.png.expect("png")).expect("read"),
            "frame {frame} differs from dray render --time {time}"
        );
    }
    assert!(!dir.join("f.0001.png").exists(), "step 2 skips frame 1");
    let _ = std::fs::remove_dir_all(&dir);
}
