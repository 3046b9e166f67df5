//! A read-only view of one wall's ray cache for the tracing threads of the worker in the
//! cache's own process (sender placement): a ray that may only be *answered* at the wall
//! (no ticket to open: the main pass of a job with `fill=false`, whose caches the coarse
//! pass filled and froze) is looked up right where it crosses the wall, with no message
//! to the wall's actor and no wait for its answer.
//!
//! The store stays the actor's: it alone inserts (under the write lock, during the
//! coarse pass and replica copies); views take the read lock for one query. With
//! `fill=false` the main pass never writes, so its lookups never wait, and they see
//! exactly the store the actor would have searched: the same answers, the same bits.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

use dray_core::ray::RayRecord;
use dray_core::wall::WallFrame;

use crate::settings::CacheSettings;
use crate::store::{Query, WallStore};

/// Lookups made in place through a wall's [`StoreView`]s, counted where they happen and
/// added to the wall's statistics when it closes.
#[derive(Debug, Default)]
pub struct StoreConsults {
    pub lookups: AtomicU64,
    pub hits: AtomicU64,
    /// Rays that could not be looked up (parallel to the wall, no direction).
    pub skipped: AtomicU64,
}

/// A wall's store, shared between its actor (the only writer) and its views.
pub(crate) type SharedStore = Arc<RwLock<WallStore>>;

/// See the module documentation.
#[derive(Clone)]
pub struct StoreView {
    frame: WallFrame,
    settings: Arc<CacheSettings>,
    store: SharedStore,
    consults: Arc<StoreConsults>,
}

impl std::fmt::Debug for StoreView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StoreView")
            .field("frame", &self.frame)
            .field("settings", &self.settings)
            .finish_non_exhaustive()
    }
}

impl StoreView {
    pub(crate) fn new(
        frame: WallFrame,
        settings: Arc<CacheSettings>,
        store: SharedStore,
        consults: Arc<StoreConsults>,
    ) -> StoreView {
        StoreView {
            frame,
            settings,
            store,
            consults,
        }
    }

    /// The radiance the cache answers `ray` with, as the wall's actor would answer a
    /// lookup that may answer and not ticket; `None` on a miss.
    pub fn answer(&self, ray: &RayRecord) -> Option<[f32; 3]> {
        let c = &self.consults;
        c.lookups.fetch_add(1, Ordering::Relaxed);
        let (Some(point), Some(dir)) = (
            self.frame.crossing(ray.origin, ray.dir),
            ray.dir.try_normalize(),
        ) else {
            c.skipped.fetch_add(1, Ordering::Relaxed);
            return None;
        };
        let q = Query {
            point,
            dir,
            radius: self.settings.radius,
            cos_min: self.settings.cos_min,
            retrieve: self.settings.retrieve,
        };
        let found = dray_sync::read(&self.store).lookup(&q);
        if found.is_some() {
            c.hits.fetch_add(1, Ordering::Relaxed);
        }
        found
    }
}
