//! `dray cluster` as a real process: it starts its members, waits for health, prints the
//! endpoints, serves jobs, and stops every member on SIGTERM, when its coordinator dies,
//! and when its own parent dies; a worker that dies is reported and the cluster keeps
//! serving; a port already in use is a clear error before anything starts.
//!
//! Most tests run no workers (`--workers 0`): the spawn/stop machinery is the same for
//! every member.

mod common;
mod support;

use std::io::{BufRead, BufReader, Lines};
use std::process::{ChildStdout, Command, Stdio};

use support::{Proc, alive, dray, eventually, free_port, gone_within};

/// A `dray cluster --workers 0` on a free base port, read up to its "ready" line.
struct Cluster {
    proc: Proc,
    port: u16,
    coordinator_pid: i32,
    lines: Vec<String>,
}

fn read_until_ready(stdout: &mut Lines<BufReader<ChildStdout>>) -> Vec<String> {
    let mut lines = Vec::new();
    for line in stdout.by_ref() {
        let line = line.expect("read cluster stdout");
        let ready = line.starts_with("dray cluster ready");
        lines.push(line);
        if ready {
            return lines;
        }
    }
    panic!("dray cluster ended before it was ready: {lines:?}");
}

fn pid_of(lines: &[String], name: &str) -> i32 {
    lines
        .iter()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no pid for {name} in {lines:?}"))
}

fn start_cluster(root: &std::path::Path) -> Cluster {
    let port = free_port();
    let mut cmd = dray();
    cmd.args([
        "cluster",
        "--workers",
        "0",
        "--base-port",
        &port.to_string(),
    ])
    .arg("--scene-root")
    .arg(root)
    .stdout(Stdio::piped())
    .stderr(Stdio::piped());
    let mut proc = Proc::spawn(cmd);
    let mut stdout = BufReader::new(proc.child.stdout.take().expect("stdout")).lines();
    let lines = read_until_ready(&mut stdout);
    let coordinator_pid = pid_of(&lines, "coordinator");
    Cluster {
        proc,
        port,
        coordinator_pid,
        lines,
    }
}

/// Kills the coordinator too if the test fails before the cluster stops it (the cluster
/// process itself is a [`Proc`]).
struct KillOnDrop(i32);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        if alive(self.0) {
            // SAFETY: kill(2) on a pid that is alive (best effort in a test).
            unsafe {
                libc::kill(self.0, libc::SIGKILL);
            }
        }
    }
}

