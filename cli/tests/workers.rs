//! Jobs on real workers: `dray cluster --workers N` (a coordinator and N `dray worker`
//! processes on local ports) serving `dray submit`.
//!
//! - the same bits as `dray render` on 1, 2 and 4 workers, every integrator, both layouts
//!   (PNG, and EXR for one case), and on a realistic glTF model;
//! - two jobs at once; Ctrl-C cancelling a job mid-render (its package removed, the
//!   workers idle again, the next job correct); invalid jobs rejected while workers are
//!   registered; a worker that cannot reach its coordinator; and a ray explosion on four
//!   workers that must finish with the right image in bounded memory.
//!
//! Every job on a cluster is checked to have run on its workers (GetJob's
//! `stats.workers`), not in the coordinator's process.

mod common;
mod support;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{GetJobRequest, Job, JobState};
use support::{Proc, WorkerCluster, capture_stderr, cpu_ticks, dray, eventually, proc_status_kb};

/// Cluster port slots, one per test (tests run in parallel).
const SLOT_SAME_BITS: u16 = 0;
const SLOT_TWO_JOBS: u16 = 1;
const SLOT_CANCEL: u16 = 2;
const SLOT_INVALID: u16 = 3;
const SLOT_REALISTIC: u16 = 4;
const SLOT_FLOW: u16 = 5;
const SLOT_FLOW_BUDGET: u16 = 6;

/// How long one `dray submit` may take before the test fails (instead of hanging).
const SUBMIT_TIMEOUT_SECS: f64 = 180.0;

/// `dray submit` (progress lines on stderr, which carry the job id), killed with a clear
/// panic if it takes longer than [`SUBMIT_TIMEOUT_SECS`].
fn submit(addr: &str, scene: &str, flags: &[&str], png: &Path, exr: Option<&Path>) -> Output {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, scene])
        .args(flags)
        .arg("--output")
        .arg(png);
    if let Some(exr) = exr {
        cmd.arg("--exr").arg(exr);
    }
    cmd.stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let err = capture_stderr(&mut p.child);
    let status = p.wait_timeout(SUBMIT_TIMEOUT_SECS);
    let text = err.after(status.is_some());
    let Some(status) = status else {
        panic!(
            "HANG: dray submit {scene} {flags:?} to {addr} did not finish within \
             {SUBMIT_TIMEOUT_SECS} s; its output:\n{text}"
        );
    };
    Output {
        status,
        stdout: Vec::new(),
        stderr: text.into_bytes(),
    }
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The job id in `dray submit`'s "dray submit: job ID accepted by URL" line.
fn job_id(err: &str) -> String {
    err.lines()
        .find_map(|l| {
            l.strip_prefix("dray submit: job ")?
                .split_once(" accepted by ")
                .map(|(id, _)| id.to_string())
        })
        .unwrap_or_else(|| panic!("no job id in dray submit's output: {err}"))
}

/// GetJob over gRPC.
fn get_job(addr: &str, id: &str) -> Job {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let mut c = RenderServiceClient::connect(format!("http://{addr}"))
            .await
            .expect("connect to the coordinator");
        c.get_job(GetJobRequest {
            job_id: id.to_string(),
        })
        .await
        .expect("GetJob")
        .into_inner()
        .job
        .expect("GetJob returned no job")
    })
}

fn state(job: &Job) -> JobState {
    job.progress.as_ref().expect("progress").state()
}

/// `dray render` with `flags`: PNG bytes, and EXR bytes when asked.
fn render(dir: &Path, tag: &str, scene: &str, flags: &[&str], exr: bool) -> (Vec<u8>, Vec<u8>) {
    let exr_path = dir.join(format!("{tag}.exr"));
    let mut all: Vec<&str> = flags.to_vec();
    let exr_s = exr_path.to_str().expect("utf-8 temp path");
    if exr {
        all.extend(["--exr", exr_s]);
    }
    let run = common::render(dir, tag, scene, &all);
    assert!(
        run.ok,
        "dray render {scene} {flags:?} failed: {}",
        run.stderr
    );
    let png = std::fs::read(run.png.expect("png")).expect("read render png");
    let exr = if exr {
        std::fs::read(&exr_path).expect("read render exr")
    } else {
        Vec::new()
    };
    (png, exr)
}

