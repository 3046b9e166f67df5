//! Environment maps from the command line (`--env-map FILE`, `--env-rotation`,
//! `--env-intensity`) end to end: the same bits from the reference renderer
//! (`--workers 0`), from in-process workers (which take the coordinator's decoded map
//! from memory) and from a real `dray cluster` whose workers fetch the map from the
//! coordinator's PackageService (`--fetch-packages always`); the effect reported only
//! when used; GetJob showing every value used; bad files refused with a message naming
//! the flag (or the field) and what is wrong. The maps are written here.

mod common;
mod support;

use common::effects;
use std::path::Path;

use support::WorkerCluster;

/// Ports of this file's cluster (see `support::cluster_base_port`).
const SLOT: u16 = 7;

/// A map with a bright warm patch above the horizon (so importance sampling matters),
/// a dim blue sky and a darker ground.
fn sky(x: usize, y: usize, w: usize, h: usize) -> (f32, f32, f32) {
    if (w / 5..w / 5 + 3).contains(&x) && (h / 4..h / 4 + 2).contains(&y) {
        (40.0, 30.0, 18.0)
    } else if y < h / 2 {
        (0.3, 0.45, 0.8)
    } else {
        (0.12, 0.1, 0.08)
    }
}

fn write_exr(path: &Path, w: usize, h: usize) {
    exr::prelude::write_rgb_file(path, w, h, |x, y| sky(x, y, w, h)).expect("write exr");
}

fn write_hdr(path: &Path, w: usize, h: usize) {
    let px: Vec<image::Rgb<f32>> = (0..w * h)
        .map(|i| {
            let (r, g, b) = sky(i % w, i / w, w, h);
            image::Rgb([r, g, b])
        })
        .collect();
    let out = std::io::BufWriter::new(std::fs::File::create(path).expect("create hdr"));
    image::codecs::hdr::HdrEncoder::new(out)
        .encode(&px, w, h)
        .expect("write hdr");
}

const FLAGS: [&str; 12] = [
    "--width",
    "48",
    "--height",
    "36",
    "--spp",
    "4",
    "--seed",
    "5",
    "--domains",
    "4",
    "--integrator",
    "path",
];

/// `dray render box.ply` with `extra` on `workers`: the EXR's bytes and the stats.
fn render(dir: &Path, tag: &str, workers: &str, extra: &[&str]) -> (Vec<u8>, serde_json::Value) {
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let scene = dir.join("box.ply");
    let args = [
        &FLAGS[..],
        &["--workers", workers, "--exr", &exr_arg][..],
        extra,
    ]
    .concat();
    let r = common::render(dir, tag, &scene.to_string_lossy(), &args);
    assert!(r.ok, "{tag}: {}", r.stderr);
    (
        std::fs::read(&exr).expect("read exr"),
        r.stats.expect("stats"),
    )
}

/// `dray submit` to `addr` with `args`, waited for (its stderr and whether it
/// succeeded).
fn submit(addr: &str, args: &[&str]) -> (bool, String) {
    let mut cmd = support::dray();
    cmd.args(["submit", "--coordinator", addr])
        .args(args)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    let mut p = support::Proc::spawn(cmd);
    let err = support::capture_stderr(&mut p.child);
    let status = p.wait_timeout(180.0);
    let text = err.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: dray submit {args:?}: {text}"));
    (status.success(), text)
}

