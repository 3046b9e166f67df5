//! The wall actor: one tokio task per wall of an open job attempt, owning that wall's
//! store and tickets (when the job has a ray cache) and its hit map (when it has
//! probability hit maps), driven only through its mailbox.
//!
//! Why an actor per wall: a wall's state is touched by every worker's stream, and
//! giving it a single owner makes every change to it sequential without a lock on the
//! hot path; walls are independent, so a host with many walls uses every core. The
//! host keeps only [`WallHandle`]s (a mailbox sender): it never reads an actor's state
//! except through the stats a `Close` returns. The mailbox is bounded, so a burst of
//! lookups waits at the sender instead of queueing without limit.

use std::sync::atomic::Ordering;
use std::sync::{Arc, RwLock};

use dray_core::ray::{FLAG_COARSE, RayRecord};
use dray_core::wall::WallFrame;
use glam::Vec3;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tracing::Instrument;

use crate::phm::{Advice, HitMap, Learned, MapView};
use crate::settings::{CacheSettings, HitMapSettings};
use crate::stats::{WallStats, worth_logging};
use crate::store::{Entry, EntryKey, InsertError, Query, WallStore};
use crate::store_view::{SharedStore, StoreConsults, StoreView};
use crate::tickets::{Applied, Return, TicketBook, TicketRay};

use crate::wire::{
    CODE_HIT, CODE_MISS, CODE_OCCLUDED, CODE_SHADED, CODE_SKIP, CODE_TICKET, OPTION_ANSWER,
    OPTION_PHM, OPTION_ROOM, OPTION_TICKET, PROBE,
};

/// Rays an actor handles between yields, so one huge lookup does not hold a runtime
/// thread away from the other walls' actors and the streams for long.
const YIELD_EVERY: usize = 1024;

/// One ray reaching a wall, with its lookup options.
#[derive(Clone, Copy, Debug)]
pub struct LookupRay {
    pub ray: RayRecord,
    pub options: u32,
}

/// The answer to one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Outcome {
    /// Not answered, no ticket: the worker traces the ray on, exactly.
    Miss,
    /// Answered with this radiance.
    Hit([f32; 3]),
    /// Not answered; the ray carries this ticket on.
    Ticket(u64),
    /// The hit map predicts a miss: the ray skips the domain behind the wall.
    Skip,
    /// The hit map predicts a hit for an occlusion ray: it is occluded.
    Occluded,
    /// The hit map predicts a hit and shades (`phm.shade`): the ray is answered with
    /// the cell's mean radiance.
    Shaded([f32; 3]),
    /// As [`Outcome::Miss`], and the ray goes on as a probe.
    Probe,
    /// As [`Outcome::Ticket`], and the ray goes on as a probe.
    ProbeTicket(u64),
}

impl Outcome {
    /// The byte in `CacheAnswers.outcomes`.
    pub fn code(&self) -> u8 {
        match self {
            Outcome::Miss => CODE_MISS,
            Outcome::Hit(_) => CODE_HIT,
            Outcome::Ticket(_) => CODE_TICKET,
            Outcome::Skip => CODE_SKIP,
            Outcome::Occluded => CODE_OCCLUDED,
            Outcome::Shaded(_) => CODE_SHADED,
            Outcome::Probe => CODE_MISS + PROBE,
            Outcome::ProbeTicket(_) => CODE_TICKET + PROBE,
        }
    }

    /// The ticket the ray carries on, if any.
    pub fn ticket(&self) -> Option<u64> {
        match self {
            Outcome::Ticket(t) | Outcome::ProbeTicket(t) => Some(*t),
            _ => None,
        }
    }

    /// This outcome for a ray that goes on as a probe; `None` when the ray does not go
    /// on into the domain (answered, skipped or occluded), so there is nothing to probe.
    fn probed(self) -> Option<Outcome> {
        match self {
            Outcome::Miss | Outcome::Probe => Some(Outcome::Probe),
            Outcome::Ticket(t) | Outcome::ProbeTicket(t) => Some(Outcome::ProbeTicket(t)),
            Outcome::Hit(_) | Outcome::Skip | Outcome::Occluded | Outcome::Shaded(_) => None,
        }
    }
}

