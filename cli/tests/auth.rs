//! Authentication end to end, with real processes (docs/security.md "Hostile requests"): a
//! `dray cluster` whose
//! coordinator requires an API token, and whose members share a cluster token that
//! `dray cluster` made for them.
//!
//! - `dray submit` without the API token, or with a wrong one, is refused
//!   (UNAUTHENTICATED, one line); with the token from a file or from `DRAY_AUTH_TOKEN`
//!   the job runs and the image is `dray render`'s, bit for bit.
//! - A worker without the cluster token cannot join, and neither can one presenting the
//!   API token (API clients never hold the cluster's credential); the cluster's own
//!   members were admitted (the job ran on them).
//! - A stand-alone `dray cache` without the cluster token cannot register either.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use support::{Proc, dray};

/// Slot of this binary's one cluster (see support::cluster_base_port).
const SLOT: u16 = 0;
/// A limit that only catches hangs.
const HANG_SECS: f64 = 120.0;

const API_TOKEN: &str = "api-token-for-the-auth-test-0123456789";

fn job_flags() -> Vec<&'static str> {
    vec![
        "cornell:glass",
        "--width",
        "32",
        "--height",
        "24",
        "--spp",
        "2",
        "--seed",
        "4",
        "--integrator",
        "path",
        "--max-depth",
        "4",
    ]
}

/// A token file only this user can read.
fn token_file(dir: &Path, name: &str, token: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let p = dir.join(name);
    std::fs::write(&p, format!("{token}\n")).expect("write token");
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    p
}

/// Run `cmd` to the end (with a hang guard).
fn run(mut cmd: Command, what: &str) -> Output {
    cmd.stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let status = p
        .wait_timeout(HANG_SECS)
        .unwrap_or_else(|| panic!("HANG: {what} did not finish within {HANG_SECS} s"));
    let mut stdout = Vec::new();
    let mut stderr = Vec::new();
    if let Some(mut o) = p.child.stdout.take() {
        let _ = std::io::Read::read_to_end(&mut o, &mut stdout);
    }
    if let Some(mut e) = p.child.stderr.take() {
        let _ = std::io::Read::read_to_end(&mut e, &mut stderr);
    }
    Output {
        status,
        stdout,
        stderr,
    }
}

fn submit(addr: &str, png: &Path, extra: &[&str], env_token: Option<&str>) -> Output {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr])
        .args(job_flags())
        .args(["--output"])
        .arg(png)
        .args(extra)
        .env_remove("DRAY_AUTH_TOKEN")
        .env_remove("DRAY_AUTH_TOKEN_FILE");
    if let Some(t) = env_token {
        cmd.env("DRAY_AUTH_TOKEN", t);
    }
    run(cmd, "dray submit")
}

/// A refused command: non-zero, one line on stderr, saying it needs `what`.
fn refused(out: &Output, what: &str, context: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{context}: it succeeded: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{context}: {err:?}");
    assert!(
        err.starts_with("dray: error: ") && err.contains(what),
        "{context}: {err}"
    );
    assert!(
        !err.contains(API_TOKEN),
        "{context}: the token leaked: {err}"
    );
}

#[test]
fn the_api_needs_its_token_and_the_cluster_services_need_theirs() {
    let dir = common::tmp("auth");
    let api = token_file(&dir, "api.token", API_TOKEN);
    let api_s = api.display().to_string();
    let wrong = token_file(&dir, "wrong.token", "not-the-api-token-0123456789");
    let wrong_s = wrong.display().to_string();
    let cluster = support::WorkerCluster::start(2, SLOT, &dir, &["--auth-token-file", &api_s]);

    // The reference image.
    let want = common::render(&dir, "want", "cornell:glass", &job_flags()[1..]);
    assert!(want.ok, "{}", want.stderr);
    let want = std::fs::read(want.png.expect("png")).expect("read png");

    // No token, and a wrong one: refused, one line, naming the API token.
    let png = dir.join("none.png");
    refused(
        &submit(&cluster.addr, &png, &[], None),
        "API token",
        "no token",
    );
    assert!(!png.exists());
    refused(
        &submit(&cluster.addr, &png, &["--auth-token-file", &wrong_s], None),
        "API token",
        "a wrong token",
    );

    // The token from a file, and from the environment: the image of dray render.
    for (tag, extra, env) in [
        ("file", vec!["--auth-token-file", api_s.as_str()], None),
        ("env", vec![], Some(API_TOKEN)),
    ] {
        let png = dir.join(format!("{tag}.png"));
        let out = submit(&cluster.addr, &png, &extra, env);
        assert!(
            out.status.success(),
            "{tag}: {}\ncluster log:\n{}",
            String::from_utf8_lossy(&out.stderr),
            cluster.log()
        );
        let got = std::fs::read(&png).expect("submit png");
        assert!(got == want, "{tag}: the image differs from dray render's");
    }

    // A worker without the cluster token, and one presenting the API token: refused.
    let url = format!("http://{}", cluster.addr);
    for (tag, extra) in [
        ("no token", vec![]),
        (
            "the API token",
            vec!["--cluster-token-file", api_s.as_str()],
        ),
    ] {
        let mut cmd = dray();
        cmd.args(["worker", "--coordinator", &url, "--listen", "127.0.0.1:0"])
            .args(["--connect-timeout", "2", "--no-cache-host"])
            .args(&extra)
            .env_remove("DRAY_CLUSTER_TOKEN")
            .env_remove("DRAY_CLUSTER_TOKEN_FILE");
        let out = run(cmd, "dray worker");
        refused(&out, "cluster token", &format!("a worker with {tag}"));
    }
    // A stand-alone cache host without it: refused too.
    let mut cmd = dray();
    cmd.args(["cache", "--coordinator", &url, "--connect-timeout", "2"])
        .env_remove("DRAY_CLUSTER_TOKEN")
        .env_remove("DRAY_CLUSTER_TOKEN_FILE");
    refused(&run(cmd, "dray cache"), "cluster token", "a cache host");

    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}
