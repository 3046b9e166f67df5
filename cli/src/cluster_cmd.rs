//! `dray cluster`: a coordinator and N workers as local processes on consecutive ports,
//! for trying dray on one machine and for tests that need real processes.
//!
//! The children are this same executable (`dray coordinator`, `dray worker`), so a cluster
//! always runs the code it was built with. The cluster owns its children's lifetime:
//! - Ctrl-C, SIGTERM or SIGHUP stops them all (SIGTERM, then SIGKILL after a grace time);
//! - a worker that exits on its own (killed, crashed) is reported on stderr and the
//!   cluster keeps serving with the workers left: the coordinator re-traces the lost
//!   worker's share of running jobs, and with no worker left it renders in its own process;
//! - the coordinator exiting on its own stops the workers, and the cluster exits non-zero
//!   naming it;
//! - if the cluster is killed outright, the kernel sends each child SIGTERM
//!   (PR_SET_PDEATHSIG on Linux), and if the cluster's own parent dies (a test harness, a
//!   terminal closed) the cluster notices through `getppid` and stops them: nothing is
//!   left holding the ports.
//!
//! Children run in their own process group, so a Ctrl-C typed at the terminal reaches
//! only the cluster, which then stops the children in order, instead of every process
//! dying at once and the cluster reporting them as crashed.

use std::net::{Ipv4Addr, SocketAddr, TcpListener};
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use tokio::signal::unix::{Signal, SignalKind, signal};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// How long the members get to become ready.
const READY_TIMEOUT: Duration = Duration::from_secs(60);
/// How long a member gets to exit after SIGTERM before it is killed.
const STOP_GRACE: Duration = Duration::from_secs(5);
/// How often children and the parent are checked.
const POLL: Duration = Duration::from_millis(200);

#[derive(Args, Debug)]
pub struct ClusterArgs {
    /// Worker processes to start (0 runs a coordinator alone).
    #[arg(long)]
    pub workers: u16,
    /// The coordinator listens on 127.0.0.1:P, worker i on 127.0.0.1:P+i. With 0 each
    /// member binds a port the system chooses (the coordinator first, whose address the
    /// workers are then given); the lines printed before the ready line name them.
    #[arg(long, default_value_t = dray_net::DEFAULT_PORT)]
    pub base_port: u16,
    /// The coordinator's scene root (scene paths in jobs are resolved against it).
    #[arg(long)]
    pub scene_root: Option<PathBuf>,
    /// The coordinator's --work-dir: where job scene packages are written for the workers.
    #[arg(long, value_name = "DIR")]
    pub work_dir: Option<PathBuf>,
    /// The coordinator's --max-running-jobs: jobs running on the workers at once; the
    /// others wait, dealt by priority, pausable. Default: no limit.
    #[arg(long, value_name = "N")]
    pub max_running_jobs: Option<std::num::NonZeroUsize>,
    /// The coordinator's --heartbeat-interval-ms.
    #[arg(long, value_name = "MS")]
    pub heartbeat_interval_ms: Option<u64>,
    /// The coordinator's --heartbeat-timeout-ms.
    #[arg(long, value_name = "MS")]
    pub heartbeat_timeout_ms: Option<u64>,
    /// Every worker's --memory-budget: bytes for resident domains and queued rays
    /// (suffixes K, M, G, T are powers of 1024; 0 = unlimited).
    #[arg(long, value_name = "BYTES", value_parser = crate::bytes::parse_bytes)]
    pub memory_budget: Option<u64>,
    /// Every worker's --load-delay-ms: added to each domain load (slow storage).
    #[arg(long, value_name = "MS")]
    pub load_delay_ms: Option<u64>,
    /// Every worker's --threads: tracing threads per worker (0 = all cores each).
    #[arg(long, value_name = "N")]
    pub threads: Option<usize>,
    /// Every worker's --fetch-packages: when to fetch job packages from the coordinator
    /// over gRPC instead of reading the coordinator's --work-dir (auto, always, never).
    #[arg(long, value_name = "MODE", value_parser = crate::worker_cmd::parse_fetch_mode)]
    pub fetch_packages: Option<dray_worker::package_fetch::FetchMode>,
    /// Fetched packages go to DIR/worker-I for worker I (its --package-cache).
    #[arg(long, value_name = "DIR")]
    pub package_cache: Option<PathBuf>,
    /// Every worker's --trace-dir: jobs that ask for a traffic trace (`dray submit
    /// --trace`) are recorded there, one file per job attempt and worker (created if
    /// missing; docs/caches.md "The trace's schema").
    #[arg(long, value_name = "DIR")]
    pub trace_dir: Option<PathBuf>,
    /// The coordinator's API token (passed on as its --auth-token-file).
    #[command(flatten)]
    pub api_token: crate::net_flags::ApiTokenArgs,
    /// The members' cluster token. Without it, `dray cluster` makes a random one for
    /// this run and hands it to its members in a file only this user can read.
    #[command(flatten)]
    pub cluster_token: crate::net_flags::ClusterTokenArgs,
    /// TLS for every member (passed on to each).
    #[command(flatten)]
    pub tls: crate::net_flags::TlsArgs,
    /// Times a worker that exits on its own is started again, after 1, 2, 4, ... s (at
    /// most 30 s); 0 never restarts one.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pub restart_limit: u32,
    /// Passed to the coordinator and every worker.
    #[command(flatten)]
    pub otlp: crate::telemetry::OtlpArgs,
    /// Every member's --emulate-link: each connection between the members behaves like
    /// a link of this bandwidth and latency (`bandwidth=1gbit,latency=100us`).
    #[arg(long, value_name = "SPEC", value_parser = crate::net_flags::parse_link)]
    pub emulate_link: Option<dray_net::LinkEmulation>,
    /// The coordinator's --http-listen: serve the web dashboard on this address (e.g.
    /// 127.0.0.1:8080). Off unless given.
    #[arg(long, value_name = "ADDR")]
    pub http_listen: Option<SocketAddr>,
}

