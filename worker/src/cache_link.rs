//! The worker's links to cache hosts (ray caches, `cache.proto`).
//!
//! One link per host, owned by one task: lookups (rays at walls), ticket returns and
//! hit-map outcomes go out in order, and the host answers each message in order. A host
//! in another process is reached over one long-lived `CacheService.Exchange` stream (the
//! task matches answers to what it sent with a FIFO); the host in this process, when
//! there is one, through its actors' mailboxes ([`dray_cache::CacheHost::lookup_rays`]
//! and friends): no protobuf, no HTTP/2, no copy into records, and the same actors give
//! the same answers. Only the gRPC link counts bytes: they are the bytes between
//! processes. A worker never
//! answers a ray from a cache itself: it only applies the actor's answer —
//! - a **hit**: the ray's weight x the cached radiance goes to its pixel, its credit
//!   back to its tile (both also to its tickets, marked as from a cache);
//! - a **miss**: the ray goes on to the domain behind the wall, with the new ticket if
//!   the actor opened one.
//!
//! A host that cannot be reached, or whose stream breaks, is *dead* for the rest of
//! this worker's life: its pending lookups and every later one go straight on to their
//! domains (traced exactly: "bypassed"), its ticket returns are dropped (those tickets
//! can never close), and every job that used it names it in its report. Tracing never
//! waits for a cache host: lookups leave through an unbounded channel counted in the
//! job's rays in flight, which bounds them like every other ray.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::sync::Mutex;
use std::time::Duration;

use dray_cache::entry_record::{ENTRY_RECORD_BYTES, decode_entries};
use dray_cache::wire::{
    CODE_HIT, CODE_MISS, CODE_OCCLUDED, CODE_SHADED, CODE_SKIP, CODE_TICKET, PROBE,
};
use dray_cache::{CacheHost, Entry, LookupRay, Outcome, Return, WallLookup};
use dray_proto::v1::cache_service_client::CacheServiceClient;
use dray_proto::v1::{
    CacheAnswers, CacheRequest, CacheResponse, TicketAck, TicketReturn, cache_response,
};
use glam::Vec3;
use prost::Message;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tokio_stream::wrappers::ReceiverStream;

use crate::cache_requests::{
    entries_request, lookup_options, lookup_payload, lookup_record, lookups_request, merge_request,
    outcomes_request, returns_request,
};
use crate::jobs::{Job, Report};
use crate::member::Member;
use crate::tracer::{Lookup, NoDomains, Outbox};
use crate::traffic::Kind;
use crate::wake::Wake;
use dray_sync::lock;

/// Lookups per message: 4096 rays of at most 64 bytes, far inside gRPC's message limit.
const LOOKUPS_PER_MESSAGE: usize = 4096;
/// Returns per message (about 40 bytes each).
const RETURNS_PER_MESSAGE: usize = 16 * 1024;
/// Entries per message (68 bytes each, and a wall).
const ENTRIES_PER_MESSAGE: usize = 16 * 1024;
/// Bytes a ticket return costs on the wire, roughly (for the job's byte count).
const RETURN_BYTES: u64 = 40;
/// Bytes a hit-map outcome costs on the wire, roughly (wall, cell and hit varints).
const OUTCOME_BYTES: u64 = 9;

/// Work for one host's stream.
pub(crate) enum CacheMessage {
    /// Rays at walls of this host.
    Lookups { job: Arc<Job>, lookups: Vec<Lookup> },
    /// Ticket returns; `done` says whether the host applied them, with the entries
    /// they stored on a replicated wall (for the wall's other replicas).
    Returns {
        job: Arc<Job>,
        returns: Vec<TicketReturn>,
        done: oneshot::Sender<Acked>,
    },
    /// Entries another replica of these walls stored (wall, entry); `done` says whether
    /// the host stored them.
    Entries {
        job: Arc<Job>,
        entries: Vec<(u32, Entry)>,
        done: oneshot::Sender<Acked>,
    },
    /// Outcomes of hit-map probes: (wall, cell, hit). Nothing waits for them.
    Outcomes {
        job: Arc<Job>,
        outcomes: Vec<(u32, u32, bool)>,
    },
    /// Outcomes gathered for another worker's copies of the maps, per cell: (wall,
    /// cell, hits, misses). Nothing waits for them.
    Merge {
        job: Arc<Job>,
        cells: crate::map_merge::Merge,
    },
}

/// What a host did with returns or entries: `None` when they did not reach it (the
/// host is dead), else the entries the returns stored on replicated walls.
pub(crate) type Acked = Option<Vec<(u32, Entry)>>;

