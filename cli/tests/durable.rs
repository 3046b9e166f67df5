//! Durable jobs, with real processes: a coordinator on a state directory is SIGKILLed in
//! the middle of a job and started again on the same directory. The running job resumes
//! (keeping the tiles it had committed) and finishes with the bits of `dray render`; the
//! job submitted behind it runs too; an image finished before the kill is still served;
//! the `dray submit` clients wait for the coordinator and follow their jobs to the end.
//! A second coordinator on a held state directory stops with one line naming the lock.
//!
//! Nothing here bounds elapsed time: tests wait for events, with limits that only catch
//! hangs.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::Stdio;

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{GetImageRequest, ImageFormat, JobSpec, ListJobsRequest, SubmitJobRequest};
use support::{Proc, capture_stderr, dray, eventually, free_port, worker};

/// A limit that only catches hangs.
const HANG_SECS: f64 = 300.0;

/// A coordinator on `port` keeping its jobs in `state`.
fn coordinator(dir: &Path, state: &Path, port: u16) -> (Proc, String, support::Captured) {
    let work = dir.join("work");
    support::logged_coordinator(
        dir,
        port,
        &[
            "--work-dir".as_ref(),
            work.as_os_str(),
            "--state-dir".as_ref(),
            state.as_os_str(),
        ],
    )
}

/// A `dray submit` running in the background; its stderr carries progress and the id.
struct Submit {
    proc: Proc,
    log: support::Captured,
    png: PathBuf,
}

fn submit(addr: &str, dir: &Path, tag: &str, flags: &[&str]) -> Submit {
    let png = dir.join(format!("{tag}.png"));
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, "cornell:glass"])
        .args(flags)
        .arg("--output")
        .arg(&png)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut proc = Proc::spawn(cmd);
    let log = capture_stderr(&mut proc.child);
    Submit { proc, log, png }
}

impl Submit {
    fn id(&self) -> Option<String> {
        support::submitted_job_id(&self.log.text())
    }

    /// Wait for the client to end; its exit status and output.
    fn finish(mut self) -> (bool, String, PathBuf) {
        let status = self.proc.wait_timeout(HANG_SECS);
        let out = self.log.after(status.is_some());
        let Some(status) = status else {
            panic!("HANG: dray submit did not finish within {HANG_SECS} s:\n{out}");
        };
        (status.success(), out, self.png)
    }
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
}

fn tiles_done(addr: &str, id: &str) -> u32 {
    support::get_job(addr, id)
        .and_then(|j| j.progress)
        .map_or(0, |p| p.tiles_done)
}

/// GetImage as PNG, or the status message.
fn get_png(addr: &str, id: &str) -> Result<Vec<u8>, String> {
    get_image(addr, id, ImageFormat::Png)
}

/// GetImage as EXR, or the status message.
fn get_exr(addr: &str, id: &str) -> Result<Vec<u8>, String> {
    get_image(addr, id, ImageFormat::Exr)
}

/// GetImage in `format`, or the status message.
fn get_image(addr: &str, id: &str, format: ImageFormat) -> Result<Vec<u8>, String> {
    rt().block_on(async {
        let mut c = RenderServiceClient::connect(format!("http://{addr}"))
            .await
            .map_err(|e| e.to_string())?
            .max_decoding_message_size(usize::MAX);
        c.get_image(GetImageRequest {
            job_id: id.to_string(),
            format: format as i32,
            ..Default::default()
        })
        .await
        .map(|r| r.into_inner().data.to_vec())
        .map_err(|s| format!("{:?}: {}", s.code(), s.message()))
    })
}

fn list_ids(addr: &str) -> Vec<String> {
    rt().block_on(async {
        let Ok(mut c) = RenderServiceClient::connect(format!("http://{addr}")).await else {
            return Vec::new();
        };
        c.list_jobs(ListJobsRequest::default())
            .await
            .map(|r| r.into_inner().jobs.into_iter().map(|j| j.job_id).collect())
            .unwrap_or_default()
    })
}

/// The reference image: `dray render --workers 0` (no actors) with the same flags.
fn reference(dir: &Path, tag: &str, flags: &[&str]) -> Vec<u8> {
    let mut all = flags.to_vec();
    all.extend(["--workers", "0"]);
    let run = common::render(dir, tag, "cornell:glass", &all);
    assert!(run.ok, "dray render failed: {}", run.stderr);
    std::fs::read(run.png.expect("png")).expect("read the reference png")
}

