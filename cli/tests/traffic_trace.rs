//! `dray render --trace-out`: a job's traffic as a trace (docs/caches.md "The trace's
//! schema"), and its replay in SimGrid (`benches/sim/replay.py`).
//!
//! - the trace's records add up to the job's own statistics (`--stats`): rays traced,
//!   rays and bytes sent between workers, domain loads;
//! - the replay runs on it: every step replayed, its rays equal to the trace's, a
//!   positive and finite time, and a slower link giving a longer time. SimGrid is
//!   fetched by `benches/sim/setup.sh`; when it cannot be, the test says so and fails
//!   under `CI=true` (it is skipped, loudly, elsewhere);
//! - bad uses are refused, naming the flag (`--trace-out` without workers, a
//!   `dray worker --trace-dir` that is no directory).

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;
use support::dray;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the workspace")
        .to_path_buf()
}

/// The trace's lines, parsed.
fn read_trace(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .expect("the trace")
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect()
}

fn u(v: &Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

/// The traced job: small, path traced, cut into 8 domains dealt to owners, so rays move
/// between workers.
const JOB: [&str; 13] = [
    "cornell:glass",
    "--width",
    "48",
    "--height",
    "32",
    "--spp",
    "2",
    "--integrator",
    "path",
    "--domains",
    "8",
    "--schedule",
    "domain",
];

/// Render a small path-traced job on `workers` in-process workers with a trace; the
/// trace's records and the `--stats` JSON.
fn record(dir: &Path, workers: u32) -> (PathBuf, Vec<Value>, Value) {
    let trace = dir.join(format!("trace-{workers}.jsonl"));
    let stats = dir.join(format!("stats-{workers}.json"));
    let mut cmd = dray();
    cmd.args(["render", "-q"])
        .args(JOB)
        .arg("--workers")
        .arg(workers.to_string())
        .arg("--output")
        .arg(dir.join(format!("img-{workers}.png")))
        .arg("--stats")
        .arg(&stats)
        .arg("--trace-out")
        .arg(&trace);
    support::run_to_success(cmd, "dray render --trace-out", 180.0);
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).expect("stats")).expect("JSON");
    (trace.clone(), read_trace(&trace), s)
}