/// A message to a wall actor.
pub(crate) enum Command {
    /// Answer these rays; the reply holds one outcome per ray, in order.
    Lookup {
        rays: Vec<LookupRay>,
        reply: oneshot::Sender<Vec<Outcome>>,
    },
    /// Apply these returns (ticket slot, return); the reply says they are applied and
    /// holds the entries they stored (for the wall's other replicas).
    Returns {
        returns: Vec<(u32, Return)>,
        reply: oneshot::Sender<Vec<Entry>>,
    },
    /// Store these entries, which another replica of the wall stored; the reply says
    /// they are stored.
    Insert {
        entries: Vec<Entry>,
        reply: oneshot::Sender<()>,
    },
    /// Teach the hit map these probe outcomes (cell, hit byte); the reply says they
    /// are applied.
    Outcomes {
        outcomes: Vec<(u32, u8)>,
        reply: oneshot::Sender<()>,
    },
    /// Merge another copy's outcomes into the hit map: (cell, hits, misses); the reply
    /// says they are applied.
    Merge {
        cells: Vec<(u32, u32, u32)>,
        reply: oneshot::Sender<()>,
    },
    /// Report the counters and stop.
    Close { reply: oneshot::Sender<WallStats> },
}

/// What an actor needs to know about its wall and its job.
#[derive(Clone, Debug)]
pub(crate) struct WallSpec {
    pub wall: u32,
    pub frame: WallFrame,
    pub outer: bool,
    /// The box of the domain the wall belongs to (the hit map bins against it).
    pub domain: (Vec3, Vec3),
    /// The job's ray cache; `None` when it has none (then the wall only has a map).
    pub settings: Option<Arc<CacheSettings>>,
    /// The job's hit maps; `None` when it has none.
    pub phm: Option<Arc<HitMapSettings>>,
    pub max_entries: usize,
    pub max_open_tickets: usize,
    pub mailbox: usize,
}

/// The host's side of an actor: its mailbox.
#[derive(Clone, Debug)]
pub(crate) struct WallHandle {
    tx: mpsc::Sender<Command>,
    pub outer: bool,
    /// A view of the wall's hit map for consulting it in place (dense maps only).
    pub map: Option<MapView>,
    /// A view of the wall's ray cache for answering rays in place.
    pub cache: Option<StoreView>,
}

impl WallHandle {
    /// Post a command. False when the actor has stopped (its job closed meanwhile).
    pub async fn send(&self, cmd: Command) -> bool {
        self.tx.send(cmd).await.is_ok()
    }
}

/// Start the actor for one wall, inside `span`.
pub(crate) fn spawn(spec: WallSpec, span: tracing::Span) -> (WallHandle, JoinHandle<()>) {
    let (tx, rx) = mpsc::channel(spec.mailbox.max(1));
    let handle = WallHandle {
        tx,
        outer: spec.outer,
        map: None,
        cache: None,
    };
    let (lo, hi) = spec.domain;
    let map = spec
        .phm
        .as_deref()
        .map(|s| HitMap::new(s, spec.wall, lo, hi));
    let store: SharedStore = Arc::new(RwLock::new(WallStore::for_radius(
        spec.max_entries,
        spec.settings.as_ref().map_or(0.0, |s| s.radius),
    )));
    let store_consults = Arc::new(StoreConsults::default());
    let handle = WallHandle {
        map: map.as_ref().and_then(HitMap::view),
        cache: spec
            .settings
            .as_ref()
            .map(|s| StoreView::new(spec.frame, s.clone(), store.clone(), store_consults.clone())),
        ..handle
    };
    let actor = WallActor {
        store,
        store_consults,
        tickets: TicketBook::new(spec.wall, spec.max_open_tickets),
        map,
        stats: WallStats::default(),
        spec,
    };
    let task = tokio::spawn(actor.run(rx).instrument(span));
    (handle, task)
}

