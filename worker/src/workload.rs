//! The tracing side's state: the jobs running here, their ray queues, the resident
//! domains, the wake for idle tracing threads, the in-flight limit on camera rays and
//! the stop flag. What the tracing threads ([`crate::work`]) choose work from, and what
//! a released job is dropped from ([`Workload::forget`]).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::domain_store::DomainStore;
use crate::jobs::Jobs;
use crate::queue::RayQueues;
use crate::wake::Wake;

/// The work held here, and how the threads tracing it are woken and stopped.
pub(crate) struct Workload {
    queues: Arc<RayQueues>,
    store: DomainStore,
    jobs: Jobs,
    wake: Arc<Wake>,
    /// Rays in flight here above which no camera rays are made (`Limits`).
    in_flight_limit: usize,
    /// Set when the worker stops: tracing threads leave.
    stopping: AtomicBool,
}

impl Workload {
    pub fn new(
        queues: Arc<RayQueues>,
        store: DomainStore,
        wake: Arc<Wake>,
        in_flight_limit: usize,
    ) -> Workload {
        Workload {
            queues,
            store,
            jobs: Jobs::default(),
            wake,
            in_flight_limit,
            stopping: AtomicBool::new(false),
        }
    }

    /// The ray queues, per job attempt and domain.
    pub fn queues(&self) -> &RayQueues {
        &self.queues
    }

    /// The resident domains.
    pub fn store(&self) -> &DomainStore {
        &self.store
    }

    /// The jobs running here.
    pub fn jobs(&self) -> &Jobs {
        &self.jobs
    }

    /// The tracing threads' wake.
    pub fn wake(&self) -> &Wake {
        &self.wake
    }

    /// Wake idle tracing threads: there may be work.
    pub fn notify(&self) {
        self.wake.notify();
    }

    /// Rays in flight here above which no camera rays are made.
    pub fn in_flight_limit(&self) -> usize {
        self.in_flight_limit
    }

    /// Tell the tracing threads to leave (and wake them to see it).
    pub fn stop(&self) {
        self.stopping.store(true, Ordering::Relaxed);
        self.notify();
    }

    /// Whether the worker is stopping.
    pub fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::Relaxed)
    }

    /// Rays waiting here in any form, for the jobs still running.
    pub fn in_flight(&self) -> usize {
        let outgoing: usize = self.jobs.all().iter().map(|j| j.waiting()).sum();
        self.queues.total() + outgoing
    }

    /// Bytes of resident domains and queued rays.
    pub fn memory_used(&self) -> u64 {
        self.store.used_bytes() + (self.in_flight() * dray_core::ray::RAY_RECORD_MAX_BYTES) as u64
    }

    /// Drop everything of a released job attempt.
    pub fn forget(&self, job_id: &str, attempt: u32) {
        self.queues.drop_job(job_id, attempt);
        self.store.release(job_id, attempt);
        self.notify();
    }
}