/// Where rays go on once a cache host answered them, or could not be reached: the
/// worker's delivery ([`crate::links`]), which also feeds the lookups here. A trait, so
/// that this file does not import the delivery back.
pub(crate) trait Onward: Send + Sync + 'static {
    /// Deliver `out` of `job` as a tracing step's results, with `report` (counters of
    /// the caller's own).
    fn deliver_onward(self: Arc<Self>, job: &Arc<Job>, out: Outbox, report: Report);
}

/// The links to cache hosts.
pub(crate) struct CacheLinks {
    state: Arc<State>,
    tasks: Mutex<JoinSet<()>>,
    runtime: tokio::runtime::Handle,
}

/// What the links' tasks share with [`CacheLinks`].
struct State {
    /// By endpoint.
    links: Mutex<HashMap<String, mpsc::UnboundedSender<CacheMessage>>>,
    /// Hosts found unreachable.
    dead: Mutex<HashSet<String>>,
    /// The cache host in this process and the endpoint it is announced at: messages for
    /// that endpoint go to it directly.
    local: Option<(String, CacheHost)>,
    /// Who the worker is (named in failures and logs).
    member: Arc<Member>,
    /// How to reach cache hosts (token, TLS).
    net: dray_net::ClientOptions,
    /// Answered rays are work for the tracing threads: they hear of it here.
    wake: Arc<Wake>,
}

/// What a link's task (and a message failed on its way) needs: the links' state, and
/// where the rays it answers go on.
#[derive(Clone)]
struct Ctx {
    state: Arc<State>,
    onward: Arc<dyn Onward>,
}

impl Ctx {
    fn deliver(&self, job: &Arc<Job>, out: Outbox, report: Report) {
        self.onward.clone().deliver_onward(job, out, report);
    }
}

impl CacheLinks {
    pub fn new(
        runtime: tokio::runtime::Handle,
        local: Option<(String, CacheHost)>,
        member: Arc<Member>,
        net: dray_net::ClientOptions,
        wake: Arc<Wake>,
    ) -> CacheLinks {
        CacheLinks {
            state: Arc::new(State {
                links: Mutex::new(HashMap::new()),
                dead: Mutex::new(HashSet::new()),
                local,
                member,
                net,
                wake,
            }),
            tasks: Mutex::new(JoinSet::new()),
            runtime,
        }
    }

    /// The cache host in this process, when `routes` make it this worker's replica of
    /// every wall (sender placement): its maps may then be consulted in place.
    pub fn local_host(&self, routes: &crate::routing::Routes) -> Option<&CacheHost> {
        let (endpoint, host) = self.state.local.as_ref()?;
        (routes.my_host_endpoint() == Some(endpoint.as_str())).then_some(host)
    }

    /// Whether the host at `endpoint` was found unreachable.
    fn is_dead(&self, endpoint: &str) -> bool {
        lock(&self.state.dead).contains(endpoint)
    }

    fn ctx(&self, onward: &Arc<dyn Onward>) -> Ctx {
        Ctx {
            state: self.state.clone(),
            onward: onward.clone(),
        }
    }

    /// Hand `msg` to the stream to `endpoint`, opening it if needed (its task delivers
    /// answered rays to `onward`). Never waits; a dead host gets the message failed at
    /// once.
    fn send(&self, onward: &Arc<dyn Onward>, endpoint: &str, msg: CacheMessage) {
        if self.is_dead(endpoint) {
            fail(&self.ctx(onward), endpoint, msg);
            return;
        }
        let tx = {
            let mut links = lock(&self.state.links);
            match links.get(endpoint) {
                Some(tx) if !tx.is_closed() => tx.clone(),
                _ => {
                    let (tx, rx) = mpsc::unbounded_channel();
                    links.insert(endpoint.to_string(), tx.clone());
                    let mut tasks = lock(&self.tasks);
                    while tasks.try_join_next().is_some() {}
                    let ctx = self.ctx(onward);
                    match &self.state.local {
                        Some((e, host)) if e == endpoint => {
                            tasks.spawn_on(local_loop(ctx, host.clone(), rx), &self.runtime)
                        }
                        _ => {
                            tasks.spawn_on(link_loop(ctx, endpoint.to_string(), rx), &self.runtime)
                        }
                    };
                    tx
                }
            }
        };
        if let Err(e) = tx.send(msg) {
            fail(&self.ctx(onward), endpoint, e.0);
        }
    }

