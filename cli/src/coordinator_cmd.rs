//! `dray coordinator`: serve the public `dray.v1.RenderService` and the internal
//! `dray.v1.ClusterService` (both with gRPC reflection and health) on `--listen`.
//!
//! Where a job runs: while no worker is registered, an accepted job renders in this
//! process, one at a time, with the same code path as `dray render`; once at least one
//! worker (`dray worker --coordinator ADDR`) is registered, jobs run on the workers, which
//! read the job's scene package from `--work-dir` when they share it, or fetch it from
//! this coordinator's `dray.v1.PackageService`. Either way the image fetched with
//! GetImage has the same bits as `dray render` with the same settings.
//!
//! Ctrl-C or SIGTERM stops the server: the workers' assignment streams are ended and the
//! work directory is removed if no job left anything in it.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args;
use dray_coordinator::cluster::{ClusterOptions, DEFAULT_STALL_TIMEOUT};
use dray_coordinator::jobs::Retention;
use dray_coordinator::membership::HeartbeatConfig;
use dray_coordinator::store::{JobStore, StoredJob};
use dray_coordinator::validate::Limits;

use crate::net_flags::{self, ApiTokenArgs, MemberArgs};

/// How long, after the server has stopped, the process waits for blocking work (a scene
/// being loaded, an in-process render) before it exits without it.
const BLOCKING_GRACE: Duration = Duration::from_millis(500);

/// How long, on a stop, package cuts in progress get to stop before their folders are
/// removed anyway (a cut looks at its cancel flag every 64 Ki triangles).
const PACKAGE_GRACE: Duration = Duration::from_secs(2);

/// How long a graceful shutdown may take before the process exits anyway (a client still
/// watching a job would otherwise hold it open).
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// Serve the render API; jobs run on the registered workers, or in this process while
/// none is registered. (The one-line help of `dray coordinator` is the doc comment of
/// `Command::Coordinator` in main.rs, which clap puts over this one.)
#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to serve gRPC on, e.g. 127.0.0.1:7070 (port 0 picks a free port).
    #[arg(long)]
    pub listen: String,
    /// Directory that scene files in jobs are resolved against; paths escaping it are
    /// rejected. Procedural scenes (cornell, spheres:N, ...) need no files.
    #[arg(long, default_value = ".")]
    pub scene_root: PathBuf,
    /// Render threads for jobs rendered in this process, while no worker is registered
    /// (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Directory where the scene packages of jobs on workers are written (one
    /// subdirectory per job, removed when the job ends). Workers that see it at the same
    /// path (a shared file system) read the packages there; others fetch the files they
    /// need from this coordinator over gRPC. Created if missing; use one directory per
    /// coordinator.
    /// [default: a new directory in the system temp directory]
    #[arg(long, value_name = "DIR")]
    pub work_dir: Option<PathBuf>,
    /// Directory where jobs and finished images are kept across restarts (an SQLite
    /// database, its lock and the images): a coordinator started again on it lists the
    /// finished jobs, serves their images, queues the queued ones again and resumes the
    /// running ones, keeping every committed tile. One coordinator per directory (a lock
    /// file says who holds it).
    /// [default: `state` in --work-dir when that is given; without either, jobs are kept
    /// in memory only]
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// How often workers send heartbeats, in milliseconds.
    #[arg(long, value_name = "MS", default_value_t = default_heartbeat().interval.as_millis() as u64)]
    pub heartbeat_interval_ms: u64,
    /// Silence after which a worker is declared lost, in milliseconds: its jobs fail and
    /// new jobs no longer go to it. Must exceed the interval (several intervals is wise:
    /// a worker busy loading a large domain still beats, but late beats happen).
    #[arg(long, value_name = "MS", default_value_t = default_heartbeat().timeout.as_millis() as u64)]
    pub heartbeat_timeout_ms: u64,
    #[command(flatten)]
    pub api_token: ApiTokenArgs,
    #[command(flatten)]
    pub member: MemberArgs,
    /// Jobs queued, preparing or running at once (1..=128: a worker holds at most twice
    /// that); SubmitJob refuses more with RESOURCE_EXHAUSTED.
    #[arg(long, value_name = "N", default_value_t = Limits::MAX_JOBS, value_parser = parse_max_jobs)]
    pub max_jobs: usize,
    /// Jobs running on the workers at once (1 or more); the others wait QUEUED, dealt by
    /// priority, and PauseJob can hold them (docs/operator.md). Default: no limit, every
    /// job starts at once and the workers share their threads between them.
    #[arg(long, value_name = "N")]
    pub max_running_jobs: Option<std::num::NonZeroUsize>,
    /// Largest memory a job may need at the coordinator (image and scene, estimated
    /// before it is accepted; suffixes K, M, G, T). [default: half the machine's memory]
    #[arg(long, value_name = "BYTES", value_parser = crate::bytes::parse_bytes)]
    pub max_job_bytes: Option<u64>,
    /// Keep the images of this many finished jobs (the newest); older ones are dropped
    /// and GetImage says so.
    #[arg(long, value_name = "N", default_value_t = Retention::KEEP_FINISHED)]
    pub keep_finished: usize,
    /// Keep finished jobs' images up to this many bytes in all (the newest first; a
    /// 2048x2048 image takes 96 MiB; suffixes K, M, G, T). [default: --max-job-bytes]
    #[arg(long, value_name = "BYTES", value_parser = crate::bytes::parse_bytes)]
    pub keep_finished_bytes: Option<u64>,
    /// Drop a finished job's image this many seconds after it finished (0: never).
    #[arg(long, value_name = "SECONDS", default_value_t = Retention::TTL.as_secs())]
    pub finished_ttl: u64,
    /// Fail a job on workers when none of them has returned any credit for this many
    /// seconds (0: never): heartbeats show a worker alive, not working, and a member
    /// that never traces would otherwise hold its job forever.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_STALL_TIMEOUT.as_secs())]
    pub stall_timeout: u64,
    /// Take stand-alone cache hosts (`dray cache`): jobs with ray caches or hit maps then
    /// place their cache actors on them. Off by default, since a cache host can change
    /// any image: only turn it on where every holder of the cluster token is trusted.
    #[arg(long)]
    pub cache_hosts: bool,
    #[command(flatten)]
    pub otlp: crate::telemetry::OtlpArgs,
    /// Serve the web dashboard on this address, e.g. 127.0.0.1:8080 (port 0 picks a free
    /// port): jobs with their progress, statistics and image, the workers and their
    /// domains, submit and cancel, through the same RenderService methods as gRPC. With
    /// --auth-token-file it requires the API token. Plain HTTP: keep it on loopback or
    /// behind a port-forward. Off unless given.
    #[arg(long, value_name = "ADDR")]
    pub http_listen: Option<String>,
}

