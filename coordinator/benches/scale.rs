//! What limits dray at 1,000 workers (docs/scaling.md): a simulated
//! cluster with no real workers, no network and no tracing. Only the coordinator's own
//! code runs, fed synthetic reports shaped like the ones workers send, so what is
//! measured is the coordinator's CPU cost per report, per round and per table; the
//! written account is docs/scaling.md.
//!
//! Run: `cargo bench -p dray-coordinator --bench scale` (add `-- --quick` for fewer
//! samples). It prints Markdown tables; every time is the median over samples, per call.
//! Last, one JSON line per (N, D) point: `workers`, `domains`, `round_ms` (a changed
//! round end to end, fan-out included), `report_us` (one contribution report as the
//! job's actor applies it), `reports_per_s` (its inverse: one job's reports per second
//! on one core), `report_no_pixels_us` and `reports_no_pixels_per_s` (the same report
//! without its pixel sums: the actor's own bookkeeping, credit and counters) and
//! `queue_report_us`.
//!
//! For N workers and D domains (D = 4N for N = 10, 100, 1,000 and 10,000, D = 32N for
//! N = 1,000 and D = 10N for N = 10,000) it measures:
//!
//! 1. **Scheduler round**: [`rebalance`] alone (pure), [`JobSchedule::round`] (adds the
//!    views, the new table and the stale-load sweep) and [`RunningJob::round`] end to end
//!    (adds the round's delta, one shared copy queued for each of the N workers: what
//!    the job's actor runs on its round timer), each fed one queue report per worker.
//! 2. **Routing table**: the prost-encoded size of the whole table the coordinator
//!    builds ([`JobSchedule::table`], sent at a job's start, a join or a restart), what
//!    N copies of it would weigh on the wire and in memory (what every round cost before
//!    rounds sent deltas), the time to encode one copy, the delta a round really sends
//!    ([`JobRouting::delta`](dray_coordinator::scheduler::table::JobRouting::delta)) and what an owner-index form would weigh (an estimate; not built).
//! 3. **Report fan-in and the credit accounting**: what a job's actor runs for a
//!    ReportContributions with 1,000 pixel sums and 10 tile credits ([`report::check`],
//!    [`report::apply`], [`RunningJob::publish`]), on a real started job (a
//!    [`Membership`] with N registered workers and a [`RunningJob`] started on them). One
//!    job's reports are applied one at a time by its actor, so this time bounds one
//!    job's report rate; other jobs run on other actors. Beside it: the same pixel and
//!    credit additions on a bare [`Film`] (the work the job cannot avoid), the report's
//!    encoded size and its prost decode time (done by tonic outside the actor, on any
//!    core).
//! 4. **Queue reports**: [`RunningJob::queue_report`] with one worker's report (its owned
//!    domains plus the domains it holds rays for).
//!
//! Why synthetic reports are shaped this way: a worker reports, per job, one entry per
//! domain it has rays queued for or holds resident (worker/src/reporter.rs). Here each
//! worker owns D/N domains (the dynamic schedule's first, round-robin table) and has the
//! first half of them resident (an out-of-core budget); rays over domains follow a Zipf
//! law (exponent 1, domains in a shuffled order, so hot domains are spread over workers);
//! 70% of a domain's rays wait at its owner and 15% at each of two other workers (rays
//! waiting to be sent); every tenth worker is idle (no ray wants its domains). So a round
//! has real work to do: wanted domains that are not resident anywhere, and idle workers
//! to give them to.
//!
//! What is not simulated: gRPC and HTTP/2 framing, the network, the tokio tasks that
//! encode each worker's stream, tracing spans with a subscriber installed, other jobs
//! sharing the machine, the actor's mailbox hop, and memory-bandwidth contention from
//! tracing on the same machine. Reports are applied from one thread: the times are the
//! actor's busy time per call, a floor on what a busy coordinator sees.

use std::collections::{BTreeMap, BTreeSet};
use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

