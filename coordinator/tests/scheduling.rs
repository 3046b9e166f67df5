//! Schedules, lost workers and joining workers on a live coordinator, with tests playing
//! the workers over the real protocol: image-plane blocks and a local table, domain round
//! robin that queue reports never change, a dynamic round moving a domain to a worker that
//! joined mid-job, schedule validation, and a worker lost mid-job: the survivors cancel
//! the old attempt, set up the next and get exactly the unfinished tiles; reports of the
//! old attempt are ignored; and the image is bit for bit that of an undisturbed run.

mod support;

use std::time::Duration;

use dray_coordinator::dispatch::TILE_CREDIT;
use dray_coordinator::membership::HeartbeatConfig;
use dray_coordinator::scheduler::SchedulerOptions;
use dray_core::film::Film;
use dray_proto::v1::assignment::Command;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    JobSpec, JobState, RayCounts, RegisterWorkerRequest, ReportContributionsRequest, RoutingTable,
    SubmitJobRequest, Tile, TileCredit, WorkerCounters,
};
use tonic::Code;

use support::*;

/// Fast rounds, so dynamic tests do not wait.
fn fast_rounds() -> SchedulerOptions {
    SchedulerOptions {
        round_interval: Duration::from_millis(10),
    }
}

fn with_schedule(spec: JobSpec, schedule: &str) -> JobSpec {
    JobSpec {
        schedule: schedule.into(),
        ..spec
    }
}

/// The worker ids a table lists, in order.
fn table_workers(t: &RoutingTable) -> Vec<String> {
    t.workers.iter().map(|w| w.worker_id.clone()).collect()
}

