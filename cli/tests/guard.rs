//! The guard against silent regressions (issue 38): a handful of fixed jobs on 4
//! in-process workers under a memory budget, each run with `dray render --stats`, and
//! the counts that do not depend on the machine (domain loads and evictions per schedule
//! and pass cut, rays by kind, rays and bytes between workers, rays forwarded, tiles
//! traced again, ray-cache hits) compared with the checked-in baseline
//! `tests/guard/baseline.json`. A count that grows past its tolerance (or, for a count
//! where more is better, falls below it) fails the test, naming the job, the count, the
//! baseline and what was measured. Timings stay out: they belong in docs/benchmarks.md.
//!
//! Every job's image is also checked against the same job with `--passes one`: passes
//! change when an image is seen, never its bits.
//!
//! Loads, evictions and rays forwarded of the dynamic and domain schedules depend on
//! timing (when queue reports and batches arrive), and on a loaded machine one run can
//! land in the tail of their spread (CI saw dynamic-one at 55 loads against runs of
//! 38-54 here). A job therefore gets up to `RUNS` runs and passes on the first whose
//! counts are all within the baseline: noise has to hit every run to fail it, while a
//! regression moves the whole spread and fails them all.
//!
//! **Updating the baseline is a deliberate commit.** Run
//! `DRAY_GUARD_WRITE=1 cargo test --release -p dray --test guard`: the counts measured
//! replace the baseline's values (tolerances are kept), and the commit says why they
//! moved. How the tolerances were chosen is in the baseline's `about` and in
//! docs/benchmarks.md ("Regression guard").

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

/// The scene: 2,221,520 / 16 domains would be slow; this one has 16 kd domains of about
/// 2.6 MB each as the workers count them, of which a worker's budget below holds one or
/// two, so every schedule loads and evicts.
const SCENE: &str = "grid:iso:gyroid:48:2x2x2";

/// Each worker's `--memory-budget`: a quarter goes to ray queues, the rest holds about
/// two of the sixteen domains (with room to build one more).
const BUDGET: &str = "12000000";

/// How many times a job may run before its counts fail the test: the first run within
/// the baseline passes it (see the loop in `counts_stay_within_the_baseline`).
const RUNS: usize = 3;

/// The flags every guarded job shares.
const COMMON: [&str; 20] = [
    "--domains",
    "16",
    "--layout",
    "kd",
    "--width",
    "64",
    "--height",
    "64",
    "--spp",
    "4",
    "--integrator",
    "path",
    "--max-depth",
    "2",
    "--workers",
    "4",
    "--threads",
    "2",
    "--memory-budget",
    BUDGET,
];

/// The guarded jobs: (name, extra flags). Every schedule with one pass and with
/// doubling passes, and one job with a ray cache (its hits are guarded).
fn jobs() -> Vec<(String, Vec<&'static str>)> {
    let mut v = Vec::new();
    for schedule in ["dynamic", "image-plane", "domain"] {
        for passes in ["one", "doubling"] {
            v.push((
                format!("{schedule}-{passes}"),
                vec!["--schedule", schedule, "--passes", passes],
            ));
        }
    }
    v.push((
        "dynamic-one-ray-cache".to_string(),
        vec![
            "--schedule",
            "dynamic",
            "--passes",
            "one",
            "--ray-cache",
            "radius=0.2,coarse=16",
        ],
    ));
    v
}

/// Whether a count should not grow ("max": loads, bytes, rays) or not fall ("min":
/// cache hits).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Direction {
    Max,
    Min,
}

/// The counts read from one job's `--stats` JSON: (name, value, direction). A count
/// the JSON lacks (no ray cache on the job) is left out.
fn counts(stats: &Value) -> Vec<(&'static str, u64, Direction)> {
    let u = |v: &Value| v.as_u64();
    let mut out = Vec::new();
    let mut put = |name: &'static str, v: Option<u64>, dir: Direction| {
        if let Some(v) = v {
            out.push((name, v, dir));
        }
    };
    put("domain_loads", u(&stats["domain_loads"]), Direction::Max);
    put("evictions", u(&stats["evictions"]), Direction::Max);
    put("rays_total", u(&stats["rays_total"]), Direction::Max);
    for kind in ["camera", "diffuse", "shadow"] {
        let name = match kind {
            "camera" => "rays_camera",
            "diffuse" => "rays_diffuse",
            _ => "rays_shadow",
        };
        put(name, u(&stats["rays"][kind]), Direction::Max);
    }
    put(
        "rays_exchanged",
        u(&stats["rays_exchanged"]),
        Direction::Max,
    );
    put(
        "rays_forwarded",
        u(&stats["rays_forwarded"]),
        Direction::Max,
    );
    put("bytes_total", u(&stats["traffic"]["total"]), Direction::Max);
    put(
        "cache_messages",
        u(&stats["traffic"]["cache_messages"]),
        Direction::Max,
    );
    put(
        "tiles_retraced",
        u(&stats["tiles_retraced"]),
        Direction::Max,
    );
    let rc = &stats["ray_cache"];
    if rc.is_object() {
        let hits = u(&rc["outer_hits"]).zip(u(&rc["inner_hits"]));
        put("cache_hits", hits.map(|(a, b)| a + b), Direction::Min);
    }
    out
}

