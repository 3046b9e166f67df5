//! How a worker runs, and why it stops.

use std::sync::Arc;
use std::time::Duration;

use dray_core::ray::RAY_RECORD_MAX_BYTES;
use dray_scene::partition::memory::MemoryPackages;

/// How a worker runs.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator, e.g. `http://127.0.0.1:50051`.
    pub coordinator: String,
    /// Where peers reach this worker, e.g. `http://10.0.0.7:50052`; by default
    /// `http://` + the listening address.
    pub advertise: Option<String>,
    /// Tracing threads (0: all cores).
    pub threads: usize,
    /// Memory for resident domains and queued rays, bytes (0: unlimited); reported to
    /// the scheduler. See [`WorkerConfig::limits`] for how it is split.
    pub memory_budget: u64,
    /// Added to every domain load, to emulate slow shared storage in experiments.
    pub load_delay: Duration,
    /// Rays the queues hold together at most (peers wait beyond it); lowered to fit
    /// the memory budget.
    pub queue_capacity: usize,
    /// Rays in flight at this worker above which no camera rays are made; lowered to
    /// fit the memory budget.
    pub in_flight_limit: usize,
    /// How long to keep trying to reach the coordinator at start.
    pub connect_timeout: Duration,
    /// How long to keep trying to register again after losing the coordinator (it
    /// restarted, or declared this worker lost) before giving up.
    pub rejoin_timeout: Duration,
    /// The in-memory package store of the coordinator in this process, when there is
    /// one (`dray render`): jobs whose package is `memory:N` read their domains from it.
    pub memory_packages: Option<Arc<MemoryPackages>>,
    /// The CacheService endpoint of the cache host running beside this worker in the
    /// same process (`dray worker` starts one unless told not to), announced when
    /// registering so the coordinator can place cache actors there. The worker itself
    /// never answers a ray from a cache: it hands rays to the walls' actors.
    pub cache_endpoint: Option<String>,
    /// That cache host itself, when it runs in this process: rays at its walls reach
    /// its actors through their mailboxes (no protobuf, no HTTP/2), and only cache
    /// hosts in other processes are reached over gRPC. The answers are the same either
    /// way (the same actors answer).
    pub cache_host: Option<dray_cache::CacheHost>,
    /// How this worker reaches the coordinator, its peers and cache hosts: the cluster
    /// token it presents, and TLS.
    pub net: dray_net::ClientOptions,
    /// How its own server (ray streams) admits calls: the cluster token it requires,
    /// TLS, load shedding.
    pub server: dray_net::ServerOptions,
    /// When job packages are fetched from the coordinator instead of read at the path
    /// the coordinator names (see [`crate::package_fetch`]).
    pub package_fetch: crate::package_fetch::FetchMode,
    /// Where fetched packages are kept; `None`: a directory of this process in the
    /// system's temp directory, removed when the worker stops.
    pub package_cache: Option<std::path::PathBuf>,
    /// Where traffic traces of jobs that ask for one (`JobSpec.trace`) are written
    /// ([`crate::traffic_trace`]); `None`: no trace is recorded.
    pub trace_dir: Option<std::path::PathBuf>,
    /// Its name for people (RegisterWorkerRequest.name: logs, ListWorkers, the
    /// dashboard); `None`: the host name when it is a valid name, else none. Checked by
    /// [`crate::run`] against `dray_proto::worker_name`.
    pub name: Option<String>,
}

impl Default for WorkerConfig {
    fn default() -> Self {
        WorkerConfig {
            coordinator: format!("http://127.0.0.1:{}", dray_net::DEFAULT_PORT),
            advertise: None,
            threads: 0,
            memory_budget: 0,
            load_delay: Duration::ZERO,
            queue_capacity: 1 << 18,
            in_flight_limit: 1 << 18,
            connect_timeout: Duration::from_secs(10),
            rejoin_timeout: Duration::from_secs(300),
            memory_packages: None,
            cache_endpoint: None,
            cache_host: None,
            net: dray_net::ClientOptions::plain(),
            server: dray_net::ServerOptions::default(),
            package_fetch: crate::package_fetch::FetchMode::Auto,
            package_cache: None,
            trace_dir: None,
            name: None,
        }
    }
}

/// How a memory budget is spent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Bytes for resident domains (0: unlimited).
    pub domain_bytes: u64,
    /// Rays the queues hold together.
    pub queue_capacity: usize,
    /// Rays in flight above which no camera rays are made.
    pub in_flight_limit: usize,
}