#[test]
fn cluster_serves_jobs_and_stops_its_members_on_sigterm() {
    let dir = common::tmp("cluster-serve");
    let mut c = start_cluster(&dir);
    let _guard = KillOnDrop(c.coordinator_pid);
    let endpoint = format!("http://127.0.0.1:{}", c.port);
    assert!(
        c.lines[0].starts_with("coordinator") && c.lines[0].contains(&endpoint),
        "{:?}",
        c.lines
    );
    assert!(
        c.lines
            .iter()
            .any(|l| l.contains("dray submit --coordinator")),
        "{:?}",
        c.lines
    );

    let png = dir.join("cluster.png");
    let flags = ["--width", "32", "--height", "24", "--spp", "2"];
    let out = dray()
        .args([
            "submit",
            "--coordinator",
            &format!("127.0.0.1:{}", c.port),
            "cornell",
            "-q",
        ])
        .args(flags)
        .arg("--output")
        .arg(&png)
        .output()
        .expect("run dray submit");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reference = common::render(&dir, "reference", "cornell", &flags);
    assert!(reference.ok, "{}", reference.stderr);
    assert!(
        std::fs::read(&png).expect("png")
            == std::fs::read(reference.png.expect("png")).expect("png"),
        "the cluster's image differs from dray render's"
    );

    c.proc.signal(libc::SIGTERM);
    let status = c
        .proc
        .wait_timeout(20.0)
        .expect("dray cluster did not stop on SIGTERM");
    assert!(
        status.success(),
        "dray cluster exited with {status} on SIGTERM"
    );
    assert!(
        gone_within(c.coordinator_pid, 5.0),
        "the coordinator outlived the cluster"
    );
    // The port is free again.
    assert!(std::net::TcpListener::bind(("127.0.0.1", c.port)).is_ok());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_coordinator_dying_stops_the_cluster_with_its_name() {
    let dir = common::tmp("cluster-member-dies");
    let mut c = start_cluster(&dir);
    let _guard = KillOnDrop(c.coordinator_pid);
    // SAFETY: kill(2) on the coordinator the cluster reported (a test's own process tree).
    unsafe {
        libc::kill(c.coordinator_pid, libc::SIGKILL);
    }
    let status = c.proc.wait_timeout(20.0).expect("the cluster kept running");
    assert!(
        !status.success(),
        "the cluster exited 0 after losing its coordinator"
    );
    let mut err = String::new();
    std::io::Read::read_to_string(&mut c.proc.child.stderr.take().expect("stderr"), &mut err)
        .expect("read stderr");
    assert!(
        err.contains("coordinator")
            && err.contains("exited unexpectedly")
            && err.contains("SIGKILL"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_port_in_use_is_a_clear_error() {
    let holder = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let port = holder.local_addr().expect("addr").port();
    let out = dray()
        .args([
            "cluster",
            "--workers",
            "0",
            "--base-port",
            &port.to_string(),
        ])
        .output()
        .expect("run dray cluster");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err:?}");
    assert!(
        err.contains(&format!("port {port}")) && err.contains("already in use"),
        "{err}"
    );
    // And a range past 65535.
    let out = dray()
        .args(["cluster", "--workers", "10", "--base-port", "65530"])
        .output()
        .expect("run dray cluster");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("65535"));
}

#[test]
fn the_cluster_stops_when_its_parent_dies() {
    let dir = common::tmp("cluster-orphan");
    let port = free_port();
    // A shell parent that starts the cluster in the background and waits; killing the
    // shell orphans the cluster, which must notice and stop its coordinator.
    let script = format!(
        "\"$0\" cluster --workers 0 --base-port {port} --scene-root \"$1\" & echo $!; wait"
    );
    let mut cmd = Command::new("sh");
    cmd.arg("-c")
        .arg(&script)
        .arg(env!("CARGO_BIN_EXE_dray"))
        .arg(&dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut shell = Proc::spawn(cmd);
    let mut stdout = BufReader::new(shell.child.stdout.take().expect("stdout")).lines();
    let cluster_pid: i32 = stdout
        .next()
        .and_then(Result::ok)
        .and_then(|l| l.trim().parse().ok())
        .expect("the shell prints the cluster's pid");
    let _cluster_guard = KillOnDrop(cluster_pid);
    let lines = read_until_ready(&mut stdout);
    let coordinator_pid = pid_of(&lines, "coordinator");
    let _coordinator_guard = KillOnDrop(coordinator_pid);

    shell.signal(libc::SIGKILL);
    let _ = shell.wait_timeout(5.0);
    assert!(
        gone_within(cluster_pid, 10.0),
        "the orphaned cluster kept running"
    );
    assert!(
        gone_within(coordinator_pid, 10.0),
        "the orphaned coordinator kept running"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `dray submit` of a small job; its `--stats` JSON (the test fails if the job does).
fn submit_small(addr: &str, dir: &std::path::Path, tag: &str, want: &[u8]) -> serde_json::Value {
    let png = dir.join(format!("{tag}.png"));
    let stats = dir.join(format!("{tag}.json"));
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, "cornell:glass", "-q"])
        .args(SMALL)
        .arg("--output")
        .arg(&png)
        .arg("--stats")
        .arg(&stats);
    support::run_to_success(cmd, &format!("dray submit {tag}"), 180.0);
    assert!(
        std::fs::read(&png).expect("png") == want,
        "{tag}: the image differs from dray render's"
    );
    serde_json::from_str(&std::fs::read_to_string(&stats).expect("stats")).expect("stats JSON")
}

const SMALL: [&str; 8] = [
    "--width",
    "32",
    "--height",
    "24",
    "--spp",
    "2",
    "--domains",
    "4",
];

#[test]
fn a_worker_that_dies_is_reported_and_the_cluster_keeps_serving() {
    let dir = common::tmp("cluster-worker-dies");
    let reference = common::render(&dir, "reference", "cornell:glass", &SMALL);
    assert!(reference.ok, "{}", reference.stderr);
    let want = std::fs::read(reference.png.expect("png")).expect("png");
    // Heartbeats every 100 ms, a worker lost after 3 s of silence.
    let mut c = support::WorkerCluster::start(
        2,
        0,
        &dir,
        &[
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            "3000",
            // This test follows the cluster down to no worker: no restarts.
            "--restart-limit",
            "0",
        ],
    );
    let stats = submit_small(&c.addr, &dir, "two", &want);
    assert_eq!(
        stats["workers"].as_array().map(Vec::len),
        Some(2),
        "{stats}"
    );

    // SIGKILL worker-2: the cluster names it and keeps serving with worker-1.
    let port = |i: u16| {
        c.addr
            .rsplit(':')
            .next()
            .and_then(|p| p.parse::<u16>().ok())
            .map(|p| p + i)
    };
    let w2 = c.worker_pids[1];
    // SAFETY: kill(2) on a worker of the cluster this test started.
    unsafe {
        libc::kill(w2, libc::SIGKILL);
    }
    let line = format!(
        "dray cluster: worker-2 (pid {w2}, http://127.0.0.1:{}) exited: signal 9 (SIGKILL); \
         the cluster keeps serving with 1 worker",
        port(2).expect("port")
    );
    assert!(
        eventually(30.0, || c.log().contains(&line)),
        "no {line:?} in:\n{}",
        c.log()
    );
    assert!(
        c.proc.child.try_wait().expect("try_wait").is_none(),
        "the cluster stopped"
    );
    assert!(
        alive(c.coordinator_pid) && alive(c.worker_pids[0]),
        "{}",
        c.log()
    );
    // Once the coordinator has noticed, jobs run on the worker left.
    assert!(
        eventually(60.0, || c.log().matches("worker lost").count() == 1),
        "{}",
        c.log()
    );
    let stats = submit_small(&c.addr, &dir, "one", &want);
    assert_eq!(
        stats["workers"].as_array().map(Vec::len),
        Some(1),
        "{stats}"
    );

    // With no worker left the coordinator renders in its own process.
    let w1 = c.worker_pids[0];
    // SAFETY: as above.
    unsafe {
        libc::kill(w1, libc::SIGKILL);
    }
    assert!(
        eventually(30.0, || c.log().contains("keeps serving with 0 workers")),
        "{}",
        c.log()
    );
    assert!(
        eventually(60.0, || c.log().matches("worker lost").count() == 2),
        "{}",
        c.log()
    );
    let stats = submit_small(&c.addr, &dir, "none", &want);
    assert_eq!(stats["schedule"], "none", "{stats}");
    assert!(
        c.proc.child.try_wait().expect("try_wait").is_none(),
        "the cluster stopped"
    );

    // SIGTERM still stops the cluster cleanly.
    c.proc.signal(libc::SIGTERM);
    let status = c
        .proc
        .wait_timeout(20.0)
        .expect("the cluster did not stop on SIGTERM");
    assert!(status.success(), "{status}: {}", c.log());
    assert!(
        gone_within(c.coordinator_pid, 5.0),
        "the coordinator outlived the cluster"
    );
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_worker_that_dies_is_started_again_and_takes_the_next_job() {
    let dir = common::tmp("cluster-worker-restarts");
    let reference = common::render(&dir, "reference", "cornell:glass", &SMALL);
    assert!(reference.ok, "{}", reference.stderr);
    let want = std::fs::read(reference.png.expect("png")).expect("png");
    let mut c = support::WorkerCluster::start(
        2,
        1,
        &dir,
        &[
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            "3000",
        ],
    );
    let w2 = c.worker_pids[1];
    // SAFETY: kill(2) on a worker of the cluster this test started.
    unsafe {
        libc::kill(w2, libc::SIGKILL);
    }
    assert!(
        eventually(30.0, || c.log().contains(
            "the cluster keeps serving with 1 worker and starts it again in 1 s (restart 1 of 3)"
        )),
        "{}",
        c.log()
    );
    assert!(
        eventually(30.0, || c
            .log()
            .contains("dray cluster: worker-2 started again (pid")),
        "{}",
        c.log()
    );
    // The new worker 2 registers (a third registration) on the same port.
    assert!(
        eventually(60.0, || c.log().matches("worker registered").count() >= 3),
        "{}",
        c.log()
    );
    // Once the coordinator has let the old one go, jobs run on both again.
    assert!(
        eventually(60.0, || c.log().contains("worker lost")),
        "{}",
        c.log()
    );
    let stats = submit_small(&c.addr, &dir, "after-restart", &want);
    assert_eq!(
        stats["workers"].as_array().map(Vec::len),
        Some(2),
        "{stats}"
    );
    assert!(
        c.proc.child.try_wait().expect("try_wait").is_none(),
        "the cluster stopped"
    );
    drop(c);
    let _ = std::fs::remove_dir_all(&dir);
}

/// docs/security.md "Hardening, second round", item 17: `--base-port 0` puts every member
/// on a port the system chooses; the
/// lines before the ready line, and the ready line, name them, and a job submitted to
/// the coordinator's announced address runs on the workers.
#[test]
fn a_cluster_on_ephemeral_ports_names_them_and_runs_a_job() {
    let dir = common::tmp("cluster-port0");
    let mut cmd = dray();
    cmd.args(["cluster", "--workers", "2", "--base-port", "0"])
        .arg("--scene-root")
        .arg(&dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut proc = Proc::spawn(cmd);
    let mut stdout = BufReader::new(proc.child.stdout.take().expect("stdout")).lines();
    let lines = read_until_ready(&mut stdout);
    let _guard = KillOnDrop(pid_of(&lines, "coordinator"));
    let port_of = |name: &str| -> u16 {
        lines
            .iter()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split("http://127.0.0.1:").nth(1))
            .and_then(|r| r.split_whitespace().next())
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("no port for {name} in {lines:?}"))
    };
    let ports = [
        port_of("coordinator"),
        port_of("worker-1"),
        port_of("worker-2"),
    ];
    assert!(ports.iter().all(|&p| p != 0), "{lines:?}");
    assert!(
        ports[0] != ports[1] && ports[1] != ports[2] && ports[0] != ports[2],
        "{lines:?}"
    );
    let ready = lines.last().unwrap();
    let announced = format!("127.0.0.1:{}", ports[0]);
    assert!(ready.contains(&announced), "{ready}");

    let png = dir.join("port0.png");
    let out = dray()
        .args(["submit", "--coordinator", &announced, "cornell", "-q"])
        .args(["--width", "32", "--height", "24", "--spp", "1"])
        .arg("--output")
        .arg(&png)
        .output()
        .expect("run dray submit");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(png.is_file());
    proc.signal(libc::SIGTERM);
    assert!(
        proc.wait_timeout(30.0).is_some(),
        "the cluster did not stop"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
