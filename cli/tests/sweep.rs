//! `dray sweep` end to end (README "dray sweep"), with real `dray` processes: the exact
//! render and every combination of the varied values, in this process and on a local
//! cluster; results.csv, table.md, pareto.png and the images; one-line errors before any
//! rendering.

mod common;
mod support;

use std::collections::HashMap;
use std::path::Path;
use std::process::Output;

use support::{WorkerCluster, dray};

/// The columns every results.csv has (besides one per varied key).
const COLUMNS: [&str; 58] = [
    "setting",
    "domain_loads",
    "domains_warm",
    "wall_s",
    "speedup",
    "rays_traced",
    "rays_sent",
    "bytes_sent",
    "outer_lookups",
    "outer_hits",
    "outer_hit_ratio",
    "inner_lookups",
    "inner_hits",
    "inner_hit_ratio",
    "hit_ratio",
    "coarse_seconds",
    "bytes_per_process",
    "rays_not_sent",
    "bytes_not_sent",
    "tickets_opened",
    "tickets_closed",
    "tickets_stored",
    "tickets_open",
    "rays_bypassed",
    "phm_lookups",
    "phm_rays_skipped",
    "phm_rays_occluded",
    "phm_rays_shaded",
    "phm_probes",
    "phm_cells_decided_hit",
    "phm_cells_decided_miss",
    "phm_map_bytes",
    "rmse",
    "rmse_linear",
    "psnr",
    "flip",
    "image",
    "render_s",
    "cache_bytes",
    "bytes_total",
    "cpu_s",
    "bytes_rays",
    "bytes_lookups",
    "bytes_answers",
    "bytes_ticket_returns",
    "bytes_entry_copies",
    "bytes_map_outcomes",
    "bytes_map_merges",
    "pareto",
    "args",
    "render_s_min",
    "render_s_max",
    "bytes_total_min",
    "bytes_total_max",
    "rmse_min",
    "rmse_max",
    "flip_min",
    "flip_max",
];