use dray_coordinator::dispatch::image_tiles;
use dray_coordinator::job::report::{self, Applied};
use dray_coordinator::job::{JobPlan, RunningJob};
use dray_coordinator::jobs::JobTable;
use dray_coordinator::membership::{HeartbeatConfig, Membership, VERSION};
use dray_coordinator::metrics::JobMetrics;
use dray_coordinator::scheduler::policy::{RoundInput, Schedule, rebalance, views};
use dray_coordinator::scheduler::state::{JobSchedule, JobWorker, RoundOutcome};
use dray_coordinator::scheduler::table::Ownership;
use dray_core::film::Film;
use dray_proto::v1::{
    DomainQueue, DomainRoute, JobSetup, JobSpec, JobStats, RayCounts, RegisterWorkerRequest,
    ReportContributionsRequest, ReportQueuesRequest, RoutingTable, TileCredit, WorkerCounters,
};
use prost::Message;

/// Image of every simulated job: 1080p, 60 x 34 = 2,040 tiles of 32 px.
const WIDTH: u32 = 1920;
const HEIGHT: u32 = 1080;
/// Samples per pixel of every simulated job.
const SPP: u32 = 64;
/// Pixel sums and tile credits per ReportContributions (the brief's typical report: a
/// worker's 10 ms of results spread over a few tiles).
const REPORT_PIXELS: usize = 1000;
const REPORT_TILES: usize = 10;
/// Report rates of one worker for one job (worker/src/reporter.rs: REPORT_INTERVAL
/// 10 ms, QUEUE_REPORT_INTERVAL 100 ms; a worker with nothing new skips a contribution
/// report, so 100/s is the busy worker's rate).
const CONTRIB_PER_S: f64 = 100.0;
const QUEUES_PER_S: f64 = 10.0;
/// Rounds per second per job: one per SchedulerOptions::round_interval (200 ms), since
/// with many workers some report is always fresh.
const ROUNDS_PER_S: f64 = 5.0;
/// Resident size every report gives a domain, and every worker's budget.
const DOMAIN_BYTES: u64 = 48 << 20;
const BUDGET: u64 = 1 << 30;
/// Mean rays queued per worker, for the Zipf law's total.
const RAYS_PER_WORKER: u64 = 4096;

/// The (N, D) cases, up to the coordinator's target: 10,000 workers and 100,000 domains
/// (docs/scaling.md).
const CASES: [(usize, u32); 6] = [
    (10, 40),
    (100, 400),
    (1000, 4000),
    (1000, 32000),
    (10_000, 40_000),
    (10_000, 100_000),
];

/// xorshift64*: deterministic, dependency-free pseudo-random numbers.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// One queue report per worker (index = position in `ids`, the job order), shaped as
/// described in the module docs.
fn queue_reports(n: usize, d: u32) -> Vec<Vec<DomainQueue>> {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ ((n as u64) << 20) ^ u64::from(d));
    // Zipf over a shuffled domain order.
    let mut order: Vec<u32> = (0..d).collect();
    for i in (1..order.len()).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        order.swap(i, j);
    }
    let h: f64 = (1..=d).map(|r| 1.0 / f64::from(r)).sum();
    let total = (RAYS_PER_WORKER * n as u64) as f64;
    let mut want = vec![0u64; d as usize];
    for (rank, &dom) in order.iter().enumerate() {
        want[dom as usize] = (total / h / (rank + 1) as f64) as u64;
    }
    let idle = |w: usize| w % 10 == 9;
    let owner = |dom: u32| dom as usize % n;
    // Per worker: domain -> rays queued there.
    let mut queued: Vec<BTreeMap<u32, u64>> = vec![BTreeMap::new(); n];
    for dom in 0..d {
        let o = owner(dom);
        let w = if idle(o) { 0 } else { want[dom as usize] };
        if w == 0 {
            continue;
        }
        let share = w * 15 / 100;
        *queued[o].entry(dom).or_default() += w - 2 * share;
        if share > 0 && n > 1 {
            for _ in 0..2 {
                let mut other = rng.below(n as u64) as usize;
                if other == o {
                    other = (other + 1) % n;
                }
                *queued[other].entry(dom).or_default() += share;
            }
        }
    }
    let k = d as usize / n;
    (0..n)
        .map(|w| {
            // Owned domains: w, w + n, w + 2n ...; the first half resident.
            let resident: BTreeSet<u32> = (0..k.div_ceil(2)).map(|j| (w + j * n) as u32).collect();
            let mut doms: BTreeSet<u32> = queued[w].keys().copied().collect();
            doms.extend(&resident);
            doms.into_iter()
                .map(|dom| DomainQueue {
                    domain: dom,
                    rays_queued: queued[w].get(&dom).copied().unwrap_or(0),
                    resident: resident.contains(&dom),
                    resident_bytes: DOMAIN_BYTES,
                })
                .collect()
        })
        .collect()
}

