//! Schedules and memory budgets end to end (docs/architecture.md "Scheduling"): every
//! schedule (auto, replicated, image-plane, domain,
//! dynamic, dynamic-from-image-plane) gives the reference renderer's bits (`dray render --workers 0`) on 1, 2 and 4
//! in-process workers and on a real `dray cluster` with `dray submit`, with and without a
//! memory budget that forces domains to be evicted; a budget smaller than one domain is a
//! clear job error that kills nothing; the `--stats` JSON of `dray render` and
//! `dray submit` carries the scheduling metrics; bad flags are one-line errors.

mod common;
mod support;

use std::path::Path;
use std::process::{Output, Stdio};

use serde_json::Value;
use support::{Proc, WorkerCluster, capture_stderr, dray};

/// Every schedule a job can ask for.
const SCHEDULES: [&str; 6] = dray_coordinator::scheduler::policy::SCHEDULE_NAMES;

/// The schedule a job asking for `schedule` ran with, from its stats: the one forced,
/// or for `auto` the one it chose (replicated or dynamic), with a reason that says auto
/// chose it.
fn ran_as(schedule: &str, stats: &Value, what: &str) -> String {
    let ran = stats["schedule"].as_str().unwrap_or_default().to_string();
    let why = stats["placement"].as_str().unwrap_or_default();
    if schedule == "auto" {
        assert!(
            (ran == "replicated" || ran == "dynamic") && why.starts_with(&format!("{ran} (auto)")),
            "{what}: auto ran as {ran:?} because {why:?}"
        );
    } else {
        assert_eq!(ran, schedule, "{what}: {stats}");
        assert!(why.contains("forced"), "{what}: placement {why:?}");
    }
    ran
}

/// The scene: 8 kd domains of about 85 kB each (as the workers count them).
const SCENE: &str = "cornell:glass";

/// A small image with several domains: two integrators.
fn flags(integrator: &str) -> Vec<&str> {
    vec![
        "--width",
        "48",
        "--height",
        "36",
        "--spp",
        "2",
        "--seed",
        "5",
        "--max-depth",
        "6",
        "--domains",
        "8",
        "--integrator",
        integrator,
    ]
}

const INTEGRATORS: [&str; 2] = ["path", "whitted"];

/// Per-worker budgets tried, smallest first, for one that forces eviction: the first
/// that renders (so it holds the biggest domain) is used. With these domains a worker's
/// share for domains (the budget less its ray queues, see `WorkerConfig::limits`) holds
/// one or two of the eight, far fewer than all of them.
const EVICTING_BUDGETS: [&str; 4] = ["600K", "700K", "800K", "1M"];

/// A cluster budget under which `--domains 8` fits (about two domains per worker) but
/// `--domains 1` (the whole scene as one domain) does not.
const CLUSTER_BUDGET: &str = "700K";

/// Cluster port slots, one per test (tests run in parallel).
const SLOT_UNBUDGETED: u16 = 0;
const SLOT_BUDGETED: u16 = 1;

/// How long one `dray submit` may take before the test fails instead of hanging.
const SUBMIT_TIMEOUT_SECS: f64 = 180.0;

/// The reference image (`--workers 0`: tiles traced through the domains, no actors)
/// and its ray counts.
fn reference(dir: &Path, integrator: &str) -> (Vec<u8>, Value) {
    let tag = format!("reference-{integrator}");
    let r = common::render(
        dir,
        &tag,
        SCENE,
        &[&flags(integrator)[..], &["--workers", "0"]].concat(),
    );
    assert!(r.ok, "{tag}: {}", r.stderr);
    let stats = r.stats.expect("reference stats");
    assert_eq!(stats["schedule"], "none", "{stats}");
    assert_eq!(stats["workers"], Value::Array(Vec::new()), "{stats}");
    (
        std::fs::read(r.png.expect("png")).expect("read png"),
        stats["rays"].clone(),
    )
}

