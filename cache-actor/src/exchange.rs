//! One `Exchange` stream: a worker's lookups, ticket returns and hit-map outcomes in,
//! answers and acknowledgements out, each message answered before the next is read.
//!
//! Answering in order is the contract the worker relies on (an ack means every return
//! before it is applied, so it may report that credit to the coordinator), and one
//! message at a time keeps it trivially true. Streams are independent: each has its own
//! task, and a message that breaks the protocol ends only its own stream, with a status
//! naming the problem.

use std::pin::Pin;

use dray_proto::v1::{CacheRequest, CacheResponse};
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Status, Streaming};
use tracing::Instrument;

use crate::host::CacheHost;

/// The response half of an `Exchange` stream.
pub type ResponseStream = Pin<Box<dyn Stream<Item = Result<CacheResponse, Status>> + Send>>;

/// Serve one stream on its own task; the returned stream carries the answers.
pub(crate) fn start(
    host: CacheHost,
    inbound: Streaming<CacheRequest>,
    peer: String,
) -> ResponseStream {
    // Answers go out as fast as the worker reads them; a short buffer is enough, and
    // a slow reader then pauses this stream's reading instead of growing memory.
    let (tx, rx) = mpsc::channel(16);
    let span = tracing::debug_span!("cache_exchange", %peer);
    tokio::spawn(run(host, inbound, tx).instrument(span));
    Box::pin(ReceiverStream::new(rx))
}

async fn run(
    host: CacheHost,
    mut inbound: Streaming<CacheRequest>,
    tx: mpsc::Sender<Result<CacheResponse, Status>>,
) {
    tracing::debug!("exchange stream opened");
    let mut messages = 0u64;
    loop {
        let msg = tokio::select! {
            m = inbound.message() => m,
            // The worker went away: stop, even while no message is pending.
            () = tx.closed() => break,
        };
        let req = match msg {
            Ok(Some(req)) => req,
            Ok(None) => break,
            Err(status) => {
                // A message too large or undecodable, or the connection failed: tell the
                // worker why if it is still listening.
                tracing::debug!(%status, "exchange stream ended by transport");
                let _ = tx.send(Err(status)).await;
                break;
            }
        };
        let result = tokio::select! {
            r = host.handle(req) => r,
            () = tx.closed() => break,
        };
        match result {
            Ok(resp) => {
                messages += 1;
                if tx.send(Ok(resp)).await.is_err() {
                    break;
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "exchange stream refused a message");
                let _ = tx.send(Err(e.into())).await;
                break;
            }
        }
    }
    tracing::debug!(messages, "exchange stream closed");
}
