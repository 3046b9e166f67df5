//! `dray submit`: send a job to a coordinator over the public `dray.v1.RenderService`,
//! follow its progress and write the image it returns.
//!
//! The flags are `dray render`'s wherever `JobSpec` has a field for them, with the same
//! defaults, so `dray submit` and `dray render` with the same flags give the same bits.
//! Validation is the server's job: it answers `INVALID_ARGUMENT` with a message naming the
//! field, which is printed as it is, so the rules live in one place. Only what never
//! reaches the server (the address, `--env`/`--translate` syntax, exposure and tone
//! curve, which are applied at fetch time) is checked here, before anything is submitted.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use clap::Args;
use dray_core::display::Display;
use dray_core::exposure::Exposure;
use dray_net::{AuthChannel, ClientOptions};
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetJobRequest, ImageFormat, Job, JobProgress, JobSpec,
    JobState, SubmitJobRequest, WatchJobRequest,
};
use serde::Serialize;

use crate::summary::{PhmSummary, RayCacheSummary, Scheduling, ray_counts, rays_by_name};

#[derive(Args, Debug)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub job: crate::job_flags::JobFlags,
    /// The coordinator's gRPC address: host:port or http://host:port.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::SUBMIT)]
    pub coordinator: String,
    /// Spatial domains to cut the scene into (default: the coordinator chooses; ignored
    /// for scene packages, which carry their own).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub domains: Option<u32>,
    /// Domain layout: grid or kd (default: the coordinator's).
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::CLUSTER)]
    pub layout: Option<String>,
    /// A label shown by ListJobs; no effect on the image.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::SUBMIT)]
    pub label: Option<String>,
    /// Where the job stands among queued jobs (JobSpec.priority): a higher one is dealt
    /// first; running jobs are not pre-empted. No effect on the image.
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    #[arg(help_heading = crate::help_heading::SUBMIT)]
    pub priority: i32,
    /// Ask the workers to record the job's traffic (JobSpec.trace): each worker started
    /// with `--trace-dir` writes its records there (docs/caches.md "The trace's
    /// schema"); others record nothing. No effect on the image.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::SUBMIT)]
    pub trace: bool,
    /// When the coordinator goes away while the job runs, wait this many seconds for it
    /// to come back and follow the job again (a coordinator with a state directory keeps
    /// its jobs across restarts); 0 fails at once.
    #[arg(long, value_name = "SECONDS", default_value_t = RECONNECT_WAIT.as_secs())]
    #[arg(help_heading = crate::help_heading::SUBMIT)]
    pub reconnect_wait: u64,
    /// Rewrite this PNG with the running job's image after each progressive pass
    /// (`--passes`), so a viewer can watch it sharpen; the final image goes to --output.
    #[arg(long, value_name = "FILE")]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub preview: Option<PathBuf>,
    /// Write the finished job's statistics as JSON (GetJob's: rays by kind, domains,
    /// and the scheduling metrics, per worker too).
    #[arg(long, value_name = "FILE")]
    #[arg(help_heading = crate::help_heading::OUTPUT)]
    pub stats: Option<PathBuf>,
    #[command(flatten, next_help_heading = crate::help_heading::SUBMIT)]
    pub api_token: crate::net_flags::ApiTokenArgs,
    #[command(flatten)]
    pub tls: crate::net_flags::TlsArgs,
}

/// `dray submit --stats`: the job as GetJob reports it once finished, with the keys of
/// `dray render --stats` where they mean the same.
#[derive(Serialize, Debug)]
pub(crate) struct SubmitStats {
    job_id: String,
    coordinator: String,
    scene: String,
    width: u32,
    height: u32,
    spp: u32,
    integrator: String,
    max_depth: u32,
    seed: u64,
    triangles: u64,
    effects: Vec<String>,
    rays: BTreeMap<&'static str, u64>,
    rays_total: u64,
    /// Spatial domains the scene was cut into.
    domains: u32,
    nonfinite_contributions: u64,
    /// Contributions clamped to the film's largest radiance.
    clamped_contributions: u64,
    /// Contributions of indirect light scaled down by `--clamp-indirect`.
    clamped_indirect: u64,
    /// Adaptive sampling (`--noise-threshold`): tiles stopped early, samples saved.
    tiles_stopped: u32,
    samples_saved: u64,
    /// The coordinator's time for the job, preparation included.
    job_time_s: f64,
    /// From submission to the image written, as seen here.
    wall_time_s: f64,
    #[serde(flatten)]
    scheduling: Scheduling,
    /// What the ray caches did; absent when the job had none.
    #[serde(skip_serializing_if = "Option::is_none")]
    ray_cache: Option<RayCacheSummary>,
    /// What the hit maps did; absent when the job had none.
    #[serde(skip_serializing_if = "Option::is_none")]
    phm: Option<PhmSummary>,
}