    /// End every stream and wait for the tasks (briefly).
    pub async fn close(&self) {
        lock(&self.state.links).clear();
        let mut tasks = std::mem::take(&mut *lock(&self.tasks));
        if tokio::time::timeout(Duration::from_secs(2), async {
            while tasks.join_next().await.is_some() {}
        })
        .await
        .is_err()
        {
            tasks.shutdown().await;
        }
    }
}

/// Send lookups to their walls' hosts (or straight on, for walls whose host is dead).
/// Called with a tracing step's lookups; never waits.
pub(crate) fn send_lookups(
    caches: &CacheLinks,
    onward: &Arc<dyn Onward>,
    job: &Arc<Job>,
    lookups: Vec<Lookup>,
) {
    let routes = job.routes();
    // Grouped by host index, and each host's liveness asked once per step, not per ray
    // (a lock and a string hash each).
    let mut by_host: Vec<Vec<Lookup>> = vec![Vec::new(); routes.cache_host_count()];
    let mut bypass = Outbox::default();
    let mut bypassed = 0u64;
    for l in lookups {
        match routes
            .lookup_host_index(l.wall)
            .and_then(|h| by_host.get_mut(h as usize))
        {
            Some(group) => group.push(l),
            None => {
                bypassed += 1;
                bypass
                    .rays
                    .entry(l.domain)
                    .or_default()
                    .push(l.ray, &l.lineage);
            }
        }
    }
    for (h, lookups) in by_host.into_iter().enumerate() {
        if lookups.is_empty() {
            continue;
        }
        let Some(host) = routes.cache_host_endpoint(h as u32) else {
            continue;
        };
        if caches.is_dead(host) {
            bypassed += lookups.len() as u64;
            for l in lookups {
                bypass
                    .rays
                    .entry(l.domain)
                    .or_default()
                    .push(l.ray, &l.lineage);
            }
            continue;
        }
        job.awaiting_cache_add(lookups.len());
        caches.send(
            onward,
            host,
            CacheMessage::Lookups {
                job: job.clone(),
                lookups,
            },
        );
    }
    if bypassed > 0 {
        let counted = Report {
            cache_rays_bypassed: bypassed,
            ..Report::default()
        };
        onward.clone().deliver_onward(job, bypass, counted);
    }
}

/// Report hit-map probe outcomes to their walls' hosts. Never waits; outcomes for a
/// dead host are dropped (its maps are gone with it).
///
/// Under sender placement every host holds a copy of every map: the copy in this
/// worker's process learns the outcomes at once, and the others get them in merges
/// ([`crate::map_merge`]).
pub(crate) fn send_outcomes(
    caches: &CacheLinks,
    onward: &Arc<dyn Onward>,
    job: &Arc<Job>,
    outcomes: Vec<(u32, u32, bool)>,
) {
    let routes = job.routes();
    if routes.cache_replicas() {
        let merge = job.merges.gather(&outcomes);
        if let Some(mine) = routes.my_host_endpoint()
            && !caches.is_dead(mine)
        {
            let job = job.clone();
            caches.send(onward, mine, CacheMessage::Outcomes { job, outcomes });
        }
        if let Some(cells) = merge {
            send_merge(caches, onward, job, &routes, cells);
        }
        return;
    }
    let mut by_host: HashMap<&str, Vec<(u32, u32, bool)>> = HashMap::new();
    for o in outcomes {
        if let Some(h) = routes.cache_host(o.0)
            && !caches.is_dead(h)
        {
            by_host.entry(h).or_default().push(o);
        }
    }
    for (host, outcomes) in by_host {
        caches.send(
            onward,
            host,
            CacheMessage::Outcomes {
                job: job.clone(),
                outcomes,
            },
        );
    }
}

/// Send the hit-map outcomes gathered for other workers' copies of the maps, if any
/// (sender placement; see [`crate::map_merge`]).
pub(crate) fn flush_merges(caches: &CacheLinks, onward: &Arc<dyn Onward>, job: &Arc<Job>) {
    if let Some(cells) = job.merges.take() {
        send_merge(caches, onward, job, &job.routes(), cells);
    }
}

/// One merge to every host but this worker's own (which learned the outcomes already).
fn send_merge(
    caches: &CacheLinks,
    onward: &Arc<dyn Onward>,
    job: &Arc<Job>,
    routes: &crate::routing::Routes,
    cells: crate::map_merge::Merge,
) {
    let mine = routes.my_host_endpoint();
    for target in routes.cache_host_endpoints() {
        if Some(target.as_str()) == mine || caches.is_dead(target) {
            continue;
        }
        caches.send(
            onward,
            target,
            CacheMessage::Merge {
                job: job.clone(),
                cells: cells.clone(),
            },
        );
    }
}

