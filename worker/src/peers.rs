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

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_core::ray::RayRecord;
use dray_proto::v1::{GetPeerPassRequest, RayTicket};
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use crate::jobs::{Job, Report, lock};
use crate::node::Shared;
use crate::peer_client::{BatchKey, PeerClientConfig, PeerSender};
use crate::routing::Peer;

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
    /// By endpoint.
    outboxes: Mutex<HashMap<String, mpsc::UnboundedSender<PeerMessage>>>,
    tasks: Mutex<JoinSet<()>>,
    runtime: tokio::runtime::Handle,
}

impl Peers {
    pub fn new(runtime: tokio::runtime::Handle) -> Peers {
        Peers {
            outboxes: Mutex::new(HashMap::new()),
            tasks: Mutex::new(JoinSet::new()),
            runtime,
        }
    }

    /// Hand `msg` to the stream to `peer`, opening it if needed. Never waits.
    pub fn send(&self, shared: &Arc<Shared>, peer: &Peer, msg: PeerMessage) {
        let n = msg.rays.len();
        msg.job.outgoing_add(n);
        let tx = {
            let mut outboxes = lock(&self.outboxes);
            match outboxes.get(&peer.endpoint) {
                Some(tx) if !tx.is_closed() => tx.clone(),
                _ => {
                    let (tx, rx) = mpsc::unbounded_channel();
                    outboxes.insert(peer.endpoint.clone(), tx.clone());
                    let mut tasks = lock(&self.tasks);
                    // Reap finished streams so the set does not grow.
                    while tasks.try_join_next().is_some() {}
                    tasks.spawn_on(peer_loop(shared.clone(), peer.clone(), rx), &self.runtime);
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
        lock(&self.outboxes).clear();
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

async fn peer_loop(shared: Arc<Shared>, peer: Peer, mut rx: mpsc::UnboundedReceiver<PeerMessage>) {
    let opened = async {
        // The receiver authenticates the stream's sender by this pass, which only the
        // coordinator can make (see dray_net::peer_pass).
        let me = shared.id();
        let pass = shared
            .client
            .clone()
            .get_peer_pass(shared.as_member(GetPeerPassRequest {
                worker_id: me.clone(),
                peer_id: peer.id.clone(),
            }))
            .await
            .map_err(|s| format!("no peer pass from the coordinator: {}", s.message()))?
            .into_inner()
            .pass;
        let config = PeerClientConfig {
            sender_id: me,
            sender_pass: pass,
            receiver_id: peer.id.clone(),
            ..PeerClientConfig::default()
        };
        let channel = shared
            .net
            .endpoint(&peer.endpoint)
            .map_err(|e| e.to_string())?
            .connect_timeout(Duration::from_secs(5))
            .connect()
            .await
            .map_err(|e| e.to_string())?;
        PeerSender::open(shared.net.wrap(channel), config)
            .await
            .map_err(|e| e.to_string())
    }
    .await;
    let mut sender = match opened {
        Ok(s) => s,
        Err(e) => {
            peer_failed(&shared, &mut rx, &peer, &e);
            return;
        }
    };
    loop {
        let msg = match sender.next_deadline() {
            Some(at) => {
                tokio::select! {
                    m = rx.recv() => m,
                    _ = tokio::time::sleep_until(at) => {
                        if let Err(e) = sender.flush_due().await {
                            peer_failed(&shared, &mut rx, &peer, &e.to_string());
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
        shared.notify();
        if let Err(e) = sent {
            if m.job.is_active() {
                unreachable(&m.job, &peer.id);
            }
            peer_failed(&shared, &mut rx, &peer, &e);
            return;
        }
    }
}

/// A peer cannot be reached: drop its rays, now and until the stream is opened again.
fn peer_failed(
    shared: &Shared,
    rx: &mut mpsc::UnboundedReceiver<PeerMessage>,
    peer: &Peer,
    error: &str,
) {
    tracing::warn!(worker = %shared.id(), peer = %peer.id, endpoint = %peer.endpoint, "cannot send rays: {error}");
    rx.close();
    // The next rays for this peer open a new stream.
    lock(&shared.peers.outboxes).retain(|_, tx| !tx.is_closed());
    while let Ok(m) = rx.try_recv() {
        m.job.outgoing_sub(m.rays.len());
        if m.job.is_active() {
            unreachable(&m.job, &peer.id);
        }
    }
    shared.notify();
}
