//! The scheduler: where each job's domains live and where its rays go
//! (docs/architecture.md "Scheduling"), after Navrátil et al. 2012. Pure state and
//! policy: each job's actor ([`crate::job`]) holds its [`state::JobSchedule`], feeds it
//! queue reports, joins and losses, and runs its rounds on its own timer, one round per
//! [`SchedulerOptions::round_interval`] at most.
//!
//! - [`auto`]: the default, `auto`: replicated when the scene fits every worker's budget,
//!   dynamic when it does not, chosen when the job starts, with the reason.
//! - [`policy`]: the schedules (replicated, image-plane, domain, dynamic) as pure
//!   functions: the first
//!   ownership, how tiles are dealt, the ownership after a loss, and the dynamic round
//!   ([`policy::rebalance`]).
//! - who owns which domain is [`crate::ownership::Ownership`], outside this folder
//!   because cache placement reads it too.
//! - [`table`]: the versioned table workers receive.
//! - [`state`]: one job's scheduling state (table, budgets, latest queue reports).
//!
//! Every table change is a new version (never reused, across attempts too) sent to every
//! worker of the job as `Assignment{routing}`; JobStats shows the last version and the
//! number of rounds.

pub mod auto;
pub mod policy;
pub mod state;
pub mod table;

use std::time::Duration;

pub use policy::{Schedule, ScheduleRequest};

/// Scheduler settings.
#[derive(Clone, Copy, Debug)]
pub struct SchedulerOptions {
    /// Least time between two rounds of one job. Workers report queues about every
    /// 100 ms (`dray_worker`'s `QUEUE_REPORT_INTERVAL`); a round more often than that
    /// sees little new, and a table change costs every worker a swap (and possibly a
    /// load).
    pub round_interval: Duration,
}

impl Default for SchedulerOptions {
    fn default() -> SchedulerOptions {
        SchedulerOptions {
            round_interval: Duration::from_millis(200),
        }
    }
}