/// A small job, finished before the kill.
const SMALL: &[&str] = &["--width", "32", "--height", "24", "--spp", "4"];
/// A job long enough to kill the coordinator in the middle of (many small tiles).
const LONG: &[&str] = &[
    "--width",
    "128",
    "--height",
    "96",
    "--spp",
    "64",
    "--max-depth",
    "6",
    "--domains",
    "4",
];
/// The job submitted behind the long one.
const BEHIND: &[&str] = &[
    "--width", "48", "--height", "32", "--spp", "8", "--seed", "7",
];

#[test]
fn a_coordinator_killed_mid_job_resumes_it_with_the_same_bits() {
    let dir = common::tmp("durable-kill");
    let state = dir.join("state");
    let port = free_port();
    let (coord, addr, log) = coordinator(&dir, &state, port);
    let mut coord = Some((coord, log));
    let workers = [worker(&addr), worker(&addr)];
    let registered = |log: &support::Captured, n: usize| {
        eventually(60.0, || {
            log.text().matches("worker registered").count() >= n
        })
    };
    let log = |c: &Option<(Proc, support::Captured)>| {
        c.as_ref().map(|(_, l)| l.text()).unwrap_or_default()
    };
    assert!(
        registered(&coord.as_ref().expect("coordinator").1, 2),
        "{}",
        log(&coord)
    );

    let want_small = reference(&dir, "ref-small", SMALL);
    let want_long = reference(&dir, "ref-long", LONG);
    let want_behind = reference(&dir, "ref-behind", BEHIND);

    // A job that finishes before the kill.
    let (ok, out, png) = submit(&addr, &dir, "small", SMALL).finish();
    assert!(ok, "the first job failed: {out}\n{}", log(&coord));
    assert!(
        std::fs::read(&png).expect("png") == want_small,
        "the first image differs"
    );
    let small_id = support::submitted_job_id(&out).expect("the first job's id");

    // The long job, and one behind it; the coordinator dies once some tiles are in.
    let long = submit(&addr, &dir, "long", LONG);
    assert!(
        eventually(HANG_SECS, || long.id().is_some()),
        "{}",
        long.log.text()
    );
    let long_id = long.id().expect("id");
    let behind = submit(&addr, &dir, "behind", BEHIND);
    assert!(
        eventually(HANG_SECS, || behind.id().is_some()),
        "{}",
        behind.log.text()
    );
    assert!(
        eventually(HANG_SECS, || tiles_done(&addr, &long_id) >= 4),
        "no tile of the long job was done: {}",
        log(&coord)
    );
    let done_before = tiles_done(&addr, &long_id);
    let total = support::get_job(&addr, &long_id)
        .and_then(|j| j.progress)
        .map_or(0, |p| p.tiles_total);
    let first_log = log(&coord);
    if let Some((c, _)) = coord.take() {
        c.signal(libc::SIGKILL);
        // Reaped when dropped.
        drop(c);
    }
    assert!(
        done_before < total,
        "the long job ended before the kill ({done_before} of {total} tiles): make it longer"
    );

    // The same state directory, the same port: the workers register again, the jobs run.
    let (c, addr2, log2) = coordinator(&dir, &state, port);
    assert_eq!(addr2, addr);
    coord = Some((c, log2));
    assert!(
        registered(&coord.as_ref().expect("coordinator").1, 1),
        "the workers did not register again: {}",
        log(&coord)
    );

    let (ok, out, png) = long.finish();
    assert!(
        ok,
        "the resumed job failed: {out}\n--- new coordinator ---\n{}\n--- old ---\n{first_log}",
        log(&coord)
    );
    assert!(
        out.contains("lost the coordinator"),
        "dray submit did not say it waited for the coordinator: {out}"
    );
    assert!(
        std::fs::read(&png).expect("png") == want_long,
        "the resumed job's image differs from dray render's"
    );
    let (ok, out, png) = behind.finish();
    assert!(ok, "the job behind it failed: {out}\n{}", log(&coord));
    assert!(
        std::fs::read(&png).expect("png") == want_behind,
        "the job behind it differs"
    );

    // The resumed job kept tiles committed before the kill (the store had them).
    let resumed = log(&coord);
    let kept: u32 = resumed
        .lines()
        .filter(|l| l.contains("job taken back from the store") && l.contains(&long_id))
        .find_map(|l| {
            let rest = &l[l.find("tiles_kept=")? + "tiles_kept=".len()..];
            rest.split(|c: char| !c.is_ascii_digit())
                .next()?
                .parse()
                .ok()
        })
        .unwrap_or_else(|| panic!("no resume line for {long_id}: {resumed}"));
    assert!(
        kept > 0,
        "the resumed job kept no committed tile: {resumed}"
    );
    // (Progressive passes: a kept tile holds the passes it had finished; the job goes
    // on from the first pass some tile had not.)
    assert!(kept <= total, "{kept} of {total}");
    eprintln!(
        "resumed {long_id} with {kept} of {total} tiles kept ({done_before} seen done before the kill)"
    );

    // The first job's image is still served, and every job is listed.
    assert_eq!(
        get_png(&addr, &small_id).as_deref(),
        Ok(want_small.as_slice())
    );
    let ids = list_ids(&addr);
    for id in [&small_id, &long_id] {
        assert!(ids.contains(id), "{id} is not listed: {ids:?}");
    }
    assert_eq!(ids.len(), 3, "{ids:?}");

    // A second coordinator on the same state directory is refused, naming the lock.
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0"])
        .arg("--state-dir")
        .arg(&state)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let out = cmd.output().expect("run a second coordinator");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a second coordinator started: {err}");
    let line = err
        .lines()
        .find(|l| l.contains("error"))
        .unwrap_or_default();
    assert!(
        line.contains(&state.join("lock").display().to_string())
            && line.contains("another coordinator"),
        "{err}"
    );
    drop(workers);
    drop(coord);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Found by cli/tests/chaos.rs: SubmitJob answered before the job's row was on disk, so a
/// coordinator SIGKILLed just after the answer came back without a job its client had
/// been told was accepted (and `dray submit` blamed a missing state directory). Jobs are
/// submitted back to back, the last answer is followed at once by the kill: every job
/// accepted is there after the restart.
#[test]
fn every_job_accepted_before_a_kill_comes_back() {
    let dir = common::tmp("durable-accepted");
    let state = dir.join("state");
    let port = free_port();
    let (coord, addr, _log) = coordinator(&dir, &state, port);
    let accepted: Vec<String> = rt().block_on(async {
        let mut c = RenderServiceClient::connect(format!("http://{addr}"))
            .await
            .expect("connect");
        let mut ids = Vec::new();
        for seed in 0..40 {
            let spec = JobSpec {
                scene: "cornell".into(),
                width: 8,
                height: 8,
                spp: 1,
                seed,
                ..Default::default()
            };
            let r = c
                .submit_job(SubmitJobRequest { spec: Some(spec) })
                .await
                .expect("submit");
            ids.push(r.into_inner().job_id);
        }
        ids
    });
    coord.signal(libc::SIGKILL);
    drop(coord);
    let (_coord, addr, log) = coordinator(&dir, &state, port);
    let missing: Vec<&String> = accepted
        .iter()
        .filter(|id| support::get_job(&addr, id).is_none())
        .collect();
    assert!(
        missing.is_empty(),
        "{} of {} accepted jobs did not come back: {missing:?}\n{}",
        missing.len(),
        accepted.len(),
        log.text()
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Found by cli/tests/chaos.rs: `dray submit` followed its job across a coordinator
/// restart, but once the job had ended, GetImage went once: a coordinator lost between the
/// job's end and that call failed the client ("GetImage failed: transport error") though
/// the job had succeeded and its image was kept. Here the client is stopped while its job
/// ends (the last progress waits in its socket), the coordinator is killed, the client
/// continued, and the coordinator started again a moment later: the client waits for it
/// and writes the image.
#[test]
fn a_coordinator_lost_between_the_end_and_the_image_is_waited_for() {
    let dir = common::tmp("durable-image");
    let state = dir.join("state");
    let port = free_port();
    let (coord, addr, log) = coordinator(&dir, &state, port);
    // No worker: the coordinator renders the job itself (the same bits).
    let want = reference(&dir, "ref-long", LONG);
    let sub = submit(&addr, &dir, "long", LONG);
    assert!(
        eventually(HANG_SECS, || sub.id().is_some()),
        "{}",
        sub.log.text()
    );
    let id = sub.id().expect("id");
    sub.proc.signal(libc::SIGSTOP);
    assert!(
        support::get_job(&addr, &id)
            .and_then(|j| j.progress)
            .is_some_and(|p| !matches!(p.state(), dray_proto::v1::JobState::Succeeded)),
        "the job ended before the client was stopped: make it longer"
    );
    let ended = eventually(HANG_SECS, || {
        support::get_job(&addr, &id)
            .and_then(|j| j.progress)
            .is_some_and(|p| p.state() == dray_proto::v1::JobState::Succeeded)
    });
    // Let the last progress reach the client's socket before the coordinator goes.
    std::thread::sleep(std::time::Duration::from_millis(500));
    coord.signal(libc::SIGKILL);
    drop(coord);
    sub.proc.signal(libc::SIGCONT);
    assert!(ended, "the job did not succeed: {}", log.text());
    // The client read the job's end from its socket, and finds the coordinator gone
    // when it asks for the image (had the end been lost with the connection, WatchJob's
    // wait would have covered it: not this test's case).
    assert!(
        eventually(HANG_SECS, || {
            let t = sub.log.text();
            t.contains("succeeded") || t.contains("lost the coordinator")
        }),
        "{}",
        sub.log.text()
    );
    assert!(
        sub.log.text().contains("succeeded"),
        "the client did not see the job's end before the coordinator went: {}",
        sub.log.text()
    );
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let (_coord, _addr, log) = coordinator(&dir, &state, port);
    let (ok, out, png) = sub.finish();
    assert!(ok, "dray submit failed: {out}\n{}", log.text());
    assert!(
        std::fs::read(&png).expect("png") == want,
        "the image differs from dray render's"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// AOVs and adaptive sampling across a restart: the Cornell box with its glass sphere
/// seen through a wide lens, so the tiles around it see only the black outside and stop
/// at the first decision (16 samples, the end of pass 5 of 10) while the lit ones go on;
/// every AOV.
const ADAPTIVE: &[&str] = &[
    "--width",
    "256",
    "--height",
    "192",
    "--spp",
    "512",
    "--fov",
    "100",
    "--noise-threshold",
    "0.01",
    "--aov",
    "albedo,normal,depth,samples",
    "--domains",
    "4",
];
/// A small job with AOVs, finished before the kill: its image is read back from its file.
const SMALL_AOVS: &[&str] = &[
    "--width",
    "32",
    "--height",
    "24",
    "--spp",
    "4",
    "--aov",
    "albedo,normal,depth",
];

/// `dray render --workers 0` with `flags` and `--exr`: the PNG, the EXR and the stats.
fn reference_exr(dir: &Path, tag: &str, flags: &[&str]) -> (Vec<u8>, Vec<u8>, serde_json::Value) {
    let exr = dir.join(format!("{tag}.exr"));
    let exr_arg = exr.to_string_lossy().into_owned();
    let mut all = flags.to_vec();
    all.extend(["--workers", "0", "--exr", &exr_arg]);
    let run = common::render(dir, tag, "cornell:glass", &all);
    assert!(run.ok, "dray render failed: {}", run.stderr);
    (
        std::fs::read(run.png.expect("png")).expect("read the reference png"),
        std::fs::read(&exr).expect("read the reference exr"),
        run.stats.expect("stats"),
    )
}

/// A job with AOVs and a noise threshold commits its tiles (their AOV sums, and the
/// samples a stopped tile stopped at): a coordinator SIGKILLed after some tiles stopped
/// resumes the job keeping them, and the PNG and the multi-layer EXR are `dray render`'s
/// bits, with the same tiles stopped. A job with AOVs that finished before the kill is
/// served from its image file (format 3) with its AOVs.
#[test]
fn a_job_with_aovs_and_adaptive_sampling_resumes_with_the_same_bits() {
    let dir = common::tmp("durable-aovs");
    let state = dir.join("state");
    let port = free_port();
    let (coord, addr, log) = coordinator(&dir, &state, port);
    let mut coord = Some((coord, log));
    let log = |c: &Option<(Proc, support::Captured)>| {
        c.as_ref().map(|(_, l)| l.text()).unwrap_or_default()
    };
    let workers = [worker(&addr), worker(&addr)];
    assert!(
        eventually(60.0, || log(&coord).matches("worker registered").count()
            >= 2),
        "{}",
        log(&coord)
    );
    let (_, want_small, _) = reference_exr(&dir, "ref-small", SMALL_AOVS);
    let (want_png, want_exr, want_stats) = reference_exr(&dir, "ref-adaptive", ADAPTIVE);
    let stopped_ref = want_stats["tiles_stopped"].as_u64().expect("tiles_stopped");
    assert!(stopped_ref > 0, "no tile stops: {want_stats}");

    let small_exr = dir.join("small.exr");
    let mut flags = SMALL_AOVS.to_vec();
    flags.extend(["--exr", small_exr.to_str().expect("utf-8 path")]);
    let (ok, out, _) = submit(&addr, &dir, "small", &flags).finish();
    assert!(ok, "the small job failed: {out}\n{}", log(&coord));
    assert!(std::fs::read(&small_exr).expect("exr") == want_small);
    let small_id = support::submitted_job_id(&out).expect("the small job's id");

    let exr = dir.join("adaptive.exr");
    let mut flags = ADAPTIVE.to_vec();
    flags.extend(["--exr", exr.to_str().expect("utf-8 path")]);
    let job = submit(&addr, &dir, "adaptive", &flags);
    assert!(
        eventually(HANG_SECS, || job.id().is_some()),
        "{}",
        job.log.text()
    );
    let id = job.id().expect("id");
    // Killed once some tiles have stopped, two passes later: their commits, posted at
    // the end of pass 5 (a channel send; the store's thread writes them a moment later),
    // are on disk by then.
    let passes_done = || {
        support::get_job(&addr, &id)
            .and_then(|j| j.progress)
            .map_or(0, |p| p.passes_done)
    };
    assert!(
        eventually(HANG_SECS, || passes_done() >= 7),
        "the job did not reach pass 7: {}",
        log(&coord)
    );
    let stopped = support::get_job(&addr, &id)
        .and_then(|j| j.stats)
        .map_or(0, |s| s.tiles_stopped);
    assert!(stopped > 0, "no tile stopped: {}", log(&coord));
    let running = support::get_job(&addr, &id)
        .and_then(|j| j.progress)
        .is_some_and(|p| p.state() == dray_proto::v1::JobState::Running);
    let first_log = log(&coord);
    if let Some((c, _)) = coord.take() {
        c.signal(libc::SIGKILL);
        drop(c);
    }
    assert!(running, "the job ended before the kill: make it longer");

    let (c, _, log2) = coordinator(&dir, &state, port);
    coord = Some((c, log2));
    let (ok, out, png) = job.finish();
    assert!(
        ok,
        "the resumed job failed: {out}\n--- new coordinator ---\n{}\n--- old ---\n{first_log}",
        log(&coord)
    );
    assert!(
        std::fs::read(&png).expect("png") == want_png,
        "the resumed job's PNG differs from dray render's"
    );
    assert!(
        std::fs::read(&exr).expect("exr") == want_exr,
        "the resumed job's EXR (AOVs, samples) differs from dray render's"
    );
    // The tiles it kept, and the stopped ones among them (the coordinator's log).
    let resumed = log(&coord);
    let field = |name: &str| -> Option<u64> {
        let l = resumed
            .lines()
            .find(|l| l.contains("committed tiles put back") && l.contains(&id))?;
        let rest = &l[l.find(&format!("{name}="))? + name.len() + 1..];
        rest.split(|c: char| !c.is_ascii_digit())
            .next()?
            .parse()
            .ok()
    };
    let kept = field("kept").unwrap_or_else(|| panic!("no resume line for {id}: {resumed}"));
    let kept_stopped = field("stopped").expect("stopped=");
    assert!(
        kept > 0 && kept_stopped > 0,
        "kept {kept} tiles, {kept_stopped} of them stopped: {resumed}"
    );
    eprintln!("resumed {id} keeping {kept} tiles, {kept_stopped} of them stopped");
    let stats = support::get_job(&addr, &id)
        .and_then(|j| j.stats)
        .expect("stats");
    assert_eq!(
        u64::from(stats.tiles_stopped),
        stopped_ref,
        "tiles stopped, kept ones included"
    );
    assert_eq!(
        Some(stats.samples_saved),
        want_stats["samples_saved"].as_u64()
    );
    // The small job's image, read back from its file, keeps its AOVs.
    assert_eq!(
        get_exr(&addr, &small_id).as_deref(),
        Ok(want_small.as_slice())
    );
    drop(workers);
    drop(coord);
    let _ = std::fs::remove_dir_all(&dir);
}
