//! The cache host: the table of open job attempts and their wall actors, and the
//! `CacheService` on top of it.
//!
//! The host is a router. It validates each request, splits a message's rays, returns
//! and hit-map outcomes by wall, posts one command to each wall's actor, waits for the
//! replies and puts the answers back in ray order. It never touches an actor's state, so the table
//! lock is held only to look up or change which actors exist, never while an actor
//! works.
//!
//! Rays for a job, attempt or wall this host does not serve are answered "miss, no
//! ticket" (the worker then traces them exactly) instead of failing the worker's
//! stream: routing tables change while a job runs, and one stale lookup must not cost
//! the worker every other lookup on its stream.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, RwLock};

use dray_core::ray::{RAY_RECORD_MAX_BYTES, check_count, decode_rays};
use dray_proto::v1::cache_service_server::{CacheService, CacheServiceServer};
use dray_proto::v1::{
    CacheAnswers, CacheLookups, CacheRequest, CacheResponse, CloseWallsRequest, CloseWallsResponse,
    OpenWallsRequest, OpenWallsResponse, PhmMerge, PhmOutcomes, PhmStats, RayCacheStats, TicketAck,
    TicketReturns, WallEntries, cache_request, cache_response,
};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::{Request, Response, Status, Streaming};

use crate::actor::{self, Command, LookupRay, Outcome, WallHandle, WallSpec};
use crate::entry_record::{ENTRY_RECORD_BYTES, decode_entries, encode_entry};
use crate::error::HostError;
use crate::job::{self, JobAttempt, OpenPlan};
use crate::phm::MapView;
use crate::stats::{WallStats, log_point_between};
use crate::store::{DEFAULT_MAX_ENTRIES, Entry};
use crate::store_view::StoreView;
use crate::ticket_id;
use crate::tickets::{DEFAULT_MAX_OPEN_TICKETS, Return};

/// Largest gRPC message the host accepts or sends: a lookup of 64 Ki rays (records
/// of at most 64 bytes plus up to 10 bytes of wall and option varints each), with room to spare.
/// (A `PhmOutcomes` costs at most 11 bytes an outcome, so this admits over 500 Ki.)
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024 * (RAY_RECORD_MAX_BYTES + 32);

/// Limits of one cache host.
#[derive(Clone, Debug)]
pub struct CacheHostConfig {
    /// Entries each wall stores at most; more are dropped and counted.
    pub max_entries_per_wall: usize,
    /// Tickets each wall keeps open at most; past it misses get no ticket.
    pub max_open_tickets_per_wall: usize,
    /// Commands waiting in each actor's mailbox before senders wait.
    pub mailbox: usize,
}

impl Default for CacheHostConfig {
    fn default() -> Self {
        CacheHostConfig {
            max_entries_per_wall: DEFAULT_MAX_ENTRIES,
            max_open_tickets_per_wall: DEFAULT_MAX_OPEN_TICKETS,
            mailbox: 64,
        }
    }
}

/// An open job attempt and the tasks of its actors.
struct JobEntry {
    job: Arc<JobAttempt>,
    tasks: Vec<JoinHandle<()>>,
}

struct Inner {
    config: CacheHostConfig,
    /// Job id → its open attempt (at most one per job).
    jobs: Mutex<HashMap<String, JobEntry>>,
}

/// A cache host: serves `dray.v1.CacheService` for the walls it is asked to open.
///
/// Cloning is cheap and every clone is the same host, so the same host can be served
/// over gRPC and called directly (an embedded, single-process render).
#[derive(Clone)]
pub struct CacheHost {
    inner: Arc<Inner>,
}

impl Default for CacheHost {
    fn default() -> Self {
        CacheHost::new()
    }
}

impl std::fmt::Debug for CacheHost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CacheHost")
            .field("config", &self.inner.config)
            .field("jobs", &self.lock().len())
            .finish()
    }
}

