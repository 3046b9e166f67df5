//! `--clamp-indirect` and `--aov` end to end: the same bits from the reference renderer
//! (`--workers 0`), from in-process workers (`--workers 2`, real gRPC over loopback,
//! in progressive passes too) and from a `dray cluster` of processes through `dray
//! submit`; the clamp counted; the AOVs' channels in the EXR with the Cornell box's
//! wall colours; bad values refused naming the flag.

mod common;
mod support;

use std::path::Path;

/// The Cornell box with a glass sphere: caustics, so fireflies for the clamp.
const SCENE: &str = "cornell:glass";
const SIZE: [&str; 8] = [
    "--width", "32", "--height", "32", "--spp", "4", "--seed", "3",
];

/// `dray render SCENE SIZE extra --exr DIR/TAG.exr`: the EXR's bytes and the stats.
fn render(dir: &Path, tag: &str, extra: &[&str]) -> (Vec<u8>, serde_json::Value) {
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let args = [&SIZE[..], &["--max-depth", "6", "--exr", &exr_arg], extra].concat();
    let r = common::render(dir, tag, SCENE, &args);
    assert!(r.ok, "{tag}: {}", r.stderr);
    (std::fs::read(&exr).expect("exr"), r.stats.expect("stats"))
}

fn clamped(stats: &serde_json::Value) -> u64 {
    stats["clamped_indirect"]
        .as_u64()
        .unwrap_or_else(|| panic!("no clamped_indirect in {stats}"))
}

