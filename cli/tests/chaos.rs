//! Chaos: many short jobs over a real multi-process cluster (a `dray coordinator` on a
//! state directory and three `dray worker`s, talking gRPC), each of a random shape
//! (scene, size, samples, integrator, schedule, pass mode, domain count and layout),
//! while a driver SIGKILLs workers (restarting them on their ports, as `dray cluster`
//! does), SIGSTOPs and SIGCONTs them (sometimes past the heartbeat timeout, so they are
//! declared lost and come back), and SIGKILLs the coordinator and starts it again on its
//! state directory, at random moments (issue 38).
//!
//! Every job must end SUCCEEDED with the bits of `dray render --workers 0` of the same
//! scene and image flags, or FAILED with a reason; a job unfinished past a bound derived
//! from its size (counted from its submission or the last disturbance of the cluster,
//! whichever is later) is a hang. The counts are printed at the end: jobs, kills, stops,
//! restarts, hangs, wrong images.
//!
//! Seeded: the seed is printed, `DRAY_CHAOS_SEED` replays it (the same jobs and the same
//! faults in the same order; their moments relative to the jobs depend on the machine),
//! `DRAY_CHAOS_JOBS` sets the number of jobs (default 40; `benches/chaos.sh --long` runs
//! hundreds); with `DRAY_CHAOS_LOGS` set, every process's log is printed when a job
//! fails (it always is for a hang). Nothing here bounds elapsed time but the hang bound,
//! which only catches hangs.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use support::port_worker::PortWorker;
use support::seeded::{self, Rng};
use support::{Captured, Proc, capture_stderr, dray, eventually};

/// Workers of the cluster; at most `WORKERS - 1` are down or stopped at once.
const WORKERS: usize = 3;
/// Jobs running at once.
const IN_FLIGHT: usize = 3;

/// One job's shape: what `dray submit` gets. The image flags alone go to the reference.
#[derive(Clone, Debug)]
struct Spec {
    scene: String,
    width: u32,
    height: u32,
    spp: u32,
    integrator: &'static str,
    max_depth: u32,
    seed: u32,
    domains: u32,
    layout: &'static str,
    schedule: &'static str,
    replicate: bool,
    passes: String,
}

impl Spec {
    fn random(rng: &mut Rng) -> Spec {
        let scene = match rng.below(5) {
            0 => "cornell".to_string(),
            1 => "cornell:glass".to_string(),
            2 => "cornell:mirror".to_string(),
            3 => format!("spheres:{}", rng.between(8, 300)),
            _ => format!("soup:{}", rng.between(50, 1500)),
        };
        let spp = rng.between(4, 64) as u32;
        let passes = match rng.below(4) {
            0 => "one".to_string(),
            1 | 2 => "doubling".to_string(),
            _ => rng.between(1, u64::from(spp)).to_string(),
        };
        let schedule = rng.pick(&[
            "auto",
            "replicated",
            "image-plane",
            "domain",
            "dynamic",
            "dynamic",
        ]);
        Spec {
            scene,
            width: rng.between(48, 160) as u32,
            height: rng.between(32, 120) as u32,
            spp,
            integrator: rng.pick(&["raycast", "whitted", "path", "path", "ao"]),
            max_depth: rng.between(1, 5) as u32,
            seed: rng.below(1000) as u32,
            domains: rng.between(1, 8) as u32,
            layout: rng.pick(&["grid", "kd"]),
            schedule,
            replicate: matches!(schedule, "dynamic" | "auto") && rng.below(3) == 0,
            passes,
        }
    }

    /// The flags that make the image (the reference gets these and nothing else).
    fn image_flags(&self) -> Vec<String> {
        [
            "--width",
            &self.width.to_string(),
            "--height",
            &self.height.to_string(),
            "--spp",
            &self.spp.to_string(),
            "--integrator",
            self.integrator,
            "--max-depth",
            &self.max_depth.to_string(),
            "--seed",
            &self.seed.to_string(),
        ]
        .map(String::from)
        .to_vec()
    }

