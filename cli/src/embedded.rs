//! `dray render`: the distributed actors, all in this process (embedded mode).
//!
//! A coordinator and N workers start on loopback ports inside one async runtime and run
//! the job exactly as `dray cluster` would: the coordinator partitions the scene into a
//! package, deals domains and tiles, the workers trace and stream rays to each other over
//! gRPC, and the image is assembled from their reports. Only the submission skips the
//! network (the coordinator's RenderService is called directly). So the embedded mode and
//! a cluster share one code path, and the tests hold it to the same bits as the
//! reference renderer (`dray render --workers 0`), which traces tiles with no actors.
//!
//! A job with ray caches or hit maps (`--ray-cache`, `--phm`) also gets a cache host
//! beside each worker, on its own loopback port, as `dray worker` runs one: the
//! coordinator places the walls on them; a worker reaches the host beside it through
//! the actors' mailboxes and in-place views, and the others' over loopback gRPC.
//! Without caches or maps none is started (nothing would use it).
//!
//! [`Actors`] are the running set; `dray render` starts them for its one job and stops
//! them after, `dray sweep` keeps them for every setting ([`crate::warm`]).

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use dray_coordinator::Coordinator;
use dray_coordinator::cluster::ClusterOptions;
use dray_core::render::RenderOutput;
use dray_core::scene::Scene;
use dray_proto::v1::{JobSpec, JobState, JobStats};
use dray_scene::partition::memory::MemoryPackages;

use crate::cache_host::LocalCacheHost;
use crate::render_cmd::RenderArgs;

/// A scene spec with its file paths made absolute, since the in-process coordinator
/// resolves scenes against `/`. Procedural names pass unchanged; `grid:` specs have
/// their inner scene resolved.
fn absolute_scene(spec: &str) -> String {
    if let Some(rest) = spec.strip_prefix("grid:")
        && let Some((inner, dims)) = rest.rsplit_once(':')
    {
        return format!("grid:{}:{dims}", absolute_scene(inner));
    }
    match Path::new(spec).canonicalize() {
        Ok(p) if p.is_file() || p.is_dir() => p.to_string_lossy().into_owned(),
        _ => spec.to_string(),
    }
}

/// How long the actors get to stop once the image is in hand.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// What a render on in-process actors gives back.
pub struct ActorsOutput {
    /// The image, rays by kind and the render time.
    pub out: RenderOutput,
    /// The job's statistics as GetJob reports them (domains, scheduling metrics, per
    /// worker).
    pub stats: JobStats,
}

/// The job spec `dray render` sends its in-process coordinator for `a` on `workers`
/// workers.
fn embedded_spec(a: &RenderArgs, workers: usize) -> Result<JobSpec> {
    // One worker renders best from one domain (no hops); several want the coordinator's
    // choice (0), several domains each.
    let domains = a.domains.unwrap_or(if workers <= 1 { 1 } else { 0 });
    let mut spec = a.job.job_spec(
        absolute_scene(&a.job.scene),
        domains,
        &a.layout,
        "dray render",
    )?;
    // The caller translated the scene it hands over.
    spec.translate = None;
    // The in-process coordinator's scene root is `/`: the map is named as `dray render`
    // was given it, from its working directory.
    if let Some(e) = spec.lighting.as_mut().and_then(|l| l.env_map.as_mut()) {
        e.path = absolute_scene(&e.path);
    }
    // Nobody watches an embedded render's passes, and each pass waits for its slowest
    // tile (14% of the wall time of a 16-spp bunny with doubling passes, 2 threads): one
    // pass unless asked (or adaptive sampling needs passes to stop tiles between). The
    // image is the same bits either way.
    if a.job.passes.is_none() && a.job.noise.noise_threshold.is_none() {
        spec.passes = "one".to_string();
    }
    spec.trace = a.trace_out.is_some();
    Ok(spec)
}

/// Whether a job of `a` needs cache hosts beside the workers (ray caches or hit maps).
pub fn wants_cache_hosts(a: &RenderArgs) -> Result<bool> {
    let spec = embedded_spec(a, a.workers)?;
    Ok(spec.ray_cache.is_some() || spec.phm.is_some())
}

