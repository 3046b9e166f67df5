//! The coordinator's ClusterService on a live server over real TCP, with a test playing
//! the worker through the generated tonic client: registration (and its refusals),
//! heartbeats, the assignment stream (JobSetup, tiles, releases), contribution reports
//! with credit and fixed-point pixel sums (dedupe by sequence, failures, over-returned
//! credit), the workers' counters in JobStats, cancellation, and the last worker of a job
//! lost to silence.

mod support;

use std::path::{Path, PathBuf};
use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_coordinator::dispatch::{TILE_CREDIT, package_checksum};
use dray_coordinator::membership::{HeartbeatConfig, VERSION};
use dray_proto::v1::assignment::Command;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetRoutingTableRequest, HeartbeatRequest, ImageFormat,
    JobSpec, JobState, RayCounts, RegisterWorkerRequest, ReportContributionsRequest,
    SubmitJobRequest, TileCredit, WatchAssignmentsRequest, WorkerCounters,
};
use prost::Message;
use tonic::Code;

use support::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_runs_on_a_registered_worker_and_returns_its_sums() {
    let server = Server::start("run", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;

    // 70x40 pixels: 3 x 2 tiles of at most 32, edge tiles smaller.
    let id = submit(&channel, spec(70, 40, 3)).await;
    let (setup, tiles) = w.setup_and_tiles(6).await;
    assert_eq!(setup.job_id, id);
    assert_eq!(setup.tile_size, 32);
    assert_eq!(setup.tile_credit, 1 << 62);
    assert_eq!(setup.domain_count, 3);
    let s = setup.spec.clone().unwrap();
    assert_eq!(
        (s.width, s.height, s.spp, s.integrator.as_str()),
        (70, 40, 1, "path")
    );
    assert_eq!(s.max_depth, Some(5));
    assert_eq!(
        s.camera.as_deref(),
        Some("0"),
        "camera resolved to an index"
    );
    assert_eq!((s.domains, s.layout.as_str()), (3, "kd"));
    assert!(setup.environment.is_some());
    assert!(
        setup.effects.iter().any(|e| e == "direct_light"),
        "cornell is lit: {:?}",
        setup.effects
    );
    // The package is real, absolute, and its checksum is the manifest's.
    let pkg = PathBuf::from(&setup.package_path);
    assert!(pkg.is_absolute() && pkg.starts_with(&server.work_dir));
    let manifest = std::fs::read(pkg.join("manifest.json")).unwrap();
    assert_eq!(setup.package_checksum, package_checksum(&manifest));
    let opened = dray_scene::partition::open_package(&pkg).unwrap();
    assert_eq!(opened.domain_count(), 3);
    // Routing: version 1, every domain to the only worker.
    assert_eq!((setup.attempt, setup.schedule.as_str()), (0, "dynamic"));
    assert_eq!(s.schedule, "dynamic", "the resolved schedule");
    let routing = setup.routing.clone().unwrap();
    assert_eq!(
        (routing.version, routing.attempt, routing.local),
        (1, 0, false)
    );
    assert_eq!(routing.workers.len(), 1);
    assert_eq!(routing.workers[0].worker_id, w.id);
    assert_eq!(routing.workers[0].endpoint, "http://127.0.0.1:7001");
    let domains: Vec<u32> = routing.routes.iter().map(|r| r.domain).collect();
    assert_eq!(domains, [0, 1, 2]);
    assert!(routing.routes.iter().all(|r| r.worker_id == w.id));
    let fetched = w
        .client
        .get_routing_table(GetRoutingTableRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner()
        .routing
        .unwrap();
    assert_eq!(fetched, routing);
    // Tiles: row-major, index = (y0/32)*3 + x0/32, full credit.
    let mut idx: Vec<u32> = tiles.iter().map(|t| t.index).collect();
    idx.sort();
    assert_eq!(idx, [0, 1, 2, 3, 4, 5]);
    for t in &tiles {
        assert_eq!(t.index, (t.y0 / 32) * 3 + t.x0 / 32);
        assert_eq!(t.credit, TILE_CREDIT);
        assert_eq!(t.attempt, 0);
        assert_eq!(t.width, 32.min(70 - t.x0));
        assert_eq!(t.height, 32.min(40 - t.y0));
    }

    // Queue reports are stored and answered with the routing version.
    let v = w
        .report_queues(&id, 0, 1, &[(0, 40, true, 1000), (2, 2, true, 1000)])
        .await;
    assert_eq!(v, 1);
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!(p.rays_in_flight, 42, "rays queued at the workers");
    // A report for an attempt the job is not at is answered 0 and not stored.
    assert_eq!(w.report_queues(&id, 1, 1, &[(1, 1000, false, 1)]).await, 0);
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!(p.rays_in_flight, 42);

    // Report 1: two pixel sums (one pixel twice) and half of every tile's credit.
    let half = TILE_CREDIT / 2;
    let first = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        pixels: vec![0, 71, 0],
        sums: vec![
            fixed(0.5),
            fixed(0.25),
            fixed(1.0),
            fixed(2.0),
            0,
            fixed(0.125),
            fixed(0.5),
            fixed(0.25),
            0,
        ],
        credits: (0..6)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        traced: Some(RayCounts {
            camera: 10,
            shadow: 7,
            ..Default::default()
        }),
        nonfinite: 1,
        ray_bytes_sent: 640,
        counters: Some(WorkerCounters {
            domain_loads: 2,
            domain_load_seconds: 0.5,
            evictions: 1,
            rays_sent: 30,
            rays_forwarded: 4,
            idle_seconds: 0.25,
            queue_peak: 40,
            ..Default::default()
        }),
        ..Default::default()
    };
    assert!(w.report(first.clone()).await.unwrap());
    // The same sequence again (a retry after a lost answer) changes nothing.
    assert!(w.report(first.clone()).await.unwrap());
    let job = get_job(&channel, &id).await;
    let p = job.progress.unwrap();
    assert_eq!(p.state(), JobState::Running);
    assert_eq!((p.tiles_done, p.tiles_total), (0, 6));
    assert_eq!(p.rays_traced, 17, "the repeated report was counted twice");
    let stats = job.stats.unwrap();
    assert_eq!((stats.workers, stats.domains), (1, 3));
    assert_eq!(stats.ray_bytes_sent, 640);

    // A malformed report is refused and changes nothing.
    let bad = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        pixels: vec![1],
        sums: vec![1, 2],
        ..Default::default()
    };
    assert_eq!(
        w.report(bad).await.unwrap_err().code(),
        Code::InvalidArgument
    );
    let outside = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        pixels: vec![70 * 40],
        sums: vec![1, 2, 3],
        ..Default::default()
    };
    assert_eq!(
        w.report(outside).await.unwrap_err().code(),
        Code::InvalidArgument
    );
    let nan = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        counters: Some(WorkerCounters {
            idle_seconds: f64::NAN,
            ..Default::default()
        }),
        ..Default::default()
    };
    let e = w.report(nan).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(
        e.message().starts_with("counters.idle_seconds:"),
        "{}",
        e.message()
    );
    let ahead = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        attempt: 1,
        ..Default::default()
    };
    assert_eq!(
        w.report(ahead).await.unwrap_err().code(),
        Code::InvalidArgument,
        "an attempt the coordinator never started"
    );

    // Report 3 arrives before report 2 (out of order is fine): tiles 0..3 complete.
    let third = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 3,
        pixels: vec![70 * 40 - 1],
        sums: vec![fixed(3.0), fixed(3.0), fixed(3.0)],
        credits: (0..3)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        traced: Some(RayCounts {
            diffuse: 5,
            ..Default::default()
        }),
        counters: Some(WorkerCounters {
            domain_loads: 1,
            domain_load_seconds: 0.25,
            rays_sent: 3,
            idle_seconds: 0.5,
            queue_peak: 12,
            ..Default::default()
        }),
        ..Default::default()
    };
    assert!(w.report(third).await.unwrap());
    let p = get_job(&channel, &id).await.progress.unwrap();
    assert_eq!((p.tiles_done, p.rays_traced), (3, 22));
    assert!(p.eta.is_some(), "an ETA once some tiles are done");

    // Report 2 returns the rest: the job succeeds and the worker is told to finish.
    let second = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        credits: (3..6)
            .map(|t| TileCredit {
                tile: t,
                credit: half,
            })
            .collect(),
        ..Default::default()
    };
    assert!(!w.report(second).await.unwrap(), "the job is over");
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    assert_eq!(job.progress.unwrap().tiles_done, 6);
    let stats = job.stats.unwrap();
    assert_eq!(stats.nonfinite, 1);
    assert_eq!(
        stats.rays.unwrap(),
        RayCounts {
            camera: 10,
            shadow: 7,
            diffuse: 5,
            ..Default::default()
        }
    );
    // The workers' counters: deltas summed, the queue peak the largest.
    assert_eq!(
        (stats.domain_loads, stats.evictions, stats.queue_peak),
        (3, 1, 40)
    );
    assert_eq!((stats.rays_exchanged, stats.rays_forwarded), (33, 4));
    assert_eq!(stats.domain_load_seconds, 0.75);
    assert_eq!(stats.schedule, "dynamic");
    assert_eq!((stats.routing_version, stats.tiles_retried), (1, 0));
    assert!(stats.scheduler_rounds >= 1, "the queue report made a round");
    assert_eq!(stats.workers_detail.len(), 1);
    let d = &stats.workers_detail[0];
    assert_eq!(d.worker_id, w.id);
    assert_eq!((d.domain_loads, d.queue_peak, d.rays_traced), (3, 40, 22));
    assert_eq!((d.idle_seconds, d.evictions), (0.75, 1));
    match w.next().await {
        Command::Finish(r) => assert_eq!(r.job_id, id),
        other => panic!("expected a finish release, got {other:?}"),
    }
    assert_dir_gone(&pkg);
    // Reports for a finished job are told it is over.
    let late = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 4,
        ..Default::default()
    };
    assert!(!w.report(late).await.unwrap());

    // The image holds exactly the sums sent (spp 1: radiance = sum / 2^24).
    let img = RenderServiceClient::new(channel.clone())
        .get_image(GetImageRequest {
            job_id: id.clone(),
            format: ImageFormat::Exr as i32,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((img.width, img.height), (70, 40));
    let (width, px) = read_exr(&img.data);
    assert_eq!(width, 70);
    assert_eq!(px[0], [1.0, 0.5, 1.0]);
    assert_eq!(px[71], [2.0, 0.0, 0.125]);
    assert_eq!(px[70 * 40 - 1], [3.0, 3.0, 3.0]);
    let lit = px.iter().filter(|p| **p != [0.0; 3]).count();
    assert_eq!(lit, 3, "only the reported pixels are lit");
}

/// `JobStats.reports` counts exactly the bytes of the reports the worker sent (each
/// sequence once: a retry of one already applied is not counted again), and the part
/// their AOV fields take.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn report_bytes_are_counted_once_with_their_aov_part() {
    let server = Server::start("report-bytes", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    // 40x20: two tiles.
    let id = submit(
        &channel,
        JobSpec {
            aovs: vec!["albedo".into(), "depth".into()],
            ..spec(40, 20, 1)
        },
    )
    .await;
    let (_, tiles) = w.setup_and_tiles(2).await;
    assert_eq!(tiles.len(), 2);
    let first = ReportContributionsRequest {
        worker_id: w.id.clone(),
        job_id: id.clone(),
        sequence: 1,
        pixels: vec![0, 5],
        sums: vec![fixed(0.5); 6],
        aov_pixels: vec![0, 5, 7],
        aov_sums: vec![1; 24],
        credits: vec![TileCredit {
            tile: 0,
            credit: TILE_CREDIT,
        }],
        ..Default::default()
    };
    let second = ReportContributionsRequest {
        sequence: 2,
        pixels: vec![39],
        sums: vec![fixed(1.0); 3],
        aov_pixels: Vec::new(),
        aov_sums: Vec::new(),
        credits: vec![TileCredit {
            tile: 1,
            credit: TILE_CREDIT,
        }],
        counters: Some(WorkerCounters {
            queue_peak: 3,
            ..Default::default()
        }),
        ..first.clone()
    };
    // The AOV fields (21 and 22: two-byte tags), their lengths (192 bytes: a two-byte
    // length), 4 bytes a pixel and 8 a word.
    let aov_bytes = (2 + 1 + 3 * 4) + (2 + 2 + 24 * 8);
    assert!(w.report(first.clone()).await.unwrap());
    assert!(w.report(first.clone()).await.unwrap(), "a retry");
    let r = get_job(&channel, &id).await.stats.unwrap().reports.unwrap();
    assert_eq!(
        (r.messages, r.bytes, r.aov_bytes),
        (1, first.encoded_len() as u64, aov_bytes)
    );
    assert!(!w.report(second.clone()).await.unwrap(), "the job is over");
    let job = wait_state(&channel, &id, JobState::Succeeded).await;
    let r = job.stats.unwrap().reports.unwrap();
    assert_eq!(
        (r.messages, r.bytes, r.aov_bytes),
        (
            2,
            (first.encoded_len() + second.encoded_len()) as u64,
            aov_bytes
        )
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_and_domains_are_dealt_round_robin_over_two_workers() {
    let server = Server::start("two", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let mut b = FakeWorker::join(channel.clone(), "http://127.0.0.1:7002").await;
    // 100x70: 4 x 3 = 12 tiles, 6 each. Domains left to the coordinator.
    let id = submit(&channel, spec(100, 70, 0)).await;
    let (sa, ta) = a.setup_and_tiles(6).await;
    let (sb, tb) = b.setup_and_tiles(6).await;
    assert_eq!(sa, sb, "every worker of a job gets the same setup");
    let routing = sa.routing.unwrap();
    let ids: Vec<&str> = routing
        .workers
        .iter()
        .map(|w| w.worker_id.as_str())
        .collect();
    assert_eq!(ids.len(), 2);
    assert!(ids.contains(&a.id.as_str()) && ids.contains(&b.id.as_str()));
    assert!(sa.domain_count >= 1);
    assert_eq!(routing.routes.len(), sa.domain_count as usize);
    for r in &routing.routes {
        assert_eq!(r.worker_id, ids[r.domain as usize % 2]);
    }
    let job = get_job(&channel, &id).await;
    assert_eq!(job.spec.unwrap().domains, sa.domain_count);
    let first = if ids[0] == a.id { &ta } else { &tb };
    let second = if ids[0] == a.id { &tb } else { &ta };
    assert!(first.iter().all(|t| t.index % 2 == 0));
    assert!(second.iter().all(|t| t.index % 2 == 1));
    // Both workers return their tiles' credit: the job succeeds once both have.
    for (w, tiles) in [(&mut a, &ta), (&mut b, &tb)] {
        let r = ReportContributionsRequest {
            job_id: id.clone(),
            sequence: 1,
            credits: tiles
                .iter()
                .map(|t| TileCredit {
                    tile: t.index,
                    credit: t.credit,
                })
                .collect(),
            ..Default::default()
        };
        w.report(r).await.unwrap();
    }
    wait_state(&channel, &id, JobState::Succeeded).await;
    assert!(matches!(a.next().await, Command::Finish(_)));
    assert!(matches!(b.next().await, Command::Finish(_)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_failure_fails_the_job_and_cancels_it_everywhere() {
    let server = Server::start("fail", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(32, 32, 1)).await;
    let (setup, _) = w.setup_and_tiles(1).await;
    let pkg = PathBuf::from(setup.package_path);
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        failure: "domain 0: checksum mismatch".into(),
        ..Default::default()
    };
    assert!(!w.report(r).await.unwrap());
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains("domain 0: checksum mismatch") && err.contains(&w.id),
        "{err}"
    );
    match w.next().await {
        Command::Cancel(r) => {
            assert_eq!(r.job_id, id);
            assert!(r.reason.contains("checksum mismatch"), "{}", r.reason);
        }
        other => panic!("expected a cancel release, got {other:?}"),
    }
    assert_dir_gone(&pkg);
    let again = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 2,
        ..Default::default()
    };
    assert!(!w.report(again).await.unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn credit_beyond_a_tiles_start_fails_the_job() {
    let server = Server::start("overdraw", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(64, 32, 1)).await;
    w.setup_and_tiles(2).await;
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![
            TileCredit {
                tile: 1,
                credit: TILE_CREDIT,
            },
            TileCredit { tile: 1, credit: 1 },
        ],
        ..Default::default()
    };
    assert!(!w.report(r).await.unwrap());
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains("tile 1") && err.contains("counted twice"),
        "{err}"
    );
    assert!(matches!(w.next().await, Command::Cancel(_)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_sends_a_cancel_release_and_later_reports_are_inactive() {
    let server = Server::start("cancel", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, spec(64, 64, 2)).await;
    let (setup, _) = w.setup_and_tiles(4).await;
    let r = RenderServiceClient::new(channel.clone())
        .cancel_job(CancelJobRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        r.job.unwrap().progress.unwrap().state(),
        JobState::Cancelled
    );
    match w.next().await {
        Command::Cancel(r) => assert_eq!(r.job_id, id),
        other => panic!("expected a cancel release, got {other:?}"),
    }
    assert_dir_gone(Path::new(&setup.package_path));
    let late = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![TileCredit {
            tile: 0,
            credit: TILE_CREDIT,
        }],
        ..Default::default()
    };
    assert!(!w.report(late).await.unwrap());
    assert_eq!(
        get_job(&channel, &id).await.progress.unwrap().state(),
        JobState::Cancelled
    );
    let missing = w
        .client
        .get_routing_table(GetRoutingTableRequest { job_id: id.clone() })
        .await
        .unwrap_err();
    assert_eq!(missing.code(), Code::NotFound);
    // An unknown job is inactive too.
    let unknown = ReportContributionsRequest {
        job_id: "no-such-job".into(),
        sequence: 1,
        ..Default::default()
    };
    assert!(!w.report(unknown).await.unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registration_refuses_mismatches_and_heartbeats_ask_strangers_to_reregister() {
    let server = Server::start("register", slow_heartbeat()).await;
    let mut c = ClusterServiceClient::new(server.channel().await);
    let old = RegisterWorkerRequest {
        version: "0.0.0-other".into(),
        ..register_request("http://127.0.0.1:7001")
    };
    let e = c.register_worker(old).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().contains("0.0.0-other") && e.message().contains(VERSION));
    let format = RegisterWorkerRequest {
        record_format: dray_proto::RAY_RECORD_FORMAT + 1,
        ..register_request("http://127.0.0.1:7001")
    };
    let e = c.register_worker(format).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    assert!(e.message().starts_with("record_format:"), "{}", e.message());
    let e = c
        .register_worker(register_request("nowhere"))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    for bad in ["http://", "https:///x", ""] {
        let e = c.register_worker(register_request(bad)).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{bad:?}");
    }
    // A short host name is fine.
    c.register_worker(register_request("http://w"))
        .await
        .unwrap();

    let hb = |id: &str| HeartbeatRequest {
        worker_id: id.into(),
        memory_used_bytes: 0,
        rays_queued: 0,
    };
    let r = c.heartbeat(hb("w1-00000000")).await.unwrap().into_inner();
    assert!(r.reregister, "an unknown id must re-register");
    let reg = c
        .register_worker(register_request("http://127.0.0.1:7001"))
        .await
        .unwrap()
        .into_inner();
    let id = reg.worker_id;
    let r = c
        .heartbeat(support::as_member(&reg.member_token, hb(&id)))
        .await
        .unwrap()
        .into_inner();
    assert!(!r.reregister);
    // Without the worker's own secret, or with another worker's, nobody speaks for it.
    let other = c
        .register_worker(register_request("http://127.0.0.1:7002"))
        .await
        .unwrap()
        .into_inner();
    for req in [
        tonic::Request::new(hb(&id)),
        support::as_member(&other.member_token, hb(&id)),
    ] {
        let e = c.heartbeat(req).await.unwrap_err();
        assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    }
    let e = c
        .report_contributions(support::as_member(
            &other.member_token,
            dray_proto::v1::ReportContributionsRequest {
                worker_id: id.clone(),
                job_id: "job-1".into(),
                ..Default::default()
            },
        ))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    // A peer pass is handed only to the worker it names, and proves exactly that worker
    // to exactly that peer (which checks it with its own secret).
    let ask = |peer: &str| dray_proto::v1::GetPeerPassRequest {
        worker_id: id.clone(),
        peer_id: peer.into(),
    };
    let pass = c
        .get_peer_pass(support::as_member(&reg.member_token, ask(&other.worker_id)))
        .await
        .unwrap()
        .into_inner()
        .pass;
    assert!(dray_net::peer_pass::verify_peer_pass(
        &other.member_token,
        &id,
        &pass
    ));
    assert!(!dray_net::peer_pass::verify_peer_pass(
        &other.member_token,
        &other.worker_id,
        &pass
    ));
    assert!(!dray_net::peer_pass::verify_peer_pass(
        &reg.member_token,
        &id,
        &pass
    ));
    for req in [
        tonic::Request::new(ask(&other.worker_id)),
        support::as_member(&other.member_token, ask(&other.worker_id)),
    ] {
        let e = c.get_peer_pass(req).await.unwrap_err();
        assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    }
    let e = c
        .get_peer_pass(support::as_member(&reg.member_token, ask("stranger")))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    // Watching assignments needs a registered id.
    let e = c
        .watch_assignments(WatchAssignmentsRequest {
            worker_id: "stranger".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
}

/// A member that is alive (its heartbeats are fine) but never traces would hold its
/// job forever: with no credit back for the stall timeout, the job fails naming its
/// workers, and they are told to drop it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_without_progress_fails_after_the_stall_timeout() {
    let server = Server::start_full(
        "stall",
        slow_heartbeat(),
        Default::default(),
        Some(Duration::from_millis(300)),
        &std::env::temp_dir(),
    )
    .await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7010").await;
    let id = submit(&channel, spec(32, 32, 1)).await;
    w.setup_and_tiles(1).await;
    // It never reports.
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.starts_with("no progress for")
            && err.contains(&w.id)
            && err.contains("--stall-timeout"),
        "{err}"
    );
    // The worker is still a member (it was never silent), and may take the next job.
    assert!(server.coordinator.cluster().membership.get(&w.id).is_some());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_only_worker_goes_silent_fails_naming_it() {
    let server = Server::start(
        "lost",
        HeartbeatConfig {
            interval: Duration::from_millis(50),
            timeout: Duration::from_millis(300),
        },
    )
    .await;
    let channel = server.channel().await;
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7009").await;
    let id = submit(&channel, spec(32, 32, 1)).await;
    w.setup_and_tiles(1).await;
    // The worker never heartbeats: within ~1.25 timeouts it is dropped, and with no
    // worker left to trace its tiles again, the job fails.
    let job = wait_state(&channel, &id, JobState::Failed).await;
    let err = job.progress.unwrap().error;
    assert!(
        err.contains(&w.id)
            && err.contains("http://127.0.0.1:7009")
            && err.contains("no worker is left"),
        "{err}"
    );
    let r = w
        .client
        .heartbeat(HeartbeatRequest {
            worker_id: w.id.clone(),
            memory_used_bytes: 0,
            rays_queued: 0,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(r.reregister);
    // Its assignment stream ends: it is no longer a member (it learns to drop its jobs
    // from the heartbeat answer).
    let end = tokio::time::timeout(PATIENCE, w.stream.message())
        .await
        .expect("the dropped worker's stream did not end")
        .unwrap();
    assert!(end.is_none(), "unexpected command {end:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_package_is_used_as_it_is_and_kept() {
    let root =
        std::env::temp_dir().join(format!("dray-cluster-test-{}-pkgroot", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    struct Cleanup(PathBuf);
    impl Drop for Cleanup {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
    let _cleanup = Cleanup(root.clone());
    let scene = dray_scene::load("cornell").unwrap();
    let pkg = root.join("cornell-pkg");
    dray_scene::partition::write_scene_package(
        &pkg,
        &scene,
        &dray_scene::partition::LayoutSpec::GridCount(2),
    )
    .unwrap();
    let server = Server::start_in("pkg", slow_heartbeat(), &root).await;
    let channel = server.channel().await;
    let mut render = RenderServiceClient::new(channel.clone());
    let package_spec = JobSpec {
        scene: "cornell-pkg".into(),
        ..spec(32, 32, 0)
    };

    // Without workers a package cannot render (the in-process path needs a whole mesh).
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(package_spec.clone()),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition, "{}", e.message());
    // A package cannot be moved.
    let moved = JobSpec {
        translate: Some(dray_proto::v1::Vec3 {
            x: 1.0,
            y: 0.0,
            z: 0.0,
        }),
        ..package_spec.clone()
    };
    let e = render
        .submit_job(SubmitJobRequest { spec: Some(moved) })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("translate:"), "{}", e.message());
    // A directory that is not a package is refused.
    std::fs::create_dir_all(root.join("empty")).unwrap();
    let e = render
        .submit_job(SubmitJobRequest {
            spec: Some(JobSpec {
                scene: "empty".into(),
                ..spec(32, 32, 0)
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);

    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let id = submit(&channel, package_spec).await;
    let (setup, tiles) = w.setup_and_tiles(1).await;
    assert_eq!(
        PathBuf::from(&setup.package_path),
        pkg.canonicalize().unwrap()
    );
    assert_eq!(setup.domain_count, 2);
    let s = setup.spec.unwrap();
    assert_eq!((s.domains, s.layout.as_str()), (2, "grid"));
    assert_eq!(s.camera.as_deref(), Some("0"));
    let manifest = std::fs::read(pkg.join("manifest.json")).unwrap();
    assert_eq!(setup.package_checksum, package_checksum(&manifest));
    let r = ReportContributionsRequest {
        job_id: id.clone(),
        sequence: 1,
        credits: vec![TileCredit {
            tile: tiles[0].index,
            credit: TILE_CREDIT,
        }],
        ..Default::default()
    };
    w.report(r).await.unwrap();
    wait_state(&channel, &id, JobState::Succeeded).await;
    assert!(
        pkg.join("manifest.json").is_file(),
        "the user's package must not be removed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cluster_service_is_listed_and_healthy_and_shutdown_ends_worker_streams() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let coordinator = Coordinator::new(&std::env::temp_dir(), 1).unwrap();
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let mut task = tokio::spawn(dray_coordinator::serve(listener, coordinator, async {
        rx.await.ok();
    }));
    struct Abort(tokio::task::AbortHandle);
    impl Drop for Abort {
        fn drop(&mut self) {
            self.0.abort();
        }
    }
    let _abort = Abort(task.abort_handle());
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();

    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let h = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "dray.v1.ClusterService".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        h.status(),
        tonic_health::pb::health_check_response::ServingStatus::Serving
    );
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let mut reflect = ServerReflectionClient::new(channel.clone());
    let req = tonic_reflection::pb::v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = reflect
        .server_reflection_info(tokio_stream::iter([req]))
        .await
        .unwrap()
        .into_inner();
    match replies.message().await.unwrap().unwrap().message_response {
        Some(MessageResponse::ListServicesResponse(l)) => {
            let names: Vec<String> = l.service.into_iter().map(|s| s.name).collect();
            for want in ["dray.v1.RenderService", "dray.v1.ClusterService"] {
                assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
            }
        }
        other => panic!("unexpected reflection reply {other:?}"),
    }
    drop(replies);
    drop(reflect);

    // A worker's stream is open; shutting down must still finish.
    let mut w = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    tx.send(()).unwrap();
    let end = tokio::time::timeout(PATIENCE, w.stream.message())
        .await
        .expect("the stream did not end on shutdown");
    assert!(matches!(end, Ok(None)), "{end:?}");
    drop(w);
    drop(health);
    drop(channel);
    tokio::time::timeout(PATIENCE, &mut task)
        .await
        .expect("serve did not return after shutdown")
        .unwrap()
        .unwrap();
}