/// Return `returns` to their tickets' hosts and wait until each host has applied its
/// share (or is found dead), and, on replicated walls, until every other replica has
/// stored the entries those returns stored: the credit in them may then be reported to
/// the coordinator. (So when the coarse pass's credit is whole, every replica holds
/// every entry it made, and the main pass sees the same caches everywhere.)
pub(crate) async fn return_tickets(
    caches: &CacheLinks,
    onward: &Arc<dyn Onward>,
    job: &Arc<Job>,
    returns: Vec<TicketReturn>,
) {
    let routes = job.routes();
    let mut by_host: HashMap<String, Vec<TicketReturn>> = HashMap::new();
    for r in returns {
        // A ticket naming a wall no host serves cannot close anywhere: drop it.
        if let Some(h) = routes.ticket_host(r.ticket) {
            by_host.entry(h.to_string()).or_default().push(r);
        }
    }
    let mut waits = Vec::new();
    for (host, returns) in by_host {
        let (done, wait) = oneshot::channel();
        caches.send(
            onward,
            &host,
            CacheMessage::Returns {
                job: job.clone(),
                returns,
                done,
            },
        );
        waits.push((host, wait));
    }
    let mut stored: Vec<(String, Vec<(u32, Entry)>)> = Vec::new();
    for (host, w) in waits {
        if let Ok(Some(entries)) = w.await
            && !entries.is_empty()
        {
            stored.push((host, entries));
        }
    }
    if stored.is_empty() || !routes.cache_replicas() {
        return;
    }
    // Each replica gets what every other replica stored.
    let mut waits = Vec::new();
    for target in routes.cache_host_endpoints() {
        let entries: Vec<(u32, Entry)> = stored
            .iter()
            .filter(|(origin, _)| origin != target)
            .flat_map(|(_, e)| e.iter().copied())
            .collect();
        if entries.is_empty() || caches.is_dead(target) {
            continue;
        }
        let (done, wait) = oneshot::channel();
        caches.send(
            onward,
            target,
            CacheMessage::Entries {
                job: job.clone(),
                entries,
                done,
            },
        );
        waits.push(wait);
    }
    for w in waits {
        let _ = w.await;
    }
}

/// A message that cannot reach its host: lookups go straight on, returns are dropped.
fn fail(ctx: &Ctx, endpoint: &str, msg: CacheMessage) {
    match msg {
        CacheMessage::Lookups { job, lookups } => {
            job.awaiting_cache_sub(lookups.len());
            lost(&job, endpoint);
            let n = lookups.len() as u64;
            let mut out = Outbox::default();
            for l in lookups {
                out.rays
                    .entry(l.domain)
                    .or_default()
                    .push(l.ray, &l.lineage);
            }
            let counted = Report {
                cache_rays_bypassed: n,
                ..Report::default()
            };
            if job.is_active() {
                ctx.deliver(&job, out, counted);
            }
        }
        CacheMessage::Returns { job, done, .. } | CacheMessage::Entries { job, done, .. } => {
            lost(&job, endpoint);
            let _ = done.send(None);
        }
        CacheMessage::Outcomes { job, .. } | CacheMessage::Merge { job, .. } => {
            lost(&job, endpoint)
        }
    }
    ctx.state.wake.notify();
}

/// Count `cache_bytes` sent to cache hosts, and a message of `(kind, size)`, in `job`'s
/// report.
fn count(job: &Job, cache_bytes: u64, message: Option<(Kind, usize)>) {
    let mut r = Report {
        cache_bytes,
        ..Report::default()
    };
    if let Some((kind, size)) = message {
        r.traffic.message(kind, size);
    }
    job.post(r);
}

/// Name a lost host in `job`'s report (once: its actor keeps names once).
fn lost(job: &Job, endpoint: &str) {
    job.post(Report {
        lost_cache_hosts: vec![endpoint.to_string()],
        ..Report::default()
    });
}

/// What was sent and awaits an answer, in order.
enum Pending {
    Lookups {
        job: Arc<Job>,
        lookups: Vec<Lookup>,
    },
    /// An ack; the last message of a `CacheMessage` carries its caller's wait. `kind`
    /// is what the acked message was (its ack's bytes count as the same kind; an ack
    /// of returns that carries entries counts as entry copies).
    Ack {
        job: Arc<Job>,
        kind: Kind,
        done: Option<oneshot::Sender<Acked>>,
    },
}

