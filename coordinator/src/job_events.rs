//! A job's event log: what happened to it (queued, started, a worker lost and its tiles
//! traced again, a pass finished, failed and why, cancelled, retried from another job),
//! oldest first, so an operator can tell why a job took three attempts or why it
//! failed without reading the coordinator's logs (issue 42). Each event is posted to
//! the job store as it is recorded, so a restarted coordinator shows the same history
//! (`store/events.rs`), and GetJob, ListJobs and the dashboard show it (`Job.events`).
//!
//! The log also holds the job's lineage (`Job.retried_from`) and counts its attempts:
//! one per STARTED event, whatever started it (the first run, a lost worker's tiles
//! traced again, a run again after a restart).

use std::sync::{Mutex, MutexGuard};
use std::time::SystemTime;

use dray_proto::v1::{JobEvent, JobEventKind};

use crate::store::{JobStore, Op, from_millis, to_millis};

/// Most events one job keeps: a job that loses workers over and over must not grow
/// without bound. Beyond it, events are counted (`dropped`) and the last one says so.
pub const MAX_EVENTS: usize = 256;

/// One job's events, lineage and attempt count.
#[derive(Debug, Default)]
pub struct EventLog {
    inner: Mutex<Log>,
}

#[derive(Debug, Default)]
struct Log {
    events: Vec<JobEvent>,
    retried_from: String,
    /// Events not kept beyond [`MAX_EVENTS`].
    dropped: u64,
}

impl EventLog {
    /// The log a job had in the store (oldest first) and the job it was retried from.
    pub fn restored(events: Vec<JobEvent>, retried_from: Option<String>) -> EventLog {
        EventLog {
            inner: Mutex::new(Log {
                events,
                retried_from: retried_from.unwrap_or_default(),
                dropped: 0,
            }),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Log> {
        dray_sync::lock(&self.inner)
    }

    /// Record an event of job `id` now, and post it to `store` when the job is kept.
    pub fn record(
        &self,
        id: &str,
        store: Option<&std::sync::Arc<JobStore>>,
        kind: JobEventKind,
        message: String,
    ) {
        // To the millisecond, as the store keeps it: the log reads the same after a
        // restart.
        let now = from_millis(to_millis(SystemTime::now()));
        let mut g = self.lock();
        if g.events.len() >= MAX_EVENTS {
            g.dropped += 1;
            tracing::debug!(job = %id, ?kind, "event log full; event not kept: {message}");
            return;
        }
        let message = if g.events.len() + 1 == MAX_EVENTS {
            format!("{message} (the log keeps {MAX_EVENTS} events; later ones are not kept)")
        } else {
            message
        };
        tracing::info!(job = %id, kind = kind.as_str_name(), "{message}");
        g.events.push(JobEvent {
            at: Some(now.into()),
            kind: kind as i32,
            message: message.clone(),
        });
        drop(g);
        if let Some(store) = store {
            store.post(Op::Event {
                id: id.to_string(),
                at_ms: to_millis(now),
                kind: kind as i32,
                message,
            });
        }
    }

    /// Set the job this one runs again, and post it to `store`.
    pub fn set_retried_from(&self, id: &str, store: Option<&std::sync::Arc<JobStore>>, from: &str) {
        self.lock().retried_from = from.to_string();
        if let Some(store) = store {
            store.post(Op::RetriedFrom {
                id: id.to_string(),
                from: from.to_string(),
            });
        }
    }

    /// The events, oldest first.
    pub fn events(&self) -> Vec<JobEvent> {
        self.lock().events.clone()
    }

    /// The job this one runs again ("" for a submitted job).
    pub fn retried_from(&self) -> String {
        self.lock().retried_from.clone()
    }

    /// Attempts started: the STARTED events.
    pub fn attempts(&self) -> u32 {
        let n = self
            .lock()
            .events
            .iter()
            .filter(|e| e.kind == JobEventKind::Started as i32)
            .count();
        u32::try_from(n).unwrap_or(u32::MAX)
    }

    /// Events not kept because the log was full.
    pub fn dropped(&self) -> u64 {
        self.lock().dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attempts_count_started_events_and_the_log_is_bounded() {
        let log = EventLog::default();
        log.record("j", None, JobEventKind::Queued, "queued".into());
        assert_eq!(log.attempts(), 0);
        log.record("j", None, JobEventKind::Started, "attempt 1".into());
        log.record("j", None, JobEventKind::WorkerLost, "w lost".into());
        log.record("j", None, JobEventKind::Started, "attempt 2".into());
        assert_eq!(log.attempts(), 2);
        for _ in 0..2 * MAX_EVENTS {
            log.record("j", None, JobEventKind::PassFinished, "pass".into());
        }
        let events = log.events();
        assert_eq!(events.len(), MAX_EVENTS);
        assert!(events[MAX_EVENTS - 1].message.contains("not kept"));
        assert_eq!(log.dropped(), (2 * MAX_EVENTS + 4 - MAX_EVENTS) as u64);
    }
}