fn default_heartbeat() -> HeartbeatConfig {
    HeartbeatConfig::default()
}

/// The cluster options the flags ask for, checked.
fn cluster_options(a: &CoordinatorArgs) -> Result<ClusterOptions> {
    if a.heartbeat_interval_ms == 0 {
        bail!("--heartbeat-interval-ms 0: the interval must be at least 1 ms");
    }
    if a.heartbeat_timeout_ms <= a.heartbeat_interval_ms {
        bail!(
            "--heartbeat-timeout-ms {} must be longer than --heartbeat-interval-ms {}, or \
             every worker would be declared lost between two beats",
            a.heartbeat_timeout_ms,
            a.heartbeat_interval_ms
        );
    }
    let mut options = ClusterOptions {
        heartbeat: HeartbeatConfig {
            interval: Duration::from_millis(a.heartbeat_interval_ms),
            timeout: Duration::from_millis(a.heartbeat_timeout_ms),
        },
        stall_timeout: (a.stall_timeout > 0).then(|| Duration::from_secs(a.stall_timeout)),
        cache_hosts: a.cache_hosts,
        max_running_jobs: a.max_running_jobs,
        ..ClusterOptions::default()
    };
    if let Some(dir) = &a.work_dir {
        options.work_dir = prepare_work_dir(dir)?.into();
    }
    options.clients = net_flags::client_options(a.member.cluster_token.token()?, &a.member.tls)?;
    Ok(options)
}

/// One line saying who may call what, so an open server is never a surprise.
pub fn describe_access(api: bool, cluster: bool, tls: bool) -> String {
    format!(
        "{} API ({}), {} cluster services ({}), {}",
        if api { "authenticated" } else { "OPEN" },
        if api {
            "the API token is required"
        } else {
            "anyone who reaches the port may submit jobs; set --auth-token-file"
        },
        if cluster { "authenticated" } else { "OPEN" },
        if cluster {
            "the cluster token is required"
        } else {
            "anyone who reaches the port may join; set --cluster-token-file"
        },
        if tls { "TLS" } else { "plaintext" }
    )
}

