//! `dray bench-rays`: closest-hit throughput on a fixed, reproducible workload, printed as
//! one JSON line so another ray tracer can be measured on exactly the same rays
//! (`--dump-rays` and `--dump-mesh` write them as little-endian f32 arrays).

use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use dray_core::bvh::{Accel, AccelOptions, Hit, QueryRay, Simd, TraversalCounts};
use dray_core::camera::Camera;
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::Serialize;

#[derive(Clone, Copy, Debug, ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RayKindArg {
    /// Pinhole camera rays through pixel centres, framing the mesh.
    Primary,
    /// Origins uniform in the bounds, directions uniform on the sphere.
    Incoherent,
}

/// The node test's instruction set (`--simd`).
#[derive(Clone, Copy, Debug, ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SimdArg {
    /// The best this CPU runs (AVX-512 if present, else AVX2, else SSE2).
    Auto,
    Avx512,
    Avx2,
    Sse2,
    /// Plain Rust, one child at a time.
    Portable,
}

/// Whether the tree is built with pre-split triangles (`--presplit`).
#[derive(Clone, Copy, Debug, ValueEnum, Serialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PresplitArg {
    /// The renderer's default ([`AccelOptions::default`]).
    Default,
    /// No pre-splitting: one reference per triangle.
    Off,
    /// Pre-splitting, with Embree's budget ([`AccelOptions::PRESPLIT`]) unless
    /// `--presplit-budget` says otherwise.
    On,
}

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// A mesh file or procedural scene.
    pub mesh: String,
    #[arg(long, value_enum, default_value = "primary")]
    pub kind: RayKindArg,
    /// Number of incoherent rays.
    #[arg(long, default_value_t = 1_000_000)]
    pub rays: usize,
    /// Image side for primary rays (res x res rays).
    #[arg(long, default_value_t = 1024)]
    pub res: u32,
    /// Threads (0 = all cores).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Timed passes over the rays; the median is reported.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Write the rays as f32 [ox, oy, oz, dx, dy, dz] records.
    #[arg(long)]
    pub dump_rays: Option<PathBuf>,
    /// Write the triangles as f32 [x0, y0, z0, x1, …, z2] records.
    #[arg(long)]
    pub dump_mesh: Option<PathBuf>,
    /// Node test instruction set (all give the same hits).
    #[arg(long, value_enum, default_value = "auto")]
    pub simd: SimdArg,
    /// Also count the nodes and triangles each ray tests (one extra, untimed pass).
    #[arg(long)]
    pub count: bool,
    /// Trace each chunk of rays with `Accel::closest_batch` (several rays in flight,
    /// their memory loads overlapped) instead of one ray at a time; same answers.
    #[arg(long)]
    pub batch: bool,
    /// Build the tree with or without pre-split triangles (same hits either way).
    #[arg(long, value_enum, default_value = "default")]
    pub presplit: PresplitArg,
    /// With `--presplit on`: the budget, extra references per triangle (default
    /// Embree's 0.2).
    #[arg(long)]
    pub presplit_budget: Option<f32>,
}

#[derive(Serialize)]
struct Report<'a> {
    mesh: &'a str,
    triangles: usize,
    build_s: f64,
    /// Extra references pre-splitting added, per triangle.
    presplit_refs_per_triangle: f64,
    /// Bytes of the tree (nodes and leaves) per triangle.
    bvh_bytes_per_triangle: f64,
    kind: RayKindArg,
    rays: usize,
    threads: usize,
    repeat: usize,
    median_s: f64,
    mrays_per_s: f64,
    hits: u64,
    /// Sum of hit distances, to compare answers between ray tracers.
    t_sum: f64,
    /// The node test's instruction set.
    simd: String,
    /// Whether the rays were traced with `closest_batch`.
    batch: bool,
    /// With `--count`: nodes and triangles tested per ray.
    #[serde(skip_serializing_if = "Option::is_none")]
    nodes_per_ray: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    triangles_per_ray: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    leaves_per_ray: Option<f64>,
}

