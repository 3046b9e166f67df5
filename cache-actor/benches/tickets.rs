//! One wall actor's parts, driven directly (docs/history/2026-11-26-lean-tickets.md): the
//! store's inserts and its `first`/`nearest`/`average` queries, and the ticket cycle (open,
//! returns, close, store) as the actor runs it (`actor.rs`: `cache_lookup` and `apply`),
//! without the mailbox or gRPC around them.
//!
//! Sizes follow the Table 5.1 set-up (docs/history/2026-11-24-ray-caches-table-5-1.md): a
//! wall 0.137 wide (one voxel of the bunny grid), camera rays from a pinhole 1 unit in front
//! of it, radius 0.00228 (the thesis's 0.005, scaled by 0.456) and 5.73 degrees. The store
//! holds 32,768 entries (a 256² coarse pass puts 7-8 k on each of the 9 outer walls facing
//! the camera; `fill=true` adds tens of thousands more), so a query finds a few tens of
//! candidates in range.
//!
//! Times are CPU time of the bench thread (`common/thread_cpu.rs`), not wall time.
//!
//! Run: `cargo bench -p dray-cache --bench tickets`.

use std::hint::black_box;

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use dray_cache::Retrieve;
use dray_cache::store::{DEFAULT_MAX_ENTRIES, Entry, EntryKey, Query, WallStore};
use dray_cache::ticket_id::ticket_slot;
use dray_cache::tickets::{Applied, Return, TicketBook, TicketRay};
use dray_core::credit::Credit;
use dray_core::integrator::RayKind;
use dray_core::ray::RayRecord;
use dray_core::sampling::{PathKey, Purpose};
use dray_core::wall::WallFrame;
use glam::Vec3;

#[path = "common/thread_cpu.rs"]
mod thread_cpu;
use thread_cpu::ThreadCpu;

/// The wall's edge, scene units.
const WALL: f32 = 0.137;
const RADIUS: f32 = 0.00228;
const ANGLE_DEG: f64 = 5.73;
/// Entries in the store the queries run against.
const ENTRIES: usize = 32_768;
/// Rays per iteration of the query and lookup benches.
const QUERIES: usize = 4096;
/// Rays of one coarse pass over the wall (the cycle bench).
const COARSE: usize = 16_384;
/// A ray's credit (any positive value; the returns split it).
const CREDIT: Credit = Credit::from_wire(1 << 20);

/// The wall: the -z face of the voxel `[0, WALL]³`, seen by rays going +z.
fn frame() -> WallFrame {
    WallFrame::new(Vec3::ZERO, Vec3::splat(WALL), 4)
}

/// `n` camera rays from a pinhole 1 unit in front of the wall through points spread
/// uniformly over it, pixels numbered from `first_pixel`.
fn rays(seed: u64, n: usize, first_pixel: u32) -> Vec<RayRecord> {
    let eye = Vec3::new(WALL * 0.5, WALL * 0.5, -1.0);
    (0..n)
        .map(|i| {
            // The renderer's own counter-based random numbers, one stream per `seed`.
            let key = PathKey {
                seed,
                pixel: i as u32,
                sample: 0,
            };
            let at = key.uniform2(0, Purpose::Film, 0) * WALL;
            let target = Vec3::new(at.x, at.y, 0.0);
            RayRecord {
                credit: CREDIT,
                origin: eye,
                dir: (target - eye).normalize(),
                tmax: f32::INFINITY,
                weight: Vec3::splat(0.9),
                bsdf_pdf: 0.0,
                pixel: first_pixel + i as u32,
                sample: 0,
                depth: 0,
                kind: RayKind::Camera,
                flags: 0,
            }
        })
        .collect()
}

fn entry(frame: &WallFrame, ray: &RayRecord, radiance: f32) -> Option<Entry> {
    Some(Entry {
        key: EntryKey::of(ray),
        point: frame.crossing(ray.origin, ray.dir)?,
        dir: ray.dir.try_normalize()?,
        radiance: [radiance, radiance * 0.5, radiance * 0.25],
    })
}