fn u64_of(stats: &Value, key: &str) -> u64 {
    stats[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no unsigned {key:?} in {stats}"))
}

/// The scheduling keys of a `--stats` JSON for a job that ran on `workers` workers
/// under `schedule`: all there, with loads counted and per-worker entries that add up.
fn check_scheduling_stats(stats: &Value, schedule: &str, workers: usize, what: &str) {
    let schedule = ran_as(schedule, stats, what);
    for key in [
        "domain_loads",
        "evictions",
        "rays_exchanged",
        "rays_forwarded",
        "ray_bytes_sent",
        "queue_peak",
        "scheduler_rounds",
        "routing_version",
        "tiles_retraced",
        "passes_ahead",
    ] {
        u64_of(stats, key);
    }
    assert!(
        stats["domain_load_seconds"]
            .as_f64()
            .is_some_and(|s| s >= 0.0),
        "{what}: {stats}"
    );
    assert!(
        u64_of(stats, "domain_loads") + u64_of(stats, "domains_warm") > 0,
        "{what}: no domain loaded or found resident: {stats}"
    );
    assert!(u64_of(stats, "routing_version") >= 1, "{what}: {stats}");
    let per_worker = stats["workers"]
        .as_array()
        .unwrap_or_else(|| panic!("{what}: no workers list in {stats}"));
    assert_eq!(per_worker.len(), workers, "{what}: {stats}");
    let mut loads = 0;
    let mut warm = 0;
    let mut evictions = 0;
    for w in per_worker {
        assert!(
            w["worker_id"].as_str().is_some_and(|id| !id.is_empty()),
            "{what}: {w}"
        );
        for key in [
            "domain_loads",
            "domains_warm",
            "evictions",
            "queue_peak",
            "rays_traced",
        ] {
            u64_of(w, key);
        }
        for key in ["domain_load_seconds", "idle_seconds"] {
            assert!(
                w[key].as_f64().is_some_and(|s| s >= 0.0),
                "{what}: {key} in {w}"
            );
        }
        loads += u64_of(w, "domain_loads");
        warm += u64_of(w, "domains_warm");
        evictions += u64_of(w, "evictions");
    }
    assert_eq!(loads, u64_of(stats, "domain_loads"), "{what}: {stats}");
    assert_eq!(warm, u64_of(stats, "domains_warm"), "{what}: {stats}");
    assert_eq!(evictions, u64_of(stats, "evictions"), "{what}: {stats}");
    if schedule == "image-plane" || schedule == "replicated" {
        assert_eq!(
            u64_of(stats, "rays_exchanged"),
            0,
            "{what}: {schedule} exchanged rays: {stats}"
        );
    }
}

/// `dray render` on `workers` in-process workers with `extra` flags: must succeed with
/// the reference bits and ray counts; returns its stats.
fn render_on_workers(
    dir: &Path,
    integrator: &str,
    schedule: &str,
    workers: usize,
    extra: &[&str],
    want: &(Vec<u8>, Value),
) -> Value {
    let what = format!("{integrator} {schedule} on {workers} in-process workers {extra:?}");
    let n = workers.to_string();
    let r = common::render(
        dir,
        "actors",
        SCENE,
        &[
            &flags(integrator)[..],
            &["--workers", &n, "--schedule", schedule],
            extra,
        ]
        .concat(),
    );
    assert!(r.ok, "{what}: {}", r.stderr);
    let png = std::fs::read(r.png.expect("png")).expect("read png");
    assert!(png == want.0, "{what}: the image differs from --workers 0");
    let stats = r.stats.unwrap_or_else(|| panic!("{what}: no stats"));
    assert_eq!(stats["rays"], want.1, "{what}: rays by kind");
    check_scheduling_stats(&stats, schedule, workers, &what);
    stats
}

#[test]
fn every_schedule_gives_the_reference_bits_on_1_2_and_4_in_process_workers() {
    let dir = common::tmp("schedules-in-process");
    for integrator in INTEGRATORS {
        let want = reference(&dir, integrator);
        for schedule in SCHEDULES {
            for workers in [1, 2, 4] {
                let stats = render_on_workers(&dir, integrator, schedule, workers, &[], &want);
                let what = format!("{integrator} {schedule} on {workers}: {stats}");
                // Unlimited memory under a static schedule: nothing is evicted; each
                // domain is loaded once by its owner (domain), at most once per worker
                // (image-plane, replicated). The dynamic schedule may move domains.
                // Unlimited memory: auto replicates (the scene fits every worker).
                let ran = ran_as(schedule, &stats, &what);
                if schedule == "auto" {
                    assert_eq!(ran, "replicated", "{what}");
                }
                match ran.as_str() {
                    "domain" => assert_eq!(u64_of(&stats, "domain_loads"), 8, "{what}"),
                    "image-plane" | "replicated" => assert!(
                        u64_of(&stats, "domain_loads") <= 8 * workers as u64,
                        "{what}"
                    ),
                    _ => {}
                }
                // The dynamic schedules may move domains (and leaving image-plane lets
                // go of those a worker no longer owns).
                if !ran.starts_with("dynamic") {
                    assert_eq!(u64_of(&stats, "evictions"), 0, "{what}");
                }
            }
        }
        // Hot-domain replication is a dynamic option; same bits.
        render_on_workers(&dir, integrator, "dynamic", 4, &["--replicate"], &want);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_budget_that_forces_eviction_keeps_the_bits() {
    let dir = common::tmp("schedules-evict");
    let want_path = reference(&dir, "path");
    // The smallest budget that holds the biggest domain.
    let mut tried = Vec::new();
    let budget = EVICTING_BUDGETS
        .iter()
        .copied()
        .find(|b| {
            let n = common::render(
                &dir,
                "probe",
                SCENE,
                &[
                    &flags("path")[..],
                    &["--workers", "1", "--memory-budget", b],
                ]
                .concat(),
            );
            tried.push(format!("{b}: {}", n.stderr.trim()));
            n.ok
        })
        .unwrap_or_else(|| panic!("no budget in {EVICTING_BUDGETS:?} renders: {tried:#?}"));
    eprintln!("eviction: a budget of {budget} per worker");
    for integrator in INTEGRATORS {
        let want = if integrator == "path" {
            want_path.clone()
        } else {
            reference(&dir, integrator)
        };
        for schedule in SCHEDULES {
            for workers in [1, 2, 4] {
                let stats = render_on_workers(
                    &dir,
                    integrator,
                    schedule,
                    workers,
                    &["--memory-budget", budget, "--load-delay-ms", "1"],
                    &want,
                );
                assert!(
                    u64_of(&stats, "evictions") > 0,
                    "{integrator} {schedule} on {workers} workers with {budget}: nothing \
                     evicted: {stats}"
                );
                assert!(
                    u64_of(&stats, "domain_loads") > 8,
                    "{integrator} {schedule} on {workers} workers: {stats}"
                );
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_budget_smaller_than_one_domain_is_a_clear_job_error() {
    let dir = common::tmp("schedules-too-small");
    for schedule in SCHEDULES {
        for workers in ["1", "3"] {
            let r = common::render(
                &dir,
                "too-small",
                SCENE,
                &[
                    &flags("path")[..],
                    &[
                        "--workers",
                        workers,
                        "--schedule",
                        schedule,
                        "--memory-budget",
                        "64K",
                    ],
                ]
                .concat(),
            );
            let what = format!("{schedule} on {workers} workers with 64K");
            assert!(!r.ok, "{what}: rendered");
            let last = r.stderr.trim_end().lines().last().unwrap_or_default();
            assert!(
                last.starts_with("dray: error: ") && last.contains("memory budget"),
                "{what}: {}",
                r.stderr
            );
            assert!(!dir.join("too-small.png").exists(), "{what}: an image");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `dray submit` with a hang guard; (output, stats JSON when it succeeded).
fn submit(addr: &str, dir: &Path, tag: &str, flags: &[&str]) -> (Output, Option<Value>) {
    let png = dir.join(format!("{tag}.png"));
    let stats = dir.join(format!("{tag}.json"));
    let _ = std::fs::remove_file(&png);
    let _ = std::fs::remove_file(&stats);
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, SCENE])
        .args(flags)
        .arg("--output")
        .arg(&png)
        .arg("--stats")
        .arg(&stats)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let err = capture_stderr(&mut p.child);
    let status = p.wait_timeout(SUBMIT_TIMEOUT_SECS);
    let text = err.after(status.is_some());
    let Some(status) = status else {
        panic!("HANG: dray submit {tag} {flags:?} did not finish: {text}");
    };
    let json = status
        .success()
        .then(|| std::fs::read_to_string(&stats).ok())
        .flatten()
        .map(|s| serde_json::from_str(&s).expect("submit --stats is JSON"));
    (
        Output {
            status,
            stdout: Vec::new(),
            stderr: text.into_bytes(),
        },
        json,
    )
}

/// Submit `flags` with `schedule` to `cluster` of `workers`: the reference bits, and
/// scheduling stats; returns the stats.
fn submit_and_compare(
    cluster: &WorkerCluster,
    workers: usize,
    dir: &Path,
    tag: &str,
    flags: &[&str],
    want: &[u8],
) -> Value {
    let (out, stats) = submit(&cluster.addr, dir, tag, flags);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "{tag}: dray submit {flags:?} failed: {err}\ncluster log:\n{}",
        cluster.log()
    );
    let png = std::fs::read(dir.join(format!("{tag}.png"))).expect("submit png");
    assert!(
        png == want,
        "{tag}: the image differs from dray render --workers 0"
    );
    let stats = stats.unwrap_or_else(|| panic!("{tag}: no --stats file"));
    let asked = flags
        .iter()
        .position(|f| *f == "--schedule")
        .map_or("auto", |i| flags[i + 1]);
    check_scheduling_stats(&stats, asked, workers, tag);
    let schedule = ran_as(asked, &stats, tag);
    // The keys `dray render --stats` has too.
    for key in ["triangles", "domains", "rays_total", "wall_time_s", "rays"] {
        assert!(!stats[key].is_null(), "{tag}: no {key} in {stats}");
    }
    // The package's cut: the job's --domains, or one domain when auto replicates a
    // scene cut for the job.
    let cut = flags
        .iter()
        .position(|f| *f == "--domains")
        .map_or(1, |i| flags[i + 1].parse::<u64>().expect("--domains N"));
    assert_eq!(u64_of(&stats, "domains"), cut, "{tag}: {stats}");
    // The summary names the schedule, the loads and why.
    assert!(
        err.contains(&format!("schedule {schedule} on {workers} worker"))
            && err.contains("domain loads")
            && err.contains(&format!("placement {schedule}")),
        "{tag}: {err}"
    );
    stats
}

#[test]
fn every_schedule_on_a_cluster_gives_the_reference_bits() {
    let dir = common::tmp("schedules-cluster");
    let cluster = WorkerCluster::start(3, SLOT_UNBUDGETED, &dir, &[]);
    let mut warm = Vec::new();
    for integrator in INTEGRATORS {
        let (want, _) = reference(&dir, integrator);
        for schedule in SCHEDULES {
            let tag = format!("cluster-{integrator}-{schedule}");
            let f = [&flags(integrator)[..], &["--schedule", schedule]].concat();
            let stats = submit_and_compare(&cluster, 3, &dir, &tag, &f, &want);
            if !schedule.starts_with("dynamic") {
                assert_eq!(u64_of(&stats, "evictions"), 0, "{tag}: {stats}");
            }
            warm.push(u64_of(&stats, "domains_warm"));
        }
    }
    // Every job is the same scene cut the same way: the workers keep the last job's
    // domains, so the later jobs find them resident, and their bits (checked above)
    // are those of domains loaded afresh.
    assert_eq!(
        warm[0], 0,
        "the first job cannot find warm domains: {warm:?}"
    );
    assert!(
        warm[1..].iter().all(|&w| w > 0),
        "a later job of the same package loaded every domain again: {warm:?}"
    );

    // The defaults on a cluster with no budget (issue 40): auto replicates the scene,
    // cut as one domain, and every worker traces whole paths for its tiles: no ray
    // between processes, no round, the passes traced ahead instead of each waiting at
    // its barrier, and the reference bits.
    let (want, _) = reference(&dir, "path");
    let mut f = flags("path");
    let at = f.iter().position(|x| *x == "--domains").expect("--domains");
    f.drain(at..at + 2);
    let stats = submit_and_compare(&cluster, 3, &dir, "cluster-defaults", &f, &want);
    assert_eq!(stats["schedule"], "replicated", "{stats}");
    for zero in ["rays_exchanged", "rays_forwarded", "scheduler_rounds"] {
        assert_eq!(u64_of(&stats, zero), 0, "{zero}: {stats}");
    }
    assert_eq!(stats["traffic"]["rays"], 0, "{stats}");
    assert_eq!(u64_of(&stats, "passes_ahead"), 1, "{stats}");
    let why = stats["placement"].as_str().unwrap_or_default();
    assert!(
        why.contains("fits every worker") && why.contains("unlimited"),
        "{why}"
    );
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cluster_with_a_memory_budget_evicts_keeps_the_bits_and_survives_a_job_too_big() {
    let dir = common::tmp("schedules-cluster-budget");
    let (want, _) = reference(&dir, "path");
    let cluster = WorkerCluster::start(
        2,
        SLOT_BUDGETED,
        &dir,
        &["--memory-budget", CLUSTER_BUDGET, "--load-delay-ms", "1"],
    );
    for schedule in SCHEDULES {
        let tag = format!("budget-{schedule}");
        let f = [&flags("path")[..], &["--schedule", schedule]].concat();
        let stats = submit_and_compare(&cluster, 2, &dir, &tag, &f, &want);
        if schedule == "auto" {
            // Eight domains of about 85 kB do not fit in three quarters of 700 kB: auto
            // owns domains and moves rays, and names the worker that decided it.
            assert_eq!(stats["schedule"], "dynamic", "{tag}: {stats}");
            let why = stats["placement"].as_str().unwrap_or_default();
            assert!(why.contains("does not fit worker"), "{tag}: {why}");
        }
        assert!(
            u64_of(&stats, "evictions") > 0,
            "{tag}: nothing evicted with {CLUSTER_BUDGET} per worker: {stats}"
        );
        // `dray submit`'s doubling passes of 2 spp, under a budget: the workers trace
        // the second pass ahead of the first (docs/architecture.md "Trace ahead"), and
        // the image is still `dray render`'s.
        assert_eq!(u64_of(&stats, "passes_ahead"), 1, "{tag}: {stats}");
    }

    // The whole scene as one domain does not fit: a clear job error, nothing killed.
    let mut one_domain = flags("path");
    let at = one_domain
        .iter()
        .position(|f| *f == "--domains")
        .expect("--domains")
        + 1;
    one_domain[at] = "1";
    let (out, _) = submit(&cluster.addr, &dir, "too-big", &one_domain);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "a job bigger than the budget succeeded: {err}"
    );
    let last = err.trim_end().lines().last().unwrap_or_default();
    assert!(
        last.starts_with("dray: error: job ") && last.contains("memory budget"),
        "{err}"
    );
    assert!(!dir.join("too-big.png").exists());
    assert!(cluster.all_alive(), "a process died: {}", cluster.log());

    // And the cluster serves the next job, right.
    submit_and_compare(&cluster, 2, &dir, "after-too-big", &flags("path"), &want);
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

/// One line on stderr, exit 2 (usage) or 1, naming `words`.
fn one_line_error(args: &[&str], words: &[&str]) {
    let out = dray().args(args).output().expect("run dray");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{args:?} succeeded");
    assert_eq!(
        err.trim_end().lines().count(),
        1,
        "{args:?}: not one line: {err:?}"
    );
    assert!(err.starts_with("dray: error: "), "{args:?}: {err}");
    for w in words {
        assert!(err.contains(w), "{args:?}: {w:?} not in {err}");
    }
}

#[test]
fn bad_schedule_and_budget_flags_are_one_line_errors() {
    let valid = [
        "bogus",
        "auto, replicated, image-plane, domain, dynamic or dynamic-from-image-plane",
    ];
    one_line_error(&["render", "cornell", "--schedule", "bogus"], &valid);
    one_line_error(
        &["render", "cornell", "--workers", "0", "--schedule", "bogus"],
        &valid,
    );
    // Checked before connecting: nobody listens on port 1.
    one_line_error(
        &[
            "submit",
            "--coordinator",
            "127.0.0.1:1",
            "cornell",
            "--schedule",
            "bogus",
        ],
        &valid,
    );
    one_line_error(
        &["render", "cornell", "--schedule", "domain", "--replicate"],
        &["--replicate", "dynamic"],
    );
    one_line_error(
        &[
            "submit",
            "--coordinator",
            "127.0.0.1:1",
            "cornell",
            "--replicate",
            "--schedule",
            "image-plane",
        ],
        &["--replicate", "dynamic"],
    );
    let bytes = ["12X", "K, M, G or T"];
    one_line_error(&["render", "cornell", "--memory-budget", "12X"], &bytes);
    one_line_error(
        &[
            "worker",
            "--coordinator",
            "127.0.0.1:1",
            "--listen",
            "127.0.0.1:0",
            "--memory-budget",
            "12X",
        ],
        &bytes,
    );
    one_line_error(
        &["cluster", "--workers", "1", "--memory-budget", "12X"],
        &bytes,
    );
    one_line_error(
        &["render", "cornell", "--load-delay-ms", "soon"],
        &["--load-delay-ms"],
    );
}
