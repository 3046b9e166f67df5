//! dray's cache actors: ray caches (Little 2011) and probability hit maps (Bolstad
//! 2017) on domain walls (docs/caches.md "Walls").
//!
//! A *cache host* serves `dray.v1.CacheService` and holds one actor per wall of each
//! open job attempt. A wall is face `f` of domain `d` (index `6 * d + f`), seen by the
//! rays entering `d` through it. A ray reaching a wall is answered from the wall's
//! store when a stored crossing lies within the job's radius and angle; otherwise it
//! leaves with a ticket, and when the credit of everything its descendants hand back is
//! whole, the radiance along it (`sum / weight`) is stored for the next ray. A job with
//! hit maps also keeps, per wall, how often rays entering through each cell hit
//! something inside the domain: a cell sure of a miss lets rays skip the domain, one
//! sure of a hit answers occlusion rays, and the rest are traced as probes whose
//! outcomes teach the map.
//!
//! How the parts fit:
//! - [`settings`]: the job's cache knobs, parsed once into typed values (the
//!   coordinator, the workers and the hosts all read them there).
//! - [`bounds`]: the largest values a job may ask for, shared by the coordinator and
//!   the workers.
//! - [`store`]: one wall's crossings over a k-d tree, with answers that do not depend
//!   on the order entries arrived in.
//! - [`tickets`]: one wall's open tickets, closed exactly once by credit.
//! - [`phm`]: one wall's hit map: counts per cell, decisions, deterministic re-probes.
//! - [`shading`]: the radiance a hit map's probes returned, per cell (`phm.shade`).
//! - [`actor`]: the wall actor, a task with a mailbox owning a store, its tickets and
//!   its hit map.
//! - [`host`]: the job table and `CacheService`; `exchange` runs one worker's stream.
//! - [`stats`]: the counters summed into `RayCacheStats` and `PhmStats` at `CloseWalls`.
//! - [`server`]: gRPC serving with health and reflection.
//!
//! To host caches: `CacheHost::new().serve(listener, shutdown)` (or [`serve`]); to use a
//! host in-process, call [`CacheHost::open_walls`], [`CacheHost::handle`] and
//! [`CacheHost::close_walls`] directly.

pub mod actor;
pub mod bounds;
pub mod entry_record;
pub mod error;
mod exchange;
pub mod host;
pub(crate) mod job;
pub mod phm;
pub mod server;
pub mod settings;
pub mod shading;
pub mod stats;
pub mod store;
pub mod store_view;
pub mod ticket_id;
pub mod tickets;
pub mod wire;

pub use actor::{LookupRay, Outcome};
pub use error::HostError;
pub use exchange::ResponseStream;
pub use host::{CacheHost, CacheHostConfig, MAX_MESSAGE_BYTES, WallLookup, WallViews};
pub use job::MAX_WALLS_PER_JOB;
pub use phm::MapView;
pub use phm::{Advice, Decision, HitMap};
pub use server::{ServeError, serve};
pub use settings::{
    CacheSettings, CoarseSampling, HitMapSettings, Named, PhmMode, Placement, Retrieve,
    SettingsError, WallSettings,
};
pub use stats::{MapStats, WallStats};
pub use store::Entry;
pub use store_view::StoreView;
pub use tickets::Return;
pub use wire::{OPTION_ANSWER, OPTION_PHM, OPTION_TICKET, PROBE};
