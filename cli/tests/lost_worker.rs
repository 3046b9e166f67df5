//! A worker SIGKILLed at a random moment of a job with doubling passes, and started
//! again at once on the same port (as `dray cluster` does): every job ends SUCCEEDED with
//! the bits of `dray render`, or FAILED with a reason; none stays RUNNING (issue 38,
//! item 1: 2 runs in 12 hung at 62 of 64 tiles of a pass).
//!
//! The cause was in the workers' outgoing ray streams, kept by endpoint: the newcomer
//! (a new worker id on its predecessor's port) was sent rays of the job's next attempt on
//! the stream opened for the lost predecessor; when that stream failed, the rays were
//! dropped and the *old* id named unreachable, which the coordinator ignores (it is no
//! longer a worker of the job), so their credit never came back.
//!
//! The moments are drawn from a seed, printed (set `DRAY_KILL_SEED` to replay one) and
//! the runs counted by `DRAY_KILL_RUNS` (default 16: at the rate seen, about 1 in 6,
//! a loop this long misses the fault 5% of the time). Nothing here bounds elapsed time
//! but the hang bound, derived from the job's size, which only catches hangs.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use dray_proto::v1::{JobEventKind, JobState};
use support::port_worker::PortWorker;
use support::seeded::{self, Rng};
use support::{Captured, Proc, capture_stderr, dray, eventually, free_port};

const SCENE: &str = "spheres:200";
const WIDTH: u32 = 192;
const HEIGHT: u32 = 192;
const SPP: u32 = 64;

/// The job's flags (doubling passes and the dynamic schedule are `dray submit`'s
/// defaults; said here so a change of default does not change the test).
fn flags() -> Vec<String> {
    [
        "--width",
        &WIDTH.to_string(),
        "--height",
        &HEIGHT.to_string(),
        "--spp",
        &SPP.to_string(),
        "--integrator",
        "path",
        "--max-depth",
        "4",
        "--passes",
        "doubling",
        "--schedule",
        "dynamic",
    ]
    .map(String::from)
    .to_vec()
}

/// How long a job may stay unfinished before it counts as hung: generous for the
/// job's size on a loaded two-core machine (it takes a few seconds undisturbed), plus
/// the coordinator's heartbeat timeout for the loss.
fn hang_bound() -> Duration {
    let work = u64::from(WIDTH) * u64::from(HEIGHT) * u64::from(SPP);
    Duration::from_secs(60 + work / 50_000)
}

fn registered(log: &Captured) -> usize {
    log.text().matches("worker registered").count()
}

fn lost(log: &Captured) -> usize {
    log.text().matches("worker lost").count()
}

/// The reference image: `dray render --workers 0` with the job's flags.
fn reference(dir: &Path) -> Vec<u8> {
    let mut all = flags();
    all.extend(["--workers", "0"].map(String::from));
    let args: Vec<&str> = all.iter().map(String::as_str).collect();
    let run = common::render(dir, "reference", SCENE, &args);
    assert!(run.ok, "dray render failed: {}", run.stderr);
    std::fs::read(run.png.expect("png")).expect("read the reference png")
}

/// `dray submit` of the job, in the background.
fn submit(addr: &str, png: &PathBuf) -> (Proc, Captured) {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, SCENE])
        .args(flags())
        .arg("--output")
        .arg(png)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut proc = Proc::spawn(cmd);
    let log = capture_stderr(&mut proc.child);
    (proc, log)
}

fn job_id(log: &Captured) -> Option<String> {
    support::submitted_job_id(&log.text())
}

