//! `results.csv` and `table.md`: one row per render, the exact one first.
//!
//! Statistics are read from the render's `--stats` JSON (`dray render`'s or `dray
//! submit`'s, which share their keys), so a row shows what those files show, and a
//! statistic a render did not report (no ray caches, no hit maps) is an empty cell
//! rather than a misleading 0.

use std::fmt::Write as _;

use dray_net::traffic::TrafficKind;
use serde_json::Value;

use super::metrics::Errors;
use super::spread::{self, Spread};

/// The ray-cache statistics, as `--stats` names them under `ray_cache` (and the CSV).
pub const RAY_CACHE_COLUMNS: [&str; 16] = [
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
];

/// Bytes between processes by kind (`dray_net::traffic::TrafficKind`): CSV column
/// `bytes_<kind>` for key `<kind>` under `--stats`' `traffic` (docs/caches.md
/// "Statistics"). With `--repeat`, from the round whose stats the row keeps (byte counts
/// hardly move between rounds); `bytes_total` is the median.
fn traffic_column(k: TrafficKind) -> String {
    format!("bytes_{}", k.name())
}

/// The hit-map statistics: CSV column and key under `--stats`' `phm`.
pub const PHM_COLUMNS: [(&str, &str); 8] = [
    ("phm_lookups", "lookups"),
    ("phm_rays_skipped", "rays_skipped"),
    ("phm_rays_occluded", "rays_occluded"),
    ("phm_rays_shaded", "rays_shaded"),
    ("phm_probes", "probes"),
    ("phm_cells_decided_hit", "cells_decided_hit"),
    ("phm_cells_decided_miss", "cells_decided_miss"),
    ("phm_map_bytes", "map_bytes"),
];

/// One render's line.
#[derive(Clone, Debug)]
pub struct Row {
    /// "exact" or the setting.
    pub setting: String,
    /// One per varied key.
    pub values: Vec<String>,
    /// From the start of the render to its image (scene loading and, in this process,
    /// starting and stopping the actors included; with a coordinator, from submission to
    /// the image fetched).
    pub wall_s: f64,
    /// The render alone (the coordinator's job time with --coordinator).
    pub render_s: f64,
    /// CPU seconds (user + system) of the processes that ran the render: in this
    /// process (embedded), this process's clock across the render, as `wall_s` spans it;
    /// with a coordinator, the job's `cpu_seconds` (the coordinator's and every worker
    /// process's, once each; stand-alone `dray cache` hosts not included).
    pub cpu_s: f64,
    /// Every byte between processes (`traffic.total` of the stats).
    pub bytes_total: u64,
    /// The render's `--stats` JSON.
    pub stats: Value,
    pub errors: Errors,
    /// Render time, bytes and errors over the rounds: their least and most.
    pub spread: Spread,
    /// The image's file name in the output directory.
    pub image: String,
    /// The render's arguments as a shell would take them (after `dray render`, or `dray
    /// submit --coordinator ADDR`), to reproduce it.
    pub args: String,
}

impl Row {
    /// Rays traced: the sum of rays by kind.
    pub fn rays_traced(&self) -> u64 {
        self.stats["rays"]
            .as_object()
            .map_or(0, |m| m.values().filter_map(Value::as_u64).sum())
    }

    /// Rays sent from one worker to another (each hop counts).
    pub fn rays_sent(&self) -> u64 {
        self.stats["rays_exchanged"].as_u64().unwrap_or(0)
    }

    /// A ray-cache statistic, empty when the render had no ray caches.
    pub fn ray_cache(&self, key: &str) -> String {
        cell(self.stats.get("ray_cache").and_then(|r| r.get(key)))
    }

    /// Bytes between processes of one kind (empty when the stats have none).
    pub fn traffic(&self, key: &str) -> String {
        cell(self.stats.get("traffic").and_then(|r| r.get(key)))
    }

    /// A hit-map statistic, empty when the render had no hit maps.
    pub fn phm(&self, key: &str) -> String {
        cell(self.stats.get("phm").and_then(|r| r.get(key)))
    }
}

