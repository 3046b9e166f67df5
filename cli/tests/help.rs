//! `dray render --help`, `dray submit --help` and `dray sweep --help` group their flags
//! by topic: no flag is left under the catch-all "Options" heading but `--help`, and the
//! topics a new user looks for are there (cli/src/help_heading.rs).

use std::process::Command;

/// (heading, flags under it) in the order `dray SUB --help` prints them.
fn sections(sub: &str) -> Vec<(String, Vec<String>)> {
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args([sub, "--help"])
        .output()
        .expect("run dray");
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let mut sections: Vec<(String, Vec<String>)> = Vec::new();
    for line in text.lines() {
        if !line.starts_with(' ') && line.ends_with(':') {
            sections.push((line.trim_end_matches(':').to_string(), Vec::new()));
        } else if let Some(flag) = line
            .split_whitespace()
            .find(|w| w.starts_with("--"))
            .filter(|_| line.trim_start().starts_with('-'))
            && let Some((_, flags)) = sections.last_mut()
        {
            flags.push(flag.trim_end_matches(',').to_string());
        }
    }
    sections
}

#[test]
fn every_flag_has_a_topic() {
    for sub in ["render", "submit", "sweep"] {
        let s = sections(sub);
        let options = s
            .iter()
            .find(|(h, _)| h == "Options")
            .map(|(_, f)| f.clone());
        assert_eq!(options, Some(vec!["--help".to_string()]), "{sub}: {s:?}");
        for topic in ["Image", "Camera", "Lights", "Output"] {
            assert!(
                s.iter().any(|(h, f)| h.starts_with(topic) && !f.is_empty()),
                "{sub}: no {topic} section in {s:?}"
            );
        }
        let lights = s
            .iter()
            .find(|(h, _)| h.starts_with("Lights"))
            .expect("lights");
        for flag in ["--sun", "--light-samples"] {
            assert!(lights.1.contains(&flag.to_string()), "{sub}: {lights:?}");
        }
        let camera = s
            .iter()
            .find(|(h, _)| h.starts_with("Camera"))
            .expect("camera");
        assert!(
            camera.1.contains(&"--look-from".to_string()),
            "{sub}: {camera:?}"
        );
    }
}
