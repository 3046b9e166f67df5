//! Bounded ray queues, one per (job attempt, domain).
//!
//! Rays wait here until the domain's BVH traces them (or, when the routing table moved
//! the domain elsewhere, until they are forwarded), and the per-domain lengths are what
//! the worker reports to the coordinator's scheduler (docs/architecture.md "Scheduling"). Queues are
//! keyed by job attempt as well as domain, so one job's report never counts another's
//! rays and a released attempt's rays can be dropped at once.
//!
//! The capacity is one number of rays for all queues together, because it is this
//! worker's memory that it protects: [`RayQueues::push`] waits while a batch does not
//! fit, that wait stalls the peer stream that carried it, which stops granting credit,
//! which stalls the sender (see `peer_server`). So a ray explosion fills bounded queues
//! instead of memory. Rays this worker makes for itself go in with
//! [`RayQueues::push_local`], which never waits (a tracing thread must never wait for its
//! own queues to drain); they are bounded instead by the worker's in-flight limit on new
//! camera rays.
//!
//! Rays are queued as whole batches ([`QueuedBatch`]), because everything in a batch
//! shares its job, attempt and routing version; lengths and capacities still count rays.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_core::ray::RayRecord;
use dray_proto::v1::RayTicket;
use tokio::sync::Notify;

/// Which queue: a job attempt and a domain.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct QueueKey {
    /// The job.
    pub job_id: Arc<str>,
    /// The job attempt (`JobSetup.attempt`).
    pub attempt: u32,
    /// The domain the rays enter next.
    pub domain: u32,
}

/// Rays bound for one domain of one job, as they arrived in one batch.
#[derive(Clone, Debug, PartialEq)]
pub struct QueuedBatch {
    /// The job the rays belong to.
    pub job_id: Arc<str>,
    /// The job attempt they belong to.
    pub attempt: u32,
    /// Routing-table version the sender used.
    pub routing_version: u64,
    /// How many times the batch has already been forwarded.
    pub forwards: u32,
    /// The rays, in batch order.
    pub rays: Vec<RayRecord>,
    /// Cache tickets of the rays whose TICKETED flag is set, by index into `rays`.
    pub tickets: Vec<RayTicket>,
}

/// Why rays could not be queued.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QueueError {
    /// The batch is larger than the queues could ever hold, so waiting would never end.
    #[error(
        "batch of {rays} rays exceeds the capacity of this worker's ray queues ({capacity} rays)"
    )]
    BatchTooLarge { rays: usize, capacity: usize },
    /// The queues are full right now ([`RayQueues::try_push`] only).
    #[error("the ray queues are full ({capacity} rays)")]
    Full { capacity: usize },
}

#[derive(Default)]
struct DomainQueue {
    batches: VecDeque<QueuedBatch>,
    rays: usize,
}

struct Inner {
    queues: BTreeMap<QueueKey, DomainQueue>,
    /// Rays in all queues.
    total: usize,
}

/// The worker's ray queues, shared between the stream servers that fill them, the
/// tracing threads that fill (with their own rays) and drain them, and the reporter.
pub struct RayQueues {
    capacity: usize,
    inner: Mutex<Inner>,
    /// Woken whenever rays leave a queue (room for waiting pushes).
    space: Notify,
    /// Woken whenever rays enter a queue (work for waiting pops).
    data: Notify,
    /// Called after every push, for consumers on plain threads (the worker's tracers)
    /// that cannot await `data`.
    on_data: std::sync::OnceLock<Box<dyn Fn() + Send + Sync>>,
}

impl RayQueues {
    /// Empty queues holding at most `capacity` rays together (at least 1).
    pub fn new(capacity: usize) -> RayQueues {
        RayQueues {
            capacity: capacity.max(1),
            inner: Mutex::new(Inner {
                queues: BTreeMap::new(),
                total: 0,
            }),
            space: Notify::new(),
            data: Notify::new(),
            on_data: std::sync::OnceLock::new(),
        }
    }

    /// Rays the queues hold together at most (pushes from peers wait beyond it).
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic while holding the lock cannot leave a queue half-updated (every update
        // is a single push or pop), so a poisoned lock is still consistent.
        dray_sync::lock(&self.inner)
    }

    /// Have `f` called after every push that queues rays (once; later calls are ignored).
    pub fn on_data(&self, f: impl Fn() + Send + Sync + 'static) {
        let _ = self.on_data.set(Box::new(f));
    }