/// Submit `scene flags` to `cluster` and check it ran on all its `workers` and wrote
/// `want_png` (and `want_exr` when given). Returns the job.
#[allow(clippy::too_many_arguments)]
fn submit_and_compare(
    cluster: &WorkerCluster,
    workers: u32,
    dir: &Path,
    tag: &str,
    scene: &str,
    flags: &[&str],
    want_png: &[u8],
    want_exr: Option<&[u8]>,
) -> Job {
    submit_to(
        &cluster.addr,
        &cluster.log,
        workers,
        dir,
        tag,
        scene,
        flags,
        want_png,
        want_exr,
    )
}

/// [`submit_and_compare`] to the coordinator at `addr`, whose stderr is `log`.
#[allow(clippy::too_many_arguments)]
fn submit_to(
    addr: &str,
    log: &Mutex<String>,
    workers: u32,
    dir: &Path,
    tag: &str,
    scene: &str,
    flags: &[&str],
    want_png: &[u8],
    want_exr: Option<&[u8]>,
) -> Job {
    let png = dir.join(format!("{tag}.png"));
    let exr = dir.join(format!("{tag}.exr"));
    let out = submit(
        addr,
        scene,
        flags,
        &png,
        want_exr.is_some().then_some(exr.as_path()),
    );
    let err = stderr(&out);
    assert!(
        out.status.success(),
        "{tag}: dray submit {scene} {flags:?} failed: {err}\ncluster log:\n{}",
        dray_sync::lock(log)
    );
    let job = get_job(addr, &job_id(&err));
    let stats = job.stats.clone().expect("stats");
    assert_eq!(
        stats.workers, workers,
        "{tag}: the job ran on {} workers, not on the cluster's {workers}",
        stats.workers
    );
    assert!(
        std::fs::read(&png).expect("submit png") == want_png,
        "{tag}: {scene} {flags:?} on {workers} workers: PNG differs from dray render's"
    );
    if let Some(want) = want_exr {
        assert!(
            std::fs::read(&exr).expect("submit exr") == want,
            "{tag}: {scene} {flags:?} on {workers} workers: EXR differs from dray render's"
        );
    }
    job
}

