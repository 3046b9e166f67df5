//! The tonic `dray.v1.RenderService`, and [`serve`], which adds gRPC server reflection
//! and the standard health service beside it.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;

use dray_core::display::Display;
use dray_core::scene::Scene;
use dray_proto::v1::cluster_service_server::ClusterServiceServer;
use dray_proto::v1::package_service_server::PackageServiceServer;
use dray_proto::v1::render_service_server::{RenderService, RenderServiceServer};
use dray_proto::v1::{
    CancelJobRequest, CancelJobResponse, GetImageRequest, GetImageResponse, GetJobRequest,
    GetJobResponse, ImageFormat, JobProgress, JobSpec, JobState, ListJobsRequest, ListJobsResponse,
    ListWorkersRequest, ListWorkersResponse, PauseJobRequest, PauseJobResponse, RetryJobRequest,
    RetryJobResponse, SubmitJobRequest, SubmitJobResponse, WatchImageRequest, WatchJobRequest,
};
use tokio::net::TcpListener;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};
use tracing::Instrument;

use crate::cluster::{Cluster, ClusterApi, ClusterOptions};
use crate::dispatch;
use crate::job::JobRecord;
use crate::jobs::{JobEntry, JobTable, encode_exr, encode_png, requested_display};
use crate::package_service::PackageApi;
use crate::scheduler::Schedule;
use crate::store::{JobStore, Resume, StoredJob};
use crate::text::bounded;
use crate::validate::{Limits, prepare, validate};

/// Default least time between two WatchImage messages.
pub const DEFAULT_IMAGE_INTERVAL: Duration = Duration::from_millis(500);
/// How long ListWorkers waits for a running job's actor to describe itself.
const VIEW_WAIT: Duration = Duration::from_secs(2);
/// Default least time between two WatchJob messages.
pub const DEFAULT_WATCH_INTERVAL: Duration = Duration::from_millis(250);
/// Default and largest ListJobs page.
pub const DEFAULT_PAGE_SIZE: usize = 50;
const MAX_PAGE_SIZE: usize = 1000;

/// The coordinator's RenderService: the job table, the limits, the scene root, and the
/// cluster of workers jobs run on when any is registered.
#[derive(Clone)]
pub struct Coordinator {
    table: Arc<JobTable>,
    /// The in-process render slot, for jobs while no worker is registered.
    local: Arc<crate::local_render::LocalRenderer>,
    limits: Limits,
    scene_root: PathBuf,
    cluster: Arc<Cluster>,
    loads: Arc<SceneLoads>,
    /// Rays per second per worker, between ListWorkers calls.
    rates: Arc<crate::worker_list::RateWindow>,
    /// Whether [`Coordinator::shutdown`] has begun, and the servers it stops.
    shutdown: Arc<crate::shutdown::Shutdown>,
}

/// Scene loads running off the request path, and how many a CancelJob stopped before
/// they finished: a cancelled job's load must end, not hold its memory for minutes.
#[derive(Debug, Default)]
struct SceneLoads {
    running: AtomicUsize,
    stopped: AtomicU64,
}

impl Coordinator {
    /// A coordinator serving scene files under `scene_root` (which must exist), rendering
    /// with `threads` threads (0 = all cores) while no worker is registered, with the
    /// default [`ClusterOptions`].
    pub fn new(scene_root: &Path, threads: usize) -> std::io::Result<Coordinator> {
        let scene_root = scene_root.canonicalize()?;
        Ok(Coordinator {
            table: Arc::new(JobTable::new()),
            local: Arc::new(crate::local_render::LocalRenderer::new(threads)),
            limits: Limits::default(),
            scene_root,
            cluster: Arc::new(Cluster::new(ClusterOptions::default())),
            loads: Arc::default(),
            rates: Arc::default(),
            shutdown: Arc::default(),
        })
    }

    /// Stop this coordinator (see [`crate::shutdown`] for the order): refuse new jobs,
    /// seal the job store once (what running jobs posted is written; the jobs the
    /// shutdown stops are resumed by the next coordinator, not recorded as ended), stop
    /// scene loads and package cuts, and tell every server started by [`serve_with`]
    /// for it to stop. Then wait up to `grace` for those servers to end: false when some
    /// still ran (clients still connected). Calling it again only waits again. The
    /// caller removes the jobs' packages after (see
    /// [`Coordinator::remove_packages_on_stop`]).
    pub async fn shutdown(&self, grace: Duration) -> bool {
        if self.shutdown.begin() {
            if let Some(store) = self.table.store().cloned() {
                // The writer drains what is queued, then its thread is joined: a wait
                // for the disk, off the runtime's threads.
                if let Err(e) = tokio::task::spawn_blocking(move || store.seal()).await {
                    tracing::error!("sealing the job store failed: {e}");
                }
            }
            // Cuts stop now, while the servers wind down, not after.
            self.stop_preparations();
            self.shutdown.stop_servers();
        }
        self.shutdown.servers_ended(grace).await
    }

