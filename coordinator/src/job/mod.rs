//! Jobs running on workers, one actor per job (docs/architecture.md "The coordinator").
//!
//! - [`registry`]: routes calls to jobs by id and holds every job's actor.
//! - [`actor`]: one job's task: its mailbox, round timer, stall timeout and cache walls.
//! - [`adaptive`]: adaptive sampling: which tiles stop after a pass.
//! - [`ahead`]: when a job's workers trace passes ahead, and the tiles they hold.
//! - [`caches`]: the job's ray caches as its actor holds them: knobs, boxes, which
//!   attempt's walls are open.
//! - [`backlog`]: a replicated job's tiles dealt on demand, so joiners take a share.
//! - [`entry`]: a job as its readers see it: the read-only view its record publishes.
//! - [`event`]: what an actor is told.
//! - [`running`]: what an actor owns: the ledger, the film and the statistics below,
//!   the schedule, the passes, the caches; and the commands they cause.
//! - [`credit`]: the credit ledger: every tile's credit and which tiles are complete.
//! - [`film`]: the exact fixed-point film and the pass images.
//! - [`statistics`]: the counters the reports carry, published as `JobStats`.
//! - [`record`]: the one writer of a job's public record, from submission to its end
//!   (the entry readers hold is its read-only view).
//! - [`report`]: a contribution report, checked and applied.
//! - [`sequences`]: which report sequences of the current attempt were applied.
//! - [`view`]: the snapshot of domains and queues a job gives `ListWorkers`.

pub mod actor;
pub mod adaptive;
pub mod ahead;
pub mod backlog;
pub mod caches;
pub mod credit;
pub mod entry;
pub mod event;
pub mod film;
pub mod record;
pub mod registry;
pub mod report;
pub mod running;
pub mod sequences;
pub mod statistics;
pub mod status;
pub mod view;

pub use actor::ActorConfig;
pub use event::{JobEvent, ReportReply};
pub use record::JobRecord;
pub use registry::JobRegistry;
pub use report::ReportOutcome;
pub use running::{JobPlan, RunningJob, TILES_PER_MESSAGE};
pub use view::JobView;