/// Per call: the median over `samples` of the mean time of a batch of calls sized to
/// take about 20 ms (after one warm-up batch).
fn per_call(samples: usize, mut f: impl FnMut()) -> Duration {
    let t = Instant::now();
    f();
    let one = t.elapsed().max(Duration::from_nanos(50));
    let batch = (Duration::from_millis(20).as_nanos() / one.as_nanos()).clamp(1, 200_000) as u32;
    for _ in 0..batch {
        f();
    }
    let mut v: Vec<Duration> = (0..samples)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..batch {
                f();
            }
            t.elapsed() / batch
        })
        .collect();
    v.sort();
    v[v.len() / 2]
}

/// The median over `samples` of one `run` on a fresh `setup()` each; setting up and
/// dropping are not timed. Returns the last run's result too.
fn per_fresh<S, R>(
    samples: usize,
    mut setup: impl FnMut() -> S,
    mut run: impl FnMut(&mut S) -> R,
) -> (Duration, R) {
    let mut times = Vec::with_capacity(samples);
    let mut last = None;
    for _ in 0..samples {
        let mut s = setup();
        let t = Instant::now();
        let r = run(&mut s);
        times.push(t.elapsed());
        last = Some(r);
        drop(s);
    }
    times.sort();
    (times[times.len() / 2], last.expect("at least one sample"))
}

/// A coordinator with N registered workers and one started dynamic job of D domains on
/// all of them (the real code path: Membership::register, JobSchedule::new,
/// RunningJob::new, RunningJob::start; start queues each worker's JobSetup and tiles in
/// its outbox, which nothing drains here). The job's state is driven directly, as its
/// actor drives it.
struct Sim {
    membership: Arc<Membership>,
    running: RunningJob,
    job: String,
    /// Worker ids in job order.
    ids: Vec<String>,
    workers: Vec<JobWorker>,
}

impl Sim {
    fn new(n: usize, d: u32) -> Sim {
        let membership = Arc::new(Membership::new(HeartbeatConfig::default()));
        let workers: Vec<JobWorker> = (0..n)
            .map(|i| {
                let rec = membership
                    .register(&RegisterWorkerRequest {
                        endpoint: format!("http://10.0.{}.{}:50052", i / 250, i % 250 + 1),
                        threads: 16,
                        memory_budget_bytes: BUDGET,
                        version: VERSION.into(),
                        record_format: dray_proto::RAY_RECORD_FORMAT,
                        hostname: format!("node{i}"),
                        cache_endpoint: String::new(),
                        name: format!("node{i}"),
                    })
                    .expect("register");
                JobWorker {
                    endpoint: rec.endpoint(),
                    budget: rec.memory_budget_bytes,
                }
            })
            .collect();
        let ids: Vec<String> = workers
            .iter()
            .map(|w| w.endpoint.worker_id.clone())
            .collect();
        let record = JobTable::new().insert(JobSpec {
            scene: "sim".into(),
            width: WIDTH,
            height: HEIGHT,
            // Progressive passes on (the default, doubling: 7 passes), so the job
            // builds its next pass image as tiles finish.
            spp: SPP,
            domains: d,
            schedule: "dynamic".into(),
            ..Default::default()
        });
        let job = record.id.clone();
        let sched = JobSchedule::new(&job, Schedule::Dynamic { replicate: false }, d, &workers);
        let setup = JobSetup {
            job_id: job.clone(),
            domain_count: d,
            ..Default::default()
        };
        let mut running = RunningJob::new(JobPlan {
            record,
            setup,
            sched,
            tiles: image_tiles(WIDTH, HEIGHT),
            owned_package: None,
            caches: None,
            resume: None,
            scene: dray_coordinator::scheduler::auto::SceneSize::default(),
        });
        // No store: the start awaits nothing, but it is async (a new attempt is made
        // durable by awaiting the store when there is one).
        tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime")
            .block_on(running.start(&membership))
            .expect("start");
        Sim {
            membership,
            running,
            job,
            ids,
            workers,
        }
    }