#[test]
fn a_worker_killed_and_restarted_on_its_port_mid_pass_never_hangs_a_job() {
    let seed = seeded::seed("DRAY_KILL_SEED");
    let runs = seeded::count("DRAY_KILL_RUNS", 16);
    eprintln!("lost_worker: seed {seed} (DRAY_KILL_SEED={seed} replays it), {runs} runs");
    let mut rng = Rng(seed);
    let dir = common::tmp("lost-worker");
    let want = reference(&dir);
    let (_coordinator, addr, clog) = support::logged_coordinator(&dir, 0, &[]);
    let mut workers: Vec<PortWorker> = (0..3)
        .map(|_| PortWorker::start(&addr, free_port()))
        .collect();
    assert!(
        eventually(60.0, || registered(&clog) >= 3),
        "the workers did not register: {}",
        clog.text()
    );
    let bound = hang_bound();
    let (mut succeeded, mut failed, mut killed_mid_job) = (0, 0, 0);
    for run in 0..runs {
        let png = dir.join(format!("run-{run}.png"));
        let _ = std::fs::remove_file(&png);
        let (mut sub, slog) = submit(&addr, &png);
        assert!(
            eventually(bound.as_secs_f64(), || slog.text().contains(": running, ")),
            "run {run}: the job never ran: {}",
            slog.text()
        );
        let id = job_id(&slog).expect("a job id");
        // A random moment of the job (it takes about two seconds undisturbed), a random worker,
        // and a random pause before its replacement starts on the same port.
        let victim = rng.below(3) as usize;
        let after = Duration::from_millis(100 + rng.below(1400));
        let pause = Duration::from_millis(rng.below(400));
        std::thread::sleep(after);
        let state = support::get_job(&addr, &id)
            .and_then(|j| j.progress)
            .map(|p| p.state());
        let (lost_before, registered_before) = (lost(&clog), registered(&clog));
        workers[victim].proc.signal(libc::SIGKILL);
        let _ = workers[victim].proc.wait_timeout(30.0);
        std::thread::sleep(pause);
        let port = workers[victim].port;
        workers[victim] = PortWorker::start(&addr, port);
        if state == Some(JobState::Running) {
            killed_mid_job += 1;
        }
        eprintln!(
            "run {run}: worker {victim} killed {} ms into the job ({state:?}), restarted on \
             port {port} {} ms later",
            after.as_millis(),
            pause.as_millis()
        );
        let started = Instant::now();
        let status = sub.wait_timeout(bound.as_secs_f64());
        let out = slog.text();
        let Some(status) = status else {
            let job = support::get_job(&addr, &id);
            panic!(
                "HANG in run {run} (seed {seed}): job {id} unfinished {} s after the kill: {:?}\n\
                 --- dray submit ---\n{out}\n--- coordinator ---\n{}\n--- worker logs ---\n{}",
                started.elapsed().as_secs(),
                job.and_then(|j| j.progress),
                clog.text(),
                workers
                    .iter()
                    .map(|w| w.log.text())
                    .collect::<Vec<_>>()
                    .join("\n---\n")
            );
        };
        if status.success() {
            let got = std::fs::read(&png).expect("read the job's png");
            assert!(
                got == want,
                "run {run} (seed {seed}): the image differs from dray render's"
            );
            succeeded += 1;
        } else {
            // FAILED is allowed, with a reason.
            assert!(
                out.to_lowercase().contains("fail"),
                "run {run} (seed {seed}): the job ended without success or a reason: {out}"
            );
            failed += 1;
        }
        // The job's event log says what happened (issue 42): each lost worker whose
        // tiles were traced again is a WORKER_LOST event and one more attempt.
        if let Some(job) = support::get_job(&addr, &id) {
            let lost_events = job
                .events
                .iter()
                .filter(|e| e.kind == JobEventKind::WorkerLost as i32)
                .count();
            let retried = job.stats.as_ref().map_or(0, |s| s.tiles_retried);
            assert!(
                (retried == 0 || lost_events > 0) && job.attempts as usize == 1 + lost_events,
                "run {run} (seed {seed}): {retried} tiles retried, {} attempts, events {:?}",
                job.attempts,
                job.events
            );
        }
        // The next run starts with three live workers: the replacement registered and
        // the killed one declared lost (its heartbeat timeout, if the job did not end
        // with it already).
        assert!(
            eventually(bound.as_secs_f64(), || registered(&clog)
                > registered_before
                && lost(&clog) > lost_before),
            "run {run}: the replacement did not register, or the killed worker was never \
             declared lost:\n{}",
            clog.text()
        );
    }
    eprintln!(
        "lost_worker: seed {seed}: {runs} jobs, {killed_mid_job} killed mid-job, {succeeded} \
         succeeded with dray render's bits, {failed} failed with a reason, 0 hung"
    );
    assert!(
        killed_mid_job > 0,
        "no kill landed while a job ran: the test tested nothing"
    );
    drop(workers);
    let _ = std::fs::remove_dir_all(&dir);
}