    /// Every flag of the job: the image's, and how it is cut and scheduled.
    fn job_flags(&self) -> Vec<String> {
        let mut f = self.image_flags();
        f.extend(
            [
                "--domains",
                &self.domains.to_string(),
                "--layout",
                self.layout,
                "--schedule",
                self.schedule,
                "--passes",
                &self.passes,
            ]
            .map(String::from),
        );
        if self.replicate {
            f.push("--replicate".into());
        }
        f
    }

    /// How long the job may stay unfinished after its submission or the cluster's last
    /// disturbance before it counts as hung: generous for its size on a loaded two-core
    /// machine (these jobs take a few seconds undisturbed), and above the heartbeat
    /// timeout a loss waits for.
    fn hang_bound(&self) -> Duration {
        let per_sample = match self.integrator {
            "path" | "whitted" => u64::from(self.max_depth),
            "ao" => 16,
            _ => 1,
        };
        let work = u64::from(self.width) * u64::from(self.height) * u64::from(self.spp);
        Duration::from_secs(60 + work * per_sample / 50_000)
    }
}

/// A job in flight: its `dray submit` and, beside it, its reference render.
struct Job {
    n: usize,
    spec: Spec,
    submit: Proc,
    log: Captured,
    png: PathBuf,
    reference: Proc,
    reference_png: PathBuf,
    submitted: Instant,
}

impl Job {
    fn start(dir: &Path, addr: &str, n: usize, spec: Spec) -> Job {
        let png = dir.join(format!("job-{n}.png"));
        let reference_png = dir.join(format!("job-{n}-reference.png"));
        let mut cmd = dray();
        cmd.args(["submit", "--coordinator", addr, &spec.scene])
            .args(spec.job_flags())
            .arg("--output")
            .arg(&png)
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut submit = Proc::spawn(cmd);
        let log = capture_stderr(&mut submit.child);
        let mut cmd = dray();
        cmd.args(["render", &spec.scene])
            .args(spec.image_flags())
            .args(["--workers", "0", "-q", "--output"])
            .arg(&reference_png)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        Job {
            n,
            spec,
            submit,
            log,
            png,
            reference: Proc::spawn(cmd),
            reference_png,
            submitted: Instant::now(),
        }
    }

    fn id(&self) -> Option<String> {
        support::submitted_job_id(&self.log.text())
    }
}

/// What a worker slot is going through.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    Healthy,
    /// SIGSTOPped; SIGCONT at the instant.
    Stopped(Instant),
    /// SIGKILLed; a new worker starts on its port at the instant.
    Down(Instant),
}

/// The cluster the driver disturbs: the coordinator (restartable on its port and state
/// directory) and the workers (restartable on their ports).
struct Cluster {
    dir: PathBuf,
    port: u16,
    addr: String,
    coordinator: Option<(Proc, Captured)>,
    /// When the killed coordinator starts again.
    coordinator_back: Option<Instant>,
    workers: Vec<PortWorker>,
    faults: Vec<Fault>,
    /// Logs of processes that were killed, for the report of a hang.
    old_logs: Vec<String>,
    /// The last moment the cluster was disturbed or came back from a disturbance.
    last_disturbance: Instant,
    kills: usize,
    stops: usize,
    restarts: usize,
}

/// Worker `i`'s flags: the first has a memory budget (ample for these scenes), so a job
/// dealt while it is in the cluster traces its passes ahead (docs/architecture.md "Trace
/// ahead") and one dealt while it is down does not: kills meet both.
fn worker_flags(i: usize) -> &'static [&'static str] {
    if i == 0 {
        &["--memory-budget", "512M"]
    } else {
        &[]
    }
}

