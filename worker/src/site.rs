//! What this worker is and where its jobs come from: the name, threads, memory budget
//! and cache host it announces at registration, and what a job setup needs to be
//! planned here (scene packages in this process's memory or fetched from the
//! coordinator, the directory traffic traces go to).
//!
//! Fixed for the worker's life: read from its configuration once, never changed.

use std::path::PathBuf;
use std::sync::Arc;

use dray_core::ray::RAY_RECORD_FORMAT;
use dray_net::AuthChannel;
use dray_proto::v1::{JobSetup, RegisterWorkerRequest};
use dray_scene::partition::memory::MemoryPackages;

use crate::config::{NodeError, WorkerConfig};
use crate::package_fetch::{FetchMode, PackageFetcher};
use crate::plan::{JobPlan, plan_job_with};
use crate::traffic_trace::TrafficTrace;

/// The dray version, sent at registration: the coordinator refuses another build.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// This machine's host name (empty when it cannot be read): sent at registration, and
/// the default worker name.
pub(crate) fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
}

/// What the worker announces and what its job setups are planned with.
pub(crate) struct Site {
    /// Its name, announced at registration (`WorkerConfig::resolved_name`).
    name: String,
    threads: usize,
    memory_budget: u64,
    /// The cache host beside this worker, announced at registration.
    cache_endpoint: Option<String>,
    memory_packages: Option<Arc<MemoryPackages>>,
    /// Fetches job packages from the coordinator when they are not on this disk (none
    /// with `FetchMode::Never`).
    fetcher: Option<Arc<PackageFetcher>>,
    /// Where jobs that ask for a traffic trace write it (none: they record nothing).
    trace_dir: Option<PathBuf>,
}

impl Site {
    /// From `config`, named `name`, with `threads` tracing threads; packages are
    /// fetched over `channel` (to the coordinator) unless the config says never.
    pub fn new(
        config: &WorkerConfig,
        name: String,
        threads: usize,
        channel: &AuthChannel,
    ) -> Result<Site, NodeError> {
        let fetcher = match config.package_fetch {
            FetchMode::Never => None,
            mode => Some(Arc::new(
                PackageFetcher::new(
                    channel.clone(),
                    tokio::runtime::Handle::current(),
                    config.package_cache.clone(),
                    mode,
                )
                .map_err(|e| NodeError::PackageCache(e.to_string()))?,
            )),
        };
        Ok(Site {
            name,
            threads,
            memory_budget: config.memory_budget,
            cache_endpoint: config.cache_endpoint.clone(),
            memory_packages: config.memory_packages.clone(),
            fetcher,
            trace_dir: config.trace_dir.clone(),
        })
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The registration of this worker, reached at `endpoint`.
    pub fn registration(&self, endpoint: &str) -> RegisterWorkerRequest {
        RegisterWorkerRequest {
            endpoint: endpoint.to_string(),
            threads: self.threads as u32,
            memory_budget_bytes: self.memory_budget,
            version: VERSION.into(),
            record_format: RAY_RECORD_FORMAT,
            hostname: hostname(),
            cache_endpoint: self.cache_endpoint.clone().unwrap_or_default(),
            name: self.name.clone(),
        }
    }

    /// Plan `setup` (reads the manifest, perhaps fetches the package) on a blocking
    /// thread; the error as its message.
    pub async fn plan(&self, setup: &JobSetup) -> Result<JobPlan, String> {
        let memory = self.memory_packages.clone();
        let fetcher = self.fetcher.clone();
        let setup = setup.clone();
        tokio::task::spawn_blocking(move || {
            plan_job_with(&setup, memory.as_deref(), fetcher.as_ref())
        })
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r.map_err(|e| e.to_string()))
    }

    /// The job's traffic trace on this worker `me`, when its spec asks for one and the
    /// worker keeps traces. A trace that cannot be opened is a warning, not a failure:
    /// the job's image does not depend on it.
    pub fn traffic_trace(&self, setup: &JobSetup, me: &str) -> Option<TrafficTrace> {
        let wanted = setup.spec.as_ref().is_some_and(|s| s.trace);
        if !wanted {
            return None;
        }
        let Some(dir) = self.trace_dir.as_deref() else {
            tracing::warn!(job = %setup.job_id, "the job asks for a traffic trace, but this worker has no --trace-dir: none recorded");
            return None;
        };
        match TrafficTrace::open(dir, &setup.job_id, setup.attempt, me, self.threads) {
            Ok(t) => Some(t),
            Err(e) => {
                tracing::warn!(job = %setup.job_id, "{e}");
                None
            }
        }
    }
}
