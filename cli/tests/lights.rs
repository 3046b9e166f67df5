//! Lights added from the command line (`--sun`) end to end: the same bits from the
//! reference renderer (`--workers 0`) and from workers (the sun reaches them through
//! `JobSpec.lighting`), the effect reported only when used, and bad values refused with
//! the flag's name.

mod common;

use common::effects;
use std::path::Path;

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
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let r = common::render(
        dir,
        tag,
        &ply.to_string_lossy(),
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
