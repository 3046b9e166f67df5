//! Cluster membership: which workers are registered, when each was last heard from, and
//! the outbox of commands ([`Assignment`]s) waiting for each worker's WatchAssignments
//! stream.
//!
//! Workers dial the coordinator, never the other way round (cluster.proto), so the only
//! way to tell a worker something is the one long-lived server stream it opens. Commands
//! are queued in a per-worker [`Outbox`] rather than written to the stream directly, so
//! that a command issued before the worker opened its stream (or while it reconnects) is
//! delivered when the stream (re)opens instead of being lost.
//!
//! Liveness is by heartbeat: a worker not heard from for `heartbeat_timeout` is dropped
//! by [`Membership::expire`]; what happens to its jobs is the scheduler's business (the
//! reaper posts a `WorkerLost` event, see [`crate::scheduler`]).

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime};

use dray_proto::v1::{Assignment, RegisterWorkerRequest, WorkerEndpoint};
use tokio::sync::Notify;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Status;

use crate::caches::hosts::CacheHosts;
pub use crate::registration::{
    MAX_ENDPOINT_BYTES, MAX_HOSTNAME_BYTES, VERSION, check_endpoint, check_hostname,
    version_mismatch,
};

/// Commands buffered between a worker's outbox and its gRPC stream. Small, so that
/// commands stay in the outbox (where a reconnecting stream finds them) rather than in
/// a channel that dies with the old stream.
const STREAM_BUFFER: usize = 4;

/// How often workers heartbeat, and how long silence is tolerated.
#[derive(Clone, Copy, Debug)]
pub struct HeartbeatConfig {
    /// Told to workers in RegisterWorkerResponse.
    pub interval: Duration,
    /// Silence after which a worker is dropped.
    pub timeout: Duration,
}

impl Default for HeartbeatConfig {
    /// One beat a second; twenty missed beats declare the worker lost. Long enough that a
    /// worker on an overloaded machine (its tracing threads compete with the task that
    /// beats) is not dropped mid-job, which costs the job a new attempt (its unfinished
    /// tiles traced again); short enough that a job does not hang for long on a dead
    /// machine.
    fn default() -> HeartbeatConfig {
        HeartbeatConfig {
            interval: Duration::from_secs(1),
            timeout: Duration::from_secs(20),
        }
    }
}

/// Commands for one worker, in order, waiting to be written to its stream. A command
/// sent to many workers (a job's new routing table) is queued once and shared (`Arc`):
/// a round's fan-out costs a pointer per worker, not a copy of the table; each stream
/// takes its own copy only as it writes it.
#[derive(Default)]
pub struct Outbox {
    queue: Mutex<VecDeque<Arc<Assignment>>>,
    notify: Notify,
    /// Bumped when a new stream takes over, so the previous stream's task stops.
    generation: AtomicU64,
    /// Set when the worker is dropped or the server shuts down: streams end.
    closed: std::sync::atomic::AtomicBool,
}

impl Outbox {
    fn lock(&self) -> MutexGuard<'_, VecDeque<Arc<Assignment>>> {
        dray_sync::lock(&self.queue)
    }

    /// Queue a command.
    pub fn push(&self, a: Arc<Assignment>) {
        self.lock().push_back(a);
        self.notify.notify_waiters();
    }

    /// End the stream that reads this outbox (after it has written what is queued).
    pub fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.notify.notify_waiters();
    }

    /// Commands queued and not yet handed to a stream (for tests and logs).
    pub fn pending(&self) -> usize {
        self.lock().len()
    }

    /// A stream of this outbox's commands. A later call takes over: the earlier stream
    /// ends (a worker that reconnects must not have two streams splitting its commands).
    pub fn stream(self: &Arc<Self>) -> ReceiverStream<Result<Assignment, Status>> {
        let generation = self.generation.fetch_add(1, Ordering::SeqCst) + 1;
        self.notify.notify_waiters();
        let (tx, rx) = tokio::sync::mpsc::channel(STREAM_BUFFER);
        let outbox = self.clone();
        tokio::spawn(async move {
            loop {
                let notified = outbox.notify.notified();
                tokio::pin!(notified);
                // Register for wake-ups before looking, so a push between the look and
                // the wait is not missed.
                notified.as_mut().enable();
                if outbox.generation.load(Ordering::SeqCst) != generation {
                    return;
                }
                let next = outbox.lock().pop_front();
                match next {
                    Some(a) => {
                        if let Err(e) = tx.send(Ok(Arc::unwrap_or_clone(a))).await {
                            // The worker went away: keep the command for its next stream.
                            if let Ok(a) = e.0 {
                                outbox.lock().push_front(Arc::new(a));
                            }
                            return;
                        }
                    }
                    None if outbox.closed.load(Ordering::SeqCst) => return,
                    None => {
                        tokio::select! {
                            _ = &mut notified => {}
                            _ = tx.closed() => return,
                        }
                    }
                }
            }
        });
        ReceiverStream::new(rx)
    }
}

