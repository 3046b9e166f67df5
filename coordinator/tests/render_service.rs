//! The coordinator's RenderService on a live in-process server, through the generated
//! client: a job renders to the same PNG bytes as the single-process path `dray render`
//! uses; invalid jobs are INVALID_ARGUMENT naming the field and the server keeps serving;
//! a large job can be cancelled mid-run; reflection lists the service.

use std::time::Duration;

use dray_coordinator::Coordinator;
use dray_core::bvh::Accel;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetJobRequest, ImageFormat, JobSpec, JobState,
    ListJobsRequest, SubmitJobRequest, WatchJobRequest,
};
use tonic::Code;
use tonic::transport::Channel;
use tonic_reflection::pb::v1::ServerReflectionRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

/// A server on a free port; stopped when dropped, even if the test panics.
struct Server {
    addr: std::net::SocketAddr,
    /// A handle on the served coordinator (clones share its state).
    coordinator: Coordinator,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    async fn start(root: &std::path::Path) -> Server {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let coordinator = Coordinator::new(root, 0).unwrap();
        let served = coordinator.clone();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            dray_coordinator::serve(listener, served, async {
                rx.await.ok();
            })
            .await
            .unwrap();
        });
        Server {
            addr,
            coordinator,
            stop: Some(tx),
            task,
        }
    }

    async fn channel(&self) -> Channel {
        tonic::transport::Endpoint::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        self.task.abort();
    }
}

fn cornell(width: u32, height: u32, spp: u32) -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width,
        height,
        spp,
        ..Default::default()
    }
}

async fn submit(
    c: &mut RenderServiceClient<Channel>,
    spec: JobSpec,
) -> Result<String, tonic::Status> {
    c.submit_job(SubmitJobRequest { spec: Some(spec) })
        .await
        .map(|r| r.into_inner().job_id)
}

/// Watch to the end; returns the final state and the number of messages.
async fn watch(c: &mut RenderServiceClient<Channel>, id: &str) -> (JobState, usize) {
    let mut s = c
        .watch_job(WatchJobRequest {
            job_id: id.into(),
            min_interval: Some(prost_types::Duration {
                seconds: 0,
                nanos: 20_000_000,
            }),
        })
        .await
        .unwrap()
        .into_inner();
    let mut last = JobState::Unspecified;
    let mut n = 0;
    while let Some(p) = s.message().await.unwrap() {
        n += 1;
        last = p.state();
        assert!(p.tiles_done <= p.tiles_total);
        // Every message carries the statistics so far (read a moment after the
        // progress, so they may count a few more rays, never fewer).
        let stats = p.stats.expect("WatchJob carries the job's statistics");
        let rays = stats.rays.map_or(0, |r| {
            r.camera + r.shadow + r.reflection + r.refraction + r.diffuse + r.ambient_occlusion
        });
        assert!(
            rays >= p.rays_traced,
            "{rays} rays in the stats, {} in progress",
            p.rays_traced
        );
    }
    (last, n)
}

