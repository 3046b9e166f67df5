//! Dispatch: turn an accepted job into work for the registered workers.
//!
//! For a job, the coordinator makes (or reuses) a scene package, sets up the job's
//! [schedule](crate::scheduler) over the registered workers, and queues on each worker's
//! WatchAssignments stream, in this order:
//!
//! 1. one `JobSetup`: the spec with every default filled in (`schedule` resolved), the
//!    environment and the effects after analysis and overrides, the package path and
//!    checksum, the domain count, `tile_size` ([`TILE_SIZE`]), `tile_credit`
//!    ([`TILE_CREDIT`]), `attempt` 0, the resolved `schedule` and the routing table
//!    (version 1, attempt 0): round robin (domain `d` to `workers[d % n]`) for the
//!    domain and dynamic schedules, `local` with no routes for image-plane;
//! 2. one or more `TileAssignment`s with the tiles dealt to that worker: the image is cut
//!    row-major into `tile_size` squares (edge tiles smaller, tile `i` has index
//!    `(y0 / tile_size) * tiles_x + x0 / tile_size`: [`TileGrid`]), each with
//!    `credit = tile_credit` and `attempt = 0`. Image-plane deals contiguous blocks
//!    (worker `i` of `n` gets tiles `[i*T/n, (i+1)*T/n)`); domain and dynamic deal round
//!    robin (tile `i` to `workers[i % n]`);
//! 3. while the job runs: `routing` tables with higher versions when the dynamic
//!    scheduler moves or replicates domains, or when a worker joins a dynamic job;
//! 4. when a worker of the job is lost: `cancel` of the old attempt, then a new
//!    `JobSetup` (attempt + 1, a new table over the survivors) and the tiles that were
//!    not complete, dealt by the same rule over the survivors (see [`crate::job`]);
//! 5. at the end, exactly one `finish` (every tile's credit came back) or `cancel`
//!    (CancelJob, a worker's failure report, a credit error, or the last worker lost)
//!    `JobRelease` of the current attempt.
//!
//! A worker that registers while a dynamic job runs gets that job's `JobSetup` (current
//! attempt and table, listing it) and no tiles; rounds then give it domains.
//!
//! A job with `ray_cache` has its walls placed on cache hosts and opened (OpenWalls)
//! before step 1, and every table of the attempt lists them (`cache_hosts`,
//! `wall_hosts`; see [`crate::caches`]). With no cache host at all (no `dray cache`
//! registered, and no worker announced one) the job fails before it starts; with hosts
//! that all fail to open, it runs without caches and says so in its statistics.
//!
//! The JobSetup's spec is what the worker must render, resolved so every worker reads the
//! same thing: `camera` is always set, to the index (as a decimal string) of the camera in
//! the package's camera list; `translate` is cleared because the package was written from
//! the already translated scene; `domains` and `layout` say how the package was cut;
//! `view`, when the job has one, is resolved (`crate::view::resolve`: no orbit, no
//! f-number, points already translated) and is the camera workers build, whatever
//! `camera` says.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use dray_core::credit::Credit;
use dray_core::scene::Scene;
use dray_core::tiles::TileGrid;
use dray_proto::v1::{EnvMapFile, JobSetup, JobSpec, JobState, Rgb, Tile};
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::memory::MemoryPackages;
use dray_scene::partition::{LayoutSpec, write_scene_package_with};
use tracing::Instrument;

use crate::caches::geometry::WallGeometry;
use crate::caches::lifecycle;
use crate::cluster::Cluster;
use crate::job::JobPlan;
use crate::job::JobRecord;
use crate::job::caches::{self as cache_job, JobCaches, OpenAttempt};
use crate::job_group::GroupLayouts;
use crate::lighting::LoadedEnvMap;
use crate::membership::Membership;
use crate::owned_package::{OwnedPackage, remove_package};
use crate::scheduler::Schedule;
use crate::scheduler::auto::{self, Choice, JobNeeds, SceneSize};
use crate::scheduler::state::{JobSchedule, JobWorker};
use crate::store::Resume;
use crate::validate::{Prepared, Validated};

