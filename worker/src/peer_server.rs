//! The receiving side of `RayExchangeService.RayStream`.
//!
//! One task per incoming stream reads batches in order, validates them (header, record
//! framing, the credit the sender was granted, tickets), decodes the packed records and
//! pushes them into the [`RayQueues`] of their job attempt and domain. Every domain is
//! accepted: rays for a job whose setup is still on its way wait for it, and rays for a
//! domain this worker does not own (any more) are forwarded by the tracing side. Credit follows the queues: the stream
//! opens with a grant of `stream_window` rays, and each batch is acknowledged, and its
//! rays granted again, only once it is queued. While a queue is full the push waits, no
//! acks go out, and the sender runs out of credit. A sender therefore never has more than
//! `stream_window` rays in flight towards this worker, and the queues never exceed their
//! capacity: memory stays bounded however many rays the scene spawns.
//!
//! A batch that breaks the protocol ends that stream with a status naming the problem;
//! other streams are not affected.

use std::pin::Pin;
use std::sync::Arc;

use dray_core::ray::{RAY_RECORD_FORMAT, RAY_RECORD_MAX_BYTES, RecordError};
use dray_core::ray::{check_count, decode_rays_into};
use dray_proto::v1::ray_exchange_service_server::{RayExchangeService, RayExchangeServiceServer};
use dray_proto::v1::{
    RayBatch, RayBatchAck, RayStreamAccept, RayStreamRequest, RayStreamResponse,
    ray_stream_request, ray_stream_response,
};
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Response, Status, Streaming};

use crate::queue::{QueueError, QueuedBatch, RayQueues};

/// Largest gRPC message the server accepts: a batch of 64 Ki rays of the largest record
/// plus its header.
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024 * RAY_RECORD_MAX_BYTES + 64 * 1024;

/// Settings of a worker's ray-stream server.
#[derive(Clone, Debug)]
pub struct PeerServerConfig {
    /// This worker's id at start (see [`PeerServer::set_worker_id`]); a stream opened for another id is refused (a restarted process
    /// on a reused port must not take rays meant for its predecessor). Empty: accept any.
    pub worker_id: String,
    /// Rays a sender may have in flight on one stream (queued-but-unacknowledged plus on
    /// the wire). Clamped to the queue capacity, so one batch always fits a queue.
    pub stream_window: u64,
}

impl Default for PeerServerConfig {
    fn default() -> Self {
        PeerServerConfig {
            worker_id: String::new(),
            stream_window: 16 * 1024,
        }
    }
}

/// Why a stream was ended by the receiver; becomes the gRPC status the sender sees.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error("the first message of a ray stream must be RayStreamOpen")]
    NotOpened,
    #[error(
        "the stream's sender_pass does not prove its sender_id (ask the coordinator for a \
         peer pass with GetPeerPass)"
    )]
    NotAuthenticated,
    #[error("RayStreamOpen sent twice")]
    OpenedTwice,
    #[error("message without content")]
    Empty,
    #[error("stream is for worker {expected:?}, but this is worker {actual:?}")]
    WrongReceiver { expected: String, actual: String },
    #[error(
        "unsupported ray record format {format} (this worker reads format {RAY_RECORD_FORMAT})"
    )]
    UnsupportedFormat { format: u32 },
    #[error("batch sequence {got}, expected {expected}")]
    Sequence { got: u64, expected: u64 },
    #[error("batch {sequence}: {source}")]
    Record {
        sequence: u64,
        #[source]
        source: RecordError,
    },
    #[error(
        "batch {sequence}: {count} rays exceed the grant ({granted} granted, {sent} already sent)"
    )]
    OverGrant {
        sequence: u64,
        count: usize,
        granted: u64,
        sent: u64,
    },
    #[error("batch {sequence}: {detail}")]
    BadTickets { sequence: u64, detail: String },
    #[error("batch {sequence}: {source}")]
    Queue {
        sequence: u64,
        #[source]
        source: QueueError,
    },
}

impl StreamError {
    fn code(&self) -> Code {
        match self {
            StreamError::WrongReceiver { .. } | StreamError::UnsupportedFormat { .. } => {
                Code::FailedPrecondition
            }
            StreamError::OverGrant { .. } => Code::ResourceExhausted,
            StreamError::NotAuthenticated => Code::PermissionDenied,
            _ => Code::InvalidArgument,
        }
    }
}