/// The task of the link to a host in another process: one `Exchange` stream, opened
/// first; messages go out as they come and answers are matched to them in order. The
/// first failure (unreachable, a broken or ended stream, an answer that does not fit)
/// makes the host dead for this worker ([`link_failed`]).
async fn link_loop(ctx: Ctx, endpoint: String, mut rx: mpsc::UnboundedReceiver<CacheMessage>) {
    let (req_tx, req_rx) = mpsc::channel::<CacheRequest>(64);
    let mut answers = match open_stream(&ctx.state.net, &endpoint, req_rx).await {
        Ok(a) => a,
        Err(e) => {
            link_failed(&ctx, &endpoint, &mut rx, VecDeque::new(), &e);
            return;
        }
    };
    let mut stream = Stream {
        ctx,
        endpoint,
        requests: req_tx,
        pending: VecDeque::new(),
        sequence: 0,
        carried: Vec::new(),
    };
    let error = loop {
        tokio::select! {
            msg = rx.recv() => {
                let Some(msg) = msg else { return };
                if !stream.send(msg).await {
                    break "the stream closed".to_string();
                }
            }
            answer = answers.message() => {
                let received = match answer {
                    Ok(Some(response)) => stream.receive(response),
                    Ok(None) => Err("the host ended the stream".to_string()),
                    Err(s) => Err(s.message().to_string()),
                };
                if let Err(e) = received {
                    break e;
                }
            }
        }
    };
    link_failed(
        &stream.ctx,
        &stream.endpoint,
        &mut rx,
        stream.pending,
        &error,
    );
}

/// Connect to the host at `endpoint` and open its `Exchange` stream, fed by `requests`.
async fn open_stream(
    net: &dray_net::ClientOptions,
    endpoint: &str,
    requests: mpsc::Receiver<CacheRequest>,
) -> Result<tonic::Streaming<CacheResponse>, String> {
    let channel = net
        .endpoint(endpoint)
        .map_err(|e| e.to_string())?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true)
        .connect()
        .await
        .map_err(|e| e.to_string())?;
    let mut client = CacheServiceClient::new(net.wrap(channel))
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20);
    client
        .exchange(ReceiverStream::new(requests))
        .await
        .map(|r| r.into_inner())
        .map_err(|s| s.message().to_string())
}

/// An open stream's state, owned by [`link_loop`]: what was sent and awaits an answer,
/// in order, so each answer is matched to its message by position and sequence.
struct Stream {
    ctx: Ctx,
    endpoint: String,
    /// Into the stream.
    requests: mpsc::Sender<CacheRequest>,
    pending: VecDeque<(u64, Pending)>,
    /// The last request's sequence number.
    sequence: u64,
    /// Entries acknowledged returns stored, until the ack that ends their message.
    carried: Vec<(u32, Entry)>,
}

impl Stream {
    /// The next request's sequence number.
    fn next_sequence(&mut self) -> u64 {
        self.sequence += 1;
        self.sequence
    }

    /// Send `msg` (in as many requests as it takes); false when the stream closed.
    async fn send(&mut self, msg: CacheMessage) -> bool {
        match msg {
            CacheMessage::Lookups { job, lookups } => self.send_lookups(job, lookups).await,
            CacheMessage::Returns { job, returns, done } => {
                self.send_returns(job, returns, done).await
            }
            CacheMessage::Outcomes { job, outcomes } => self.send_outcomes(job, outcomes).await,
            CacheMessage::Merge { job, cells } => self.send_merge(job, cells).await,
            CacheMessage::Entries { job, entries, done } => {
                self.send_entries(job, entries, done).await
            }
        }
    }

    /// Lookups in messages of at most [`LOOKUPS_PER_MESSAGE`] rays. Those that could
    /// not be sent stay pending, to be failed with the rest.
    async fn send_lookups(&mut self, job: Arc<Job>, lookups: Vec<Lookup>) -> bool {
        let mut rest = lookups;
        while !rest.is_empty() {
            let tail = rest.split_off(rest.len().min(LOOKUPS_PER_MESSAGE));
            let chunk = std::mem::replace(&mut rest, tail);
            let sequence = self.next_sequence();
            let request = lookups_request(&job, sequence, &chunk);
            count(
                &job,
                lookup_payload(&request, chunk.len()),
                Some((Kind::Lookups, request.encoded_len())),
            );
            self.trace(&job, Kind::Lookups, true, || request.encoded_len());
            let p = Pending::Lookups {
                job: job.clone(),
                lookups: chunk,
            };
            self.pending.push_back((sequence, p));
            if self.requests.send(request).await.is_err() {
                if !rest.is_empty() {
                    let p = Pending::Lookups {
                        job: job.clone(),
                        lookups: rest,
                    };
                    self.pending.push_back((0, p));
                }
                return false;
            }
        }
        true
    }