    /// One ReportQueues per worker, from [`queue_reports`].
    fn queue_requests(&self, d: u32) -> Vec<ReportQueuesRequest> {
        queue_reports(self.ids.len(), d)
            .into_iter()
            .zip(&self.ids)
            .map(|(queues, id)| ReportQueuesRequest {
                worker_id: id.clone(),
                job_id: self.job.clone(),
                routing_version: 1,
                queues,
                memory_used_bytes: 512 << 20,
                attempt: 0,
            })
            .collect()
    }

    /// One ReportContributions per worker (sequence 0: the caller numbers them):
    /// REPORT_PIXELS sums over REPORT_TILES tiles of the image, credit for those tiles.
    fn contribution_requests(&self) -> Vec<ReportContributionsRequest> {
        let tiles = image_tiles(WIDTH, HEIGHT);
        let mut rng = Rng(7);
        self.ids
            .iter()
            .map(|id| {
                let mine: Vec<usize> = (0..REPORT_TILES)
                    .map(|_| rng.below(tiles.len() as u64) as usize)
                    .collect();
                let pixels: Vec<u32> = (0..REPORT_PIXELS)
                    .map(|i| {
                        let t = &tiles[mine[i % REPORT_TILES]];
                        let x = t.x0 + rng.below(u64::from(t.width)) as u32;
                        let y = t.y0 + rng.below(u64::from(t.height)) as u32;
                        y * WIDTH + x
                    })
                    .collect();
                let sums = (0..3 * REPORT_PIXELS)
                    .map(|_| rng.below(1 << 26) as i64)
                    .collect();
                let mut credits: Vec<TileCredit> = mine
                    .iter()
                    .map(|&t| TileCredit {
                        tile: t as u32,
                        credit: 1 + rng.below(1 << 40),
                    })
                    .collect();
                credits.sort_by_key(|c| c.tile);
                ReportContributionsRequest {
                    worker_id: id.clone(),
                    job_id: self.job.clone(),
                    sequence: 0,
                    pixels,
                    sums,
                    credits,
                    traced: Some(RayCounts {
                        camera: 300,
                        shadow: 600,
                        reflection: 200,
                        diffuse: 400,
                        ..Default::default()
                    }),
                    nonfinite: 0,
                    ray_bytes_sent: 1 << 16,
                    attempt: 0,
                    counters: Some(WorkerCounters {
                        domain_loads: 0,
                        domain_load_seconds: 0.0,
                        evictions: 0,
                        rays_sent: 1000,
                        rays_forwarded: 3,
                        idle_seconds: 0.001,
                        queue_peak: 50_000,
                        ..Default::default()
                    }),
                    ..Default::default()
                }
            })
            .collect()
    }
}

/// Heap bytes of a RoutingTable held in memory (strings and vectors; allocator
/// overhead left out), for what N outbox copies weigh.
fn heap_bytes(t: &RoutingTable) -> usize {
    let s = |x: &String| x.capacity();
    size_of::<RoutingTable>()
        + s(&t.job_id)
        + t.workers.capacity() * size_of::<dray_proto::v1::WorkerEndpoint>()
        + t.workers
            .iter()
            .map(|w| s(&w.worker_id) + s(&w.endpoint))
            .sum::<usize>()
        + t.routes.capacity() * size_of::<DomainRoute>()
        + t.routes.iter().map(|r| s(&r.worker_id)).sum::<usize>()
}

fn us(d: Duration) -> String {
    let x = d.as_secs_f64() * 1e6;
    if x >= 100.0 {
        format!("{x:.0} µs")
    } else if x >= 10.0 {
        format!("{x:.1} µs")
    } else {
        format!("{x:.2} µs")
    }
}