impl CacheHost {
    /// A host with the default limits and no open jobs.
    pub fn new() -> CacheHost {
        CacheHost::with_config(CacheHostConfig::default())
    }

    /// A host with the given limits.
    pub fn with_config(config: CacheHostConfig) -> CacheHost {
        CacheHost {
            inner: Arc::new(Inner {
                config,
                jobs: Mutex::new(HashMap::new()),
            }),
        }
    }

    /// The tonic service, with message limits sized for full lookups.
    pub fn into_service(self) -> CacheServiceServer<CacheHost> {
        CacheServiceServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, JobEntry>> {
        // A panic elsewhere cannot leave the table half-changed (every change is one
        // insert or remove), so a poisoned lock is still good.
        dray_sync::lock(&self.inner.jobs)
    }

    /// The open attempt `attempt` of `job_id`, if that is the one open here.
    fn job(&self, job_id: &str, attempt: u32) -> Option<Arc<JobAttempt>> {
        self.lock()
            .get(job_id)
            .filter(|e| e.job.attempt == attempt)
            .map(|e| Arc::clone(&e.job))
    }

    fn spawn_walls(
        &self,
        job: &JobAttempt,
        walls: &[u32],
    ) -> Vec<(u32, WallHandle, JoinHandle<()>)> {
        let c = &self.inner.config;
        walls
            .iter()
            .filter_map(|&wall| {
                let (frame, outer) = job.layout.wall(wall)?;
                let domain = job.layout.domain_of(wall)?;
                let spec = WallSpec {
                    wall,
                    frame,
                    outer,
                    domain,
                    settings: job.settings.clone(),
                    phm: job.phm.clone(),
                    max_entries: c.max_entries_per_wall,
                    max_open_tickets: c.max_open_tickets_per_wall,
                    mailbox: c.mailbox,
                };
                let span = tracing::debug_span!(
                    "wall_actor",
                    job = %job.job_id,
                    attempt = job.attempt,
                    wall,
                    outer
                );
                let (handle, task) = actor::spawn(spec, span);
                Some((wall, handle, task))
            })
            .collect()
    }

    /// Open a job attempt's walls (`OpenWalls`). Returns the number of actors the
    /// attempt has here.
    #[tracing::instrument(skip_all, fields(job = %req.job_id, attempt = req.attempt))]
    pub async fn open_walls(&self, req: OpenWallsRequest) -> Result<OpenWallsResponse, HostError> {
        let OpenPlan {
            settings,
            phm,
            layout,
            walls,
            replica,
        } = job::plan(&req)?;
        let (ray_cache, hit_maps) = (settings.is_some(), phm.is_some());
        let replaced = {
            let mut jobs = self.lock();
            match jobs.get_mut(&req.job_id) {
                Some(e) if e.job.attempt > req.attempt => {
                    return Err(HostError::StaleAttempt {
                        job_id: req.job_id,
                        attempt: req.attempt,
                        open: e.job.attempt,
                    });
                }
                Some(e) if e.job.attempt == req.attempt => {
                    // Idempotent, and a re-open may add walls; but the same attempt with
                    // different settings or bounds is a caller bug worth surfacing.
                    if e.job.settings.as_deref() != settings.as_ref()
                        || e.job.phm.as_deref() != phm.as_ref()
                        || e.job.layout != layout
                    {
                        return Err(HostError::Conflict {
                            job_id: req.job_id,
                            attempt: req.attempt,
                        });
                    }
                    let job = Arc::clone(&e.job);
                    job.replica.store(replica, Ordering::Relaxed);
                    let missing: Vec<u32> = {
                        let map = dray_sync::read(&job.walls);
                        walls
                            .iter()
                            .copied()
                            .filter(|w| !map.contains_key(w))
                            .collect()
                    };
                    let spawned = self.spawn_walls(&job, &missing);
                    let mut map = dray_sync::write(&job.walls);
                    for (wall, handle, task) in spawned {
                        map.insert(wall, handle);
                        e.tasks.push(task);
                    }
                    let actors = u32::try_from(map.len()).unwrap_or(u32::MAX);
                    tracing::debug!(actors, added = missing.len(), "walls re-opened");
                    return Ok(OpenWallsResponse { actors });
                }
                _ => {}
            }
            let job = Arc::new(JobAttempt {
                job_id: req.job_id.clone(),
                attempt: req.attempt,
                settings: settings.map(Arc::new),
                phm: phm.map(Arc::new),
                layout,
                replica: replica.into(),
                walls: RwLock::new(HashMap::new()),
                stray_returns: Default::default(),
                stray_outcomes: Default::default(),
            });
            let spawned = self.spawn_walls(&job, &walls);
            let mut tasks = Vec::with_capacity(spawned.len());
            {
                let mut map = dray_sync::write(&job.walls);
                for (wall, handle, task) in spawned {
                    map.insert(wall, handle);
                    tasks.push(task);
                }
            }
            jobs.insert(req.job_id.clone(), JobEntry { job, tasks })
        };
        if let Some(old) = replaced {
            tracing::info!(
                old_attempt = old.job.attempt,
                "newer attempt replaces the open one"
            );
            let (stats, phm, _) = close_entry(old).await;
            tracing::debug!(?stats, ?phm, "replaced attempt closed");
        }
        let actors = u32::try_from(walls.len()).unwrap_or(u32::MAX);
        tracing::info!(actors, ray_cache, phm = hit_maps, "walls opened");
        Ok(OpenWallsResponse { actors })
    }

    /// Close a job attempt (`CloseWalls`): stop its actors and sum their statistics:
    /// `stats` when the job has a ray cache, `phm` when it has hit maps.
    #[tracing::instrument(skip_all, fields(job = %req.job_id, attempt = req.attempt))]
    pub async fn close_walls(
        &self,
        req: CloseWallsRequest,
    ) -> Result<CloseWallsResponse, HostError> {
        let entry = {
            let mut jobs = self.lock();
            match jobs.get(&req.job_id) {
                Some(e) if e.job.attempt == req.attempt => jobs.remove(&req.job_id),
                _ => None,
            }
        };
        let Some(entry) = entry else {
            return Err(HostError::UnknownJob {
                job_id: req.job_id,
                attempt: req.attempt,
            });
        };
        let (stats, phm, total) = close_entry(entry).await;
        if phm.is_some() {
            let m = &total.phm;
            tracing::info!(
                lookups = m.lookups,
                unplaced = m.unplaced,
                skipped = m.skipped,
                occluded = m.occluded,
                probes = m.probes,
                outcomes = m.outcomes,
                outcomes_frozen = m.outcomes_frozen,
                outcomes_rejected = m.outcomes_rejected,
                cells = m.cells,
                cells_decided_hit = m.cells_decided_hit,
                cells_decided_miss = m.cells_decided_miss,
                "hit maps closed"
            );
        }
        if stats.is_some() {
            tracing::info!(
                lookups = total.lookups,
                hits = total.hits,
                tickets_opened = total.tickets_opened,
                tickets_closed = total.tickets_closed,
                tickets_stored = total.tickets_stored,
                tickets_open = total.tickets_open,
                entries = total.entries,
                entries_dropped = total.entries_dropped,
                over_credit = total.over_credit,
                stray_returns = total.stray_returns,
                "walls closed"
            );
        }
        Ok(CloseWallsResponse { stats, phm })
    }

    /// Answer one message of an `Exchange` stream. Public so an in-process worker can
    /// use the host without gRPC; an error ends the stream it came from.
    pub async fn handle(&self, req: CacheRequest) -> Result<CacheResponse, HostError> {
        let msg = match req.msg {
            Some(cache_request::Msg::Lookups(l)) => {
                cache_response::Msg::Answers(self.lookups(l).await?)
            }
            Some(cache_request::Msg::Returns(r)) => cache_response::Msg::Ack(self.returns(r).await),
            Some(cache_request::Msg::Entries(e)) => {
                cache_response::Msg::Ack(self.entries(e).await?)
            }
            Some(cache_request::Msg::Outcomes(o)) => {
                cache_response::Msg::Ack(self.outcomes(o).await?)
            }
            Some(cache_request::Msg::Merge(m)) => {
                cache_response::Msg::Ack(self.merge_message(m).await?)
            }
            None => return Err(HostError::Empty),
        };
        Ok(CacheResponse { msg: Some(msg) })
    }

    /// Answer a `CacheLookups`, ray for ray.
    pub async fn lookups(&self, l: CacheLookups) -> Result<CacheAnswers, HostError> {
        let sequence = l.sequence;
        let bad = |detail: String| HostError::BadLookups { sequence, detail };
        let n = check_count(u64::from(l.count), l.records.len())
            .map_err(|source| HostError::Record { sequence, source })?;
        if l.walls.len() != n {
            return Err(bad(format!("{} walls for {n} rays", l.walls.len())));
        }
        if l.options.len() != n {
            return Err(bad(format!("{} options for {n} rays", l.options.len())));
        }
        let rays =
            decode_rays(&l.records, n).map_err(|source| HostError::Record { sequence, source })?;
        let rays: Vec<WallLookup> = rays
            .into_iter()
            .zip(&l.walls)
            .zip(&l.options)
            .map(|((ray, &wall), &options)| WallLookup {
                wall,
                ray: LookupRay { ray, options },
            })
            .collect();
        let outcomes = self.lookup_rays(&l.job_id, l.attempt, rays).await;
        let mut answers = CacheAnswers {
            sequence,
            outcomes: outcomes.iter().map(Outcome::code).collect(),
            radiance: Vec::new(),
            tickets: Vec::new(),
        };
        for o in &outcomes {
            if let Outcome::Hit(rgb) | Outcome::Shaded(rgb) = o {
                answers.radiance.extend_from_slice(rgb);
            }
            if let Some(t) = o.ticket() {
                answers.tickets.push(t);
            }
        }
        Ok(answers)
    }

    /// Answer rays at walls of attempt `attempt` of `job_id`, one outcome per ray in
    /// order: what a `CacheLookups` does, for a worker in this process (no encoding, no
    /// copy into records). Rays for a job, attempt or wall not served here are misses
    /// without a ticket.
    pub async fn lookup_rays(
        &self,
        job_id: &str,
        attempt: u32,
        rays: Vec<WallLookup>,
    ) -> Vec<Outcome> {
        let n = rays.len();
        let mut outcomes = vec![Outcome::Miss; n];
        let Some(job) = self.job(job_id, attempt) else {
            tracing::debug!(job = %job_id, attempt, rays = n, "lookups for a job not open here: all miss");
            return outcomes;
        };
        // Group by wall, keeping each ray's position; one command per actor.
        let mut groups: BTreeMap<u32, (Vec<usize>, Vec<LookupRay>)> = BTreeMap::new();
        for (i, l) in rays.into_iter().enumerate() {
            let g = groups.entry(l.wall).or_default();
            g.0.push(i);
            g.1.push(l.ray);
        }
        let handles = job.handles(groups.keys().copied());
        let mut pending = Vec::with_capacity(groups.len());
        for ((_, (positions, rays)), handle) in groups.into_iter().zip(handles) {
            // A wall not served here: those rays stay "miss, no ticket".
            let Some(handle) = handle else { continue };
            let (reply, rx) = oneshot::channel();
            if handle.send(Command::Lookup { rays, reply }).await {
                pending.push((positions, rx));
            }
        }
        for (positions, rx) in pending {
            // An actor that stopped meanwhile (its job closed) leaves misses.
            let Ok(answers) = rx.await else { continue };
            for (p, o) in positions.into_iter().zip(answers) {
                if let Some(slot) = outcomes.get_mut(p) {
                    *slot = o;
                }
            }
        }
        let replica = job.replica.load(Ordering::Relaxed);
        if replica != 0 {
            // A replica's tickets name it, so returns from anywhere find it.
            for o in &mut outcomes {
                match o {
                    Outcome::Ticket(t) | Outcome::ProbeTicket(t) => {
                        *t = ticket_id::with_replica(*t, replica);
                    }
                    _ => {}
                }
            }
        }
        outcomes
    }

    /// Apply a `TicketReturns`; the ack is built only once every actor has applied its
    /// share. Returns for a job not open here are acknowledged and dropped (the job may
    /// have closed while they were on their way).
    pub async fn returns(&self, r: TicketReturns) -> TicketAck {
        let returns = r.returns.iter().map(|t| (t.ticket, Return::from(t)));
        let stored = self.return_tickets(&r.job_id, r.attempt, returns).await;
        let mut ack = TicketAck {
            sequence: r.sequence,
            walls: Vec::with_capacity(stored.len()),
            entries: Vec::with_capacity(stored.len() * ENTRY_RECORD_BYTES),
        };
        for (wall, entry) in &stored {
            ack.walls.push(*wall);
            encode_entry(entry, &mut ack.entries);
        }
        ack
    }

    /// Apply ticket returns (ticket, what is returned to it) of attempt `attempt` of
    /// `job_id`, returning once every actor has applied its share: what a
    /// `TicketReturns` does, for a worker in this process. Returns for a job not open
    /// here, or for tickets another replica issued, are dropped. Returns, for
    /// replicated walls, the entries the returns stored (wall, entry), in wall order,
    /// for the wall's other replicas; nothing otherwise.
    pub async fn return_tickets(
        &self,
        job_id: &str,
        attempt: u32,
        returns: impl IntoIterator<Item = (u64, Return)>,
    ) -> Vec<(u32, Entry)> {
        let Some(job) = self.job(job_id, attempt) else {
            tracing::debug!(job = %job_id, attempt, "returns for a job not open here: dropped");
            return Vec::new();
        };
        let replica = job.replica.load(Ordering::Relaxed);
        let mut groups: BTreeMap<u32, Vec<(u32, Return)>> = BTreeMap::new();
        let mut foreign = 0u64;
        for (ticket, ret) in returns {
            if ticket_id::ticket_replica(ticket) != replica {
                foreign += 1;
                continue;
            }
            groups
                .entry(ticket_id::ticket_wall(ticket))
                .or_default()
                .push((ticket_id::ticket_slot(ticket), ret));
        }
        if foreign > 0 {
            let before = job.stray_returns.fetch_add(foreign, Ordering::Relaxed);
            if log_point_between(before, before + foreign) {
                tracing::warn!(job = %job.job_id, replica, count = before + foreign, "ticket returns for another replica's tickets (ignored)");
            }
        }
        let handles = job.handles(groups.keys().copied());
        let mut pending = Vec::with_capacity(groups.len());
        for ((wall, returns), handle) in groups.into_iter().zip(handles) {
            let Some(handle) = handle else {
                let n = returns.len() as u64;
                let before = job.stray_returns.fetch_add(n, Ordering::Relaxed);
                if log_point_between(before, before + n) {
                    tracing::warn!(job = %job.job_id, wall, count = before + n, "ticket returns for a wall not served here (ignored)");
                }
                continue;
            };
            let (reply, rx) = oneshot::channel();
            if handle.send(Command::Returns { returns, reply }).await {
                pending.push((wall, rx));
            }
        }
        let mut stored = Vec::new();
        for (wall, rx) in pending {
            if let Ok(entries) = rx.await
                && replica != 0
            {
                stored.extend(entries.into_iter().map(|e| (wall, e)));
            }
        }
        stored
    }

    /// Apply a `WallEntries`: store another replica's entries here.
    pub async fn entries(&self, e: WallEntries) -> Result<TicketAck, HostError> {
        let sequence = e.sequence;
        let entries = decode_entries(&e.entries, e.walls.len())
            .map_err(|source| HostError::Entries { sequence, source })?;
        self.insert_entries(&e.job_id, e.attempt, e.walls.into_iter().zip(entries))
            .await;
        Ok(TicketAck {
            sequence,
            ..TicketAck::default()
        })
    }

    /// Store entries (wall, entry) that another replica of the walls stored, returning
    /// once every actor has them: what a `WallEntries` does, for a worker in this
    /// process. Entries for a job or wall not open here are dropped.
    pub async fn insert_entries(
        &self,
        job_id: &str,
        attempt: u32,
        entries: impl IntoIterator<Item = (u32, Entry)>,
    ) {
        let Some(job) = self.job(job_id, attempt) else {
            tracing::debug!(job = %job_id, attempt, "entries for a job not open here: dropped");
            return;
        };
        let mut groups: BTreeMap<u32, Vec<Entry>> = BTreeMap::new();
        for (wall, entry) in entries {
            groups.entry(wall).or_default().push(entry);
        }
        let handles = job.handles(groups.keys().copied());
        let mut pending = Vec::with_capacity(groups.len());
        for ((_, entries), handle) in groups.into_iter().zip(handles) {
            let Some(handle) = handle else { continue };
            let (reply, rx) = oneshot::channel();
            if handle.send(Command::Insert { entries, reply }).await {
                pending.push(rx);
            }
        }
        for rx in pending {
            let _ = rx.await;
        }
    }

    /// Apply a `PhmOutcomes`; the ack is built only once every actor has applied its
    /// share. Mismatched lengths are a protocol error (the stream ends); outcomes for a
    /// job not open here, or a wall not served here, are acknowledged and dropped (the
    /// job may have closed, or the routing changed, while they were on their way).
    pub async fn outcomes(&self, o: PhmOutcomes) -> Result<TicketAck, HostError> {
        let sequence = o.sequence;
        let n = o.walls.len();
        if o.cells.len() != n || o.hits.len() != n {
            return Err(HostError::BadOutcomes {
                sequence,
                detail: format!(
                    "{n} walls, {} cells and {} hits must be as many",
                    o.cells.len(),
                    o.hits.len()
                ),
            });
        }
        let outcomes = o
            .walls
            .iter()
            .zip(&o.cells)
            .zip(&o.hits)
            .map(|((&wall, &cell), &hit)| (wall, cell, hit));
        self.learn(&o.job_id, o.attempt, outcomes).await;
        Ok(TicketAck {
            sequence,
            ..TicketAck::default()
        })
    }

    /// Teach the hit maps probe outcomes (wall, cell, hit byte) of attempt `attempt` of
    /// `job_id`, returning once every actor has applied its share: what a `PhmOutcomes`
    /// does, for a worker in this process. Outcomes for a job or wall not served here
    /// are dropped.
    pub async fn learn(
        &self,
        job_id: &str,
        attempt: u32,
        outcomes: impl IntoIterator<Item = (u32, u32, u8)>,
    ) {
        let Some(job) = self.job(job_id, attempt) else {
            tracing::debug!(job = %job_id, attempt, "hit-map outcomes for a job not open here: dropped");
            return;
        };
        let mut groups: BTreeMap<u32, Vec<(u32, u8)>> = BTreeMap::new();
        for (wall, cell, hit) in outcomes {
            groups.entry(wall).or_default().push((cell, hit));
        }
        let handles = job.handles(groups.keys().copied());
        let mut pending = Vec::with_capacity(groups.len());
        for ((wall, outcomes), handle) in groups.into_iter().zip(handles) {
            let Some(handle) = handle else {
                let n = outcomes.len() as u64;
                let before = job.stray_outcomes.fetch_add(n, Ordering::Relaxed);
                if log_point_between(before, before + n) {
                    tracing::warn!(job = %job.job_id, wall, count = before + n, "hit-map outcomes for a wall not served here (ignored)");
                }
                continue;
            };
            let (reply, rx) = oneshot::channel();
            if handle.send(Command::Outcomes { outcomes, reply }).await {
                pending.push(rx);
            }
        }
        for rx in pending {
            let _ = rx.await;
        }
    }
}

impl CacheHost {
    /// Views of the ray caches and hit maps of attempt `attempt` of `job_id` on this
    /// host, for a worker in this process to consult in place ([`StoreView`],
    /// [`MapView`]); `None` while the attempt is not open here.
    pub fn wall_views(&self, job_id: &str, attempt: u32) -> Option<Arc<WallViews>> {
        let job = self.job(job_id, attempt)?;
        let mut views = WallViews::default();
        for (wall, handle) in job.all_handles() {
            let i = wall as usize;
            if views.maps.len() <= i {
                views.maps.resize(i + 1, None);
                views.caches.resize(i + 1, None);
            }
            views.maps[i] = handle.map;
            views.caches[i] = handle.cache;
        }
        Some(Arc::new(views))
    }

