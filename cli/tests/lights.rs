//! Lights added from the command line (`--sun`, `--sun-size`, `--sun-color`) and the
//! samples each takes (`--light-samples`) end to end: the same bits from the reference
//! renderer (`--workers 0`), from in-process workers and from a `dray cluster` reached
//! by `dray submit` (the sun reaches them through `JobSpec.lighting` and
//! `JobSpec.sun_color`, the count through `JobSpec.light_samples`), the effect reported
//! only when used, and bad values refused with the flag's name.

mod common;
mod support;

use common::effects;
use std::path::Path;

/// Ports of this file's cluster (see `support::cluster_base_port`).
const SLOT: u16 = 6;

/// A box on a ground quad (no lights of its own), lit by `extra`, on `workers`.
fn render(
    dir: &Path,
    tag: &str,
    integrator: &str,
    workers: &str,
    extra: &[&str],
) -> (Vec<u8>, serde_json::Value) {
    let ply = dir.join("box.ply");
    if !ply.exists() {
        common::write_box_ply(&ply);
    }
    render_scene(dir, tag, &ply.to_string_lossy(), integrator, workers, extra)
}

/// `scene` with `extra`, on `workers`: its EXR's bytes and its stats.
fn render_scene(
    dir: &Path,
    tag: &str,
    scene: &str,
    integrator: &str,
    workers: &str,
    extra: &[&str],
) -> (Vec<u8>, serde_json::Value) {
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let r = common::render(
        dir,
        tag,
        scene,
        &[
            &[
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
                integrator,
                "--workers",
                workers,
                "--exr",
                &exr_arg,
            ][..],
            extra,
        ]
        .concat(),
    );
    assert!(r.ok, "{tag}: {}", r.stderr);
    (
        std::fs::read(&exr).expect("read exr"),
        r.stats.expect("stats"),
    )
}

#[test]
fn a_sun_gives_the_same_bits_on_workers_as_in_the_reference_renderer() {
    let dir = common::tmp("lights-sun");
    for integrator in ["path", "whitted"] {
        let sun = ["--sun", "200,30,3"];
        let (want, stats) = render(&dir, &format!("ref-{integrator}"), integrator, "0", &sun);
        assert!(effects(&stats).contains(&"sun".to_string()), "{stats}");
        let (got, stats2) = render(&dir, &format!("w2-{integrator}"), integrator, "2", &sun);
        assert!(
            got == want,
            "{integrator}: 2 workers differ from --workers 0"
        );
        assert_eq!(effects(&stats2), effects(&stats));
        // The sun changes the image, and a scene without one does not pay for it.
        let (none, stats) = render(&dir, &format!("none-{integrator}"), integrator, "0", &[]);
        assert!(none != want, "{integrator}: the sun changed nothing");
        assert!(!effects(&stats).contains(&"sun".to_string()), "{stats}");
        // Another sun, another image.
        let (other, _) = render(
            &dir,
            &format!("other-{integrator}"),
            integrator,
            "0",
            &["--sun", "20,60,3"],
        );
        assert!(
            other != want,
            "{integrator}: the sun's direction changed nothing"
        );
    }
}

/// `--light-samples 8`: the same bits from the reference renderer and on 1 and 3
/// in-process workers (the count reaches them through `JobSpec.light_samples`), with
/// the Cornell box's area light and with a wide sun, and another image than one
/// sample's; out of range refused naming the flag and the bound.
#[test]
fn light_samples_give_the_same_bits_on_1_and_3_workers() {
    let dir = common::tmp("lights-samples");
    let sun = ["--sun", "200,30,3", "--sun-size", "6"];
    let eight = ["--light-samples", "8"];
    for (what, scene, extra) in [("cornell", "cornell", &[][..]), ("sun", "", &sun[..])] {
        let run = |tag: &str, workers: &str, flags: &[&str]| {
            let flags = [extra, flags].concat();
            if scene.is_empty() {
                render(&dir, &format!("{what}-{tag}"), "path", workers, &flags).0
            } else {
                render_scene(
                    &dir,
                    &format!("{what}-{tag}"),
                    scene,
                    "path",
                    workers,
                    &flags,
                )
                .0
            }
        };
        let want = run("ref", "0", &eight);
        for workers in ["1", "3"] {
            let got = run(&format!("w{workers}"), workers, &eight);
            assert!(
                got == want,
                "{what}: {workers} workers differ from --workers 0 at 8 light samples"
            );
        }
        let one = run("one", "0", &[]);
        assert!(one != want, "{what}: --light-samples 8 changed nothing");
        assert!(
            run("one-explicit", "0", &["--light-samples", "1"]) == one,
            "{what}: --light-samples 1 is not the image without the flag"
        );
    }
    for bad in ["0", "257", "x"] {
        let r = common::render(
            &dir,
            "bad",
            "cornell",
            &["--light-samples", bad, "--workers", "0"],
        );
        assert!(!r.ok, "--light-samples {bad} was accepted");
        assert!(
            r.stderr.contains("--light-samples") && r.stderr.contains("1..=256"),
            "--light-samples {bad}: {}",
            r.stderr
        );
    }
}