fn entries(n: usize) -> Vec<Entry> {
    let f = frame();
    rays(1, n, 0)
        .iter()
        .enumerate()
        .filter_map(|(i, r)| entry(&f, r, (i % 97) as f32 * 0.01))
        .collect()
}

/// A store as the actor makes it for a job of radius `RADIUS`.
fn store_for_job() -> WallStore {
    WallStore::for_radius(DEFAULT_MAX_ENTRIES, RADIUS)
}

fn filled(es: &[Entry]) -> WallStore {
    let mut s = store_for_job();
    for e in es {
        s.insert(*e).expect("room");
    }
    s
}

fn query(frame: &WallFrame, ray: &RayRecord, retrieve: Retrieve) -> Option<Query> {
    Some(Query {
        point: frame.crossing(ray.origin, ray.dir)?,
        dir: ray.dir.try_normalize()?,
        radius: RADIUS,
        cos_min: ANGLE_DEG.to_radians().cos(),
        retrieve,
    })
}

fn store(c: &mut Criterion<ThreadCpu>) {
    let es = entries(ENTRIES);
    let f = frame();
    let mut g = c.benchmark_group("store");
    g.throughput(Throughput::Elements(ENTRIES as u64));
    g.bench_function("insert_32k", |b| {
        b.iter_batched(
            || es.clone(),
            |es| black_box(filled(&es)),
            BatchSize::LargeInput,
        )
    });
    let s = filled(&es);
    let qs = rays(2, QUERIES, 1 << 24);
    g.throughput(Throughput::Elements(QUERIES as u64));
    for (name, retrieve) in [
        ("lookup_first", Retrieve::First),
        ("lookup_nearest", Retrieve::Nearest),
        ("lookup_average", Retrieve::Average),
    ] {
        let queries: Vec<Query> = qs.iter().filter_map(|r| query(&f, r, retrieve)).collect();
        eprintln!(
            "{name}: {} of {} queries hit",
            hits(&s, &queries),
            queries.len()
        );
        g.bench_function(name, |b| b.iter(|| hits(&s, &queries)));
    }
    // The same `nearest` queries in the order a camera's rays reach the wall: scanlines
    // (rows 4 radii high), left to right. Neighbouring queries read the same cells.
    let mut scanline: Vec<Query> = qs
        .iter()
        .filter_map(|r| query(&f, r, Retrieve::Nearest))
        .collect();
    let row = |q: &Query| (q.point[1] / (4.0 * RADIUS)) as u32;
    scanline.sort_by(|a, b| row(a).cmp(&row(b)).then(a.point[0].total_cmp(&b.point[0])));
    g.bench_function("lookup_nearest_scanline", |b| {
        b.iter(|| hits(&s, &scanline))
    });
    g.finish();
}

/// Queries of `queries` that hit.
fn hits(s: &WallStore, queries: &[Query]) -> usize {
    queries
        .iter()
        .filter(|q| black_box(s.lookup(q)).is_some())
        .count()
}

/// The actor's answer to one ray (`actor.rs` `cache_lookup`): crossing point and
/// direction, a query when `answer`, else (or on a miss) a ticket.
fn ask(
    frame: &WallFrame,
    store: &WallStore,
    book: &mut TicketBook,
    ray: &RayRecord,
    answer: bool,
) -> Option<u64> {
    let point = frame.crossing(ray.origin, ray.dir)?;
    let dir = ray.dir.try_normalize()?;
    if answer {
        let q = Query {
            point,
            dir,
            radius: RADIUS,
            cos_min: ANGLE_DEG.to_radians().cos(),
            retrieve: Retrieve::Nearest,
        };
        if store.lookup(&q).is_some() {
            return None;
        }
    }
    book.open(TicketRay {
        key: EntryKey::of(ray),
        point,
        dir,
        weight: ray.weight,
        credit: ray.credit,
        coarse: true,
        cache: true,
        cell: None,
    })
    .ok()
}