    /// Apply a `PhmMerge` (another worker's outcomes, counted per cell); the ack is
    /// built once every actor has applied its share. Mismatched lengths are a protocol
    /// error; merges for a job not open here, or a wall not served here, are
    /// acknowledged and dropped, as outcomes are.
    pub async fn merge_message(&self, m: PhmMerge) -> Result<TicketAck, HostError> {
        let sequence = m.sequence;
        let n = m.walls.len();
        if m.cells.len() != n || m.hits.len() != n || m.misses.len() != n {
            return Err(HostError::BadOutcomes {
                sequence,
                detail: format!(
                    "merge: {n} walls, {} cells, {} hits and {} misses must be as many",
                    m.cells.len(),
                    m.hits.len(),
                    m.misses.len()
                ),
            });
        }
        let cells = (0..n).map(|i| (m.walls[i], m.cells[i], m.hits[i], m.misses[i]));
        self.merge(&m.job_id, m.attempt, cells).await;
        Ok(TicketAck {
            sequence,
            ..TicketAck::default()
        })
    }

    /// Merge another worker's outcomes (wall, cell, hits, misses) of attempt `attempt`
    /// of `job_id` into this host's copies of the maps, returning once every actor has
    /// applied its share: what a `PhmMerge` does, for a worker in this process.
    pub async fn merge(
        &self,
        job_id: &str,
        attempt: u32,
        cells: impl IntoIterator<Item = (u32, u32, u32, u32)>,
    ) {
        let Some(job) = self.job(job_id, attempt) else {
            tracing::debug!(job = %job_id, attempt, "hit-map merge for a job not open here: dropped");
            return;
        };
        let mut groups: BTreeMap<u32, Vec<(u32, u32, u32)>> = BTreeMap::new();
        for (wall, cell, hits, misses) in cells {
            groups.entry(wall).or_default().push((cell, hits, misses));
        }
        let handles = job.handles(groups.keys().copied());
        let mut pending = Vec::with_capacity(groups.len());
        for ((wall, cells), handle) in groups.into_iter().zip(handles) {
            let Some(handle) = handle else {
                let n: u64 = cells.iter().map(|c| u64::from(c.1) + u64::from(c.2)).sum();
                let before = job.stray_outcomes.fetch_add(n, Ordering::Relaxed);
                if log_point_between(before, before + n) {
                    tracing::warn!(job = %job.job_id, wall, count = before + n, "hit-map merge for a wall not served here (ignored)");
                }
                continue;
            };
            let (reply, rx) = oneshot::channel();
            if handle.send(Command::Merge { cells, reply }).await {
                pending.push(rx);
            }
        }
        for rx in pending {
            let _ = rx.await;
        }
    }
}

/// The walls of one job attempt on a host that can be consulted in place, by wall.
#[derive(Debug, Default)]
pub struct WallViews {
    maps: Vec<Option<MapView>>,
    caches: Vec<Option<StoreView>>,
}

impl WallViews {
    /// The view of `wall`'s hit map, if this host serves it with one.
    pub fn map(&self, wall: u32) -> Option<&MapView> {
        self.maps.get(wall as usize)?.as_ref()
    }