/// Tile edge in pixels: the same tiles as `dray render`, so progress reads the same.
pub use dray_core::tiles::TILE_SIZE;

/// Credit each tile starts with, [`Credit::TILE`], as `Tile.credit` and
/// `JobSetup.tile_credit` carry it (docs/architecture.md "Credit").
pub const TILE_CREDIT: u64 = Credit::TILE.to_wire();

pub use crate::job::TILES_PER_MESSAGE;

/// Domains per worker when the job does not say: the dynamic-scheduling paper found
/// several times more domains than processes best, and it gives the dynamic scheduler
/// something to move.
pub const DOMAINS_PER_WORKER: u32 = 4;

/// Fewest triangles worth a domain of their own when the coordinator chooses the count:
/// below this a domain's BVH and the hops between domains cost more than they save.
pub const MIN_TRIANGLES_PER_DOMAIN: u64 = 64;

/// Errors preparing a job for workers.
#[derive(Debug, thiserror::Error)]
pub enum DispatchError {
    /// The job's package folder could not be made in the work directory (it exists
    /// already, or the work directory is missing).
    #[error("cannot create the job's package folder {dir}: {source}")]
    WorkDir {
        /// The directory.
        dir: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Partitioning or writing the package failed.
    #[error("cannot write the scene package to {dir}: {message}")]
    Package {
        /// The package directory.
        dir: PathBuf,
        /// Why.
        message: String,
    },
    /// The package manifest could not be read back for its checksum.
    #[error("cannot read the package manifest {path}: {source}")]
    Manifest {
        /// The manifest file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Every worker left before the job could start.
    #[error("no worker is registered any more")]
    NoWorkers,
    /// The job asks for ray caches and nothing can host them.
    #[error(
        "ray caches need a cache host: workers announced none and no `dray cache` \
         registered (start workers without --no-cache-host, or a `dray cache`, or submit \
         the job without ray_cache)"
    )]
    NoCacheHost,
    /// A blocking task died.
    #[error("the package task died: {0}")]
    Task(String),
}

/// The number of domains for a job on `workers` workers: `requested` when the job says,
/// otherwise [`DOMAINS_PER_WORKER`] per worker, at most one per
/// [`MIN_TRIANGLES_PER_DOMAIN`] triangles and at most `max`, and at least 1.
pub fn choose_domains(requested: Option<u32>, workers: usize, triangles: u64, max: u32) -> u32 {
    if let Some(n) = requested {
        return n;
    }
    let wanted = (workers as u64).saturating_mul(u64::from(DOMAINS_PER_WORKER));
    let by_size = triangles / MIN_TRIANGLES_PER_DOMAIN;
    wanted.min(by_size).min(u64::from(max)).max(1) as u32
}

/// The schedule job `v` runs with on the registered workers: what it forced, or what
/// `auto` makes of the scene's resident size (`prepared`'s scene, or its package's
/// domains) against every worker's budget ([`auto::choose`]); `domains` is what the scene
/// is cut into if it is not replicated (the room for copies is counted in them).
pub fn choose_schedule(
    membership: &Membership,
    v: &Validated,
    prepared: &Prepared,
    domains: u32,
) -> Choice {
    let size = match &prepared.package {
        Some(pkg) => SceneSize::of_manifest(pkg.manifest()),
        None => SceneSize::of_scene(&prepared.scene),
    };
    let budgets: Vec<(String, u64)> = membership
        .workers()
        .iter()
        .map(|w| (w.id.clone(), w.memory_budget_bytes))
        .collect();
    let needs = JobNeeds {
        walls: v.spec.ray_cache.is_some() || v.spec.phm.is_some(),
        domains,
    };
    let choice = auto::choose(v.schedule, size, &budgets, needs);
    tracing::info!(
        schedule = choice.schedule.name(),
        replicate = choice.schedule.replicates(),
        scene_bytes = size.bytes,
        reason = %choice.reason,
        "schedule chosen"
    );
    choice
}

