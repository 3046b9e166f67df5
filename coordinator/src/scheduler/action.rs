//! The coordinator's [`EventAction`]: what each [`SchedulerEvent`] does to the jobs in the
//! [`Ledger`]. The ledger holds each job's [`JobSchedule`](super::state::JobSchedule) and
//! sends the commands (under its lock, so a job's credit, attempt and table change
//! together); this action decides *when*: it paces rounds per job and orders losses and
//! joins.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::event::{EventAction, SchedulerEvent};
use super::state::RoundOutcome;
use crate::ledger::Ledger;

/// Handles scheduler events against the ledger.
pub struct SchedulerAction {
    ledger: Arc<Ledger>,
    interval: Duration,
    /// Jobs with fresh reports whose round waits for the pacing interval.
    due: BTreeMap<String, Instant>,
}

impl SchedulerAction {
    /// An action over `ledger` running at most one round per job every `interval`.
    pub fn new(ledger: Arc<Ledger>, interval: Duration) -> SchedulerAction {
        SchedulerAction {
            ledger,
            interval,
            due: BTreeMap::new(),
        }
    }

    fn try_round(&mut self, job_id: &str, now: Instant) {
        match self.ledger.round(job_id, now, self.interval) {
            Some(RoundOutcome::NotBefore(at)) => {
                self.due.insert(job_id.to_string(), at);
            }
            _ => {
                self.due.remove(job_id);
            }
        }
    }
}

impl EventAction<SchedulerEvent> for SchedulerAction {
    fn on_start(&mut self) {
        tracing::debug!(interval = ?self.interval, "scheduler started");
    }

    fn on_receive(&mut self, event: SchedulerEvent, now: Instant) {
        match event {
            SchedulerEvent::QueueReport { job_id } => {
                // A round already waiting for its time covers this report too.
                if !self.due.contains_key(&job_id) {
                    self.try_round(&job_id, now);
                }
            }
            SchedulerEvent::WorkerJoined(w) => self.ledger.worker_joined(&w),
            SchedulerEvent::WorkerLost(w) => self.ledger.worker_lost(&w),
            SchedulerEvent::JobEnded { job_id } => {
                self.due.remove(&job_id);
            }
        }
    }

    fn next_timer(&self) -> Option<Instant> {
        self.due.values().min().copied()
    }

    fn on_timer(&mut self, now: Instant) {
        let ready: Vec<String> = self
            .due
            .iter()
            .filter(|(_, at)| **at <= now)
            .map(|(j, _)| j.clone())
            .collect();
        for j in ready {
            self.try_round(&j, now);
        }
    }
}
