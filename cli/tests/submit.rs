//! `dray submit` against a real `dray coordinator` process: the images it writes are the
//! bytes `dray render` writes with the same flags; an invalid job, an unreachable
//! coordinator and an interrupted job end with one line on stderr and a non-zero exit.

mod common;
mod support;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Output, Stdio};

use support::{Proc, coordinator, dray};

fn submit(addr: &str, scene: &str, flags: &[&str], png: &Path, exr: Option<&Path>) -> Output {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, scene])
        .args(flags)
        .arg("--output")
        .arg(png);
    if let Some(exr) = exr {
        cmd.arg("--exr").arg(exr);
    }
    cmd.output().expect("run dray submit")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// `dray render` with `flags`, writing PNG and EXR into `dir` under `tag`.
fn render(dir: &Path, tag: &str, scene: &str, flags: &[&str]) -> (Vec<u8>, Vec<u8>) {
    let exr = dir.join(format!("{tag}.exr"));
    let mut all: Vec<&str> = flags.to_vec();
    let exr_s = exr.to_str().expect("utf-8 temp path");
    all.extend(["--exr", exr_s]);
    let run = common::render(dir, tag, scene, &all);
    assert!(run.ok, "dray render failed: {}", run.stderr);
    let png = std::fs::read(run.png.expect("png")).expect("read render png");
    (png, std::fs::read(&exr).expect("read render exr"))
}

