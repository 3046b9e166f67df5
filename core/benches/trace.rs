//! Criterion benchmarks of the tracing core: closest-hit and any-hit queries on a random
//! triangle soup and the BVH build, so regressions in the hot path show up as numbers.
//! Run: `cargo bench -p dray-core --bench trace`.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use dray_core::bvh::{Accel, QueryRay};
use dray_core::sampling::{PathKey, Purpose, uniform_sphere};
use dray_core::scene::Mesh;
use glam::Vec3;

fn key(i: u32) -> PathKey {
    PathKey {
        seed: 9,
        pixel: i,
        sample: 0,
    }
}

/// `n` random triangles in the unit cube, each within 0.6/cbrt(n) of its centre.
fn soup(n: u32) -> Mesh {
    let size = 0.6 / (n as f32).cbrt();
    let mut m = Mesh::default();
    let mut pts = Vec::with_capacity(n as usize * 3);
    for i in 0..n {
        let k = key(i);
        let c = Vec3::new(
            k.uniform(0, Purpose::Film, 0),
            k.uniform(0, Purpose::Film, 1),
            k.uniform(0, Purpose::Film, 2),
        );
        for j in 0..3 {
            pts.push(c + uniform_sphere(k.uniform2(1, Purpose::Film, j)) * size);
        }
    }
    m.push_vertices(&pts);
    m.indices = (0..n).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    m.material = vec![0; n as usize];
    m
}

fn rays(n: u32) -> Vec<QueryRay> {
    (0..n)
        .map(|i| {
            let k = key(i + 1_000_000);
            let o = Vec3::new(
                k.uniform(2, Purpose::Film, 0),
                k.uniform(2, Purpose::Film, 1),
                k.uniform(2, Purpose::Film, 2),
            );
            QueryRay {
                origin: o,
                dir: uniform_sphere(k.uniform2(3, Purpose::Film, 0)),
                tmin: 0.0,
                tmax: f32::INFINITY,
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let mesh = soup(200_000);
    let accel = Accel::build(&mesh);
    let rs = rays(100_000);
    let mut g = c.benchmark_group("trace");
    g.sample_size(10);
    g.throughput(Throughput::Elements(rs.len() as u64));
    g.bench_function("closest_incoherent_200k_tris", |b| {
        b.iter(|| {
            let mut hits = 0u32;
            for r in &rs {
                hits += accel.closest(black_box(r), |_, _| true).is_some() as u32;
            }
            hits
        })
    });
    g.bench_function("occluded_incoherent_200k_tris", |b| {
        b.iter(|| {
            let mut hits = 0u32;
            for r in &rs {
                hits += accel.occluded(black_box(r), |_, _| true) as u32;
            }
            hits
        })
    });
    g.finish();
    let mut g = c.benchmark_group("build");
    g.sample_size(10);
    g.throughput(Throughput::Elements(mesh.indices.len() as u64));
    g.bench_function("cwbvh_200k_tris", |b| {
        b.iter(|| Accel::build(black_box(&mesh)).triangle_count())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