fn sweep(args: &[&str], out: &Path, env: &[(&str, &str)]) -> Output {
    let mut cmd = dray();
    cmd.arg("sweep").args(args).arg("--out").arg(out);
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd.output().expect("run dray sweep")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// results.csv as rows of column -> cell (no cell of these sweeps holds a comma, except
/// `args`, which is last and quoted when it does).
fn read_csv(path: &Path) -> (Vec<String>, Vec<HashMap<String, String>>) {
    let text = std::fs::read_to_string(path).expect("read results.csv");
    let mut lines = text.lines();
    let head: Vec<String> = lines
        .next()
        .expect("a header")
        .split(',')
        .map(String::from)
        .collect();
    let rows = lines
        .map(|l| {
            let cells: Vec<&str> = l.splitn(head.len(), ',').collect();
            assert_eq!(cells.len(), head.len(), "{l}");
            head.iter()
                .cloned()
                .zip(cells.iter().map(|c| c.to_string()))
                .collect()
        })
        .collect();
    (head, rows)
}

fn num(row: &HashMap<String, String>, col: &str) -> f64 {
    row[col]
        .parse()
        .unwrap_or_else(|_| panic!("{col} = {:?} is not a number in {row:?}", row[col]))
}

/// What every sweep's output must hold: the columns, an exact first row with no error,
/// balanced tickets, the table, a plot that decodes and every image.
fn check_outputs(out: &Path, keys: &[&str], settings: usize) -> Vec<HashMap<String, String>> {
    let (head, rows) = read_csv(&out.join("results.csv"));
    for c in COLUMNS.iter().chain(keys) {
        assert!(head.iter().any(|h| h == c), "no column {c} in {head:?}");
    }
    assert_eq!(rows.len(), settings + 1, "{rows:?}");
    let exact = &rows[0];
    assert_eq!(exact["setting"], "exact");
    assert_eq!(num(exact, "rmse"), 0.0);
    assert_eq!(num(exact, "rmse_linear"), 0.0);
    assert_eq!(num(exact, "flip"), 0.0);
    assert_eq!(exact["psnr"], "inf");
    assert_eq!(num(exact, "speedup"), 1.0);
    assert_eq!(exact["image"], "exact.png");
    // The exact render has no caches: empty cells, not zeros.
    assert_eq!(exact["tickets_opened"], "");
    for r in &rows {
        assert_eq!(
            r["tickets_opened"], r["tickets_closed"],
            "{}: tickets opened and closed differ",
            r["setting"]
        );
        assert!(num(r, "wall_s") > 0.0, "{r:?}");
        assert!(num(r, "rays_traced") > 0.0, "{r:?}");
        // Every render costs CPU somewhere; bytes are a whole count.
        assert!(num(r, "cpu_s") > 0.0, "{r:?}");
        assert!(r["bytes_total"].parse::<u64>().is_ok(), "{r:?}");
        assert!(r["bytes_rays"].parse::<u64>().is_ok(), "{r:?}");
        let flip = num(r, "flip");
        assert!((0.0..=1.0).contains(&flip), "{r:?}");
        // Little 2011's total hit ratio (both sides of a wall) is a share, its coarse
        // pass a time and its cache memory a size, on every row that has caches.
        if !r["hit_ratio"].is_empty() {
            assert!((0.0..=1.0).contains(&num(r, "hit_ratio")), "{r:?}");
            assert!(num(r, "coarse_seconds") >= 0.0, "{r:?}");
            assert!(r["bytes_per_process"].parse::<u64>().is_ok(), "{r:?}");
        }
        let img = common::rgb(&out.join(&r["image"]));
        assert_eq!(img.dimensions(), (32, 24), "{}", r["image"]);
    }
    let table = std::fs::read_to_string(out.join("table.md")).expect("read table.md");
    assert!(table.contains("| exact |"), "{table}");
    assert!(table.contains("8-bit sRGB"), "{table}");
    for r in &rows[1..] {
        assert!(table.contains(&format!("| {} |", r["setting"])), "{table}");
    }
    let plot = image::open(out.join("pareto.png")).expect("pareto.png decodes");
    assert!(plot.width() >= 400 && plot.height() >= 300);
    rows
}

const BASE: [&str; 9] = [
    "cornell",
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
fn sweeps_ray_cache_radius_and_spp_in_this_process() {
    let dir = common::tmp("sweep-embedded");
    let out = dir.join("out");
    let o = sweep(
        &[
            &BASE[..],
            &[
                "--workers",
                "2",
                "--vary",
                "ray-cache.radius=0,0.2",
                "--vary",
                "spp=1,2",
            ],
        ]
        .concat(),
        &out,
        &[],
    );
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    let rows = check_outputs(&out, &["ray-cache.radius", "spp"], 4);
    let names: Vec<&str> = rows.iter().map(|r| r["setting"].as_str()).collect();
    assert_eq!(
        names,
        [
            "exact",
            "ray-cache.radius=0 spp=1",
            "ray-cache.radius=0 spp=2",
            "ray-cache.radius=0.2 spp=1",
            "ray-cache.radius=0.2 spp=2"
        ]
    );
    assert_eq!(rows[0]["spp"], "2", "the exact row shows the base spp");
    assert_eq!(rows[3]["ray-cache.radius"], "0.2");
    for r in &rows[1..] {
        // Caches were on: every setting looked rays up and ticketed them.
        assert!(num(r, "tickets_opened") > 0.0, "{r:?}");
        assert_eq!(num(r, "tickets_open"), 0.0, "{r:?}");
        assert!(
            Path::new(&out).join(&r["image"]).is_file(),
            "{}",
            r["image"]
        );
        assert!(r["args"].contains("--ray-cache"), "{r:?}");
    }
    // Radius 0 never answers: with the exact render's spp, the exact image.
    assert_eq!(num(&rows[2], "rmse"), 0.0, "{:?}", rows[2]);
    assert_eq!(num(&rows[2], "flip"), 0.0, "{:?}", rows[2]);
    // Half the samples: not the exact image.
    assert!(num(&rows[1], "rmse") > 0.0, "{:?}", rows[1]);
    assert!(num(&rows[1], "flip") > 0.0, "{:?}", rows[1]);
    assert_eq!(rows[1]["image"], "ray-cache.radius-0_spp-1.png");
    // The exact render is `dray render` with the same flags, bit for bit.
    let r = common::render(
        &dir,
        "render",
        "cornell",
        &[&BASE[1..], &["--workers", "2"]].concat(),
    );
    assert!(r.ok, "{}", r.stderr);
    assert_eq!(
        common::rgb(&r.png.expect("png")),
        common::rgb(&out.join("exact.png"))
    );
    let last = err.lines().last().unwrap_or_default();
    for f in ["results.csv", "table.md", "pareto.png"] {
        assert!(last.contains(f), "the last line names {f}: {last:?}");
    }
}

/// A sweep in this process keeps its actors, package and domains from one setting to
/// the next (cli/src/warm.rs): the exact render (no warm-up before it) loads the
/// domains, and no later setting loads one again (counted by the workers, not timed);
/// the images keep their bits.
#[test]
fn the_second_setting_of_a_sweep_loads_no_domain_again() {
    let dir = common::tmp("sweep-warm");
    let out = dir.join("out");
    let o = sweep(
        &[
            &BASE[..],
            &[
                "--workers",
                "2",
                "--schedule",
                "domain",
                "--no-warmup",
                "--vary",
                "spp=1,2",
            ],
        ]
        .concat(),
        &out,
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let rows = check_outputs(&out, &["spp"], 2);
    assert!(num(&rows[0], "domain_loads") > 0.0, "{:?}", rows[0]);
    assert_eq!(num(&rows[0], "domains_warm"), 0.0, "{:?}", rows[0]);
    for r in &rows[1..] {
        assert_eq!(num(r, "domain_loads"), 0.0, "loaded again: {r:?}");
        assert!(num(r, "domains_warm") > 0.0, "{r:?}");
    }
    // spp=2 is the exact render's setting: on warm domains, the same bits.
    assert_eq!(rows[2]["spp"], "2");
    assert_eq!(num(&rows[2], "rmse"), 0.0, "{:?}", rows[2]);
    assert_eq!(
        std::fs::read(out.join(&rows[2]["image"])).expect("png"),
        std::fs::read(out.join("exact.png")).expect("png")
    );
    let table = std::fs::read_to_string(out.join("table.md")).expect("read table.md");
    assert!(table.contains(" warm) |"), "{table}");
}

#[test]
fn the_metrics_do_not_depend_on_the_pngs_exposure_or_tone_curve() {
    // rmse, psnr and flip compare the linear images at a fixed exposure with no curve
    // (README "dray sweep"): the default (automatic exposure, AgX), the old fixed
    // encoding and another curve give other PNGs but the same numbers.
    let dir = common::tmp("sweep-display");
    let mut metrics = Vec::new();
    let mut exact_pngs = Vec::new();
    for (tag, flags) in [
        ("default", &[][..]),
        ("fixed", &["--exposure", "0", "--tonemap", "clamp"][..]),
        ("aces", &["--tonemap", "aces"][..]),
    ] {
        let out = dir.join(tag);
        let o = sweep(
            &[&BASE[..], flags, &["--workers", "0", "--vary", "spp=1"]].concat(),
            &out,
            &[],
        );
        assert!(o.status.success(), "{tag}: {}", stderr(&o));
        let (_, rows) = read_csv(&out.join("results.csv"));
        metrics.push(["rmse", "rmse_linear", "psnr", "flip"].map(|c| rows[1][c].clone()));
        exact_pngs.push(common::rgb(&out.join("exact.png")));
    }
    assert!(
        metrics[1][0] != "0",
        "spp 1 is not the exact image: {metrics:?}"
    );
    assert_eq!(metrics[0], metrics[1]);
    assert_eq!(metrics[0], metrics[2]);
    assert!(exact_pngs[0] != exact_pngs[1] && exact_pngs[1] != exact_pngs[2]);
}

#[test]
fn sweeps_hit_map_thresholds() {
    let dir = common::tmp("sweep-phm");
    let out = dir.join("out");
    // miss=0 and hit=1 never decide: the exact image, every shadow ray a probe.
    let o = sweep(
        &[
            &BASE[..],
            &[
                "--workers",
                "2",
                "--phm",
                "hit=1",
                "--vary",
                "phm.miss=0",
                "--vary",
                "max-depth=5",
                "--repeat",
                "2",
            ],
        ]
        .concat(),
        &out,
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let rows = check_outputs(&out, &["phm.miss", "max-depth"], 1);
    // Two rounds: each median lies within its spread; maps that never decide give the
    // exact image in every round, and so does the exact render.
    for r in &rows {
        for m in ["render_s", "bytes_total"] {
            let (lo, mid, hi) = (
                num(r, &format!("{m}_min")),
                num(r, m),
                num(r, &format!("{m}_max")),
            );
            assert!(lo <= mid && mid <= hi, "{m}: {lo} {mid} {hi} in {r:?}");
        }
        assert_eq!(num(r, "rmse_max"), 0.0, "{r:?}");
        assert_eq!(num(r, "flip_max"), 0.0, "{r:?}");
    }
    assert_eq!(rows[0]["phm_lookups"], "", "the exact render has no maps");
    let r = &rows[1];
    assert_eq!(r["setting"], "phm.miss=0 max-depth=5");
    assert_eq!(rows[0]["max-depth"], "5");
    assert!(num(r, "phm_lookups") > 0.0, "{r:?}");
    // The maps' memory: 8 bytes a cell, every wall's map having cells.
    let map_bytes: u64 = r["phm_map_bytes"].parse().expect("a byte count");
    assert!(map_bytes > 0 && map_bytes.is_multiple_of(8), "{r:?}");
    assert_eq!(num(r, "phm_rays_skipped"), 0.0, "{r:?}");
    assert_eq!(num(r, "phm_cells_decided_hit"), 0.0, "{r:?}");
    assert_eq!(num(r, "rmse"), 0.0, "{r:?}");
    assert_eq!(r["tickets_opened"], "", "no ray caches: {r:?}");
    // The base --phm and the varied knob, merged.
    assert!(r["args"].contains("--phm hit=1,miss=0"), "{r:?}");
}

#[test]
fn bad_keys_and_values_fail_in_one_line_before_rendering() {
    let dir = common::tmp("sweep-errors");
    for (vary, want) in [
        ("bogus=1", "--vary bogus: unknown key"),
        ("spp=", "--vary spp: no values"),
        ("spp=1,0", "--vary spp=0: --spp 0 is out of range"),
        (
            "ray-cache.radius=-1",
            "--vary ray-cache.radius=-1: ray_cache.radius must be",
        ),
        (
            "ray-cache.bogus=1",
            "--vary ray-cache.bogus: unknown ray-cache knob",
        ),
        (
            "phm.miss=0.7",
            "--vary phm.miss=0.7: phm.miss must be in [0, 0.5]",
        ),
        ("max-depth=two", "--vary max-depth=two: invalid value 'two'"),
    ] {
        let out = dir.join("out");
        let o = sweep(&[&BASE[..], &["--vary", vary]].concat(), &out, &[]);
        let err = stderr(&o);
        assert!(!o.status.success(), "{vary}: {err}");
        assert_eq!(o.status.code(), Some(1), "{vary}: {err}");
        assert_eq!(err.lines().count(), 1, "{vary}: one line: {err}");
        assert!(
            err.starts_with(&format!("dray: error: {want}")),
            "{vary}: {err}"
        );
        assert!(
            !out.exists(),
            "{vary}: nothing is written before the plan holds"
        );
    }
    // A flag the sweep sets itself.
    let o = sweep(
        &["cornell", "--output", "x.png", "--vary", "spp=1"],
        &dir.join("o2"),
        &[],
    );
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("--output: dray sweep writes"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn a_failed_render_keeps_the_results_before_it() {
    let dir = common::tmp("sweep-partial");
    let out = dir.join("out");
    // A camera the scene lacks fails only when that setting renders.
    let o = sweep(
        &[&BASE[..], &["--workers", "2", "--vary", "camera=0,nosuch"]].concat(),
        &out,
        &[],
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let last = err.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("dray: error: setting camera=nosuch: camera \"nosuch\" not found"),
        "{err}"
    );
    assert!(
        last.contains("the results of the 2 renders before it are in"),
        "{err}"
    );
    let rows = check_outputs(&out, &["camera"], 1);
    assert_eq!(rows[1]["setting"], "camera=0");
}

#[test]
fn sweeps_on_a_cluster_and_without_a_font() {
    let dir = common::tmp("sweep-cluster");
    let cluster = WorkerCluster::start(2, 0, &dir, &[]);
    let out = dir.join("out");
    // No font: the plot is drawn without text, and the sweep says so, not fails.
    let o = sweep(
        &[
            &BASE[..],
            &[
                "--coordinator",
                &cluster.addr,
                "--vary",
                "ray-cache.radius=0",
                "--vary",
                "spp=1,2",
            ],
        ]
        .concat(),
        &out,
        &[("DRAY_FONT", "/nonexistent/font.ttf")],
    );
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("no TrueType font found"), "{err}");
    let rows = check_outputs(&out, &["ray-cache.radius", "spp"], 2);
    assert!(num(&rows[1], "tickets_opened") > 0.0, "{:?}", rows[1]);
    assert_eq!(num(&rows[2], "rmse"), 0.0, "{:?}", rows[2]);
    assert!(num(&rows[1], "rmse") > 0.0, "{:?}", rows[1]);
    // Flags only an in-process render has are refused with a coordinator.
    let o = sweep(
        &[
            &BASE[..],
            &["--coordinator", &cluster.addr, "--vary", "workers=1,2"],
        ]
        .concat(),
        &dir.join("o2"),
        &[],
    );
    assert!(!o.status.success());
    assert!(
        stderr(&o).starts_with("dray: error: --vary workers: only for renders in this process"),
        "{}",
        stderr(&o)
    );
}