/// The checked-in baseline.
fn baseline_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/guard/baseline.json")
}

/// Whether `measured` is within `entry`'s tolerance of its baseline value: at most
/// `value * (1 + tolerance) + slack` for a count that must not grow, at least
/// `value * (1 - tolerance) - slack` for one that must not fall.
fn within(entry: &Value, measured: u64, dir: Direction) -> Result<(), String> {
    let value = entry["value"].as_f64().ok_or("no value")?;
    let tol = entry["tolerance"].as_f64().unwrap_or(0.0);
    let slack = entry["slack"].as_f64().unwrap_or(0.0);
    let m = measured as f64;
    match dir {
        Direction::Max => {
            let bound = value * (1.0 + tol) + slack;
            (m <= bound).then_some(()).ok_or(format!(
                "{measured} > {bound:.0} (baseline {value}, tolerance {tol}, slack {slack})"
            ))
        }
        Direction::Min => {
            let bound = value * (1.0 - tol) - slack;
            (m >= bound).then_some(()).ok_or(format!(
                "{measured} < {bound:.0} (baseline {value}, tolerance {tol}, slack {slack})"
            ))
        }
    }
}

#[test]
fn counts_stay_within_the_baseline() {
    let dir = common::tmp("guard");
    let text = std::fs::read_to_string(baseline_path()).expect("tests/guard/baseline.json");
    let mut baseline: Value = serde_json::from_str(&text).expect("baseline JSON");
    let write = std::env::var_os("DRAY_GUARD_WRITE").is_some();
    let mut failures = Vec::new();
    let mut measured_all: BTreeMap<String, BTreeMap<&str, u64>> = BTreeMap::new();
    let mut one_pass_png: BTreeMap<String, Vec<u8>> = BTreeMap::new();
    for (name, extra) in jobs() {
        let mut args: Vec<&str> = COMMON.to_vec();
        args.extend(extra.iter().copied());
        // Up to RUNS runs: the first that keeps every count within the baseline passes
        // the job. Loads, evictions and rays forwarded of the dynamic and domain
        // schedules depend on when queue reports and batches arrive, so one run on a
        // loaded machine can land in the tail of their spread; a regression moves the
        // whole spread and fails every run.
        let mut last_failures = Vec::new();
        for run_index in 0..RUNS {
            let run_name = format!("{name}-run{run_index}");
            let run = common::render(&dir, &run_name, SCENE, &args);
            assert!(run.ok, "{name}: dray render failed: {}", run.stderr);
            let stats = run.stats.expect("stats JSON");
            let png = std::fs::read(run.png.as_ref().expect("png")).expect("read png");
            // Same bits: a schedule's doubling passes give its one-pass image, and every
            // run of a job gives the same image.
            let schedule = name.split('-').next().unwrap_or_default().to_string();
            if name.ends_with("-one") {
                let first = one_pass_png.entry(schedule).or_insert_with(|| png.clone());
                assert!(
                    *first == png,
                    "{run_name}: the image differs from the job's first run"
                );
            } else if name.ends_with("-doubling") {
                let one = one_pass_png.get(&schedule).expect("one pass ran first");
                assert!(
                    *one == png,
                    "{run_name}: the image differs from the same job with --passes one"
                );
            }
            let got = counts(&stats);
            eprintln!(
                "guard {run_name}: {}",
                got.iter()
                    .map(|(k, v, _)| format!("{k}={v}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            );
            let mut run_failures = Vec::new();
            for &(count, value, dir) in &got {
                measured_all
                    .entry(name.clone())
                    .or_default()
                    .insert(count, value);
                if write {
                    continue;
                }
                let entry = &baseline["jobs"][&name][count];
                if entry.is_null() {
                    run_failures.push(format!(
                        "{name}.{count}: not in the baseline (measured {value}); add it with \
                         DRAY_GUARD_WRITE=1"
                    ));
                    continue;
                }
                if let Err(e) = within(entry, value, dir) {
                    run_failures.push(format!("{run_name}.{count}: {e}"));
                }
            }
            if write || run_failures.is_empty() {
                last_failures.clear();
                break;
            }
            eprintln!(
                "guard {run_name}: past the baseline: {}",
                run_failures.join("; ")
            );
            last_failures = run_failures;
        }
        failures.extend(last_failures);
    }
    if write {
        for (job, got) in &measured_all {
            for (count, value) in got {
                let slot = &mut baseline["jobs"][job.as_str()][*count];
                if slot.is_null() {
                    *slot = json!({ "value": value, "tolerance": 0.1, "slack": 2 });
                } else {
                    slot["value"] = json!(value);
                    // The spread the tolerance was chosen from belongs to the old value.
                    if let Some(o) = slot.as_object_mut() {
                        o.remove("runs");
                    }
                }
            }
        }
        let text = serde_json::to_string_pretty(&baseline).expect("JSON") + "\n";
        std::fs::write(baseline_path(), text).expect("write the baseline");
        eprintln!("guard: baseline written to {}", baseline_path().display());
        return;
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        failures.is_empty(),
        "counts past the baseline (tests/guard/baseline.json; update it only in a commit \
         that says why):\n  {}",
        failures.join("\n  ")
    );
}
