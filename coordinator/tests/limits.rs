//! Admission and lifetime limits on a live in-process server (docs/security.md "Hostile
//! requests"): a job whose
//! estimated memory exceeds `max_job_bytes` is refused with RESOURCE_EXHAUSTED before
//! anything is prepared; beyond `max_jobs` jobs queued or running, SubmitJob refuses
//! more; and a finished job's image is dropped once newer jobs push it out of
//! `keep_finished`, after which GetImage says so (and GetJob still lists the job).

use dray_coordinator::Coordinator;
use dray_coordinator::jobs::Retention;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetJobRequest, ImageFormat, JobSpec, JobState,
    SubmitJobRequest, WatchJobRequest,
};
use tonic::transport::Channel;

/// A limits-configured coordinator on a free port; stopped when dropped.
struct Server {
    addr: std::net::SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    async fn start(max_jobs: usize, max_job_bytes: u64, keep_finished: usize) -> Server {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let coordinator = Coordinator::new(&std::env::temp_dir(), 1)
            .unwrap()
            .with_admission(
                max_jobs,
                max_job_bytes,
                Retention {
                    keep_finished,
                    ttl: None,
                    max_bytes: None,
                },
            );
        Server::serve(listener, coordinator)
    }

    /// Serve `coordinator` on `listener` until dropped.
    fn serve(listener: tokio::net::TcpListener, coordinator: Coordinator) -> Server {
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            dray_coordinator::serve(listener, coordinator, async {
                rx.await.ok();
            })
            .await
            .unwrap();
        });
        Server {
            addr,
            stop: Some(tx),
            task,
        }
    }

    async fn client(&self) -> RenderServiceClient<Channel> {
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap();
        RenderServiceClient::new(channel).max_decoding_message_size(usize::MAX)
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

async fn wait_end(c: &mut RenderServiceClient<Channel>, id: &str) -> JobState {
    let mut s = c
        .watch_job(WatchJobRequest {
            job_id: id.into(),
            min_interval: None,
        })
        .await
        .unwrap()
        .into_inner();
    let mut last = JobState::Unspecified;
    while let Some(p) = s.message().await.unwrap() {
        last = p.state();
    }
    last
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_estimated_above_the_memory_limit_is_refused() {
    let server = Server::start(8, 1 << 20, 10).await;
    let mut c = server.client().await;
    // 1024 x 1024 pixels need 36 MiB of film alone.
    let e = submit(&mut c, cornell(1024, 1024, 1)).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("--max-job-bytes"), "{}", e.message());
    // A small one is accepted and runs.
    let id = submit(&mut c, cornell(32, 24, 1)).await.unwrap();
    assert_eq!(wait_end(&mut c, &id).await, JobState::Succeeded);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_procedural_scene_too_large_for_the_limit_is_refused_before_it_is_made() {
    // 8 GiB: a 100M-triangle soup is within the generators' cap but needs ~75 GiB.
    let server = Server::start(8, 8 << 30, 10).await;
    let mut c = server.client().await;
    for scene in [
        "soup:100000000",
        "grid:spheres:1000:10x10x10",
        "iso:gyroid:2048",
    ] {
        let spec = JobSpec {
            scene: scene.into(),
            ..cornell(16, 16, 1)
        };
        let e = submit(&mut c, spec).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{scene}: {e:?}");
        assert!(e.message().contains("--max-job-bytes"), "{}", e.message());
    }
    // A procedural scene that fits is made and rendered.
    let spec = JobSpec {
        scene: "soup:1000".into(),
        ..cornell(16, 16, 1)
    };
    let id = submit(&mut c, spec).await.unwrap();
    assert_eq!(wait_end(&mut c, &id).await, JobState::Succeeded);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_never_echo_an_unbounded_field() {
    let server = Server::start(8, 1 << 40, 10).await;
    let mut c = server.client().await;
    let huge = "x".repeat(1 << 20);
    type Set = fn(&mut JobSpec, String);
    let fields: [(&str, Set); 4] = [
        ("scene", |s, v| s.scene = v),
        ("integrator", |s, v| s.integrator = v),
        ("camera", |s, v| s.camera = Some(v)),
        ("effects", |s, v| s.effects = v),
    ];
    for (field, set) in fields {
        let mut spec = cornell(16, 16, 1);
        set(&mut spec, huge.clone());
        let e = submit(&mut c, spec).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{field}");
        assert!(e.message().starts_with(field), "{field}: {}", e.message());
        assert!(
            e.message().len() < 200,
            "{field}: {} bytes",
            e.message().len()
        );
    }
    let e = c.get_job(GetJobRequest { job_id: huge }).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    assert!(e.message().len() < 200, "{} bytes", e.message().len());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn beyond_max_jobs_submit_is_refused_until_one_ends() {
    let server = Server::start(1, 1 << 40, 10).await;
    let mut c = server.client().await;
    // A long job holds the one place.
    let long = submit(&mut c, cornell(128, 128, 1 << 11)).await.unwrap();
    let e = submit(&mut c, cornell(16, 16, 1)).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("--max-jobs"), "{}", e.message());
    c.cancel_job(CancelJobRequest {
        job_id: long.clone(),
    })
    .await
    .unwrap();
    assert_eq!(wait_end(&mut c, &long).await, JobState::Cancelled);
    let id = submit(&mut c, cornell(16, 16, 1)).await.unwrap();
    assert_eq!(wait_end(&mut c, &id).await, JobState::Succeeded);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_images_beyond_keep_finished_are_dropped_and_get_image_says_so() {
    let server = Server::start(8, 1 << 40, 1).await;
    let mut c = server.client().await;
    let first = submit(&mut c, cornell(16, 16, 1)).await.unwrap();
    assert_eq!(wait_end(&mut c, &first).await, JobState::Succeeded);
    let image = |id: &str| GetImageRequest {
        job_id: id.into(),
        format: ImageFormat::Png as i32,
        ..Default::default()
    };
    assert!(c.get_image(image(&first)).await.is_ok());
    let second = submit(&mut c, cornell(16, 16, 1)).await.unwrap();
    assert_eq!(wait_end(&mut c, &second).await, JobState::Succeeded);
    // Only the newest finished job keeps its image.
    let e = c.get_image(image(&first)).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound, "{e:?}");
    assert!(
        e.message().contains("dropped") && e.message().contains("--keep-finished"),
        "{}",
        e.message()
    );
    assert!(c.get_image(image(&second)).await.is_ok());
    // The job itself is still listed.
    let job = c
        .get_job(GetJobRequest { job_id: first })
        .await
        .unwrap()
        .into_inner()
        .job
        .unwrap();
    assert_eq!(job.progress.unwrap().state(), JobState::Succeeded);
}

/// docs/security.md "Hardening, second round", item 8: finished images were kept without
/// regard to `--max-job-bytes`
/// (+84 MB per finished 2048² job, 1.1 GB after 12; only `--keep-finished` bounded
/// them). Kept images now add up to at most the byte budget, `--max-job-bytes` by
/// default: here 16 MiB, and each 512² image holds 6 MiB of sums.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_images_are_kept_within_a_byte_budget() {
    let server = Server::start(8, 16 << 20, 100).await;
    let mut c = server.client().await;
    let image = |id: &str| GetImageRequest {
        job_id: id.into(),
        format: ImageFormat::Png as i32,
        ..Default::default()
    };
    let mut ids = Vec::new();
    for _ in 0..3 {
        let id = submit(&mut c, cornell(512, 512, 1)).await.unwrap();
        assert_eq!(wait_end(&mut c, &id).await, JobState::Succeeded);
        ids.push(id);
    }
    // 3 x 6 MiB > 16 MiB: the oldest image went, the two newest stay.
    let e = c.get_image(image(&ids[0])).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound, "{e:?}");
    assert!(
        e.message().contains("dropped") && e.message().contains("--keep-finished-bytes"),
        "{}",
        e.message()
    );
    for id in &ids[1..] {
        assert!(c.get_image(image(id)).await.is_ok(), "{id}");
    }
}

/// A job stored by a coordinator with a larger `--max-job-bytes` (or a file that grew
/// since) is held to the limits of the coordinator that resumes it (issue 45, item 5: a
/// stored `soup:100000000` aborted the coordinator on every start). The job fails,
/// naming the limit; the coordinator goes on serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stored_job_beyond_the_limits_fails_on_resume_instead_of_running() {
    use dray_coordinator::store::{JobStore, Op};
    let dir = tempfile::tempdir().unwrap();
    {
        let (store, _) = JobStore::open(dir.path()).unwrap();
        store.post(Op::Insert {
            id: "huge".into(),
            spec: JobSpec {
                scene: "soup:100000000".into(),
                ..cornell(16, 16, 1)
            },
            submitted_ms: 1,
        });
        store.flush();
    }
    let (store, stored) = JobStore::open(dir.path()).unwrap();
    assert_eq!(stored.len(), 1);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let coordinator = Coordinator::new(&std::env::temp_dir(), 1)
        .unwrap()
        .with_admission(
            8,
            1 << 30,
            Retention {
                keep_finished: 10,
                ttl: None,
                max_bytes: None,
            },
        )
        .with_store(std::sync::Arc::new(store));
    assert_eq!(
        coordinator.resume(stored, std::time::Duration::from_millis(10)),
        1
    );
    let server = Server::serve(listener, coordinator);
    let mut c = server.client().await;
    assert_eq!(wait_end(&mut c, "huge").await, JobState::Failed);
    let job = c
        .get_job(GetJobRequest {
            job_id: "huge".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let why = format!("{job:?}");
    assert!(why.contains("--max-job-bytes"), "{why}");
    // The coordinator still takes and runs jobs.
    let id = submit(&mut c, cornell(16, 16, 1)).await.unwrap();
    assert_eq!(wait_end(&mut c, &id).await, JobState::Succeeded);
}