    /// Returns in messages of at most [`RETURNS_PER_MESSAGE`]; the last carries the
    /// caller's wait (an empty one is sent for no returns, so the wait is answered in
    /// order).
    async fn send_returns(
        &mut self,
        job: Arc<Job>,
        returns: Vec<TicketReturn>,
        done: oneshot::Sender<Acked>,
    ) -> bool {
        count(&job, returns.len() as u64 * RETURN_BYTES, None);
        let mut rest = returns;
        let mut dones = Some(done);
        while !rest.is_empty() || dones.is_some() {
            let tail = rest.split_off(rest.len().min(RETURNS_PER_MESSAGE));
            let chunk = std::mem::replace(&mut rest, tail);
            let sequence = self.next_sequence();
            let request = returns_request(&job, sequence, chunk);
            // The last chunk carries the caller's wait.
            let done = if rest.is_empty() {
                match dones.take() {
                    Some(done) => Some(done),
                    None => break,
                }
            } else {
                None
            };
            count(&job, 0, Some((Kind::TicketReturns, request.encoded_len())));
            self.trace(&job, Kind::TicketReturns, true, || request.encoded_len());
            self.expect_ack(&job, sequence, Kind::TicketReturns, done);
            if self.requests.send(request).await.is_err() {
                return false;
            }
        }
        true
    }

    /// Hit-map probe outcomes, in one message.
    async fn send_outcomes(&mut self, job: Arc<Job>, outcomes: Vec<(u32, u32, bool)>) -> bool {
        count(&job, outcomes.len() as u64 * OUTCOME_BYTES, None);
        let sequence = self.next_sequence();
        let request = outcomes_request(&job, sequence, &outcomes);
        count(&job, 0, Some((Kind::MapOutcomes, request.encoded_len())));
        self.trace(&job, Kind::MapOutcomes, true, || request.encoded_len());
        self.expect_ack(&job, sequence, Kind::MapOutcomes, None);
        self.requests.send(request).await.is_ok()
    }

    /// A merge of hit-map outcomes, in one message.
    async fn send_merge(&mut self, job: Arc<Job>, cells: crate::map_merge::Merge) -> bool {
        let sequence = self.next_sequence();
        let request = merge_request(&job, sequence, &cells);
        let bytes = request.encoded_len();
        count(&job, bytes as u64, Some((Kind::MapMerges, bytes)));
        self.trace(&job, Kind::MapMerges, true, || bytes);
        self.expect_ack(&job, sequence, Kind::MapMerges, None);
        self.requests.send(request).await.is_ok()
    }

    /// Entries in messages of at most [`ENTRIES_PER_MESSAGE`]; the last carries the
    /// caller's wait, answered at once when there is nothing to send.
    async fn send_entries(
        &mut self,
        job: Arc<Job>,
        entries: Vec<(u32, Entry)>,
        done: oneshot::Sender<Acked>,
    ) -> bool {
        count(
            &job,
            entries.len() as u64 * (ENTRY_RECORD_BYTES as u64 + 4),
            None,
        );
        let mut ok = true;
        let mut chunks = entries.chunks(ENTRIES_PER_MESSAGE).peekable();
        let mut dones = Some(done);
        while let Some(chunk) = chunks.next() {
            let sequence = self.next_sequence();
            let request = entries_request(&job, sequence, chunk);
            let done = if chunks.peek().is_none() {
                dones.take()
            } else {
                None
            };
            count(&job, 0, Some((Kind::EntryCopies, request.encoded_len())));
            self.trace(&job, Kind::EntryCopies, true, || request.encoded_len());
            self.expect_ack(&job, sequence, Kind::EntryCopies, done);
            if self.requests.send(request).await.is_err() {
                ok = false;
                break;
            }
        }
        if let Some(done) = dones {
            // Nothing to send (no entries): done at once.
            let _ = done.send(Some(Vec::new()));
        }
        ok
    }

    /// A `kind` message of `bytes()` to (`sent`) or from this host in `job`'s traffic
    /// trace, when it records one (`bytes` is not computed otherwise).
    fn trace(&self, job: &Job, kind: Kind, sent: bool, bytes: impl FnOnce() -> usize) {
        if let Some(t) = &job.trace {
            let mine = self.ctx.state.local.as_ref().map(|(e, _)| e.as_str());
            t.cache(mine, &self.endpoint, kind, sent, bytes() as u64);
        }
    }

