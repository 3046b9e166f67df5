//! Same bits everywhere: cutting the scene into domains, each with its own BVH, and
//! walking rays through them gives the very same image as one BVH, for every integrator
//! and both layouts. Also `dray partition` end to end.

mod common;

use std::process::Command;

use common::{render, tmp};

#[test]
fn domains_do_not_change_a_single_bit() {
    let d = tmp("domains");
    for (scene, integ) in [
        ("cornell:glass", "path"),
        ("cornell:mirror", "whitted"),
        ("spheres:40", "raycast"),
        ("city:3", "ao"),
    ] {
        let args = [
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "2",
            "--integrator",
            integ,
        ];
        let one = render(&d, "one", scene, &args);
        assert!(one.ok, "{}", one.stderr);
        let reference = std::fs::read(one.png.unwrap()).unwrap();
        for (n, layout) in [("4", "grid"), ("9", "kd"), ("27", "grid")] {
            let r = render(
                &d,
                "many",
                scene,
                &[&args[..], &["--domains", n, "--layout", layout]].concat(),
            );
            assert!(r.ok, "{}", r.stderr);
            assert_eq!(
                std::fs::read(r.png.unwrap()).unwrap(),
                reference,
                "{scene} ({integ}) with {n} {layout} domains differs from one BVH"
            );
        }
    }
}

/// `dray partition ARGS`, run to the end.
fn partition(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dray"))
        .arg("partition")
        .args(args)
        .output()
        .expect("run dray")
}

#[test]
fn partition_writes_a_package_and_rejects_bad_input() {
    let d = tmp("partition");
    let out = d.join("pkg");
    let run = partition;
    let ok = run(&[
        "soup:5000",
        "--domains",
        "8",
        "--layout",
        "kd",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let line = String::from_utf8_lossy(&ok.stdout);
    let v: serde_json::Value = serde_json::from_str(line.trim()).expect("one JSON line");
    assert_eq!(v["domains"], 8);
    assert!(out.join("manifest.json").is_file());
    let bad = run(&[
        "soup:5000",
        "--domains",
        "0",
        "--out",
        d.join("x").to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.starts_with("dray: error:"), "{err}");
}

/// `dray partition` streams a PLY file (same package as the loaded scene, checked in
/// dray-scene's tests) and a malformed one is a one-line error naming the file and face.
#[test]
fn partition_streams_a_ply_and_rejects_a_malformed_one() {
    let d = tmp("partition-ply");
    let run = partition;
    let ply = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
               property float z\nelement face 2\nproperty list uchar int vertex_indices\n\
               end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 1\n3 0 1 2\n4 0 2 3 1\n";
    let good = d.join("good.ply");
    std::fs::write(&good, ply).unwrap();
    let out = d.join("pkg");
    let ok = run(&[
        good.to_str().unwrap(),
        "--domains",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let v: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&ok.stdout).trim()).expect("one JSON line");
    assert_eq!(v["triangles"], 3);
    assert!(out.join("manifest.json").is_file());

    let bad = d.join("bad.ply");
    std::fs::write(&bad, ply.replace("4 0 2 3 1", "4 0 2 7 1")).unwrap();
    let r = run(&[
        bad.to_str().unwrap(),
        "--domains",
        "2",
        "--out",
        d.join("x").to_str().unwrap(),
    ]);
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("bad.ply") && err.contains("face 1") && err.contains("out of range"),
        "{err}"
    );
    assert!(!d.join("x").exists(), "nothing written for a bad file");
}

/// `dray render` runs the job on in-process worker actors (coordinator, in-memory
/// package, gRPC ray streams, credit, reports): the image is the reference renderer's
/// (`--workers 0`, tiles traced with no actors), bit for bit, and the rays counted by
/// kind are the same, on 1 (the default) and 3 workers.
#[test]
fn in_process_actors_give_the_tile_renderers_bits() {
    let d = tmp("actors");
    for (scene, integ, extra) in [
        (
            "cornell:glass",
            "path",
            &["--domains", "6", "--layout", "kd"][..],
        ),
        (
            "cornell:mirror",
            "whitted",
            &["--domains", "4", "--layout", "grid"][..],
        ),
        ("city:3", "ao", &[][..]),
        ("spheres:40", "raycast", &["--domains", "5"][..]),
    ] {
        let args = [
            &[
                "--width",
                "56",
                "--height",
                "40",
                "--spp",
                "2",
                "--integrator",
                integ,
            ][..],
            extra,
        ]
        .concat();
        let one = render(
            &d,
            "tiles",
            scene,
            &[&args[..], &["--workers", "0"]].concat(),
        );
        assert!(one.ok, "{}", one.stderr);
        let reference = std::fs::read(one.png.unwrap()).unwrap();
        let rays = |stats: &Option<serde_json::Value>| stats.as_ref().unwrap()["rays"].clone();
        let reference_rays = rays(&one.stats);
        assert!(reference_rays.is_object(), "{:?}", one.stats);
        for workers in ["default", "3"] {
            let flags: &[&str] = if workers == "default" {
                &[]
            } else {
                &["--workers", workers]
            };
            let r = render(&d, "actors", scene, &[&args[..], flags].concat());
            assert!(r.ok, "{scene} {workers} workers: {}", r.stderr);
            let png = std::fs::read(r.png.clone().unwrap()).unwrap();
            assert!(
                png == reference,
                "{scene} {integ} on {workers} in-process workers differs from the tile renderer"
            );
            assert_eq!(rays(&r.stats), reference_rays, "{scene} rays");
        }
    }
}

/// Whitted and path tracing at the deepest depth a job accepts, on glass: the actors'
/// credit lasts the whole tree (docs/numerics.md "Deep ray trees"), and the image and
/// ray counts are the tile renderer's (`--workers 0`), bit for bit.
#[test]
fn deepest_trees_render_on_actors_as_without() {
    let d = tmp("deepest");
    for integ in ["whitted", "path"] {
        let args = [
            "--width",
            "24",
            "--height",
            "24",
            "--spp",
            "2",
            "--integrator",
            integ,
            "--max-depth",
            "1024",
        ];
        let one = render(
            &d,
            "tiles",
            "cornell:glass",
            &[&args[..], &["--workers", "0"]].concat(),
        );
        assert!(one.ok, "{}", one.stderr);
        let reference = std::fs::read(one.png.unwrap()).unwrap();
        let rays = |stats: &Option<serde_json::Value>| stats.as_ref().unwrap()["rays"].clone();
        for extra in [&[][..], &["--domains", "4", "--workers", "2"][..]] {
            let r = render(&d, "actors", "cornell:glass", &[&args[..], extra].concat());
            assert!(r.ok, "{integ} {extra:?}: {}", r.stderr);
            assert!(
                std::fs::read(r.png.clone().unwrap()).unwrap() == reference,
                "{integ} {extra:?} differs from the tile renderer"
            );
            assert_eq!(rays(&r.stats), rays(&one.stats), "{integ} {extra:?}");
        }
    }
}