fn bytes(b: f64) -> String {
    if b >= 1e9 {
        format!("{:.2} GB", b / 1e9)
    } else if b >= 1e6 {
        format!("{:.2} MB", b / 1e6)
    } else if b >= 1e3 {
        format!("{:.1} kB", b / 1e3)
    } else {
        format!("{b:.0} B")
    }
}

/// CPU jiffies: (busy on the whole machine, used by this process), from /proc; None
/// where /proc is missing. For "other load": how much else ran during the measurement.
fn jiffies() -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let cpu: Vec<u64> = stat
        .lines()
        .next()?
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    // user nice system idle iowait irq softirq steal ...: busy = all but idle, iowait.
    let busy = cpu.iter().sum::<u64>() - cpu.get(3)? - cpu.get(4).unwrap_or(&0);
    let me = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the ")" that ends the command name: utime is the 12th, stime the 13th.
    let rest: Vec<&str> = me.rsplit_once(')')?.1.split_whitespace().collect();
    let own = rest.get(11)?.parse::<u64>().ok()? + rest.get(12)?.parse::<u64>().ok()?;
    Some((busy, own))
}

/// Per-case results the summary needs.
#[derive(Default, Clone, Copy)]
struct Case {
    n: usize,
    d: u32,
    job_round: Duration,
    contrib: Duration,
    /// A report with no pixel sums: the actor's own work per report.
    bookkeeping: Duration,
    queues: Duration,
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let samples = if quick { 5 } else { 15 };
    let big_samples = if quick { 1 } else { 5 };
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!("# dray coordinator scale simulation");
    println!();
    println!("cores: {cores}; CPU: {cpu}; samples: {samples} (job rounds: {big_samples})");
    println!(
        "image {WIDTH}x{HEIGHT}; a contribution report: {REPORT_PIXELS} pixel sums, \
         {REPORT_TILES} tile credits"
    );
    let start = (Instant::now(), jiffies());
    let mut cases: Vec<Case> = Vec::new();

    println!();
    println!("## 1. Scheduler round (dynamic, replicate off)");
    println!();
    println!(
        "| N | D | queue entries (all reports) | moves | rebalance | JobSchedule::round | \
         RunningJob::round (with N table copies) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|");
    let mut tables = Vec::new();
    for (n, d) in CASES {
        let rs = if n * d as usize > 1_000_000 {
            big_samples
        } else {
            samples
        };
        let sim = Sim::new(n, d);
        let reqs = sim.queue_requests(d);
        let entries: usize = reqs.iter().map(|r| r.queues.len()).sum();
        // Pure policy.
        let reports: BTreeMap<String, Vec<DomainQueue>> = reqs
            .iter()
            .map(|r| (r.worker_id.clone(), r.queues.clone()))
            .collect();
        let budgets: BTreeMap<String, u64> = sim.ids.iter().map(|i| (i.clone(), BUDGET)).collect();
        let routes = Ownership::round_robin(d, &sim.ids);
        let loading = BTreeSet::new();
        let wv = views(&sim.ids, &budgets, &reports);
        let input = RoundInput {
            domains: d,
            routes: &routes,
            workers: &wv,
            loading: &loading,
            replicate: false,
        };
        let decision = rebalance(&input).expect("the simulated round moves domains");
        let moves = decision.changes.len();
        let t_rebalance = per_call(samples, || {
            black_box(rebalance(black_box(&input)));
        });
        // The job's scheduling state, with every report recorded.
        let mut sched = JobSchedule::new(
            &sim.job,
            Schedule::Dynamic { replicate: false },
            d,
            &sim.workers,
        );
        for r in &reqs {
            sched.record_queues(r);
        }
        let now = Instant::now();
        let (t_sched, out) = per_fresh(samples, || sched.clone(), |s| s.round(now, Duration::ZERO));
        let RoundOutcome::Changed(delta, changes) = out else {
            panic!("JobSchedule::round changed nothing");
        };
        // The whole table after the round (what a join or a restart sends).
        let mut after = sched.clone();
        after.round(now, Duration::ZERO);
        let new_table = after.table();
        // End to end through the job's state, on a fresh coordinator each sample.
        drop(sim);
        let (t_job, out) = per_fresh(
            rs,
            || {
                let mut sim = Sim::new(n, d);
                for r in sim.queue_requests(d) {
                    sim.running.queue_report(&r).expect("job running");
                }
                sim
            },
            |s| {
                s.running
                    .round(&s.membership, Instant::now(), Duration::ZERO)
            },
        );
        assert!(matches!(out, RoundOutcome::Changed(..)));
        println!(
            "| {n} | {d} | {entries} | {moves} | {} | {} | {} |",
            us(t_rebalance),
            us(t_sched),
            us(t_job)
        );
        cases.push(Case {
            n,
            d,
            job_round: t_job,
            ..Default::default()
        });
        tables.push((n, d, sched.table(), new_table, delta, changes));
    }