/// Returns for `tickets`: three per ticket (the ray's descendants handing credit back in
/// parts), as workers send them: a worker drains its ledger sorted by ticket, and the
/// rays of one tile took consecutive tickets, so returns come in runs of a tile's
/// tickets (256) in order, the runs of many tiles and the three parts interleaved.
fn returns(tickets: &[u64]) -> Vec<(u32, Return)> {
    const TILE: usize = 256;
    let part = |i: usize, k: u64| Return {
        rgb: [(i as i64 + 1) << 20, (i as i64) << 19, 3 << 18],
        credit: Credit::from_wire(if k == 2 {
            CREDIT.to_wire() - 2 * (CREDIT.to_wire() / 3)
        } else {
            CREDIT.to_wire() / 3
        }),
        tainted: false,
    };
    let tiles = tickets.len().div_ceil(TILE);
    let mut out = Vec::with_capacity(tickets.len() * 3);
    for k in 0..3u64 {
        // Each round visits the tiles in a different (fixed) order.
        let stride = [1usize, 7, 13][k as usize];
        for j in 0..tiles {
            let tile = (j * stride + k as usize * 5) % tiles;
            let first = tile * TILE;
            for (i, &t) in tickets.iter().enumerate().skip(first).take(TILE) {
                out.push((ticket_slot(t), part(i, k)));
            }
        }
    }
    out
}

/// What the actor does with a return (`actor.rs` `apply`): apply it, and store the
/// radiance of a ticket that closes.
fn apply(book: &mut TicketBook, store: &mut WallStore, slot: u32, ret: Return) -> bool {
    match book.apply(slot, ret, true) {
        Applied::Closed { entry: Some(e), .. } => store.insert(e).is_ok(),
        _ => false,
    }
}

fn wall(c: &mut Criterion<ThreadCpu>) {
    let f = frame();
    let mut g = c.benchmark_group("wall");

    // The coarse pass from an empty wall: every ray is ticketed (no query), its returns
    // come back in three parts, and the closing one stores the radiance.
    let coarse = rays(3, COARSE, 0);
    let empty = store_for_job();
    {
        // The returns do not depend on the book's state: slots are issued 1, 2, 3, ...
        let mut book = TicketBook::new(5, usize::MAX);
        let tickets: Vec<u64> = coarse
            .iter()
            .filter_map(|r| ask(&f, &empty, &mut book, r, false))
            .collect();
        let rets = returns(&tickets);
        g.throughput(Throughput::Elements(tickets.len() as u64));
        g.bench_function("coarse_cycle_16k", |b| {
            b.iter(|| {
                let mut book = TicketBook::new(5, usize::MAX);
                let mut store = store_for_job();
                for r in &coarse {
                    black_box(ask(&f, &empty, &mut book, r, false));
                }
                let mut stored = 0usize;
                for &(slot, ret) in &rets {
                    stored += usize::from(apply(&mut book, &mut store, slot, ret));
                }
                assert_eq!(stored, tickets.len());
                store
            })
        });
    }

    // The main pass against a sparsely filled wall (fill=true, early in the render: 2,048
    // entries, under two in a query's reach): each ray is looked up, and a miss (about
    // one in six) opens a ticket.
    let s = filled(&entries(ENTRIES / 16));
    let main = rays(4, QUERIES, 1 << 24);
    let mut book = TicketBook::new(5, usize::MAX);
    let opened = main
        .iter()
        .filter(|r| ask(&f, &s, &mut book, r, true).is_some())
        .count();
    eprintln!("lookup_or_ticket: {opened} of {} rays ticketed", main.len());
    g.throughput(Throughput::Elements(main.len() as u64));
    g.bench_function("lookup_or_ticket", |b| {
        b.iter_batched_ref(
            || TicketBook::new(5, usize::MAX),
            |book| {
                main.iter()
                    .filter(|r| ask(&f, &s, book, r, true).is_some())
                    .count()
            },
            BatchSize::SmallInput,
        )
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = thread_cpu::criterion(4);
    targets = store, wall
}
criterion_main!(benches);