/// Create `dir` if needed, check it is a writable directory, and make it absolute:
/// workers, which run elsewhere, are given this path.
fn prepare_work_dir(dir: &Path) -> Result<PathBuf> {
    if dir.as_os_str().is_empty() {
        bail!("--work-dir: empty path");
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("--work-dir {}: cannot create it", dir.display()))?;
    let abs = dir
        .canonicalize()
        .with_context(|| format!("--work-dir {}", dir.display()))?;
    if !abs.is_dir() {
        bail!("--work-dir {}: not a directory", dir.display());
    }
    let probe = abs.join(format!(".dray-write-test-{}", std::process::id()));
    std::fs::write(&probe, b"")
        .with_context(|| format!("--work-dir {}: cannot write there", abs.display()))?;
    let _ = std::fs::remove_file(&probe);
    Ok(abs)
}

/// Completes on the first Ctrl-C or SIGTERM.
pub async fn stop_signal() {
    use tokio::signal::unix::{SignalKind, signal};
    let term = signal(SignalKind::terminate());
    let int = signal(SignalKind::interrupt());
    match (term, int) {
        (Ok(mut term), Ok(mut int)) => {
            tokio::select! {
                _ = term.recv() => {}
                _ = int.recv() => {}
            }
        }
        // Without handlers the default action (exit) applies: never complete.
        _ => std::future::pending().await,
    }
}

/// The state directory the flags ask for, if any: `--state-dir`, else `state` in
/// `--work-dir` (made absolute by [`prepare_work_dir`] already).
fn state_dir(a: &CoordinatorArgs, work_dir: &Path) -> Option<PathBuf> {
    match (&a.state_dir, &a.work_dir) {
        (Some(dir), _) => Some(dir.clone()),
        (None, Some(_)) => Some(work_dir.join("state")),
        (None, None) => None,
    }
}

