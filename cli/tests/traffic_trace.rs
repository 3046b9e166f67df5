//! `dray render --trace-out`: a job's traffic as a trace (docs/caches.md "The trace's
//! schema"), and its replay in SimGrid (`benches/sim/replay.py`).
//!
//! - the trace's records add up to the job's own statistics (`--stats`): rays traced,
//!   rays and bytes sent between workers, domain loads;
//! - the replay runs on it: every step replayed, its rays equal to the trace's, a
//!   positive and finite time, and a slower link giving a longer time. SimGrid is
//!   fetched by `benches/sim/setup.sh`; when it cannot be, the test says so and fails
//!   under `CI=true` (it is skipped, loudly, elsewhere);
//! - cache-link messages (`cache` records) add up, kind by kind, to the job's traffic
//!   between processes under both placements, with ray caches and with hit maps, and the
//!   replay sends every one of them between two nodes;
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
    record_with(dir, &workers.to_string(), workers, &[])
}

/// [`record`] with more flags, in files named by `tag`.
fn record_with(
    dir: &Path,
    tag: &str,
    workers: u32,
    flags: &[&str],
) -> (PathBuf, Vec<Value>, Value) {
    let trace = dir.join(format!("trace-{tag}.jsonl"));
    let stats = dir.join(format!("stats-{tag}.json"));
    let mut cmd = dray();
    cmd.args(["render", "-q"])
        .args(JOB)
        .args(flags)
        .arg("--workers")
        .arg(workers.to_string())
        .arg("--output")
        .arg(dir.join(format!("img-{tag}.png")))
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
        recs.iter().all(|r| r["v"] == 2),
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

/// Jobs with ray caches and hit maps on 3 in-process workers, under both placements:
/// the trace's `cache` lines add up to the job's traffic between processes kind by kind
/// (bytes, and messages to `cache_messages`), each kind the placement sends is there,
/// and each worker that sent one declared its own cache host. The replay sends every
/// message between two nodes at the trace's node count, and takes longer with them
/// on slow links.
///
/// "Add up" allows one thing: a message counted after its worker's last report reached
/// the coordinator is on the wire, so in the trace, but not in `--stats` (2 runs of 36
/// on 2026-11-30: a lookup and its answer, or the 2 merges and 2 acks a worker flushes
/// as the job ends). So the trace may exceed the stats by at most [`LATE`] messages per
/// worker, and never fall short.
#[test]
fn cache_link_messages_add_up_to_the_traffic_by_kind_and_replay() {
    let dir = common::tmp("traffic-trace-caches");
    let cache = "radius=15,angle-deg=20,coarse=24,fill=true";
    let remote = format!("{cache},placement=remote");
    for (tag, flags, sent) in [
        (
            "cache-remote",
            vec!["--ray-cache", remote.as_str()],
            &["lookups", "answers", "ticket_returns"][..],
        ),
        (
            "cache-sender",
            vec!["--ray-cache", cache],
            &["ticket_returns", "entry_copies"][..],
        ),
        (
            "phm-remote",
            vec!["--phm", "miss=0.2,hit=0.8,placement=remote"],
            &["lookups", "answers"][..],
        ),
        (
            "phm-sender",
            vec!["--phm", "miss=0.2,hit=0.8,merge=64"],
            &["map_merges"][..],
        ),
    ] {
        let workers = 3;
        let (path, recs, stats) = record_with(&dir, tag, workers, &flags);
        let t = &stats["traffic"];
        let cache: Vec<&Value> = recs.iter().filter(|r| r["rec"] == "cache").collect();
        let msgs: u64 = cache.iter().map(|r| u(&r["msgs"])).sum();
        let late = msgs
            .checked_sub(u(&t["cache_messages"]))
            .unwrap_or_else(|| {
                panic!("{tag}: {msgs} messages in the trace, fewer than --stats counts: {t}")
            });
        assert!(
            late <= LATE * workers as u64,
            "{tag}: {late} messages in the trace beyond --stats: {t}"
        );
        // Every kind of cache-link message `--stats` names (all but ray batches).
        let kinds = t.as_object().expect("traffic by kind").keys();
        for kind in kinds.filter(|k| !["rays", "total", "cache_messages"].contains(&k.as_str())) {
            let kind = kind.as_str();
            let of_kind: Vec<u64> = cache
                .iter()
                .filter(|r| r["kind"] == kind)
                .map(|r| u(&r["bytes"]))
                .collect();
            let (bytes, counted) = (of_kind.iter().sum::<u64>(), u(&t[kind]));
            // At most the `late` largest messages of the kind beyond --stats.
            let mut largest = of_kind.clone();
            largest.sort_unstable_by(|a, b| b.cmp(a));
            let slack: u64 = largest.iter().take(late as usize).sum();
            assert!(
                bytes >= counted && bytes - counted <= slack,
                "{tag}: {kind}: {bytes} bytes in the trace, {counted} in --stats ({late} late messages): {t}"
            );
            if late == 0 {
                assert_eq!(bytes, counted, "{tag}: {kind} bytes: trace against --stats");
            }
            if sent.contains(&kind) {
                assert!(bytes > 0, "{tag}: no {kind} between processes: {t}");
            }
        }
        for r in &cache {
            assert!(r["dir"] == "sent" || r["dir"] == "received", "{tag}: {r}");
            assert!(r["host"].is_string() && u(&r["t"]) > 0, "{tag}: {r}");
        }
        let senders: std::collections::BTreeSet<&str> =
            cache.iter().filter_map(|r| r["worker"].as_str()).collect();
        let declared: std::collections::BTreeSet<&str> = recs
            .iter()
            .filter(|r| r["rec"] == "cache_host")
            .filter_map(|r| r["worker"].as_str())
            .collect();
        assert_eq!(
            senders, declared,
            "{tag}: a cache_host line per worker that sent"
        );
        if tag != "cache-remote" {
            continue;
        }
        let Some(r) = replay(&path, &[]) else {
            continue;
        };
        assert_eq!(u(&r["steps"]), u(&r["trace"]["steps"]), "{tag}: every step");
        assert_eq!(
            (u(&r["cache_messages"]), u(&r["cache_local"])),
            (msgs, 0),
            "{tag}: every message between two nodes"
        );
        let slow = |extra: &[&str]| {
            let args = [&["--bandwidth", "1Mbps", "--latency", "1ms"][..], extra].concat();
            let r = replay(&path, &args).expect("replayed");
            r["makespan_s"].as_f64().expect("a time")
        };
        let (with, without) = (slow(&[]), slow(&["--no-cache-messages"]));
        assert!(
            with > without,
            "{tag}: cache messages on 1 Mbit/s links take time: {with} s with, {without} s without"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Cache-link messages per worker that may be on the wire after its last report reached
/// the coordinator (so in a trace, not in `--stats`): a lookup and its answer, or the
/// merges and acks flushed as a job ends (2 merges, 2 acks on 3 workers).
const LATE: u64 = 4;

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
    let emulated = [
        "--bandwidth",
        "10Mbps",
        "--latency",
        "1ms",
        "--topology",
        "pairs",
        "--network-model",
        "CM02",
    ];
    let pairs = replay(trace, &emulated).expect("replayed");
    assert_eq!(u(&pairs["steps"]), u(&pairs["trace"]["steps"]));
    assert_eq!(u(&pairs["rays_sent"]), sent);
    assert_eq!(pairs["topology"], "pairs", "{pairs}");
    let p = pairs["makespan_s"].as_f64().expect("time");
    assert!(
        p > 0.0 && p <= s,
        "links per pair without TCP factors: {p} s, one link per node with them: {s} s"
    );
    // The same links, every node computing on one shared host of one core (worker
    // processes of `dray cluster --emulate-link` sharing a machine).
    let shared = replay(
        trace,
        &[&emulated[..], &["--one-host", "--cores", "1"]].concat(),
    )
    .expect("replayed");
    assert_eq!(u(&shared["steps"]), u(&shared["trace"]["steps"]));
    assert_eq!(u(&shared["rays_sent"]), sent);
    assert_eq!(
        (&shared["topology"], &shared["shared_cores"]),
        (&Value::from("pairs"), &Value::from(true)),
        "{shared}"
    );
    assert!(
        shared["predicted_s"]
            .as_f64()
            .is_some_and(|t| t > 0.0 && t.is_finite())
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