/// Fewest rays the queues and the in-flight limit are cut to, however small the budget:
/// below this batches could not be formed at all.
const MIN_RAYS: usize = 4096;

impl WorkerConfig {
    /// The name this worker registers under: [`WorkerConfig::name`] when given (checked:
    /// a bad one is an error naming what is wrong), else the host name when it is a
    /// valid name, else none (empty).
    pub fn resolved_name(&self, hostname: &str) -> Result<String, NodeError> {
        match &self.name {
            Some(name) => dray_proto::worker_name::check_worker_name(name)
                .map(|()| name.clone())
                .map_err(|source| NodeError::Name {
                    name: name.clone(),
                    source,
                }),
            None => Ok(dray_proto::worker_name::default_worker_name(hostname)),
        }
    }

    /// The split of the memory budget: a quarter for rays (queued, and waiting for
    /// peers: the queue capacity and the in-flight limit each get half of it, 64 bytes
    /// a ray, the largest record), the rest for resident domains. Without a budget the configured ray
    /// limits hold and domains are unlimited.
    pub fn limits(&self) -> Limits {
        if self.memory_budget == 0 {
            return Limits {
                domain_bytes: 0,
                queue_capacity: self.queue_capacity.max(1),
                in_flight_limit: self.in_flight_limit.max(1),
            };
        }
        let rays = (self.memory_budget / 4 / 2 / RAY_RECORD_MAX_BYTES as u64) as usize;
        let rays = rays.max(MIN_RAYS);
        let queue_capacity = self.queue_capacity.min(rays).max(1);
        let in_flight_limit = self.in_flight_limit.min(rays).max(1);
        let ray_bytes = ((queue_capacity + in_flight_limit) * RAY_RECORD_MAX_BYTES) as u64;
        Limits {
            domain_bytes: self.memory_budget.saturating_sub(ray_bytes).max(1),
            queue_capacity,
            in_flight_limit,
        }
    }
}

/// Why a worker stopped.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("invalid coordinator address {address:?}: {message}")]
    Address { address: String, message: String },
    #[error("cannot reach the coordinator at {address} (tried for {seconds} s): {message}")]
    Unreachable {
        address: String,
        seconds: u64,
        message: String,
    },
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
    #[error("lost the coordinator: {0}")]
    Lost(String),
    #[error("cannot start the tracing threads: {0}")]
    Threads(String),
    #[error("the ray-stream server failed: {0}")]
    Serve(String),
    #[error("cannot set up the package cache: {0}")]
    PackageCache(String),
    #[error("--name {name:?}: {source}")]
    Name {
        name: String,
        source: dray_proto::worker_name::WorkerNameError,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_budget_is_split_between_rays_and_domains() {
        let c = WorkerConfig {
            memory_budget: 64 << 20,
            ..WorkerConfig::default()
        };
        let l = c.limits();
        assert_eq!(l.queue_capacity, (64 << 20) / 8 / 64);
        assert_eq!(l.in_flight_limit, l.queue_capacity);
        assert_eq!(l.domain_bytes, (64 << 20) - (64 << 20) / 4);
        let unlimited = WorkerConfig::default().limits();
        assert_eq!(unlimited.domain_bytes, 0);
        assert_eq!(unlimited.queue_capacity, 1 << 18);
        // A tiny budget still leaves room for whole batches.
        let tiny = WorkerConfig {
            memory_budget: 1000,
            ..WorkerConfig::default()
        };
        assert_eq!(tiny.limits().queue_capacity, MIN_RAYS);
        assert_eq!(tiny.limits().domain_bytes, 1);
    }

    #[test]
    fn a_name_is_checked_and_defaults_to_the_host_name() {
        let named = |n: &str| WorkerConfig {
            name: Some(n.into()),
            ..WorkerConfig::default()
        };
        assert_eq!(named("worker-2").resolved_name("host").unwrap(), "worker-2");
        let e = named("worker 2")
            .resolved_name("host")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--name \"worker 2\": ' ' (character 7) is not allowed"),
            "{e}"
        );
        let long = "n".repeat(65);
        let e = named(&long).resolved_name("host").unwrap_err().to_string();
        assert!(e.contains("65 characters is longer than 64"), "{e}");
        let default = WorkerConfig::default();
        assert_eq!(default.resolved_name("pod-7").unwrap(), "pod-7");
        assert_eq!(default.resolved_name("not a name").unwrap(), "");
    }
}
