//! Jobs that survive their workers and their coordinator, with real processes:
//!
//! - a worker SIGKILLed mid-job: the job completes with the bits of `dray render`;
//! - a worker SIGSTOPped past the heartbeat timeout: the same; once resumed it registers
//!   again and takes the next job;
//! - a worker that joins mid-job (dynamic schedule) takes domains;
//! - a worker that joins a replicated job mid-pass takes tiles nobody had started, and
//!   the image is a 1-worker render's, byte for byte;
//! - a coordinator restart without a state directory fails its jobs with a clear status
//!   (dray submit waits for the coordinator, then says the job is gone), and the workers
//!   stay up and take the next job (cli/tests/durable.rs: with one, nothing is lost).
//!
//! Each test starts its own coordinator (heartbeats every 100 ms, lost after 2 s) and
//! workers one by one, so it can stop any of them. Nothing here bounds elapsed time:
//! tests wait for events, with generous limits that only catch hangs.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_proto::v1::GetJobRequest;
use dray_proto::v1::render_service_client::RenderServiceClient;
use support::{Proc, capture_stderr, dray, eventually, free_port};

/// A limit that only catches hangs.
const HANG_SECS: f64 = 240.0;

fn text(log: &Arc<Mutex<String>>) -> String {
    dray_sync::lock(log).clone()
}

/// A coordinator and the workers started against it, one process each.
struct Cluster {
    dir: PathBuf,
    addr: String,
    log: support::Captured,
    workers: Vec<Proc>,
    /// Each worker's stderr, for failure messages.
    worker_logs: Vec<support::Captured>,
    coordinator: Proc,
}

impl Cluster {
    /// A coordinator on `port` (0: any) with a 2 s heartbeat timeout.
    fn coordinator(dir: &Path, port: u16) -> (Proc, String, support::Captured) {
        support::logged_coordinator(dir, port, &[])
    }

    fn start(tag: &str, workers: usize, worker_flags: &[&str]) -> Cluster {
        let dir = common::tmp(tag);
        let (coordinator, addr, log) = Cluster::coordinator(&dir, 0);
        let mut c = Cluster {
            dir,
            addr,
            log,
            workers: Vec::new(),
            worker_logs: Vec::new(),
            coordinator,
        };
        for _ in 0..workers {
            c.add_worker(worker_flags);
        }
        let want = workers;
        assert!(
            eventually(60.0, || c.registered() >= want),
            "the workers did not register: {}",
            text(&c.log)
        );
        c
    }

    fn registered(&self) -> usize {
        text(&self.log).matches("worker registered").count()
    }

    fn add_worker(&mut self, flags: &[&str]) {
        let mut cmd = dray();
        cmd.args(["worker", "--coordinator", &format!("http://{}", self.addr)])
            .args(["--listen", "127.0.0.1:0", "--threads", "1"])
            .args(flags)
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut p = Proc::spawn(cmd);
        self.worker_logs.push(capture_stderr(&mut p.child));
        self.workers.push(p);
    }

    /// How many times the coordinator declared a worker lost.
    fn lost(&self) -> usize {
        text(&self.log).matches("worker lost").count()
    }

    /// What a failure message needs: the coordinator's log and whether it still
    /// answers, and worker `w`'s process state and log.
    fn diagnose(&self, w: usize) -> String {
        format!(
            "coordinator alive: {}, GetJob: {}\nworker {w} state: {}\n\
             --- coordinator log ---\n{}\n--- worker {w} log ---\n{}",
            support::alive(self.coordinator.pid()),
            probe(&self.addr),
            process_state(self.workers[w].pid()),
            text(&self.log),
            text(&self.worker_logs[w]),
        )
    }
}

/// The state letter of `pid` from /proc (R, S, T for stopped, Z), or why it is unknown.
fn process_state(pid: i32) -> String {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(s) => s
            .rsplit(')')
            .next()
            .and_then(|rest| rest.split_whitespace().next())
            .unwrap_or("?")
            .to_string(),
        Err(e) => format!("unreadable ({e})"),
    }
}

/// A `dray submit` running in the background; its stderr carries progress and the id.
struct Submit {
    proc: Proc,
    log: support::Captured,
}

fn submit(addr: &str, scene: &str, flags: &[&str], png: &Path, stats: &Path) -> Submit {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, scene])
        .args(flags)
        .arg("--output")
        .arg(png)
        .arg("--stats")
        .arg(stats)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut proc = Proc::spawn(cmd);
    let log = capture_stderr(&mut proc.child);
    Submit { proc, log }
}