/// The package a job renders from.
pub enum PackageSource {
    /// Partition this (loaded, translated) scene into a fresh package.
    Write {
        /// The scene (boxed: it is large and moved between tasks).
        scene: Box<Scene>,
        /// How to cut it.
        layout: LayoutSpec,
    },
    /// A package that already exists (the job's scene was one).
    Existing(PathBuf),
}

/// The layout spec for `layout` ("grid" or "kd") and `domains`.
pub fn layout_spec(layout: &str, domains: u32) -> LayoutSpec {
    match layout {
        "grid" => LayoutSpec::GridCount(domains),
        _ => LayoutSpec::Kd(domains),
    }
}

/// The package as the job's workers will see it.
struct PackageInfo {
    /// `JobSetup.package_path`: a directory, or an in-memory package's name.
    path: String,
    checksum: String,
    domains: u32,
    /// Set when the package was made for this job (and goes with it).
    owned: Option<OwnedPackage>,
    /// The boxes of its domains, when the job has ray caches.
    geometry: Option<WallGeometry>,
}

/// Write (or check) the package: into `memory` when given, else into `dir`; with
/// `walls`, also take the boxes its cache hosts need. Blocking.
fn make_package(
    src: PackageSource,
    dir: &Path,
    memory: Option<&Arc<MemoryPackages>>,
    walls: bool,
    group: Option<(Arc<GroupLayouts>, String)>,
) -> Result<PackageInfo, DispatchError> {
    let src = match (src, memory) {
        (PackageSource::Write { scene, layout }, Some(store)) => {
            return memory_package(*scene, &layout, store, dir, walls);
        }
        (src, _) => src,
    };
    let (dir, owned) = match src {
        PackageSource::Write { scene, layout } => {
            // The job's folder is new (mkdir refuses an existing path, so nothing planted
            // there beforehand is used); the work directory must exist already (a private
            // one this process made, or the user's), and is not made here, where a
            // missing private directory could be remade by another user.
            std::fs::create_dir(dir).map_err(|source| DispatchError::WorkDir {
                dir: dir.to_path_buf(),
                source,
            })?;
            let package_err = |e: dray_scene::SceneError| DispatchError::Package {
                dir: dir.to_path_buf(),
                message: e.to_string(),
            };
            let given = match &group {
                Some((layouts, id)) => layouts
                    .layout_for(id, &scene, &layout)
                    .map_err(package_err)?,
                None => None,
            };
            write_scene_package_with(dir, &scene, &layout, given).map_err(package_err)?;
            (dir.to_path_buf(), true)
        }
        PackageSource::Existing(d) => (d, false),
    };
    let pkg = dray_scene::partition::open_package(&dir).map_err(|e| DispatchError::Package {
        dir: dir.clone(),
        message: e.to_string(),
    })?;
    let path = dir.join(MANIFEST_FILE);
    let bytes = std::fs::read(&path).map_err(|source| DispatchError::Manifest {
        path: path.clone(),
        source,
    })?;
    let dir = std::path::absolute(&dir).unwrap_or(dir);
    Ok(PackageInfo {
        path: dir.to_string_lossy().into_owned(),
        checksum: package_checksum(&bytes),
        domains: pkg.domain_count(),
        owned: owned.then_some(OwnedPackage::Dir(dir)),
        geometry: walls.then(|| WallGeometry::of(pkg.layout())),
    })
}

