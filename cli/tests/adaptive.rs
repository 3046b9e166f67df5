//! Adaptive sampling (`--noise-threshold`) end to end: the same bits and the same counts
//! from the reference renderer (`--workers 0`, any thread count), from in-process workers
//! (real gRPC over loopback) under every schedule and with a memory budget, and from a
//! `dray cluster` of processes through `dray submit`; tiles with nothing to converge
//! stop at the first decision while lit ones take every sample, as the `samples` AOV
//! and `--stats` say; bad values refused naming the flag.

mod common;
mod support;

use std::path::Path;

/// The Cornell box seen through a wide lens: it fills the two middle tiles of a 4 x 3
/// grid of 32-pixel tiles, and the ten around them see only the black outside.
const SCENE: &str = "cornell";
const SIZE: [&str; 10] = [
    "--width", "128", "--height", "96", "--spp", "64", "--seed", "5", "--fov", "100",
];
/// Below the lit tiles' error at 16 and 32 samples (about 0.03 and 0.02).
const THRESHOLD: [&str; 2] = ["--noise-threshold", "0.01"];
/// Tiles whose every pixel sees the black outside (row-major over the 4 x 3 grid).
const DARK_TILES: [usize; 10] = [0, 1, 2, 3, 4, 7, 8, 9, 10, 11];

/// `dray render SCENE SIZE THRESHOLD extra --aov samples --exr DIR/TAG.exr`: the EXR's
/// bytes and the stats.
fn render(dir: &Path, tag: &str, extra: &[&str]) -> (Vec<u8>, serde_json::Value) {
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let args = [
        &SIZE[..],
        &THRESHOLD[..],
        &["--aov", "samples", "--exr", &exr_arg],
        extra,
    ]
    .concat();
    let r = common::render(dir, tag, SCENE, &args);
    assert!(r.ok, "{tag}: {}", r.stderr);
    (std::fs::read(&exr).expect("exr"), r.stats.expect("stats"))
}

/// (tiles stopped, samples saved) from a summary or `dray submit --stats`.
fn saved(stats: &serde_json::Value) -> (u64, u64) {
    let get = |k: &str| {
        stats[k]
            .as_u64()
            .unwrap_or_else(|| panic!("no {k} in {stats}"))
    };
    (get("tiles_stopped"), get("samples_saved"))
}

#[test]
fn dark_tiles_stop_early_and_lit_ones_take_every_sample() {
    let dir = common::tmp("adaptive-counts");
    let (exr, stats) = render(&dir, "ref", &["--workers", "0"]);
    let ch = common::exr_channels(&exr);
    let samples = &ch.iter().find(|c| c.0 == "samples.Y").expect("samples.Y").1;
    let tile_of = |p: usize| (p / 128 / 32) * 4 + (p % 128) / 32;
    for (p, &n) in samples.iter().enumerate() {
        let want = if DARK_TILES.contains(&tile_of(p)) {
            16.0
        } else {
            64.0
        };
        assert_eq!(n, want, "pixel {p} (tile {})", tile_of(p));
    }
    assert_eq!(saved(&stats), (10, 10 * 32 * 32 * (64 - 16)), "{stats}");
    // The lit tiles took no fewer rays than without a threshold: they are the same
    // image there, and the dark ones are black either way.
    let plain = common::render(
        &dir,
        "plain",
        SCENE,
        &[&SIZE[..], &["--workers", "0"]].concat(),
    );
    assert!(plain.ok, "{}", plain.stderr);
    let plain_stats = plain.stats.expect("stats");
    assert_eq!(saved(&plain_stats), (0, 0), "{plain_stats}");
    assert!(
        common::rays(&stats, "camera") < common::rays(&plain_stats, "camera"),
        "adaptive sampling made as many camera rays: {stats}"
    );
    assert_eq!(
        common::rgb(&dir.join("ref.png")),
        common::rgb(plain.png.as_deref().expect("png")),
        "stopping black tiles changed the image"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn adaptive_sampling_gives_the_same_bits_on_every_configuration() {
    let dir = common::tmp("adaptive-bits");
    let (want, stats) = render(&dir, "ref", &["--workers", "0", "--threads", "2"]);
    assert!(saved(&stats).0 > 0, "{stats}");
    for (tag, extra) in [
        ("w0-t1", &["--workers", "0", "--threads", "1"][..]),
        ("w0-domains", &["--workers", "0", "--domains", "4"][..]),
        ("w1", &["--workers", "1"][..]),
        ("w2", &["--workers", "2", "--domains", "4"][..]),
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
        (
            "w2-domain",
            &["--workers", "2", "--domains", "4", "--schedule", "domain"][..],
        ),
        (
            "w2-replicated",
            &["--workers", "2", "--schedule", "replicated"][..],
        ),
        (
            "w2-budget",
            // A memory budget would trace passes ahead; adaptive sampling turns it off.
            &[
                "--workers",
                "2",
                "--domains",
                "8",
                "--memory-budget",
                "512M",
            ][..],
        ),
    ] {
        let (got, s) = render(&dir, tag, extra);
        assert!(got == want, "{tag}: differs from --workers 0");
        assert_eq!(saved(&s), saved(&stats), "{tag}: {s}");
        if tag == "w2-budget" {
            assert_eq!(s["passes_ahead"].as_u64(), Some(0), "{s}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cluster_gives_dray_renders_bits_with_adaptive_sampling() {
    let dir = common::tmp("adaptive-cluster");
    let (want, stats) = render(&dir, "ref", &["--workers", "0"]);
    let c = support::WorkerCluster::start(2, 0, &dir, &[]);
    let (got, s) = support::submit_exr(
        &c.addr,
        &dir,
        SCENE,
        &[&SIZE[..], &THRESHOLD[..], &["--aov", "samples"]].concat(),
    );
    assert!(got == want, "the cluster's EXR differs from dray render's");
    assert_eq!(saved(&s), saved(&stats), "{s}");
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_thresholds_are_refused_naming_the_flag() {
    let dir = common::tmp("adaptive-bad");
    for (args, says) in [
        (vec!["--noise-threshold", "0"], "default), got 0 "),
        (vec!["--noise-threshold", "1.5"], "default), got 1.5 "),
        (vec!["--noise-threshold", "nan"], "above 0 and at most 1"),
        (vec!["--noise-threshold", "low"], "\"low\" is not a number"),
        (
            vec!["--noise-threshold", "0.01", "--passes", "one"],
            "--noise-threshold stops tiles between passes",
        ),
    ] {
        for workers in ["0", "2"] {
            let r = common::render(
                &dir,
                "bad",
                SCENE,
                &[&SIZE[..], &args[..], &["--workers", workers]].concat(),
            );
            assert!(!r.ok, "{args:?} was accepted");
            assert!(
                r.stderr.contains(says) && r.stderr.contains("--noise-threshold"),
                "{args:?}: {}",
                r.stderr
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
