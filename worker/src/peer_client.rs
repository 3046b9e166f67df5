//! The sending side of `RayExchangeService.RayStream`: one [`PeerSender`] per peer.
//!
//! Rays are packed into records (32 to 64 bytes, `dray_core::ray`) as they are handed over and collected in one
//! open batch per destination (job, domain, routing version). A batch is sent when it
//! reaches `batch_rays` rays, or once it is older than `max_delay` (checked on every
//! [`PeerSender::send`] and by [`PeerSender::flush_due`], which the owner calls when it
//! has nothing else to do, at [`PeerSender::next_deadline`] at the latest), or on
//! [`PeerSender::flush`].
//!
//! Flow control: the receiver grants a running total of rays; before sending a batch the
//! sender waits until `rays sent + batch <= rays granted`. So when the receiver's queues
//! fill, `send` stops returning and the tracer feeding it stalls with them, instead of
//! rays piling up in memory. Batches are never larger than the receiver's window (the
//! first grant), so a wait always ends once the receiver drains.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_core::ray::{RAY_RECORD_FORMAT, RAY_RECORD_MAX_BYTES, RayRecord};
use dray_net::AuthChannel;
use dray_proto::v1::ray_exchange_service_client::RayExchangeServiceClient;
use dray_proto::v1::{
    RayBatch, RayStreamOpen, RayStreamRequest, RayTicket, ray_stream_request, ray_stream_response,
};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Status;

use crate::peer_server::MAX_MESSAGE_BYTES;
use crate::tickets::check_tickets;

/// Largest batch sent, so that a batch always fits the receiver's message limit.
pub const MAX_BATCH_RAYS: usize = 64 * 1024;

/// Settings of one outgoing ray stream.
#[derive(Clone, Debug)]
pub struct PeerClientConfig {
    /// This worker's id (`RayStreamOpen.sender_id`).
    pub sender_id: String,
    /// Its peer pass for the receiver (`RayStreamOpen.sender_pass`, from
    /// ClusterService.GetPeerPass).
    pub sender_pass: String,
    /// The id of the worker the stream is for; empty if not known.
    pub receiver_id: String,
    /// Rays per batch before it is sent (clamped to the receiver's window).
    pub batch_rays: usize,
    /// Longest time a ray waits in an open batch.
    pub max_delay: Duration,
}

impl Default for PeerClientConfig {
    fn default() -> Self {
        PeerClientConfig {
            sender_id: String::new(),
            sender_pass: String::new(),
            receiver_id: String::new(),
            batch_rays: 4096,
            max_delay: Duration::from_millis(2),
        }
    }
}

/// Where a batch goes: every ray of a batch shares these.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct BatchKey {
    /// The job the rays belong to.
    pub job_id: String,
    /// The domain the rays enter next.
    pub domain: u32,
    /// Routing-table version used to pick the receiver.
    pub routing_version: u64,
    /// The job attempt the rays belong to.
    pub attempt: u32,
    /// How many times these rays were forwarded before (0 for rays sent by the worker
    /// that made them).
    pub forwards: u32,
}

