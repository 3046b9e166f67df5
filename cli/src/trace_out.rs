//! `dray render --trace-out FILE`: the job's traffic as one trace file, for replay in a
//! simulator (docs/caches.md "The trace's schema", `benches/sim/replay.py`).
//!
//! The in-process workers write their records (`dray_worker::traffic_trace`) to files of
//! their own in a private directory; once the actors have stopped (so every worker's
//! file is whole), this joins them into FILE after a `job` line: the job's wall time,
//! its configuration and the totals the coordinator counted, which a reader checks the
//! records against.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use dray_proto::v1::JobStats;
use serde_json::json;

/// The trace schema's version (the workers' records carry the same).
pub const VERSION: u32 = dray_worker::traffic_trace::TRACE_VERSION;

/// A private directory the in-process workers write their traces to, removed when
/// dropped.
pub struct TraceDir {
    dir: tempfile::TempDir,
}

impl TraceDir {
    pub fn new() -> Result<TraceDir> {
        let dir = dray_scene::private_fs::private_temp_dir("dray-trace-", "")
            .context("cannot create a directory for the workers' traces")?;
        Ok(TraceDir { dir })
    }

    pub fn path(&self) -> PathBuf {
        self.dir.path().to_path_buf()
    }
}

/// What the `job` line says about the run besides the coordinator's statistics.
pub struct JobFacts {
    pub wall_seconds: f64,
    pub workers: usize,
    pub threads: usize,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub integrator: String,
    pub load_delay_ms: u64,
}

/// Write `out`: the `job` line, then every worker's records from `dir` (files in name
/// order, lines as written).
pub fn assemble(out: &Path, dir: &TraceDir, facts: &JobFacts, stats: &JobStats) -> Result<()> {
    let traffic = stats.traffic.unwrap_or_default();
    let rays = stats.rays.unwrap_or_default();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let header = json!({
        "v": VERSION,
        "rec": "job",
        "wall_ns": (facts.wall_seconds * 1e9) as u64,
        "workers": facts.workers,
        "threads": facts.threads,
        "cores": cores,
        "width": facts.width,
        "height": facts.height,
        "spp": facts.spp,
        "integrator": facts.integrator,
        "domains": stats.domains,
        "schedule": stats.schedule,
        "load_delay_ms": facts.load_delay_ms,
        "emulate_link": serde_json::Value::Null,
        "stats": {
            "rays_traced": crate::summary::ray_counts(&rays).total(),
            "rays_exchanged": stats.rays_exchanged,
            "rays_forwarded": stats.rays_forwarded,
            "ray_bytes_sent": stats.ray_bytes_sent,
            "traffic_rays": traffic.rays,
            "traffic_total": traffic.total,
            "domain_loads": stats.domain_loads,
            "domain_load_seconds": stats.domain_load_seconds,
            "cpu_seconds": stats.cpu_seconds,
        },
    });
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir.dir.path())
        .context("cannot list the workers' traces")?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jsonl"))
        .collect();
    files.sort();
    let f = std::fs::File::create(out)
        .with_context(|| format!("cannot write the trace {}", out.display()))?;
    let mut w = std::io::BufWriter::new(f);
    let write_err = || format!("cannot write the trace {}", out.display());
    writeln!(w, "{header}").with_context(write_err)?;
    for p in files {
        let mut r = std::fs::File::open(&p)
            .with_context(|| format!("cannot read the worker trace {}", p.display()))?;
        std::io::copy(&mut r, &mut w).with_context(write_err)?;
    }
    w.flush().with_context(write_err)?;
    Ok(())
}