/// The PNG `dray render cornell --width W --height H --spp S` writes, made by the same
/// core calls and written by the same `Film::write_png`.
fn reference_png(width: u32, height: u32, spp: u32) -> Vec<u8> {
    let scene = dray_scene::load("cornell").unwrap();
    let environment = dray_scene::effects::default_environment(&scene);
    let effects = dray_scene::effects::analyze(&scene, environment);
    let camera = match scene.cameras.first() {
        Some(c) => c.clone(),
        None => {
            let (lo, hi) = scene.bounds();
            dray_core::camera::Camera::framing(lo, hi, width as f32 / height as f32)
        }
    };
    let settings = RenderSettings {
        width,
        height,
        spp,
        integrator: IntegratorKind::Path,
        max_depth: 5,
        seed: 0,
        environment,
        effects,
        ao_samples: 16,
        ao_distance: f32::INFINITY,
        lighting: Default::default(),
        clamp_indirect: None,
        aovs: Default::default(),
    };
    let integrator = Integrator::new(&scene, camera, settings);
    let accel = Accel::build(&scene.mesh);
    let out = dray_core::render::render(&integrator, &accel, 1, &|_, _| {}).unwrap();
    let path = std::env::temp_dir().join(format!("dray-coord-ref-{}.png", std::process::id()));
    out.film.write_png(&path, spp, 1.0).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    bytes
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_service_end_to_end() {
    // The scene root is a folder of its own, with a file beside it (outside the root).
    let base = std::env::temp_dir().join(format!("dray-render-service-{}", std::process::id()));
    let root = base.join("root");
    std::fs::create_dir_all(&root).unwrap();
    let outside_file = base.join("outside.gltf");
    std::fs::write(&outside_file, "{}").unwrap();
    let server = Server::start(&root).await;
    let channel = server.channel().await;
    let mut c = RenderServiceClient::new(channel.clone()).max_decoding_message_size(64 << 20);

    // Reflection lists the service, as `grpcurl -plaintext ADDR list` shows.
    let mut reflect = ServerReflectionClient::new(channel.clone());
    let req = ServerReflectionRequest {
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
            for want in ["dray.v1.RenderService", "grpc.health.v1.Health"] {
                assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
            }
        }
        other => panic!("unexpected reflection reply {other:?}"),
    }

    // A small job: watch to SUCCEEDED, fetch the PNG, compare with the embedded path.
    // Exposure 0 with no tone curve is the encoding of dray before automatic exposure,
    // byte for byte.
    let id = submit(&mut c, cornell(64, 64, 4)).await.unwrap();
    let (state, msgs) = watch(&mut c, &id).await;
    assert_eq!(state, JobState::Succeeded);
    assert!(msgs >= 1);
    let img = c
        .get_image(GetImageRequest {
            job_id: id.clone(),
            format: ImageFormat::Png as i32,
            exposure: Some(0.0),
            tonemap: "clamp".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(img.content_type, "image/png");
    assert_eq!((img.width, img.height), (64, 64));
    assert!(
        img.data == reference_png(64, 64, 4),
        "PNG differs from dray render's"
    );
    // Nothing said: automatic exposure and the default curve, another image.
    let auto = c
        .get_image(GetImageRequest {
            job_id: id.clone(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(auto.content_type, "image/png");
    assert!(auto.data != img.data, "the default is the fixed encoding");
    // A bad exposure or curve is INVALID_ARGUMENT naming the field.
    for (exposure, tonemap, field) in [
        (Some(f32::INFINITY), "", "exposure: "),
        (None, "filmic", "tonemap: "),
    ] {
        let e = c
            .get_image(GetImageRequest {
                job_id: id.clone(),
                exposure,
                tonemap: tonemap.into(),
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        assert!(e.message().starts_with(field), "{}", e.message());
    }
    let exr = c
        .get_image(GetImageRequest {
            job_id: id.clone(),
            format: ImageFormat::Exr as i32,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(&exr.data[..4], &[0x76, 0x2f, 0x31, 0x01], "EXR magic");
    let job = c
        .get_job(GetJobRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap();
    let p = job.progress.unwrap();
    assert_eq!(p.tiles_done, p.tiles_total);
    assert!(p.rays_traced >= 64 * 64 * 4);
    assert_eq!(job.spec.unwrap().integrator, "path");

    // Invalid jobs: INVALID_ARGUMENT naming the field.
    // A file that exists but lies outside the scene root.
    let outside = outside_file.to_string_lossy().into_owned();
    let cases: Vec<(JobSpec, &str)> = vec![
        (cornell(0, 64, 4), "width"),
        (cornell(64, 20000, 4), "height"),
        (cornell(64, 64, 0), "spp"),
        (cornell(64, 64, 1 << 20), "spp"),
        (
            JobSpec {
                integrator: "photon".into(),
                ..cornell(8, 8, 1)
            },
            "integrator",
        ),
        (
            JobSpec {
                scene: "no-such-scene".into(),
                ..cornell(8, 8, 1)
            },
            "scene",
        ),
        (
            JobSpec {
                scene: outside,
                ..cornell(8, 8, 1)
            },
            "scene",
        ),
        (
            JobSpec {
                scene: "../../../../etc/hostname".into(),
                ..cornell(8, 8, 1)
            },
            "scene",
        ),
        (
            JobSpec {
                effects: "+sparkles".into(),
                ..cornell(8, 8, 1)
            },
            "effects",
        ),
        (
            JobSpec {
                env: Some(dray_proto::v1::Rgb {
                    r: f32::NAN,
                    g: 0.0,
                    b: 0.0,
                }),
                ..cornell(8, 8, 1)
            },
            "env",
        ),
        (
            JobSpec {
                noise_threshold: Some(0.0),
                ..cornell(8, 8, 64)
            },
            "noise_threshold",
        ),
        (
            JobSpec {
                noise_threshold: Some(f32::NAN),
                ..cornell(8, 8, 64)
            },
            "noise_threshold",
        ),
        (
            // One pass leaves no pass end to stop a tile at.
            JobSpec {
                noise_threshold: Some(0.01),
                passes: "one".into(),
                ..cornell(8, 8, 64)
            },
            "noise_threshold",
        ),
    ];
    for (spec, field) in cases {
        let err = submit(&mut c, spec).await.unwrap_err();
        assert_eq!(err.code(), Code::InvalidArgument, "{field}: {err:?}");
        assert!(
            err.message().starts_with(&format!("{field}:")),
            "{field}: {}",
            err.message()
        );
    }
    // Unknown ids are NOT_FOUND.
    let err = c
        .get_job(GetJobRequest {
            job_id: "nope".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::NotFound);

    // A large job: cancel it mid-run; GetImage is FAILED_PRECONDITION.
    let big = submit(&mut c, cornell(512, 512, 1024)).await.unwrap();
    for attempt in 0.. {
        assert!(attempt < 6000, "the large job never started running");
        let j = c
            .get_job(GetJobRequest {
                job_id: big.clone(),
            })
            .await
            .unwrap()
            .into_inner()
            .job
            .unwrap();
        if j.progress.unwrap().state() == JobState::Running {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let err = c
        .get_image(GetImageRequest {
            job_id: big.clone(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition);
    let after = c
        .cancel_job(CancelJobRequest {
            job_id: big.clone(),
        })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap();
    assert_eq!(after.progress.unwrap().state(), JobState::Cancelled);
    let (state, _) = watch(&mut c, &big).await;
    assert_eq!(state, JobState::Cancelled);

    // The server still serves the next valid job once the cancelled one has let go.
    let next = submit(&mut c, cornell(32, 32, 1)).await.unwrap();
    let (state, _) = tokio::time::timeout(Duration::from_secs(120), watch(&mut c, &next))
        .await
        .expect("the job after a cancelled one finishes");
    assert_eq!(state, JobState::Succeeded);

    let listed = c
        .list_jobs(ListJobsRequest {
            page_size: 2,
            page_token: String::new(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<&str> = listed.jobs.iter().map(|j| j.job_id.as_str()).collect();
    assert_eq!(ids, [next.as_str(), big.as_str()], "newest first");
    assert_eq!(listed.next_page_token, "2");
    drop(server);
    let _ = std::fs::remove_dir_all(&base);
}

/// A scene that must be loaded is prepared off the request path: SubmitJob answers with
/// the job PREPARING; what loading finds wrong fails the job with the field named; and
/// CancelJob ends a job whose scene is still loading at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scenes_load_after_submit_and_a_loading_job_can_be_cancelled() {
    let root = std::env::temp_dir();
    let server = Server::start(&root).await;
    let mut c = RenderServiceClient::new(server.channel().await);
    let state = |j: &dray_proto::v1::Job| j.progress.as_ref().map(|p| p.state());

    // Found only once the scene is loaded: the job fails, naming the field.
    let id = submit(
        &mut c,
        JobSpec {
            camera: Some("no-such-camera".into()),
            ..cornell(8, 8, 1)
        },
    )
    .await
    .unwrap();
    let (end, _) = watch(&mut c, &id).await;
    assert_eq!(end, JobState::Failed);
    let job = get(&mut c, &id).await;
    let error = job.progress.unwrap().error;
    assert!(error.starts_with("camera:"), "{error}");

    // An eight-million-triangle soup takes seconds to make: SubmitJob does not wait for
    // it, and CancelJob stops it part-way.
    let id = submit(
        &mut c,
        JobSpec {
            scene: "soup:8000000".into(),
            ..cornell(8, 8, 1)
        },
    )
    .await
    .unwrap();
    let job = get(&mut c, &id).await;
    assert_eq!(state(&job), Some(JobState::Preparing));
    let after = c
        .cancel_job(CancelJobRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap();
    assert_eq!(state(&after), Some(JobState::Cancelled));
    let (end, _) = watch(&mut c, &id).await;
    assert_eq!(end, JobState::Cancelled);
    // The load stops at its next chunk of triangles, and what it made is dropped (a
    // limit that only catches a hang: no load is left running, and it was stopped, not
    // finished).
    let mut loads = server.coordinator.scene_loads();
    for _ in 0..2400 {
        if loads.0 == 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        loads = server.coordinator.scene_loads();
    }
    assert_eq!(
        loads,
        (0, 1),
        "(loads running, loads stopped by a cancel): the cancelled job's load must stop"
    );

    // The server goes on: the next job loads and renders.
    let next = submit(&mut c, cornell(16, 16, 1)).await.unwrap();
    assert_eq!(watch(&mut c, &next).await.0, JobState::Succeeded);
    drop(server);
}

async fn get(c: &mut RenderServiceClient<Channel>, id: &str) -> dray_proto::v1::Job {
    c.get_job(GetJobRequest { job_id: id.into() })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap()
}

/// A spec with `frames` is a job group over gRPC: one job per frame, each with its time
/// and its place in the group, ListJobs lists the group alone; bad ranges and rates are
/// INVALID_ARGUMENT naming the field, and nothing is accepted then.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_make_a_job_group_and_bad_ranges_are_refused() {
    let root = std::env::temp_dir();
    let server = Server::start(&root).await;
    let mut c = RenderServiceClient::new(server.channel().await);
    let before = server.coordinator.job_count();
    for (frames, fps, words) in [
        (
            "5..1",
            Some(24.0),
            "frames: \"5..1\": the range ends before it starts",
        ),
        ("1..", Some(24.0), "frames: \"1..\" is not a frame range"),
        ("1..3:0", Some(24.0), "the step must be at least 1"),
        (
            "1..3",
            Some(0.0),
            "fps: the frame rate must be finite and above 0",
        ),
        ("1..3", None, "fps: required with frames"),
    ] {
        let spec = JobSpec {
            frames: frames.into(),
            fps,
            ..cornell(8, 8, 1)
        };
        let e = submit(&mut c, spec).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{frames} {fps:?}");
        assert!(e.message().contains(words), "{frames}: {}", e.message());
    }
    assert_eq!(
        server.coordinator.job_count(),
        before,
        "a refused group left jobs"
    );

    let r = c
        .submit_job(SubmitJobRequest {
            spec: Some(JobSpec {
                frames: "2..6:2".into(),
                fps: Some(8.0),
                ..cornell(8, 8, 1)
            }),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.job_ids.len(), 3);
    assert_eq!(r.job_id, r.job_ids[0]);
    for (id, (frame, time)) in r.job_ids.iter().zip([(2, 0.25), (4, 0.5), (6, 0.75)]) {
        assert_eq!(watch(&mut c, id).await.0, JobState::Succeeded);
        let job = get(&mut c, id).await;
        let g = job.group.expect("a frame names its group");
        assert_eq!((g.group_id.as_str(), g.frame), (r.group_id.as_str(), frame));
        let spec = job.spec.unwrap();
        assert_eq!(spec.time, Some(time));
        assert!(spec.frames.is_empty() && spec.fps.is_none());
    }
    let listed = c
        .list_jobs(ListJobsRequest {
            group_id: r.group_id.clone(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let mut ids: Vec<String> = listed.jobs.into_iter().map(|j| j.job_id).collect();
    ids.reverse();
    assert_eq!(ids, r.job_ids, "ListJobs of the group, newest first");
    // A lone job is in no group.
    let lone = submit(&mut c, cornell(8, 8, 1)).await.unwrap();
    assert!(get(&mut c, &lone).await.group.is_none());
    drop(server);
}