impl Submit {
    fn id(&self) -> String {
        let t = text(&self.log);
        t.lines()
            .find_map(|l| {
                l.strip_prefix("dray submit: job ")?
                    .split_once(" accepted by ")
                    .map(|(id, _)| id.to_string())
            })
            .unwrap_or_else(|| panic!("no job id in dray submit's output: {t}"))
    }

    fn running(&self) -> bool {
        text(&self.log).contains(": running, ")
    }

    /// Wait for the client to end; its exit status and output.
    fn finish(mut self) -> (bool, String) {
        let status = self.proc.wait_timeout(HANG_SECS);
        let out = self.log.after(status.is_some());
        let Some(status) = status else {
            panic!("HANG: dray submit did not finish within {HANG_SECS} s:\n{out}");
        };
        (status.success(), out)
    }
}

/// Whether the coordinator answers an API call: the status of GetJob for an unknown
/// job (NOT_FOUND when it does), with a limit so a wedged server shows as such.
fn probe(addr: &str) -> String {
    let Ok(rt) = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    else {
        return "no runtime to ask".into();
    };
    rt.block_on(async {
        let call = async {
            let mut c = RenderServiceClient::connect(format!("http://{addr}"))
                .await
                .map_err(|e| format!("cannot connect: {e}"))?;
            c.get_job(GetJobRequest {
                job_id: "probe-unknown".into(),
            })
            .await
            .map(|_| "answered".to_string())
            .map_err(|s| format!("{:?}: {}", s.code(), s.message()))
        };
        match tokio::time::timeout(Duration::from_secs(10), call).await {
            Ok(Ok(s)) | Ok(Err(s)) => s,
            Err(_) => "no answer within 10 s".into(),
        }
    })
}

fn tiles_done(addr: &str, id: &str) -> u32 {
    support::get_job(addr, id)
        .and_then(|j| j.progress)
        .map_or(0, |p| p.tiles_done)
}

/// The reference image: `dray render --workers 0` (no actors) with the same flags.
fn reference(dir: &Path, tag: &str, scene: &str, flags: &[&str]) -> Vec<u8> {
    let mut all = flags.to_vec();
    all.extend(["--workers", "0"]);
    let run = common::render(dir, tag, scene, &all);
    assert!(run.ok, "dray render failed: {}", run.stderr);
    std::fs::read(run.png.expect("png")).expect("read the reference png")
}

/// A small job on the cluster as it is now gives the reference image; its stats.
fn next_job_is_right(c: &Cluster, tag: &str, domains: u32) -> serde_json::Value {
    let d = domains.to_string();
    let flags = [
        "--width",
        "40",
        "--height",
        "30",
        "--spp",
        "4",
        "--domains",
        &d,
    ];
    let want = reference(&c.dir, &format!("{tag}-reference"), "cornell", &flags);
    let png = c.dir.join(format!("{tag}.png"));
    let stats = c.dir.join(format!("{tag}.json"));
    let (ok, out) = submit(&c.addr, "cornell", &flags, &png, &stats).finish();
    assert!(ok, "the next job failed: {out}");
    assert!(
        std::fs::read(&png).expect("png") == want,
        "the next job's image differs"
    );
    serde_json::from_slice(&std::fs::read(&stats).expect("read stats")).expect("stats json")
}

/// A job long enough to lose a worker in the middle of (many small tiles), with domains
/// spread over every worker.
const SCENE: &str = "cornell:glass";
const FLAGS: &[&str] = &[
    "--width",
    "128",
    "--height",
    "96",
    "--spp",
    "48",
    "--integrator",
    "path",
    "--max-depth",
    "6",
    "--domains",
    "9",
    "--schedule",
    "domain",
];

