//! The dashboard's calls in progress, bounded as the gRPC API's are (`--max-calls`,
//! `dray_net::admission`): at most that many `/api/` requests in progress at once, in
//! a budget of the dashboard's own (so the page cannot take gRPC clients' places, nor
//! they the page's); more are refused at once with 429 RESOURCE_EXHAUSTED, as gRPC
//! sheds with RESOURCE_EXHAUSTED. A request holds its place until its response has
//! been sent (an event stream: until it ends), not only while its handler runs: an
//! image a slow client reads holds its place (issue 45, item 4: the image endpoint was
//! outside `--max-calls`). Requests are counted once they are let in, so refused
//! credentials cost nothing here.

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body::{Frame, SizeHint};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::Dashboard;
use super::error::ApiError;

/// The places; see the module.
pub struct CallBudget {
    limit: usize,
    places: Arc<Semaphore>,
}

impl CallBudget {
    /// `limit` calls in progress at once (at least 1).
    pub fn new(limit: usize) -> CallBudget {
        let limit = limit.max(1);
        CallBudget {
            limit,
            places: Arc::new(Semaphore::new(limit)),
        }
    }

    /// The most calls in progress at once.
    pub fn limit(&self) -> usize {
        self.limit
    }
}

/// The middleware: a place for the request, kept in its response's body.
pub async fn admit(State(d): State<Dashboard>, req: Request, next: Next) -> Response {
    let Ok(place) = d.calls.places.clone().try_acquire_owned() else {
        let limit = d.calls.limit;
        tracing::warn!(path = %req.uri().path(), limit, "dashboard shed: too many calls in progress");
        return ApiError::new(
            StatusCode::TOO_MANY_REQUESTS,
            "RESOURCE_EXHAUSTED",
            format!(
                "the dashboard has {limit} calls in progress, its limit (--max-calls): try \
                 again shortly"
            ),
        )
        .into_response();
    };
    let (parts, body) = next.run(req).await.into_parts();
    Response::from_parts(
        parts,
        Body::new(Held {
            body,
            place: Some(place),
        }),
    )
}

/// A response body that keeps its call's place until its last frame is sent, or until
/// it is dropped (the client went away).
struct Held {
    body: Body,
    place: Option<OwnedSemaphorePermit>,
}

impl http_body::Body for Held {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let r = Pin::new(&mut self.body).poll_frame(cx);
        if matches!(r, Poll::Ready(None) | Poll::Ready(Some(Err(_)))) {
            self.place = None;
        }
        r
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}