/// Cut `scene` into the in-memory `store` (the workers share this process). A store
/// that keeps its last package (`MemoryPackages::keeping_last`, `dray sweep`) hands the
/// kept one back when `scene` and `layout` equal what it was cut from, so the workers
/// find its domains resident; the kept package then belongs to the store, not the job.
fn memory_package(
    scene: Scene,
    layout: &LayoutSpec,
    store: &Arc<MemoryPackages>,
    dir: &Path,
    walls: bool,
) -> Result<PackageInfo, DispatchError> {
    if let Some(name) = store.kept(&scene, layout)
        && let Some(pkg) = store.get(&name)
    {
        tracing::info!(package = %name, "the scene and layout of the kept package: reused");
        return Ok(PackageInfo {
            path: name,
            checksum: String::new(),
            domains: pkg.domain_count(),
            owned: None,
            geometry: walls.then(|| WallGeometry::of(pkg.layout())),
        });
    }
    let copy = store.keeps().then(|| scene.clone());
    // The next frame of an animation keeps the domains no moving mesh touches.
    let pkg = store
        .cut(scene, layout)
        .map_err(|e| DispatchError::Package {
            dir: dir.to_path_buf(),
            message: e.to_string(),
        })?;
    let domains = pkg.domain_count();
    let geometry = walls.then(|| WallGeometry::of(pkg.layout()));
    let name = store.insert(pkg);
    let owned = match copy {
        Some(scene) => {
            store.keep(&name, scene, *layout);
            None
        }
        None => Some(OwnedPackage::Memory {
            store: store.clone(),
            name: name.clone(),
        }),
    };
    Ok(PackageInfo {
        path: name,
        // The name is unique in the process that holds it; there are no bytes to pin.
        checksum: String::new(),
        domains,
        owned,
        geometry,
    })
}

/// `JobSetup.package_checksum`: XXH3-64 of the bytes of the package's `manifest.json`, as
/// 16 lowercase hex digits. The manifest records every domain file's checksum, so this
/// one value pins the whole package.
pub fn package_checksum(manifest_bytes: &[u8]) -> String {
    to_hex(checksum(manifest_bytes))
}

/// The tiles of a `width` x `height` image ([`TileGrid::image`]), each with
/// [`TILE_CREDIT`].
pub fn image_tiles(width: u32, height: u32) -> Vec<Tile> {
    grid_tiles(TileGrid::image(width, height), 0, false)
}

/// The tiles of a ray-cache coarse pass over an `n` x `n` image, numbered from `first`
/// (the image's tile count) in the same row-major order and size as the image's tiles,
/// as the workers number them (cluster.proto `Tile.coarse`).
pub fn coarse_tiles(n: u32, first: u32) -> Vec<Tile> {
    grid_tiles(TileGrid::image(n, n), first, true)
}

/// `grid`'s tiles as dealt, numbered from `first`, each with [`TILE_CREDIT`].
fn grid_tiles(grid: TileGrid, first: u32, coarse: bool) -> Vec<Tile> {
    grid.iter()
        .zip(first..)
        .map(|(t, index)| Tile {
            index,
            x0: t.x0,
            y0: t.y0,
            width: t.w,
            height: t.h,
            credit: TILE_CREDIT,
            attempt: 0,
            coarse,
            first_sample: 0,
            samples: 0,
        })
        .collect()
}

/// What dispatch keeps of [`Prepared`] (the scene itself goes into the package).
pub struct PreparedSummary {
    /// Environment radiance after defaults.
    pub environment: glam::Vec3,
    /// Effect names after analysis and overrides.
    pub effects: Vec<String>,
    /// Triangles in the scene.
    pub triangles: u64,
    /// The environment map, when the job has one: its file for the workers, and the
    /// decoded map for workers in this process.
    pub env_map: Option<LoadedEnvMap>,
}

/// Plan a prepared job for workers: resolve `spec` (camera index, no translate) and keep
/// the scene for the package. A scene without cameras gets the framing camera `prepare`
/// chose, so the package's camera list holds exactly the camera the job renders with.
/// A scene package is used as it is: a package without cameras leaves `spec.camera`
/// unset, meaning the camera framing the manifest's bounds.
pub fn plan(mut p: Prepared, mut spec: JobSpec, layout: LayoutSpec, choice: Choice) -> Planned {
    let summary = PreparedSummary {
        environment: p.settings.environment,
        effects: p
            .settings
            .effects
            .names()
            .into_iter()
            .map(String::from)
            .collect(),
        triangles: p.triangles,
        env_map: p.env_map.take(),
    };
    spec.translate = None;
    // A view travels resolved in the spec, and workers build the camera from it.
    spec.view = p.view.take();
    let index = camera_index(&p.scene, spec.camera.as_deref());
    let package = match p.package {
        Some(pkg) => {
            spec.camera = index.map(|i| i.to_string());
            PackageSource::Existing(pkg.dir().to_path_buf())
        }
        None => {
            // Without a view, the package's camera list holds the camera the job
            // renders with (the framing camera added when the scene has none).
            spec.camera = match index {
                Some(i) => Some(i.to_string()),
                None if spec.view.is_some() => None,
                None => {
                    p.scene.cameras.push(p.camera.clone());
                    Some((p.scene.cameras.len() - 1).to_string())
                }
            };
            PackageSource::Write {
                scene: Box::new(p.scene),
                layout,
            }
        }
    };
    Planned {
        setup_spec: spec,
        prepared: summary,
        package,
        schedule: choice.schedule,
        placement: choice.reason,
        scene: choice.scene,
    }
}