struct WallActor {
    spec: WallSpec,
    /// The wall's entries: written by this actor only, read by it and by the
    /// [`StoreView`]s of the worker in this process.
    store: SharedStore,
    /// Lookups made through the views.
    store_consults: Arc<StoreConsults>,
    tickets: TicketBook,
    map: Option<HitMap>,
    stats: WallStats,
}

impl WallActor {
    async fn run(mut self, mut rx: mpsc::Receiver<Command>) {
        tracing::debug!("wall actor started");
        while let Some(cmd) = rx.recv().await {
            match cmd {
                Command::Lookup { rays, reply } => {
                    let mut out = Vec::with_capacity(rays.len());
                    for chunk in rays.chunks(YIELD_EVERY) {
                        out.extend(chunk.iter().map(|r| self.lookup(r)));
                        if rays.len() > YIELD_EVERY {
                            tokio::task::yield_now().await;
                        }
                    }
                    // The asker may have gone (its stream ended): nothing to do then.
                    let _ = reply.send(out);
                }
                Command::Returns { returns, reply } => {
                    let stored: Vec<Entry> = returns
                        .into_iter()
                        .filter_map(|(slot, ret)| self.apply(slot, ret))
                        .collect();
                    let _ = reply.send(stored);
                }
                Command::Insert { entries, reply } => {
                    for entry in entries {
                        self.store_entry(entry);
                    }
                    let _ = reply.send(());
                }
                Command::Outcomes { outcomes, reply } => {
                    for chunk in outcomes.chunks(YIELD_EVERY) {
                        for &(cell, hit) in chunk {
                            self.learn(cell, hit);
                        }
                        if outcomes.len() > YIELD_EVERY {
                            tokio::task::yield_now().await;
                        }
                    }
                    let _ = reply.send(());
                }
                Command::Merge { cells, reply } => {
                    for &(cell, hits, misses) in &cells {
                        self.merge(cell, hits, misses);
                    }
                    let _ = reply.send(());
                }
                Command::Close { reply } => {
                    let stats = self.stats();
                    tracing::debug!(?stats, "wall actor closed");
                    let _ = reply.send(stats);
                    return;
                }
            }
        }
        tracing::debug!("wall actor stopped: its job attempt was dropped");
    }

    fn stats(&self) -> WallStats {
        let mut stats = WallStats {
            tickets_open: self.tickets.open_count() as u64,
            entries: self.store().len() as u64,
            entries_dropped: self.store().dropped,
            ..self.stats
        };
        // Lookups made in place, through the store's views.
        let c = &self.store_consults;
        stats.lookups += c.lookups.load(Ordering::Relaxed);
        stats.hits += c.hits.load(Ordering::Relaxed);
        stats.skipped += c.skipped.load(Ordering::Relaxed);
        if let Some(map) = &self.map {
            let (hit, miss) = map.decided();
            // Consults made in place, through the map's views.
            let c = map.consults();
            let get = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
            stats.phm.lookups += get(&c.lookups);
            stats.phm.unplaced += get(&c.unplaced);
            stats.phm.skipped += get(&c.skipped);
            stats.phm.occluded += get(&c.occluded);
            stats.phm.probes += get(&c.probes);
            stats.phm.cells = u64::from(map.len());
            stats.phm.cells_decided_hit = hit;
            stats.phm.cells_decided_miss = miss;
        }
        stats
    }