impl SubmitStats {
    pub(crate) fn of(job: &Job, url: &str, wall: Duration) -> SubmitStats {
        let spec = job.spec.clone().unwrap_or_default();
        let stats = job.stats.clone().unwrap_or_default();
        let rays = ray_counts(&stats.rays.unwrap_or_default());
        SubmitStats {
            job_id: job.job_id.clone(),
            coordinator: url.to_string(),
            scene: spec.scene,
            width: spec.width,
            height: spec.height,
            spp: spec.spp,
            integrator: spec.integrator,
            max_depth: spec.max_depth.unwrap_or_default(),
            seed: spec.seed,
            triangles: stats.triangles,
            effects: stats.effects.clone(),
            rays: rays_by_name(&rays),
            rays_total: rays.total(),
            domains: stats.domains,
            nonfinite_contributions: stats.nonfinite,
            clamped_contributions: stats.clamped,
            clamped_indirect: stats.clamped_indirect,
            tiles_stopped: stats.tiles_stopped,
            samples_saved: stats.samples_saved,
            job_time_s: job
                .progress
                .as_ref()
                .and_then(|p| p.elapsed)
                .map_or(0.0, |d| d.seconds as f64 + f64::from(d.nanos) * 1e-9),
            wall_time_s: wall.as_secs_f64(),
            scheduling: Scheduling::of(&stats),
            ray_cache: RayCacheSummary::of(&stats),
            phm: PhmSummary::of(&stats),
        }
    }
}

/// How long `dray submit` waits by default for a coordinator that went away mid-job.
pub const RECONNECT_WAIT: Duration = Duration::from_secs(120);

/// `host:port` or `http://host:port` as the URL tonic wants. Plaintext only: dray's
/// servers do not speak TLS, and saying so beats a handshake error.
pub fn endpoint_url(addr: &str) -> Result<String> {
    let addr = addr.trim();
    if addr.is_empty() {
        bail!("--coordinator: empty address (expected host:port or http://host:port)");
    }
    if addr.starts_with("https://") {
        bail!("--coordinator {addr}: https is not supported (dray serves plaintext gRPC)");
    }
    let url = if addr.starts_with("http://") {
        addr.to_string()
    } else if addr.contains("://") {
        bail!("--coordinator {addr}: expected host:port or http://host:port");
    } else {
        format!("http://{addr}")
    };
    Ok(url)
}

/// The job spec the flags describe.
pub(crate) fn job_spec(a: &SubmitArgs) -> Result<JobSpec> {
    let spec = a.job.job_spec(
        a.job.scene.clone(),
        a.domains.unwrap_or(0),
        a.layout.as_deref().unwrap_or_default(),
        a.label.as_deref().unwrap_or_default(),
    )?;
    Ok(JobSpec {
        priority: a.priority,
        trace: a.trace,
        ..spec
    })
}

/// A gRPC failure as one line: what was being done and what the server said.
pub(crate) fn rpc_error(what: &str, url: &str, s: tonic::Status) -> anyhow::Error {
    let msg = s.message().replace('\n', " ");
    match s.code() {
        tonic::Code::InvalidArgument => anyhow!("the coordinator rejected the job: {msg}"),
        tonic::Code::Unavailable => {
            anyhow!("{what}: the coordinator at {url} is unavailable: {msg}")
        }
        tonic::Code::Unimplemented => anyhow!(
            "{what}: {url} does not serve dray.v1.RenderService (is it a dray coordinator?): {msg}"
        ),
        code => anyhow!("{what} failed ({code:?}): {msg}"),
    }
}

pub fn run(a: SubmitArgs) -> Result<()> {
    let spec = job_spec(&a)?;
    a.job.check_passes()?;
    a.job.check_aovs()?;
    let url = endpoint_url(&a.coordinator)?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    if let Some(range) = a.job.anim.frames {
        return rt.block_on(crate::frames::submit_frames(a, spec, url, range));
    }
    rt.block_on(submit(a, spec, url))
}