/// Longest wait before a worker is started again.
const MAX_RESTART_BACKOFF: Duration = Duration::from_secs(30);

/// The wait before restart number `n` (0-based): 1 s, 2 s, 4 s, ... at most 30 s.
fn restart_backoff(n: u32) -> Duration {
    Duration::from_secs(1u64 << n.min(5)).min(MAX_RESTART_BACKOFF)
}

/// A new directory for this run's secrets (the cluster token handed to the members): a
/// random name in the system temp directory, made atomically (an existing path, which
/// another local user could have made and could write into, is never used), readable
/// only by this user (0700), and removed with its contents when the guard drops.
fn secrets_dir() -> Result<tempfile::TempDir> {
    dray_scene::private_fs::private_temp_dir("dray-cluster-", "-secrets")
        .context("cannot create a private directory for the cluster token in the temp directory")
}

/// One child process of the cluster.
struct Member {
    name: String,
    /// Its address; port 0 until it announced the port it bound (`--base-port 0`).
    addr: SocketAddr,
    child: Child,
    /// The address it announces on its first line of stdout, when it binds port 0.
    announced: Option<std::sync::mpsc::Receiver<SocketAddr>>,
    /// Set once the member answered its health check.
    ready: bool,
    /// Set once it has been reaped.
    exited: Option<ExitStatus>,
    /// Its command line, to start it again.
    args: Vec<String>,
    /// Times it was started again.
    restarts: u32,
    /// When to start it again, if it is to be.
    restart_at: Option<tokio::time::Instant>,
}

/// The running members. Dropping it stops every member still running, so an early
/// return (an error while starting, a panic) never leaves processes behind.
struct Cluster {
    members: Vec<Member>,
}

impl Cluster {
    /// A member that exited: its index (0 is the coordinator), a description naming
    /// it, and its status (reaped here).
    fn exited(&mut self) -> Option<(usize, String, ExitStatus)> {
        for (i, m) in self.members.iter_mut().enumerate() {
            if m.exited.is_none()
                && let Ok(Some(status)) = m.child.try_wait()
            {
                m.exited = Some(status);
                return Some((
                    i,
                    format!("{} (pid {}, http://{})", m.name, m.child.id(), m.addr),
                    status,
                ));
            }
        }
        None
    }

    /// Workers not known to have exited.
    fn workers_running(&self) -> usize {
        self.members
            .iter()
            .skip(1)
            .filter(|m| m.exited.is_none())
            .count()
    }