    /// Answer one ray. The hit map speaks first (a ray it skips, occludes or shades
    /// never reaches the ray cache, so it is not a cache lookup); every other ray gets
    /// the ray cache's answer, marked as a probe when the map wants to learn from it and
    /// the ray goes on into the domain. A map that shades asks for a ticket on such a
    /// ray of a kind it shades (when the ray has room for one), to learn the radiance it
    /// returns; the ray cache's ticket, if it asks for one too, is the same ticket.
    fn lookup(&mut self, r: &LookupRay) -> Outcome {
        let mut probe = false;
        let mut shade_cell = None;
        if r.options & OPTION_PHM != 0
            && let Some(map) = &mut self.map
        {
            self.stats.phm.lookups += 1;
            let traced = match map.advise(&r.ray) {
                Advice::Skip => {
                    self.stats.phm.skipped += 1;
                    return Outcome::Skip;
                }
                Advice::Occlude => {
                    self.stats.phm.occluded += 1;
                    return Outcome::Occluded;
                }
                Advice::Shade(rgb) => {
                    self.stats.phm.shaded += 1;
                    return Outcome::Shaded(rgb);
                }
                Advice::Probe => {
                    probe = true;
                    true
                }
                Advice::Trace => true,
                Advice::Unplaced => {
                    self.stats.phm.unplaced += 1;
                    false
                }
            };
            if traced && r.options & OPTION_ROOM != 0 && map.shades(r.ray.kind) {
                shade_cell = map.ask_shading(&r.ray);
            }
        }
        let outcome = self.cache_lookup(r, shade_cell);
        if !probe {
            return outcome;
        }
        match outcome.probed() {
            Some(o) => {
                self.stats.phm.probes += 1;
                o
            }
            None => outcome,
        }
    }

    /// The ray cache's answer: a hit from the store, else a ticket if asked for (by
    /// the ray cache, or by the map for `shade_cell`), else a miss. On a wall without a
    /// ray cache, a ticket for the map or a miss.
    fn cache_lookup(&mut self, r: &LookupRay, shade_cell: Option<u32>) -> Outcome {
        let settings = self.spec.settings.as_deref();
        let answer = settings.is_some() && r.options & OPTION_ANSWER != 0;
        let cache_ticket = settings.is_some() && r.options & OPTION_TICKET != 0;
        if answer {
            self.stats.lookups += 1;
        }
        if !answer && !cache_ticket && shade_cell.is_none() {
            return Outcome::Miss;
        }
        let ray = &r.ray;
        // The crossing point and the direction are what the store is keyed by; a ray
        // that has neither (parallel to the wall, zero or non-finite direction) can
        // neither be answered nor stored.
        let (Some(point), Some(dir)) = (
            self.spec.frame.crossing(ray.origin, ray.dir),
            ray.dir.try_normalize(),
        ) else {
            if answer || cache_ticket {
                self.stats.skipped += 1;
            }
            return Outcome::Miss;
        };
        if answer && let Some(settings) = settings {
            let q = Query {
                point,
                dir,
                radius: settings.radius,
                cos_min: settings.cos_min,
                retrieve: settings.retrieve,
            };
            let found = self.store().lookup(&q);
            if let Some(radiance) = found {
                self.stats.hits += 1;
                return Outcome::Hit(radiance);
            }
        }
        if !cache_ticket && shade_cell.is_none() {
            return Outcome::Miss;
        }
        let opened = self.tickets.open(TicketRay {
            key: EntryKey::of(ray),
            point,
            dir,
            weight: ray.weight,
            credit: ray.credit,
            coarse: ray.flags & FLAG_COARSE != 0,
            cache: cache_ticket,
            cell: shade_cell,
        });
        match opened {
            Ok(id) => {
                self.stats.tickets_opened += 1;
                Outcome::Ticket(id)
            }
            Err(e) => {
                self.stats.tickets_refused += 1;
                if worth_logging(self.stats.tickets_refused) {
                    tracing::warn!(
                        error = %e,
                        refused = self.stats.tickets_refused,
                        "miss without a ticket"
                    );
                }
                Outcome::Miss
            }
        }
    }

    /// Teach the map one probe's outcome. Outcomes that do not fit (no map on this
    /// wall, a cell beyond the map, a hit byte other than 0 or 1) are counted and
    /// dropped: they mean a bug or a mismatch elsewhere, and must not take the host
    /// down.
    fn learn(&mut self, cell: u32, hit: u8) {
        let learned = match (&mut self.map, hit) {
            (Some(map), 0 | 1) => map.learn(cell, hit == 1),
            _ => Learned::OutOfRange,
        };
        let phm = &mut self.stats.phm;
        match learned {
            Learned::Counted => phm.outcomes += 1,
            Learned::Frozen => {
                phm.outcomes += 1;
                phm.outcomes_frozen += 1;
            }
            Learned::OutOfRange => {
                phm.outcomes_rejected += 1;
                if worth_logging(phm.outcomes_rejected) {
                    tracing::warn!(
                        cell,
                        hit,
                        has_map = self.map.is_some(),
                        count = phm.outcomes_rejected,
                        "hit-map outcome that fits no cell of this wall's map (ignored)"
                    );
                }
            }
        }
    }