/// Lose worker `victim` of three with `signal` once some tiles are done: the job
/// completes with the reference bits, and the loss shows in its stats.
fn lose_a_worker_mid_job(tag: &str, signal: i32) -> Cluster {
    let c = Cluster::start(tag, 3, &[]);
    let want = reference(&c.dir, "reference", SCENE, FLAGS);
    let png = c.dir.join("job.png");
    let stats = c.dir.join("job.json");
    let s = submit(&c.addr, SCENE, FLAGS, &png, &stats);
    assert!(
        eventually(HANG_SECS, || s.running()),
        "the job never ran: {}",
        text(&s.log)
    );
    let id = s.id();
    assert!(
        eventually(HANG_SECS, || tiles_done(&c.addr, &id) > 0),
        "no tile was done: {}",
        text(&s.log)
    );
    let lost_before = c.lost();
    c.workers[1].signal(signal);
    let (ok, out) = s.finish();
    assert!(
        ok,
        "the job did not survive a lost worker: {out}\n{}",
        text(&c.log)
    );
    let got = std::fs::read(&png).expect("read the job's png");
    assert!(got == want, "the image changed after a worker was lost");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&stats).expect("read stats")).expect("stats json");
    eprintln!(
        "{tag}: tiles re-traced {}, domain loads {}",
        json["tiles_retraced"], json["domain_loads"]
    );
    // The job may end before the loss is noticed (the victim's share can be done by
    // then); either way the coordinator must declare it lost, within its heartbeat
    // timeout for a stopped worker.
    assert!(
        eventually(HANG_SECS, || c.lost() > lost_before),
        "the coordinator never declared worker 1 lost:\n{}",
        c.diagnose(1)
    );
    c
}

#[test]
fn a_killed_worker_changes_nothing_in_the_image() {
    let c = lose_a_worker_mid_job("faults-kill", libc::SIGKILL);
    let _ = std::fs::remove_dir_all(&c.dir);
}

#[test]
fn a_worker_stopped_past_the_heartbeat_timeout_changes_nothing_and_rejoins() {
    let c = lose_a_worker_mid_job("faults-stop", libc::SIGSTOP);
    // Resumed, it learns it was declared lost, registers again and takes work.
    let before = c.registered();
    c.workers[1].signal(libc::SIGCONT);
    assert!(
        eventually(HANG_SECS, || c.registered() > before),
        "the resumed worker did not register again:\n{}",
        c.diagnose(1)
    );
    next_job_is_right(&c, "after", 6);
    assert!(c.workers.iter().all(|w| support::alive(w.pid())));
    let _ = std::fs::remove_dir_all(&c.dir);
}

/// Submit `flags` on SCENE to `c` (one worker), start a second worker once the job runs
/// and wait for it to register; the job must succeed with the reference image (`dray
/// render --workers 0`, the same bits as one worker). Its `--stats` JSON.
fn join_mid_job(c: &mut Cluster, flags: &[&str]) -> serde_json::Value {
    let want = reference(&c.dir, "reference", SCENE, flags);
    let png = c.dir.join("job.png");
    let stats = c.dir.join("job.json");
    let s = submit(&c.addr, SCENE, flags, &png, &stats);
    assert!(
        eventually(HANG_SECS, || s.running()),
        "the job never ran: {}",
        text(&s.log)
    );
    c.add_worker(&[]);
    assert!(
        eventually(HANG_SECS, || c.registered() >= 2),
        "{}",
        text(&c.log)
    );
    let (ok, out) = s.finish();
    assert!(ok, "{out}\n{}", text(&c.log));
    assert!(
        std::fs::read(&png).expect("png") == want,
        "the image differs from the reference"
    );
    serde_json::from_slice(&std::fs::read(&stats).expect("read stats")).expect("stats json")
}

#[test]
fn a_worker_joining_mid_job_takes_domains() {
    // The first worker's budget holds only some of the domains, so wanted domains wait
    // unloaded for the newcomer, which the dynamic scheduler gives them to.
    let flags: &[&str] = &[
        "--width",
        "160",
        "--height",
        "120",
        "--spp",
        "48",
        "--integrator",
        "path",
        "--domains",
        "12",
        "--schedule",
        "dynamic",
    ];
    // The first worker's loads are slowed (`--load-delay-ms`) so the job outlasts the
    // newcomer's start; on a machine slow enough that it still ends first, the job runs
    // again with slower loads, and the test fails (never skips) if it never overlaps.
    for (round, delay_ms) in ["100", "400", "1500"].into_iter().enumerate() {
        let tag = format!("faults-join-{round}");
        let mut c = Cluster::start(
            &tag,
            1,
            &["--memory-budget", "800000", "--load-delay-ms", delay_ms],
        );
        let json = join_mid_job(&mut c, flags);
        let workers = json["workers"].as_array().cloned().unwrap_or_default();
        eprintln!("join (load delay {delay_ms} ms): per worker {workers:?}");
        let _ = std::fs::remove_dir_all(&c.dir);
        if workers.len() < 2 {
            // The whole job ended before the newcomer registered: slower loads next.
            eprintln!("join: the job ended before the new worker joined; again with slower loads");
            continue;
        }
        let newcomer = &workers[1];
        assert!(
            newcomer["domain_loads"].as_u64().unwrap_or(0) > 0
                && newcomer["rays_traced"].as_u64().unwrap_or(0) > 0,
            "the worker that joined took no domain: {json}"
        );
        return;
    }
    panic!("the job ended before the new worker joined in every round, loads slowed to 1.5 s");
}

