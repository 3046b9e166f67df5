//! Ray caches on domain walls (docs/caches.md "Walls"; cache.proto): the coordinator's side.
//!
//! The coordinator never answers a ray from a cache. It decides where each job attempt's
//! cache actors live, tells the cache hosts to open and close them, and sums what they
//! and the workers report:
//!
//! - [`hosts`]: stand-alone hosts (`dray cache`, RegisterCacheHost). Workers announce
//!   the host in their own process when they register (`cache_endpoint`).
//! - [`placement`]: hosts and the host of every wall for one attempt, a pure function of
//!   the attempt's hosts and first routing table (walls beside their domain's owner,
//!   else round robin), and the re-placement when a host fails.
//! - [`lifecycle`]: OpenWalls before an attempt's tiles go out (re-placing around hosts
//!   that fail), CloseWalls when it ends, with deadlines.
//! - a job's caches as its actor holds them (knobs, boxes, which attempt is open) are
//!   `crate::job::caches`, with the actor: they read the membership and the job's
//!   schedule, which read this folder.
//! - [`geometry`]: the scene and domain boxes OpenWalls carries.
//! - [`tally`]: the job's `RayCacheStats`, from the hosts and the workers.
//!
//! The placement is in every routing table of the attempt (`cache_hosts`,
//! `wall_hosts`) and does not change while the attempt runs; a new attempt (a lost
//! worker) gets a new placement over the hosts then available.

pub mod geometry;
pub mod hosts;
pub mod lifecycle;
pub mod placement;
pub mod tally;