    /// Merge another copy's counts at `cell` into the map. Like [`Self::learn`], counts
    /// that fit no cell are counted as rejected and dropped.
    fn merge(&mut self, cell: u32, hits: u32, misses: u32) {
        let learned = match &mut self.map {
            Some(map) => map.merge(cell, hits, misses),
            None => Learned::OutOfRange,
        };
        let n = u64::from(hits) + u64::from(misses);
        let phm = &mut self.stats.phm;
        match learned {
            Learned::Counted => phm.outcomes_merged += n,
            Learned::Frozen => {
                phm.outcomes_merged += n;
                phm.outcomes_frozen += n;
            }
            Learned::OutOfRange => {
                phm.outcomes_rejected += n;
                if worth_logging(phm.outcomes_rejected) {
                    tracing::warn!(
                        cell,
                        has_map = self.map.is_some(),
                        count = phm.outcomes_rejected,
                        "hit-map merge for a cell beyond this wall's map (ignored)"
                    );
                }
            }
        }
    }

    /// The store, to read.
    fn store(&self) -> std::sync::RwLockReadGuard<'_, WallStore> {
        dray_sync::read(&self.store)
    }

    /// Store one entry; false when the store refused it (full, or not finite).
    fn store_entry(&mut self, entry: Entry) -> bool {
        let mut store = dray_sync::write(&self.store);
        match store.insert(entry) {
            Ok(()) => true,
            Err(InsertError::Full) => {
                if worth_logging(store.dropped) {
                    tracing::warn!(
                        dropped = store.dropped,
                        entries = store.len(),
                        "wall store full: radiance dropped"
                    );
                }
                false
            }
            // A ticket's point and direction were checked when it opened, and a
            // replica's entry was checked where it was made; harmless either way: the
            // radiance is just not stored.
            Err(InsertError::NotFinite) => false,
        }
    }

    /// Apply one return to its ticket; a ticket whose credit is whole closes and, when
    /// the ray cache asked for it and the job fills the caches or the ray was of the
    /// coarse pass, stores its radiance (returned, so other replicas of the wall can
    /// store it too); when the hit map asked for it (`phm.shade`), the radiance is
    /// added to the averaged shading of the ray's cell. A tainted ticket does neither.
    fn apply(&mut self, slot: u32, ret: Return) -> Option<Entry> {
        let fill = self.spec.settings.as_ref().is_some_and(|s| s.fill);
        match self.tickets.apply(slot, ret, fill) {
            Applied::Pending => None,
            Applied::Closed { entry, shading } => {
                self.stats.tickets_closed += 1;
                if let (Some((cell, rgb)), Some(map)) = (shading, &mut self.map)
                    && map.learn_shading(cell, rgb)
                {
                    self.stats.phm.shading_learned += 1;
                }
                let entry = entry?;
                if self.store_entry(entry) {
                    self.stats.tickets_stored += 1;
                    Some(entry)
                } else {
                    None
                }
            }
            Applied::Unknown => {
                self.stats.stray_returns += 1;
                if worth_logging(self.stats.stray_returns) {
                    tracing::warn!(
                        slot,
                        count = self.stats.stray_returns,
                        "return for a ticket that is not open (ignored)"
                    );
                }
                None
            }
            Applied::OverCredit => {
                self.stats.over_credit += 1;
                if worth_logging(self.stats.over_credit) {
                    tracing::warn!(
                        slot,
                        credit = %ret.credit,
                        count = self.stats.over_credit,
                        "return exceeds its ticket's credit (ignored)"
                    );
                }
                None
            }
        }
    }
}