pub(crate) async fn connect(
    net: &ClientOptions,
    url: &str,
) -> Result<RenderServiceClient<AuthChannel>> {
    let channel = net
        .endpoint(url)
        .with_context(|| format!("--coordinator: {url} is not a valid address"))?
        .connect_timeout(Duration::from_secs(10))
        .connect()
        .await
        .with_context(|| format!("cannot connect to the coordinator at {url}"))?;
    // Images are one message each: a large EXR is far beyond tonic's 4 MiB default.
    Ok(RenderServiceClient::new(net.wrap(channel)).max_decoding_message_size(usize::MAX))
}

async fn submit(a: SubmitArgs, spec: JobSpec, url: String) -> Result<()> {
    let started = Instant::now();
    let net = crate::net_flags::client_options(a.api_token.token()?, &a.tls)?;
    let url = net.url(&url);
    let mut client = connect(&net, &url).await?;
    let reconnect = Duration::from_secs(a.reconnect_wait);
    let preview = a.preview.clone().map(|p| (p, a.job.display()));
    let (id, last) = run_job(
        &mut client,
        spec,
        &url,
        a.job.quiet,
        "dray submit",
        reconnect,
        preview,
    )
    .await?;

    // The job has ended; the coordinator may still go away before its image is fetched
    // (a coordinator with a state directory keeps it): each call waits for it as the
    // watch did.
    let again = Reconnect {
        who: "dray submit",
        wait: reconnect,
    };
    let png = across_restarts(&url, &again, "GetImage", || {
        image(client.clone(), &id, ImageFormat::Png, a.job.display())
    })
    .await?;
    std::fs::write(&a.job.output, &png)
        .with_context(|| format!("cannot write {}", a.job.output.display()))?;
    if let Some(path) = &a.job.exr {
        let exr = across_restarts(&url, &again, "GetImage", || {
            image(client.clone(), &id, ImageFormat::Exr, Display::default())
        })
        .await?;
        std::fs::write(path, &exr).with_context(|| format!("cannot write {}", path.display()))?;
    }
    // The final statistics (scheduling metrics included) are GetJob's: WatchJob carries
    // progress only.
    let job = if a.stats.is_some() || !a.job.quiet {
        let job = across_restarts(&url, &again, "GetJob", || {
            let mut c = client.clone();
            let job_id = id.clone();
            async move { Ok(c.get_job(GetJobRequest { job_id }).await?.into_inner().job) }
        })
        .await?;
        Some(job.with_context(|| format!("GetJob: no job {id}"))?)
    } else {
        None
    };
    if let (Some(path), Some(job)) = (&a.stats, &job) {
        let stats = SubmitStats::of(job, &url, started.elapsed());
        let json = serde_json::to_string_pretty(&stats).context("cannot encode statistics")?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    if !a.job.quiet {
        let secs = last
            .elapsed
            .map(|d| d.seconds as f64 + f64::from(d.nanos) * 1e-9)
            .unwrap_or(0.0);
        eprintln!(
            "dray submit: job {id} done in {secs:.2} s, {} rays traced; wrote {}{}",
            last.rays_traced,
            a.job.output.display(),
            a.job
                .exr
                .as_ref()
                .map(|p| format!(" and {}", p.display()))
                .unwrap_or_default()
        );
        let stats = job.and_then(|j| j.stats).unwrap_or_default();
        let scheduling = Scheduling::of(&stats);
        if let Some(line) = scheduling.line() {
            eprintln!("dray submit: schedule {line}");
        }
        if let Some(why) = scheduling.placement_line() {
            eprintln!("dray submit: placement {why}");
        }
        if let Some(rc) = RayCacheSummary::of(&stats) {
            for line in rc.lines() {
                eprintln!("dray submit: ray caches {line}");
            }
        }
        if let Some(p) = PhmSummary::of(&stats) {
            eprintln!("dray submit: hit maps {}", p.line());
        }
    }
    Ok(())
}

/// Submit `spec` and follow the job to its end (a progress view unless `quiet`; `who`
/// prefixes the messages); its id and last progress once it succeeded. Ctrl-C cancels
/// it. Shared with `dray sweep --coordinator`, which fetches what it needs itself.
pub(crate) async fn run_job(
    client: &mut RenderServiceClient<AuthChannel>,
    spec: JobSpec,
    url: &str,
    quiet: bool,
    who: &str,
    reconnect: Duration,
    preview: Option<(PathBuf, Display)>,
) -> Result<(String, JobProgress)> {
    // SubmitJob answers after the scene is loaded, which can take a while; a Ctrl-C in
    // that window must still cancel the job the server is about to accept.
    let submit = client.clone();
    let mut submitting = Box::pin(async move {
        let mut c = submit;
        c.submit_job(SubmitJobRequest { spec: Some(spec) }).await
    });
    let response = tokio::select! {
        r = &mut submitting => r,
        _ = tokio::signal::ctrl_c() => {
            eprintln!("{who}: interrupted; waiting for the job id to cancel it (Ctrl-C again to leave it)");
            tokio::select! {
                r = &mut submitting => {
                    if let Ok(resp) = r {
                        let id = resp.into_inner().job_id;
                        cancel(client, &id).await;
                        bail!("interrupted: job {id} cancelled");
                    }
                    bail!("interrupted before the job was accepted");
                }
                _ = tokio::signal::ctrl_c() => bail!("interrupted; the job may still run on the coordinator"),
            }
        }
    }
    .map_err(|s| rpc_error("SubmitJob", url, s))?;
    let id = response.into_inner().job_id;
    if !quiet {
        eprintln!("{who}: job {id} accepted by {url}");
    }

    let preview = preview.map(|(path, display)| {
        crate::preview::spawn(client.clone(), id.clone(), path, display, quiet)
    });
    let watcher = client.clone();
    let last = tokio::select! {
        r = watch(watcher, &id, url, quiet, Reconnect { who, wait: reconnect }) => r,
        _ = tokio::signal::ctrl_c() => {
            cancel(client, &id).await;
            Err(anyhow::anyhow!("interrupted: job {id} cancelled"))
        }
    };
    if let Some(p) = preview {
        // The last image of a job that succeeded is the final one: let it land.
        if last
            .as_ref()
            .is_ok_and(|l| l.state() == JobState::Succeeded)
        {
            let _ = tokio::time::timeout(Duration::from_secs(30), p).await;
        } else {
            p.abort();
        }
    }
    let last = last?;
    match last.state() {
        JobState::Succeeded => Ok((id, last)),
        JobState::Failed => bail!("job {id} failed: {}", last.error.replace('\n', " ")),
        JobState::Cancelled => bail!("job {id} was cancelled"),
        other => bail!("job {id} ended in unexpected state {}", other.as_str_name()),
    }
}

/// GetJob: the job as the coordinator knows it.
pub(crate) async fn get_job(
    client: &mut RenderServiceClient<AuthChannel>,
    id: &str,
    url: &str,
) -> Result<Job> {
    client
        .get_job(GetJobRequest {
            job_id: id.to_string(),
        })
        .await
        .map_err(|s| rpc_error("GetJob", url, s))?
        .into_inner()
        .job
        .with_context(|| format!("GetJob: no job {id}"))
}

/// Best effort: the user asked to stop, so a failure to cancel is reported, not fatal.
pub(crate) async fn cancel(client: &mut RenderServiceClient<AuthChannel>, id: &str) {
    let req = CancelJobRequest {
        job_id: id.to_string(),
    };
    match tokio::time::timeout(Duration::from_secs(10), client.cancel_job(req)).await {
        Ok(Ok(_)) => {}
        Ok(Err(s)) => eprintln!("dray submit: could not cancel job {id}: {}", s.message()),
        Err(_) => eprintln!("dray submit: could not cancel job {id}: no answer within 10 s"),
    }
}

/// `display` as GetImageRequest and WatchImageRequest spell it: `exposure` absent for
/// automatic, the curve by name.
pub(crate) fn wire_display(display: Display) -> (Option<f32>, String) {
    let exposure = match display.exposure {
        Exposure::Auto => None,
        Exposure::Stops(ev) => Some(ev),
    };
    (exposure, display.tonemap.name().to_string())
}

/// GetImage: the job's image as `format`, a PNG through `display` (which the
/// coordinator applies to the assembled film, as `dray render` does to its own).
pub(crate) async fn fetch(
    client: &mut RenderServiceClient<AuthChannel>,
    id: &str,
    format: ImageFormat,
    display: Display,
    url: &str,
) -> Result<Vec<u8>> {
    image(client.clone(), id, format, display)
        .await
        .map_err(|s| rpc_error("GetImage", url, s))
}

/// [`fetch`]'s call, its status kept (to tell a coordinator gone from an answer).
pub(crate) fn image(
    mut client: RenderServiceClient<AuthChannel>,
    id: &str,
    format: ImageFormat,
    display: Display,
) -> impl Future<Output = Result<Vec<u8>, tonic::Status>> + use<> {
    let (exposure, tonemap) = wire_display(display);
    let req = GetImageRequest {
        job_id: id.to_string(),
        format: format as i32,
        exposure,
        tonemap,
    };
    async move { Ok(client.get_image(req).await?.into_inner().data.to_vec()) }
}

/// `call` (named `what` in errors), made again while the coordinator is gone, for at most
/// `reconnect.wait` (saying so once): for the calls after a job's end, whose coordinator
/// may restart in between and, with a state directory, still answers for the job.
pub(crate) async fn across_restarts<T, F>(
    url: &str,
    reconnect: &Reconnect<'_>,
    what: &str,
    mut call: impl FnMut() -> F,
) -> Result<T>
where
    F: Future<Output = Result<T, tonic::Status>>,
{
    let mut lost: Option<Instant> = None;
    loop {
        let status = match call().await {
            Ok(v) => return Ok(v),
            Err(s) if coordinator_gone(&s) => s,
            Err(s) => return Err(rpc_error(what, url, s)),
        };
        let since = *lost.get_or_insert_with(|| {
            eprintln!(
                "{}: lost the coordinator at {url} ({}) after the job's end; waiting up to \
                 {} s for it to come back ({what})",
                reconnect.who,
                status.message().replace('\n', " "),
                reconnect.wait.as_secs()
            );
            Instant::now()
        });
        if since.elapsed() >= reconnect.wait {
            return Err(rpc_error(what, url, status));
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

fn is_terminal(s: JobState) -> bool {
    matches!(
        s,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

/// Human name of a state: "running" for JOB_STATE_RUNNING.
fn state_name(s: JobState) -> String {
    s.as_str_name()
        .trim_start_matches("JOB_STATE_")
        .to_ascii_lowercase()
}

/// How [`watch`] follows a job across a coordinator that goes away.
#[derive(Clone, Copy)]
pub(crate) struct Reconnect<'a> {
    /// Prefix of the messages.
    pub(crate) who: &'a str,
    /// Longest wait for the coordinator to come back.
    pub(crate) wait: Duration,
}

/// Whether `s` says the coordinator went away (a restart, a dropped connection), rather
/// than answering about the job.
fn coordinator_gone(s: &tonic::Status) -> bool {
    use tonic::Code;
    match s.code() {
        Code::Unavailable | Code::Unknown | Code::Cancelled | Code::Aborted => true,
        Code::Internal => {
            let m = s.message();
            m.contains("h2 protocol error") || m.contains("connection") || m.contains("transport")
        }
        _ => false,
    }
}

/// Follow WatchJob to a terminal state and return the last progress message. A stream
/// that ends early (a proxy timeout, a restart) is not the job's end: GetJob tells, and
/// the job is watched again. When the coordinator goes away, it is waited for (at most
/// `reconnect.wait`, saying so) and the same job followed again once it is back: a
/// coordinator with a state directory resumes its jobs.
pub(crate) async fn watch(
    mut client: RenderServiceClient<AuthChannel>,
    id: &str,
    url: &str,
    quiet: bool,
    reconnect: Reconnect<'_>,
) -> Result<JobProgress> {
    let mut view = ProgressView::new(quiet);
    let mut lost: Option<Instant> = None;
    loop {
        let outcome = watch_once(&mut client, id, &mut view).await;
        let status = match outcome {
            Ok(Some(p)) => {
                view.finish();
                return Ok(p);
            }
            // The stream ended before the job did: ask where it is.
            Ok(None) => match client
                .get_job(GetJobRequest {
                    job_id: id.to_string(),
                })
                .await
            {
                Ok(r) => {
                    let p = r
                        .into_inner()
                        .job
                        .and_then(|j| j.progress)
                        .with_context(|| format!("GetJob: no progress for job {id}"))?;
                    if is_terminal(p.state()) {
                        view.finish();
                        return Ok(p);
                    }
                    if lost.take().is_some() {
                        eprintln!(
                            "{}: the coordinator at {url} is back; following job {id} again",
                            reconnect.who
                        );
                    }
                    tokio::time::sleep(Duration::from_millis(200)).await;
                    continue;
                }
                Err(s) => s,
            },
            Err(s) => s,
        };
        if status.code() == tonic::Code::NotFound && lost.is_some() {
            view.finish();
            bail!(
                "the coordinator at {url} came back without job {id}: it keeps jobs across \
                 restarts only with a state directory (--state-dir, or --work-dir)"
            );
        }
        if !coordinator_gone(&status) {
            view.finish();
            return Err(rpc_error("WatchJob", url, status));
        }
        let since = *lost.get_or_insert_with(|| {
            view.finish();
            eprintln!(
                "{}: lost the coordinator at {url} ({}); waiting up to {} s for it to come \
                 back to follow job {id}",
                reconnect.who,
                status.message().replace('\n', " "),
                reconnect.wait.as_secs()
            );
            Instant::now()
        });
        if since.elapsed() >= reconnect.wait {
            bail!(
                "the coordinator at {url} did not come back within {} s (job {id} may still \
                 be kept by it: look with ListJobs once it is back)",
                reconnect.wait.as_secs()
            );
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// One WatchJob stream to its end: the terminal progress, None when the stream ended
/// before the job did, or the stream's error.
async fn watch_once(
    client: &mut RenderServiceClient<AuthChannel>,
    id: &str,
    view: &mut ProgressView,
) -> Result<Option<JobProgress>, tonic::Status> {
    let mut stream = client
        .watch_job(WatchJobRequest {
            job_id: id.to_string(),
            min_interval: None,
        })
        .await?
        .into_inner();
    while let Some(p) = stream.message().await? {
        view.show(&p);
        if is_terminal(p.state()) {
            return Ok(Some(p));
        }
    }
    Ok(None)
}

/// A progress bar on a terminal, plain lines (state changes and at most one a second)
/// when stderr is a file or a pipe, nothing with `--quiet`.
enum ProgressView {
    Quiet,
    Bar(indicatif::ProgressBar),
    Lines {
        last_state: Option<JobState>,
        last_line: Option<Instant>,
    },
}

/// ", pass 3/9" while a job of several passes runs (its tiles count again each pass).
fn pass_of(p: &JobProgress) -> String {
    if p.passes_total > 1 && p.state() == JobState::Running {
        format!(
            ", pass {}/{}",
            (p.passes_done + 1).min(p.passes_total),
            p.passes_total
        )
    } else {
        String::new()
    }
}

impl ProgressView {
    fn new(quiet: bool) -> ProgressView {
        if quiet {
            ProgressView::Quiet
        } else if std::io::stderr().is_terminal() {
            let b = indicatif::ProgressBar::new(0);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} {msg:10} [{bar:40}] {pos}/{len} tiles {elapsed}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b.enable_steady_tick(Duration::from_millis(120));
            ProgressView::Bar(b)
        } else {
            ProgressView::Lines {
                last_state: None,
                last_line: None,
            }
        }
    }

    fn show(&mut self, p: &JobProgress) {
        match self {
            ProgressView::Quiet => {}
            ProgressView::Bar(b) => {
                b.set_length(u64::from(p.tiles_total));
                b.set_position(u64::from(p.tiles_done));
                b.set_message(format!("{}{}", state_name(p.state()), pass_of(p)));
            }
            ProgressView::Lines {
                last_state,
                last_line,
            } => {
                let changed = *last_state != Some(p.state());
                let due = last_line.is_none_or(|t| t.elapsed() >= Duration::from_secs(1));
                if changed || due {
                    eprintln!(
                        "job {}: {}{}, {}/{} tiles, {} rays traced, {} in flight",
                        p.job_id,
                        state_name(p.state()),
                        pass_of(p),
                        p.tiles_done,
                        p.tiles_total,
                        p.rays_traced,
                        p.rays_in_flight
                    );
                    *last_state = Some(p.state());
                    *last_line = Some(Instant::now());
                }
            }
        }
    }

    fn finish(&mut self) {
        if let ProgressView::Bar(b) = self {
            b.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses() {
        assert_eq!(endpoint_url("127.0.0.1:1").unwrap(), "http://127.0.0.1:1");
        assert_eq!(endpoint_url("http://h:2").unwrap(), "http://h:2");
        assert!(endpoint_url("https://h:2").is_err());
        assert!(endpoint_url("ftp://h:2").is_err());
        assert!(endpoint_url(" ").is_err());
    }
}