/// What in-process actors are started with. A render whose flags give the same shape
/// can run on actors already up ([`Actors`]); another needs new ones.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorsShape {
    workers: usize,
    /// Tracing threads in all (the coordinator's, for a job it renders itself).
    threads: usize,
    memory_budget: u64,
    load_delay_ms: u64,
    /// A cache host beside each worker.
    cache_hosts: bool,
    /// Where the workers write traffic traces (`--trace-out`).
    trace_dir: Option<std::path::PathBuf>,
}

impl ActorsShape {
    /// The actors `a` asks for, on `workers` workers, with cache hosts or not.
    pub fn of(a: &RenderArgs, workers: usize, cache_hosts: bool) -> ActorsShape {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        ActorsShape {
            workers,
            threads: if a.threads == 0 { cores } else { a.threads },
            memory_budget: a.memory_budget,
            load_delay_ms: a.load_delay_ms,
            cache_hosts,
            trace_dir: None,
        }
    }
}

/// A coordinator, its workers and their cache hosts, running in this process on
/// loopback ports, for one render ([`render_on_actors`]) or for many in a row (`dray
/// sweep`, [`crate::warm::WarmProcess`]): the workers keep the domains they loaded
/// between jobs of one package, and with [`Actors::start`]'s `keep_package` the
/// coordinator hands a job of an equal scene and layout the package the last job used.
pub struct Actors {
    shape: ActorsShape,
    rt: tokio::runtime::Runtime,
    coordinator: Coordinator,
    nodes: Vec<tokio::task::JoinHandle<Result<(), dray_worker::NodeError>>>,
    caches: Vec<LocalCacheHost>,
    server: tokio::task::JoinHandle<Result<(), dray_net::server::ServeError>>,
    stop_workers_tx: tokio::sync::watch::Sender<bool>,
}

impl Actors {
    /// Start the actors of `shape` and wait until every worker has registered.
    pub fn start(shape: ActorsShape, keep_package: bool) -> Result<Actors> {
        let workers = shape.workers;
        // A private directory (random name, 0700, never one made beforehand by another
        // user), removed however the render ends.
        let work_dir = dray_coordinator::cluster::WorkDir::private("dray-embedded-")
            .context("cannot create the coordinator's work directory")?;
        let wiring = Wiring::new(keep_package)?;
        let coordinator = wiring.coordinator(shape.threads, work_dir)?;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .context("cannot start the async runtime")?;
        // Workers stop first, then the coordinator (`Coordinator::shutdown`): a worker
        // that saw its coordinator go first would warn that it lost it and try to
        // register again.
        let (stop_workers_tx, stop_workers_rx) = tokio::sync::watch::channel(false);
        let started = rt.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
                .await
                .context("cannot listen on a loopback port")?;
            let addr = listener
                .local_addr()
                .context("cannot read the bound address")?;
            let coordinator_server = wiring.server.clone();
            let serving = coordinator.clone();
            // Stopped by `Coordinator::shutdown`, which waits for it.
            let server = tokio::spawn(async move {
                dray_coordinator::serve_with(
                    &coordinator_server,
                    listener,
                    serving,
                    std::future::pending(),
                )
                .await
            });
            let mut nodes = Vec::new();
            let mut caches = Vec::new();
            for i in 0..workers {
                let stop = stopped(stop_workers_rx.clone());
                let (node, cache) = wiring.start_worker(&shape, i, addr, stop).await?;
                caches.extend(cache);
                nodes.push(node);
            }
            wait_for_registration(&coordinator, &nodes).await?;
            anyhow::Ok((server, nodes, caches))
        });
        let (server, nodes, caches) = match started {
            Ok(s) => s,
            Err(e) => {
                let _ = stop_workers_tx.send(true);
                // The server is told to stop; the runtime, dropped with the error, ends
                // it (no grace: nothing ran).
                rt.block_on(coordinator.shutdown(Duration::ZERO));
                return Err(e);
            }
        };
        Ok(Actors {
            shape,
            rt,
            coordinator,
            nodes,
            caches,
            server,
            stop_workers_tx,
        })
    }

    /// The shape these actors were started with.
    pub fn shape(&self) -> &ActorsShape {
        &self.shape
    }

    /// Render `a` on these actors; `scene` is the job's scene, loaded and translated by
    /// the caller. `progress` gets (tiles done, total).
    pub fn render(
        &self,
        a: &RenderArgs,
        scene: Scene,
        progress: &dyn Fn(usize, usize),
    ) -> Result<ActorsOutput> {
        let spec = embedded_spec(a, self.shape.workers)?;
        let coordinator = &self.coordinator;
        self.rt.block_on(async {
            let start = Instant::now();
            let id = coordinator
                .submit_loaded(spec, scene)
                .await
                .map_err(|s| anyhow::anyhow!("{}", s.message()))?;
            let entry = coordinator
                .job_entry(&id)
                .context("the coordinator lost the job")?;
            loop {
                let p = entry.progress();
                progress(p.tiles_done as usize, p.tiles_total as usize);
                match JobState::try_from(p.state) {
                    Ok(JobState::Succeeded) => break,
                    Ok(JobState::Failed | JobState::Cancelled) => bail!("{}", p.error),
                    // Progress every 50 ms; the end as soon as it comes.
                    _ => tokio::select! {
                        _ = tokio::time::sleep(Duration::from_millis(50)) => {}
                        _ = entry.wait_ended() => {}
                    },
                }
            }
            let render_time = start.elapsed();
            let film = entry.film().context("the job has no image")?;
            let job = entry.to_job();
            let stats = job.stats.unwrap_or_default();
            let rays = crate::summary::ray_counts(&stats.rays.unwrap_or_default());
            Ok(ActorsOutput {
                out: RenderOutput {
                    film: (*film).clone(),
                    rays,
                    render_time,
                },
                stats,
            })
        })
    }

    /// Stop the workers, then their cache hosts and the coordinator.
    pub fn stop(self) {
        let Actors {
            rt,
            coordinator,
            nodes,
            caches,
            server,
            stop_workers_tx,
            ..
        } = self;
        let _ = stop_workers_tx.send(true);
        // The image is in hand: give the actors a moment to stop cleanly, no more.
        let stop_all = async {
            for n in nodes {
                let _ = n.await;
            }
            for c in caches {
                c.stop().await;
            }
            // The library's shutdown, as `dray coordinator` runs it (no store here).
            coordinator.shutdown(STOP_GRACE).await;
            let _ = server.await;
        };
        rt.block_on(async {
            let _ = tokio::time::timeout(STOP_GRACE, stop_all).await;
        });
    }
}