    /// Completes once [`Coordinator::shutdown`] has sealed the store and told the
    /// servers to stop: for a server beside the coordinator's (the dashboard) to stop
    /// with them.
    pub fn stopped(&self) -> impl Future<Output = ()> + Send + 'static {
        self.shutdown.stopped()
    }

    /// Scene loads running now on blocking threads, and loads that a CancelJob stopped
    /// part-way (since the coordinator started).
    pub fn scene_loads(&self) -> (usize, u64) {
        (
            self.loads.running.load(Ordering::SeqCst),
            self.loads.stopped.load(Ordering::SeqCst),
        )
    }

    /// For a stopping coordinator, as soon as it is told to stop: every scene load and
    /// package cut in progress stops at its next look at its job's cancel flag (the
    /// jobs' states are left as they are: the process is ending).
    pub fn stop_preparations(&self) {
        self.table.stop_preparations();
    }

    /// For a stopping coordinator: stop every scene load and package cut in progress (as
    /// CancelJob does), wait up to `grace` for the cuts to end, then remove every job's
    /// package folder from the work directory, and the work directory itself if that
    /// leaves it empty. Without this a SIGTERM during the preparation of a large job
    /// left its partial package (hundreds of MB) behind, and a running job's whole one.
    pub async fn remove_packages_on_stop(&self, grace: std::time::Duration) {
        self.stop_preparations();
        let jobs = self.table.list();
        let deadline = tokio::time::Instant::now() + grace;
        while self.cluster.cuts.load(Ordering::SeqCst) > 0 {
            if tokio::time::Instant::now() >= deadline {
                tracing::warn!(
                    "package cuts still running after {grace:?}; removing their folders anyway"
                );
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        let work_dir = &self.cluster.options.work_dir;
        for e in &jobs {
            let dir = work_dir.join(&e.id);
            // A cut still writing may add a file between the listing and the rmdir.
            for _ in 0..5 {
                match std::fs::remove_dir_all(&dir) {
                    Ok(()) => break,
                    Err(err) if err.kind() == std::io::ErrorKind::NotFound => break,
                    Err(err) => {
                        tracing::debug!(dir = %dir.display(), "removing a job's package: {err}");
                        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
                    }
                }
            }
        }
        let _ = std::fs::remove_dir(work_dir.path());
    }

    /// The same coordinator with admission limits: at most `max_jobs` jobs queued or
    /// running, none estimated above `max_job_bytes`, and finished jobs' images kept per
    /// `retention`. Call before serving.
    pub fn with_admission(
        mut self,
        max_jobs: usize,
        max_job_bytes: u64,
        retention: crate::jobs::Retention,
    ) -> Coordinator {
        // Never more than a worker holds (`dray_cache::bounds::MAX_COORDINATOR_JOBS`).
        self.limits.max_jobs = max_jobs.min(dray_cache::bounds::MAX_COORDINATOR_JOBS);
        self.limits.max_job_bytes = max_job_bytes;
        // Finished images count against a memory budget too: by default the same bytes
        // one job may take.
        let retention = crate::jobs::Retention {
            max_bytes: Some(retention.max_bytes.unwrap_or(max_job_bytes)),
            ..retention
        };
        self.table = Arc::new(JobTable::new().with_retention(retention));
        self
    }

    /// The same coordinator with other cluster settings (heartbeats, work directory).
    /// Call before serving: workers and jobs on workers start afresh.
    pub fn with_cluster_options(mut self, options: ClusterOptions) -> Coordinator {
        self.cluster = Arc::new(Cluster::new(options));
        self
    }

    /// Keep every job in `store` (call after [`Coordinator::with_admission`], before
    /// serving), and take back the jobs it held: see [`Coordinator::resume`].
    pub fn with_store(self, store: Arc<JobStore>) -> Coordinator {
        self.table.keep_in(store);
        self
    }

    /// Take back the jobs a store held (`stored`, in submission order): ended jobs are
    /// listed again with their images; the others are queued again and, once a worker
    /// has registered or `grace` has passed (workers that outlived the old coordinator
    /// register again within their heartbeat timeout), run again in their order. A job
    /// that was running resumes as a new attempt that keeps its committed tiles and
    /// traces only the rest, so its image has the bits of an undisturbed run. Returns
    /// how many jobs run again. Must be called within a tokio runtime.
    pub fn resume(&self, stored: Vec<StoredJob>, grace: Duration) -> usize {
        let again = self.table.restore(stored);
        let n = again.len();
        if n == 0 {
            return 0;
        }
        let this = self.clone();
        tokio::spawn(async move {
            let deadline = tokio::time::Instant::now() + grace;
            while this.cluster.membership.is_empty() && tokio::time::Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            for (entry, job) in again {
                if entry.is_terminal() {
                    continue;
                }
                if let Err(e) = this.run_again(&entry, job).await {
                    tracing::warn!(id = %entry.id, "job could not run again after the restart: {e}");
                    entry.finish(
                        JobState::Failed,
                        format!("could not run again after the coordinator restarted: {e}"),
                        None,
                    );
                }
            }
        });
        n
    }

    /// Validate, prepare and launch a job taken back from the store, as at submission.
    async fn run_again(&self, entry: &Arc<JobRecord>, job: StoredJob) -> Result<(), String> {
        let v = validate(&job.spec, &self.limits, &self.scene_root)
            .map_err(|s| s.message().to_string())?;
        // Admission again, under this coordinator's limits (which may be lower than the
        // one that accepted the job, or the file may have grown): a job that does not fit
        // fails here, named, rather than taking the process down on every start.
        crate::admission::admit(&v, &self.limits).map_err(|s| s.message().to_string())?;
        let v2 = v.clone();
        let cancel = entry.cancel_flag().clone();
        let prepared = tokio::task::spawn_blocking(move || prepare(&v2, None, &cancel))
            .await
            .map_err(|e| format!("scene loading task died: {e}"))?
            .map_err(|s| s.message().to_string())?;
        if entry.is_terminal() {
            return Ok(());
        }
        // The package the old coordinator was cutting or running from: cut again (it
        // may be partial), into a folder made new as for any job.
        let stale = self.cluster.options.work_dir.join(&entry.id);
        if let Err(e) = std::fs::remove_dir_all(&stale)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            return Err(format!(
                "cannot remove its old package {}: {e}",
                stale.display()
            ));
        }
        let resume = Resume {
            attempt: job.attempt.map_or(0, |a| a.saturating_add(1)),
            tiles: job.tiles,
        };
        tracing::info!(
            id = %entry.id,
            attempt = resume.attempt,
            tiles_kept = resume.tiles.len(),
            "job taken back from the store"
        );
        self.launch(entry, &v, prepared, Some(resume))
            .map_err(|s| s.message().to_string())
    }

    /// A job just inserted is answered to its client only once the store has it: a
    /// store that cannot write (a full disk) fails the job, named, and SubmitJob says
    /// UNAVAILABLE, instead of accepting a job a restart would lose.
    async fn confirm_kept(&self, job: &Arc<JobRecord>) -> Result<(), Status> {
        if self.table.confirm_kept().await {
            return Ok(());
        }
        let why = self
            .table
            .store_health()
            .err()
            .unwrap_or_else(|| "the job store did not confirm the job within 10 s".into());
        job.finish(JobState::Failed, format!("not kept: {why}"), None);
        Err(store_unavailable(why))
    }

    /// How many jobs the coordinator lists.
    pub fn job_count(&self) -> usize {
        self.table.list().len()
    }

    /// The cluster state (registered workers, jobs on workers).
    pub fn cluster(&self) -> &Arc<Cluster> {
        &self.cluster
    }

    /// The canonical scene root.
    pub fn scene_root(&self) -> &Path {
        &self.scene_root
    }

    /// A job's entry (state, progress, film), for a process that hosts the coordinator
    /// itself (the embedded mode) and reads the result without a GetImage round trip.
    pub fn job_entry(&self, id: &str) -> Option<Arc<JobEntry>> {
        self.table.get(id)
    }

    /// Submit a job whose scene this process has already loaded: `scene` is the scene
    /// `spec.scene` names (untranslated; `spec.translate` still applies). The spec is
    /// validated as SubmitJob validates it, and the job runs exactly as if submitted, but
    /// the scene is not read again. Returns the job id.
    pub async fn submit_loaded(&self, spec: JobSpec, scene: Scene) -> Result<String, Status> {
        self.submit(spec, Some(scene)).await
    }

    /// SubmitJob, with the scene already loaded or not.
    ///
    /// Everything that needs no scene is checked before the job is accepted: the fields,
    /// the scene's path, the memory estimate, the job count. A scene already in memory
    /// or a package (whose manifest is all the coordinator reads) is then prepared at
    /// once, so its errors (a camera it lacks) still refuse the call. A scene file or a
    /// procedural scene may take minutes to load: the job is accepted PREPARING and its
    /// scene is loaded off the request path; an error then fails the job (GetJob and
    /// WatchJob say why), and CancelJob ends it at once without waiting for the load.
    pub(crate) async fn submit(
        &self,
        spec: JobSpec,
        loaded: Option<Scene>,
    ) -> Result<String, Status> {
        self.submit_as(spec, loaded, None).await
    }

    /// [`Coordinator::submit`] under `id` when given (a frame of a job group,
    /// `crate::job_group`).
    pub(crate) async fn submit_as(
        &self,
        spec: JobSpec,
        loaded: Option<Scene>,
        id: Option<String>,
    ) -> Result<String, Status> {
        if self.shutdown.begun() {
            return Err(Status::unavailable(
                "the coordinator is stopping: submit the job to the next one",
            ));
        }
        let active = self.table.active();
        if active >= self.limits.max_jobs {
            return Err(Status::resource_exhausted(format!(
                "the coordinator has {active} jobs queued or running, its --max-jobs: submit \
                 again when one has finished"
            )));
        }
        let v = validate(&spec, &self.limits, &self.scene_root)?;
        crate::admission::admit(&v, &self.limits)?;
        self.check_placement(&v)?;
        if loaded.is_some() || v.package.is_some() {
            let v2 = v.clone();
            // Prepared within this call: nothing can cancel it before it has an id.
            let never = Arc::new(AtomicBool::new(false));
            let prepared = tokio::task::spawn_blocking(move || prepare(&v2, loaded, &never))
                .await
                .map_err(|e| Status::internal(format!("scene loading task died: {e}")))??;
            let job = self.table.insert_as(v.spec.clone(), id);
            self.confirm_kept(&job).await?;
            self.launch(&job, &v, prepared, None)?;
            return Ok(job.id.clone());
        }
        let job = self.table.insert_as(v.spec.clone(), id);
        self.confirm_kept(&job).await?;
        job.set_state(JobState::Preparing);
        tracing::info!(id = %job.id, scene = %job.spec.scene, "job accepted; preparing its scene");
        let (this, entry) = (self.clone(), job.clone());
        tokio::spawn(async move {
            let (v2, cancel) = (v.clone(), entry.cancel_flag().clone());
            this.loads.running.fetch_add(1, Ordering::SeqCst);
            let loaded = tokio::task::spawn_blocking(move || prepare(&v2, None, &cancel)).await;
            this.loads.running.fetch_sub(1, Ordering::SeqCst);
            // A job cancelled while its scene loaded is already CANCELLED; its load
            // stopped at the next primitive (or chunk of elements), and what it made is
            // dropped here.
            if entry.is_cancelled() {
                if matches!(loaded, Ok(Err(_))) {
                    this.loads.stopped.fetch_add(1, Ordering::SeqCst);
                    tracing::info!(id = %entry.id, "scene load stopped: the job was cancelled");
                }
                return;
            }
            let outcome = match loaded {
                Err(e) => Err(format!("scene loading task died: {e}")),
                Ok(Err(status)) => Err(status.message().to_string()),
                Ok(Ok(prepared)) => this
                    .launch(&entry, &v, prepared, None)
                    .map_err(|s| s.message().to_string()),
            };
            if let Err(e) = outcome {
                tracing::info!(id = %entry.id, error = %e, "job failed while preparing");
                entry.finish(JobState::Failed, e, None);
            }
        });
        Ok(job.id.clone())
    }

    /// Refuse what cannot run where the job would run now: with no worker registered
    /// the coordinator renders in process, which has no cache hosts and cannot read a
    /// package's domains.
    fn check_placement(&self, v: &crate::validate::Validated) -> Result<(), Status> {
        if !self.cluster.membership.is_empty() {
            return Ok(());
        }
        if v.spec.ray_cache.is_some() {
            return Err(Status::failed_precondition(
                "ray_cache: ray caches run on workers' cache hosts, and no worker is \
                 registered (this coordinator would render the job itself, exactly)",
            ));
        }
        if v.spec.phm.is_some() {
            return Err(Status::failed_precondition(
                "phm: hit maps run on workers' cache hosts, and no worker is \
                 registered (this coordinator would render the job itself, exactly)",
            ));
        }
        if v.package.is_some() {
            return Err(Status::failed_precondition(format!(
                "scene: {} is a scene package, which renders on workers, and no \
                 worker is registered",
                bounded(&v.spec.scene)
            )));
        }
        Ok(())
    }

    /// Run `job`, in the table and prepared: in process while no worker is registered,
    /// else on the workers (from where `resume` left it, for a job this coordinator
    /// took back from its store), at once or, under `--max-running-jobs`, once the
    /// cluster's deal queue gives it a slot.
    fn launch(
        &self,
        job: &Arc<JobRecord>,
        v: &crate::validate::Validated,
        prepared: crate::validate::Prepared,
        resume: Option<Resume>,
    ) -> Result<(), Status> {
        // In process, or on workers with no cluster-wide limit: now.
        let Some(queue) = self
            .cluster
            .queue
            .clone()
            .filter(|_| !self.cluster.membership.is_empty())
        else {
            if job.state() == JobState::Paused {
                self.start_when_resumed(job, v, prepared, resume);
                return Ok(());
            }
            return self.start_now(job, v, prepared, resume);
        };
        // Waiting for a slot is QUEUED, and PauseJob can hold it there.
        let waiting = queue.join(job.entry());
        if job.state() == JobState::Preparing {
            job.set_state(JobState::Queued);
        }
        let (this, job, v) = (self.clone(), job.clone(), v.clone());
        let span = tracing::info_span!("cluster_queue", id = %job.id);
        tokio::spawn(
            async move {
                let Some(slot) = waiting.turn().await else {
                    return;
                };
                if job.is_cancelled() {
                    return;
                }
                // Held until the job ends, whatever way it ends: a job that cannot start
                // (its workers left, its package cannot be cut) gives its slot back at once.
                let started = this.start_now(&job, &v, prepared, resume);
                if let Err(e) = started {
                    job.finish(JobState::Failed, e.message().to_string(), None);
                }
                job.wait_ended().await;
                drop(slot);
            }
            .instrument(span),
        );
        Ok(())
    }

    /// A job taken back PAUSED by this restarted coordinator, with no slot queue to be
    /// held in (jobs on workers start at once without `--max-running-jobs`): it stays
    /// PAUSED until ResumeJob, then starts as [`Coordinator::start_now`] (cancelled
    /// meanwhile, it never starts).
    fn start_when_resumed(
        &self,
        job: &Arc<JobRecord>,
        v: &crate::validate::Validated,
        prepared: crate::validate::Prepared,
        resume: Option<Resume>,
    ) {
        let (this, job, v) = (self.clone(), job.clone(), v.clone());
        let span = tracing::info_span!("paused", id = %job.id);
        tokio::spawn(
            async move {
                tracing::info!("held PAUSED until it is resumed");
                if !this.local.queue().resumed(&job).await {
                    return;
                }
                if let Err(e) = this.start_now(&job, &v, prepared, resume) {
                    job.finish(JobState::Failed, e.message().to_string(), None);
                }
            }
            .instrument(span),
        );
    }

    /// Start `job` where it can run now: on the workers, or in process (in that
    /// queue) when none is registered (none yet, or every worker left while it waited
    /// for a cluster slot).
    fn start_now(
        &self,
        job: &Arc<JobRecord>,
        v: &crate::validate::Validated,
        prepared: crate::validate::Prepared,
        resume: Option<Resume>,
    ) -> Result<(), Status> {
        // Workers may have come or gone while the scene loaded or the job waited.
        self.check_placement(v)?;
        if self.cluster.membership.is_empty() {
            self.local.start(job, prepared);
            tracing::info!(id = %job.id, scene = %job.spec.scene, workers = 0, "job started");
            return Ok(());
        }
        self.start_on_workers(job, v, prepared, resume)
    }

    /// Plan `job` on the registered workers (at least one) and start it.
    fn start_on_workers(
        &self,
        job: &Arc<JobRecord>,
        v: &crate::validate::Validated,
        prepared: crate::validate::Prepared,
        resume: Option<Resume>,
    ) -> Result<(), Status> {
        let workers = self.cluster.membership.len();
        // On workers: the spec shows the domain count and layout the package is cut
        // with, so GetJob says what ran.
        let mut spec = v.spec.clone();
        // What the scene is cut into unless it is replicated whole.
        let cut = match &prepared.package {
            Some(pkg) => pkg.domain_count(),
            None => dispatch::choose_domains(
                (!v.domains_auto).then_some(spec.domains),
                workers,
                prepared.triangles,
                self.limits.max_domains,
            ),
        };
        let choice = dispatch::choose_schedule(&self.cluster.membership, v, &prepared, cut);
        spec.schedule = choice.schedule.name().to_string();
        match &prepared.package {
            Some(pkg) => {
                spec.domains = pkg.domain_count();
                spec.layout = pkg.layout().kind_name().to_string();
            }
            // Every worker holds the whole scene: one BVH over it, no walk between
            // domains, unless the job asked for domains.
            None if choice.schedule == Schedule::Replicated && v.domains_auto => {
                spec.domains = 1;
            }
            None => spec.domains = cut,
        }
        let layout = dispatch::layout_spec(&spec.layout, spec.domains);
        let planned = dispatch::plan(prepared, spec.clone(), layout, choice);
        job.resolve(spec);
        dispatch::spawn(self.cluster.clone(), job.clone(), planned, resume);
        tracing::info!(id = %job.id, scene = %job.spec.scene, workers, "job started");
        Ok(())
    }

    /// Jobs queued, preparing or running, and the most taken at once (`--max-jobs`).
    pub(crate) fn job_room(&self) -> (usize, usize) {
        (self.table.active(), self.limits.max_jobs)
    }

    /// A new job group's id (`crate::job_group`).
    pub(crate) fn new_group_id(&self) -> String {
        self.table.new_group_id()
    }

    /// SubmitJob of a spec with `frames`: one job per frame, in frame order. Returns the
    /// group's id and its jobs' ids.
    pub(crate) async fn submit_group(
        &self,
        spec: JobSpec,
    ) -> Result<(String, Vec<String>), Status> {
        let frames = crate::job_group::expand(&spec)?;
        let (active, max) = self.job_room();
        if active + frames.len() > max {
            return Err(Status::resource_exhausted(format!(
                "frames: {} makes {} jobs, and with the {active} queued or running that \
                 is more than the coordinator's --max-jobs {max}: submit a shorter range, \
                 or again when jobs have finished",
                bounded(&spec.frames),
                frames.len()
            )));
        }
        let group = self.new_group_id();
        let span = tracing::info_span!("job_group", group = %group, frames = frames.len());
        async move {
            let mut ids = Vec::with_capacity(frames.len());
            for (frame, one) in frames {
                match self
                    .submit_as(one, None, Some(crate::job_group::frame_id(&group, frame)))
                    .await
                {
                    Ok(id) => ids.push(id),
                    Err(e) => {
                        for id in ids {
                            let cancel = Request::new(CancelJobRequest { job_id: id });
                            let _ = self.cancel_job(cancel).await;
                        }
                        return Err(e);
                    }
                }
            }
            tracing::info!(jobs = ids.len(), "job group accepted");
            Ok((group, ids))
        }
        .instrument(span)
        .await
    }

    /// The deal queues (`priority`): jobs waiting to render in this process, and, under
    /// `--max-running-jobs`, jobs waiting for a slot on the workers.
    pub(crate) fn queues(&self) -> impl Iterator<Item = &Arc<crate::priority::DealQueue>> {
        std::iter::once(self.local.queue()).chain(self.cluster.queue.as_ref())
    }

    /// Job `id`, to read.
    pub(crate) fn job(&self, id: &str) -> Result<Arc<JobEntry>, Status> {
        self.record(id).map(|r| r.entry().clone())
    }

    /// Job `id`'s record, to change it: cancel, pause, resume, note an operator's action.
    pub(crate) fn record(&self, id: &str) -> Result<Arc<JobRecord>, Status> {
        self.table
            .record(id)
            .ok_or_else(|| Status::not_found(format!("no job {}", bounded(id))))
    }
}