pub fn run(a: CoordinatorArgs) -> Result<()> {
    let options = cluster_options(&a)?;
    // The store is opened first: a locked, damaged or newer one stops the coordinator
    // before it serves anything, with one line naming the file.
    let store = match state_dir(&a, options.work_dir.path()) {
        Some(dir) => {
            let (store, jobs) = JobStore::open(&dir).map_err(|e| anyhow::anyhow!("{e}"))?;
            Some((std::sync::Arc::new(store), jobs))
        }
        None => None,
    };
    // Workers that outlived an earlier coordinator register again within their
    // heartbeat timeout: jobs taken back wait that long (twice) for one.
    let resume_grace = options.heartbeat.timeout.saturating_mul(2);
    let api = a.api_token.token()?;
    let cluster_token = a.member.cluster_token.token()?;
    let access = describe_access(
        api.is_some(),
        cluster_token.is_some(),
        a.member.tls.tls_cert.is_some(),
    );
    let server = net_flags::server_options(api.clone(), cluster_token, &a.member)?;
    let heartbeat = options.heartbeat;
    let work_dir = options.work_dir.clone();
    let coordinator = new_coordinator(&a, options)?;
    let (coordinator, stored, store) = match store {
        Some((store, jobs)) => (coordinator.with_store(store.clone()), jobs, Some(store)),
        None => (coordinator, Vec::new(), None),
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let result = rt.block_on(async {
        let listener = tokio::net::TcpListener::bind(&a.listen)
            .await
            .with_context(|| format!("cannot listen on {}", a.listen))?;
        let addr = listener
            .local_addr()
            .context("cannot read the bound address")?;
        // One line on stdout, so scripts and tests can find the port.
        println!("dray coordinator listening on {addr}");
        let client_certs = a.member.tls.tls_ca.is_some();
        let dashboard = match &a.http_listen {
            Some(http) => Some(
                start_dashboard(
                    http,
                    &coordinator,
                    api,
                    client_certs,
                    server.connection_limits(),
                    server.max_calls,
                )
                .await?,
            ),
            None => None,
        };
        eprintln!(
            "dray coordinator: scene root {}, work dir {}, heartbeats every {} ms (lost after \
             {} ms); jobs run on the registered workers, or in this process while none is \
             registered",
            coordinator.scene_root().display(),
            work_dir.display(),
            heartbeat.interval.as_millis(),
            heartbeat.timeout.as_millis(),
        );
        eprintln!("dray coordinator: {access}");
        take_back(&coordinator, store.as_deref(), stored, resume_grace);
        serve_until_stopped(&coordinator, &server, listener, dashboard).await
    });
    // A scene still loading or a job still rendering runs on a blocking thread, which
    // dropping the runtime would wait for: a stop signal must not wait minutes for it.
    rt.shutdown_timeout(BLOCKING_GRACE);
    result
}

/// The coordinator the flags describe (without its store), on the cluster `options`.
fn new_coordinator(
    a: &CoordinatorArgs,
    options: ClusterOptions,
) -> Result<dray_coordinator::Coordinator> {
    Ok(dray_coordinator::Coordinator::new(&a.scene_root, a.threads)
        .with_context(|| format!("--scene-root {}", a.scene_root.display()))?
        .with_cluster_options(options)
        .with_admission(
            a.max_jobs.max(1),
            a.max_job_bytes
                .unwrap_or_else(dray_coordinator::admission::default_max_job_bytes),
            Retention {
                keep_finished: a.keep_finished,
                ttl: (a.finished_ttl > 0).then(|| Duration::from_secs(a.finished_ttl)),
                max_bytes: a.keep_finished_bytes,
            },
        ))
}

/// Take back the jobs `stored` in `store` (those that had not ended run again, waiting
/// up to `grace` for a worker), and say where jobs are kept.
fn take_back(
    coordinator: &dray_coordinator::Coordinator,
    store: Option<&JobStore>,
    stored: Vec<StoredJob>,
    grace: Duration,
) {
    match store {
        Some(s) => {
            let again = coordinator.resume(stored, grace);
            eprintln!(
                "dray coordinator: jobs kept in {} ({} taken back, {again} to run again)",
                s.dir().display(),
                coordinator.job_count(),
            );
        }
        None => eprintln!(
            "dray coordinator: jobs are kept in memory only (set --state-dir or --work-dir \
             to keep them across restarts)"
        ),
    }
}

/// Serve gRPC on `listener` until a stop signal (or until the server ends on its own,
/// with an error), then shut the coordinator down: the library's one shutdown, then
/// the dashboard, then every job's package.
async fn serve_until_stopped(
    coordinator: &dray_coordinator::Coordinator,
    server: &dray_net::ServerOptions,
    listener: tokio::net::TcpListener,
    dashboard: Option<tokio::task::JoinHandle<()>>,
) -> Result<()> {
    let options = server.clone();
    let serving = coordinator.clone();
    // Stopped by `Coordinator::shutdown`, which also waits for it.
    let mut served = tokio::spawn(async move {
        dray_coordinator::serve_with(&options, listener, serving, std::future::pending()).await
    });
    // Serve until a signal (or the server ends on its own, with an error).
    let ended = tokio::select! {
        r = &mut served => Some(r),
        () = stop_signal() => None,
    };
    // One shutdown, the library's (the embedded mode runs the same): new jobs
    // refused, the store sealed once (jobs stopped by the shutdown itself are not
    // recorded as ended: the next coordinator on this state directory resumes them),
    // cuts stopped, the servers given a bounded time to end.
    let stopped = coordinator.shutdown(SHUTDOWN_GRACE).await;
    let result = match ended {
        Some(r) => r,
        None if stopped || served.is_finished() => served.await,
        None => {
            eprintln!(
                "dray coordinator: clients still connected after {SHUTDOWN_GRACE:?}; \
                 exiting anyway"
            );
            served.abort();
            Ok(Ok(()))
        }
    };
    if let Some(d) = dashboard {
        d.abort();
    }
    // No job's package outlives the coordinator: cuts in progress are stopped and
    // every job folder removed (a large preparation's partial package included).
    coordinator.remove_packages_on_stop(PACKAGE_GRACE).await;
    result
        .context("the gRPC server task died")?
        .context("the gRPC server stopped")
}

/// Bind `--http-listen` and serve the dashboard there until the coordinator's shutdown
/// stops its servers; says
/// where on stdout (`dray coordinator dashboard on http://ADDR`).
async fn start_dashboard(
    http: &str,
    coordinator: &dray_coordinator::Coordinator,
    api: Option<dray_net::Token>,
    client_certs: bool,
    limits: dray_net::connections::ConnectionLimits,
    max_calls: usize,
) -> Result<tokio::task::JoinHandle<()>> {
    let listener = tokio::net::TcpListener::bind(http)
        .await
        .with_context(|| format!("--http-listen: cannot listen on {http}"))?;
    let addr = listener
        .local_addr()
        .context("cannot read the dashboard's bound address")?;
    let warning = dashboard_exposure(addr, api.is_some(), client_certs)?;
    // Its calls in progress under --max-calls, as each class of gRPC caller's are.
    let dashboard = dray_coordinator::http::Dashboard::new(coordinator.clone(), api.clone())?
        .with_max_calls(max_calls);
    println!("dray coordinator dashboard on http://{addr}");
    eprintln!(
        "dray coordinator: dashboard on http://{addr} ({}; requests must name an IP address \
         or localhost as their Host)",
        if api.is_some() {
            "the API token is required"
        } else {
            "OPEN: no API token"
        }
    );
    if let Some(w) = warning {
        eprintln!("dray coordinator: WARNING: {w}");
    }
    // It stops with the gRPC server, once the coordinator's shutdown has sealed the store.
    let shutdown = coordinator.stopped();
    Ok(tokio::spawn(async move {
        if let Err(e) = dray_coordinator::http::serve(listener, dashboard, limits, shutdown).await {
            eprintln!("dray coordinator: {e}");
        }
    }))
}

/// What serving the plain-HTTP dashboard on `addr` exposes: nothing to say on loopback;
/// a warning on any other address (the API token, the session cookie and images cross
/// the network unencrypted, and without a token anyone who reaches the port may submit
/// and cancel jobs); a refusal when the gRPC side requires client certificates
/// (`--tls-ca`), since the dashboard would be a way around them.
fn dashboard_exposure(
    addr: std::net::SocketAddr,
    api_token: bool,
    client_certs: bool,
) -> Result<Option<String>> {
    if addr.ip().is_loopback() {
        return Ok(None);
    }
    if client_certs {
        bail!(
            "--http-listen {addr}: the dashboard is plain HTTP without client certificates, \
             so on a non-loopback address it would let anyone who reaches it past the \
             certificates --tls-ca requires; bind it to 127.0.0.1 (or [::1]) and reach it \
             through an SSH tunnel, kubectl port-forward or a TLS proxy"
        );
    }
    Ok(Some(format!(
        "the dashboard on http://{addr} is plain HTTP on a non-loopback address: {}; bind it \
         to 127.0.0.1 and reach it through an SSH tunnel, kubectl port-forward or a TLS proxy",
        if api_token {
            "the API token and the session cookie cross the network unencrypted"
        } else {
            "with no API token, anyone who reaches this port can submit and cancel jobs"
        }
    )))
}

/// `--max-jobs`: 1..=[`MAX_COORDINATOR_JOBS`](dray_cache::bounds::MAX_COORDINATOR_JOBS),
/// so a worker never refuses a job the coordinator admitted.
fn parse_max_jobs(s: &str) -> Result<usize, String> {
    let max = dray_cache::bounds::MAX_COORDINATOR_JOBS;
    match s.parse::<usize>() {
        Ok(n) if (1..=max).contains(&n) => Ok(n),
        _ => Err(format!("expected a whole number in 1..={max}")),
    }
}

#[cfg(test)]
mod tests {
    use super::dashboard_exposure;

    /// Issue 45, item 10: a plain-HTTP dashboard on a public address said nothing, even
    /// when the gRPC side required client certificates.
    #[test]
    fn a_public_plain_http_dashboard_is_warned_about_or_refused() {
        let public = "0.0.0.0:8080".parse().expect("address");
        let lan = "192.168.1.5:8080".parse().expect("address");
        for local in ["127.0.0.1:8080", "[::1]:8080", "127.0.0.2:1"] {
            let a = local.parse().expect("address");
            assert!(
                dashboard_exposure(a, false, true)
                    .expect("loopback is fine")
                    .is_none()
            );
        }
        let open = dashboard_exposure(public, false, false)
            .expect("a warning, not a refusal")
            .expect("a warning");
        assert!(
            open.contains("anyone") && open.contains("127.0.0.1"),
            "{open}"
        );
        let token = dashboard_exposure(lan, true, false)
            .expect("a warning")
            .expect("a warning");
        assert!(token.contains("unencrypted"), "{token}");
        let refused = dashboard_exposure(public, true, true).expect_err("refused");
        assert!(refused.to_string().contains("--tls-ca"), "{refused}");
    }
}
