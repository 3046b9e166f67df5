//! A request body that must arrive whole within a deadline.
//!
//! An HTTP/2 client can send a call's headers and never its body (no DATA frame, no
//! END_STREAM), or its message and never END_STREAM (tonic's unary and
//! server-streaming handlers read the request to its end, for its trailers, before they
//! run). The call has then been admitted and waits for what never comes, holding its
//! place among the calls in progress ([`crate::admission`]). [`BodyDeadline`] wraps such
//! a request's body: until the body has ended, reading it fails with DEADLINE_EXCEEDED
//! once the deadline has passed; the handler's decoder then ends the call with that
//! status and its place is freed. It is only used for requests made of one message:
//! a streaming request's messages may come at any time.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http_body::{Body as HttpBody, Frame, SizeHint};
use tokio::time::{Instant, Sleep};
use tonic::Status;
use tonic::body::Body;

/// See the module.
pub struct BodyDeadline {
    inner: Body,
    /// `None` once the body has ended (or the deadline was reported).
    waiting: Option<Waiting>,
}

struct Waiting {
    deadline: Pin<Box<Sleep>>,
    timeout: Duration,
}

impl BodyDeadline {
    /// `inner`, which must end within `timeout` from now.
    pub fn new(inner: Body, timeout: Duration) -> BodyDeadline {
        BodyDeadline {
            inner,
            waiting: Some(Waiting {
                deadline: Box::pin(tokio::time::sleep_until(Instant::now() + timeout)),
                timeout,
            }),
        }
    }
}

impl HttpBody for BodyDeadline {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => Poll::Ready(Some(Ok(frame))),
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
                    "a request did not arrive whole in time; the call ends"
                );
                Poll::Ready(Some(Err(Status::deadline_exceeded(format!(
                    "the request did not arrive whole within the server's limit of {} s",
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

    async fn next(body: &mut BodyDeadline) -> Option<Result<Frame<Bytes>, Status>> {
        std::future::poll_fn(|cx| Pin::new(&mut *body).poll_frame(cx)).await
    }

    #[tokio::test]
    async fn a_body_that_does_not_end_fails_with_deadline_exceeded() {
        let (tx, rx) = tokio::sync::mpsc::channel::<Result<Frame<Bytes>, Status>>(4);
        let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
        let mut body = BodyDeadline::new(
            Body::new(http_body_util::StreamBody::new(stream)),
            Duration::from_millis(50),
        );
        // A message arrives, the end of the body never does.
        tx.send(Ok(Frame::data(Bytes::from_static(&[0, 0, 0, 0, 0]))))
            .await
            .expect("send");
        assert!(matches!(next(&mut body).await, Some(Ok(_))));
        match next(&mut body).await {
            Some(Err(s)) => assert_eq!(s.code(), tonic::Code::DeadlineExceeded),
            _ => panic!("expected DEADLINE_EXCEEDED"),
        }
    }

    #[tokio::test]
    async fn a_body_that_ends_in_time_is_passed_through() {
        let (tx, rx) = tokio::sync::mpsc::channel::<Result<Frame<Bytes>, Status>>(4);
        let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
        let mut body = BodyDeadline::new(
            Body::new(http_body_util::StreamBody::new(stream)),
            Duration::from_millis(50),
        );
        tx.send(Ok(Frame::data(Bytes::from_static(&[0, 0, 0, 0, 0]))))
            .await
            .expect("send");
        drop(tx);
        assert!(matches!(next(&mut body).await, Some(Ok(_))));
        assert!(next(&mut body).await.is_none());
        // Long after the deadline, nothing more.
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(next(&mut body).await.is_none());
    }
}