    println!();
    println!("## 2. Routing table (as JobSchedule::table builds it)");
    println!();
    println!(
        "| N | D | encoded | x N per change | in memory | x N (outbox copies) | encode one | \
         x N encodes | N clones (no longer made) | delta sent by a round (moves) | x N | owner-index form |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (n, d, first, new_table, delta, changes) in &tables {
        let len = new_table.encoded_len();
        let mem = heap_bytes(new_table);
        let t_encode = per_call(samples, || {
            black_box(black_box(new_table).encode_to_vec());
        });
        // What N deep copies of the new table would cost (the outboxes now share one
        // copy: RunningJob::round queues a pointer per worker), kept until the sample ends.
        // (Skipped where N copies would not fit in memory: that is the point.)
        let t_clones = (*n * mem <= 2 << 30).then(|| {
            per_fresh(
                if *n * *d as usize > 1_000_000 {
                    big_samples
                } else {
                    samples
                },
                || Vec::with_capacity(*n),
                |v: &mut Vec<RoutingTable>| {
                    for _ in 0..*n {
                        v.push(new_table.clone());
                    }
                },
            )
            .0
        });
        // The delta a round really sends (JobRouting::delta): the moved domains'
        // owners, no endpoint list.
        assert_eq!(delta.base_version, first.version);
        // Owner-index form estimate: the same table with each route as a packed varint
        // index into `workers` (domain = position), instead of (domain, worker id).
        let index: BTreeMap<&str, u64> = new_table
            .workers
            .iter()
            .enumerate()
            .map(|(i, w)| (w.worker_id.as_str(), i as u64))
            .collect();
        let packed: usize = new_table
            .routes
            .iter()
            .map(|r| prost::encoding::encoded_len_varint(index[r.worker_id.as_str()]))
            .sum();
        let indexed = RoutingTable {
            routes: Vec::new(),
            ..new_table.clone()
        }
        .encoded_len()
            + 1
            + prost::encoding::encoded_len_varint(packed as u64)
            + packed;
        let nf = *n as f64;
        assert_eq!(first.routes.len(), *d as usize);
        println!(
            "| {n} | {d} | {} | {} | {} | {} | {} | {} | {} | {} ({}) | {} | {} |",
            bytes(len as f64),
            bytes(nf * len as f64),
            bytes(mem as f64),
            bytes(nf * mem as f64),
            us(t_encode),
            us(t_encode * *n as u32),
            t_clones.map_or_else(|| "(too large)".to_string(), us),
            bytes(delta.encoded_len() as f64),
            changes.len(),
            bytes(nf * delta.encoded_len() as f64),
            bytes(indexed as f64),
        );
    }