#[test]
fn a_trace_adds_up_to_the_jobs_statistics_and_replays_in_simgrid() {
    let dir = common::tmp("traffic-trace");
    let (path, recs, stats) = record(&dir, 2);
    assert!(!recs.is_empty());
    assert!(
        recs.iter().all(|r| r["v"] == 1),
        "every line carries the schema version"
    );
    let of = |kind: &str| -> Vec<&Value> { recs.iter().filter(|r| r["rec"] == kind).collect() };
    let job = of("job");
    assert_eq!(job.len(), 1, "one job line");
    assert_eq!(recs[0]["rec"], "job", "the job line comes first");
    assert_eq!(u(&job[0]["workers"]), 2);
    assert!(u(&job[0]["wall_ns"]) > 0);
    assert_eq!(of("worker").len(), 2, "a header line per worker");

    let steps = of("step");
    let traced: u64 = steps.iter().map(|s| u(&s["traced"])).sum();
    let rays_total: u64 = stats["rays"]
        .as_object()
        .expect("rays by kind")
        .values()
        .map(u)
        .sum();
    assert!(rays_total > 0);
    assert_eq!(traced, rays_total, "rays traced: trace against --stats");

    let sched = &stats;
    let remote = |field: &str| -> u64 {
        steps
            .iter()
            .flat_map(|s| s["out"].as_array().expect("out"))
            .filter(|o| o["remote"] == true)
            .map(|o| u(&o[field]))
            .sum::<u64>()
            + of("forward").iter().map(|f| u(&f[field])).sum::<u64>()
    };
    assert!(
        u(&sched["rays_exchanged"]) > 0,
        "a job whose rays cross workers"
    );
    assert_eq!(
        remote("rays"),
        u(&sched["rays_exchanged"]),
        "rays sent: trace against --stats"
    );
    assert_eq!(
        remote("bytes"),
        u(&sched["traffic"]["rays"]),
        "ray bytes sent: trace against --stats"
    );
    assert_eq!(
        of("load").len() as u64,
        u(&sched["domain_loads"]),
        "domain loads: trace against --stats"
    );
    // Rays queued for a domain are the rays later steps take there (no forwards under
    // the domain schedule).
    let into: u64 = steps
        .iter()
        .flat_map(|s| s["out"].as_array().expect("out"))
        .map(|o| u(&o["rays"]))
        .sum();
    let taken: u64 = steps
        .iter()
        .filter(|s| !s["domain"].is_null())
        .map(|s| u(&s["rays_in"]))
        .sum();
    assert_eq!(
        into, taken,
        "every ray sent to a domain is taken by a step there"
    );
    assert!(
        steps.iter().map(|s| u(&s["cpu_ns"])).sum::<u64>() > 0,
        "steps count CPU"
    );

    replay_checks(&path, traced, remote("rays"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// `benches/sim/run.sh replay.py` on `trace` with `args`, as JSON; None when SimGrid
/// cannot be had outside CI.
fn replay(trace: &Path, args: &[&str]) -> Option<Value> {
    let out = Command::new(repo().join("benches/sim/run.sh"))
        .arg("replay.py")
        .arg(trace)
        .arg("--json")
        .args(args)
        .output()
        .expect("run benches/sim/run.sh");
    let err = String::from_utf8_lossy(&out.stderr);
    if out.status.code() == Some(3) {
        common::dependency_missing(&format!(
            "SimGrid could not be fetched: the replay was NOT tested ({err})"
        ));
        return None;
    }
    assert!(
        out.status.success(),
        "replay.py {args:?} failed ({}):\n{err}",
        out.status
    );
    let text = String::from_utf8_lossy(&out.stdout);
    Some(
        serde_json::from_str(text.trim())
            .unwrap_or_else(|e| panic!("replay.py printed no JSON ({e}):\n{text}\n{err}")),
    )
}

fn replay_checks(trace: &Path, traced: u64, sent: u64) {
    let Some(fast) = replay(trace, &["--bandwidth", "10Gbps", "--latency", "10us"]) else {
        return;
    };
    let slow = replay(trace, &["--bandwidth", "10Mbps", "--latency", "1ms"]).expect("replayed");
    for r in [&fast, &slow] {
        let t = r["predicted_s"].as_f64().expect("a time");
        assert!(t.is_finite() && t > 0.0, "predicted {t}");
        assert_eq!(
            u(&r["rays_traced"]),
            traced,
            "the replay's rays are the trace's"
        );
        assert_eq!(
            u(&r["steps"]),
            u(&r["trace"]["steps"]),
            "every step replayed"
        );
        assert_eq!(
            u(&r["rays_sent"]),
            sent,
            "at the trace's node count, the same rays cross nodes"
        );
    }
    let (f, s) = (
        fast["makespan_s"].as_f64().expect("time"),
        slow["makespan_s"].as_f64().expect("time"),
    );
    assert!(s > f, "a slower link gives a longer time: {s} s vs {f} s");
    // The emulation's links (`validate.py --link`): one per ordered pair of nodes, no TCP
    // factors. Every step replayed, and no slower than one link per node with TCP's
    // factors on the same bandwidth (more capacity, less latency).
    let pairs = replay(
        trace,
        &[
            "--bandwidth",
            "10Mbps",
            "--latency",
            "1ms",
            "--topology",
            "pairs",
            "--network-model",
            "CM02",
        ],
    )
    .expect("replayed");
    assert_eq!(u(&pairs["steps"]), u(&pairs["trace"]["steps"]));
    assert_eq!(u(&pairs["rays_sent"]), sent);
    assert_eq!(pairs["topology"], "pairs", "{pairs}");
    let p = pairs["makespan_s"].as_f64().expect("time");
    assert!(
        p > 0.0 && p <= s,
        "links per pair without TCP factors: {p} s, one link per node with them: {s} s"
    );
    // More nodes than the trace had: domains re-dealt, every step still replayed.
    let wide = replay(trace, &["--nodes", "8"]).expect("replayed");
    assert_eq!(u(&wide["steps"]), u(&wide["trace"]["steps"]));
    assert!(wide["predicted_s"].as_f64().is_some_and(|t| t > 0.0));
    // The dynamic schedule (replicas of busy domains on idle nodes, rounds of 1 ms) and
    // the overhead modelled from counts: every step still replayed exactly once.
    let dynamic = replay(
        trace,
        &[
            "--nodes",
            "8",
            "--schedule",
            "dynamic",
            "--round-ms",
            "1",
            "--min-queue",
            "1",
            "--overhead",
            "model",
        ],
    )
    .expect("replayed");
    assert_eq!(u(&dynamic["steps"]), u(&dynamic["trace"]["steps"]));
    assert_eq!(u(&dynamic["rays_traced"]), traced);
    assert_eq!(dynamic["schedule"], "dynamic", "{dynamic}");
    assert!(
        dynamic["predicted_s"]
            .as_f64()
            .is_some_and(|t| t > 0.0 && t.is_finite())
    );
}

#[test]
fn trace_out_without_workers_is_refused_naming_the_flag() {
    let dir = common::tmp("traffic-trace-bad");
    let out = dray()
        .args(["render", "cornell", "-q", "--width", "8", "--height", "8"])
        .args(["--workers", "0", "--trace-out"])
        .arg(dir.join("t.jsonl"))
        .arg("--output")
        .arg(dir.join("x.png"))
        .output()
        .expect("dray");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--trace-out"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_worker_trace_dir_that_is_no_directory_is_refused_naming_the_flag() {
    let out = dray()
        .args([
            "worker",
            "--coordinator",
            "http://127.0.0.1:1",
            "--listen",
            "127.0.0.1:0",
            "--trace-dir",
            "/nonexistent/dray-traces",
        ])
        .output()
        .expect("dray");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--trace-dir /nonexistent/dray-traces: not a directory"),
        "{err}"
    );
}

/// `dray cluster --trace-dir` hands the directory to every worker: a job submitted with
/// `--trace` leaves one file per worker that traced it, each with its worker header and
/// traced steps.
#[test]
fn a_cluster_started_with_a_trace_dir_records_a_submitted_jobs_trace() {
    let dir = common::tmp("cluster-trace");
    let traces = dir.join("traces");
    let traces_arg = traces.display().to_string();
    let cluster = support::WorkerCluster::start(2, 0, &dir, &["--trace-dir", &traces_arg]);
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &cluster.addr, "--trace"])
        .args(JOB)
        .arg("--output")
        .arg(dir.join("img.png"));
    support::run_to_success(cmd, "dray submit --trace", 180.0);
    let files: Vec<PathBuf> = std::fs::read_dir(&traces)
        .expect("the cluster made --trace-dir")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jsonl"))
        .collect();
    assert!(!files.is_empty(), "no trace file in {}", traces.display());
    let mut steps = 0;
    for f in &files {
        let records = read_trace(f);
        assert!(
            records.iter().any(|r| r["rec"] == "worker"),
            "{}: no worker header",
            f.display()
        );
        steps += records.iter().filter(|r| r["rec"] == "step").count();
    }
    assert!(steps > 0, "no traced step in {files:?}");
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}