fn make_rays(a: &BenchArgs, lo: Vec3, hi: Vec3) -> Vec<(Vec3, Vec3)> {
    match a.kind {
        RayKindArg::Primary => {
            let cam = Camera::framing(lo, hi, 1.0);
            let r = a.res;
            (0..r * r)
                .map(|i| {
                    let film = Vec2::new(
                        ((i % r) as f32 + 0.5) / r as f32,
                        ((i / r) as f32 + 0.5) / r as f32,
                    );
                    let c = cam.generate(film, 1.0);
                    (c.origin, c.dir)
                })
                .collect()
        }
        RayKindArg::Incoherent => (0..a.rays as u32)
            .map(|i| {
                let k = PathKey {
                    seed: a.seed,
                    pixel: i,
                    sample: 0,
                };
                let u = k.uniform2(0, Purpose::Film, 0);
                let v = k.uniform2(0, Purpose::Film, 1);
                let w = k.uniform(0, Purpose::Film, 2);
                let o = lo + (hi - lo) * Vec3::new(u.x, u.y, w);
                (o, uniform_sphere(v))
            })
            .collect(),
    }
}

fn write_f32s(path: &PathBuf, values: impl Iterator<Item = f32>) -> Result<()> {
    let f =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = std::io::BufWriter::new(f);
    for v in values {
        w.write_all(&v.to_le_bytes())?;
    }
    w.flush()
        .with_context(|| format!("cannot write {}", path.display()))
}

pub fn run(a: BenchArgs) -> Result<()> {
    if a.repeat == 0 || a.rays == 0 || a.res == 0 {
        bail!("--repeat, --rays and --res must be positive");
    }
    if a.presplit_budget.is_some() && a.presplit != PresplitArg::On {
        bail!("--presplit-budget needs --presplit on");
    }
    if a.presplit_budget
        .is_some_and(|b| !(b.is_finite() && b >= 0.0))
    {
        bail!("--presplit-budget must be a finite number at least 0");
    }
    if a.rays > u32::MAX as usize {
        bail!("--rays must be below 2^32");
    }
    let scene =
        dray_scene::load(&a.mesh).with_context(|| format!("cannot load mesh {:?}", a.mesh))?;
    let t0 = Instant::now();
    let options = match a.presplit {
        PresplitArg::Default => AccelOptions::default(),
        PresplitArg::Off => AccelOptions::UNSPLIT,
        PresplitArg::On => AccelOptions {
            presplit: a.presplit_budget.unwrap_or(AccelOptions::PRESPLIT),
        },
    };
    let mut accel = Accel::build_with(&scene.mesh, None, options);
    let build_s = t0.elapsed().as_secs_f64();
    let triangles = accel.triangle_count().max(1) as f64;
    let per_triangle = |x: usize| x as f64 / triangles;
    select_simd(&mut accel, a.simd)?;
    let (lo, hi) = scene.bounds();
    let rays = make_rays(&a, lo, hi);
    dump(&a, &scene.mesh, &rays)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(a.threads)
        .build()
        .context("cannot start the thread pool")?;
    let threads = pool.current_num_threads();
    let Timed {
        mut times,
        hits,
        t_sum,
    } = time_rays(&a, &accel, &pool, &rays);
    let counts = a.count.then(|| {
        let mut c = TraversalCounts::default();
        for r in &rays {
            accel.closest_counted(&query(r), |_, _| true, &mut c);
        }
        c
    });
    times.sort_by(f64::total_cmp);
    let median_s = times[times.len() / 2];
    let report = Report {
        mesh: &a.mesh,
        triangles: scene.mesh.triangle_count(),
        build_s,
        presplit_refs_per_triangle: per_triangle(accel.reference_count() - accel.triangle_count()),
        bvh_bytes_per_triangle: per_triangle(accel.bytes()),
        kind: a.kind,
        rays: rays.len(),
        threads,
        repeat: a.repeat,
        median_s,
        mrays_per_s: rays.len() as f64 / median_s / 1e6,
        hits,
        t_sum,
        simd: format!("{:?}", accel.simd()).to_lowercase(),
        batch: a.batch,
        nodes_per_ray: counts.map(|c| c.nodes as f64 / rays.len() as f64),
        triangles_per_ray: counts.map(|c| c.triangles as f64 / rays.len() as f64),
        leaves_per_ray: counts.map(|c| c.leaves as f64 / rays.len() as f64),
    };
    println!(
        "{}",
        serde_json::to_string(&report).context("cannot encode the report")?
    );
    Ok(())
}