#[test]
fn an_env_map_gives_the_same_bits_everywhere_and_reaches_remote_workers() {
    let dir = common::tmp("env-map");
    common::write_box_ply(&dir.join("box.ply"));
    write_exr(&dir.join("sky.exr"), 64, 32);
    write_hdr(&dir.join("sky.hdr"), 64, 32);
    let map = |f: &str| dir.join(f).to_string_lossy().into_owned();
    let (exr_map, hdr_map) = (map("sky.exr"), map("sky.hdr"));
    let lit = [
        "--env-map",
        &exr_map,
        "--env-rotation",
        "-30",
        "--env-intensity",
        "1.5",
    ];
    let (want, stats) = render(&dir, "ref", "0", &lit);
    assert!(effects(&stats).contains(&"env_map".to_string()), "{stats}");
    let (got, stats2) = render(&dir, "w2", "2", &lit);
    assert!(got == want, "2 in-process workers differ from --workers 0");
    assert_eq!(effects(&stats2), effects(&stats));
    // The map, its rotation and its intensity each change the image; a scene without a
    // map does not pay for one.
    let (none, stats) = render(&dir, "none", "0", &[]);
    assert!(none != want, "the map changed nothing");
    assert!(!effects(&stats).contains(&"env_map".to_string()), "{stats}");
    let (turned, _) = render(&dir, "turned", "0", &["--env-map", &exr_map]);
    assert!(turned != want, "rotation and intensity changed nothing");
    let (hdr, _) = render(&dir, "hdr", "0", &["--env-map", &hdr_map]);
    assert!(hdr != none, "the .hdr map changed nothing");

    // A real cluster whose workers never read the coordinator's disk: the map (as the
    // package) comes through PackageService, checksummed.
    let cluster = WorkerCluster::start(2, SLOT, &dir, &["--fetch-packages", "always"]);
    let out = dir.join("cluster.exr");
    let png = dir.join("cluster.png");
    let (ok, err) = submit(
        &cluster.addr,
        &[
            &["box.ply"][..],
            &FLAGS[..],
            &[
                "--env-map",
                "sky.exr",
                "--env-rotation",
                "-30",
                "--env-intensity",
                "1.5",
                "--output",
                &png.to_string_lossy(),
                "--exr",
                &out.to_string_lossy(),
            ][..],
        ]
        .concat(),
    );
    assert!(
        ok,
        "dray submit failed: {err}\ncluster log:\n{}",
        cluster.log()
    );
    assert!(
        std::fs::read(&out).expect("cluster exr") == want,
        "2 fetching workers differ from --workers 0; cluster log:\n{}",
        cluster.log()
    );
    let id = support::submitted_job_id(&err).expect("job id");
    let job = support::get_job(&cluster.addr, &id).expect("GetJob");
    let e = job
        .spec
        .and_then(|s| s.lighting)
        .and_then(|l| l.env_map)
        .expect("GetJob shows the map");
    assert_eq!(
        (e.path.as_str(), e.rotation_deg, e.intensity),
        ("sky.exr", Some(-30.0), Some(1.5))
    );
    let stats = job.stats.expect("stats");
    assert_eq!(stats.workers, 2);
    assert!(stats.effects.contains(&"env_map".to_string()), "{stats:?}");
    // Defaults filled in, and bad files refused naming the field.
    let (ok, err) = submit(
        &cluster.addr,
        &[
            &["box.ply"][..],
            &FLAGS[..],
            &["--env-map", "sky.hdr", "--output", &png.to_string_lossy()][..],
        ]
        .concat(),
    );
    assert!(ok, "{err}");
    let id = support::submitted_job_id(&err).expect("job id");
    let e = support::get_job(&cluster.addr, &id)
        .and_then(|j| j.spec)
        .and_then(|s| s.lighting)
        .and_then(|l| l.env_map)
        .expect("map");
    assert_eq!((e.rotation_deg, e.intensity), (Some(0.0), Some(1.0)));
    write_nan_exr(&dir.join("nan.exr"));
    for (map, says) in [
        ("missing.hdr", "no such file under the scene root"),
        ("../outside.hdr", "no such file under the scene root"),
        ("box.ply", "unsupported file type"),
        ("nan.exr", "pixel (3, 1)"),
    ] {
        let (ok, err) = submit(
            &cluster.addr,
            &[
                &["box.ply"][..],
                &FLAGS[..],
                &["--env-map", map, "--output", &png.to_string_lossy()][..],
            ]
            .concat(),
        );
        assert!(!ok, "--env-map {map} was accepted: {err}");
        assert!(
            err.contains("lighting.env_map.path") && err.contains(says),
            "--env-map {map}: {err}"
        );
        assert!(
            !err.contains(&*dir.to_string_lossy()),
            "the scene root shows: {err}"
        );
    }
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 4 x 2 map whose pixel (3, 1) is NaN.
fn write_nan_exr(path: &Path) {
    exr::prelude::write_rgb_file(path, 4, 2, |x, y| {
        if (x, y) == (3, 1) {
            (f32::NAN, 0.0, 0.0)
        } else {
            (1.0, 1.0, 1.0)
        }
    })
    .expect("write exr");
}

#[test]
fn bad_env_maps_are_refused_naming_the_flag() {
    let dir = common::tmp("env-map-bad");
    let nan = dir.join("nan.exr");
    write_nan_exr(&nan);
    let big = dir.join("big.hdr");
    std::fs::write(
        &big,
        b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4096 +X 4097\n",
    )
    .expect("write header");
    let junk = dir.join("junk.hdr");
    std::fs::write(&junk, b"no radiance here").expect("write junk");
    let path = |p: &Path| p.to_string_lossy().into_owned();
    let (nan, big, junk) = (path(&nan), path(&big), path(&junk));
    let missing = path(&dir.join("missing.exr"));
    for (args, says) in [
        (vec!["--env-map", &missing], "no such file"),
        (vec!["--env-map", "sky.png"], "unsupported file type"),
        (vec!["--env-map", &nan], "pixel (3, 1)"),
        (vec!["--env-map", &big], "4097x4096 pixels is more than"),
        (
            vec!["--env-map", &junk],
            "not a readable Radiance .hdr image",
        ),
        (
            vec!["--env-map", &nan, "--env-intensity", "-1"],
            "non-negative",
        ),
        (vec!["--env-map", &nan, "--env-rotation", "inf"], "finite"),
    ] {
        let flag = args[args.len() - 2];
        for workers in ["0", "2"] {
            let mut all = args.clone();
            all.extend(["--workers", workers]);
            let r = common::render(&dir, "bad", "cornell", &all);
            assert!(!r.ok, "{args:?} was accepted");
            assert!(
                r.stderr.contains(flag) && r.stderr.contains(says),
                "{args:?} on {workers} workers: {}",
                r.stderr
            );
        }
    }
    // The map's knobs without a map are refused, not ignored.
    let r = common::render(&dir, "bad", "cornell", &["--env-intensity", "2"]);
    assert!(!r.ok && r.stderr.contains("--env-map"), "{}", r.stderr);
    let _ = std::fs::remove_dir_all(&dir);
}