/// A job ready for dispatch, before it has an entry in the job table.
pub struct Planned {
    /// The spec workers receive in JobSetup (resolved camera, no translate).
    pub setup_spec: JobSpec,
    /// Settings and statistics of the loaded scene.
    pub prepared: PreparedSummary,
    /// Where the package comes from.
    pub package: PackageSource,
    /// How domains and rays are placed on the workers.
    pub schedule: Schedule,
    /// Why (`JobStats.placement`).
    pub placement: String,
    /// The scene's size as the schedule was chosen from (a replicated job's joiners
    /// must hold it).
    pub scene: SceneSize,
}

/// The index of the camera `which` names (an index first, then a name, as
/// `validate::choose_camera` resolves it), or of the first camera; None when the scene
/// has no cameras (the framing camera is used).
fn camera_index(scene: &Scene, which: Option<&str>) -> Option<usize> {
    match which {
        Some(w) => w
            .parse::<usize>()
            .ok()
            .filter(|&i| i < scene.cameras.len())
            .or_else(|| scene.cameras.iter().position(|c| c.name == w)),
        None => (!scene.cameras.is_empty()).then_some(0),
    }
}

/// One package cut in progress, counted in [`Cluster::cuts`] while it lives.
struct Cutting<'a>(&'a Cluster);

impl<'a> Cutting<'a> {
    fn start(cluster: &'a Cluster) -> Cutting<'a> {
        cluster
            .cuts
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        Cutting(cluster)
    }
}

impl Drop for Cutting<'_> {
    fn drop(&mut self) {
        self.0
            .cuts
            .fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
    }
}

/// Run the job whose record (its one writer, handed on to its actor) is `record` on the
/// cluster's workers: make the package, then queue the setup and
/// tiles on the workers' streams. Returns at once; the work runs on a task.
pub fn spawn(
    cluster: Arc<Cluster>,
    record: Arc<JobRecord>,
    planned: Planned,
    resume: Option<Resume>,
) {
    let span = tracing::info_span!("job", id = %record.id, scene = %record.spec.scene);
    tokio::spawn(
        async move {
            match run(&cluster, &record, planned, resume).await {
                Ok(()) => {}
                // CANCELLED already; the package was stopped part-way and removed.
                Err(e) if record.is_cancelled() => {
                    tracing::info!("job cancelled before it started: {e}");
                }
                Err(e) => {
                    tracing::warn!("job failed before it started: {e}");
                    record.finish(JobState::Failed, e.to_string(), None);
                }
            }
        }
        .instrument(span),
    );
}