fn sorted_indices(tiles: &[Tile]) -> Vec<u32> {
    let mut v: Vec<u32> = tiles.iter().map(|t| t.index).collect();
    v.sort();
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn image_plane_deals_contiguous_blocks_with_a_local_table() {
    let server = Server::start("image-plane", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut ws = Vec::new();
    for port in [7001, 7002, 7003] {
        ws.push(FakeWorker::join(channel.clone(), &format!("http://127.0.0.1:{port}")).await);
    }
    // 100x70: 4 x 3 = 12 tiles, 4 per worker, in blocks.
    let id = submit(&channel, with_schedule(spec(100, 70, 3), "image-plane")).await;
    let mut setups = Vec::new();
    for w in &mut ws {
        setups.push(w.setup_and_tiles(4).await);
    }
    let table = setups[0].0.routing.clone().unwrap();
    assert!(table.local && table.routes.is_empty(), "{table:?}");
    assert_eq!((table.version, table.attempt), (1, 0));
    let order = table_workers(&table);
    for (w, (setup, tiles)) in ws.iter().zip(&setups) {
        assert_eq!(setup.schedule, "image-plane");
        assert_eq!(setup.attempt, 0);
        assert_eq!(setup.routing.as_ref(), Some(&table));
        let i = order.iter().position(|o| *o == w.id).unwrap() as u32;
        assert_eq!(
            sorted_indices(tiles),
            (4 * i..4 * i + 4).collect::<Vec<_>>()
        );
    }
    // Queue reports never change an image-plane table: no rounds.
    let v = ws[0]
        .report_queues(&id, 0, 1, &[(0, 1000, false, 10), (1, 500, false, 10)])
        .await;
    assert_eq!(v, 1);
    assert!(
        ws[1]
            .next_within(Duration::from_millis(400))
            .await
            .is_none()
    );
    let stats = get_job(&channel, &id).await.stats.unwrap();
    assert_eq!(
        (
            stats.schedule.as_str(),
            stats.scheduler_rounds,
            stats.routing_version
        ),
        ("image-plane", 0, 1)
    );
}

/// Workers on ports 7001, 7002, ... with these memory budgets, in order.
async fn join_with_budgets(
    channel: &tonic::transport::Channel,
    budgets: &[u64],
) -> Vec<FakeWorker> {
    let mut ws = Vec::new();
    for (port, &budget) in (7001..).zip(budgets) {
        let req = RegisterWorkerRequest {
            memory_budget_bytes: budget,
            ..register_request(&format!("http://127.0.0.1:{port}"))
        };
        ws.push(FakeWorker::join_with(channel.clone(), req).await);
    }
    ws
}

/// `auto` (the default) on workers whose budgets all hold the scene: the replicated
/// schedule, one domain, a local table, tiles dealt round robin (interleaved, not in
/// blocks), the reason in GetJob's statistics; with one worker too small for it: the
/// dynamic schedule over owned domains, naming that worker (issue 40).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_replicates_a_scene_every_worker_holds_and_owns_domains_otherwise() {
    let server = Server::start("auto", slow_heartbeat()).await;
    let channel = server.channel().await;
    // cornell's resident size is far below a megabyte: 10 MB holds it with its load.
    let mut ws = join_with_budgets(&channel, &[0, 10_000_000]).await;
    // 128x64: 4 x 2 = 8 tiles, 4 per worker; no --domains, no --schedule.
    let id = submit(&channel, with_schedule(spec(128, 64, 0), "")).await;
    let mut setups = Vec::new();
    for w in &mut ws {
        setups.push(w.setup_and_tiles(4).await);
    }
    let table = setups[0].0.routing.clone().unwrap();
    assert!(table.local && table.routes.is_empty(), "{table:?}");
    let order = table_workers(&table);
    for (w, (setup, tiles)) in ws.iter().zip(&setups) {
        assert_eq!(setup.schedule, "replicated");
        assert_eq!(setup.domain_count, 1, "the whole scene as one domain");
        assert_eq!(setup.spec.as_ref().unwrap().schedule, "replicated");
        let i = order.iter().position(|o| *o == w.id).unwrap() as u32;
        assert_eq!(
            sorted_indices(tiles),
            (0..8).filter(|t| t % 2 == i).collect::<Vec<_>>(),
            "round robin"
        );
    }
    let job = get_job(&channel, &id).await;
    assert_eq!(
        job.spec.unwrap().schedule,
        "replicated",
        "GetJob says what ran"
    );
    let stats = job.stats.unwrap();
    assert_eq!((stats.schedule.as_str(), stats.domains), ("replicated", 1));
    assert!(
        stats.placement.starts_with("replicated (auto)")
            && stats.placement.contains("smallest 10.00 MB"),
        "{}",
        stats.placement
    );
    drop(ws);
    drop(server);

    let server = Server::start("auto-small", slow_heartbeat()).await;
    let channel = server.channel().await;
    // About 7 kB resident: it loads with 11 kB, and three quarters of 5 kB do not hold
    // that.
    let mut ws = join_with_budgets(&channel, &[0, 5_000]).await;
    let id = submit(&channel, with_schedule(spec(128, 64, 0), "")).await;
    for w in &mut ws {
        let (setup, _) = w.setup_and_tiles(4).await;
        assert_eq!(setup.schedule, "dynamic");
        assert!(!setup.routing.unwrap().local);
    }
    let stats = get_job(&channel, &id).await.stats.unwrap();
    assert_eq!(stats.schedule, "dynamic");
    assert!(
        stats.placement.starts_with("dynamic (auto)")
            && stats.placement.contains(&format!("worker {}", ws[1].id)),
        "{}",
        stats.placement
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn domain_schedule_is_round_robin_and_static() {
    let server = Server::start_with(
        "domain",
        slow_heartbeat(),
        fast_rounds(),
        &std::env::temp_dir(),
    )
    .await;
    let channel = server.channel().await;
    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let mut b = FakeWorker::join(channel.clone(), "http://127.0.0.1:7002").await;
    let id = submit(&channel, with_schedule(spec(100, 70, 4), "domain")).await;
    let (sa, ta) = a.setup_and_tiles(6).await;
    let (sb, tb) = b.setup_and_tiles(6).await;
    assert_eq!(sa, sb);
    assert_eq!(sa.schedule, "domain");
    let table = sa.routing.unwrap();
    assert!(!table.local);
    let order = table_workers(&table);
    assert_eq!(table.routes.len(), 4);
    for r in &table.routes {
        assert_eq!(r.worker_id, order[r.domain as usize % 2]);
    }
    let (first, second) = if order[0] == a.id {
        (&ta, &tb)
    } else {
        (&tb, &ta)
    };
    assert!(first.iter().all(|t| t.index % 2 == 0));
    assert!(second.iter().all(|t| t.index % 2 == 1));
    // b idle and a's domains unloaded and wanted: a dynamic schedule would move one; the
    // domain schedule does not.
    let a_owns: Vec<u32> = table
        .routes
        .iter()
        .filter(|r| r.worker_id == a.id)
        .map(|r| r.domain)
        .collect();
    let q: Vec<(u32, u64, bool, u64)> = a_owns.iter().map(|&d| (d, 100, false, 10)).collect();
    assert_eq!(a.report_queues(&id, 0, 1, &q).await, 1);
    assert_eq!(b.report_queues(&id, 0, 1, &[]).await, 1);
    assert!(b.next_within(Duration::from_millis(300)).await.is_none());
    let stats = get_job(&channel, &id).await.stats.unwrap();
    assert_eq!((stats.scheduler_rounds, stats.routing_version), (0, 1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn schedules_are_validated_and_resolved() {
    let server = Server::start("validate-schedule", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut render = RenderServiceClient::new(channel.clone());
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(with_schedule(spec(8, 8, 1), "fastest")),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(
        e.message().starts_with("schedule:")
            && e.message().contains(
                "auto, replicated, image-plane, domain, dynamic or dynamic-from-image-plane"
            ),
        "{}",
        e.message()
    );
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(JobSpec {
                replicate: true,
                ..with_schedule(spec(8, 8, 1), "domain")
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("replicate:"), "{}", e.message());
    // Empty means auto, and the reply says so (no worker: it renders in process,
    // which ignores the schedule, so auto is never resolved).
    let r = render
        .submit_job(SubmitJobRequest {
            spec: Some(with_schedule(spec(8, 8, 1), "")),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.spec.unwrap().schedule, "auto");
    wait_state(&channel, &r.job_id, JobState::Succeeded).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_joining_a_dynamic_job_is_set_up_and_given_a_domain() {
    let server = Server::start_with(
        "join",
        slow_heartbeat(),
        fast_rounds(),
        &std::env::temp_dir(),
    )
    .await;
    let channel = server.channel().await;
    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(64, 32, 3)).await;
    let (setup, _) = a.setup_and_tiles(2).await;
    assert_eq!(setup.schedule, "dynamic");
    let mut b = FakeWorker::join_with(
        channel.clone(),
        RegisterWorkerRequest {
            memory_budget_bytes: 5000,
            ..register_request("http://127.0.0.1:7002")
        },
    )
    .await;
    // The joiner: a JobSetup of the current attempt whose table lists it, and no tiles.
    let joined = match b.next().await {
        Command::Setup(s) => s,
        other => panic!("expected a JobSetup, got {other:?}"),
    };
    assert_eq!((joined.job_id.as_str(), joined.attempt), (id.as_str(), 0));
    let t2 = joined.routing.clone().unwrap();
    assert_eq!((t2.version, t2.attempt), (2, 0));
    assert_eq!(table_workers(&t2), [a.id.clone(), b.id.clone()]);
    assert!(
        t2.routes.iter().all(|r| r.worker_id == a.id),
        "owns nothing yet"
    );
    assert_eq!(joined.spec, setup.spec);
    // The others learn the new table.
    match a.next().await {
        Command::Routing(t) => assert_eq!(t, t2),
        other => panic!("expected the new table, got {other:?}"),
    }
    // a has 0 loaded; 1 (most wanted) and 2 wait for loads. b is idle: it gets 1 if it
    // fits its budget; 1 does not (9000 bytes), so it gets 2.
    let v = a
        .report_queues(
            &id,
            0,
            2,
            &[(0, 100, true, 10), (1, 80, false, 9000), (2, 20, false, 10)],
        )
        .await;
    assert_eq!(v, 2);
    let t3 = match a.next().await {
        Command::Routing(t) => t,
        other => panic!("expected a round's table, got {other:?}"),
    };
    match b.next().await {
        Command::Routing(t) => assert_eq!(t, t3),
        other => panic!("expected a round's table, got {other:?}"),
    }
    assert_eq!((t3.version, t3.attempt), (3, 0));
    // A round sends a delta from the table the workers hold: the moved domain only.
    assert_eq!(t3.base_version, 2);
    assert!(t3.workers.is_empty(), "a delta does not repeat the workers");
    assert!(
        t3.routes.iter().all(|r| r.domain == 2),
        "only domain 2 moved"
    );
    let moved: Vec<u32> = t3.routes.iter().map(|r| r.domain).collect();
    let mut whole = t2.clone();
    whole.routes.retain(|r| !moved.contains(&r.domain));
    whole.routes.extend(t3.routes.iter().cloned());
    let owner = |d: u32| -> Vec<String> {
        whole
            .routes
            .iter()
            .filter(|r| r.domain == d)
            .map(|r| r.worker_id.clone())
            .collect()
    };
    assert_eq!(owner(0), [a.id.clone()]);
    assert_eq!(owner(1), [a.id.clone()]);
    assert_eq!(owner(2), [b.id.clone()]);
    let stats = get_job(&channel, &id).await.stats.unwrap();
    assert_eq!(stats.routing_version, 3);
    assert!(stats.scheduler_rounds >= 1);
    assert_eq!(stats.workers, 2);
    // Reports of the joiner count (it is a worker of the job now).
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        counters: Some(WorkerCounters {
            domain_loads: 1,
            ..Default::default()
        }),
        ..Default::default()
    };
    assert!(b.report(r).await.unwrap());
    let stats = get_job(&channel, &id).await.stats.unwrap();
    assert_eq!(stats.domain_loads, 1);
}

/// What the tracer of tile `t` contributes, deterministically: every pixel of the tile,
/// once, as two reports' worth (`part` 0 and 1) so a tile can be left half done.
fn tile_pixels(t: &Tile, width: u32, part: u32) -> (Vec<u32>, Vec<i64>) {
    let mut pixels = Vec::new();
    let mut sums = Vec::new();
    for y in t.y0..t.y0 + t.height {
        for x in t.x0..t.x0 + t.width {
            let p = y * width + x;
            if p % 2 != part {
                continue;
            }
            pixels.push(p);
            sums.extend([
                fixed(f64::from(p % 97) / 7.0),
                i64::from(p) * 3 + 1,
                fixed(0.125) + i64::from(t.index),
            ]);
        }
    }
    (pixels, sums)
}

/// A report of `tiles`' contributions (`parts` of them) and `credit` per tile.
fn contribution(
    job: &str,
    attempt: u32,
    sequence: u64,
    tiles: &[Tile],
    width: u32,
    parts: &[u32],
    credit: u64,
) -> ReportContributionsRequest {
    let mut r = ReportContributionsRequest {
        job_id: job.into(),
        attempt,
        sequence,
        traced: Some(RayCounts {
            camera: tiles.len() as u64,
            ..Default::default()
        }),
        ..Default::default()
    };
    for t in tiles {
        for &part in parts {
            let (p, s) = tile_pixels(t, width, part);
            r.pixels.extend(p);
            r.sums.extend(s);
        }
        if credit > 0 {
            r.credits.push(TileCredit {
                tile: t.index,
                credit,
            });
        }
    }
    r
}

async fn film_of(server: &Server, id: &str) -> Film {
    let film = server
        .coordinator
        .job_entry(id)
        .expect("job")
        .film()
        .expect("a succeeded job has a film");
    (*film).clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_worker_restarts_its_unfinished_tiles_and_the_image_is_unchanged() {
    const W: u32 = 128;
    const H: u32 = 96; // 4 x 3 = 12 tiles of 32.
    let beat = Duration::from_millis(50);
    let server = Server::start(
        "retrace",
        HeartbeatConfig {
            interval: beat,
            timeout: Duration::from_millis(3000),
        },
    )
    .await;
    let channel = server.channel().await;

    // The reference: one worker, every tile's contributions reported once.
    let reference = {
        let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7000").await;
        let alive = w.keep_alive(beat);
        let id = submit(&channel, with_schedule(spec(W, H, 3), "domain")).await;
        let (_, tiles) = w.setup_and_tiles(12).await;
        let r = contribution(&id, 0, 1, &tiles, W, &[0, 1], TILE_CREDIT);
        assert!(!w.report(r).await.unwrap(), "the job completes");
        wait_state(&channel, &id, JobState::Succeeded).await;
        assert!(matches!(w.next().await, Command::Finish(_)));
        let film = film_of(&server, &id).await;
        // This worker leaves the cluster for good: it stops heartbeating and is dropped
        // before the next job starts (it has no job, so nothing restarts).
        drop(alive);
        let deadline = tokio::time::Instant::now() + PATIENCE;
        while server.coordinator.cluster().membership.get(&w.id).is_some() {
            assert!(tokio::time::Instant::now() < deadline, "not dropped");
            tokio::time::sleep(beat).await;
        }
        film
    };

    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let mut b = FakeWorker::join(channel.clone(), "http://127.0.0.1:7002").await;
    let mut c = FakeWorker::join(channel.clone(), "http://127.0.0.1:7003").await;
    let _alive_a = a.keep_alive(beat);
    let _alive_b = b.keep_alive(beat);
    let alive_c = c.keep_alive(beat);
    let id = submit(&channel, with_schedule(spec(W, H, 3), "domain")).await;
    let (setup, ta) = a.setup_and_tiles(4).await;
    let (_, tb) = b.setup_and_tiles(4).await;
    let (_, tc) = c.setup_and_tiles(4).await;
    let t1 = setup.routing.unwrap();
    assert_eq!(
        table_workers(&t1),
        [a.id.clone(), b.id.clone(), c.id.clone()]
    );

    // Attempt 0: a finishes all its tiles. b returns half the credit of each of its
    // tiles with half their pixels. c finishes its first tile and sends pixels (no
    // credit) for its second.
    let half = TILE_CREDIT / 2;
    assert!(
        a.report(contribution(&id, 0, 1, &ta, W, &[0, 1], TILE_CREDIT))
            .await
            .unwrap()
    );
    assert!(
        b.report(contribution(&id, 0, 1, &tb, W, &[0], half))
            .await
            .unwrap()
    );
    assert!(
        c.report(contribution(&id, 0, 1, &tc[..1], W, &[0, 1], TILE_CREDIT))
            .await
            .unwrap()
    );
    assert!(
        c.report(contribution(&id, 0, 2, &tc[1..2], W, &[1], 0))
            .await
            .unwrap()
    );
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!(p.tiles_done, 5);

    // c goes silent and is dropped: the survivors cancel attempt 0, set up attempt 1
    // and get the 7 unfinished tiles (b's 4 and c's last 3), round robin over [a, b].
    drop(alive_c);
    let mut unfinished: Vec<Tile> = tb.iter().chain(&tc[1..]).copied().collect();
    unfinished.sort_by_key(|t| t.index);
    let survivors = [a.id.clone(), b.id.clone()];
    let lost = c.id.clone();
    let mut again = Vec::new();
    for (i, w) in [&mut a, &mut b].into_iter().enumerate() {
        match w.next().await {
            Command::Cancel(r) => {
                assert_eq!((r.job_id.as_str(), r.attempt), (id.as_str(), 0));
                assert!(
                    r.reason.contains(&lost) && r.reason.contains("7003"),
                    "{}",
                    r.reason
                );
            }
            other => panic!("expected the old attempt's cancel, got {other:?}"),
        }
        let s = match w.next().await {
            Command::Setup(s) => s,
            other => panic!("expected the new attempt's setup, got {other:?}"),
        };
        assert_eq!(
            (s.job_id.as_str(), s.attempt, s.schedule.as_str()),
            (id.as_str(), 1, "domain")
        );
        let t = s.routing.unwrap();
        assert_eq!((t.version, t.attempt, t.local), (2, 1, false));
        assert_eq!(table_workers(&t), survivors);
        for r in &t.routes {
            assert_eq!(r.worker_id, t.workers[r.domain as usize % 2].worker_id);
        }
        let expect: Vec<Tile> = unfinished
            .iter()
            .enumerate()
            .filter(|(j, _)| j % 2 == i)
            .map(|(_, t)| Tile { attempt: 1, ..*t })
            .collect();
        let got = w.tiles(&id, expect.len()).await;
        assert_eq!(got, expect);
        again.push(got);
    }
    let job = get_job(&channel, &id).await;
    assert_eq!(
        job.progress.unwrap().tiles_done,
        5,
        "complete tiles stay complete"
    );
    let stats = job.stats.unwrap();
    assert_eq!((stats.tiles_retried, stats.routing_version), (7, 2));
    assert_eq!(stats.workers, 3, "c took part");

    // Stale: attempt-0 reports (from a survivor and from the lost worker) are ignored.
    let stale = contribution(&id, 0, 7, &tb, W, &[0, 1], half);
    assert!(!b.report(stale).await.unwrap());
    let stale = contribution(&id, 0, 3, &tc[1..], W, &[0, 1], TILE_CREDIT);
    assert!(!c.report(stale).await.unwrap());
    assert_eq!(get_job(&channel, &id).await.progress.unwrap().tiles_done, 5);
    assert_eq!(b.report_queues(&id, 0, 1, &[(0, 5, false, 1)]).await, 0);
    assert_eq!(a.report_queues(&id, 1, 2, &[(0, 5, true, 1)]).await, 2);

    // Attempt 1 (sequences start again at 1): the re-dealt tiles, whole.
    assert!(
        a.report(contribution(&id, 1, 1, &again[0], W, &[0, 1], TILE_CREDIT))
            .await
            .unwrap()
    );
    assert!(
        !b.report(contribution(&id, 1, 1, &again[1], W, &[0, 1], TILE_CREDIT))
            .await
            .unwrap(),
        "the job completes"
    );
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    for w in [&mut a, &mut b] {
        match w.next().await {
            Command::Finish(r) => assert_eq!((r.job_id.as_str(), r.attempt), (id.as_str(), 1)),
            other => panic!("expected the finish of attempt 1, got {other:?}"),
        }
    }
    assert_eq!(job.stats.unwrap().tiles_retried, 7);
    let film = film_of(&server, &id).await;
    assert_eq!(
        film, reference,
        "the image after a lost worker must be bit for bit that of an undisturbed run"
    );
}