impl Cluster {
    fn start(dir: &Path) -> Cluster {
        // Ports below the kernel's ephemeral range, so that no outgoing connection takes
        // one between a kill and the restart on it.
        let port = (0..8)
            .map(|attempt| support::cluster_base_port(0, attempt))
            .find(|&p| {
                (0..=WORKERS as u16)
                    .all(|i| std::net::TcpListener::bind(("127.0.0.1", p + i)).is_ok())
            })
            .expect("no free ports for the chaos cluster");
        let (proc, addr, log) = Cluster::coordinator(dir, port);
        let workers: Vec<PortWorker> = (1..=WORKERS as u16)
            .map(|i| PortWorker::start_with(&addr, port + i, worker_flags(usize::from(i) - 1)))
            .collect();
        assert!(
            eventually(60.0, || log.text().matches("worker registered").count()
                >= WORKERS),
            "the workers did not register: {}",
            log.text()
        );
        Cluster {
            dir: dir.to_path_buf(),
            port,
            addr,
            coordinator: Some((proc, log)),
            coordinator_back: None,
            workers,
            faults: vec![Fault::Healthy; WORKERS],
            old_logs: Vec::new(),
            last_disturbance: Instant::now(),
            kills: 0,
            stops: 0,
            restarts: 0,
        }
    }

    /// A coordinator on `port` keeping its jobs in DIR/state.
    fn coordinator(dir: &Path, port: u16) -> (Proc, String, Captured) {
        let (state, work) = (dir.join("state"), dir.join("work"));
        support::logged_coordinator(
            dir,
            port,
            &[
                "--state-dir".as_ref(),
                state.as_os_str(),
                "--work-dir".as_ref(),
                work.as_os_str(),
            ],
        )
    }

    fn coordinator_up(&self) -> bool {
        self.coordinator.is_some()
    }

    /// End the faults whose time has come: SIGCONT, a new worker, the coordinator back.
    fn heal(&mut self, now: Instant) {
        for i in 0..WORKERS {
            match self.faults[i] {
                Fault::Stopped(at) if now >= at => {
                    self.workers[i].proc.signal(libc::SIGCONT);
                    eprintln!("chaos: worker {i} continued");
                }
                Fault::Down(at) if now >= at => {
                    let port = self.workers[i].port;
                    self.workers[i] = PortWorker::start_with(&self.addr, port, worker_flags(i));
                    eprintln!("chaos: worker {i} started again on port {port}");
                }
                _ => continue,
            }
            self.faults[i] = Fault::Healthy;
            self.last_disturbance = now;
        }
        if self.coordinator_back.is_some_and(|at| now >= at) {
            let (proc, addr, log) = Cluster::coordinator(&self.dir, self.port);
            assert_eq!(addr, self.addr, "the coordinator came back elsewhere");
            self.coordinator = Some((proc, log));
            self.coordinator_back = None;
            self.last_disturbance = now;
            eprintln!("chaos: coordinator started again on its state directory");
        }
    }

    /// One random fault: kill or stop a healthy worker (leaving at least one healthy),
    /// or kill the coordinator when `may_kill_coordinator`. False when the fault drawn
    /// was not possible (nothing was done).
    fn disturb(&mut self, rng: &mut Rng, now: Instant, may_kill_coordinator: bool) -> bool {
        let healthy: Vec<usize> = (0..WORKERS)
            .filter(|&i| self.faults[i] == Fault::Healthy)
            .collect();
        let kind = rng.below(6);
        if kind == 5 {
            if may_kill_coordinator && self.coordinator_up() {
                let pause = Duration::from_millis(rng.below(1000));
                if let Some((proc, log)) = self.coordinator.take() {
                    proc.signal(libc::SIGKILL);
                    drop(proc);
                    self.old_logs
                        .push(format!("--- coordinator (killed) ---\n{}", log.to_end()));
                }
                self.coordinator_back = Some(now + pause);
                self.restarts += 1;
                self.last_disturbance = now;
                eprintln!(
                    "chaos: coordinator killed, back in {} ms",
                    pause.as_millis()
                );
                return true;
            }
            return false;
        }
        if healthy.len() < 2 {
            return false;
        }
        let i = rng.pick(&healthy);
        if kind < 3 {
            let pause = Duration::from_millis(rng.below(1000));
            self.workers[i].proc.signal(libc::SIGKILL);
            let _ = self.workers[i].proc.wait_timeout(30.0);
            self.old_logs.push(format!(
                "--- worker {i} (killed) ---\n{}",
                self.workers[i].log.text()
            ));
            self.faults[i] = Fault::Down(now + pause);
            self.kills += 1;
            eprintln!(
                "chaos: worker {i} killed, a new one in {} ms",
                pause.as_millis()
            );
        } else {
            // Up to twice the heartbeat timeout (2 s): sometimes declared lost.
            let pause = Duration::from_millis(rng.between(200, 4000));
            self.workers[i].proc.signal(libc::SIGSTOP);
            self.faults[i] = Fault::Stopped(now + pause);
            self.stops += 1;
            eprintln!("chaos: worker {i} stopped for {} ms", pause.as_millis());
        }
        self.last_disturbance = now;
        true
    }