fn cell(v: Option<&Value>) -> String {
    match v {
        Some(Value::Number(n)) => n.to_string(),
        Some(Value::String(s)) => s.clone(),
        Some(Value::Bool(b)) => b.to_string(),
        _ => String::new(),
    }
}

/// exact wall / this wall: above 1 is faster than exact.
pub fn speedup(exact_wall: f64, wall: f64) -> f64 {
    if wall > 0.0 { exact_wall / wall } else { 0.0 }
}

/// A number in a cell: `inf` for infinity, otherwise Rust's shortest exact form.
fn num(x: f64) -> String {
    if x.is_infinite() && x > 0.0 {
        "inf".into()
    } else {
        x.to_string()
    }
}

/// A CSV field, quoted when it holds a comma, a quote or a line break (RFC 4180).
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The CSV's columns: `setting`, the varied keys, then the measures.
pub fn header(keys: &[String]) -> Vec<String> {
    let mut h = vec!["setting".to_string()];
    h.extend(keys.iter().cloned());
    h.extend(
        [
            "wall_s",
            "render_s",
            "speedup",
            "rays_traced",
            "rays_sent",
            "bytes_sent",
            "cache_bytes",
            "bytes_total",
            "cpu_s",
            "domain_loads",
            "domains_warm",
        ]
        .map(String::from),
    );
    h.extend(TrafficKind::ALL.map(traffic_column));
    h.extend(RAY_CACHE_COLUMNS.map(String::from));
    h.extend(PHM_COLUMNS.map(|(c, _)| c.to_string()));
    h.extend(["rmse", "rmse_linear", "psnr", "flip"].map(String::from));
    h.extend(spread::COLUMNS.map(String::from));
    h.extend(["pareto", "image", "args"].map(String::from));
    h
}

/// `results.csv`: the header and one line per row; `front[i]` marks rows on the Pareto
/// front.
pub fn csv(keys: &[String], rows: &[Row], front: &[bool]) -> String {
    let mut out = String::new();
    let line = |cells: Vec<String>| {
        cells
            .iter()
            .map(|c| csv_field(c))
            .collect::<Vec<_>>()
            .join(",")
            + "\n"
    };
    out += &line(header(keys));
    let exact_wall = rows.first().map_or(0.0, |r| r.wall_s);
    for (i, r) in rows.iter().enumerate() {
        let mut c = vec![r.setting.clone()];
        c.extend(r.values.iter().cloned());
        c.push(format!("{:.4}", r.wall_s));
        c.push(format!("{:.4}", r.render_s));
        c.push(format!("{:.4}", speedup(exact_wall, r.wall_s)));
        c.push(r.rays_traced().to_string());
        c.push(r.rays_sent().to_string());
        c.push(cell(r.stats.get("ray_bytes_sent")));
        c.push(r.ray_cache("cache_bytes"));
        c.push(r.bytes_total.to_string());
        c.push(format!("{:.4}", r.cpu_s));
        c.push(cell(r.stats.get("domain_loads")));
        c.push(cell(r.stats.get("domains_warm")));
        c.extend(TrafficKind::ALL.iter().map(|k| r.traffic(k.name())));
        c.extend(RAY_CACHE_COLUMNS.iter().map(|k| r.ray_cache(k)));
        c.extend(PHM_COLUMNS.iter().map(|(_, k)| r.phm(k)));
        c.push(num(r.errors.rmse));
        c.push(num(r.errors.rmse_linear));
        c.push(num(r.errors.psnr));
        c.push(num(r.errors.flip));
        c.extend(spread::cells(&r.spread));
        c.push(front.get(i).copied().unwrap_or(false).to_string());
        c.push(r.image.clone());
        c.push(r.args.clone());
        out += &line(c);
    }
    out
}