    /// SIGTERM to every member still running (workers first, so they do not see the
    /// coordinator vanish), then SIGKILL to any that outlive the grace time.
    fn stop(&mut self) {
        for m in self.members.iter_mut().rev() {
            if m.exited.is_none() {
                if let Ok(Some(s)) = m.child.try_wait() {
                    m.exited = Some(s);
                    continue;
                }
                if let Ok(pid) = libc::pid_t::try_from(m.child.id()) {
                    // SAFETY: kill(2) with a pid we spawned and have not reaped yet, so it
                    // cannot name a recycled process.
                    unsafe {
                        libc::kill(pid, libc::SIGTERM);
                    }
                }
            }
        }
        let deadline = Instant::now() + STOP_GRACE;
        loop {
            let mut running = 0;
            for m in &mut self.members {
                if m.exited.is_none() {
                    match m.child.try_wait() {
                        Ok(Some(s)) => m.exited = Some(s),
                        _ => running += 1,
                    }
                }
            }
            if running == 0 {
                return;
            }
            if Instant::now() >= deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        for m in &mut self.members {
            if m.exited.is_none() {
                eprintln!(
                    "dray cluster: {} did not stop within {:?}; killing it",
                    m.name, STOP_GRACE
                );
                let _ = m.child.kill();
                m.exited = m.child.wait().ok();
            }
        }
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Ctrl-C, SIGTERM and SIGHUP, registered before any child starts so that a signal during
/// start-up is not lost.
struct Signals {
    int: Signal,
    term: Signal,
    hup: Signal,
}

impl Signals {
    fn new() -> Result<Signals> {
        let reg = |k: SignalKind, name: &str| {
            signal(k).with_context(|| format!("cannot install the {name} handler"))
        };
        Ok(Signals {
            int: reg(SignalKind::interrupt(), "SIGINT")?,
            term: reg(SignalKind::terminate(), "SIGTERM")?,
            hup: reg(SignalKind::hangup(), "SIGHUP")?,
        })
    }

    async fn next(&mut self) -> &'static str {
        tokio::select! {
            _ = self.int.recv() => "interrupted",
            _ = self.term.recv() => "terminated",
            _ = self.hup.recv() => "hung up",
        }
    }
}

/// How a member ended, for a human: "signal 9 (SIGKILL)", "exit status 1".
fn describe(status: ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    if let Some(sig) = status.signal() {
        let name = match sig {
            libc::SIGKILL => " (SIGKILL)",
            libc::SIGTERM => " (SIGTERM)",
            libc::SIGINT => " (SIGINT)",
            libc::SIGSEGV => " (SIGSEGV)",
            libc::SIGABRT => " (SIGABRT)",
            libc::SIGBUS => " (SIGBUS)",
            _ => "",
        };
        format!("signal {sig}{name}")
    } else if let Some(code) = status.code() {
        format!("exit status {code}")
    } else {
        status.to_string()
    }
}

/// Fail early, naming the port, when something already listens there: otherwise the
/// child would fail on its own and the message would arrive second-hand.
fn check_port_free(port: u16, name: &str) -> Result<()> {
    match TcpListener::bind((Ipv4Addr::LOCALHOST, port)) {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AddrInUse => bail!(
            "port {port} (for the {name}) is already in use on 127.0.0.1; stop what holds it \
             or choose another --base-port"
        ),
        Err(e) => Err(e).with_context(|| format!("cannot use port {port} for the {name}")),
    }
}

/// The address in a member's first line of stdout ("dray coordinator listening on
/// 127.0.0.1:PORT", "dray worker listening on ...").
fn announced_addr(line: &str) -> Option<SocketAddr> {
    line.rsplit_once(" listening on ")?.1.trim().parse().ok()
}

/// Read `stdout`'s first line on a thread of its own and send the address it announces;
/// the rest is read and dropped, so the member never blocks on a full pipe.
fn watch_announcement(stdout: std::process::ChildStdout) -> std::sync::mpsc::Receiver<SocketAddr> {
    use std::io::BufRead;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = std::io::BufReader::new(stdout).lines();
        if let Some(Ok(first)) = lines.next()
            && let Some(addr) = announced_addr(&first)
        {
            let _ = tx.send(addr);
        }
        for _ in lines.map_while(|l| l.ok()) {}
    });
    rx
}