/// Why rays could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum PeerError {
    #[error("cannot connect to the peer: {0}")]
    Connect(#[from] tonic::transport::Error),
    #[error("the peer ended the ray stream: {0}")]
    Status(Box<Status>),
    #[error("the peer broke the ray-stream protocol: {0}")]
    Protocol(&'static str),
    #[error("the ray stream is closed")]
    Closed,
    #[error("tickets do not match the ticketed rays: {detail}")]
    TicketMismatch { detail: String },
}

impl From<Status> for PeerError {
    fn from(s: Status) -> Self {
        PeerError::Status(Box::new(s))
    }
}

/// What the receiver has told the sender so far.
#[derive(Clone, Copy, Debug, Default)]
struct Grant {
    rays_granted: u64,
    acked_through: u64,
}

struct Pending {
    key: BatchKey,
    records: Vec<u8>,
    count: usize,
    tickets: Vec<RayTicket>,
    since: Instant,
}

/// One open ray stream to a peer.
pub struct PeerSender {
    requests: Option<mpsc::Sender<RayStreamRequest>>,
    grants: watch::Receiver<Grant>,
    failure: Arc<Mutex<Option<Status>>>,
    reader: JoinHandle<()>,
    config: PeerClientConfig,
    batch_rays: usize,
    sent: u64,
    sequence: u64,
    pending: Vec<Pending>,
}

impl Drop for PeerSender {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

impl PeerSender {
    /// Open a stream on `channel` and wait for the receiver's first grant.
    pub async fn open(
        channel: AuthChannel,
        config: PeerClientConfig,
    ) -> Result<PeerSender, PeerError> {
        let mut client = RayExchangeServiceClient::new(channel)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        // Two batches in the channel keep the wire busy while the next one is packed.
        let (tx, rx) = mpsc::channel(2);
        let open = RayStreamRequest {
            msg: Some(ray_stream_request::Msg::Open(RayStreamOpen {
                sender_id: config.sender_id.clone(),
                receiver_id: config.receiver_id.clone(),
                record_format: RAY_RECORD_FORMAT,
                sender_pass: config.sender_pass.clone(),
            })),
        };
        tx.send(open).await.map_err(|_| PeerError::Closed)?;
        let mut inbound = client
            .ray_stream(ReceiverStream::new(rx))
            .await?
            .into_inner();
        let window = match inbound.message().await? {
            Some(dray_proto::v1::RayStreamResponse {
                msg: Some(ray_stream_response::Msg::Accept(a)),
            }) => a.rays_granted,
            Some(_) => return Err(PeerError::Protocol("first response is not RayStreamAccept")),
            None => return Err(PeerError::Protocol("stream ended before RayStreamAccept")),
        };
        if window == 0 {
            return Err(PeerError::Protocol("receiver granted no rays"));
        }
        let (grant_tx, grants) = watch::channel(Grant {
            rays_granted: window,
            acked_through: 0,
        });
        let failure = Arc::new(Mutex::new(None));
        let reader_failure = Arc::clone(&failure);
        let reader = tokio::spawn(async move {
            loop {
                match inbound.message().await {
                    Ok(Some(dray_proto::v1::RayStreamResponse {
                        msg: Some(ray_stream_response::Msg::Ack(ack)),
                    })) => {
                        // Grants are cumulative: never let a stale ack shrink them.
                        grant_tx.send_modify(|g| {
                            g.rays_granted = g.rays_granted.max(ack.rays_granted);
                            g.acked_through = g.acked_through.max(ack.acked_through);
                        });
                    }
                    Ok(Some(_)) => {
                        set_failure(
                            &reader_failure,
                            Status::internal("unexpected message on ray stream"),
                        );
                        break;
                    }
                    Ok(None) => break,
                    Err(status) => {
                        set_failure(&reader_failure, status);
                        break;
                    }
                }
            }
            // Dropping `grant_tx` wakes every waiter with an error.
        });
        let batch_rays = config
            .batch_rays
            .clamp(1, usize::try_from(window).unwrap_or(usize::MAX))
            .min(MAX_BATCH_RAYS);
        Ok(PeerSender {
            requests: Some(tx),
            grants,
            failure,
            reader,
            config,
            batch_rays,
            sent: 0,
            sequence: 0,
            pending: Vec::new(),
        })
    }

    /// Rays per batch actually used (the configured size, at most the receiver's window).
    pub fn batch_rays(&self) -> usize {
        self.batch_rays
    }

    /// Rays sent on the stream so far (not counting open batches).
    pub fn rays_sent(&self) -> u64 {
        self.sent
    }

    /// The receiver's cumulative grant.
    pub fn rays_granted(&self) -> u64 {
        self.grants.borrow().rays_granted
    }

    /// Rays waiting in open batches.
    pub fn rays_buffered(&self) -> usize {
        self.pending.iter().map(|p| p.count).sum()
    }

    /// Add `rays` to the open batch for `key`, sending batches that fill up or are due.
    /// `tickets` are the rays' cache tickets by index into `rays`, in increasing order,
    /// one or more for each ray with the TICKETED flag and none for the others. Waits
    /// while the receiver has not granted room for a full batch.
    pub async fn send(
        &mut self,
        key: &BatchKey,
        rays: &[RayRecord],
        tickets: &[RayTicket],
    ) -> Result<(), PeerError> {
        check_tickets(rays, tickets).map_err(|detail| PeerError::TicketMismatch { detail })?;
        let mut idx = match self.pending.iter().position(|p| &p.key == key) {
            Some(i) => i,
            None => self.new_pending(key.clone()),
        };
        let mut tickets = tickets.iter().peekable();
        let mut index = 0u32;
        let mut rest = rays;
        while !rest.is_empty() {
            let p = &mut self.pending[idx];
            let take = (self.batch_rays - p.count).min(rest.len());
            let (now, later) = rest.split_at(take);
            rest = later;
            p.records.reserve(take * RAY_RECORD_MAX_BYTES);
            for r in now {
                while let Some(t) = tickets.next_if(|t| t.record == index) {
                    p.tickets.push(RayTicket {
                        record: p.count as u32,
                        ticket: t.ticket,
                    });
                }
                index += 1;
                r.write_to(&mut p.records);
                p.count += 1;
            }
            if p.count >= self.batch_rays {
                self.flush_at(idx).await?;
                idx = match self.pending.iter().position(|p| &p.key == key) {
                    Some(i) => i,
                    None => self.new_pending(key.clone()),
                };
            }
        }
        self.flush_due().await
    }

    fn new_pending(&mut self, key: BatchKey) -> usize {
        self.pending.push(Pending {
            key,
            records: Vec::with_capacity(self.batch_rays * RAY_RECORD_MAX_BYTES),
            count: 0,
            tickets: Vec::new(),
            since: Instant::now(),
        });
        self.pending.len() - 1
    }

    /// When the oldest open batch becomes due, if any batch is open.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.pending
            .iter()
            .filter(|p| p.count > 0)
            .map(|p| p.since + self.config.max_delay)
            .min()
    }

    /// Send every open batch older than `max_delay`.
    pub async fn flush_due(&mut self) -> Result<(), PeerError> {
        let now = Instant::now();
        while let Some(i) = self
            .pending
            .iter()
            .position(|p| p.count > 0 && p.since + self.config.max_delay <= now)
        {
            self.flush_at(i).await?;
        }
        Ok(())
    }

    /// Send every open batch.
    pub async fn flush(&mut self) -> Result<(), PeerError> {
        while let Some(i) = self.pending.iter().position(|p| p.count > 0) {
            self.flush_at(i).await?;
        }
        Ok(())
    }

    /// Send the open batch at `idx` (removing it), waiting for credit first.
    async fn flush_at(&mut self, idx: usize) -> Result<(), PeerError> {
        let p = self.pending.swap_remove(idx);
        if p.count == 0 {
            return Ok(());
        }
        let n = p.count as u64;
        let sent = self.sent;
        self.wait_until(|g| sent + n <= g.rays_granted).await?;
        self.sequence += 1;
        let batch = RayBatch {
            job_id: p.key.job_id,
            domain: p.key.domain,
            routing_version: p.key.routing_version,
            sequence: self.sequence,
            count: p.count as u32,
            records: p.records,
            tickets: p.tickets,
            forwards: p.key.forwards,
            attempt: p.key.attempt,
        };
        self.send_raw(RayStreamRequest {
            msg: Some(ray_stream_request::Msg::Batch(batch)),
        })
        .await?;
        self.sent += n;
        Ok(())
    }

    /// Put a message on the stream as is, bypassing batching and credit (for tests of
    /// the receiver's checks, and for forwarding a batch unchanged).
    pub async fn send_raw(&mut self, msg: RayStreamRequest) -> Result<(), PeerError> {
        let Some(tx) = &self.requests else {
            return Err(PeerError::Closed);
        };
        if tx.send(msg).await.is_err() {
            return Err(self.failure_or_closed());
        }
        Ok(())
    }

    async fn wait_until(&mut self, ready: impl Fn(&Grant) -> bool) -> Result<(), PeerError> {
        loop {
            if ready(&self.grants.borrow_and_update()) {
                return Ok(());
            }
            if self.grants.changed().await.is_err() {
                // The stream ended; the last grant may still have been enough.
                if ready(&self.grants.borrow()) {
                    return Ok(());
                }
                return Err(self.failure_or_closed());
            }
        }
    }

    fn failure_or_closed(&self) -> PeerError {
        match dray_sync::lock(&self.failure).take() {
            Some(s) => PeerError::from(s),
            None => PeerError::Closed,
        }
    }

    /// Send every open batch and wait until the receiver has queued all of them.
    pub async fn drain(&mut self) -> Result<(), PeerError> {
        self.flush().await?;
        let last = self.sequence;
        self.wait_until(|g| g.acked_through >= last).await
    }

    /// Wait until the receiver ends the stream: `Ok` if it ended cleanly, the receiver's
    /// status otherwise (for example after a refused batch).
    pub async fn closed(&mut self) -> Result<(), PeerError> {
        while self.grants.changed().await.is_ok() {}
        match self.failure_or_closed() {
            PeerError::Closed => Ok(()),
            e => Err(e),
        }
    }

    /// [`drain`](Self::drain), then end the stream.
    pub async fn close(mut self) -> Result<(), PeerError> {
        self.drain().await?;
        self.requests = None;
        Ok(())
    }
}

fn set_failure(slot: &Mutex<Option<Status>>, status: Status) {
    *dray_sync::lock(slot) = Some(status);
}
