//! Animation frames on a real cluster (issue 42): `dray submit --frames 1..3 --fps 4`
//! to a `dray cluster` makes a job group of three ordinary jobs, each frame's PNG the
//! same bits as `dray render --time frame/fps` in one process; `dray submit --time`
//! renders the posed scene on workers too (the coordinator cuts the posed package); the
//! group shows in GetJob and ListJobs. Bad ranges and frame rates are refused, naming
//! what is wrong. Geometry that does not move stays warm from frame to frame: only the
//! domains the moving mesh touches are loaded and built again, in one process and on a
//! cluster, each frame still the bits of `dray render --time`.

mod common;
#[path = "../../scene-loader/tests/support/mod.rs"]
mod gltf_support;
mod support;

use std::path::{Path, PathBuf};
use std::process::Command;

/// A ground quad that stays and a triangle that slides along +X from x = -1 to x = 1
/// over one second ("slide"), written with the glTF test builder.
fn write_sliding(dir: &Path) -> PathBuf {
    write_slide(dir, "slide", 0.5, -1.0, 1.0)
}

/// A 4x4 ground quad at y = 0 that stays, and a triangle `half` wide each side of its
/// node that slides along +X from x = `from` to x = `to` over one second (the animation
/// "slide"), written as `name`.gltf with the glTF test builder.
fn write_slide(dir: &Path, name: &str, half: f32, from: f32, to: f32) -> PathBuf {
    let mut b = gltf_support::Builder::default();
    let ground = [
        -2.0, 0.0, -2.0, 2.0, 0.0, -2.0, 2.0, 0.0, 2.0, -2.0, 0.0, 2.0,
    ];
    b.floats(&ground, "VEC3"); // 0
    b.indices(&[0, 2, 1, 0, 3, 2]); // 1
    b.floats(&[-half, 0.0, 0.0, half, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3"); // 2
    b.floats(&[0.0, 1.0], "SCALAR"); // 3: key times
    b.floats(&[from, 0.0, 0.0, to, 0.0, 0.0], "VEC3"); // 4: key translations
    let rest = format!(
        r#""materials":[{{"doubleSided":true}}],
"meshes":[{{"name":"ground","primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"material":0}}]}},
          {{"name":"tri","primitives":[{{"attributes":{{"POSITION":2}},"material":0}}]}}],
"nodes":[{{"mesh":0}},{{"mesh":1,"translation":[{from},0,0]}}],
"scenes":[{{"nodes":[0,1]}}],
"animations":[{{"name":"slide","samplers":[{{"input":3,"output":4}}],
  "channels":[{{"sampler":0,"target":{{"node":1,"path":"translation"}}}}]}}]"#
    );
    b.write(dir, name, &rest)
}

/// The camera, light and image of every render here.
fn view() -> Vec<&'static str> {
    "--width 40 --height 30 --spp 2 --look-from 0,1.5,4 --look-at 0,0.4,0 --sun 30,60 \
     --animation slide"
        .split_whitespace()
        .collect()
}

/// The image of `dray render SCENE FLAGS --time TIME --workers 0`: one process, the
/// reference every frame on a cluster must equal.
fn render_time(dir: &Path, tag: &str, scene: &Path, flags: &[&str], time: &str) -> Vec<u8> {
    let scene = scene.to_str().expect("utf-8");
    let run = common::render(
        dir,
        tag,
        scene,
        &[flags, &["--time", time, "--workers", "0"]].concat(),
    );
    assert!(run.ok, "dray render {scene} --time {time}: {}", run.stderr);
    std::fs::read(run.png.expect("png")).expect("read the reference png")
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
        let want = render_time(&dir, &format!("render-{frame}"), &scene, &view(), time);
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
        let want = render_time(&dir, &format!("t{frame}"), &scene, &view(), time);
        let got = std::fs::read(dir.join(format!("f.{frame:04}.png")))
            .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
        assert!(
            got == want,
            "frame {frame} differs from dray render --time {time}"
        );
    }
    assert!(!dir.join("f.0001.png").exists(), "step 2 skips frame 1");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A limit that only catches hangs.
const HANG_SECS: f64 = 300.0;

/// Frames long enough to lose a worker in the middle of a group: domains spread over
/// every worker (the domain schedule), so the frame running at the kill loses some.
fn heavy_view() -> Vec<&'static str> {
    "--width 96 --height 72 --spp 8 --look-from 0,1.5,4 --look-at 0,0.4,0 --sun 30,60 \
     --animation slide --domains 6 --schedule domain"
        .split_whitespace()
        .collect()
}

fn text(log: &std::sync::Arc<std::sync::Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

fn succeeded(addr: &str, group: &str) -> usize {
    support::list_group(addr, group).map_or(0, |jobs| {
        jobs.iter()
            .filter(|j| {
                j.progress.as_ref().map(|p| p.state)
                    == Some(dray_proto::v1::JobState::Succeeded as i32)
            })
            .count()
    })
}

#[test]
fn a_group_of_24_frames_survives_a_killed_worker_each_frame_the_bits_of_render_time() {
    use std::process::Stdio;
    let dir = common::tmp("frames-kill");
    let scene = write_sliding(&dir);
    // A coordinator that declares a silent worker lost after 2 s, and three workers.
    let (_coordinator, addr, log) = support::logged_coordinator(&dir, 0, &[]);
    let workers: Vec<support::Proc> = (0..3).map(|_| support::worker(&addr)).collect();
    let registered = || text(&log).matches("worker registered").count();
    assert!(
        support::eventually(60.0, || registered() >= 3),
        "the workers did not register: {}",
        text(&log)
    );

    // Frames 0..23 at 24 fps: the slide's first second.
    let (frames, fps) = (24u32, 24.0f64);
    let mut cmd = support::dray();
    cmd.args(["submit", "slide.gltf", "--coordinator", &addr])
        .args(heavy_view())
        .args(["--frames", "0..23", "--fps", "24", "--output"])
        .arg(dir.join("kill.##.png"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut submit = support::Proc::spawn(cmd);
    let out = support::capture_stderr(&mut submit.child);
    let group = || {
        text(&out)
            .lines()
            .find_map(|l| l.strip_prefix("dray submit: job group "))
            .and_then(|l| l.split(' ').next())
            .map(str::to_string)
    };
    assert!(
        support::eventually(HANG_SECS, || group().is_some()),
        "no group in dray submit's output: {}",
        text(&out)
    );
    let group = group().expect("the group id");

    // Once a frame is done, and while frames remain, worker 1 is killed.
    assert!(
        support::eventually(HANG_SECS, || succeeded(&addr, &group) > 0),
        "no frame finished: {}\n{}",
        text(&out),
        text(&log)
    );
    let lost_before = text(&log).matches("worker lost").count();
    let done_at_kill = succeeded(&addr, &group);
    workers[1].signal(libc::SIGKILL);
    assert!(
        done_at_kill < frames as usize,
        "every frame ended before the kill ({done_at_kill} of {frames}): nothing was lost"
    );
    let status = submit.wait_timeout(HANG_SECS);
    let said = out.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: dray submit --frames: {said}"));
    assert!(
        status.success(),
        "the group did not survive a killed worker: {said}\n{}",
        text(&log)
    );
    assert!(
        support::eventually(HANG_SECS, || text(&log).matches("worker lost").count()
            > lost_before),
        "the coordinator never declared the killed worker lost:\n{}",
        text(&log)
    );
    assert_eq!(
        succeeded(&addr, &group),
        frames as usize,
        "ListJobs of group {group}"
    );
    let retried: u32 = support::list_group(&addr, &group)
        .unwrap_or_default()
        .iter()
        .filter_map(|j| j.stats.as_ref().map(|s| s.tiles_retried))
        .sum();
    eprintln!(
        "frames-kill: {done_at_kill} of {frames} frames were done at the kill; tiles retried \
         over the group: {retried}"
    );

    // Each frame: the bits of `dray render --time frame/fps` in one process.
    for frame in 0..frames {
        let time = (f64::from(frame) / fps).to_string();
        let want = render_time(&dir, &format!("ref-{frame}"), &scene, &heavy_view(), &time);
        let got = std::fs::read(dir.join(format!("kill.{frame:02}.png")))
            .unwrap_or_else(|e| panic!("frame {frame}'s image: {e}; submit said {said}"));
        assert!(
            got == want,
            "frame {frame}: the image differs from dray render --time {time} after a \
             worker was killed"
        );
    }
    drop(workers);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_unknown_animation_is_refused_at_submit_and_a_grid_poses_its_file() {
    use dray_proto::v1::{JobSpec, SubmitJobRequest};
    let dir = common::tmp("frames-refuse");
    let scene = write_sliding(&dir);
    let cluster = support::WorkerCluster::start(2, 4, &dir, &[]);

    // SubmitJob answers INVALID_ARGUMENT naming the field and what the file has, for a
    // lone job and for a group, and accepts nothing.
    let base = JobSpec {
        scene: "slide.gltf".into(),
        width: 16,
        height: 16,
        spp: 1,
        animation: "walk".into(),
        ..Default::default()
    };
    for spec in [
        JobSpec {
            time: Some(0.5),
            ..base.clone()
        },
        JobSpec {
            frames: "0..3".into(),
            fps: Some(4.0),
            ..base.clone()
        },
        JobSpec {
            scene: "grid:slide.gltf:2x1x1".into(),
            time: Some(0.5),
            ..base.clone()
        },
    ] {
        let status = support::with_client(&cluster.addr, |mut c| async move {
            c.submit_job(SubmitJobRequest { spec: Some(spec) })
                .await
                .err()
        })
        .expect("SubmitJob was accepted");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        assert_eq!(
            status.message(),
            "animation: \"slide.gltf\": no animation \"walk\" (the file has \"slide\")"
        );
    }
    let listed = support::with_client(&cluster.addr, |mut c| async move {
        Some(
            c.list_jobs(dray_proto::v1::ListJobsRequest::default())
                .await
                .ok()?
                .into_inner()
                .jobs,
        )
    })
    .expect("ListJobs");
    assert!(listed.is_empty(), "a refused job was accepted: {listed:?}");

    // A time on a grid of the file poses every copy: the cluster's image is the bits
    // of `dray render --time`, and another time gives another image.
    let grid = PathBuf::from(format!("grid:{}:2x1x1", scene.to_str().expect("utf-8")));
    let png = dir.join("grid.png");
    let mut cmd = support::dray();
    cmd.args([
        "submit",
        "grid:slide.gltf:2x1x1",
        "--coordinator",
        &cluster.addr,
    ])
    .args(view())
    .args(["--time", "0.25", "--output"])
    .arg(&png);
    support::run_to_success(cmd, "dray submit grid --time", HANG_SECS);
    let mut images = Vec::new();
    for time in ["0.25", "0.75"] {
        images.push(render_time(
            &dir,
            &format!("grid-{time}"),
            &grid,
            &view(),
            time,
        ));
    }
    assert!(
        std::fs::read(&png).expect("the grid's image") == images[0],
        "the cluster's grid at 0.25 s differs from dray render --time 0.25"
    );
    assert!(
        images[0] != images[1],
        "the grid's copies did not move between 0.25 s and 0.75 s"
    );
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A ground quad that stays and a small triangle that slides along +X from x = 1.3 to
/// x = 1.5 over one second ("slide"): it stays in the +x, near-z = 0 part of the ground,
/// and every frame has the same bounds, so the frames are cut alike and the domains it
/// never touches are the same in each.
fn write_still_and_moving(dir: &Path) -> PathBuf {
    write_slide(dir, "still", 0.1, 1.3, 1.5)
}

/// (domain_loads, domains_warm) of a `--stats` file.
fn loads(path: &Path) -> (u64, u64) {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("the statistics {}: {e}", path.display()));
    let v: serde_json::Value = serde_json::from_str(&text).expect("statistics JSON");
    let n = |k: &str| {
        v[k].as_u64()
            .unwrap_or_else(|| panic!("no {k} in {}", path.display()))
    };
    (n("domain_loads"), n("domains_warm"))
}

/// The frames 0..3 at 4 fps of the still-and-moving scene, cut into 4 domains.
fn moving_view() -> Vec<&'static str> {
    let mut v = view();
    v.extend(["--domains", "4"]);
    v
}

/// Per frame: after the first, the domains the triangle never touches are found warm
/// and only the others are loaded; every domain is used in every frame.
fn assert_static_domains_stay_warm(counts: &[(u64, u64)], what: &str) {
    let (first, _) = counts[0];
    assert!(first >= 2, "{what}: frame 0 loaded {counts:?}");
    assert_eq!(
        counts[0].1, 0,
        "{what}: nothing is warm in frame 0: {counts:?}"
    );
    for (k, &(l, w)) in counts.iter().enumerate().skip(1) {
        assert!(
            l >= 1,
            "{what}: frame {k} moved a mesh and loaded nothing: {counts:?}"
        );
        assert!(
            w >= 1,
            "{what}: frame {k} found no static domain warm: {counts:?}"
        );
        assert_eq!(
            l + w,
            first,
            "{what}: frame {k} used other domains: {counts:?}"
        );
    }
}

/// `dray render --frames` in one process keeps its actors from frame to frame: the
/// static domains are loaded and built once, in frame 0, the moving triangle's domains
/// in every frame (on a 2x1x2 grid: the triangle is on the z = 0 wall of the two +x
/// domains, so 4 loads, then 2 loads and 2 warm a frame; on a kd split, cut once with
/// the first frame's layout, at least one is warm). Each frame is the bits of `dray
/// render --time`.
#[test]
fn render_frames_loads_static_domains_once_and_keeps_the_bits() {
    let dir = common::tmp("frames-warm");
    let scene = write_still_and_moving(&dir);
    let frames = [(0u32, "0"), (1, "0.25"), (2, "0.5"), (3, "0.75")];
    for layout in ["grid", "kd"] {
        let out = Command::new(env!("CARGO_BIN_EXE_dray"))
            .arg("render")
            .arg(&scene)
            .args(moving_view())
            .args(["--layout", layout, "--workers", "1", "-q"])
            .args(["--frames", "0..3", "--fps", "4", "--stats"])
            .arg(dir.join(format!("{layout}.json")))
            .arg("--output")
            .arg(dir.join(format!("{layout}.png")))
            .output()
            .expect("run dray");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let counts: Vec<(u64, u64)> = frames
            .iter()
            .map(|(f, _)| loads(&dir.join(format!("{layout}.{f:04}.json"))))
            .collect();
        eprintln!("frames-warm {layout}: (loads, warm) per frame {counts:?}");
        assert_static_domains_stay_warm(&counts, layout);
        if layout == "grid" {
            assert_eq!(counts, [(4, 0), (2, 2), (2, 2), (2, 2)]);
        }
        for (frame, time) in frames {
            let want = render_time(
                &dir,
                &format!("{layout}-ref-{frame}"),
                &scene,
                &moving_view(),
                time,
            );
            let got = std::fs::read(dir.join(format!("{layout}.{frame:04}.png")))
                .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
            assert!(
                got == want,
                "{layout}: frame {frame} differs from dray render --time {time}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A job group on a one-worker cluster, one frame at a time (`--max-running-jobs 1`, in
/// the order the frames' scenes are ready):
/// the coordinator cuts every frame with the first frame's kd layout, and the worker,
/// keying loaded domains by their content, loads the static domains once; each frame's
/// PNG is the bits of `dray render --time`.
#[test]
fn a_group_on_a_cluster_loads_static_domains_once_and_keeps_the_bits() {
    let dir = common::tmp("frames-warm-cluster");
    let scene = write_still_and_moving(&dir);
    let cluster = support::WorkerCluster::start(1, 5, &dir, &["--max-running-jobs", "1"]);
    let mut cmd = support::dray();
    cmd.args(["submit", "still.gltf", "--coordinator", &cluster.addr])
        .args(moving_view())
        .args([
            "--layout", "kd", "--frames", "0..3", "--fps", "4", "--stats",
        ])
        .arg(dir.join("s.json"))
        .arg("--output")
        .arg(dir.join("g.png"));
    let said = support::run_to_success(cmd, "dray submit --frames", HANG_SECS);
    let frames = [(0u32, "0"), (1, "0.25"), (2, "0.5"), (3, "0.75")];
    let counts: Vec<(u64, u64)> = frames
        .iter()
        .map(|(f, _)| loads(&dir.join(format!("s.{f:04}.json"))))
        .collect();
    eprintln!("frames-warm-cluster: (loads, warm) per frame {counts:?}");
    // The frames are dealt in the order their scenes are ready, not always frame
    // order: the one that ran first is the one that found nothing warm.
    let mut in_run_order = counts.clone();
    in_run_order.sort_by_key(|&(_, warm)| warm);
    assert_static_domains_stay_warm(&in_run_order, &format!("cluster ({said})"));
    for (frame, time) in frames {
        let want = render_time(&dir, &format!("ref-{frame}"), &scene, &moving_view(), time);
        let got = std::fs::read(dir.join(format!("g.{frame:04}.png")))
            .unwrap_or_else(|e| panic!("frame {frame}: {e}; submit said {said}"));
        assert!(
            got == want,
            "frame {frame}: the cluster's image differs from dray render --time {time}"
        );
    }
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}