    fn insert(
        &self,
        domain: u32,
        batch: QueuedBatch,
        bounded: bool,
    ) -> Result<(), (QueueError, QueuedBatch)> {
        let n = batch.rays.len();
        if bounded && n > self.capacity {
            return Err((
                QueueError::BatchTooLarge {
                    rays: n,
                    capacity: self.capacity,
                },
                batch,
            ));
        }
        let mut inner = self.lock();
        if bounded && inner.total + n > self.capacity {
            return Err((
                QueueError::Full {
                    capacity: self.capacity,
                },
                batch,
            ));
        }
        if n > 0 {
            let key = QueueKey {
                job_id: batch.job_id.clone(),
                attempt: batch.attempt,
                domain,
            };
            let q = inner.queues.entry(key).or_default();
            q.rays += n;
            q.batches.push_back(batch);
            inner.total += n;
            drop(inner);
            self.data.notify_waiters();
            if let Some(f) = self.on_data.get() {
                f();
            }
        }
        Ok(())
    }

    /// Queue `batch` for `domain` if it fits now.
    pub fn try_push(&self, domain: u32, batch: QueuedBatch) -> Result<(), QueueError> {
        self.insert(domain, batch, true).map_err(|(e, _)| e)
    }

    /// Queue rays this worker made for itself: never waits and never refuses (see the
    /// module docs for what bounds them).
    pub fn push_local(&self, domain: u32, batch: QueuedBatch) {
        let _ = self.insert(domain, batch, false);
    }

    /// Queue `batch` for `domain`, waiting while the queues have no room for all of it.
    /// Fails at once for a batch larger than the capacity.
    pub async fn push(&self, domain: u32, mut batch: QueuedBatch) -> Result<(), QueueError> {
        loop {
            // Register for the wake-up before checking, so a pop between the check and
            // the wait is not missed.
            let space = self.space.notified();
            tokio::pin!(space);
            space.as_mut().enable();
            match self.insert(domain, batch, true) {
                Ok(()) => return Ok(()),
                Err((QueueError::Full { .. }, b)) => batch = b,
                Err((e, _)) => return Err(e),
            }
            space.await;
        }
    }

    /// Take the oldest batch of queue `key`, if any.
    pub fn pop(&self, key: &QueueKey) -> Option<QueuedBatch> {
        let mut inner = self.lock();
        let q = inner.queues.get_mut(key)?;
        let b = q.batches.pop_front()?;
        q.rays -= b.rays.len();
        if q.rays == 0 && q.batches.is_empty() {
            inner.queues.remove(key);
        }
        inner.total -= b.rays.len();
        drop(inner);
        self.space.notify_waiters();
        Some(b)
    }

    /// The routing version of the oldest batch of queue `key`, if any.
    pub fn front_version(&self, key: &QueueKey) -> Option<u64> {
        self.lock()
            .queues
            .get(key)
            .and_then(|q| q.batches.front())
            .map(|b| b.routing_version)
    }

    /// Take the oldest batch of any queue (lowest key first), waiting while every queue
    /// is empty. Returns the domain with the batch.
    pub async fn pop_any(&self) -> (u32, QueuedBatch) {
        loop {
            let data = self.data.notified();
            tokio::pin!(data);
            data.as_mut().enable();
            let first = self.lock().queues.keys().next().cloned();
            if let Some(key) = first
                && let Some(b) = self.pop(&key)
            {
                return (key.domain, b);
            }
            data.await;
        }
    }

    /// Drop every queued ray of `job_id` whose attempt is at most `attempt` (a released
    /// or replaced attempt). Returns how many rays were dropped.
    pub fn drop_job(&self, job_id: &str, attempt: u32) -> usize {
        let mut inner = self.lock();
        let mut dropped = 0;
        inner.queues.retain(|k, q| {
            let gone = &*k.job_id == job_id && k.attempt <= attempt;
            if gone {
                dropped += q.rays;
            }
            !gone
        });
        inner.total -= dropped;
        drop(inner);
        if dropped > 0 {
            self.space.notify_waiters();
        }
        dropped
    }

    /// Rays waiting in queue `key`.
    pub fn len(&self, key: &QueueKey) -> usize {
        self.lock().queues.get(key).map_or(0, |q| q.rays)
    }

    /// Rays waiting in all queues.
    pub fn total(&self) -> usize {
        self.lock().total
    }

    /// Whether no rays wait in any queue.
    pub fn is_empty(&self) -> bool {
        self.lock().total == 0
    }

    /// Every non-empty queue with its length, in key order.
    pub fn lengths(&self) -> Vec<(QueueKey, usize)> {
        self.lock()
            .queues
            .iter()
            .filter(|(_, q)| q.rays > 0)
            .map(|(k, q)| (k.clone(), q.rays))
            .collect()
    }

    /// Rays waiting per domain for one job attempt, in domain order: what a queue
    /// report carries.
    pub fn job_lengths(&self, job_id: &str, attempt: u32) -> Vec<(u32, usize)> {
        self.lock()
            .queues
            .iter()
            .filter(|(k, q)| &*k.job_id == job_id && k.attempt == attempt && q.rays > 0)
            .map(|(k, q)| (k.domain, q.rays))
            .collect()
    }
}