/// Completes once `rx` says to stop (or its sender is gone): a worker's shutdown.
async fn stopped(mut rx: tokio::sync::watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

/// Wait until each of `nodes` has registered with `coordinator`: an error when one
/// stopped first, or after 20 s.
async fn wait_for_registration(
    coordinator: &Coordinator,
    nodes: &[tokio::task::JoinHandle<Result<(), dray_worker::NodeError>>],
) -> Result<()> {
    let workers = nodes.len();
    let deadline = Instant::now() + Duration::from_secs(20);
    while coordinator.cluster().membership.workers().len() < workers {
        if Instant::now() > deadline {
            bail!("the in-process workers did not register within 20 s");
        }
        if let Some(n) = nodes.iter().position(|n| n.is_finished()) {
            bail!("in-process worker {} stopped while starting", n + 1);
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    Ok(())
}

/// What the in-process actors share: the packages the coordinator cuts into memory
/// and the workers read, and the loopback network's credentials.
struct Wiring {
    memory: Arc<MemoryPackages>,
    clients: dray_net::ClientOptions,
    server: dray_net::ServerOptions,
}

impl Wiring {
    /// A package store (keeping the last package for the next job, with
    /// `keep_package`) and a token made for this run: the actors listen on loopback
    /// ports, and the token keeps other local users' processes from joining or
    /// injecting rays.
    fn new(keep_package: bool) -> Result<Wiring> {
        // The coordinator cuts the scene into this store and the workers read it: no
        // package is written to disk for a scene this process already holds.
        let memory = Arc::new(if keep_package {
            MemoryPackages::keeping_last()
        } else {
            MemoryPackages::default()
        });
        let token = dray_net::Token::generate()?;
        let clients = dray_net::ClientOptions::plain().with_token(Some(token.clone()));
        let server = dray_net::ServerOptions {
            auth: dray_net::AuthPolicy {
                api: None,
                cluster: Some(token),
            },
            ..dray_net::ServerOptions::default()
        };
        Ok(Wiring {
            memory,
            clients,
            server,
        })
    }

    /// The coordinator, with `threads` for a job it renders itself, its packages in
    /// memory (and `work_dir` for anything else).
    fn coordinator(
        &self,
        threads: usize,
        work_dir: dray_coordinator::cluster::WorkDir,
    ) -> Result<Coordinator> {
        Ok(Coordinator::new(Path::new("/"), threads)
            .context("cannot start the coordinator")?
            .with_cluster_options(ClusterOptions {
                work_dir,
                memory_packages: Some(self.memory.clone()),
                clients: self.clients.clone(),
                // Its workers are its own threads: no member to distrust, and a slow
                // render (a huge scene, --load-delay-ms) is not a stuck one.
                stall_timeout: None,
                ..ClusterOptions::default()
            }))
    }

    /// Start worker `i` of `shape` (and its cache host, when the shape has them) on a
    /// loopback port, registering with the coordinator at `addr`, until `stop`.
    async fn start_worker(
        &self,
        shape: &ActorsShape,
        i: usize,
        addr: std::net::SocketAddr,
        stop: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<(
        tokio::task::JoinHandle<Result<(), dray_worker::NodeError>>,
        Option<LocalCacheHost>,
    )> {
        let l = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .context("cannot listen on a loopback port")?;
        let host = if shape.cache_hosts {
            Some(LocalCacheHost::start("127.0.0.1:0", None, None, &self.server).await?)
        } else {
            None
        };
        let (cache_endpoint, cache_host) = host
            .as_ref()
            .map(|h| (h.endpoint.clone(), h.host.clone()))
            .unzip();
        let config = dray_worker::WorkerConfig {
            coordinator: format!("http://{addr}"),
            threads: shape.threads.div_ceil(shape.workers).max(1),
            memory_packages: Some(self.memory.clone()),
            memory_budget: shape.memory_budget,
            load_delay: Duration::from_millis(shape.load_delay_ms),
            cache_endpoint,
            cache_host,
            net: self.clients.clone(),
            server: self.server.clone(),
            // The workers read the coordinator's in-memory packages: nothing to
            // fetch.
            package_fetch: dray_worker::package_fetch::FetchMode::Never,
            trace_dir: shape.trace_dir.clone(),
            // Named as `dray cluster` names its workers (the host name would be
            // the same for all of them).
            name: Some(format!("worker-{}", i + 1)),
            ..dray_worker::WorkerConfig::default()
        };
        let node = tokio::spawn(dray_worker::run(config, l, stop));
        Ok((node, host))
    }
}

/// Render `a` on `workers` in-process worker actors started for it and stopped after;
/// `scene` is the job's scene, loaded and translated by the caller. `progress` gets
/// (tiles done, total).
pub fn render_on_actors(
    a: &RenderArgs,
    workers: usize,
    scene: Scene,
    progress: &dyn Fn(usize, usize),
) -> Result<ActorsOutput> {
    let caches = {
        let spec = embedded_spec(a, workers)?;
        spec.ray_cache.is_some() || spec.phm.is_some()
    };
    let trace = a
        .trace_out
        .as_ref()
        .map(|out| anyhow::Ok((out, crate::trace_out::TraceDir::new()?)))
        .transpose()?;
    let mut shape = ActorsShape::of(a, workers, caches);
    shape.trace_dir = trace.as_ref().map(|(_, d)| d.path());
    let threads = shape.threads.div_ceil(workers).max(1);
    let actors = Actors::start(shape, false)?;
    let result = actors.render(a, scene, progress);
    // Stopped first: every worker's trace is whole once its jobs are gone.
    actors.stop();
    let result = result?;
    if let Some((out, dir)) = trace {
        let spec = embedded_spec(a, workers)?;
        let facts = crate::trace_out::JobFacts {
            wall_seconds: result.out.render_time.as_secs_f64(),
            workers,
            threads,
            width: spec.width,
            height: spec.height,
            spp: spec.spp,
            integrator: spec.integrator.clone(),
            load_delay_ms: a.load_delay_ms,
        };
        crate::trace_out::assemble(out, &dir, &facts, &result.stats)?;
    }
    Ok(result)
}