/// Start `exe args…` as a member: in its own process group, stdout discarded (the
/// cluster prints the endpoints) unless `addr` has port 0 (then its first line, which
/// names the port it bound, is read), stderr shared so its errors reach the user.
fn spawn(exe: &PathBuf, name: String, addr: SocketAddr, args: &[String]) -> Result<Member> {
    let ephemeral = addr.port() == 0;
    let mut cmd = Command::new(exe);
    cmd.args(args)
        .stdin(Stdio::null())
        .stdout(if ephemeral {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .stderr(Stdio::inherit())
        .process_group(0);
    #[cfg(target_os = "linux")]
    {
        let parent = std::process::id();
        // SAFETY: the closure runs between fork and exec and calls only prctl(2) and
        // getppid(2), which are async-signal-safe, and builds an io::Error from a raw code
        // without allocating. The death signal is tied to the thread that forks: this is
        // the main thread (the cluster runs on a current-thread runtime), which lives as
        // long as the cluster.
        unsafe {
            cmd.pre_exec(move || {
                if libc::prctl(
                    libc::PR_SET_PDEATHSIG,
                    libc::SIGTERM as libc::c_ulong,
                    0,
                    0,
                    0,
                ) == -1
                {
                    return Err(std::io::Error::last_os_error());
                }
                // The cluster may have died before prctl took effect.
                if libc::getppid() as u32 != parent {
                    return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
                }
                Ok(())
            });
        }
    }
    let mut child = cmd
        .spawn()
        .with_context(|| format!("cannot start the {name} ({})", exe.display()))?;
    let announced = child.stdout.take().map(watch_announcement);
    Ok(Member {
        name,
        addr,
        child,
        announced,
        ready: false,
        exited: None,
        args: args.to_vec(),
        restarts: 0,
        restart_at: None,
    })
}

impl Cluster {
    /// Take the addresses members on port 0 announced; tell of those of members started
    /// again (`report`).
    fn take_announced(&mut self, report: bool) {
        for m in &mut self.members {
            if m.addr.port() == 0
                && let Some(addr) = m.announced.as_ref().and_then(|rx| rx.try_recv().ok())
            {
                m.addr = addr;
                if report {
                    eprintln!("dray cluster: {} listens on http://{addr}", m.name);
                }
            }
        }
    }

    /// Start again the workers whose restart time has come; a start that fails is
    /// tried again after the next backoff, within the limit.
    fn restart_due(&mut self, exe: &PathBuf, limit: u32) {
        let now = tokio::time::Instant::now();
        for m in self.members.iter_mut().skip(1) {
            if m.restart_at.is_none_or(|t| t > now) {
                continue;
            }
            m.restart_at = None;
            m.restarts += 1;
            // A member on a port of its choosing binds a new one.
            let addr = if m.announced.is_some() {
                SocketAddr::from((Ipv4Addr::LOCALHOST, 0))
            } else {
                m.addr
            };
            match spawn(exe, m.name.clone(), addr, &m.args) {
                Ok(new) => {
                    eprintln!(
                        "dray cluster: {} started again (pid {}, http://{}; restart {} of {limit})",
                        m.name,
                        new.child.id(),
                        if addr.port() == 0 {
                            "a new port".to_string()
                        } else {
                            addr.to_string()
                        },
                        m.restarts
                    );
                    m.child = new.child;
                    m.addr = addr;
                    m.announced = new.announced;
                    m.exited = None;
                }
                Err(e) => {
                    let retry = m.restarts < limit;
                    eprintln!(
                        "dray cluster: cannot start {} again: {e:#}{}",
                        m.name,
                        if retry { "; trying later" } else { "" }
                    );
                    if retry {
                        m.restart_at = Some(now + restart_backoff(m.restarts));
                    }
                }
            }
        }
    }
}

/// Whether the gRPC server at `addr` reports `service` as SERVING. A worker without the
/// health service (UNIMPLEMENTED) still proves its gRPC server is up.
async fn healthy(
    net: &dray_net::ClientOptions,
    addr: SocketAddr,
    service: &str,
    unimplemented_ok: bool,
) -> bool {
    let Ok(endpoint) = net.endpoint(&addr.to_string()) else {
        return false;
    };
    let Ok(channel) = endpoint
        .connect_timeout(Duration::from_secs(1))
        .timeout(Duration::from_secs(2))
        .connect()
        .await
    else {
        return false;
    };
    let request = HealthCheckRequest {
        service: service.to_string(),
    };
    match HealthClient::new(channel).check(request).await {
        Ok(r) => r.into_inner().status == ServingStatus::Serving as i32,
        Err(s) => unimplemented_ok && s.code() == tonic::Code::Unimplemented,
    }
}

/// Refuse, before anything starts, flags that cannot work: ports past 65535 or taken, a
/// scene root that is not a folder, a dashboard address in use.
fn check_flags(a: &ClusterArgs, worker_addrs: &[SocketAddr]) -> Result<()> {
    if u32::from(a.base_port) + u32::from(a.workers) > 65535 {
        bail!(
            "--base-port {} with --workers {} needs ports up to {}, past 65535",
            a.base_port,
            a.workers,
            u32::from(a.base_port) + u32::from(a.workers)
        );
    }
    if let Some(root) = &a.scene_root
        && !root.is_dir()
    {
        bail!("--scene-root {}: not a directory", root.display());
    }
    if let Some(http) = a.http_listen
        && http.port() != 0
        && let Err(e) = TcpListener::bind(http)
    {
        if e.kind() == std::io::ErrorKind::AddrInUse {
            bail!("--http-listen {http} is already in use; stop what holds it or choose another");
        }
        return Err(e).with_context(|| format!("--http-listen {http}"));
    }
    if a.base_port != 0 {
        check_port_free(a.base_port, "coordinator")?;
        for (i, w) in worker_addrs.iter().enumerate() {
            check_port_free(w.port(), &format!("worker-{}", i + 1))?;
        }
    }
    Ok(())
}

/// The members' cluster token file: the one given, or one made for this run in a
/// directory private to it (see `secrets_dir`), removed when the returned guard drops.
fn token_file(a: &ClusterArgs) -> Result<(Option<tempfile::TempDir>, PathBuf)> {
    if let Some(f) = &a.cluster_token.cluster_token_file {
        return Ok((None, f.clone()));
    }
    let token = match a.cluster_token.token()? {
        Some(t) => t,
        None => dray_net::Token::generate()?,
    };
    let dir = secrets_dir()?;
    let file = crate::net_flags::write_token_file(dir.path(), "cluster.token", &token)?;
    Ok((Some(dir), file))
}

/// `--flag value` for each flag that is set.
fn push_flags(args: &mut Vec<String>, flags: &[(&str, Option<String>)]) {
    for (flag, value) in flags {
        if let Some(v) = value {
            args.push((*flag).to_string());
            args.push(v.clone());
        }
    }
}

/// The coordinator's command line.
fn coordinator_args(a: &ClusterArgs, addr: SocketAddr, shared: &[String]) -> Vec<String> {
    let mut args = vec![
        "coordinator".to_string(),
        "--listen".to_string(),
        addr.to_string(),
    ];
    let path = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string());
    push_flags(
        &mut args,
        &[
            ("--scene-root", path(&a.scene_root)),
            ("--work-dir", path(&a.work_dir)),
            (
                "--max-running-jobs",
                a.max_running_jobs.map(|n| n.to_string()),
            ),
            (
                "--heartbeat-interval-ms",
                a.heartbeat_interval_ms.map(|n| n.to_string()),
            ),
            (
                "--heartbeat-timeout-ms",
                a.heartbeat_timeout_ms.map(|n| n.to_string()),
            ),
            ("--auth-token-file", path(&a.api_token.auth_token_file)),
            ("--http-listen", a.http_listen.map(|h| h.to_string())),
        ],
    );
    args.extend(shared.iter().cloned());
    args
}

/// Worker `name`'s command line.
fn worker_args(
    a: &ClusterArgs,
    name: &str,
    coordinator_url: &str,
    addr: SocketAddr,
    shared: &[String],
) -> Vec<String> {
    let mut args = vec![
        "worker".to_string(),
        "--coordinator".to_string(),
        coordinator_url.to_string(),
        "--listen".to_string(),
        addr.to_string(),
        "--name".to_string(),
        name.to_string(),
    ];
    push_flags(
        &mut args,
        &[
            ("--memory-budget", a.memory_budget.map(|b| b.to_string())),
            ("--load-delay-ms", a.load_delay_ms.map(|n| n.to_string())),
            ("--threads", a.threads.map(|n| n.to_string())),
            (
                "--fetch-packages",
                a.fetch_packages.map(|m| m.name().to_string()),
            ),
            (
                "--package-cache",
                a.package_cache
                    .as_ref()
                    .map(|d| d.join(name).display().to_string()),
            ),
            (
                "--trace-dir",
                a.trace_dir.as_ref().map(|d| d.display().to_string()),
            ),
        ],
    );
    args.extend(shared.iter().cloned());
    args
}

/// How a wait of the starting cluster ended, when it did not fail.
enum Started {
    Done,
    /// A signal came: the caller stops (the members are stopped when `Cluster` drops).
    Signalled,
}

impl Cluster {
    /// Wait until the coordinator, started on a port of its choosing, names it.
    async fn coordinator_port(
        &mut self,
        signals: &mut Signals,
        tick: &mut tokio::time::Interval,
        start: Instant,
    ) -> Result<Started> {
        while self.members[0].addr.port() == 0 {
            tokio::select! {
                why = signals.next() => {
                    eprintln!("dray cluster: {why} while starting; stopping");
                    return Ok(Started::Signalled);
                }
                _ = tick.tick() => {}
            }
            self.take_announced(false);
            if let Some((_, name, status)) = self.exited() {
                bail!("{name} exited while starting ({status}); stopped the others");
            }
            if start.elapsed() > READY_TIMEOUT {
                bail!("the coordinator did not name its port within {READY_TIMEOUT:?}; stopped it");
            }
        }
        Ok(Started::Done)
    }

    /// Wait until every member answers its health check.
    async fn all_ready(
        &mut self,
        signals: &mut Signals,
        tick: &mut tokio::time::Interval,
        start: Instant,
        net: &dray_net::ClientOptions,
    ) -> Result<Started> {
        while self.members.iter().any(|m| !m.ready) {
            tokio::select! {
                why = signals.next() => {
                    eprintln!("dray cluster: {why} while starting; stopping");
                    return Ok(Started::Signalled);
                }
                _ = tick.tick() => {}
            }
            if let Some((_, name, status)) = self.exited() {
                bail!("{name} exited while starting ({status}); stopped the others");
            }
            if start.elapsed() > READY_TIMEOUT {
                let waiting: Vec<&str> = self
                    .members
                    .iter()
                    .filter(|m| !m.ready)
                    .map(|m| m.name.as_str())
                    .collect();
                bail!(
                    "not ready after {:?}: {}; stopped them all",
                    READY_TIMEOUT,
                    waiting.join(", ")
                );
            }
            self.take_announced(false);
            for (i, m) in self.members.iter_mut().enumerate() {
                if !m.ready && m.addr.port() != 0 {
                    m.ready = if i == 0 {
                        healthy(net, m.addr, "dray.v1.RenderService", false).await
                    } else {
                        healthy(net, m.addr, "", true).await
                    };
                }
            }
        }
        Ok(Started::Done)
    }

    /// A worker exited: say so, and schedule its restart within the limit. The
    /// coordinator notices it too (its stream ends) and re-traces its share; the cluster
    /// serves on with the others.
    fn worker_exited(&mut self, i: usize, name: &str, status: ExitStatus, restart_limit: u32) {
        let n = self.workers_running();
        let m = &mut self.members[i];
        let restart = if m.restarts < restart_limit {
            let wait = restart_backoff(m.restarts);
            m.restart_at = Some(tokio::time::Instant::now() + wait);
            format!(
                " and starts it again in {} s (restart {} of {})",
                wait.as_secs(),
                m.restarts + 1,
                restart_limit
            )
        } else if restart_limit > 0 {
            format!(
                " (it was started again {} times, the --restart-limit)",
                m.restarts
            )
        } else {
            String::new()
        };
        eprintln!(
            "dray cluster: {name} exited: {}; the cluster keeps serving with {n} worker{}{}{restart}",
            describe(status),
            if n == 1 { "" } else { "s" },
            if n == 0 {
                " (jobs run in the coordinator's process)"
            } else {
                ""
            }
        );
    }

    /// Serve until a signal, the coordinator's exit or the parent's: restart lost
    /// workers, take the ports they announce.
    async fn supervise(
        &mut self,
        signals: &mut Signals,
        tick: &mut tokio::time::Interval,
        exe: &PathBuf,
        restart_limit: u32,
    ) -> Result<()> {
        let parent = std::os::unix::process::parent_id();
        loop {
            tokio::select! {
                why = signals.next() => {
                    let n = self.workers_running();
                    eprintln!(
                        "dray cluster: {why}; stopping the coordinator and {n} worker{}",
                        if n == 1 { "" } else { "s" }
                    );
                    self.stop();
                    return Ok(());
                }
                _ = tick.tick() => {}
            }
            while let Some((i, name, status)) = self.exited() {
                if i == 0 {
                    self.stop();
                    bail!("{name} exited unexpectedly ({status}); stopped the others");
                }
                self.worker_exited(i, &name, status, restart_limit);
            }
            self.restart_due(exe, restart_limit);
            self.take_announced(true);
            if std::os::unix::process::parent_id() != parent {
                eprintln!("dray cluster: the parent process is gone; stopping");
                self.stop();
                return Ok(());
            }
        }
    }
}

/// What the cluster prints once every member is ready: the members, the dashboard and
/// how to reach the coordinator.
fn print_ready(
    cluster: &Cluster,
    a: &ClusterArgs,
    coordinator_addr: SocketAddr,
    tls: bool,
    api_token: bool,
) {
    for m in &cluster.members {
        println!("{:<12} http://{}  pid {}", m.name, m.addr, m.child.id());
    }
    if let Some(http) = a.http_listen.filter(|h| h.port() != 0) {
        println!("{:<12} http://{http}  (open it in a browser)", "dashboard");
    }
    println!(
        "example: dray submit --coordinator {coordinator_addr} cornell --width 320 --height 240 --output cornell.png"
    );
    let grpcurl_tls = if tls { "-cacert CA.pem" } else { "-plaintext" };
    let header = if api_token {
        " -H \"authorization: Bearer $(cat TOKEN_FILE)\""
    } else {
        ""
    };
    println!("example: grpcurl {grpcurl_tls}{header} {coordinator_addr} list");
    println!(
        "dray cluster ready: 1 coordinator, {} worker{}; coordinator at {coordinator_addr}; \
         Ctrl-C stops them all",
        a.workers,
        if a.workers == 1 { "" } else { "s" }
    );
}

pub fn run(a: ClusterArgs) -> Result<()> {
    // --base-port 0: every member on a port the system chooses.
    let port_of = |i: u16| if a.base_port == 0 { 0 } else { a.base_port + i };
    let worker_addrs: Vec<SocketAddr> = (1..=a.workers)
        .map(|i| SocketAddr::from((Ipv4Addr::LOCALHOST, port_of(i))))
        .collect();
    check_flags(&a, &worker_addrs)?;
    let coordinator_addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port_of(0)));
    let exe = std::env::current_exe().context("cannot find the dray executable to start")?;
    // `_secrets` lives until `run` returns: the token's directory goes with it.
    let (_secrets, token_file) = token_file(&a)?;
    let api_token = a.api_token.token()?;
    let net = crate::net_flags::client_options(None, &a.tls)?;
    let scheme = if net.tls() { "https" } else { "http" };
    let mut shared_args = vec![
        "--cluster-token-file".to_string(),
        token_file.display().to_string(),
    ];
    shared_args.extend(a.tls.to_args());
    shared_args.extend(a.otlp.to_args());
    shared_args.extend(crate::net_flags::link_args(a.emulate_link.as_ref()));

    // Current-thread: children are forked from the main thread (see `spawn`).
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async move {
        let mut signals = Signals::new()?;
        let mut cluster = Cluster {
            members: Vec::new(),
        };
        let args = coordinator_args(&a, coordinator_addr, &shared_args);
        cluster
            .members
            .push(spawn(&exe, "coordinator".into(), coordinator_addr, &args)?);
        // On a port of its choosing, the coordinator names it before the workers start.
        let start = Instant::now();
        let mut tick = tokio::time::interval(POLL);
        if let Started::Signalled = cluster
            .coordinator_port(&mut signals, &mut tick, start)
            .await?
        {
            return Ok(());
        }
        if let Some(dir) = &a.trace_dir {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("--trace-dir {}: cannot create it", dir.display()))?;
        }
        let coordinator_addr = cluster.members[0].addr;
        let coordinator_url = format!("{scheme}://{coordinator_addr}");
        for (i, w) in worker_addrs.iter().enumerate() {
            // One name for the worker everywhere: these lines, the coordinator's logs,
            // ListWorkers and the dashboard; a worker started again keeps it.
            let name = format!("worker-{}", i + 1);
            let args = worker_args(&a, &name, &coordinator_url, *w, &shared_args);
            cluster.members.push(spawn(&exe, name, *w, &args)?);
        }
        if let Started::Signalled = cluster
            .all_ready(&mut signals, &mut tick, start, &net)
            .await?
        {
            return Ok(());
        }
        print_ready(
            &cluster,
            &a,
            coordinator_addr,
            net.tls(),
            api_token.is_some(),
        );
        cluster
            .supervise(&mut signals, &mut tick, &exe, a.restart_limit)
            .await
    })
}