    /// The logs that tell a hang's story: the last processes killed, the live ones; each
    /// cut to its end (a long run's logs would bury the moment).
    fn logs(&self) -> String {
        let mut parts = self.old_logs[self.old_logs.len().saturating_sub(6)..].to_vec();
        if let Some((_, log)) = &self.coordinator {
            parts.push(format!("--- coordinator ---\n{}", log.text()));
        }
        for (i, w) in self.workers.iter().enumerate() {
            parts.push(format!("--- worker {i} ---\n{}", w.log.text()));
        }
        parts
            .iter()
            .map(|p| match p.char_indices().rev().nth(20_000) {
                Some((at, _)) => format!("[...]{}", &p[at..]),
                None => p.clone(),
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

/// How a job ended.
#[derive(Debug, PartialEq)]
enum End {
    Succeeded,
    Failed(String),
    Wrong(String),
    Unexplained(String),
    Hung(String),
}

/// The end of a job whose `dray submit` exited with `ok`.
fn judge(job: &mut Job, ok: bool) -> End {
    let out = job.log.to_end();
    if !ok {
        let reason = job
            .id()
            .and_then(|id| {
                let marker = format!("job {id} failed: ");
                out.lines()
                    .find_map(|l| Some(l[l.find(&marker)? + marker.len()..].trim().to_string()))
            })
            .filter(|r| !r.is_empty());
        return match reason {
            Some(r) => End::Failed(r),
            None => End::Unexplained(out),
        };
    }
    let reference = match job.reference.wait_timeout(300.0) {
        Some(s) if s.success() => std::fs::read(&job.reference_png).ok(),
        _ => None,
    };
    let Some(reference) = reference else {
        return End::Unexplained(format!("the reference render of job {} failed", job.n));
    };
    match std::fs::read(&job.png) {
        Ok(got) if got == reference => End::Succeeded,
        Ok(_) => End::Wrong(format!(
            "{} differs from dray render's {}",
            job.png.display(),
            job.reference_png.display()
        )),
        Err(e) => End::Unexplained(format!("no image at {}: {e}", job.png.display())),
    }
}

#[test]
fn jobs_under_kills_stops_and_coordinator_restarts_succeed_with_the_bits_or_fail_with_a_reason() {
    let seed = seeded::seed("DRAY_CHAOS_SEED");
    let jobs = seeded::count("DRAY_CHAOS_JOBS", 40);
    eprintln!("chaos: seed {seed} (DRAY_CHAOS_SEED={seed} replays it), {jobs} jobs");
    let mut rng = Rng(seed);
    let dir = common::tmp("chaos");
    let began = Instant::now();
    let mut cluster = Cluster::start(&dir);
    let mut running: Vec<Job> = Vec::new();
    let (mut submitted, mut succeeded, mut failed) = (0, 0, 0);
    let mut bad: Vec<String> = Vec::new();
    let (mut hangs, mut wrong, mut unexplained, mut disturbed_jobs) = (0, 0, 0, 0);
    let mut next_fault = Instant::now() + Duration::from_millis(rng.between(200, 1500));
    while submitted < jobs || !running.is_empty() {
        let now = Instant::now();
        cluster.heal(now);
        while running.len() < IN_FLIGHT && submitted < jobs && cluster.coordinator_up() {
            let spec = Spec::random(&mut rng);
            eprintln!(
                "chaos: job {submitted}: {} {}",
                spec.scene,
                spec.job_flags().join(" ")
            );
            running.push(Job::start(&dir, &cluster.addr, submitted, spec));
            submitted += 1;
        }
        // Faults while jobs are still being submitted; the last ones finish in peace.
        if submitted < jobs && now >= next_fault {
            // Not while a submission is under way (the client's SubmitJob is not what
            // this tests): the coordinator dies only once every job has its id.
            let all_accepted = running.iter().all(|j| j.id().is_some());
            if cluster.disturb(&mut rng, now, all_accepted) {
                disturbed_jobs += running.len();
            }
            next_fault = now + Duration::from_millis(rng.between(200, 1500));
        }
        let mut i = 0;
        while i < running.len() {
            let job = &mut running[i];
            let end = match job.submit.child.try_wait() {
                Ok(Some(status)) => judge(job, status.success()),
                _ => {
                    let since = job.submitted.max(cluster.last_disturbance);
                    if now.saturating_duration_since(since) <= job.spec.hang_bound() {
                        i += 1;
                        continue;
                    }
                    let progress = job
                        .id()
                        .and_then(|id| support::get_job(&cluster.addr, &id))
                        .and_then(|j| j.progress);
                    End::Hung(format!(
                        "unfinished {} s after the cluster's last disturbance: {progress:?}\n\
                         --- dray submit ---\n{}\n{}",
                        now.saturating_duration_since(since).as_secs(),
                        job.log.text(),
                        cluster.logs()
                    ))
                }
            };
            let job = running.swap_remove(i);
            let what = format!(
                "job {} ({:?}, {} s)",
                job.n,
                job.id(),
                job.submitted.elapsed().as_secs()
            );
            match end {
                End::Succeeded => {
                    succeeded += 1;
                    eprintln!("chaos: {what}: SUCCEEDED with dray render's bits");
                }
                End::Failed(reason) => {
                    failed += 1;
                    eprintln!("chaos: {what}: FAILED: {reason}");
                    if std::env::var_os("DRAY_CHAOS_LOGS").is_some() {
                        eprintln!("{}", cluster.logs());
                    }
                }
                other => {
                    let label = match &other {
                        End::Wrong(_) => {
                            wrong += 1;
                            "WRONG IMAGE"
                        }
                        End::Hung(_) => {
                            hangs += 1;
                            "HANG"
                        }
                        _ => {
                            unexplained += 1;
                            "ENDED WITHOUT SUCCESS OR A REASON"
                        }
                    };
                    eprintln!("chaos: {what}: {label} (seed {seed}): {other:?}");
                    bad.push(format!("{label}: {what}: {:?}", job.spec));
                }
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!(
        "chaos: seed {seed}: {jobs} jobs ({succeeded} succeeded with dray render's bits, \
         {failed} failed with a reason), {} worker kills, {} stops, {} coordinator \
         restarts ({disturbed_jobs} running jobs disturbed), {hangs} hangs, {wrong} wrong \
         images, {unexplained} ended without success or a reason, {} s",
        cluster.kills,
        cluster.stops,
        cluster.restarts,
        began.elapsed().as_secs()
    );
    assert!(
        bad.is_empty(),
        "seed {seed} (DRAY_CHAOS_SEED={seed} DRAY_CHAOS_JOBS={jobs} replays it):\n{}",
        bad.join("\n")
    );
    assert!(
        disturbed_jobs > 0,
        "no fault landed while a job ran: the test tested nothing"
    );
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}