#[test]
fn submit_writes_the_same_bits_as_render() {
    let dir = common::tmp("submit-same");
    let server = coordinator(&dir);
    let cases: [(&str, &str, &[&str]); 3] = [
        (
            "path",
            "cornell:glass",
            &[
                "--width",
                "48",
                "--height",
                "40",
                "--spp",
                "3",
                "--seed",
                "7",
                "--max-depth",
                "4",
                "--exposure",
                "0.5",
                "--tonemap",
                "aces",
            ],
        ),
        (
            "ao",
            "spheres:6",
            &[
                "--width",
                "40",
                "--height",
                "32",
                "--spp",
                "2",
                "--integrator",
                "ao",
                "--ao-samples",
                "3",
                "--ao-distance",
                "2.5",
                "--env",
                "0.5,0.6,0.7",
                "--translate",
                "1000,-20,5",
                "--domains",
                "4",
                "--layout",
                "grid",
                "--effects",
                "-environment",
            ],
        ),
        (
            // The camera flags (JobSpec.view), resolved once, with a moved scene.
            "view",
            "cornell",
            &[
                "--width",
                "40",
                "--height",
                "30",
                "--spp",
                "2",
                "--orbit",
                "-25,15",
                "--fov",
                "50",
                "--aperture",
                "f/0.2",
                "--focus-on",
                "0.3,0.2,0.1",
                "--translate",
                "50,0,0",
            ],
        ),
    ];
    for (i, (tag, scene, flags)) in cases.iter().enumerate() {
        let (want_png, want_exr) = render(&dir, &format!("render-{tag}"), scene, flags);
        let png = dir.join(format!("submit-{tag}.png"));
        let exr = dir.join(format!("submit-{tag}.exr"));
        // Both address forms.
        let addr = if i == 0 {
            server.addr.clone()
        } else {
            format!("http://{}", server.addr)
        };
        let out = submit(&addr, scene, flags, &png, Some(&exr));
        let err = stderr(&out);
        assert!(out.status.success(), "dray submit {tag} failed: {err}");
        // stderr is a pipe here: plain progress lines, ending with the terminal state.
        assert!(
            err.contains(": succeeded, "),
            "no plain progress lines: {err}"
        );
        let got_png = std::fs::read(&png).expect("submit png");
        let img = image::load_from_memory(&got_png).expect("decode the submitted png");
        let w: u32 = flags[1].parse().expect("width");
        let h: u32 = flags[3].parse().expect("height");
        assert_eq!((img.width(), img.height()), (w, h));
        assert!(got_png == want_png, "{tag}: PNG differs from dray render's");
        let got_exr = std::fs::read(&exr).expect("submit exr");
        assert!(got_exr == want_exr, "{tag}: EXR differs from dray render's");
    }
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn invalid_jobs_and_unreachable_coordinators_are_one_line_errors() {
    let dir = common::tmp("submit-invalid");
    let server = coordinator(&dir);
    let png = dir.join("never.png");
    let cases: [(&str, &[&str], &str); 3] = [
        ("cornell", &["--spp", "0"], "spp"),
        ("cornell", &["--max-depth", "100000", "-q"], "max_depth"),
        ("../outside.ply", &["-q"], "scene"),
    ];
    for (scene, flags, field) in cases {
        let out = submit(&server.addr, scene, flags, &png, None);
        let err = stderr(&out);
        assert!(!out.status.success(), "{flags:?} was accepted");
        assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err:?}");
        assert!(
            err.starts_with("dray: error: the coordinator rejected the job: ")
                && err.contains(field),
            "{err}"
        );
        assert!(!png.exists(), "an image was written for a rejected job");
    }
    // The server still serves after the rejections.
    let ok = submit(
        &server.addr,
        "cornell",
        &["--width", "8", "--height", "8", "--spp", "1", "-q"],
        &png,
        None,
    );
    assert!(ok.status.success(), "{}", stderr(&ok));
    assert_eq!(stderr(&ok), "", "-q should print nothing");

    // Nobody listens on a port that was just free.
    let port = support::free_port();
    let out = submit(&format!("127.0.0.1:{port}"), "cornell", &["-q"], &png, None);
    let err = stderr(&out);
    assert!(!out.status.success());
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err:?}");
    assert!(err.contains("cannot connect to the coordinator"), "{err}");
    // A malformed address never reaches the network.
    let out = submit("https://127.0.0.1:1", "cornell", &["-q"], &png, None);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("https is not supported"),
        "{}",
        stderr(&out)
    );
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ctrl_c_cancels_the_job() {
    let dir = common::tmp("submit-cancel");
    let server = coordinator(&dir);
    let png = dir.join("cancelled.png");
    // Long enough to be interrupted mid-render on any machine (minutes at full size).
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &server.addr, "cornell:glass"])
        .args(["--width", "1024", "--height", "1024", "--spp", "4096"])
        .arg("--output")
        .arg(&png)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut client = Proc::spawn(cmd);
    let err = client.child.stderr.take().expect("stderr");
    let mut lines = BufReader::new(err).lines();
    let mut job_id = None;
    for line in lines.by_ref() {
        let line = line.expect("read submit stderr");
        // "job job-1: running, 0/256 tiles, ..."
        if line.contains(": running, ") {
            job_id = line
                .strip_prefix("job ")
                .and_then(|r| r.split(':').next())
                .map(str::to_string);
            break;
        }
    }
    let job_id = job_id.expect("dray submit never reported the job running");
    client.signal(libc::SIGINT);
    let status = client
        .wait_timeout(30.0)
        .expect("dray submit did not exit after Ctrl-C");
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    assert!(!status.success(), "an interrupted submit exited 0");
    assert!(
        rest.iter()
            .any(|l| l.contains(&format!("job {job_id} cancelled"))),
        "{rest:?}"
    );
    assert!(!png.exists());

    // The coordinator agrees: the job is CANCELLED.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let state = rt.block_on(async {
        let mut c = dray_proto::v1::render_service_client::RenderServiceClient::connect(format!(
            "http://{}",
            server.addr
        ))
        .await
        .expect("connect");
        c.get_job(dray_proto::v1::GetJobRequest { job_id })
            .await
            .expect("GetJob")
            .into_inner()
            .job
            .and_then(|j| j.progress)
            .expect("progress")
            .state()
    });
    assert_eq!(state, dray_proto::v1::JobState::Cancelled);
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}