impl From<StreamError> for Status {
    fn from(e: StreamError) -> Status {
        Status::new(e.code(), e.to_string())
    }
}

/// `RayExchangeService` backed by a worker's ray queues.
#[derive(Clone)]
pub struct PeerServer {
    queues: Arc<RayQueues>,
    config: PeerServerConfig,
    /// The worker id streams must be opened for; starts as `config.worker_id` and
    /// changes when the worker registers again (a new coordinator gives a new id).
    worker_id: Arc<std::sync::RwLock<String>>,
    /// This worker's member secret, once registered: a stream's sender must present the
    /// pass made from it (see `dray_net::peer_pass`). Empty until then.
    secret: Arc<std::sync::RwLock<String>>,
}

impl PeerServer {
    /// A server that queues incoming rays into `queues`.
    pub fn new(queues: Arc<RayQueues>, config: PeerServerConfig) -> PeerServer {
        PeerServer {
            queues,
            worker_id: Arc::new(std::sync::RwLock::new(config.worker_id.clone())),
            secret: Arc::new(std::sync::RwLock::new(String::new())),
            config,
        }
    }

    /// From now on, accept streams opened for `id` (the worker registered again).
    /// Clones of this server share the change.
    pub fn set_worker_id(&self, id: &str) {
        let mut w = dray_sync::write(&self.worker_id);
        *w = id.to_string();
    }

    /// From now on, require senders' passes made from `secret`, this worker's member
    /// secret at its coordinator. Clones of this server share the change.
    pub fn set_member_secret(&self, secret: &str) {
        let mut w = dray_sync::write(&self.secret);
        *w = secret.to_string();
    }

    fn worker_id(&self) -> String {
        dray_sync::read(&self.worker_id).clone()
    }

    /// The tonic service, with message limits sized for full batches.
    pub fn into_service(self) -> RayExchangeServiceServer<PeerServer> {
        RayExchangeServiceServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }

    fn window(&self) -> u64 {
        let cap = u64::try_from(self.queues.capacity()).unwrap_or(u64::MAX);
        self.config.stream_window.clamp(1, cap)
    }
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<RayStreamResponse, Status>> + Send>>;

#[tonic::async_trait]
impl RayExchangeService for PeerServer {
    type RayStreamStream = ResponseStream;

