//! Jobs running on workers, one actor per job (docs/architecture.md "The coordinator").
//!
//! - [`registry`]: routes calls to jobs by id and holds every job's actor.
//! - [`actor`]: one job's task: its mailbox, round timer, stall timeout and cache walls.
//! - [`adaptive`]: adaptive sampling: which tiles stop after a pass.
//! - [`ahead`]: when a job's workers trace passes ahead, and the tiles they hold.
//! - [`backlog`]: a replicated job's tiles dealt on demand, so joiners take a share.
//! - [`event`]: what an actor is told.
//! - [`running`]: what an actor owns: tiles and credit, the film, the schedule, the
//!   caches, the counters it publishes; and the commands they cause.
//! - [`report`]: a contribution report, checked and applied.
//! - [`view`]: the snapshot of domains and queues a job gives `ListWorkers`.

pub mod actor;
pub mod adaptive;
pub mod ahead;
pub mod backlog;
pub mod event;
pub mod registry;
pub mod report;
pub mod running;
pub mod view;

pub use actor::ActorConfig;
pub use event::{JobEvent, ReportReply};
pub use registry::JobRegistry;
pub use report::ReportOutcome;
pub use running::{JobPlan, RunningJob, TILES_PER_MESSAGE};
pub use view::JobView;
