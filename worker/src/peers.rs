//! Outgoing ray streams: one task per peer owns the gRPC stream to it.
//!
//! Tracing threads hand rays over through an unbounded channel (they never wait for the
//! network; the in-flight limit on camera rays bounds what piles up here), and the
//! task sends them as the peer grants room ([`crate::peer_client`]). Rays of a job that
//! is released while they wait are dropped with it, so a peer that stopped granting
//! (it was lost) cannot hold the worker up.
//!
//! A peer that cannot be reached is not a reason to fail the job here: its rays are
//! dropped, and the peer is named to the coordinator (`unreachable_peers`), which treats
//! it as lost and traces the unfinished tiles again on the workers that remain.
//!
//! **A stream is to one peer, not to an address.** A worker started again on the same
//! port (`dray cluster` restarts a killed worker there) registers under a new id while
//! its predecessor may still be in a job's table; streams are kept by (id, endpoint), so
//! rays for the newcomer never ride a stream opened for the old id. They used to: when
//! that stream then failed, the rays were dropped and the *old* id named, which the
//! coordinator ignores once the old worker is out of the job, so the credit never came
//! back and the job stayed RUNNING for ever (issue 38). And when a stream fails, every
//! job whose rays it carried (queued, in open batches, or sent and not yet acknowledged)
//! names the peer, not only the job of the message at hand: a ray lost without a name is
//! a hang.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use dray_core::ray::RayRecord;
use dray_proto::v1::RayTicket;
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use crate::jobs::{Job, Report};
use crate::member::Member;
use crate::peer_client::{BatchKey, PeerClientConfig, PeerSender};
use crate::routing::Peer;
use crate::wake::Wake;
use dray_sync::lock;

/// Rays for one peer.
pub(crate) struct PeerMessage {
    pub job: Arc<Job>,
    pub domain: u32,
    pub rays: Vec<RayRecord>,
    /// The rays' cache tickets, by index into `rays` (see `tickets::RayBundle`).
    pub tickets: Vec<RayTicket>,
    pub forwards: u32,
    pub routing_version: u64,
}

/// The streams to this worker's peers.
pub(crate) struct Peers {
    state: Arc<State>,
    tasks: Mutex<JoinSet<()>>,
    runtime: tokio::runtime::Handle,
}

/// What the streams' tasks share with [`Peers`].
struct State {
    /// By peer: (worker id, endpoint). Never by endpoint alone: see the module docs.
    outboxes: Mutex<HashMap<(String, String), mpsc::UnboundedSender<PeerMessage>>>,
    /// Who opens the streams (a stream opens with a peer pass asked for as this member).
    member: Arc<Member>,
    /// How to reach peers (token, TLS).
    net: dray_net::ClientOptions,
    /// Rays leaving make room for camera rays: the tracing threads hear of it here.
    wake: Arc<Wake>,
}

impl Peers {
    pub fn new(
        runtime: tokio::runtime::Handle,
        member: Arc<Member>,
        net: dray_net::ClientOptions,
        wake: Arc<Wake>,
    ) -> Peers {
        Peers {
            state: Arc::new(State {
                outboxes: Mutex::new(HashMap::new()),
                member,
                net,
                wake,
            }),
            tasks: Mutex::new(JoinSet::new()),
            runtime,
        }
    }

    /// Hand `msg` to the stream to `peer`, opening it if needed. Never waits.
    pub fn send(&self, peer: &Peer, msg: PeerMessage) {
        let n = msg.rays.len();
        msg.job.outgoing_add(n);
        let tx = {
            let mut outboxes = lock(&self.state.outboxes);
            let key = (peer.id.clone(), peer.endpoint.clone());
            match outboxes.get(&key) {
                Some(tx) if !tx.is_closed() => tx.clone(),
                _ => {
                    let (tx, rx) = mpsc::unbounded_channel();
                    outboxes.insert(key, tx.clone());
                    let mut tasks = lock(&self.tasks);
                    // Reap finished streams so the set does not grow.
                    while tasks.try_join_next().is_some() {}
                    tasks.spawn_on(
                        peer_loop(self.state.clone(), peer.clone(), rx),
                        &self.runtime,
                    );
                    tx
                }
            }
        };
        if let Err(e) = tx.send(msg) {
            let m = e.0;
            m.job.outgoing_sub(n);
            unreachable(&m.job, &peer.id);
        }
    }

