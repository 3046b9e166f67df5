//! Build time of the accelerator alone, on triangles dumped by
//! `dray bench-rays MESH --dump-mesh M` (little-endian f32 records, nine per triangle), so
//! a change to the BVH build can be timed, and checked to give the same tree, after
//! rebuilding `dray-core` only.
//!
//! Usage: `cargo run --release -p dray-core --example build_time -- MESH [REPEAT]`.
//! Prints every build's wall time, their median, and the tree's [`Accel::digest`]
//! (the same digest before and after a change: the same tree, node for node). Run it
//! under `taskset -c N` for one thread (rayon's pool follows the affinity mask), and
//! with REPEAT 1 under `valgrind --tool=callgrind` for instruction counts.

use std::time::Instant;

use dray_core::bvh::Accel;

#[path = "shared/dump.rs"]
mod dump;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: build_time MESH_F32 [REPEAT]");
        std::process::exit(2);
    };
    let repeat: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(5).max(1);
    let mesh = dump::read_mesh(path);
    let t = mesh.indices.len();
    let mut times = Vec::with_capacity(repeat);
    let mut digest = None;
    for _ in 0..repeat {
        let start = Instant::now();
        let accel = Accel::build(&mesh);
        times.push(start.elapsed().as_secs_f64());
        let d = accel.digest();
        assert!(
            digest.is_none_or(|p| p == d),
            "two builds of one mesh differ"
        );
        digest = Some(d);
    }
    let all: Vec<String> = times.iter().map(|s| format!("{s:.4}")).collect();
    times.sort_by(f64::total_cmp);
    println!(
        "triangles {t} builds {repeat} median {:.4} s digest {:016x} all [{}]",
        times[times.len() / 2],
        digest.unwrap_or(0),
        all.join(" "),
    );
}
