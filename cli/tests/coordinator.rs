//! `dray coordinator` as a real process on a free port, driven by a tonic client: a job
//! gives the same PNG bytes as `dray render` with the same settings, and an invalid job is
//! INVALID_ARGUMENT while the server keeps serving. The child is killed on drop, so it is
//! stopped even when an assertion fails.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{GetImageRequest, JobSpec, JobState, SubmitJobRequest, WatchJobRequest};

/// The coordinator process; killed and reaped when dropped.
struct Coordinator {
    child: Child,
    addr: String,
}

impl Coordinator {
    fn start(root: &std::path::Path) -> Coordinator {
        let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
            .args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
            .arg(root)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start dray coordinator");
        let stdout = child.stdout.take().expect("stdout");
        let mut guard = Coordinator {
            child,
            addr: String::new(),
        };
        let mut line = String::new();
        BufReader::new(stdout)
            .read_line(&mut line)
            .expect("read the listening line");
        guard.addr = line
            .trim()
            .rsplit(' ')
            .next()
            .filter(|a| a.contains(':'))
            .unwrap_or_else(|| panic!("no address in {line:?}"))
            .to_string();
        guard
    }
}

impl Drop for Coordinator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn coordinator_process_matches_dray_render() {
    let dir = common::tmp("coordinator");
    let server = Coordinator::start(&dir);
    let reference = common::render(
        &dir,
        "ref",
        "cornell",
        &["--width", "64", "--height", "64", "--spp", "4"],
    );
    assert!(reference.ok, "{}", reference.stderr);
    let want = std::fs::read(reference.png.expect("png")).unwrap();

    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let got = rt.block_on(async {
        let mut c = RenderServiceClient::connect(format!("http://{}", server.addr))
            .await
            .expect("connect");
        let bad = c
            .submit_job(SubmitJobRequest {
                spec: Some(JobSpec {
                    scene: "cornell".into(),
                    width: 64,
                    height: 64,
                    spp: 0,
                    ..Default::default()
                }),
            })
            .await
            .unwrap_err();
        assert_eq!(bad.code(), tonic::Code::InvalidArgument);
        assert!(bad.message().starts_with("spp:"), "{}", bad.message());

        let id = c
            .submit_job(SubmitJobRequest {
                spec: Some(JobSpec {
                    scene: "cornell".into(),
                    width: 64,
                    height: 64,
                    spp: 4,
                    ..Default::default()
                }),
            })
            .await
            .expect("submit")
            .into_inner()
            .job_id;
        let mut watch = c
            .watch_job(WatchJobRequest {
                job_id: id.clone(),
                min_interval: None,
            })
            .await
            .expect("watch")
            .into_inner();
        let mut last = JobState::Unspecified;
        while let Some(p) = watch.message().await.expect("progress") {
            last = p.state();
        }
        assert_eq!(last, JobState::Succeeded);
        c.get_image(GetImageRequest {
            job_id: id,
            ..Default::default()
        })
        .await
        .expect("image")
        .into_inner()
        .data
    });
    assert!(got == want, "GetImage PNG differs from dray render's");
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}