/// Run a planned job: cut (or check) its package, set its schedule up over the
/// registered workers (and open its first attempt's cache walls when it has any), then
/// hand it to its actor. A job cancelled while its package was cut ends here, its
/// package removed; an error is the job's failure before it started.
async fn run(
    cluster: &Arc<Cluster>,
    record: &Arc<JobRecord>,
    planned: Planned,
    resume: Option<Resume>,
) -> Result<(), DispatchError> {
    let Planned {
        setup_spec,
        prepared,
        package,
        schedule,
        placement,
        scene,
    } = planned;
    let walled = setup_spec.ray_cache.is_some() || setup_spec.phm.is_some();
    let mut info = cut_package(cluster, record, package, walled).await?;
    let owned = info.owned.clone();
    if record.is_terminal() {
        // Cancelled while the package was being written.
        remove_package(owned.as_ref());
        return Ok(());
    }
    let workers = job_workers(&cluster.membership);
    if workers.is_empty() {
        remove_package(owned.as_ref());
        return Err(DispatchError::NoWorkers);
    }
    let mut sched = JobSchedule::new(&record.id, schedule, info.domains, &workers);
    if let Some(r) = &resume {
        sched.set_first_attempt(r.attempt);
    }
    let caches = match info.geometry.take() {
        Some(geometry) if walled => {
            match open_caches(cluster, record, &mut sched, &setup_spec, geometry).await {
                Ok(c) => Some(c),
                Err(e) => {
                    remove_package(owned.as_ref());
                    return Err(e);
                }
            }
        }
        _ => None,
    };
    let (env_map, owned) = env_map_for_workers(cluster, prepared.env_map.clone(), owned);
    let tiles = job_tiles(record, &setup_spec);
    let mut setup = job_setup(record, setup_spec, &prepared, &info, schedule, env_map);
    setup.passes_ahead = crate::job::ahead::passes_ahead(
        record.passes.total(),
        u64::from(record.spec.width) * u64::from(record.spec.height),
        tiles.len(),
        workers.iter().any(|w| w.budget > 0) || schedule == Schedule::Replicated,
        walled,
        record.spec.noise_threshold.is_some(),
    );
    record.update_stats(|s| {
        s.triangles = prepared.triangles;
        s.domains = info.domains;
        s.workers = workers.len() as u32;
        s.effects = prepared.effects.clone();
        s.schedule = schedule.name().to_string();
        s.placement = placement;
    });
    let plan = JobPlan {
        record: record.clone(),
        setup,
        sched,
        tiles,
        owned_package: owned,
        caches,
        resume,
        scene,
    };
    start_job(cluster, plan, workers.len()).await;
    Ok(())
}

/// The job's package, cut on a blocking task (or checked, for an existing one) while
/// the job reads PREPARING and counts in [`Cluster::cuts`]. CancelJob stops the cut
/// part-way; on any failure the folder the job made is removed again.
async fn cut_package(
    cluster: &Arc<Cluster>,
    record: &Arc<JobRecord>,
    package: PackageSource,
    walls: bool,
) -> Result<PackageInfo, DispatchError> {
    record.set_state(JobState::Preparing);
    // Counted until the cut has ended and, on failure, its folder is gone.
    let _cutting = Cutting::start(cluster);
    let dir = cluster.options.work_dir.join(&record.id);
    let dir2 = dir.clone();
    let memory = cluster.options.memory_packages.clone();
    // A frame of a job group is cut with its group's layout.
    let group = record
        .group
        .as_ref()
        .map(|g| (cluster.group_layouts.clone(), g.group_id.clone()));
    // CancelJob stops the cut part-way (its files are removed below).
    let cancel = record.cancel_flag().clone();
    let info = tokio::task::spawn_blocking(move || {
        dray_scene::cancel::with_cancel(&cancel, || {
            make_package(package, &dir2, memory.as_ref(), walls, group)
        })
    })
    .await
    .map_err(|e| DispatchError::Task(e.to_string()));
    match info {
        Ok(Ok(i)) => Ok(i),
        Ok(Err(e)) | Err(e) => {
            // A folder the job could not make is not the job's to remove.
            if !matches!(e, DispatchError::WorkDir { .. }) {
                remove_package(Some(&OwnedPackage::Dir(dir)));
            }
            Err(e)
        }
    }
}

/// The registered workers as the job's schedule starts over them, in membership order.
fn job_workers(membership: &Membership) -> Vec<JobWorker> {
    membership
        .workers()
        .iter()
        .map(|w| JobWorker {
            endpoint: w.endpoint(),
            budget: w.memory_budget_bytes,
        })
        .collect()
}