/// Pins the node test to `--simd` unless it is `auto`.
fn select_simd(accel: &mut Accel, simd: SimdArg) -> Result<()> {
    let want = match simd {
        SimdArg::Auto => None,
        SimdArg::Avx512 => Some(Simd::Avx512),
        SimdArg::Avx2 => Some(Simd::Avx2),
        SimdArg::Sse2 => Some(Simd::Sse2),
        SimdArg::Portable => Some(Simd::Portable),
    };
    if let Some(s) = want
        && !accel.set_simd(s)
    {
        bail!("this CPU cannot run the {s:?} node test");
    }
    Ok(())
}

/// Writes the rays and the mesh's triangles as raw little-endian f32s, when asked
/// (`--dump-rays`, `--dump-mesh`), so another tracer (`benches/`, Embree) traces the same.
fn dump(a: &BenchArgs, m: &dray_core::scene::Mesh, rays: &[(Vec3, Vec3)]) -> Result<()> {
    if let Some(p) = &a.dump_rays {
        write_f32s(
            p,
            rays.iter()
                .flat_map(|(o, d)| [o.x, o.y, o.z, d.x, d.y, d.z]),
        )?;
    }
    if let Some(p) = &a.dump_mesh {
        write_f32s(
            p,
            (0..m.indices.len())
                .flat_map(|t| m.corners(t).into_iter().flat_map(|v| [v.x, v.y, v.z])),
        )?;
    }
    Ok(())
}

/// `--repeat` timed rounds over the rays: each round's seconds, and the last round's hit
/// count and sum of hit distances (the same every round: a check that rounds agree with
/// another tracer, not a timing).
struct Timed {
    times: Vec<f64>,
    hits: u64,
    t_sum: f64,
}

fn time_rays(
    a: &BenchArgs,
    accel: &Accel,
    pool: &rayon::ThreadPool,
    rays: &[(Vec3, Vec3)],
) -> Timed {
    let mut times = Vec::with_capacity(a.repeat);
    let hits = AtomicU64::new(0);
    let mut t_sum = 0.0;
    for _ in 0..a.repeat {
        hits.store(0, Ordering::Relaxed);
        let start = Instant::now();
        let sum: f64 = pool.install(|| {
            rays.par_chunks(4096)
                .map(|chunk| {
                    let mut s = 0.0f64;
                    let mut h = 0u64;
                    let mut count = |hit: Option<Hit>| {
                        if let Some(hit) = hit {
                            h += 1;
                            s += hit.t as f64;
                        }
                    };
                    if a.batch {
                        let queries: Vec<QueryRay> = chunk.iter().map(query).collect();
                        let mut out = vec![None; queries.len()];
                        accel.closest_batch(&queries, |_, _, _| true, &mut out);
                        out.into_iter().for_each(&mut count);
                    } else {
                        for r in chunk {
                            count(accel.closest(&query(r), |_, _| true));
                        }
                    }
                    hits.fetch_add(h, Ordering::Relaxed);
                    s
                })
                .sum()
        });
        times.push(start.elapsed().as_secs_f64());
        t_sum = sum;
    }
    Timed {
        times,
        hits: hits.load(Ordering::Relaxed),
        t_sum,
    }
}

/// A benchmark ray as a query: from its origin, unbounded.
fn query((o, d): &(Vec3, Vec3)) -> QueryRay {
    QueryRay {
        origin: *o,
        dir: *d,
        tmin: 0.0,
        tmax: f32::INFINITY,
    }
}
