//! The ray-cache surfaces of the `dray` command as real processes: `--ray-cache` values
//! that cannot be right are one-line errors naming the key (on `dray render` and `dray
//! submit`, whether the flag's syntax or the coordinator's ranges refuse them), and the
//! cache hosts: `dray cache` registers with a `dray coordinator` and stops cleanly on
//! SIGTERM, `dray worker` announces the cache host it runs unless `--no-cache-host`.

mod common;
mod support;

use std::io::{BufRead, BufReader};
use std::process::{Output, Stdio};
use std::sync::{Arc, Mutex};

use dray_proto::v1::RegisterCacheHostRequest;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use support::{Proc, capture_stderr, coordinator, dray, eventually};

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn text(log: &Arc<Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

/// Assert `o` failed with exactly one line on stderr containing every one of `want`.
fn one_line_error(o: &Output, what: &str, want: &[&str]) {
    let err = stderr(o);
    assert!(!o.status.success(), "{what} was accepted");
    assert_eq!(
        err.trim_end().lines().count(),
        1,
        "{what}: not one line: {err:?}"
    );
    assert!(err.starts_with("dray: error: "), "{what}: {err}");
    for w in want {
        assert!(err.contains(w), "{what}: {err:?} does not name {w:?}");
    }
}

/// Values the flag's syntax refuses, and the key each error must name.
/// The coordinator's heartbeat timeout in the expiry test: a host not heard from for
/// this long is dropped.
const HOST_TIMEOUT: std::time::Duration = std::time::Duration::from_millis(4000);

const BAD_SYNTAX: [(&str, &str); 7] = [
    ("radius=x", "radius: \"x\" is not a number"),
    ("size=3", "unknown key \"size\""),
    ("radius", "radius: missing =VALUE"),
    ("fill=maybe", "fill: \"maybe\" is not true or false"),
    ("coarse=-2", "coarse: \"-2\" is not a whole number"),
    ("angle-deg=wide", "angle-deg:"),
    ("kinds=camera,diffuse", "\"diffuse\" is not KEY=VALUE"),
];

#[test]
fn bad_ray_cache_flags_are_one_line_errors_naming_the_key() {
    let dir = common::tmp("cache-flags");
    let png = dir.join("never.png");
    let small = ["--width", "8", "--height", "8", "--spp", "1", "-q"];
    for (value, want) in BAD_SYNTAX {
        for cmd in ["render", "submit"] {
            let mut c = dray();
            c.args([cmd, "cornell", "--ray-cache", value])
                .args(small)
                .arg("--output")
                .arg(&png);
            if cmd == "submit" {
                // Never reached: the flag is refused before anything connects.
                c.args(["--coordinator", "127.0.0.1:1"]);
            }
            let out = c.output().expect("run dray");
            one_line_error(
                &out,
                &format!("{cmd} --ray-cache {value}"),
                &["--ray-cache", want],
            );
        }
    }
    // Well-formed but out of range: the coordinator (in process for `dray render`)
    // refuses it, naming the field.
    for (value, want) in [
        (
            "radius=-1",
            "ray_cache.radius must be finite and >= 0, got -1",
        ),
        ("angle-deg=120", "ray_cache.angle_deg"),
        ("retrieve=best", "ray_cache.retrieve"),
        ("kinds=camera+shadow", "ray_cache.kinds: \"shadow\""),
        ("coarse=5000", "ray_cache.coarse must be in 0..=4096"),
    ] {
        let out = dray()
            .args(["render", "cornell", "--ray-cache", value])
            .args(small)
            .arg("--output")
            .arg(&png)
            .output()
            .expect("run dray render");
        one_line_error(&out, &format!("render --ray-cache {value}"), &[want]);
    }
    // The reference renderer has no cache hosts.
    let out = dray()
        .args(["render", "cornell", "--workers", "0", "--ray-cache", "on"])
        .args(small)
        .arg("--output")
        .arg(&png)
        .output()
        .expect("run dray render");
    one_line_error(
        &out,
        "--workers 0 --ray-cache on",
        &["--ray-cache", "--workers 0"],
    );
    assert!(!png.exists(), "an image was written for a refused job");

    // Through `dray submit` the coordinator's refusal arrives the same way, and the
    // server serves on.
    let server = coordinator(&dir);
    let out = dray()
        .args(["submit", "--coordinator", &server.addr, "cornell"])
        .args(["--ray-cache", "radius=-1"])
        .args(small)
        .arg("--output")
        .arg(&png)
        .output()
        .expect("run dray submit");
    one_line_error(
        &out,
        "submit --ray-cache radius=-1",
        &["rejected the job", "ray_cache.radius"],
    );
    let ok = dray()
        .args(["submit", "--coordinator", &server.addr, "cornell"])
        .args(small)
        .arg("--output")
        .arg(&png)
        .output()
        .expect("run dray submit");
    assert!(ok.status.success(), "{}", stderr(&ok));
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A process whose first stdout line ends with its address: (process, address, stderr,
/// the rest of stdout as it comes).
fn spawn_with_address(
    mut cmd: std::process::Command,
) -> (
    Proc,
    String,
    support::Captured,
    std::io::Lines<BufReader<std::process::ChildStdout>>,
) {
    cmd.env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let log = capture_stderr(&mut p.child);
    let mut lines = BufReader::new(p.child.stdout.take().expect("stdout")).lines();
    let first = lines
        .next()
        .and_then(Result::ok)
        .unwrap_or_else(|| panic!("no first line; stderr: {}", text(&log)));
    let addr = first
        .trim()
        .rsplit(' ')
        .next()
        .filter(|a| a.contains(':'))
        .unwrap_or_else(|| panic!("no address in {first:?}"))
        .to_string();
    (p, addr, log, lines)
}

fn coordinator_with_log(
    dir: &std::path::Path,
    extra: &[&str],
) -> (Proc, String, support::Captured) {
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(dir)
        .args(extra)
        .env("DRAY_LOG", "warn,dray_coordinator=info");
    let (p, addr, log, _) = spawn_with_address(cmd);
    (p, addr, log)
}

#[test]
fn dray_cache_registers_and_stops_cleanly_on_sigterm() {
    let dir = common::tmp("cache-standalone");
    let (_coordinator, addr, coordinator_log) = coordinator_with_log(&dir, &["--cache-hosts"]);
    let url = format!("http://{addr}");
    let mut cmd = dray();
    cmd.args(["cache", "--coordinator", &url, "--listen", "127.0.0.1:0"]);
    let (mut cache, cache_addr, cache_log, _) = spawn_with_address(cmd);
    let endpoint = format!("http://{cache_addr}");
    assert!(
        eventually(60.0, || text(&cache_log).contains("registered with")),
        "dray cache did not register: {}",
        text(&cache_log)
    );
    let said = text(&cache_log);
    assert!(
        said.contains(&format!(
            "registered with {url} as cache-1, serving at {endpoint}"
        )),
        "{said}"
    );
    assert!(
        eventually(10.0, || text(&coordinator_log)
            .contains("cache host registered")),
        "{}",
        text(&coordinator_log)
    );
    // The coordinator lists it: registering the same endpoint again without the host's
    // member secret is refused (docs/security.md "Hardening, second round", item 6: no one
    // takes over a host).
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let refused = rt.block_on(async {
        let mut c = ClusterServiceClient::connect(url.clone())
            .await
            .expect("connect");
        c.register_cache_host(RegisterCacheHostRequest {
            endpoint: endpoint.clone(),
            version: env!("CARGO_PKG_VERSION").into(),
            hostname: "test".into(),
            member_token: String::new(),
        })
        .await
        .expect_err("a registration of a listed endpoint without its secret")
    });
    assert_eq!(refused.code(), tonic::Code::PermissionDenied, "{refused:?}");
    assert!(refused.message().contains("cache-1"), "{refused:?}");

    cache.signal(libc::SIGTERM);
    let status = cache
        .wait_timeout(30.0)
        .unwrap_or_else(|| panic!("dray cache did not stop on SIGTERM: {}", text(&cache_log)));
    assert!(status.success(), "{status}: {}", text(&cache_log));
    // The process has exited, but the thread copying its stderr may not have taken the
    // last line yet.
    assert!(
        eventually(10.0, || text(&cache_log)
            .contains("dray cache: terminated; stopping")),
        "{}",
        text(&cache_log)
    );
    // Its port is free again.
    assert!(std::net::TcpListener::bind(&cache_addr).is_ok());

    // With no coordinator to register with, it gives up with one line.
    let port = support::free_port();
    let out = dray()
        .args(["cache", "--coordinator", &format!("127.0.0.1:{port}")])
        .args(["--connect-timeout", "1"])
        .stdout(Stdio::null())
        .output()
        .expect("run dray cache");
    one_line_error(
        &out,
        "dray cache without a coordinator",
        &["cannot reach the coordinator"],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dray_worker_announces_its_cache_host_unless_told_not_to() {
    let dir = common::tmp("cache-worker");
    let (_coordinator, addr, coordinator_log) = coordinator_with_log(&dir, &[]);
    let url = format!("http://{addr}");
    let mut cmd = dray();
    cmd.args(["worker", "--coordinator", &url, "--listen", "127.0.0.1:0"])
        .args(["--threads", "1"]);
    let (_worker, _, _, mut lines) = spawn_with_address(cmd);
    let second = lines.next().and_then(Result::ok).unwrap_or_default();
    let cache_addr = second
        .strip_prefix("dray worker cache host listening on ")
        .unwrap_or_else(|| panic!("no cache host line: {second:?}"))
        .trim()
        .to_string();
    assert!(
        eventually(60.0, || text(&coordinator_log)
            .contains(&format!("cache_endpoint=http://{cache_addr}"))),
        "the worker did not announce http://{cache_addr}: {}",
        text(&coordinator_log)
    );
    let mut cmd = dray();
    cmd.args(["worker", "--coordinator", &url, "--listen", "127.0.0.1:0"])
        .args(["--threads", "1", "--no-cache-host"]);
    let (_plain, _, _, _) = spawn_with_address(cmd);
    assert!(
        eventually(60.0, || text(&coordinator_log)
            .contains("cache_endpoint=none")),
        "{}",
        text(&coordinator_log)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// docs/security.md "Hardening, second round", items 6 and 15. A coordinator takes
/// stand-alone cache hosts only when its
/// operator says so (`--cache-hosts`): before, any holder of the cluster token could
/// register one, be given every wall of later jobs and answer every lookup. And hosts
/// that stop refreshing are dropped (before, 3,000 dead hosts stayed listed).
#[test]
fn cache_hosts_are_opt_in_and_silent_ones_are_dropped() {
    let dir = common::tmp("cache-optin");
    // Without --cache-hosts: refused, in one line naming the flag.
    let (_plain, addr, _) = coordinator_with_log(&dir, &[]);
    let out = dray()
        .args(["cache", "--coordinator", &addr, "--connect-timeout", "10"])
        .stdout(Stdio::null())
        .output()
        .expect("run dray cache");
    one_line_error(
        &out,
        "a cache host on a coordinator without --cache-hosts",
        &["refused this cache host", "--cache-hosts"],
    );

    // With it, and heartbeats every 100 ms, silence for 4 s (long enough that a loaded
    // machine's late refreshes drop no live host): two hosts register and refresh; the
    // one killed is dropped, the live one stays.
    let (_coordinator, addr, log) = coordinator_with_log(
        &dir,
        &[
            "--cache-hosts",
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            &HOST_TIMEOUT.as_millis().to_string(),
        ],
    );
    let url = format!("http://{addr}");
    let start_host = || {
        let mut cmd = dray();
        cmd.args(["cache", "--coordinator", &url, "--listen", "127.0.0.1:0"]);
        let (p, host_addr, host_log, _) = spawn_with_address(cmd);
        assert!(
            eventually(60.0, || text(&host_log).contains("registered with")),
            "dray cache did not register: {}",
            text(&host_log)
        );
        (p, format!("http://{host_addr}"), host_log)
    };
    let (mut dead, dead_endpoint, _) = start_host();
    let (_live, live_endpoint, live_log) = start_host();
    let live_registered = std::time::Instant::now();
    dead.signal(libc::SIGKILL);
    assert!(dead.wait_timeout(30.0).is_some(), "SIGKILL did not end it");
    let lost = |endpoint: &str| {
        text(&log)
            .lines()
            .any(|l| l.contains("cache host lost") && l.contains(endpoint))
    };
    assert!(
        eventually(60.0, || lost(&dead_endpoint)),
        "the killed host was never dropped: {}",
        text(&log)
    );
    // The live host keeps refreshing, so it is still listed a timeout and a half after
    // its registration. What is tested is an absence over a span of time, which no
    // event can stand for (the host's refreshes are silent on both sides), so the test
    // lets that span pass, measured from the registration rather than slept blindly.
    let quiet_until = live_registered + HOST_TIMEOUT.mul_f64(1.5);
    std::thread::sleep(quiet_until.saturating_duration_since(std::time::Instant::now()));
    assert!(
        !lost(&live_endpoint),
        "the live host was dropped: {}",
        text(&log)
    );
    assert!(
        !text(&live_log).contains("had dropped this host"),
        "{}",
        text(&live_log)
    );
    let _ = std::fs::remove_dir_all(&dir);
}