/// The ray caches and hit maps of a job with walls (`spec`'s knobs over the package's
/// `geometry`), their first attempt's walls placed and opened ([`open_first_attempt`]),
/// and the job's statistics filled from them before any worker hears of the job.
async fn open_caches(
    cluster: &Arc<Cluster>,
    record: &Arc<JobRecord>,
    sched: &mut JobSchedule,
    spec: &JobSpec,
    geometry: WallGeometry,
) -> Result<JobCaches, DispatchError> {
    let caches = JobCaches::new(
        spec.ray_cache.clone(),
        spec.phm.clone(),
        Arc::new(geometry),
        cluster.options.clients.clone(),
    );
    let c = open_first_attempt(cluster, record, sched, caches).await?;
    // The statistics from the start (hosts lost while opening), before any worker
    // hears of the job: GetJob must not show less than they did.
    record.update_stats(|s| c.tally.fill(s));
    Ok(c)
}

/// The environment map as the job's workers get it, and the packages the job owns with
/// it: workers in this process take the decoded map from memory (an entry of the
/// in-memory store, which the job then owns too), the others the file.
fn env_map_for_workers(
    cluster: &Cluster,
    env_map: Option<LoadedEnvMap>,
    owned: Option<OwnedPackage>,
) -> (Option<EnvMapFile>, Option<OwnedPackage>) {
    match (env_map, &cluster.options.memory_packages) {
        (Some(e), Some(store)) => {
            let name = store.insert_env_map(e.map);
            let owned_map = OwnedPackage::Memory {
                store: store.clone(),
                name: name.clone(),
            };
            let file = EnvMapFile {
                path: name,
                ..e.file
            };
            (Some(file), OwnedPackage::with(owned, owned_map))
        }
        (e, _) => (e.map(|e| e.file), owned),
    }
}

/// Every tile of the job: the image's, then the ray-cache coarse pass's, which come
/// after the image's so that, traced first, they fill the caches before any image ray
/// looks them up (see `crate::job::running`).
fn job_tiles(record: &JobRecord, spec: &JobSpec) -> Vec<Tile> {
    let mut tiles = image_tiles(record.spec.width, record.spec.height);
    let coarse = spec.ray_cache.as_ref().map_or(0, |rc| rc.coarse);
    if coarse > 0 {
        let first = tiles.len() as u32;
        tiles.extend(coarse_tiles(coarse, first));
    }
    tiles
}

/// The JobSetup every worker of the job is sent (see the module's step 1), with
/// `routing` and `attempt` left for the actor to fill from the schedule and
/// `passes_ahead` for the caller, once the tiles are known.
fn job_setup(
    record: &JobRecord,
    spec: JobSpec,
    prepared: &PreparedSummary,
    info: &PackageInfo,
    schedule: Schedule,
    env_map: Option<EnvMapFile>,
) -> JobSetup {
    let env = prepared.environment;
    JobSetup {
        job_id: record.id.clone(),
        spec: Some(spec),
        environment: Some(Rgb {
            r: env.x,
            g: env.y,
            b: env.z,
        }),
        effects: prepared.effects.clone(),
        package_path: info.path.clone(),
        package_checksum: info.checksum.clone(),
        domain_count: info.domains,
        tile_size: TILE_SIZE,
        tile_credit: TILE_CREDIT,
        // Filled in from the schedule each time the setup is sent.
        routing: None,
        attempt: 0,
        schedule: schedule.name().to_string(),
        // The job's span (this task runs in it): the workers' spans join its trace.
        trace_context: dray_net::trace::inject(&tracing::Span::current()),
        // Set by the caller, once the tiles are known.
        passes_ahead: 0,
        pass: 0,
        env_map,
    }
}