/// One registered worker.
#[derive(Clone)]
pub struct WorkerRecord {
    /// Id minted at registration.
    pub id: String,
    /// Its RayExchangeService endpoint.
    pub endpoint: String,
    /// The CacheService of the cache host in its process, if it runs one.
    pub cache_endpoint: Option<String>,
    /// Tracing threads.
    pub threads: u32,
    /// Memory budget for resident domains (0 = unlimited).
    pub memory_budget_bytes: u64,
    /// Host name, for logs.
    pub hostname: String,
    /// Its name for people (RegisterWorkerRequest.name), empty when it gave none.
    pub name: String,
    /// Last heartbeat (or registration).
    pub last_seen: Instant,
    /// From the last heartbeat.
    pub memory_used_bytes: u64,
    /// From the last heartbeat.
    pub rays_queued: u64,
    /// Commands for it.
    pub outbox: Arc<Outbox>,
    /// Its own secret (RegisterWorkerResponse.member_token): calls naming it must carry
    /// it.
    pub member_token: dray_net::Token,
}

impl std::fmt::Debug for WorkerRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerRecord")
            .field("id", &self.id)
            .field("endpoint", &self.endpoint)
            .field("cache_endpoint", &self.cache_endpoint)
            .field("threads", &self.threads)
            .field("memory_budget_bytes", &self.memory_budget_bytes)
            .field("hostname", &self.hostname)
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

impl WorkerRecord {
    /// Its id and endpoint, as routing tables list them.
    pub fn endpoint(&self) -> WorkerEndpoint {
        WorkerEndpoint {
            worker_id: self.id.clone(),
            endpoint: self.endpoint.clone(),
        }
    }

    /// How logs and messages name it: `w3-1a2b3c4d (worker-2)`.
    pub fn label(&self) -> String {
        dray_proto::worker_name::worker_label(&self.id, &self.name)
    }
}

/// A worker [`Membership::expire`] dropped.
#[derive(Clone, Debug)]
pub struct LostWorker {
    /// Its id.
    pub id: String,
    /// Its name (RegisterWorkerRequest.name), empty when it gave none.
    pub name: String,
    /// Its endpoint, so messages can say which machine it was.
    pub endpoint: String,
    /// How long it had been silent.
    pub silent_for: Duration,
    /// Why it was declared lost, for messages: "no heartbeat for 2.1 s", or a peer that
    /// could not reach it.
    pub cause: String,
}

impl LostWorker {
    /// How logs and job events name it: `w3-1a2b3c4d (worker-2)`.
    pub fn label(&self) -> String {
        dray_proto::worker_name::worker_label(&self.id, &self.name)
    }
}

pub use dray_net::auth::MEMBER_HEADER;

/// The registered workers.
pub struct Membership {
    workers: Mutex<BTreeMap<String, WorkerRecord>>,
    next: AtomicU64,
    /// Distinguishes this coordinator's ids from those of an earlier run, so a worker
    /// that outlived a coordinator restart is told to re-register instead of being
    /// mistaken for a new worker that got the same number.
    nonce: u32,
    /// Heartbeat settings.
    pub heartbeat: HeartbeatConfig,
    /// Stand-alone cache hosts (`dray cache`), which register apart from workers.
    pub cache_hosts: CacheHosts,
}