#[test]
fn the_clamp_gives_the_same_bits_on_workers_and_is_counted() {
    let dir = common::tmp("noise-clamp");
    let clamp = ["--clamp-indirect", "1"];
    let (want, stats) = render(&dir, "ref", &[&clamp[..], &["--workers", "0"]].concat());
    assert!(clamped(&stats) > 0, "{stats}");
    for (tag, extra) in [
        ("w2", &["--workers", "2", "--domains", "4"][..]),
        (
            "w2-passes",
            &["--workers", "2", "--domains", "4", "--passes", "doubling"][..],
        ),
        (
            "w2-image-plane",
            &[
                "--workers",
                "2",
                "--domains",
                "4",
                "--schedule",
                "image-plane",
            ][..],
        ),
    ] {
        let (got, s) = render(&dir, tag, &[&clamp[..], extra].concat());
        assert!(got == want, "{tag}: differs from --workers 0");
        assert_eq!(clamped(&s), clamped(&stats), "{tag}: {s}");
    }
    // Without the clamp: another image, nothing clamped.
    let (free, stats) = render(&dir, "free", &["--workers", "0"]);
    assert!(free != want, "the clamp changed nothing");
    assert_eq!(clamped(&stats), 0, "{stats}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn aovs_give_the_same_bits_on_workers_and_the_walls_colours() {
    let dir = common::tmp("noise-aovs");
    let aov = ["--aov", "albedo,normal,depth,samples"];
    let (want, _) = render(&dir, "ref", &[&aov[..], &["--workers", "0"]].concat());
    for (tag, extra) in [
        ("w2", &["--workers", "2", "--domains", "4"][..]),
        (
            "w2-passes",
            &["--workers", "2", "--domains", "4", "--passes", "doubling"][..],
        ),
        (
            "w2-ahead",
            // A memory budget: the workers trace passes ahead and hold their sums.
            &[
                "--workers",
                "2",
                "--domains",
                "8",
                "--passes",
                "1",
                "--memory-budget",
                "512M",
            ][..],
        ),
    ] {
        let (got, stats) = render(&dir, tag, &[&aov[..], extra].concat());
        assert!(got == want, "{tag}: differs from --workers 0");
        if tag == "w2-ahead" {
            assert!(stats["passes_ahead"].as_u64() > Some(0), "{stats}");
        }
    }
    let ch = common::exr_channels(&want);
    let names: Vec<&str> = ch.iter().map(|c| c.0.as_str()).collect();
    assert_eq!(
        names,
        [
            "B",
            "G",
            "R",
            "albedo.B",
            "albedo.G",
            "albedo.R",
            "depth.Z",
            "normal.X",
            "normal.Y",
            "normal.Z",
            "samples.Y"
        ]
    );
    let get = |name: &str| &ch.iter().find(|c| c.0 == name).expect(name).1;
    // The red wall (the box's left, +X) fills the middle of the image's left edge: its
    // albedo is the wall's paint (dray_scene's Cornell RED).
    let p = 16 * 32 + 1;
    let albedo = [get("albedo.R")[p], get("albedo.G")[p], get("albedo.B")[p]];
    let red = [0.63f32, 0.065, 0.05];
    for k in 0..3 {
        assert!((albedo[k] - red[k]).abs() < 1e-6, "albedo {albedo:?}");
    }
    // Its normal faces into the box (-X), and it is nearer than the back wall.
    assert!(
        get("normal.X")[p] < -0.999,
        "normal.X {}",
        get("normal.X")[p]
    );
    let (side, middle) = (get("depth.Z")[p], get("depth.Z")[16 * 32 + 16]);
    assert!(
        side > 0.0 && side < middle && middle.is_finite(),
        "{side} {middle}"
    );
    assert!(get("samples.Y").iter().all(|&s| s == 4.0));
    // The beauty is the image without AOVs.
    let (plain, _) = render(&dir, "plain", &["--workers", "0"]);
    let beauty = |b: &[u8]| {
        common::exr_channels(b)
            .into_iter()
            .filter(|c| ["R", "G", "B"].contains(&c.0.as_str()))
            .collect::<Vec<_>>()
    };
    assert!(beauty(&plain) == beauty(&want), "AOVs changed the beauty");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cluster_gives_dray_renders_bits_with_the_clamp_and_aovs() {
    let dir = common::tmp("noise-cluster");
    let knobs = [
        "--clamp-indirect",
        "1",
        "--aov",
        "albedo,normal,depth",
        "--domains",
        "4",
    ];
    let (want, stats) = render(&dir, "ref", &[&knobs[..], &["--workers", "0"]].concat());
    let c = support::WorkerCluster::start(2, 0, &dir, &[]);
    let (got, s) = support::submit_exr(
        &c.addr,
        &dir,
        SCENE,
        &[&SIZE[..], &["--max-depth", "6"], &knobs[..]].concat(),
    );
    assert!(got == want, "the cluster's EXR differs from dray render's");
    assert_eq!(clamped(&s), clamped(&stats), "{s}");
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The report bytes of a `--stats` JSON: (messages, bytes, aov_bytes).
fn reports(stats: &serde_json::Value) -> (u64, u64, u64) {
    let r = &stats["reports"];
    let get = |k: &str| {
        r[k].as_u64()
            .unwrap_or_else(|| panic!("no reports.{k} in {stats}"))
    };
    (get("messages"), get("bytes"), get("aov_bytes"))
}

/// AOV sums travel in the workers' reports and are counted there (`JobStats.reports`):
/// a job with AOVs reports more bytes than the same job without, and its AOV part is
/// at least the 68 bytes of one entry for every pixel a camera ray hit (each such pixel
/// is in some report). `coordinator/tests/cluster_service.rs` checks that the count is
/// exactly the bytes of the messages sent.
#[test]
fn report_bytes_count_the_aovs() {
    let dir = common::tmp("noise-report-bytes");
    let workers = ["--workers", "2", "--domains", "4"];
    let aov = ["--aov", "albedo,normal,depth"];
    let (exr, with) = render(&dir, "aovs", &[&aov[..], &workers[..]].concat());
    let (_, without) = render(&dir, "plain", &workers);
    let (n_with, bytes_with, aov_with) = reports(&with);
    let (n_without, bytes_without, aov_without) = reports(&without);
    assert!(n_with > 0 && n_without > 0, "{with}\n{without}");
    assert_eq!(aov_without, 0, "{without}");
    let hit = common::exr_channels(&exr)
        .into_iter()
        .find(|c| c.0 == "depth.Z")
        .expect("depth.Z")
        .1
        .iter()
        .filter(|z| z.is_finite())
        .count() as u64;
    assert!(hit > 0);
    assert!(
        aov_with >= 68 * hit && aov_with < bytes_with,
        "{aov_with} AOV bytes of {bytes_with} for {hit} pixels hit"
    );
    eprintln!(
        "reports with AOVs: {n_with} messages, {bytes_with} bytes ({aov_with} of AOVs); \
         without: {n_without} messages, {bytes_without} bytes; {hit} pixels hit"
    );
    assert!(
        bytes_with > bytes_without,
        "with AOVs {bytes_with} bytes, without {bytes_without}"
    );
    // `dray render --workers 0` sends no reports.
    let (_, alone) = render(&dir, "alone", &[&aov[..], &["--workers", "0"]].concat());
    assert_eq!(reports(&alone), (0, 0, 0), "{alone}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_values_are_refused_naming_the_flag() {
    let dir = common::tmp("noise-bad");
    let exr = dir.join("x.exr");
    let exr = exr.to_string_lossy();
    for (args, says) in [
        (vec!["--clamp-indirect", "0"], "--clamp-indirect"),
        (vec!["--clamp-indirect", "nan"], "finite number above 0"),
        (
            vec!["--aov", "albdo", "--exr", &exr],
            "unknown AOV \"albdo\"",
        ),
        (vec!["--aov", "depth,depth", "--exr", &exr], "named twice"),
        (vec!["--aov", "depth"], "give --exr FILE"),
    ] {
        let r = common::render(
            &dir,
            "bad",
            SCENE,
            &[&args[..], &["--workers", "0"]].concat(),
        );
        assert!(!r.ok, "{args:?} was accepted");
        assert!(r.stderr.contains(says), "{args:?}: {}", r.stderr);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