/// A hit ratio as a percentage, empty without caches.
fn percent(r: &Row, key: &str) -> String {
    r.stats
        .get("ray_cache")
        .and_then(|c| c.get(key))
        .and_then(Value::as_f64)
        .map(|x| format!("{:.1}%", 100.0 * x))
        .unwrap_or_default()
}

/// Domain loads, and the domains found resident instead when there were any: `0 (27
/// warm)`. Empty when no worker took part.
fn loads(r: &Row) -> String {
    let n = |k: &str| r.stats.get(k).and_then(Value::as_u64);
    match (n("domain_loads"), n("domains_warm")) {
        (Some(l), Some(w)) if w > 0 => format!("{l} ({w} warm)"),
        (Some(l), _) => l.to_string(),
        _ => String::new(),
    }
}

/// A Markdown cell: pipes escaped.
fn md(s: &str) -> String {
    s.replace('|', "\\|")
}

/// `table.md`: the key columns as a Markdown table, and how the errors are measured.
pub fn table(title: &str, base: &str, rows: &[Row], front: &[bool], repeat: u32) -> String {
    let mut out = String::new();
    let exact_wall = rows.first().map_or(0.0, |r| r.wall_s);
    let _ = writeln!(out, "# dray sweep: {}\n", md(title));
    let _ = writeln!(
        out,
        "Render flags: `{base}`. Every setting is compared with the exact render (these \
         flags with ray caches and hit maps off).\n"
    );
    if repeat > 1 {
        let _ = writeln!(
            out,
            "Times, CPU seconds and total bytes are medians of {repeat} interleaved rounds; \
             errors and other counts are the first round's (results.csv gives each setting's \
             least and most render time, bytes and error over the rounds: `*_min`, `*_max`).\n"
        );
    }
    let _ = writeln!(
        out,
        "| setting | wall s | speedup | CPU s | bytes | rays sent | domain loads | outer hits | inner hits | rmse | psnr dB | flip | Pareto |"
    );
    let _ = writeln!(
        out,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|"
    );
    for (i, r) in rows.iter().enumerate() {
        let psnr = if r.errors.psnr.is_infinite() {
            "inf".to_string()
        } else {
            format!("{:.2}", r.errors.psnr)
        };
        let _ = writeln!(
            out,
            "| {} | {:.3} | {:.2}x | {:.3} | {} | {} | {} | {} | {} | {:.5} | {psnr} | {:.5} | {} |",
            md(&r.setting),
            r.wall_s,
            speedup(exact_wall, r.wall_s),
            r.cpu_s,
            r.bytes_total,
            r.rays_sent(),
            loads(r),
            percent(r, "outer_hit_ratio"),
            percent(r, "inner_hit_ratio"),
            r.errors.rmse,
            r.errors.flip,
            if front.get(i).copied().unwrap_or(false) {
                "*"
            } else {
                ""
            }
        );
    }
    let _ = writeln!(
        out,
        "\nRMSE is the root mean square difference from the exact image of the 8-bit sRGB \
         PNG values scaled to [0, 1], over all pixels and channels (results.csv also gives \
         `rmse_linear`, on linear radiance); PSNR = 20 log10(1 / RMSE); FLIP is the mean \
         NVIDIA FLIP error (LDR, 67 pixels per degree) against the exact PNG. Wall time runs \
         from the start of a render to its image (scene loading included); speedup = exact \
         wall / setting wall. Domain loads: domains the workers loaded (read and BVH built) \
         for the render, and those they found resident from an earlier render of the same \
         scene (`domain_loads`, `domains_warm`). CPU s: user + system seconds of the processes that ran the \
         render (results.csv `cpu_s`); bytes: every byte between processes \
         (`bytes_total`, docs/caches.md \"Statistics\"). Pareto: no other setting is both faster and closer to exact."
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn row(setting: &str, wall: f64, stats: Value, rmse: f64) -> Row {
        let errors = Errors {
            rmse,
            rmse_linear: rmse,
            psnr: super::super::metrics::psnr(rmse),
            flip: rmse,
        };
        Row {
            setting: setting.into(),
            values: vec!["0.1".into()],
            wall_s: wall,
            render_s: wall / 2.0,
            cpu_s: wall * 1.5,
            bytes_total: 1000,
            stats,
            spread: Spread::first(wall / 2.0, 1000, &errors),
            errors,
            image: format!("{setting}.png"),
            args: "cornell --spp 2".into(),
        }
    }

    #[test]
    fn csv_rows_and_empty_cells() {
        let exact = row(
            "exact",
            2.0,
            json!({"rays": {"camera": 10, "shadow": 5}, "rays_exchanged": 3, "ray_bytes_sent": 192}),
            0.0,
        );
        let cached = row(
            "ray-cache.radius=0.1",
            1.0,
            json!({"rays": {"camera": 4}, "rays_exchanged": 1, "ray_bytes_sent": 64,
                   "domain_loads": 0, "domains_warm": 27,
                   "ray_cache": {"outer_lookups": 8, "outer_hit_ratio": 0.5, "tickets_opened": 4,
                                 "tickets_closed": 4, "cache_bytes": 99},
                   "phm": {"lookups": 7}}),
            0.25,
        );
        let text = csv(
            &["ray-cache.radius".into()],
            &[exact, cached],
            &[true, true],
        );
        let lines: Vec<&str> = text.lines().collect();
        let head: Vec<&str> = lines[0].split(',').collect();
        assert_eq!(head[0], "setting");
        assert_eq!(head[1], "ray-cache.radius");
        let col = |line: &str, name: &str| -> String {
            let i = head.iter().position(|h| *h == name).expect(name);
            line.split(',').nth(i).expect("cell").to_string()
        };
        assert_eq!(col(lines[1], "rays_traced"), "15");
        assert_eq!(col(lines[1], "rays_sent"), "3");
        assert_eq!(col(lines[1], "bytes_sent"), "192");
        assert_eq!(col(lines[1], "tickets_opened"), "");
        assert_eq!(col(lines[1], "phm_lookups"), "");
        assert_eq!(col(lines[1], "rmse"), "0");
        assert_eq!(col(lines[1], "psnr"), "inf");
        assert_eq!(col(lines[2], "speedup"), "2.0000");
        assert_eq!(col(lines[2], "outer_hit_ratio"), "0.5");
        assert_eq!(col(lines[2], "tickets_closed"), "4");
        assert_eq!(col(lines[2], "cache_bytes"), "99");
        assert_eq!(col(lines[2], "bytes_total"), "1000");
        assert_eq!(col(lines[2], "cpu_s"), "1.5000");
        assert_eq!(col(lines[2], "domain_loads"), "0");
        assert_eq!(col(lines[2], "domains_warm"), "27");
        assert_eq!(col(lines[1], "domain_loads"), "");
        assert_eq!(col(lines[2], "phm_lookups"), "7");
        assert_eq!(col(lines[2], "rmse"), "0.25");
        assert_eq!(col(lines[2], "psnr"), "12.041199826559248");
        assert_eq!(lines.len(), 3);
        let t = table(
            "cornell",
            "cornell --spp 2",
            &[row("exact", 1.0, json!({}), 0.0)],
            &[true],
            1,
        );
        assert!(t.contains("| exact | 1.000 | 1.00x |"), "{t}");
        let warm = json!({"domain_loads": 0, "domains_warm": 27});
        let t2 = table("c", "", &[row("s", 1.0, warm, 0.0)], &[true], 1);
        assert!(t2.contains("| 0 (27 warm) |"), "{t2}");
        assert!(t.contains("8-bit sRGB"), "{t}");
        assert!(!t.contains("medians"), "{t}");
        let t = table(
            "cornell",
            "",
            &[row("exact", 1.0, json!({}), 0.0)],
            &[true],
            3,
        );
        assert!(t.contains("medians of 3 interleaved rounds"), "{t}");
    }

    #[test]
    fn csv_quoting() {
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("say \"x\""), "\"say \"\"x\"\"\"");
        assert_eq!(csv_field("plain"), "plain");
    }
}
