//! Closest-hit throughput of the core alone, on triangles and rays dumped by
//! `dray bench-rays --dump-mesh M --dump-rays R` (little-endian f32 records), so a change
//! to the BVH can be timed after rebuilding `dray-core` only, not the whole CLI.
//!
//! Usage: `cargo run --release -p dray-core --example trace_dump -- MESH RAYS [REPEAT] [SIMD]`
//! (SIMD: auto, avx512, avx2, sse2 or portable). Prints the build time, the median pass's
//! Mrays/s on one thread, hits and the sum of hit distances (to compare answers between
//! builds), and the nodes, triangles and leaves tested per ray; then the same for
//! `Accel::closest_batch`, with the number of rays whose answer differs (must be 0).

use std::time::Instant;

use dray_core::bvh::{Accel, QueryRay, Simd, TraversalCounts};
use glam::Vec3;

#[path = "shared/dump.rs"]
mod dump;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: trace_dump MESH_F32 RAYS_F32 [REPEAT] [auto|avx512|avx2|sse2|portable]");
        std::process::exit(2);
    }
    let repeat: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(5);
    let simd = match args.get(4).map(String::as_str) {
        Some("avx512") => Some(Simd::Avx512),
        Some("avx2") => Some(Simd::Avx2),
        Some("sse2") => Some(Simd::Sse2),
        Some("portable") => Some(Simd::Portable),
        _ => None,
    };
    let rays: Vec<QueryRay> = dump::read_f32s(&args[2])
        .chunks_exact(6)
        .map(|c| QueryRay {
            origin: Vec3::new(c[0], c[1], c[2]),
            dir: Vec3::new(c[3], c[4], c[5]),
            tmin: 0.0,
            tmax: f32::INFINITY,
        })
        .collect();
    let mesh = dump::read_mesh(&args[1]);
    let t = mesh.indices.len() as u32;
    let t0 = Instant::now();
    let mut accel = Accel::build(&mesh);
    let build_s = t0.elapsed().as_secs_f64();
    if let Some(s) = simd
        && !accel.set_simd(s)
    {
        eprintln!("this CPU cannot run {s:?}");
        std::process::exit(2);
    }
    let mut times = Vec::new();
    let (mut hits, mut t_sum) = (0u64, 0f64);
    for _ in 0..repeat {
        let start = Instant::now();
        hits = 0;
        t_sum = 0.0;
        for r in &rays {
            if let Some(h) = accel.closest(r, |_, _| true) {
                hits += 1;
                t_sum += f64::from(h.t);
            }
        }
        times.push(start.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    // The same rays through `closest_batch`: the same answers, ray for ray.
    let single: Vec<Option<dray_core::bvh::Hit>> =
        rays.iter().map(|r| accel.closest(r, |_, _| true)).collect();
    let mut batch = vec![None; rays.len()];
    let mut batch_times = Vec::new();
    for _ in 0..repeat {
        let start = Instant::now();
        accel.closest_batch(&rays, |_, _, _| true, &mut batch);
        batch_times.push(start.elapsed().as_secs_f64());
    }
    let differ = single.iter().zip(&batch).filter(|(a, b)| a != b).count();
    batch_times.sort_by(f64::total_cmp);
    let batch_median = batch_times[batch_times.len() / 2];
    let mut counts = TraversalCounts::default();
    for r in &rays {
        accel.closest_counted(r, |_, _| true, &mut counts);
    }
    let n = rays.len() as f64;
    println!(
        "triangles {t} bvh {:.1} B/triangle build {build_s:.3} s simd {:?} rays {} median {median:.4} s \
         {:.3} Mrays/s batch {batch_median:.4} s {:.3} Mrays/s ({differ} answers differ) \
         hits {hits} t_sum {t_sum:.6e} nodes/ray {:.2} tris/ray {:.2} leaves/ray {:.2}",
        accel.bytes() as f64 / f64::from(t.max(1)),
        accel.simd(),
        rays.len(),
        n / median / 1e6,
        n / batch_median / 1e6,
        counts.nodes as f64 / n,
        counts.triangles as f64 / n,
        counts.leaves as f64 / n,
    );
}