fn is_terminal(s: i32) -> bool {
    matches!(
        JobState::try_from(s),
        Ok(JobState::Succeeded | JobState::Failed | JobState::Cancelled)
    )
}

#[tonic::async_trait]
impl RenderService for Coordinator {
    async fn submit_job(
        &self,
        r: Request<SubmitJobRequest>,
    ) -> Result<Response<SubmitJobResponse>, Status> {
        let spec = r
            .into_inner()
            .spec
            .ok_or_else(|| Status::invalid_argument("spec: missing"))?;
        let (group_id, job_ids) = if spec.frames.is_empty() {
            (String::new(), vec![self.submit(spec, None).await?])
        } else {
            self.submit_group(spec).await?
        };
        let id = job_ids
            .first()
            .cloned()
            .ok_or_else(|| Status::internal("a job group of no jobs"))?;
        let job = self.job(&id)?;
        Ok(Response::new(SubmitJobResponse {
            job_id: id,
            spec: job.to_job().spec,
            job_ids: if group_id.is_empty() {
                Vec::new()
            } else {
                job_ids
            },
            group_id,
        }))
    }

    type WatchJobStream = ReceiverStream<Result<JobProgress, Status>>;

    async fn watch_job(
        &self,
        r: Request<WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let r = r.into_inner();
        let job = self.job(&r.job_id)?;
        let interval = r
            .min_interval
            .and_then(|d| Duration::try_from(d).ok())
            .filter(|d| !d.is_zero())
            .unwrap_or(DEFAULT_WATCH_INTERVAL)
            .clamp(Duration::from_millis(10), Duration::from_secs(60));
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            let mut last: Option<(i32, u32, u64)> = None;
            loop {
                let mut p = job.progress();
                p.stats = Some(job.to_job().stats.unwrap_or_default());
                let key = (p.state, p.tiles_done, p.rays_traced);
                let done = is_terminal(p.state);
                if last != Some(key) {
                    if tx.send(Ok(p)).await.is_err() {
                        return;
                    }
                    last = Some(key);
                }
                if done {
                    return;
                }
                // The interval paces progress messages; the end is sent at once.
                tokio::select! {
                    _ = tokio::time::sleep(interval) => {}
                    _ = job.wait_ended() => {}
                    _ = tx.closed() => return,
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn get_job(&self, r: Request<GetJobRequest>) -> Result<Response<GetJobResponse>, Status> {
        let job = self.job(&r.get_ref().job_id)?;
        Ok(Response::new(GetJobResponse {
            job: Some(job.to_job()),
        }))
    }

    async fn list_jobs(
        &self,
        r: Request<ListJobsRequest>,
    ) -> Result<Response<ListJobsResponse>, Status> {
        let r = r.into_inner();
        let size = match r.page_size as usize {
            0 => DEFAULT_PAGE_SIZE,
            n => n.min(MAX_PAGE_SIZE),
        };
        let start = if r.page_token.is_empty() {
            0
        } else {
            r.page_token.parse::<usize>().map_err(|_| {
                Status::invalid_argument(format!(
                    "page_token: {} is not valid",
                    bounded(&r.page_token)
                ))
            })?
        };
        let mut all = self.table.list();
        if !r.group_id.is_empty() {
            all.retain(|j| j.group.as_ref().is_some_and(|g| g.group_id == r.group_id));
        }
        let end = (start + size).min(all.len());
        let jobs = all
            .get(start..end)
            .unwrap_or_default()
            .iter()
            .map(|j| j.to_job())
            .collect();
        Ok(Response::new(ListJobsResponse {
            jobs,
            next_page_token: if end < all.len() {
                end.to_string()
            } else {
                String::new()
            },
        }))
    }

    async fn cancel_job(
        &self,
        r: Request<CancelJobRequest>,
    ) -> Result<Response<CancelJobResponse>, Status> {
        let job = self.record(&r.get_ref().job_id)?;
        // Mark it first: a dispatch racing with this sees the state and does not start.
        job.cancel();
        self.cluster.jobs.cancel(&job.id).await;
        Ok(Response::new(CancelJobResponse {
            job: Some(job.to_job()),
        }))
    }

    async fn get_image(
        &self,
        r: Request<GetImageRequest>,
    ) -> Result<Response<GetImageResponse>, Status> {
        let r = r.into_inner();
        let (format, display) = image_request(r.format, r.exposure, &r.tonemap)?;
        self.table.sweep();
        let job = self.job(&r.job_id)?;
        let image = match job_image(&job)? {
            Some(image) => image,
            None => {
                return Err(Status::failed_precondition(format!(
                    "job {:?} is {} with no complete pass yet; its image is available once \
                     its first pass is complete (JobProgress.passes_done)",
                    job.id,
                    job.state().as_str_name()
                )));
            }
        };
        Ok(Response::new(
            encode_image(&job, image, format, display).await?,
        ))
    }

    type WatchImageStream = ReceiverStream<Result<GetImageResponse, Status>>;

    async fn watch_image(
        &self,
        r: Request<WatchImageRequest>,
    ) -> Result<Response<Self::WatchImageStream>, Status> {
        let r = r.into_inner();
        let (format, display) = image_request(r.format, r.exposure, &r.tonemap)?;
        let job = self.job(&r.job_id)?;
        job_image(&job)?;
        let interval = r
            .min_interval
            .and_then(|d| Duration::try_from(d).ok())
            .filter(|d| !d.is_zero())
            .unwrap_or(DEFAULT_IMAGE_INTERVAL)
            .clamp(Duration::from_millis(50), Duration::from_secs(60));
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        let mut passes = job.passes.subscribe();
        tokio::spawn(async move {
            // (passes done, final) of the last image sent.
            let mut sent: Option<(u32, bool)> = None;
            loop {
                passes.borrow_and_update();
                let image = match job_image(&job) {
                    Ok(image) => image,
                    Err(e) => {
                        let _ = tx.send(Err(e)).await;
                        return;
                    }
                };
                if let Some(image) = image {
                    let key = (image.passes_done, image.final_image);
                    if sent != Some(key) {
                        let msg = encode_image(&job, image, format, display).await;
                        let end = msg.is_err() || key.1;
                        if tx.send(msg).await.is_err() || end {
                            return;
                        }
                        sent = Some(key);
                    }
                }
                if job.is_terminal() && job.state() != JobState::Succeeded {
                    // Failed or cancelled: no more images (job_image says why next).
                    continue;
                }
                tokio::select! {
                    _ = passes.changed() => {}
                    _ = job.wait_ended() => {}
                    _ = tx.closed() => return,
                }
                // At most one image per interval (the final one waits at most that).
                tokio::select! {
                    _ = tokio::time::sleep(interval) => {}
                    _ = tx.closed() => return,
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn list_workers(
        &self,
        r: Request<ListWorkersRequest>,
    ) -> Result<Response<ListWorkersResponse>, Status> {
        let r = r.into_inner();
        let page = crate::worker_list::PageRequest::parse(r.page_size, &r.page_token)
            .map_err(Status::invalid_argument)?;
        let cluster = &self.cluster;
        let views = cluster.jobs.views(VIEW_WAIT).await;
        let now = std::time::Instant::now();
        let rates = self.rates.rates(&views, now);
        let (workers, more) = cluster
            .membership
            .workers_after(page.after.as_deref(), page.size);
        let mut out = crate::worker_list::list(
            &workers,
            views,
            &rates,
            cluster.membership.heartbeat,
            now,
            page.first() && !r.omit_jobs,
        );
        if more && let Some(last) = workers.last() {
            out.next_page_token = last.id.clone();
        }
        Ok(Response::new(out))
    }

    async fn retry_job(
        &self,
        r: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Ok(Response::new(
            self.retry_or_requeue(r.into_inner(), false).await?,
        ))
    }

    async fn requeue_job(
        &self,
        r: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Ok(Response::new(
            self.retry_or_requeue(r.into_inner(), true).await?,
        ))
    }

    async fn pause_job(
        &self,
        r: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Ok(Response::new(self.hold_job(&r.get_ref().job_id, true)?))
    }

    async fn resume_job(
        &self,
        r: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Ok(Response::new(self.hold_job(&r.get_ref().job_id, false)?))
    }
}

/// SubmitJob's answer while the job store cannot write.
fn store_unavailable(why: String) -> Status {
    Status::unavailable(format!(
        "{why}; new jobs are refused until the job store can write again (free space in \
         the --state-dir), since they would not survive a restart"
    ))
}

/// The encoding GetImage and WatchImage are asked for, and the display transform of a
/// PNG (`exposure` absent: automatic; `tonemap` empty: the default), checked.
fn image_request(
    format: i32,
    exposure: Option<f32>,
    tonemap: &str,
) -> Result<(ImageFormat, Display), Status> {
    let display = requested_display(exposure, tonemap).map_err(Status::invalid_argument)?;
    match ImageFormat::try_from(format) {
        Ok(ImageFormat::Unspecified | ImageFormat::Png) => Ok((ImageFormat::Png, display)),
        Ok(ImageFormat::Exr) => Ok((ImageFormat::Exr, display)),
        Err(_) => Err(Status::invalid_argument(format!(
            "format: unknown image format {format}"
        ))),
    }
}

/// The image a job can show now, before encoding.
struct JobImage {
    /// The film, or the job store's file of a job that finished before this
    /// coordinator started.
    film: Result<Arc<dray_core::film::Film>, PathBuf>,
    samples: u32,
    passes_done: u32,
    final_image: bool,
}

/// The final image of a SUCCEEDED job, or the last pass's image of a running one; None
/// while no pass is complete. An error for a job whose image is gone (dropped by the
/// retention policy, or the job failed or was cancelled).
fn job_image(job: &JobEntry) -> Result<Option<JobImage>, Status> {
    if let Some(why) = job.dropped() {
        return Err(Status::not_found(format!(
            "job {:?} finished, but its image was dropped: {why}",
            job.id
        )));
    }
    let total = job.passes.total();
    let final_film = match (job.film(), job.image_file()) {
        (Some(film), _) => Some(Ok(film)),
        (None, Some(file)) => Some(Err(file)),
        (None, None) => None,
    };
    if let Some(film) = final_film {
        return Ok(Some(JobImage {
            film,
            samples: job.spec.spp,
            passes_done: total,
            final_image: true,
        }));
    }
    let state = job.state();
    if is_terminal(state as i32) {
        return Err(Status::failed_precondition(format!(
            "job {:?} is {}; it has no image",
            job.id,
            state.as_str_name()
        )));
    }
    Ok(job.passes.latest().map(|p| JobImage {
        film: Ok(p.film),
        samples: p.samples,
        passes_done: p.passes_done,
        final_image: false,
    }))
}

/// `image` encoded as GetImage answers it (on a blocking thread: a large PNG takes a
/// while).
async fn encode_image(
    job: &JobEntry,
    image: JobImage,
    format: ImageFormat,
    display: Display,
) -> Result<GetImageResponse, Status> {
    let samples = image.samples;
    let film = image.film;
    let key = crate::image_memo::ImageKey {
        passes_done: image.passes_done,
        final_image: image.final_image,
        format: format as i32,
        display: match format {
            ImageFormat::Exr => String::new(),
            _ => format!("{display:?}"),
        },
    };
    // One encode per key, shared by every caller (see `image_memo`).
    let data = job
        .images
        .get_or_encode(key, || async move {
            tokio::task::spawn_blocking(move || {
                let film = match film {
                    Ok(film) => film,
                    Err(file) => Arc::new(
                        crate::store::image_file::read(&file)
                            .map_err(|e| format!("cannot read the stored image: {e}"))?,
                    ),
                };
                match format {
                    ImageFormat::Exr => encode_exr(&film, samples),
                    _ => encode_png(&film, samples, display),
                }
                .map(prost::bytes::Bytes::from)
            })
            .await
            .map_err(|e| Status::internal(format!("image encoding task died: {e}")))?
            .map_err(Status::internal)
        })
        .await?;
    Ok(GetImageResponse {
        data,
        format: format as i32,
        content_type: match format {
            ImageFormat::Exr => "image/x-exr",
            _ => "image/png",
        }
        .into(),
        width: job.spec.width,
        height: job.spec.height,
        samples,
        r#final: image.final_image,
        passes_done: image.passes_done,
        passes_total: job.passes.total(),
    })
}

/// Aborts a task when dropped, so the heartbeat reaper stops with the
/// server however `serve` ends (returned, failed, or its future dropped).
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Serve `coordinator` on `listener` (RenderService, ClusterService and PackageService) with gRPC
/// reflection and health until `shutdown` completes, open and in plaintext: see
/// [`serve_with`].
pub async fn serve(
    listener: TcpListener,
    coordinator: Coordinator,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), dray_net::server::ServeError> {
    serve_with(
        &dray_net::ServerOptions::default(),
        listener,
        coordinator,
        shutdown,
    )
    .await
}

/// [`serve`] with `options`: the API and cluster tokens calls must present, TLS, load
/// shedding (dray-net's one server builder). GetImage replies may exceed 4 MiB, so the
/// encoding limit is raised. On shutdown the workers' assignment streams are ended, so
/// a graceful shutdown does not wait for them forever.
///
/// The server stops when `shutdown` completes or when [`Coordinator::shutdown`] is
/// called, which waits for it to end.
pub async fn serve_with(
    options: &dray_net::ServerOptions,
    listener: TcpListener,
    coordinator: Coordinator,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), dray_net::server::ServeError> {
    let stop = coordinator.shutdown.clone();
    let _serving = stop.serving();
    let stopped = stop.stopped();
    let cluster = coordinator.cluster.clone();
    let work_dir = cluster.options.work_dir.clone();
    let _reaper = AbortOnDrop(tokio::spawn(cluster.clone().reaper()));
    let shutdown = async move {
        tokio::select! {
            () = shutdown => {}
            () = stopped => {}
        }
        cluster.membership.close_all();
    };
    let cluster_api = ClusterServiceServer::new(ClusterApi {
        cluster: coordinator.cluster.clone(),
    });
    // Workers without the coordinator's disk fetch the jobs' packages from here.
    let packages = PackageServiceServer::new(PackageApi::new(coordinator.cluster.jobs.clone()));
    let render = RenderServiceServer::new(coordinator).max_encoding_message_size(usize::MAX);
    let routes = tonic::service::Routes::new(render)
        .add_service(cluster_api)
        .add_service(packages);
    let served = dray_net::server::serve(
        options,
        listener,
        routes,
        &[
            dray_proto::RENDER_SERVICE,
            dray_proto::CLUSTER_SERVICE,
            dray_proto::PACKAGE_SERVICE,
        ],
        shutdown,
    )
    .await;
    // Job packages are removed as jobs end; the work directory itself goes if empty.
    let _ = std::fs::remove_dir(work_dir.path());
    served
}