    println!();
    println!("## 3. Report fan-in: ReportContributions through the job's state");
    println!();
    println!(
        "| N | report encoded | prost decode | film + credit adds only | has_worker | \
         metrics.fill | check + apply + publish | reports/s per core | \
         workers per core at 100/s | actor load at N workers | wire in at N |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut contrib_by_n = BTreeMap::new();
    let mut book_by_n = BTreeMap::new();
    for &(n, d) in CASES.iter().filter(|(n, d)| *d as usize == 4 * n) {
        let mut sim = Sim::new(n, d);
        let mut reqs = sim.contribution_requests();
        let wire = reqs[0].encode_to_vec();
        let t_decode = per_call(samples, || {
            black_box(ReportContributionsRequest::decode(black_box(&wire[..])).expect("decode"));
        });
        // The unavoidable work: the same adds on a bare film and credit array.
        let mut film = Film::new(WIDTH, HEIGHT);
        let mut back = vec![0u64; image_tiles(WIDTH, HEIGHT).len()];
        // Steady state: a running job's film has had every report's pixels before (the
        // first touch of each page of a fresh film is the kernel's work, once a job).
        for r in &reqs {
            film.add_fixed_run(&r.pixels, &r.sums);
        }
        let mut k = 0;
        let t_bare = per_call(samples, || {
            let r = &reqs[k % n];
            k += 1;
            film.add_fixed_run(&r.pixels, &r.sums);
            for c in &r.credits {
                back[c.tile as usize] = back[c.tile as usize].wrapping_add(c.credit);
            }
        });
        black_box((&film, &back));
        // Two steps every report takes: the membership check and JobStats' per-worker
        // detail, rebuilt by RunningJob::publish through JobMetrics::fill.
        let sched = sim.running.schedule().clone();
        let mut k = 0;
        let t_has = per_call(samples, || {
            black_box(sched.has_worker(black_box(&sim.ids[k % n])));
            k += 1;
        });
        let mut metrics = JobMetrics::default();
        for id in &sim.ids {
            metrics.add_worker(id);
            metrics.add(id, reqs[0].counters.as_ref(), reqs[0].traced.as_ref());
        }
        let mut stats = JobStats::default();
        let t_fill = per_call(samples, || {
            metrics.fill(black_box(&mut stats));
        });
        // What the job's actor runs: workers in turn, each report a new sequence (after
        // one report of each, for the steady state, as above).
        for r in &mut reqs {
            r.sequence += 1;
            report::check(&sim.running, r).expect("report accepted");
            report::apply(&mut sim.running, r);
        }
        let mut k = 0;
        let t_report = per_call(samples, || {
            let r = &mut reqs[k % n];
            k += 1;
            r.sequence += 1;
            let checked = report::check(&sim.running, r).expect("report accepted");
            debug_assert_eq!(checked, None);
            let out = report::apply(&mut sim.running, r);
            debug_assert_eq!(out, Applied::Counted);
            sim.running.publish();
            black_box(out);
        });
        // The actor's own bookkeeping: the same reports with credit and counters but no
        // pixel sums (what is left when the film adds leave the actor).
        let mut bare: Vec<ReportContributionsRequest> = reqs
            .iter()
            .map(|r| ReportContributionsRequest {
                pixels: Vec::new(),
                sums: Vec::new(),
                credits: r
                    .credits
                    .iter()
                    .map(|c| TileCredit { credit: 0, ..*c })
                    .collect(),
                ..r.clone()
            })
            .collect();
        let mut k = 0;
        let t_book = per_call(samples, || {
            let r = &mut bare[k % n];
            k += 1;
            r.sequence = reqs[0].sequence + k as u64;
            let checked = report::check(&sim.running, r).expect("report accepted");
            debug_assert_eq!(checked, None);
            let out = report::apply(&mut sim.running, r);
            sim.running.publish();
            black_box(out);
        });
        book_by_n.insert(n, t_book);
        let per_s = 1.0 / t_report.as_secs_f64();
        let load = n as f64 * CONTRIB_PER_S * t_report.as_secs_f64();
        println!(
            "| {n} | {} | {} | {} | {} | {} | {} | {:.0} | {:.0} | {load:.2} cores | {}/s |",
            bytes(wire.len() as f64),
            us(t_decode),
            us(t_bare),
            us(t_has),
            us(t_fill),
            us(t_report),
            per_s,
            per_s / CONTRIB_PER_S,
            bytes(n as f64 * CONTRIB_PER_S * wire.len() as f64),
        );
        contrib_by_n.insert(n, t_report);
    }

    println!();
    println!("## 4. Queue reports through RunningJob::queue_report");
    println!();
    println!(
        "| N | D | entries per report (mean) | RunningJob::queue_report | reports/s per core | \
         actor load at N workers (10/s each) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|");
    for c in &mut cases {
        let (n, d) = (c.n, c.d);
        let mut sim = Sim::new(n, d);
        let reqs = sim.queue_requests(d);
        for r in &reqs {
            sim.running.queue_report(r).expect("job running");
        }
        let mean = reqs.iter().map(|r| r.queues.len()).sum::<usize>() as f64 / n as f64;
        let mut k = 0;
        let t = per_call(samples, || {
            let r = &reqs[k % n];
            k += 1;
            black_box(sim.running.queue_report(r));
        });
        println!(
            "| {n} | {d} | {mean:.1} | {} | {:.0} | {:.2} cores |",
            us(t),
            1.0 / t.as_secs_f64(),
            n as f64 * QUEUES_PER_S * t.as_secs_f64()
        );
        c.queues = t;
        c.contrib = contrib_by_n[&n];
        c.bookkeeping = book_by_n[&n];
    }

    println!();
    println!("## 5. Load on one job's actor, one job on all N workers");
    println!();
    println!(
        "Cores of the job actor's time per second: N x 100 contribution reports, N x 10 queue \
         reports, 5 rounds (one per 200 ms round interval). Above 1.0 one job's actor cannot \
         keep up, however many cores the coordinator has (other jobs have their own)."
    );
    println!();
    println!("| N | D | contributions | queue reports | rounds | total |");
    println!("|---:|---:|---:|---:|---:|---:|");
    for c in &cases {
        let nf = c.n as f64;
        let a = nf * CONTRIB_PER_S * c.contrib.as_secs_f64();
        let b = nf * QUEUES_PER_S * c.queues.as_secs_f64();
        let r = ROUNDS_PER_S * c.job_round.as_secs_f64();
        println!(
            "| {} | {} | {a:.3} | {b:.3} | {r:.3} | **{:.3}** |",
            c.n,
            c.d,
            a + b + r
        );
    }
    // Where contributions alone fill one job's actor: fit t(N) = a + bN through the N = 100 and
    // N = 1000 points and solve 100 N t(N) = 1.
    if let (Some(t1), Some(t2)) = (contrib_by_n.get(&100), contrib_by_n.get(&1000)) {
        let (t1, t2) = (t1.as_secs_f64(), t2.as_secs_f64());
        let b = (t2 - t1) / 900.0;
        let a = t1 - 100.0 * b;
        // 100 b N^2 + 100 a N - 1 = 0
        let nstar = if b > 0.0 {
            (-100.0 * a + ((100.0 * a).powi(2) + 400.0 * b).sqrt()) / (200.0 * b)
        } else {
            1.0 / (100.0 * a)
        };
        println!();
        println!(
            "Contribution report cost fitted as t(N) = {:.2} µs + {:.2} ns x N; one job's \
             actor is full of contribution reports alone at N = {nstar:.0} workers (100 reports/s each).",
            a * 1e6,
            b * 1e9
        );
    }
    println!();
    println!("## 6. One line per point (JSON)");
    println!();
    for c in &cases {
        println!(
            "{{\"workers\": {}, \"domains\": {}, \"round_ms\": {:.3}, \"report_us\": {:.3}, \
             \"reports_per_s\": {:.0}, \"report_no_pixels_us\": {:.3}, \
             \"reports_no_pixels_per_s\": {:.0}, \"queue_report_us\": {:.3}}}",
            c.n,
            c.d,
            c.job_round.as_secs_f64() * 1e3,
            c.contrib.as_secs_f64() * 1e6,
            1.0 / c.contrib.as_secs_f64(),
            c.bookkeeping.as_secs_f64() * 1e6,
            1.0 / c.bookkeeping.as_secs_f64(),
            c.queues.as_secs_f64() * 1e6,
        );
    }
    if let (Some((b0, o0)), Some((b1, o1))) = (start.1, jiffies()) {
        // USER_HZ is 100 on Linux.
        let secs = start.0.elapsed().as_secs_f64();
        let other = (b1 - b0).saturating_sub(o1 - o0) as f64 / 100.0 / secs;
        println!();
        println!(
            "Run took {secs:.0} s; other load (CPU used by other processes while it ran): \
             {other:.2} cores on average."
        );
    }
}