    /// End every stream (after it sends what it holds, for a moment) and wait for the
    /// tasks.
    pub async fn close(&self) {
        lock(&self.state.outboxes).clear();
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

/// Note that `job`'s rays for `peer` could not be sent (its actor keeps each name once).
fn unreachable(job: &Job, peer: &str) {
    job.post(Report {
        unreachable: vec![peer.to_string()],
        ..Report::default()
    });
}

async fn peer_loop(state: Arc<State>, peer: Peer, mut rx: mpsc::UnboundedReceiver<PeerMessage>) {
    let opened = async {
        // The receiver authenticates the stream's sender by this pass, which only the
        // coordinator can make (see dray_net::peer_pass).
        let me = state.member.id();
        let pass = state
            .member
            .peer_pass(&peer.id)
            .await
            .map_err(|s| format!("no peer pass from the coordinator: {}", s.message()))?;
        let config = PeerClientConfig {
            sender_id: me,
            sender_pass: pass,
            receiver_id: peer.id.clone(),
            ..PeerClientConfig::default()
        };
        let channel = state
            .net
            .endpoint(&peer.endpoint)
            .map_err(|e| e.to_string())?
            .connect_timeout(Duration::from_secs(5))
            .connect()
            .await
            .map_err(|e| e.to_string())?;
        PeerSender::open(state.net.wrap(channel), config)
            .await
            .map_err(|e| e.to_string())
    }
    .await;
    let mut sender = match opened {
        Ok(s) => s,
        Err(e) => {
            peer_failed(&state, &mut rx, &peer, &e, &Carried::default());
            return;
        }
    };
    let mut carried = Carried::default();
    loop {
        let msg = match sender.next_deadline() {
            Some(at) => {
                tokio::select! {
                    m = rx.recv() => m,
                    _ = tokio::time::sleep_until(at) => {
                        if let Err(e) = sender.flush_due().await {
                            peer_failed(&state, &mut rx, &peer, &e.to_string(), &carried);
                            return;
                        }
                        continue;
                    }
                }
            }
            None => rx.recv().await,
        };
        let Some(m) = msg else {
            let _ = sender.flush().await;
            return;
        };
        let n = m.rays.len();
        carried.note(&m.job);
        let key = BatchKey {
            job_id: m.job.key.id.to_string(),
            domain: m.domain,
            routing_version: m.routing_version,
            attempt: m.job.key.attempt,
            forwards: m.forwards,
        };
        // A peer that stops granting room (it was lost) must not hold this stream
        // forever: once the job is released, its rays are dropped with the stream.
        let sent = if m.job.is_active() {
            tokio::select! {
                r = sender.send(&key, &m.rays, &m.tickets) => r.map_err(|e| e.to_string()),
                _ = m.job.released() => {
                    Err("the job was released while its rays waited for the peer".to_string())
                }
            }
        } else {
            Ok(())
        };
        m.job.outgoing_sub(n);
        // Room for camera rays again, perhaps.
        state.wake.notify();
        if let Err(e) = sent {
            peer_failed(&state, &mut rx, &peer, &e, &carried);
            return;
        }
    }
}

/// The jobs whose rays a stream has carried, held weakly (a released job's tracer and
/// scene are not kept alive by a stream that outlives it): when the stream fails, each
/// one still running lost rays with it (in open batches, or sent and not yet queued by
/// the peer) and must name the peer.
#[derive(Default)]
struct Carried(Vec<Weak<Job>>);

impl Carried {
    /// `job`'s rays go on the stream. Jobs released meanwhile are let go.
    fn note(&mut self, job: &Arc<Job>) {
        if self
            .0
            .iter()
            .any(|j| std::ptr::eq(j.as_ptr(), Arc::as_ptr(job)))
        {
            return;
        }
        self.0
            .retain(|j| j.upgrade().is_some_and(|j| j.is_active()));
        self.0.push(Arc::downgrade(job));
    }

    /// The jobs carried that still run.
    fn active(&self) -> impl Iterator<Item = Arc<Job>> + '_ {
        self.0
            .iter()
            .filter_map(Weak::upgrade)
            .filter(|j| j.is_active())
    }
}

/// A peer cannot be reached: drop its rays, now and until the stream is opened again,
/// and name it to every running job that lost rays with the stream (`carried`, and the
/// jobs of the messages still queued for it).
fn peer_failed(
    state: &State,
    rx: &mut mpsc::UnboundedReceiver<PeerMessage>,
    peer: &Peer,
    error: &str,
    carried: &Carried,
) {
    tracing::warn!(worker = %state.member.id(), peer = %peer.id, endpoint = %peer.endpoint, "cannot send rays: {error}");
    rx.close();
    // The next rays for this peer open a new stream.
    lock(&state.outboxes).retain(|_, tx| !tx.is_closed());
    for job in carried.active() {
        unreachable(&job, &peer.id);
    }
    while let Ok(m) = rx.try_recv() {
        m.job.outgoing_sub(m.rays.len());
        if m.job.is_active() {
            unreachable(&m.job, &peer.id);
        }
    }
    state.wake.notify();
}