/// Hand `plan` to the job table, which starts the job's actor. If it cannot start, the
/// job's package is removed, the walls it opened are closed (their statistics kept),
/// and the job fails unless it has ended already (cancelled while its walls opened).
async fn start_job(cluster: &Arc<Cluster>, plan: JobPlan, workers: usize) {
    let record = plan.record.clone();
    let owned = plan.owned_package.clone();
    // What to close if the job never starts (cancelled while its walls opened).
    let opened = plan.caches.as_ref().and_then(|c| {
        c.opened
            .clone()
            .map(|o| (o, c.tally.clone(), c.net.clone()))
    });
    let (domains, tiles) = (plan.setup.domain_count, plan.tiles.len());
    let (schedule, package) = (plan.setup.schedule.clone(), plan.setup.package_path.clone());
    match cluster.jobs.start(plan).await {
        Ok(()) => {
            tracing::info!(
                workers,
                domains,
                tiles,
                schedule = schedule.as_str(),
                package = %package,
                "job dispatched"
            );
        }
        Err(msg) => {
            remove_package(owned.as_ref());
            if let Some((o, tally, net)) = opened {
                let closed = lifecycle::close(&record.id, o.attempt, &o.placement, &net).await;
                closed.add_to(&tally);
                record.update_stats(|s| tally.fill(s));
            }
            if record.is_terminal() {
                return;
            }
            record.finish(JobState::Failed, msg, None);
        }
    }
}

/// Place the first attempt's cache walls by `sched`'s first table and open them, then
/// put the placement in the table. Hosts that fail are left out (their walls placed on
/// the others) and listed as lost; if all fail, the job runs without caches. Fails when
/// there is no host at all.
async fn open_first_attempt(
    cluster: &Arc<Cluster>,
    record: &Arc<JobRecord>,
    sched: &mut JobSchedule,
    mut caches: JobCaches,
) -> Result<JobCaches, DispatchError> {
    let candidates = cache_job::candidates(&cluster.membership, sched);
    if candidates.is_empty() {
        return Err(DispatchError::NoCacheHost);
    }
    let placement = cache_job::place(&candidates, sched, sched.domains(), &caches);
    let walls = caches.attempt_walls(&record.id, sched.attempt());
    let opened = lifecycle::open(&walls, placement).await;
    caches
        .tally
        .lose(opened.failed.iter().map(|f| f.host.endpoint.as_str()));
    if opened.placement.is_empty() {
        tracing::warn!(
            hosts = candidates.hosts.len(),
            "no cache host could open the walls: the job runs without ray caches"
        );
    } else {
        tracing::info!(
            hosts = opened.placement.hosts().len(),
            walls = opened.placement.wall_hosts().len(),
            "cache walls open"
        );
        caches.opened = Some(OpenAttempt {
            attempt: walls.attempt,
            placement: opened.placement.clone(),
        });
    }
    sched.set_caches(opened.placement);
    Ok(caches)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn domain_choice() {
        assert_eq!(choose_domains(Some(7), 3, 10, 100), 7);
        assert_eq!(choose_domains(None, 3, 1_000_000, 65536), 12);
        // A tiny scene is not cut finer than MIN_TRIANGLES_PER_DOMAIN allows.
        assert_eq!(choose_domains(None, 4, 200, 65536), 3);
        assert_eq!(choose_domains(None, 4, 10, 65536), 1);
        assert_eq!(choose_domains(None, 100_000, u64::MAX, 65536), 65536);
    }

    #[test]
    fn tiles_are_row_major_with_the_documented_index() {
        let t = image_tiles(70, 40);
        let grid = TileGrid::image(70, 40);
        assert_eq!(t.len(), 3 * 2);
        for tile in &t {
            assert_eq!(tile.index, grid.index_of(tile.x0, tile.y0));
            assert_eq!(tile.credit, TILE_CREDIT);
        }
        let c = coarse_tiles(40, 6);
        assert_eq!(c.len(), 4);
        assert!(c.iter().all(|t| t.coarse));
        assert_eq!(c.iter().map(|t| t.index).collect::<Vec<_>>(), [6, 7, 8, 9]);
        assert_eq!((t[2].width, t[2].height), (6, 32));
        assert_eq!((t[5].width, t[5].height), (6, 8));
        let px: u32 = t.iter().map(|t| t.width * t.height).sum();
        assert_eq!(px, 70 * 40);
    }
}