#[test]
fn a_worker_joining_a_replicated_job_takes_tiles_nobody_started() {
    // One pass (no later pass to take a share of): the newcomer's tiles can only come
    // from those the job had not dealt when it joined. 48 tiles of 32x32 on one worker
    // deal in windows of 12, so 36 wait for whoever has room.
    let base: &[&str] = &[
        "--width",
        "256",
        "--height",
        "192",
        "--integrator",
        "path",
        "--max-depth",
        "6",
        "--schedule",
        "replicated",
        "--passes",
        "one",
    ];
    // On a machine fast enough to finish before the newcomer starts, the job runs again
    // with more samples; the test fails (never skips) if it never overlaps.
    for (round, spp) in ["48", "192", "768"].into_iter().enumerate() {
        let flags = [base, &["--spp", spp]].concat();
        let tag = format!("faults-join-replicated-{round}");
        let mut c = Cluster::start(&tag, 1, &[]);
        let json = join_mid_job(&mut c, &flags);
        assert_eq!(json["schedule"], "replicated", "{json}");
        let workers = json["workers"].as_array().cloned().unwrap_or_default();
        eprintln!(
            "join replicated ({spp} spp): tiles dealt later {}, per worker {workers:?}",
            json["tiles_dealt_later"]
        );
        let _ = std::fs::remove_dir_all(&c.dir);
        if workers.len() < 2 {
            eprintln!("join replicated: the job ended before the new worker joined; more samples");
            continue;
        }
        let newcomer = &workers[1];
        assert!(
            newcomer["rays_traced"].as_u64().unwrap_or(0) > 0,
            "the worker that joined traced nothing: {json}"
        );
        assert_eq!(
            newcomer["domain_loads"].as_u64().unwrap_or(0)
                + newcomer["domains_warm"].as_u64().unwrap_or(0),
            1,
            "the newcomer holds the whole scene (one domain): {json}"
        );
        assert!(
            json["tiles_dealt_later"].as_u64().unwrap_or(0) > 0,
            "{json}"
        );
        assert_eq!(
            json["rays_exchanged"], 0,
            "replicated: no ray moves: {json}"
        );
        return;
    }
    panic!("the replicated job ended before the new worker joined in every round, at 768 spp");
}

#[test]
fn a_coordinator_restart_fails_its_jobs_and_the_workers_take_the_next() {
    let port = free_port();
    let dir = common::tmp("faults-restart");
    let (coordinator, addr, log) = Cluster::coordinator(&dir, port);
    let mut c = Cluster {
        dir,
        addr,
        log,
        workers: Vec::new(),
        worker_logs: Vec::new(),
        coordinator,
    };
    c.add_worker(&[]);
    assert!(eventually(60.0, || c.registered() >= 1), "{}", text(&c.log));
    let png = c.dir.join("lost.png");
    let s = submit(&c.addr, SCENE, FLAGS, &png, &c.dir.join("lost.json"));
    assert!(
        eventually(HANG_SECS, || s.running()),
        "the job never ran: {}",
        text(&s.log)
    );
    c.coordinator.signal(libc::SIGKILL);
    // A new coordinator on the same port, with no state directory: the worker registers
    // again; dray submit, which waited for it, finds its job gone and says why.
    let (coordinator, addr, log) = Cluster::coordinator(&c.dir, port);
    c.coordinator = coordinator;
    c.addr = addr;
    c.log = log;
    let (ok, out) = s.finish();
    assert!(
        !ok,
        "a job whose coordinator died without a state directory cannot succeed: {out}"
    );
    let last = out.lines().last().unwrap_or_default().to_string();
    eprintln!("restart: dray submit said: {last}");
    assert!(
        out.contains("lost the coordinator") && last.contains("came back without job"),
        "dray submit did not say what happened: {out}"
    );
    assert!(
        eventually(HANG_SECS, || c.registered() >= 1),
        "the worker did not register with the new coordinator: {}",
        text(&c.log)
    );
    assert!(support::alive(c.workers[0].pid()), "the worker exited");
    let json = next_job_is_right(&c, "next", 4);
    assert!(
        json["workers"].as_array().is_some_and(|w| !w.is_empty()),
        "the next job did not run on the worker: {json}"
    );
    let _ = std::fs::remove_dir_all(&c.dir);
}