    /// Remember that the request `sequence` of `job` (a `kind` message) awaits an ack.
    fn expect_ack(
        &mut self,
        job: &Arc<Job>,
        sequence: u64,
        kind: Kind,
        done: Option<oneshot::Sender<Acked>>,
    ) {
        let job = job.clone();
        self.pending
            .push_back((sequence, Pending::Ack { job, kind, done }));
    }

    /// Apply the host's next answer to the oldest message pending; an error (the
    /// host's answers do not fit what was sent) fails the link.
    fn receive(&mut self, response: CacheResponse) -> Result<(), String> {
        let size = response.encoded_len();
        let Some((seq, p)) = self.pending.pop_front() else {
            return Err("an answer to nothing sent".to_string());
        };
        match (response.msg, p) {
            (Some(cache_response::Msg::Answers(a)), Pending::Lookups { job, lookups })
                if a.sequence == seq =>
            {
                count(&job, 0, Some((Kind::Answers, size)));
                self.trace(&job, Kind::Answers, false, || size);
                apply_answers(&self.ctx, &job, lookups, answers_of(&a));
            }
            (Some(cache_response::Msg::Ack(a)), Pending::Ack { job, kind, done })
                if a.sequence == seq =>
            {
                let kind = if a.entries.is_empty() {
                    kind
                } else {
                    Kind::EntryCopies
                };
                count(&job, 0, Some((kind, size)));
                self.trace(&job, kind, false, || size);
                self.carried.extend(entries_of(&a)?);
                if let Some(done) = done {
                    let _ = done.send(Some(std::mem::take(&mut self.carried)));
                }
            }
            (_, p) => {
                self.pending.push_front((seq, p));
                return Err("answers out of order".to_string());
            }
        }
        Ok(())
    }
}

/// The entries an ack carries (wall, entry).
fn entries_of(a: &TicketAck) -> Result<Vec<(u32, Entry)>, String> {
    if a.walls.is_empty() && a.entries.is_empty() {
        return Ok(Vec::new());
    }
    let entries = decode_entries(&a.entries, a.walls.len()).map_err(|e| e.to_string())?;
    Ok(a.walls.iter().copied().zip(entries).collect())
}

/// The answer to one ray, however it came.
#[derive(Clone, Copy, Debug)]
struct Answer {
    /// cache.proto's outcome code (with [`PROBE`] added for probes).
    code: u8,
    /// The cached radiance of a hit, or the averaged shading of a shaded ray.
    radiance: Option<[f32; 3]>,
    /// The ticket of a ticketed miss.
    ticket: Option<u64>,
}

impl From<Outcome> for Answer {
    fn from(o: Outcome) -> Answer {
        Answer {
            code: o.code(),
            radiance: match o {
                Outcome::Hit(rgb) | Outcome::Shaded(rgb) => Some(rgb),
                _ => None,
            },
            ticket: o.ticket(),
        }
    }
}

/// A `CacheAnswers` ray for ray: the radiance of each hit or shaded ray and the ticket
/// of each ticketed miss taken in order from their lists (missing ones stay `None`).
fn answers_of(a: &CacheAnswers) -> impl Iterator<Item = Answer> + '_ {
    let mut radiance = a.radiance.chunks_exact(3);
    let mut tickets = a.tickets.iter();
    a.outcomes.iter().map(move |&code| Answer {
        code,
        radiance: if matches!(code & !PROBE, CODE_HIT | CODE_SHADED) {
            radiance.next().map(|c| [c[0], c[1], c[2]])
        } else {
            None
        },
        ticket: if code & !PROBE == CODE_TICKET {
            tickets.next().copied()
        } else {
            None
        },
    })
}

/// The link to the cache host in this process: each message is handed to the host's
/// actors and answered before the next (the order a gRPC link keeps, so an applied
/// return means what it means there).
async fn local_loop(ctx: Ctx, host: CacheHost, mut rx: mpsc::UnboundedReceiver<CacheMessage>) {
    while let Some(msg) = rx.recv().await {
        match msg {
            CacheMessage::Lookups { job, lookups } => {
                let rays = lookups
                    .iter()
                    .map(|l| WallLookup {
                        wall: l.wall,
                        ray: LookupRay {
                            ray: lookup_record(l),
                            options: lookup_options(&job, l),
                        },
                    })
                    .collect();
                let outcomes = host.lookup_rays(&job.key.id, job.key.attempt, rays).await;
                apply_answers(&ctx, &job, lookups, outcomes.into_iter().map(Answer::from));
            }
            CacheMessage::Returns { job, returns, done } => {
                let returns = returns.iter().map(|t| (t.ticket, Return::from(t)));
                let stored = host
                    .return_tickets(&job.key.id, job.key.attempt, returns)
                    .await;
                let _ = done.send(Some(stored));
            }
            CacheMessage::Entries { job, entries, done } => {
                host.insert_entries(&job.key.id, job.key.attempt, entries)
                    .await;
                let _ = done.send(Some(Vec::new()));
            }
            CacheMessage::Outcomes { job, outcomes } => {
                let outcomes = outcomes.iter().map(|&(w, c, hit)| (w, c, u8::from(hit)));
                host.learn(&job.key.id, job.key.attempt, outcomes).await;
            }
            CacheMessage::Merge { job, cells } => {
                host.merge(&job.key.id, job.key.attempt, cells).await;
            }
        }
    }
}

