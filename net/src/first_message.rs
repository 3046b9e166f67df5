//! A request body whose first gRPC message must arrive within a deadline.
//!
//! An HTTP/2 client can send a call's headers and never its body (no DATA frame, no
//! END_STREAM). The call has then been admitted and its handler waits for a message
//! that never comes, holding its place among the calls in progress
//! ([`crate::admission`]). [`FirstMessage`] wraps such a request's body: until the first
//! message is complete (its 5-byte gRPC prefix and the length it announces) or the body
//! ends, reading it fails with DEADLINE_EXCEEDED once the deadline has passed. The
//! handler's decoder then ends the call with that status and its place is freed.
//! After the first message nothing is timed: it is only used for requests made of one
//! message.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::{Buf, Bytes};
use http_body::{Body as HttpBody, Frame, SizeHint};
use tokio::time::{Instant, Sleep};
use tonic::Status;
use tonic::body::Body;

/// The gRPC message prefix: a compression flag and a 32-bit big-endian length.
const PREFIX: usize = 5;

/// See the module.
pub struct FirstMessage {
    inner: Body,
    /// `None` once the first message has arrived (or the body ended, or the deadline
    /// was reported).
    waiting: Option<Waiting>,
}

struct Waiting {
    deadline: Pin<Box<Sleep>>,
    timeout: Duration,
    /// The first bytes of the message prefix seen so far.
    prefix: [u8; PREFIX],
    /// Bytes of the body seen so far.
    seen: u64,
}

impl FirstMessage {
    /// `inner`, whose first message must be complete within `timeout` from now.
    pub fn new(inner: Body, timeout: Duration) -> FirstMessage {
        FirstMessage {
            inner,
            waiting: Some(Waiting {
                deadline: Box::pin(tokio::time::sleep_until(Instant::now() + timeout)),
                timeout,
                prefix: [0; PREFIX],
                seen: 0,
            }),
        }
    }
}

impl Waiting {
    /// Count `data`; whether the first message is now complete.
    fn complete_after(&mut self, data: &Bytes) -> bool {
        let mut chunk = data.chunk();
        while (self.seen as usize) < PREFIX && !chunk.is_empty() {
            self.prefix[self.seen as usize] = chunk[0];
            chunk = &chunk[1..];
            self.seen += 1;
        }
        self.seen += chunk.len() as u64;
        if (self.seen as usize) < PREFIX {
            return false;
        }
        let length = u32::from_be_bytes([
            self.prefix[1],
            self.prefix[2],
            self.prefix[3],
            self.prefix[4],
        ]);
        self.seen >= PREFIX as u64 + u64::from(length)
    }
}

impl HttpBody for FirstMessage {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let (Some(waiting), Some(data)) = (this.waiting.as_mut(), frame.data_ref())
                    && waiting.complete_after(data)
                {
                    this.waiting = None;
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(other) => {
                this.waiting = None;
                Poll::Ready(other)
            }
            Poll::Pending => {
                let Some(waiting) = this.waiting.as_mut() else {
                    return Poll::Pending;
                };
                if waiting.deadline.as_mut().poll(cx).is_pending() {
                    return Poll::Pending;
                }
                let timeout = waiting.timeout;
                this.waiting = None;
                tracing::warn!(
                    timeout_s = timeout.as_secs_f64(),
                    "a request's message did not arrive in time; the call ends"
                );
                Poll::Ready(Some(Err(Status::deadline_exceeded(format!(
                    "the request's message did not arrive within the server's limit of {} s",
                    timeout.as_secs_f64()
                )))))
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn waiting() -> Waiting {
        Waiting {
            deadline: Box::pin(tokio::time::sleep(Duration::from_secs(1))),
            timeout: Duration::from_secs(1),
            prefix: [0; PREFIX],
            seen: 0,
        }
    }

    #[tokio::test]
    async fn a_message_is_complete_when_its_announced_length_has_arrived() {
        let mut w = waiting();
        // Prefix split over frames: flag, then length 3 in two pieces.
        assert!(!w.complete_after(&Bytes::from_static(&[0, 0])));
        assert!(!w.complete_after(&Bytes::from_static(&[0, 0, 3, 1])));
        assert!(!w.complete_after(&Bytes::from_static(&[2])));
        assert!(w.complete_after(&Bytes::from_static(&[3])));
        // An empty message: the prefix alone.
        let mut w = waiting();
        assert!(w.complete_after(&Bytes::from_static(&[0, 0, 0, 0, 0])));
        // A message and the start of another in one frame.
        let mut w = waiting();
        assert!(w.complete_after(&Bytes::from_static(&[0, 0, 0, 0, 1, 9, 0, 0])));
    }

    #[tokio::test]
    async fn a_body_that_never_comes_fails_with_deadline_exceeded() {
        // A body that never yields a frame.
        let (_tx, body) = {
            let (tx, rx) = tokio::sync::mpsc::channel::<Result<Frame<Bytes>, Status>>(1);
            let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
            (tx, Body::new(http_body_util::StreamBody::new(stream)))
        };
        let mut body = FirstMessage::new(body, Duration::from_millis(50));
        let frame = std::future::poll_fn(|cx| Pin::new(&mut body).poll_frame(cx)).await;
        let status = match frame {
            Some(Err(s)) => s,
            _ => panic!("expected an error"),
        };
        assert_eq!(status.code(), tonic::Code::DeadlineExceeded);
    }
}