    async fn ray_stream(
        &self,
        request: Request<Streaming<RayStreamRequest>>,
    ) -> Result<Response<ResponseStream>, Status> {
        let mut inbound = request.into_inner();
        let open = match inbound.message().await? {
            Some(RayStreamRequest {
                msg: Some(ray_stream_request::Msg::Open(open)),
            }) => open,
            _ => return Err(StreamError::NotOpened.into()),
        };
        let me = self.worker_id();
        if !me.is_empty() && !open.receiver_id.is_empty() && open.receiver_id != me {
            return Err(StreamError::WrongReceiver {
                expected: open.receiver_id,
                actual: me,
            }
            .into());
        }
        let secret = dray_sync::read(&self.secret).clone();
        if !secret.is_empty()
            && !dray_net::peer_pass::verify_peer_pass(&secret, &open.sender_id, &open.sender_pass)
        {
            tracing::warn!(
                sender = %open.sender_id.chars().take(80).collect::<String>(),
                "ray stream refused: the sender's pass is not valid"
            );
            return Err(StreamError::NotAuthenticated.into());
        }
        if open.record_format != RAY_RECORD_FORMAT {
            return Err(StreamError::UnsupportedFormat {
                format: open.record_format,
            }
            .into());
        }
        let window = self.window();
        tracing::debug!(sender = %open.sender_id, window, "ray stream opened");
        // Acks are small and the sender reads them as they come; a short buffer is enough.
        let (tx, rx) = mpsc::channel(16);
        let accept = RayStreamResponse {
            msg: Some(ray_stream_response::Msg::Accept(RayStreamAccept {
                rays_granted: window,
            })),
        };
        // Cannot fail: the receiver is alive and the buffer empty.
        let _ = tx.try_send(Ok(accept));
        let receiver = StreamReceiver {
            queues: Arc::clone(&self.queues),
            granted: window,
            sent: 0,
            next_sequence: 1,
            scratch: Vec::new(),
        };
        // A panic while taking the peer's rays ends this stream with the panic's
        // message to the sender, not silently (the sender reports it; the job fails).
        let fail = tx.clone();
        let sender = open.sender_id.clone();
        tokio::spawn(async move {
            if let Err(panic) =
                dray_net::contain::contained(receiver.run(inbound, tx, sender)).await
            {
                tracing::error!(sender = %open.sender_id, %panic, "ray stream receiver panicked");
                let _ = fail
                    .send(Err(Status::internal(format!(
                        "internal error (a panic while receiving rays, contained): {panic}"
                    ))))
                    .await;
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// The state of one incoming stream.
struct StreamReceiver {
    queues: Arc<RayQueues>,
    /// Cumulative grant sent to the peer.
    granted: u64,
    /// Rays received on the stream so far.
    sent: u64,
    next_sequence: u64,
    scratch: Vec<dray_core::ray::RayRecord>,
}

type AckSender = mpsc::Sender<Result<RayStreamResponse, Status>>;

impl StreamReceiver {
    async fn run(
        mut self,
        mut inbound: Streaming<RayStreamRequest>,
        tx: AckSender,
        sender: String,
    ) {
        loop {
            let msg = tokio::select! {
                m = inbound.message() => m,
                // The peer went away: stop, even while no message is pending.
                () = tx.closed() => return,
            };
            let batch = match msg {
                Ok(Some(RayStreamRequest {
                    msg: Some(ray_stream_request::Msg::Batch(b)),
                })) => b,
                Ok(Some(RayStreamRequest {
                    msg: Some(ray_stream_request::Msg::Open(_)),
                })) => {
                    let _ = tx.send(Err(StreamError::OpenedTwice.into())).await;
                    return;
                }
                Ok(Some(RayStreamRequest { msg: None })) => {
                    let _ = tx.send(Err(StreamError::Empty.into())).await;
                    return;
                }
                Ok(None) => return,
                Err(status) => {
                    tracing::debug!(%sender, %status, "ray stream ended by transport");
                    return;
                }
            };
            let result = tokio::select! {
                r = self.accept_batch(batch) => r,
                () = tx.closed() => return,
            };
            match result {
                Ok(acked) => {
                    let ack = RayStreamResponse {
                        msg: Some(ray_stream_response::Msg::Ack(RayBatchAck {
                            acked_through: acked,
                            rays_granted: self.granted,
                        })),
                    };
                    if tx.send(Ok(ack)).await.is_err() {
                        return;
                    }
                }
                Err(e) => {
                    tracing::warn!(%sender, error = %e, "ray stream refused a batch");
                    let _ = tx.send(Err(e.into())).await;
                    return;
                }
            }
        }
    }

    /// Validate, decode and queue one batch; returns its sequence number once queued.
    async fn accept_batch(&mut self, batch: RayBatch) -> Result<u64, StreamError> {
        let sequence = batch.sequence;
        if sequence != self.next_sequence {
            return Err(StreamError::Sequence {
                got: sequence,
                expected: self.next_sequence,
            });
        }
        // `count` against the bytes first (each record is 32 to 64 bytes), so the grant
        // check below trusts a plausible count; decoding then checks it exactly.
        let records = check_count(u64::from(batch.count), batch.records.len())
            .map_err(|source| StreamError::Record { sequence, source })?;
        let n = records as u64;
        if self.sent + n > self.granted {
            return Err(StreamError::OverGrant {
                sequence,
                count: records,
                granted: self.granted,
                sent: self.sent,
            });
        }
        self.scratch.clear();
        decode_rays_into(&batch.records, records, &mut self.scratch)
            .map_err(|source| StreamError::Record { sequence, source })?;
        crate::tickets::check_tickets(&self.scratch, &batch.tickets)
            .map_err(|detail| StreamError::BadTickets { sequence, detail })?;
        let rays = std::mem::replace(&mut self.scratch, Vec::with_capacity(records));
        let queued = QueuedBatch {
            job_id: Arc::from(batch.job_id),
            attempt: batch.attempt,
            routing_version: batch.routing_version,
            forwards: batch.forwards,
            rays,
            tickets: batch.tickets,
        };
        self.queues
            .push(batch.domain, queued)
            .await
            .map_err(|source| StreamError::Queue { sequence, source })?;
        self.sent += n;
        self.next_sequence += 1;
        // The batch is out of flight and in the queue: the sender may send as many rays
        // again. The queue's own capacity bounds what is queued; this bounds what waits.
        self.granted += n;
        Ok(sequence)
    }
}