/// Apply a host's answers to the lookups they answer, ray for ray. An answer that
/// does not fit its lookups (a host bug) sends the unanswered rays straight on.
fn apply_answers(
    ctx: &Ctx,
    job: &Arc<Job>,
    lookups: Vec<Lookup>,
    answers: impl Iterator<Item = Answer>,
) {
    job.awaiting_cache_sub(lookups.len());
    if !job.is_active() {
        return;
    }
    let routes = job.routes();
    let residency = NoDomains {
        walls: routes.has_caches(),
    };
    let mut out = Outbox::default();
    let (mut cache_not_sent, mut phm_not_sent) = (0u64, 0u64);
    let mut answers = answers.fuse();
    for l in lookups {
        let answer = answers.next();
        let code = answer.map_or(CODE_MISS, |a| a.code);
        let mut lin = l.lineage;
        lin.probe = code & PROBE != 0 && matches!(code & !PROBE, CODE_MISS | CODE_TICKET);
        match code & !PROBE {
            // A cache's hit, or a map's averaged shading (`phm.shade`).
            answered @ (CODE_HIT | CODE_SHADED) => {
                if let Some(c) = answer.and_then(|a| a.radiance) {
                    job.tracer
                        .answer_hit(&l.ray, &lin, Vec3::from_array(c), &mut out);
                    if !routes.owns(l.domain) {
                        match answered {
                            CODE_HIT => cache_not_sent += 1,
                            _ => phm_not_sent += 1,
                        }
                    }
                    continue;
                }
            }
            CODE_TICKET => {
                if let Some(t) = answer.and_then(|a| a.ticket) {
                    lin = lin.with_ticket(t);
                }
            }
            CODE_SKIP => {
                if !routes.owns(l.domain) {
                    phm_not_sent += 1;
                }
                if let Err(e) = job.tracer.skip(&l.ray, lin, l.domain, &residency, &mut out) {
                    job.fail(format!("worker {}: {e}", ctx.state.member.id()));
                    return;
                }
                continue;
            }
            CODE_OCCLUDED if l.ray.kind.is_occlusion() => {
                if !routes.owns(l.domain) {
                    phm_not_sent += 1;
                }
                job.tracer.answer_occluded(&l.ray, &lin, &mut out);
                continue;
            }
            _ => {}
        }
        out.rays.entry(l.domain).or_default().push(l.ray, &lin);
    }
    let counted = Report {
        cache_rays_not_sent: cache_not_sent,
        phm_rays_not_sent: phm_not_sent,
        ..Report::default()
    };
    ctx.deliver(job, out, counted);
    ctx.state.wake.notify();
}

/// The stream to `endpoint` failed: the host is dead for this worker; everything sent
/// or waiting for it is failed (lookups go straight on, returns are dropped).
fn link_failed(
    ctx: &Ctx,
    endpoint: &str,
    rx: &mut mpsc::UnboundedReceiver<CacheMessage>,
    pending: VecDeque<(u64, Pending)>,
    error: &str,
) {
    tracing::warn!(worker = %ctx.state.member.id(), host = %endpoint, "cache host lost: {error}");
    lock(&ctx.state.dead).insert(endpoint.to_string());
    rx.close();
    lock(&ctx.state.links).retain(|_, tx| !tx.is_closed());
    for (_, p) in pending {
        match p {
            Pending::Lookups { job, lookups } => {
                fail(ctx, endpoint, CacheMessage::Lookups { job, lookups })
            }
            Pending::Ack { done, .. } => {
                if let Some(done) = done {
                    let _ = done.send(None);
                }
            }
        }
    }
    while let Ok(m) = rx.try_recv() {
        fail(ctx, endpoint, m);
    }
}