impl Membership {
    /// No workers yet.
    pub fn new(heartbeat: HeartbeatConfig) -> Membership {
        let t = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap_or_default();
        let nonce = (t.subsec_nanos() ^ (t.as_secs() as u32).rotate_left(16))
            ^ std::process::id().rotate_left(8);
        Membership {
            workers: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(1),
            nonce,
            heartbeat,
            cache_hosts: CacheHosts::default(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, BTreeMap<String, WorkerRecord>> {
        dray_sync::lock(&self.workers)
    }

    /// Check a registration and add the worker. A version or record-format mismatch is
    /// FAILED_PRECONDITION (the worker must be rebuilt, retrying cannot help); a missing
    /// endpoint is INVALID_ARGUMENT.
    pub fn register(&self, r: &RegisterWorkerRequest) -> Result<WorkerRecord, Status> {
        if r.version != VERSION {
            return Err(version_mismatch("worker", &r.version));
        }
        check_hostname(&r.hostname)?;
        dray_proto::worker_name::check_worker_name(&r.name).map_err(|e| {
            Status::invalid_argument(format!("name: {} {e}", crate::text::bounded(&r.name)))
        })?;
        if r.record_format != dray_proto::RAY_RECORD_FORMAT {
            return Err(Status::failed_precondition(format!(
                "record_format: the worker uses ray record format {} but the coordinator \
                 expects {}",
                r.record_format,
                dray_proto::RAY_RECORD_FORMAT
            )));
        }
        let endpoint = check_endpoint("endpoint", &r.endpoint)?;
        // A worker may host no cache actors (empty); one it announces must be usable.
        let cache_endpoint = if r.cache_endpoint.trim().is_empty() {
            None
        } else {
            Some(check_endpoint("cache_endpoint", &r.cache_endpoint)?)
        };
        let n = self.next.fetch_add(1, Ordering::Relaxed);
        let rec = WorkerRecord {
            id: format!("w{n}-{:08x}", self.nonce),
            endpoint,
            cache_endpoint,
            threads: r.threads,
            memory_budget_bytes: r.memory_budget_bytes,
            hostname: r.hostname.clone(),
            name: r.name.clone(),
            last_seen: Instant::now(),
            memory_used_bytes: 0,
            rays_queued: 0,
            outbox: Arc::new(Outbox::default()),
            member_token: dray_net::Token::generate()
                .map_err(|e| Status::internal(format!("cannot make a member token: {e}")))?,
        };
        let twins = {
            let mut g = self.lock();
            let twins: Vec<String> = if rec.name.is_empty() {
                Vec::new()
            } else {
                g.values()
                    .filter(|w| w.name == rec.name)
                    .map(|w| w.id.clone())
                    .collect()
            };
            g.insert(rec.id.clone(), rec.clone());
            twins
        };
        tracing::info!(
            worker = %rec.id,
            name = %rec.name,
            endpoint = %rec.endpoint,
            cache_endpoint = %rec.cache_endpoint.as_deref().unwrap_or("none"),
            host = %rec.hostname,
            "worker registered: {}",
            rec.label()
        );
        // Allowed (see RegisterWorkerRequest.name): a restarted worker registers again
        // under its name before its old record expires. Said, so a name given twice by
        // mistake is seen.
        if !twins.is_empty() {
            tracing::warn!(
                worker = %rec.id,
                name = %rec.name,
                others = %twins.join(", "),
                "worker name {:?} is also used by {}: names are labels, ids tell them apart",
                rec.name,
                twins.join(", ")
            );
        }
        Ok(rec)
    }

    /// Whether a call naming worker `id` may speak for it: it carries the worker's own
    /// secret in `x-dray-member`. An unknown worker passes (the call then says it must
    /// register again).
    pub fn check_member(
        &self,
        id: &str,
        metadata: &tonic::metadata::MetadataMap,
    ) -> Result<(), Status> {
        let Some(token) = self.lock().get(id).map(|w| w.member_token.clone()) else {
            return Ok(());
        };
        let presented = metadata
            .get(MEMBER_HEADER)
            .map(|v| v.as_bytes())
            .unwrap_or_default();
        if token.matches(presented) {
            Ok(())
        } else {
            Err(Status::permission_denied(format!(
                "worker_id {}: the call does not carry that worker's member credential",
                crate::text::bounded(id)
            )))
        }
    }

    /// Record a heartbeat. False when the worker is unknown (it must re-register).
    pub fn heartbeat(&self, id: &str, memory_used_bytes: u64, rays_queued: u64) -> bool {
        match self.lock().get_mut(id) {
            Some(w) => {
                w.last_seen = Instant::now();
                w.memory_used_bytes = memory_used_bytes;
                w.rays_queued = rays_queued;
                true
            }
            None => false,
        }
    }

    /// Note that `id` was heard from (any call counts as a sign of life).
    pub fn touch(&self, id: &str) {
        if let Some(w) = self.lock().get_mut(id) {
            w.last_seen = Instant::now();
        }
    }

    /// The worker with id `id`.
    pub fn get(&self, id: &str) -> Option<WorkerRecord> {
        self.lock().get(id).cloned()
    }

    /// Every registered worker, ordered by id (so dispatch is deterministic).
    pub fn workers(&self) -> Vec<WorkerRecord> {
        self.lock().values().cloned().collect()
    }

    /// At most `n` registered workers whose ids sort after `after` (from the first
    /// when `None`), in id order, and whether more follow them: one ListWorkers page.
    /// A cursor by id, not by position, so a worker leaving between two pages does not
    /// shift a worker that stays onto a page already sent.
    pub fn workers_after(&self, after: Option<&str>, n: usize) -> (Vec<WorkerRecord>, bool) {
        use std::ops::Bound;
        let workers = self.lock();
        let from = after.map_or(Bound::Unbounded, |a| Bound::Excluded(a.to_string()));
        let mut range = workers.range((from, Bound::Unbounded));
        let page: Vec<WorkerRecord> = range.by_ref().take(n).map(|(_, w)| w.clone()).collect();
        (page, range.next().is_some())
    }

    /// Number of registered workers.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// True when no worker is registered.
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }

    /// Queue `a` for worker `id`. False when the worker is gone.
    pub fn send(&self, id: &str, a: Assignment) -> bool {
        self.send_shared(id, Arc::new(a))
    }

    /// Queue one shared copy of `a` for each of `ids` (those still registered).
    pub fn send_all(&self, ids: &[String], a: Assignment) {
        let a = Arc::new(a);
        for id in ids {
            self.send_shared(id, a.clone());
        }
    }

    /// Queue `a`, which other workers may be sent too, for worker `id`. False when the
    /// worker is gone.
    pub fn send_shared(&self, id: &str, a: Arc<Assignment>) -> bool {
        let outbox = self.lock().get(id).map(|w| w.outbox.clone());
        match outbox {
            Some(o) => {
                o.push(a);
                true
            }
            None => false,
        }
    }

    /// Drop every worker silent for longer than the heartbeat timeout at `now`, ending
    /// their streams, and return them.
    pub fn expire(&self, now: Instant) -> Vec<LostWorker> {
        let mut g = self.lock();
        let timeout = self.heartbeat.timeout;
        let dead: Vec<String> = g
            .values()
            .filter(|w| now.saturating_duration_since(w.last_seen) > timeout)
            .map(|w| w.id.clone())
            .collect();
        dead.into_iter()
            .filter_map(|id| g.remove(&id))
            .map(|w| {
                w.outbox.close();
                let silent_for = now.saturating_duration_since(w.last_seen);
                let label = w.label();
                tracing::warn!(worker = %w.id, name = %w.name, endpoint = %w.endpoint, ?silent_for, "worker lost: {label}, no heartbeat");
                LostWorker {
                    id: w.id,
                    name: w.name,
                    endpoint: w.endpoint,
                    silent_for,
                    cause: format!("no heartbeat for {:.1} s", silent_for.as_secs_f64()),
                }
            })
            .collect()
    }

    /// Drop worker `id` because a peer could not send it rays (`by` names that peer):
    /// a worker its peers cannot reach cannot take part in a job, whatever its
    /// heartbeats say. If it is alive it is told to register again at its next
    /// heartbeat, and joins as a new worker.
    pub fn drop_unreachable(&self, id: &str, by: &str, now: Instant) -> Option<LostWorker> {
        let w = self.lock().remove(id)?;
        w.outbox.close();
        let silent_for = now.saturating_duration_since(w.last_seen);
        let label = w.label();
        tracing::warn!(worker = %w.id, name = %w.name, endpoint = %w.endpoint, peer = %by, "worker lost: {label}, a peer cannot reach it");
        Some(LostWorker {
            id: w.id,
            name: w.name,
            endpoint: w.endpoint,
            silent_for,
            cause: format!("worker {by} could not send it rays"),
        })
    }

    /// End every worker's stream (server shutdown), so a graceful shutdown does not wait
    /// forever on streams that never end by themselves.
    pub fn close_all(&self) {
        for w in self.lock().values() {
            w.outbox.close();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::JobRelease;
    use dray_proto::v1::assignment::Command;
    use tokio_stream::StreamExt;

    fn release(id: &str) -> Arc<Assignment> {
        Arc::new(Assignment {
            command: Some(Command::Finish(JobRelease {
                job_id: id.into(),
                reason: String::new(),
                attempt: 0,
            })),
        })
    }

    fn job_of(a: Option<Result<Assignment, Status>>) -> String {
        match a.expect("stream ended").expect("stream error").command {
            Some(Command::Finish(r)) => r.job_id,
            other => panic!("unexpected {other:?}"),
        }
    }

    async fn next(
        s: &mut ReceiverStream<Result<Assignment, Status>>,
    ) -> Option<Result<Assignment, Status>> {
        tokio::time::timeout(Duration::from_secs(10), s.next())
            .await
            .expect("nothing arrived")
    }

    #[tokio::test]
    async fn outbox_keeps_order_survives_reconnects_and_closes() {
        let o = Arc::new(Outbox::default());
        // Queued before any stream is open: delivered when one opens.
        o.push(release("a"));
        let mut s1 = o.stream();
        assert_eq!(job_of(next(&mut s1).await), "a");
        o.push(release("b"));
        assert_eq!(job_of(next(&mut s1).await), "b");
        // A second stream takes over; the first ends.
        let mut s2 = o.stream();
        assert!(next(&mut s1).await.is_none());
        o.push(release("c"));
        o.push(release("d"));
        assert_eq!(job_of(next(&mut s2).await), "c");
        assert_eq!(job_of(next(&mut s2).await), "d");
        // Closing ends the stream once what is queued has been written.
        o.push(release("e"));
        o.close();
        assert_eq!(job_of(next(&mut s2).await), "e");
        assert!(next(&mut s2).await.is_none());
        assert_eq!(o.pending(), 0);
    }

    #[test]
    fn expire_drops_only_silent_workers() {
        let m = Membership::new(HeartbeatConfig {
            interval: Duration::from_millis(10),
            timeout: Duration::from_secs(1),
        });
        let req = RegisterWorkerRequest {
            endpoint: "http://h:1".into(),
            version: VERSION.into(),
            record_format: dray_proto::RAY_RECORD_FORMAT,
            ..Default::default()
        };
        let a = m.register(&req).unwrap();
        let b = m.register(&req).unwrap();
        assert_ne!(a.id, b.id);
        let later = Instant::now() + Duration::from_millis(1500);
        assert!(m.expire(Instant::now()).is_empty());
        // b heartbeats "at" a point 1 s after now; simulate by checking only a is older.
        {
            let mut g = m.lock();
            g.get_mut(&b.id).unwrap().last_seen = later;
        }
        let lost = m.expire(later);
        assert_eq!(lost.len(), 1);
        assert_eq!(lost[0].id, a.id);
        assert!(m.get(&a.id).is_none() && m.get(&b.id).is_some());
        assert!(
            !m.heartbeat(&a.id, 0, 0),
            "a dropped worker must re-register"
        );
        assert!(m.heartbeat(&b.id, 0, 0));
    }

    /// docs/security.md "Hardening, second round", item 11: a 3 MB `version`, `endpoint`
    /// or `hostname` came back whole in
    /// the error (and the logs). Every echoed field is cut.
    #[test]
    fn registration_errors_never_echo_an_unbounded_field() {
        let m = Membership::new(HeartbeatConfig::default());
        let huge = "x".repeat(3 << 20);
        let ok = RegisterWorkerRequest {
            endpoint: "http://h:1".into(),
            version: VERSION.into(),
            record_format: dray_proto::RAY_RECORD_FORMAT,
            ..Default::default()
        };
        let cases = [
            (
                "version",
                RegisterWorkerRequest {
                    version: huge.clone(),
                    ..ok.clone()
                },
            ),
            (
                "endpoint",
                RegisterWorkerRequest {
                    endpoint: huge.clone(),
                    ..ok.clone()
                },
            ),
            (
                "endpoint",
                RegisterWorkerRequest {
                    endpoint: format!("h{huge}"),
                    ..ok.clone()
                },
            ),
            (
                "cache_endpoint",
                RegisterWorkerRequest {
                    cache_endpoint: huge.clone(),
                    ..ok.clone()
                },
            ),
            (
                "hostname",
                RegisterWorkerRequest {
                    hostname: huge.clone(),
                    ..ok.clone()
                },
            ),
        ];
        for (field, req) in cases {
            let e = m.register(&req).unwrap_err();
            assert!(
                e.message().starts_with(field),
                "{field}: {}",
                &e.message()[..100.min(e.message().len())]
            );
            assert!(
                e.message().len() < 400,
                "{field}: {} bytes",
                e.message().len()
            );
        }
        // A bad endpoint short enough is still quoted in full.
        let e = m
            .register(&RegisterWorkerRequest {
                endpoint: "h:1".into(),
                ..ok
            })
            .unwrap_err();
        assert!(e.message().contains("\"h:1\""), "{}", e.message());
    }

    /// RegisterWorkerRequest.name: checked (INVALID_ARGUMENT naming the field and what is
    /// wrong), kept on the record and on a lost worker, and not unique: a second worker
    /// with the same name registers under its own id (a restarted worker does so before
    /// its old record expires).
    #[test]
    fn names_are_checked_kept_and_may_repeat() {
        let m = Membership::new(HeartbeatConfig {
            interval: Duration::from_millis(10),
            timeout: Duration::from_secs(1),
        });
        let named = |name: &str| RegisterWorkerRequest {
            endpoint: "http://h:1".into(),
            version: VERSION.into(),
            record_format: dray_proto::RAY_RECORD_FORMAT,
            name: name.into(),
            ..Default::default()
        };
        for (bad, why) in [
            ("worker 2", "' ' (character 7) is not allowed"),
            ("<script>", "'<' (character 1) is not allowed"),
            (&"n".repeat(65), "65 characters is longer than 64"),
        ] {
            let e = m.register(&named(bad)).unwrap_err();
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(
                e.message().starts_with("name: ") && e.message().contains(why),
                "{}",
                e.message()
            );
        }
        let huge = m.register(&named(&"x".repeat(3 << 20))).unwrap_err();
        assert!(huge.message().len() < 400, "{} bytes", huge.message().len());

        let a = m.register(&named("worker-2")).unwrap();
        let b = m.register(&named("worker-2")).unwrap();
        let none = m.register(&named("")).unwrap();
        assert_ne!(a.id, b.id);
        assert_eq!((a.name.as_str(), b.name.as_str()), ("worker-2", "worker-2"));
        assert_eq!(a.label(), format!("{} (worker-2)", a.id));
        assert_eq!(none.label(), none.id);
        assert_eq!(m.workers().len(), 3);
        let lost = m.drop_unreachable(&a.id, "w9", Instant::now()).unwrap();
        assert_eq!(lost.name, "worker-2");
        assert_eq!(lost.label(), format!("{} (worker-2)", a.id));
    }
}
