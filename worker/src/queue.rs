//! Bounded per-domain ray queues.
//!
//! A worker keeps one queue per domain it owns (DESIGN.md "Scheduling"): rays wait there
//! until the domain's BVH traces them, and the per-domain lengths are what the worker
//! reports to the coordinator's scheduler. Every queue has a capacity in rays, and
//! [`RayQueues::push`] waits while a batch does not fit: that wait is what stalls a peer
//! stream, which stops granting credit, which stalls the sender (see `peer_server`). So a
//! ray explosion fills bounded queues instead of memory.
//!
//! Rays are queued as whole batches ([`QueuedBatch`]), because everything in a batch
//! shares its job and routing version; lengths and capacities still count rays.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_proto::RayRecord;
use dray_proto::v1::RayTicket;
use tokio::sync::Notify;

/// Rays bound for one domain of one job, as they arrived in one batch.
#[derive(Clone, Debug, PartialEq)]
pub struct QueuedBatch {
    /// The job the rays belong to.
    pub job_id: Arc<str>,
    /// Routing-table version the sender used.
    pub routing_version: u64,
    /// The rays, in batch order.
    pub rays: Vec<RayRecord>,
    /// Cache tickets of the rays whose TICKETED flag is set, by index into `rays`.
    pub tickets: Vec<RayTicket>,
}

/// Why rays could not be queued.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QueueError {
    /// The domain has no queue here (this worker does not own it).
    #[error("domain {domain} has no ray queue on this worker")]
    UnknownDomain { domain: u32 },
    /// The batch is larger than the queue could ever hold, so waiting would never end.
    #[error(
        "batch of {rays} rays exceeds the capacity of domain {domain}'s queue ({capacity} rays)"
    )]
    BatchTooLarge {
        domain: u32,
        rays: usize,
        capacity: usize,
    },
    /// The queue is full right now ([`RayQueues::try_push`] only).
    #[error("ray queue of domain {domain} is full")]
    Full { domain: u32 },
}

#[derive(Default)]
struct DomainQueue {
    batches: VecDeque<QueuedBatch>,
    rays: usize,
}

/// One bounded queue per owned domain, shared between the stream servers that fill them
/// and the tracers that drain them.
pub struct RayQueues {
    capacity: usize,
    queues: Mutex<BTreeMap<u32, DomainQueue>>,
    /// Woken whenever rays leave a queue (room for waiting pushes).
    space: Notify,
    /// Woken whenever rays enter a queue (work for waiting pops).
    data: Notify,
    /// Called after every push, for consumers on plain threads (the worker's tracers)
    /// that cannot await `data`.
    on_data: std::sync::OnceLock<Box<dyn Fn() + Send + Sync>>,
}

impl RayQueues {
    /// Queues for `domains`, each holding at most `capacity` rays (at least 1).
    pub fn new(domains: impl IntoIterator<Item = u32>, capacity: usize) -> RayQueues {
        RayQueues {
            capacity: capacity.max(1),
            queues: Mutex::new(
                domains
                    .into_iter()
                    .map(|d| (d, DomainQueue::default()))
                    .collect(),
            ),
            space: Notify::new(),
            data: Notify::new(),
            on_data: std::sync::OnceLock::new(),
        }
    }

    /// Capacity of each domain's queue, in rays.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Whether this worker has a queue for `domain`.
    pub fn owns(&self, domain: u32) -> bool {
        self.lock().contains_key(&domain)
    }

    /// Start queueing rays for `domain` (a newly assigned domain); no-op if present.
    pub fn add_domain(&self, domain: u32) {
        self.lock().entry(domain).or_default();
    }

    fn lock(&self) -> MutexGuard<'_, BTreeMap<u32, DomainQueue>> {
        // A panic while holding the lock cannot leave a queue half-updated (every update
        // is a single push or pop), so a poisoned lock is still consistent.
        self.queues.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Have `f` called after every push that queues rays (once; later calls are ignored).
    pub fn on_data(&self, f: impl Fn() + Send + Sync + 'static) {
        let _ = self.on_data.set(Box::new(f));
    }

    /// Queue `batch` for `domain` if it fits now.
    pub fn try_push(&self, domain: u32, batch: QueuedBatch) -> Result<(), QueueError> {
        match self.try_push_inner(domain, batch) {
            Ok(()) => Ok(()),
            Err((e, _)) => Err(e),
        }
    }

    fn try_push_inner(
        &self,
        domain: u32,
        batch: QueuedBatch,
    ) -> Result<(), (QueueError, QueuedBatch)> {
        let n = batch.rays.len();
        if n > self.capacity {
            return Err((
                QueueError::BatchTooLarge {
                    domain,
                    rays: n,
                    capacity: self.capacity,
                },
                batch,
            ));
        }
        let mut queues = self.lock();
        let Some(q) = queues.get_mut(&domain) else {
            return Err((QueueError::UnknownDomain { domain }, batch));
        };
        if q.rays + n > self.capacity {
            return Err((QueueError::Full { domain }, batch));
        }
        if n > 0 {
            q.rays += n;
            q.batches.push_back(batch);
            drop(queues);
            self.data.notify_waiters();
            if let Some(f) = self.on_data.get() {
                f();
            }
        }
        Ok(())
    }

    /// Queue `batch` for `domain`, waiting while the queue has no room for all of it.
    /// Fails at once for an unknown domain or a batch larger than the capacity.
    pub async fn push(&self, domain: u32, mut batch: QueuedBatch) -> Result<(), QueueError> {
        loop {
            // Register for the wake-up before checking, so a pop between the check and
            // the wait is not missed.
            let space = self.space.notified();
            tokio::pin!(space);
            space.as_mut().enable();
            match self.try_push_inner(domain, batch) {
                Ok(()) => return Ok(()),
                Err((QueueError::Full { .. }, b)) => batch = b,
                Err((e, _)) => return Err(e),
            }
            space.await;
        }
    }

    /// Take the oldest batch of `domain`, if any.
    pub fn pop(&self, domain: u32) -> Option<QueuedBatch> {
        let mut queues = self.lock();
        let q = queues.get_mut(&domain)?;
        let b = q.batches.pop_front()?;
        q.rays -= b.rays.len();
        drop(queues);
        self.space.notify_waiters();
        Some(b)
    }

    /// Take the oldest batch of any domain (lowest domain first), waiting while every
    /// queue is empty. Returns the domain with the batch.
    pub async fn pop_any(&self) -> (u32, QueuedBatch) {
        loop {
            let data = self.data.notified();
            tokio::pin!(data);
            data.as_mut().enable();
            {
                let mut queues = self.lock();
                if let Some((&d, q)) = queues.iter_mut().find(|(_, q)| q.rays > 0)
                    && let Some(b) = q.batches.pop_front()
                {
                    q.rays -= b.rays.len();
                    drop(queues);
                    self.space.notify_waiters();
                    return (d, b);
                }
            }
            data.await;
        }
    }

    /// Rays waiting for `domain` (0 for a domain without a queue).
    pub fn len(&self, domain: u32) -> usize {
        self.lock().get(&domain).map_or(0, |q| q.rays)
    }

    /// Whether no rays wait in any queue.
    pub fn is_empty(&self) -> bool {
        self.lock().values().all(|q| q.rays == 0)
    }

    /// Rays waiting per domain, in domain order: what a queue report carries.
    pub fn lengths(&self) -> Vec<(u32, usize)> {
        self.lock().iter().map(|(&d, q)| (d, q.rays)).collect()
    }
}