#[test]
fn bad_sun_values_are_refused_naming_the_flag() {
    let dir = common::tmp("lights-bad");
    for (value, says) in [
        ("0,NaN", "elevation"),
        ("0,95", "elevation"),
        ("0,45,-2", "irradiance"),
        ("10", "AZ,EL"),
    ] {
        let r = common::render(&dir, "bad", "cornell", &["--sun", value, "--workers", "0"]);
        assert!(!r.ok, "--sun {value} was accepted");
        assert!(
            r.stderr.contains("--sun") && r.stderr.contains(says),
            "--sun {value}: {}",
            r.stderr
        );
    }
}

/// The channel `name` of an EXR's bytes.
fn channel(exr: &[u8], name: &str) -> Vec<f32> {
    common::exr_channels(exr)
        .into_iter()
        .find(|(n, _)| n == name)
        .unwrap_or_else(|| panic!("no channel {name}"))
        .1
}

#[test]
fn a_coloured_wider_sun_gives_the_same_bits_everywhere_and_scales_each_channel() {
    let dir = common::tmp("lights-colour");
    let base = ["--sun", "200,30,3", "--sun-size", "6"];
    let coloured = [&base[..], &["--sun-color", "1,0.5,0.25"][..]].concat();
    let (want, stats) = render(&dir, "ref", "path", "0", &coloured);
    assert!(effects(&stats).contains(&"sun".to_string()), "{stats}");
    let (got, _) = render(&dir, "w2", "path", "2", &coloured);
    assert!(got == want, "2 workers differ from --workers 0");

    // All light comes from the sun and nothing the sampler decides reads its colour, so
    // the coloured image is the grey one times the colour, per channel: red (factor 1)
    // to the bit, green and blue within float rounding.
    let (grey, _) = render(&dir, "grey", "path", "0", &base);
    let (white, _) = render(
        &dir,
        "white",
        "path",
        "0",
        &[&base[..], &["--sun-color", "1,1,1"][..]].concat(),
    );
    assert!(
        white == grey,
        "a white --sun-color is not the grey sun's bits"
    );
    assert_eq!(channel(&want, "R"), channel(&grey, "R"));
    let mut lit = 0;
    for (name, k) in [("G", 0.5f32), ("B", 0.25)] {
        for (c, g) in channel(&want, name).iter().zip(channel(&grey, name)) {
            assert!(
                (c - k * g).abs() <= 1e-5 * g.abs() + 1e-12,
                "{name}: {c} vs {k} x {g}"
            );
            lit += usize::from(g > 0.0);
        }
    }
    assert!(lit > 0, "the sun lit nothing");
    // The size changes the image (wider penumbrae) at the same colour.
    let (small, _) = render(
        &dir,
        "small",
        "path",
        "0",
        &["--sun", "200,30,3", "--sun-color", "1,0.5,0.25"],
    );
    assert!(small != want, "--sun-size changed nothing");

    // A real cluster reached by `dray submit`: the same bits, and GetJob shows both.
    let ply = dir.join("box.ply");
    let cluster = support::WorkerCluster::start(2, SLOT, &dir, &[]);
    let out = dir.join("cluster.exr");
    let png = dir.join("cluster.png");
    let mut cmd = support::dray();
    cmd.args(["submit", "--coordinator", &cluster.addr])
        .arg(&ply)
        .args([
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
        ])
        .args(&coloured)
        .arg("--output")
        .arg(&png)
        .arg("--exr")
        .arg(&out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    let mut p = support::Proc::spawn(cmd);
    let err = support::capture_stderr(&mut p.child);
    let status = p.wait_timeout(180.0);
    let text = err.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: dray submit: {text}"));
    assert!(
        status.success(),
        "dray submit failed: {text}\ncluster log:\n{}",
        cluster.log()
    );
    assert!(
        std::fs::read(&out).expect("cluster exr") == want,
        "the cluster's image differs from --workers 0; cluster log:\n{}",
        cluster.log()
    );
    let id = support::submitted_job_id(&text).expect("job id");
    let spec = support::get_job(&cluster.addr, &id)
        .expect("GetJob")
        .spec
        .expect("spec");
    let c = spec.sun_color.expect("sun_color");
    assert_eq!((c.r, c.g, c.b), (1.0, 0.5, 0.25));
    let sun = spec.lighting.and_then(|l| l.sun).expect("sun");
    assert_eq!(sun.angular_diameter_deg, Some(6.0));
}

#[test]
fn bad_sun_sizes_and_colours_are_refused_naming_the_flag() {
    let dir = common::tmp("lights-bad-colour");
    for (args, flag, says) in [
        (
            &["--sun", "0,45", "--sun-size", "0"][..],
            "--sun-size",
            "angular diameter",
        ),
        (
            &["--sun", "0,45", "--sun-size", "50"][..],
            "--sun-size",
            "angular diameter",
        ),
        (
            &["--sun", "0,45", "--sun-color", "1,-1,1"][..],
            "--sun-color",
            "colour",
        ),
        (
            &["--sun", "0,45", "--sun-color", "1,1"][..],
            "--sun-color",
            "R,G,B",
        ),
        (&["--sun-color", "1,1,1"][..], "--sun", "--sun"),
        (&["--sun-size", "2"][..], "--sun", "--sun"),
    ] {
        let r = common::render(
            &dir,
            "bad",
            "cornell",
            &[args, &["--workers", "0"][..]].concat(),
        );
        assert!(!r.ok, "{args:?} was accepted");
        assert!(
            r.stderr.contains(flag) && r.stderr.contains(says),
            "{args:?}: {}",
            r.stderr
        );
    }
}
