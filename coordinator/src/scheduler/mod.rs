//! The scheduler: where each job's domains live and where its rays go
//! (docs/architecture.md "Scheduling"), after Navrátil et al. 2012.
//!
//! - [`event`]: the event loop. Queue reports, joins, losses and job ends arrive as typed
//!   [`SchedulerEvent`]s, posted by the RPC handlers and the heartbeat reaper, and are
//!   handled one at a time by one task.
//! - [`action`]: what each event does: paces one round per job per
//!   [`SchedulerOptions::round_interval`], restarts a job without a lost worker, adds a
//!   joining worker to running dynamic jobs.
//! - [`policy`]: the schedules (image-plane, domain, dynamic) as pure functions: the first
//!   ownership, how tiles are dealt, the ownership after a loss, and the dynamic round
//!   ([`policy::rebalance`]).
//! - [`table`]: ownership ([`table::Ownership`]) and the versioned table workers receive.
//! - [`state`]: one job's scheduling state (table, budgets, latest queue reports), held
//!   by the ledger next to the job's credit.
//!
//! Every table change is a new version (never reused, across attempts too) sent to every
//! worker of the job as `Assignment{routing}`; JobStats shows the last version and the
//! number of rounds.

pub mod action;
pub mod event;
pub mod policy;
pub mod state;
pub mod table;

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

pub use event::SchedulerEvent;
pub use policy::Schedule;

use crate::ledger::Ledger;

/// Scheduler settings.
#[derive(Clone, Copy, Debug)]
pub struct SchedulerOptions {
    /// Least time between two rounds of one job. Workers report queues about every
    /// 100 ms (`dray_worker`'s `QUEUE_REPORT_INTERVAL`); a round more often than that sees little new, and a table change costs
    /// every worker a swap (and possibly a load).
    pub round_interval: Duration,
}

impl Default for SchedulerOptions {
    fn default() -> SchedulerOptions {
        SchedulerOptions {
            round_interval: Duration::from_millis(200),
        }
    }
}

/// The scheduler's event channel and the loop that serves it.
pub struct Scheduler {
    events: event::EventLoop<SchedulerEvent>,
    ledger: Arc<Ledger>,
    options: SchedulerOptions,
}

impl Scheduler {
    /// A scheduler over `ledger`, not running until [`Scheduler::run`] is polled.
    pub fn new(ledger: Arc<Ledger>, options: SchedulerOptions) -> Scheduler {
        Scheduler {
            events: event::EventLoop::new("scheduler"),
            ledger,
            options,
        }
    }

    /// Queue an event (never blocks).
    pub fn post(&self, e: SchedulerEvent) {
        self.events.post(e);
    }

    /// The settings.
    pub fn options(&self) -> SchedulerOptions {
        self.options
    }

    /// Handle events until the returned future is dropped (the server aborts it on
    /// shutdown). Events posted before it runs are handled when it starts.
    pub fn run(&self) -> impl Future<Output = ()> + Send + use<> {
        self.events.run(action::SchedulerAction::new(
            self.ledger.clone(),
            self.options.round_interval,
        ))
    }
}