    /// The view of `wall`'s ray cache, if this host serves it with one.
    pub fn cache(&self, wall: u32) -> Option<&StoreView> {
        self.caches.get(wall as usize)?.as_ref()
    }
}

/// One ray at one wall, as a worker in the host's process hands it over.
#[derive(Clone, Copy, Debug)]
pub struct WallLookup {
    /// The wall (`6 * domain + face`).
    pub wall: u32,
    /// The ray and its lookup options.
    pub ray: LookupRay,
}

/// Stop every actor of a job attempt and sum their counters, into the job's
/// `RayCacheStats` (when it has a ray cache) and `PhmStats` (when it has hit maps), and
/// into a total of the host-side counters.
async fn close_entry(entry: JobEntry) -> (Option<RayCacheStats>, Option<PhmStats>, WallStats) {
    let JobEntry { job, tasks } = entry;
    let handles = job.all_handles();
    // Post every Close first, so the actors wind down in parallel.
    let mut replies = Vec::with_capacity(handles.len());
    for (wall, handle) in &handles {
        let (reply, rx) = oneshot::channel();
        if handle.send(Command::Close { reply }).await {
            replies.push((*wall, handle.outer, rx));
        }
    }
    let mut stats = job.settings.as_ref().map(|_| RayCacheStats::default());
    let mut phm = job.phm.as_ref().map(|_| PhmStats::default());
    let mut total = WallStats::default();
    for (wall, outer, rx) in replies {
        match rx.await {
            Ok(s) => {
                if let Some(stats) = stats.as_mut() {
                    s.add_to(outer, stats);
                }
                if let Some(phm) = phm.as_mut() {
                    s.phm.add_to(phm);
                }
                total.merge(&s);
            }
            Err(_) => tracing::warn!(wall, "wall actor stopped before reporting its stats"),
        }
    }
    total.stray_returns += job.stray_returns.load(Ordering::Relaxed);
    total.phm.outcomes_rejected += job.stray_outcomes.load(Ordering::Relaxed);
    drop(handles);
    for task in tasks {
        if let Err(e) = task.await {
            tracing::error!(error = %e, "wall actor failed");
        }
    }
    (stats, phm, total)
}

#[tonic::async_trait]
impl CacheService for CacheHost {
    async fn open_walls(
        &self,
        request: Request<OpenWallsRequest>,
    ) -> Result<Response<OpenWallsResponse>, Status> {
        Ok(Response::new(
            CacheHost::open_walls(self, request.into_inner()).await?,
        ))
    }

    async fn close_walls(
        &self,
        request: Request<CloseWallsRequest>,
    ) -> Result<Response<CloseWallsResponse>, Status> {
        Ok(Response::new(
            CacheHost::close_walls(self, request.into_inner()).await?,
        ))
    }

    type ExchangeStream = crate::exchange::ResponseStream;

    async fn exchange(
        &self,
        request: Request<Streaming<CacheRequest>>,
    ) -> Result<Response<Self::ExchangeStream>, Status> {
        let peer = request
            .remote_addr()
            .map(|a| a.to_string())
            .unwrap_or_default();
        Ok(Response::new(crate::exchange::start(
            self.clone(),
            request.into_inner(),
            peer,
        )))
    }
}