/// Directories in `dir` (job packages).
/// The job package folders in a coordinator's work directory (its job store, `state`,
/// is not one).
fn subdirs(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .map(|r| {
            r.flatten()
                .map(|e| e.path())
                .filter(|p| p.is_dir() && !p.ends_with("state"))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn same_bits_as_dray_render_on_1_2_and_4_workers() {
    let started = Instant::now();
    let dir = common::tmp("workers-same-bits");
    let size = [
        "--width", "48", "--height", "36", "--spp", "4", "--seed", "3",
    ];
    let integrators: [(&str, &str, &[&str]); 5] = [
        ("raycast", "city:3", &["--integrator", "raycast"]),
        ("primary", "city:3", &["--integrator", "primary"]),
        ("whitted", "cornell:glass", &["--integrator", "whitted"]),
        (
            "path",
            "cornell:glass",
            &["--integrator", "path", "--max-depth", "6"],
        ),
        (
            "ao",
            "cornell",
            &[
                "--integrator",
                "ao",
                "--ao-samples",
                "4",
                "--ao-distance",
                "1.5",
            ],
        ),
    ];
    // (tag, scene, flags, reference png, reference exr)
    let mut cases = Vec::new();
    for (name, scene, iflags) in integrators {
        for layout in ["grid", "kd"] {
            let tag = format!("{name}-{layout}");
            let mut flags: Vec<&str> = size.to_vec();
            flags.extend_from_slice(iflags);
            flags.extend(["--domains", "6", "--layout", layout]);
            // EXR bytes too for one case.
            let exr = name == "path" && layout == "kd";
            let (png, exr_bytes) = render(&dir, &format!("render-{tag}"), scene, &flags, exr);
            cases.push((tag, scene, flags, png, exr.then_some(exr_bytes)));
        }
    }
    for workers in [1u16, 2, 4] {
        let work = dir.join(format!("work-{workers}"));
        let work_s = work.to_str().expect("utf-8 temp path").to_string();
        let cluster = WorkerCluster::start(workers, SLOT_SAME_BITS, &dir, &["--work-dir", &work_s]);
        for (tag, scene, flags, png, exr) in &cases {
            let job = submit_and_compare(
                &cluster,
                u32::from(workers),
                &dir,
                &format!("{tag}-{workers}w"),
                scene,
                flags,
                png,
                exr.as_deref(),
            );
            assert_eq!(job.stats.expect("stats").domains, 6, "{tag}");
        }
        // Packages went to --work-dir and are removed as jobs end.
        assert!(
            work.is_dir(),
            "--work-dir {} was not created",
            work.display()
        );
        assert!(
            eventually(10.0, || subdirs(&work).is_empty()),
            "job packages left in {}: {:?}",
            work.display(),
            subdirs(&work)
        );
        assert!(cluster.all_alive(), "{}", cluster.log());
    }
    eprintln!(
        "same bits on 1, 2 and 4 workers: {} jobs in {:.1} s",
        3 * cases.len(),
        started.elapsed().as_secs_f64()
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_realistic_model_on_two_workers_is_dray_render() {
    let Some(scenes) = common::scenes_dir() else {
        return;
    };
    let models: [(&str, &[&str]); 3] = [
        (
            "flight_helmet/FlightHelmet.gltf",
            &["--integrator", "path", "--spp", "2", "--domains", "8"],
        ),
        // Photometric (a 68,300-lux sun): the PNG's automatic exposure, about -16 EV,
        // is chosen from the assembled film, so it is dray render's to the bit.
        (
            "volumetric_fog_room/VolumetricFogExample.glb",
            &["--integrator", "path", "--spp", "2", "--domains", "4"],
        ),
        (
            "water_bottle/WaterBottle.gltf",
            &[
                "--integrator",
                "whitted",
                "--spp",
                "2",
                "--layout",
                "grid",
                "--domains",
                "6",
            ],
        ),
    ];
    let present: Vec<_> = models
        .iter()
        .filter(|(m, _)| {
            let ok = scenes.join(m).is_file();
            if !ok {
                common::dependency_missing(&format!("{m} is not in {}", scenes.display()));
            }
            ok
        })
        .collect();
    if present.is_empty() {
        return;
    }
    let dir = common::tmp("workers-realistic");
    let cluster = WorkerCluster::start(2, SLOT_REALISTIC, &scenes, &[]);
    for (i, (model, extra)) in present.iter().enumerate() {
        let mut flags = vec!["--width", "64", "--height", "48", "--seed", "1"];
        flags.extend_from_slice(extra);
        let path = scenes.join(model);
        let (png, _) = render(
            &dir,
            &format!("render-{i}"),
            path.to_str().expect("utf-8 path"),
            &flags,
            false,
        );
        // The coordinator resolves the scene against its --scene-root.
        submit_and_compare(
            &cluster,
            2,
            &dir,
            &format!("submit-{i}"),
            model,
            &flags,
            &png,
            None,
        );
    }
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn two_jobs_at_once_both_succeed() {
    let dir = common::tmp("workers-two-jobs");
    let a: (&str, Vec<&str>) = (
        "cornell:glass",
        vec![
            "--width",
            "96",
            "--height",
            "72",
            "--spp",
            "16",
            "--max-depth",
            "6",
            "--domains",
            "5",
        ],
    );
    let b: (&str, Vec<&str>) = (
        "city:3",
        vec![
            "--width",
            "96",
            "--height",
            "72",
            "--spp",
            "8",
            "--integrator",
            "whitted",
            "--layout",
            "grid",
            "--domains",
            "4",
        ],
    );
    let (want_a, _) = render(&dir, "render-a", a.0, &a.1, false);
    let (want_b, _) = render(&dir, "render-b", b.0, &b.1, false);
    let cluster = WorkerCluster::start(2, SLOT_TWO_JOBS, &dir, &[]);
    let (job_a, job_b) = std::thread::scope(|s| {
        let ta =
            s.spawn(|| submit_and_compare(&cluster, 2, &dir, "submit-a", a.0, &a.1, &want_a, None));
        let tb =
            s.spawn(|| submit_and_compare(&cluster, 2, &dir, "submit-b", b.0, &b.1, &want_b, None));
        (
            ta.join().expect("job a's thread"),
            tb.join().expect("job b's thread"),
        )
    });
    assert_ne!(job_a.job_id, job_b.job_id);
    let at = |t: Option<(i64, i32)>| t.map_or(f64::NAN, |(s, n)| s as f64 + f64::from(n) * 1e-9);
    let submitted = |j: &Job| at(j.submitted_at.as_ref().map(|t| (t.seconds, t.nanos)));
    let finished = |j: &Job| at(j.finished_at.as_ref().map(|t| (t.seconds, t.nanos)));
    let overlap = submitted(&job_a) < finished(&job_b) && submitted(&job_b) < finished(&job_a);
    eprintln!("two jobs at once: the jobs overlapped in time: {overlap}");
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ctrl_c_cancels_a_job_on_workers_and_the_cluster_goes_on() {
    let dir = common::tmp("workers-cancel");
    let work = dir.join("work");
    let work_s = work.to_str().expect("utf-8 temp path").to_string();
    let cluster = WorkerCluster::start(2, SLOT_CANCEL, &dir, &["--work-dir", &work_s]);
    let png = dir.join("cancelled.png");
    // Minutes of work on this machine: it is interrupted long before the end.
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &cluster.addr, "cornell:glass"])
        .args(["--width", "512", "--height", "512", "--spp", "4096"])
        .args(["--max-depth", "8", "--domains", "6"])
        .arg("--output")
        .arg(&png)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut client = Proc::spawn(cmd);
    let mut lines = BufReader::new(client.child.stderr.take().expect("stderr")).lines();
    let mut seen = Vec::new();
    let mut id = None;
    for line in lines.by_ref() {
        let line = line.expect("read submit stderr");
        if id.is_none() {
            id = line
                .strip_prefix("dray submit: job ")
                .and_then(|r| r.split_once(" accepted by "))
                .map(|(id, _)| id.to_string());
        }
        let running = line.contains(": running, ");
        seen.push(line);
        if running {
            break;
        }
    }
    let id = id.unwrap_or_else(|| panic!("no job id / running line: {seen:?}"));
    assert!(
        state(&get_job(&cluster.addr, &id)) == JobState::Running,
        "{seen:?}"
    );
    // The job's package is in --work-dir while it runs.
    assert!(
        work.join(&id).is_dir(),
        "no package for {id} in --work-dir {}: {:?}",
        work.display(),
        subdirs(&work)
    );
    // Let rays spread over the workers (the job reports traced rays), then interrupt.
    assert!(
        eventually(60.0, || get_job(&cluster.addr, &id)
            .progress
            .is_some_and(|p| p.rays_traced > 0)),
        "job {id} traced no rays"
    );
    let before = get_job(&cluster.addr, &id);
    assert_eq!(state(&before), JobState::Running);
    client.signal(libc::SIGINT);
    let status = client
        .wait_timeout(30.0)
        .expect("dray submit did not exit after Ctrl-C");
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    assert!(!status.success(), "an interrupted submit exited 0");
    assert!(
        rest.iter()
            .any(|l| l.contains(&format!("job {id} cancelled"))),
        "{rest:?}"
    );
    assert!(!png.exists(), "an image was written for a cancelled job");
    let after = get_job(&cluster.addr, &id);
    assert_eq!(state(&after), JobState::Cancelled, "{after:?}");
    // The workers free the job: its package goes, and they stop tracing it.
    assert!(
        eventually(15.0, || !work.join(&id).exists()),
        "the cancelled job's package is still in {}",
        work.display()
    );
    // The workers stop tracing it: wait for a window of one second in which no worker
    // used half a core (heartbeats and reports only), rather than sleeping a
    // fixed time and hoping a loaded machine has caught up.
    let tick = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
    let mut last = Vec::new();
    let idle = eventually(30.0, || {
        let t0: Vec<u64> = cluster
            .worker_pids
            .iter()
            .map(|&p| cpu_ticks(p).expect("worker cpu time"))
            .collect();
        std::thread::sleep(Duration::from_secs(1));
        last = cluster
            .worker_pids
            .iter()
            .zip(&t0)
            .map(|(&p, t)| cpu_ticks(p).expect("worker cpu time") - t)
            .collect();
        last.iter().all(|&b| b * 2 < tick)
    });
    assert!(
        idle,
        "workers still busy 30 s after the job was cancelled: {last:?} ticks in the last second (at {tick}/s)"
    );
    let traced_then = get_job(&cluster.addr, &id)
        .progress
        .expect("progress")
        .rays_traced;
    eprintln!(
        "cancel: {} rays traced before Ctrl-C, {traced_then} counted in the end",
        before.progress.expect("progress").rays_traced
    );

    // The cluster still serves: a further job is right.
    let flags = [
        "--width",
        "40",
        "--height",
        "30",
        "--spp",
        "4",
        "--domains",
        "6",
    ];
    let (want, _) = render(&dir, "render-after", "cornell:glass", &flags, false);
    submit_and_compare(
        &cluster,
        2,
        &dir,
        "after-cancel",
        "cornell:glass",
        &flags,
        &want,
        None,
    );
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_worker_that_cannot_reach_the_coordinator_fails_clearly() {
    // Nobody listens on a port that was just free.
    let port = support::free_port();
    let target = format!("127.0.0.1:{port}");
    let mut cmd = dray();
    cmd.args(["worker", "--coordinator", &format!("http://{target}")])
        .args(["--listen", "127.0.0.1:0", "--connect-timeout", "1"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut worker = Proc::spawn(cmd);
    let status = worker
        .wait_timeout(60.0)
        .expect("the worker kept running without a coordinator");
    let mut err = String::new();
    std::io::Read::read_to_string(&mut worker.child.stderr.take().expect("stderr"), &mut err)
        .expect("read stderr");
    assert!(!status.success(), "exited 0 without a coordinator: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err:?}");
    assert!(
        err.starts_with("dray: error: ") && err.contains(&target),
        "the message does not name {target}: {err}"
    );
}

#[test]
fn invalid_jobs_are_rejected_while_workers_are_registered() {
    let dir = common::tmp("workers-invalid");
    let cluster = WorkerCluster::start(2, SLOT_INVALID, &dir, &[]);
    let png = dir.join("never.png");
    let cases: [(&str, &[&str], &str); 7] = [
        ("cornell", &["--spp", "0"], "spp"),
        ("cornell", &["--width", "0"], "width"),
        ("cornell", &["--height", "20000"], "height"),
        ("cornell", &["--max-depth", "100000"], "max_depth"),
        ("no_such_scene", &[], "scene"),
        ("missing/model.gltf", &[], "scene"),
        ("../outside.gltf", &[], "scene"),
    ];
    for (scene, flags, field) in cases {
        let out = submit(&cluster.addr, scene, flags, &png, None);
        let err = stderr(&out);
        assert!(
            !out.status.success(),
            "{scene} {flags:?} was accepted: {err}"
        );
        assert_eq!(
            err.trim_end().lines().count(),
            1,
            "{scene} {flags:?}: not one line: {err:?}"
        );
        assert!(
            err.starts_with("dray: error: the coordinator rejected the job: ")
                && err.contains(field),
            "{scene} {flags:?}: {err}"
        );
        assert!(!png.exists(), "an image was written for a rejected job");
    }
    // A camera the scene lacks is found once the scene is loaded, after SubmitJob has
    // answered: the job fails, and dray submit ends with that one error line.
    let out = submit(
        &cluster.addr,
        "cornell",
        &["--camera", "no-such-camera"],
        &png,
        None,
    );
    let err = stderr(&out);
    assert!(
        !out.status.success(),
        "a job with a missing camera succeeded: {err}"
    );
    let last = err.trim_end().lines().last().unwrap_or_default();
    assert!(
        last.starts_with("dray: error: job ") && last.contains("failed: camera: "),
        "{err}"
    );
    assert!(!png.exists(), "an image was written for a failed job");
    assert!(cluster.all_alive(), "{}", cluster.log());
    // The cluster still serves, on its workers.
    let flags = [
        "--width",
        "32",
        "--height",
        "24",
        "--spp",
        "2",
        "--integrator",
        "whitted",
    ];
    let (want, _) = render(&dir, "render-ok", "cornell:mirror", &flags, false);
    submit_and_compare(
        &cluster,
        2,
        &dir,
        "after-invalid",
        "cornell:mirror",
        &flags,
        &want,
        None,
    );
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_ray_explosion_on_four_workers_finishes_right_in_bounded_memory() {
    ray_explosion("workers-flow", SLOT_FLOW, &[], 1 << 20); // 1 GiB per worker
}

/// The same explosion on workers whose memory budget (4 MiB) holds every domain of the
/// scene but few rays: queues stay within the budget's share, peers wait on flow
/// control, and nothing deadlocks.
#[test]
fn a_ray_explosion_under_a_small_memory_budget_finishes_right_without_deadlock() {
    ray_explosion(
        "workers-flow-budget",
        SLOT_FLOW_BUDGET,
        &["--memory-budget", "4M"],
        256 << 10, // 256 MiB per worker: the process, not the budget, dominates
    );
}

fn ray_explosion(tag: &str, slot: u16, cluster_flags: &[&str], peak_limit_kb: u64) {
    const STALL: Duration = Duration::from_secs(60);
    let dir = common::tmp(tag);
    let scene = "cornell:glass";
    // 96x72 pixels x 64 spp = 442,368 camera rays (more than a worker lets in flight),
    // each with up to 32 bounces of reflection, refraction and shadow rays.
    let flags = [
        "--width",
        "96",
        "--height",
        "72",
        "--spp",
        "64",
        "--integrator",
        "path",
        "--max-depth",
        "32",
        "--domains",
        "8",
    ];
    let (want, _) = render(&dir, "render-flow", scene, &flags, false);
    let cluster = WorkerCluster::start(4, slot, &dir, cluster_flags);
    let png = dir.join("flow.png");
    let log = dir.join("submit.log");
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", &cluster.addr, scene])
        .args(flags)
        .arg("--output")
        .arg(&png)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("create the submit log"));
    let started = Instant::now();
    let mut client = Proc::spawn(cmd);
    let mut id = None;
    let mut last_traced = 0u64;
    let mut last_change = Instant::now();
    let mut peak_in_flight = 0u64;
    let status = loop {
        if let Some(s) = client.wait_timeout(1.0) {
            break s;
        }
        if id.is_none() {
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            if text.contains(" accepted by ") {
                id = Some(job_id(&text));
            }
        }
        if let Some(id) = &id {
            let p = get_job(&cluster.addr, id).progress.expect("progress");
            peak_in_flight = peak_in_flight.max(p.rays_in_flight);
            if p.rays_traced != last_traced {
                last_traced = p.rays_traced;
                last_change = Instant::now();
            }
            if last_change.elapsed() > STALL {
                let rss: Vec<_> = cluster
                    .worker_pids
                    .iter()
                    .map(|&p| proc_status_kb(p, "VmRSS"))
                    .collect();
                panic!(
                    "DEADLOCK? job {id}: no ray traced for {STALL:?}: state {:?}, {}/{} tiles, \
                     {} rays traced, {} in flight; worker RSS {rss:?} kB; cluster log:\n{}",
                    p.state(),
                    p.tiles_done,
                    p.tiles_total,
                    p.rays_traced,
                    p.rays_in_flight,
                    cluster.log()
                );
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(600),
            "the job is still running after 10 minutes (progress is being made)"
        );
    };
    let took = started.elapsed();
    let err = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(
        status.success(),
        "dray submit failed: {err}\ncluster log:\n{}",
        cluster.log()
    );
    let peaks: Vec<u64> = cluster
        .worker_pids
        .iter()
        .map(|&p| proc_status_kb(p, "VmHWM").expect("worker VmHWM"))
        .collect();
    let job = get_job(&cluster.addr, &job_id(&err));
    let stats = job.stats.clone().expect("stats");
    eprintln!(
        "ray explosion {cluster_flags:?}: {} rays traced on 4 workers in {:.1} s, at most \
         {peak_in_flight} in flight when sampled; worker peak RSS {peaks:?} kB",
        job.progress.as_ref().expect("progress").rays_traced,
        took.as_secs_f64()
    );
    assert_eq!(stats.workers, 4);
    assert!(
        std::fs::read(&png).expect("submit png") == want,
        "the ray explosion's image differs from dray render's"
    );
    for (i, kb) in peaks.iter().enumerate() {
        assert!(
            *kb < peak_limit_kb,
            "worker {} peaked at {kb} kB (limit {peak_limit_kb} kB)",
            i + 1
        );
    }
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

// A worker lost mid-job (SIGKILL, or SIGSTOP past the heartbeat timeout) no longer fails
// the job: its tiles are traced again. cli/tests/faults.rs tests that.
