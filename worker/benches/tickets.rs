//! The worker's ticket bookkeeping (docs/history/2026-11-26-lean-tickets.md), without the
//! tracing or the streams around it: a ray's ticket set as it gains tickets at walls and is
//! inherited by its children (`Lineage`), the sparse ticket table of a ray batch (encode:
//! `RayBundle::push`; decode: `with_lineage`), and the per-ticket sums (`TicketLedger`:
//! contributions and credit under each ray's tickets, drained into returns).
//!
//! The mix of tickets per ray follows a coarse pass over a domain grid: camera rays miss
//! one outer wall and then one or two inner walls, so they carry 1-3 tickets, and a
//! batch holds rays of 0 to 3 tickets. Each bench reports per ray.
//!
//! Times are CPU time of the bench thread (`cache-actor/benches/common/thread_cpu.rs`),
//! not wall time.
//!
//! Run: `cargo bench -p dray-worker --bench tickets`.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use dray_cache::ticket_id::ticket_id;
use dray_core::credit::Credit;
use dray_core::integrator::RayKind;
use dray_core::ray::RayRecord;
use dray_core::sampling::{PathKey, Purpose};
use dray_worker::tickets::{Lineage, RayBundle, TicketLedger, with_lineage};
use glam::Vec3;

#[path = "../../cache-actor/benches/common/thread_cpu.rs"]
mod thread_cpu;
use thread_cpu::ThreadCpu;

/// Rays per iteration.
const RAYS: usize = 4096;
/// Tickets a batch's rays share (rays of one tile cross the same walls).
const OPEN: u64 = 1024;

fn ray(i: usize) -> RayRecord {
    RayRecord {
        credit: Credit::from_wire(1 << 20),
        origin: Vec3::new(i as f32 * 1e-3, 0.5, -1.0),
        dir: Vec3::new(0.0, 0.1, 1.0).normalize(),
        tmax: f32::INFINITY,
        weight: Vec3::splat(0.9),
        bsdf_pdf: 0.0,
        pixel: i as u32,
        sample: 0,
        depth: 0,
        kind: RayKind::Camera,
        flags: 0,
    }
}

/// Ticket `j` of ray `i` in stream `seed`: one of 54 walls, from a pool of `OPEN` (the
/// renderer's own counter-based random numbers).
fn ticket(seed: u64, i: usize, j: u32) -> u64 {
    let key = PathKey {
        seed,
        pixel: i as u32,
        sample: j,
    };
    let slot = (key.bits(0, Purpose::Film, 0) % OPEN + 1) as u32;
    ticket_id(0, slot % 54, slot)
}

/// `RAYS` lineages of 0-3 tickets (a quarter each), as `Lineage::with_ticket` builds them.
fn lineages() -> Vec<Lineage> {
    (0..RAYS)
        .map(|i| {
            let mut l = Lineage {
                coarse: i % 2 == 0,
                ..Lineage::default()
            };
            for j in 0..(i % 4) as u32 {
                l = l.with_ticket(ticket(11, i, j));
            }
            l
        })
        .collect()
}

fn lineage(c: &mut Criterion<ThreadCpu>) {
    let mut g = c.benchmark_group("lineage");
    g.throughput(Throughput::Elements(RAYS as u64));
    // A camera ray missing three walls in turn, each time leaving with one more ticket,
    // and its two children at each step inheriting the set.
    g.bench_function("three_walls_two_children", |b| {
        let tickets: Vec<[u64; 3]> = (0..RAYS)
            .map(|i| [0, 1, 2].map(|j| ticket(5, i, j)))
            .collect();
        b.iter(|| {
            let mut carried = 0usize;
            for ts in &tickets {
                let mut l = Lineage::default();
                for &t in ts {
                    l = l.with_ticket(t);
                    let a = l.inherited();
                    let b = l.inherited();
                    carried += a.ticket_count() + b.ticket_count();
                    black_box((a, b));
                }
            }
            carried
        })
    });
    g.finish();
}

fn bundle(c: &mut Criterion<ThreadCpu>) {
    let lins = lineages();
    let rays: Vec<RayRecord> = (0..RAYS).map(ray).collect();
    let mut g = c.benchmark_group("bundle");
    g.throughput(Throughput::Elements(RAYS as u64));
    g.bench_function("encode", |b| {
        b.iter(|| {
            let mut bundle = RayBundle::default();
            for (r, l) in rays.iter().zip(&lins) {
                bundle.push(*r, l);
            }
            bundle
        })
    });
    let mut bundle = RayBundle::default();
    for (r, l) in rays.iter().zip(&lins) {
        bundle.push(*r, l);
    }
    g.bench_function("decode", |b| {
        b.iter(|| {
            let mut carried = 0usize;
            for (_, l) in with_lineage(&bundle.rays, &bundle.tickets) {
                carried += l.ticket_count();
                black_box(l);
            }
            carried
        })
    });
    g.finish();
}

fn ledger(c: &mut Criterion<ThreadCpu>) {
    let lins = lineages();
    let mut g = c.benchmark_group("ledger");
    g.throughput(Throughput::Elements(RAYS as u64));
    // Each ray makes one contribution and hands its credit back, both owed to every ticket
    // it carries; the ledger is then drained into returns.
    g.bench_function("contribute_credit_drain", |b| {
        let mut ledger = TicketLedger::default();
        b.iter(|| {
            for (i, l) in lins.iter().enumerate() {
                if let Some(t) = &l.tickets {
                    ledger.contribute(t, [i as i64, 2 * i as i64, 3], false);
                    ledger.credit(t, Credit::from_wire(1 << 20), false);
                }
            }
            ledger.drain()
        })
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = thread_cpu::criterion(3);
    targets = lineage, bundle, ledger
}
criterion_main!(benches);
