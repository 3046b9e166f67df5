//! Real `dray` processes for the tests of `dray submit`, `dray cluster` and the
//! reflection client: every process is held by a [`Proc`], which kills and reaps it when
//! dropped, so a failing assertion never leaves a server behind.
#![allow(dead_code)]

pub mod port_worker;
pub mod seeded;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};

/// The `dray` binary under test.
pub fn dray() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dray"))
}

/// A child process, killed (SIGKILL) and reaped on drop.
pub struct Proc {
    pub child: Child,
}

impl Proc {
    pub fn spawn(mut cmd: Command) -> Proc {
        Proc {
            child: cmd.spawn().expect("spawn a dray process"),
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Send `sig` (libc::SIGTERM, SIGINT, ...).
    pub fn signal(&self, sig: i32) {
        // SAFETY: kill(2) on our own child, not yet reaped.
        unsafe {
            libc::kill(self.pid(), sig);
        }
    }

    /// Wait up to `secs` for the process to exit; its status, or None on timeout.
    pub fn wait_timeout(&mut self, secs: f64) -> Option<std::process::ExitStatus> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(secs);
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return Some(s);
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `dray worker` of the coordinator at `addr` (host:port), one tracer thread, any
/// port, its output dropped.
pub fn worker(addr: &str) -> Proc {
    let mut cmd = dray();
    cmd.args(["worker", "--coordinator", &format!("http://{addr}")])
        .args(["--listen", "127.0.0.1:0", "--threads", "1"])
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    Proc::spawn(cmd)
}

/// A `dray coordinator` on a free port (port 0; the address is read from its first line).
pub struct Coordinator {
    pub proc: Proc,
    /// host:port
    pub addr: String,
}

pub fn coordinator(scene_root: &Path) -> Coordinator {
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--scene-root"])
        .arg(scene_root)
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut proc = Proc::spawn(cmd);
    let addr = listening_address(&mut proc.child)
        .unwrap_or_else(|line| panic!("no address in the coordinator's first line {line:?}"));
    Coordinator { proc, addr }
}

/// A `dray coordinator` on `port` (0: any) with heartbeats every 100 ms (lost after 2 s),
/// `extra` flags, and its log (coordinator events at info) captured: the process, its
/// address and the log.
pub fn logged_coordinator(
    scene_root: &Path,
    port: u16,
    extra: &[&std::ffi::OsStr],
) -> (Proc, String, Captured) {
    let mut cmd = dray();
    cmd.args(["coordinator", "--listen", &format!("127.0.0.1:{port}")])
        .arg("--scene-root")
        .arg(scene_root)
        .args([
            "--heartbeat-interval-ms",
            "100",
            "--heartbeat-timeout-ms",
            "2000",
        ])
        .args(extra)
        .env("DRAY_LOG", "warn,dray_coordinator=info")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let log = capture_stderr(&mut p.child);
    let addr = listening_address(&mut p.child)
        .unwrap_or_else(|first| panic!("no address in {first:?}: {}", dray_sync::lock(&log)));
    (p, addr, log)
}

/// The address a dray server announces in its first stdout line ("dray ... listening
/// on ADDR"), or that line when it holds none. Takes the child's stdout.
pub fn listening_address(child: &mut Child) -> Result<String, String> {
    let line = first_line(child.stdout.take().expect("the server's stdout is piped"));
    line.trim()
        .rsplit(' ')
        .next()
        .filter(|a| a.contains(':'))
        .map(str::to_string)
        .ok_or(line)
}

fn first_line(stdout: ChildStdout) -> String {
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("read the first line");
    line
}

/// A port that was free a moment ago (bind port 0 and let it go).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("bind a free port")
        .port()
}

/// Whether `pid` is still a live (not zombie) process.
pub fn alive(pid: i32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the parenthesised command name.
        Ok(s) => s
            .rsplit(')')
            .next()
            .and_then(|rest| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X"),
        Err(_) => false,
    }
}

/// Poll until `f` holds, up to `secs`: a limit that only catches hangs (tests wait for
/// events, they do not time them).
pub fn eventually(secs: f64, mut f: impl FnMut() -> bool) -> bool {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(secs);
    while std::time::Instant::now() < deadline {
        if f() {
            return true;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    f()
}

/// Poll until `pid` is gone, up to `secs`.
pub fn gone_within(pid: i32, secs: f64) -> bool {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(secs);
    while std::time::Instant::now() < deadline {
        if !alive(pid) {
            return true;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    !alive(pid)
}

// ---------------------------------------------------------------------------------------
// A `dray cluster` with workers (cli/tests/workers.rs).

/// A `dray cluster --workers N` whose workers have all registered with its coordinator,
/// with a 30 s heartbeat timeout unless the caller sets one. Dropping it sends SIGTERM to the cluster (which stops its members), then SIGKILLs
/// whatever is left, members included.
pub struct WorkerCluster {
    pub proc: Proc,
    /// host:port of the coordinator.
    pub addr: String,
    pub coordinator_pid: i32,
    pub worker_pids: Vec<i32>,
    /// Everything the cluster and its members wrote to stderr so far.
    pub log: std::sync::Arc<std::sync::Mutex<String>>,
}

/// Ports below the kernel's ephemeral range (32768..) so that outgoing connections of
/// other tests cannot take them; each test passes its own `slot` (0..8), and the pid
/// spreads concurrent test binaries apart. Five ports per slot (a coordinator, 4 workers).
pub fn cluster_base_port(slot: u16, attempt: u32) -> u16 {
    let spread = (std::process::id().wrapping_add(attempt.wrapping_mul(7919))) % 550;
    10_000 + (spread as u16) * 40 + slot * 5
}

impl WorkerCluster {
    /// Start `dray cluster --workers n` with `extra` cluster flags on a base port of
    /// `slot`, and wait (up to 60 s) until every worker has registered.
    pub fn start(n: u16, slot: u16, scene_root: &Path, extra: &[&str]) -> WorkerCluster {
        assert!(slot < 8 && n <= 4, "eight slots of five ports");
        let mut last_err = String::new();
        for attempt in 0..8 {
            let port = cluster_base_port(slot, attempt);
            let ports_free =
                (0..=n).all(|i| std::net::TcpListener::bind(("127.0.0.1", port + i)).is_ok());
            if !ports_free {
                last_err = format!("ports {port}..={} not all free", port + n);
                continue;
            }
            match WorkerCluster::try_start(n, port, scene_root, extra) {
                Ok(c) => return c,
                Err(e) if e.contains("already in use") => last_err = e,
                Err(e) => panic!("dray cluster --workers {n} did not start: {e}"),
            }
        }
        panic!("dray cluster --workers {n}: no free ports: {last_err}");
    }

    fn try_start(
        n: u16,
        port: u16,
        scene_root: &Path,
        extra: &[&str],
    ) -> Result<WorkerCluster, String> {
        use std::sync::{Arc, Mutex};
        let mut cmd = dray();
        cmd.args(["cluster", "--workers", &n.to_string()])
            .args(["--base-port", &port.to_string(), "--scene-root"])
            .arg(scene_root)
            .args(extra);
        // Tests share a small machine with builds and benchmarks: a worker whose beats
        // arrive late must not fail a job here (the heartbeat test sets its own timeout).
        if !extra.contains(&"--heartbeat-timeout-ms") {
            cmd.args(["--heartbeat-timeout-ms", "30000"]);
        }
        cmd
            // Registrations are logged at info: that is how readiness is seen from here.
            .env("DRAY_LOG", "warn,dray_coordinator::membership=info")
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut proc = Proc::spawn(cmd);
        let log = capture_stderr(&mut proc.child);
        let stdout = proc.child.stdout.take().expect("cluster stdout");
        let mut lines = Vec::new();
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            let ready = line.starts_with("dray cluster ready");
            lines.push(line);
            if ready {
                break;
            }
        }
        let text = |log: &Arc<Mutex<String>>| dray_sync::lock(log).clone();
        if !lines
            .last()
            .is_some_and(|l| l.starts_with("dray cluster ready"))
        {
            let _ = proc.wait_timeout(10.0);
            return Err(format!("stdout {lines:?}, stderr {}", text(&log)));
        }
        let pid_of = |name: &str| -> i32 {
            lines
                .iter()
                .find(|l| l.starts_with(name))
                .and_then(|l| l.rsplit(' ').next())
                .and_then(|p| p.parse().ok())
                .unwrap_or_else(|| panic!("no pid for {name} in {lines:?}"))
        };
        let coordinator_pid = pid_of("coordinator ");
        let worker_pids = (1..=n).map(|i| pid_of(&format!("worker-{i} "))).collect();
        let c = WorkerCluster {
            proc,
            addr: format!("127.0.0.1:{port}"),
            coordinator_pid,
            worker_pids,
            log: log.log.clone(),
        };
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        loop {
            let registered = c.log().matches("worker registered").count();
            if registered >= usize::from(n) {
                return Ok(c);
            }
            if std::time::Instant::now() >= deadline {
                panic!(
                    "{registered} of {n} workers registered within 60 s; log:\n{}",
                    c.log()
                );
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }

    /// The stderr of the cluster and its members so far.
    pub fn log(&self) -> String {
        dray_sync::lock(&self.log).clone()
    }

    /// Every member is still running.
    pub fn all_alive(&self) -> bool {
        alive(self.coordinator_pid) && self.worker_pids.iter().all(|&p| alive(p))
    }
}

impl Drop for WorkerCluster {
    fn drop(&mut self) {
        // Not once reaped (a test may have stopped the cluster): the pid may be reused.
        if !matches!(self.proc.child.try_wait(), Ok(Some(_))) {
            self.proc.signal(libc::SIGTERM);
            if self.proc.wait_timeout(15.0).is_none() {
                let _ = self.proc.child.kill();
            }
        }
        for &pid in std::iter::once(&self.coordinator_pid).chain(&self.worker_pids) {
            if alive(pid) {
                // SAFETY: kill(2) on a member of the cluster this test started (best
                // effort; the cluster already had its chance to stop it).
                unsafe {
                    libc::kill(pid, libc::SIGKILL);
                }
            }
        }
    }
}

/// A line of /proc/PID/status in kB (VmHWM, VmRSS, ...).
pub fn proc_status_kb(pid: i32, field: &str) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    s.lines()
        .find(|l| l.starts_with(field) && l[field.len()..].starts_with(':'))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// CPU time (user + system) of `pid` in clock ticks.
pub fn cpu_ticks(pid: i32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = s.rsplit(')').next()?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    // After the name: state(0) ... utime(11) stime(12).
    Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
}

/// A child's stderr, collected on a thread as it comes (see [`capture_stderr`]). It
/// dereferences to the text so far; [`Captured::to_end`] waits for the reader to see
/// end-of-file, so nothing the child wrote just before it exited is missed.
pub struct Captured {
    pub log: std::sync::Arc<std::sync::Mutex<String>>,
    ended: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl std::ops::Deref for Captured {
    type Target = std::sync::Arc<std::sync::Mutex<String>>;
    fn deref(&self) -> &Self::Target {
        &self.log
    }
}

impl Captured {
    /// The text so far.
    pub fn text(&self) -> String {
        dray_sync::lock(&self.log).clone()
    }

    /// Everything the child wrote, once its stderr has closed (it exited, and so did any
    /// child of its holding the pipe). Waits for that event, up to 60 s, a limit that
    /// only catches hangs; then it panics.
    pub fn to_end(&self) -> String {
        use std::sync::atomic::Ordering;
        assert!(
            eventually(60.0, || self.ended.load(Ordering::Acquire)),
            "the child's stderr was still open 60 s later"
        );
        dray_sync::lock(&self.log).clone()
    }

    /// [`Captured::to_end`] when the child has exited, else the text so far (for the
    /// message about a child that hung).
    pub fn after(&self, exited: bool) -> String {
        if exited {
            self.to_end()
        } else {
            dray_sync::lock(&self.log).clone()
        }
    }
}

/// The job id in `dray submit`'s stderr ("dray submit: job ID accepted by ..."), once
/// it has said it.
pub fn submitted_job_id(stderr: &str) -> Option<String> {
    stderr.lines().find_map(|l| {
        l.strip_prefix("dray submit: job ")?
            .split_once(" accepted by ")
            .map(|(id, _)| id.to_string())
    })
}

/// Collect a child's piped stderr on a thread, as it comes.
pub fn capture_stderr(child: &mut Child) -> Captured {
    use std::io::Read;
    use std::sync::atomic::{AtomicBool, Ordering};
    let log = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let ended = std::sync::Arc::new(AtomicBool::new(false));
    let mut err = child.stderr.take().expect("piped stderr");
    let (sink, done) = (log.clone(), ended.clone());
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(k) = err.read(&mut buf) {
            if k == 0 {
                break;
            }
            dray_sync::lock(&sink).push_str(&String::from_utf8_lossy(&buf[..k]));
        }
        done.store(true, Ordering::Release);
    });
    Captured { log, ended }
}

/// Run `cmd` (stdin and stdout to null, stderr captured) to its end and require success:
/// a run still going after `secs` is a hang, killed and reported with `what` and its
/// stderr, as is a failure. Returns the stderr.
pub fn run_to_success(mut cmd: Command, what: &str, secs: f64) -> String {
    cmd.stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let err = capture_stderr(&mut p.child);
    let status = p.wait_timeout(secs);
    let err = err.after(status.is_some());
    let status = status.unwrap_or_else(|| panic!("HANG: {what}: {err}"));
    assert!(status.success(), "{what}: {err}");
    err
}

/// `dray submit --coordinator ADDR SCENE -q ARGS` writing `DIR/submitted.{png,exr,json}`,
/// run to success: the EXR's bytes and the `--stats` JSON.
pub fn submit_exr(
    addr: &str,
    dir: &Path,
    scene: &str,
    args: &[&str],
) -> (Vec<u8>, serde_json::Value) {
    let exr = dir.join("submitted.exr");
    let json = dir.join("submitted.json");
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr, scene, "-q"])
        .args(args)
        .arg("--output")
        .arg(dir.join("submitted.png"))
        .arg("--exr")
        .arg(&exr)
        .arg("--stats")
        .arg(&json);
    run_to_success(cmd, "dray submit", 180.0);
    let stats =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("stats")).expect("json");
    (std::fs::read(&exr).expect("exr"), stats)
}

/// `call` with a RenderService client of the coordinator at `addr`, on a runtime of its
/// own; None when the coordinator cannot be reached or `call` gives none.
pub fn with_client<T, F, Fut>(addr: &str, call: F) -> Option<T>
where
    F: FnOnce(
        dray_proto::v1::render_service_client::RenderServiceClient<tonic::transport::Channel>,
    ) -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let c = dray_proto::v1::render_service_client::RenderServiceClient::connect(format!(
            "http://{addr}"
        ))
        .await
        .ok()?;
        call(c).await
    })
}

/// Job `id` as the coordinator at `addr` reports it (GetJob); None when the coordinator
/// cannot be reached or does not know the job.
pub fn get_job(addr: &str, id: &str) -> Option<dray_proto::v1::Job> {
    with_client(addr, |mut c| async move {
        c.get_job(dray_proto::v1::GetJobRequest {
            job_id: id.to_string(),
        })
        .await
        .ok()?
        .into_inner()
        .job
    })
}

/// The jobs of job group `group` (ListJobs with its `group_id`, one page of up to 1000);
/// None when the coordinator cannot be reached or refuses.
pub fn list_group(addr: &str, group: &str) -> Option<Vec<dray_proto::v1::Job>> {
    with_client(addr, |mut c| async move {
        let r = c
            .list_jobs(dray_proto::v1::ListJobsRequest {
                group_id: group.to_string(),
                page_size: 1000,
                ..Default::default()
            })
            .await
            .ok()?;
        Some(r.into_inner().jobs)
    })
}
