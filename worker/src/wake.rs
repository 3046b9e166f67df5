//! How idle tracing threads learn that work arrived: a generation counter and a
//! condition variable. Everything that hands the threads work (queued rays, dealt
//! tiles, a loaded domain, room for camera rays again) notifies it; a thread waits only
//! when it found nothing since the generation it saw, so no notification is missed.

use std::sync::{Condvar, Mutex};
use std::time::Duration;

use dray_sync::lock;

/// Wakes idle tracing threads when work arrives.
#[derive(Default)]
pub(crate) struct Wake {
    generation: Mutex<u64>,
    cond: Condvar,
}

impl Wake {
    pub fn notify(&self) {
        *lock(&self.generation) += 1;
        self.cond.notify_all();
    }

    /// The current generation, to pass to [`Wake::wait`].
    pub fn seen(&self) -> u64 {
        *lock(&self.generation)
    }

    /// Sleep until a notification after `seen`, or `timeout` (a safety net only).
    pub fn wait(&self, seen: u64, timeout: Duration) {
        let g = lock(&self.generation);
        if *g == seen {
            let _ = self.cond.wait_timeout(g, timeout);
        }
    }
}
