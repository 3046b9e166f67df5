//! `dray health ADDR` against a real `dray coordinator` process: SERVING is exit 0 (the
//! server as a whole, a named service, the address from `DRAY_HEALTH_ADDR`); a service the
//! server does not know, a closed port and an address that is not one are exit 1 with one
//! line saying why. This is what the image's Docker HEALTHCHECK runs.

mod common;
mod support;

use std::process::Output;

fn health(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = support::dray();
    cmd.arg("health").args(args);
    for (k, v) in env {
        cmd.env(k, v);
    }
    // The TLS variables of the machine running the tests must not change the outcome.
    for k in ["DRAY_TLS_CERT", "DRAY_TLS_KEY", "DRAY_TLS_CA"] {
        cmd.env_remove(k);
    }
    cmd.output().expect("run dray health")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn health_of_a_coordinator_and_of_a_closed_port() {
    let root = common::tmp("health");
    let c = support::coordinator(&root);

    // The server as a whole.
    let out = health(&[&c.addr], &[]);
    assert!(
        out.status.success(),
        "dray health {}: {}",
        c.addr,
        text(&out.stderr)
    );
    assert_eq!(text(&out.stdout).trim(), format!("{}: SERVING", c.addr));

    // The public API by name, with an http:// address, quietly.
    let url = format!("http://{}", c.addr);
    let out = health(&[&url, "--service", "dray.v1.RenderService", "-q"], &[]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(text(&out.stdout), "");

    // The address from the environment (the image sets DRAY_HEALTH_ADDR).
    let out = health(&[], &[("DRAY_HEALTH_ADDR", &c.addr)]);
    assert!(out.status.success(), "{}", text(&out.stderr));

    // A service the server does not serve.
    let out = health(&[&c.addr, "--service", "no.such.Service"], &[]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    let err = text(&out.stderr);
    assert!(
        err.contains("does not know the service \"no.such.Service\"") && err.contains("NOT_FOUND"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");

    // A closed port: nothing listens there.
    drop(c);
    let port = support::free_port();
    let addr = format!("127.0.0.1:{port}");
    let out = health(&[&addr], &[]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    let err = text(&out.stderr);
    assert!(
        err.starts_with(&format!("dray: error: {addr} is unreachable: ")),
        "{err}"
    );
    assert!(err.to_lowercase().contains("refused"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    assert_eq!(text(&out.stdout), "");

    // Not an address at all.
    let out = health(&["not an address"], &[]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("not a valid address"),
        "{}",
        text(&out.stderr)
    );
    let _ = std::fs::remove_dir_all(&root);
}
