//! Load shedding: at most N calls in progress **per class of caller**; beyond that a
//! call is refused at once with RESOURCE_EXHAUSTED instead of waiting in a queue that
//! only grows under overload.
//!
//! - **Separate budgets** ([`Budget`]): health checks, reflection, the public API and
//!   the cluster's own calls each have `limit` places of their own, so API clients (who
//!   may need no credential at all) can never take the places of registrations,
//!   heartbeats and ray streams, and a probe's health check is never refused because of
//!   them.
//! - **A call holds its place until its response has been sent**: the place is kept in
//!   the response body, so a streaming response (WatchJob, WatchAssignments, a ray
//!   stream) counts until the stream ends or the client goes away, not only while its
//!   handler sets it up.
//! - **A one-message request must arrive whole in time**: for methods whose request is
//!   a single message (every method but the client- and bidi-streaming ones, see
//!   [`single_message_request`]), the request body must end within the body timeout
//!   of the call's admission, or the call ends with DEADLINE_EXCEEDED and frees its
//!   place ([`crate::body_deadline`]). A client that sends headers and never a body
//!   (or a message and never its end) cannot hold a place longer than that.
//!
//! Public API calls ([`Access::Api`]) also end with DEADLINE_EXCEEDED when their
//! handler runs longer than the API timeout; the cluster's own calls are not timed
//! (some are client streams that live as long as a job).

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http_body::{Body as HttpBody, Frame, SizeHint};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::Status;
use tonic::body::Body;
use tower::{Layer, Service};

use crate::auth::{Access, access_of};
use crate::body_deadline::BodyDeadline;

/// The budgets calls are counted against, one per class of caller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Budget {
    /// `grpc.health.v1.Health`: probes and `dray`'s own readiness checks.
    Health,
    /// Server reflection (grpcurl's discovery).
    Reflection,
    /// The public API ([`Access::Api`]).
    Api,
    /// The cluster's own services ([`Access::Cluster`]).
    Cluster,
}

impl Budget {
    const ALL: [Budget; 4] = [
        Budget::Health,
        Budget::Reflection,
        Budget::Api,
        Budget::Cluster,
    ];

    /// The budget a request path is counted against.
    pub fn of(path: &str) -> Budget {
        match access_of(path) {
            Access::Open if path.starts_with("/grpc.health.v1.Health/") => Budget::Health,
            Access::Open => Budget::Reflection,
            Access::Api => Budget::Api,
            Access::Cluster => Budget::Cluster,
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// The methods whose request is a stream of messages (client or bidi streaming): their
/// later messages may come at any time (a ray stream lives as long as a job), so only
/// the other methods' requests are held to the body timeout. A test checks this list
/// against the protocol's descriptors.
const STREAMING_REQUESTS: [&str; 4] = [
    "/dray.v1.RayExchangeService/RayStream",
    "/dray.v1.CacheService/Exchange",
    "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
    "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
];

/// Whether a method's request is one message (unary and server-streaming methods).
pub fn single_message_request(path: &str) -> bool {
    !STREAMING_REQUESTS.contains(&path)
}

/// The tower layer; see the module.
#[derive(Clone, Debug)]
pub struct AdmissionLayer {
    budgets: Arc<[Arc<Semaphore>; 4]>,
    limit: usize,
    api_timeout: Duration,
    body_timeout: Duration,
}

impl AdmissionLayer {
    /// At most `limit` calls in progress per [`Budget`] (at least 1); API calls end
    /// after `api_timeout`; a single-message request must arrive within
    /// `body_timeout`.
    pub fn new(limit: usize, api_timeout: Duration, body_timeout: Duration) -> AdmissionLayer {
        let limit = limit.max(1);
        AdmissionLayer {
            budgets: Arc::new(Budget::ALL.map(|_| Arc::new(Semaphore::new(limit)))),
            limit,
            api_timeout,
            body_timeout,
        }
    }
}

impl<S> Layer<S> for AdmissionLayer {
    type Service = Admission<S>;
    fn layer(&self, inner: S) -> Admission<S> {
        Admission {
            inner,
            layer: self.clone(),
        }
    }
}

/// See [`AdmissionLayer`].
#[derive(Clone, Debug)]
pub struct Admission<S> {
    inner: S,
    layer: AdmissionLayer,
}

impl<S> Service<http::Request<Body>> for Admission<S>
where
    S: Service<http::Request<Body>, Response = http::Response<Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<Body>;
    type Error = S::Error;
    type Future =
        Pin<Box<dyn std::future::Future<Output = Result<http::Response<Body>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<Body>) -> Self::Future {
        let budget = Budget::of(req.uri().path());
        let permits = &self.layer.budgets[budget.index()];
        let Ok(permit) = permits.clone().try_acquire_owned() else {
            let limit = self.layer.limit;
            tracing::warn!(path = %req.uri().path(), ?budget, limit, "shed: too many calls in progress");
            let response = Status::resource_exhausted(format!(
                "the server has {limit} calls of this kind in progress, its limit: try again shortly"
            ))
            .into_http::<Body>();
            return Box::pin(async move { Ok(response) });
        };
        let req = if single_message_request(req.uri().path()) {
            let timeout = self.layer.body_timeout;
            req.map(|body| Body::new(BodyDeadline::new(body, timeout)))
        } else {
            req
        };
        let timeout = (budget == Budget::Api).then_some(self.layer.api_timeout);
        let fut = self.inner.call(req);
        Box::pin(async move {
            let r = match timeout {
                Some(timeout) => match tokio::time::timeout(timeout, fut).await {
                    Ok(r) => r,
                    Err(_) => Ok(Status::deadline_exceeded(format!(
                        "the call took longer than the server's limit of {} s",
                        timeout.as_secs_f64()
                    ))
                    .into_http::<Body>()),
                },
                None => fut.await,
            };
            // The place goes with the response body: it is freed when the last frame
            // has been sent, or when the body is dropped (the client reset the stream
            // or went away).
            r.map(|response| response.map(|body| Body::new(Held::new(body, permit))))
        })
    }
}

/// A response body that keeps its call's place in the budget until it ends.
struct Held {
    inner: Body,
    permit: Option<OwnedSemaphorePermit>,
}

impl Held {
    fn new(inner: Body, permit: OwnedSemaphorePermit) -> Held {
        Held {
            inner,
            permit: Some(permit),
        }
    }
}

impl HttpBody for Held {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let r = Pin::new(&mut self.inner).poll_frame(cx);
        if matches!(r, Poll::Ready(None) | Poll::Ready(Some(Err(_)))) {
            self.permit = None;
        }
        r
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
    use prost::Message;

    #[test]
    fn budgets_by_class() {
        assert_eq!(Budget::of("/grpc.health.v1.Health/Check"), Budget::Health);
        assert_eq!(Budget::of("/grpc.health.v1.Health/Watch"), Budget::Health);
        assert_eq!(
            Budget::of("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"),
            Budget::Reflection
        );
        assert_eq!(Budget::of("/dray.v1.RenderService/WatchJob"), Budget::Api);
        assert_eq!(
            Budget::of("/dray.v1.ClusterService/Heartbeat"),
            Budget::Cluster
        );
        assert_eq!(Budget::of("/nothing"), Budget::Cluster);
    }

    /// The list of streaming requests is the protocol's: every client- or bidi-streaming
    /// method of `dray.v1` is in it, and no other `dray.v1` method.
    #[test]
    fn streaming_requests_match_the_descriptors() {
        let set = prost_types::FileDescriptorSet::decode(dray_proto::FILE_DESCRIPTOR_SET)
            .expect("the descriptor set decodes");
        let mut streaming = Vec::new();
        let mut methods = 0;
        for file in &set.file {
            let package = file.package();
            for service in &file.service {
                for method in &service.method {
                    let path = format!("/{package}.{}/{}", service.name(), method.name());
                    methods += 1;
                    if method.client_streaming() {
                        streaming.push(path.clone());
                    }
                    assert_eq!(
                        single_message_request(&path),
                        !method.client_streaming(),
                        "{path}"
                    );
                }
            }
        }
        assert!(
            methods > 10,
            "{methods} methods: the descriptor set is dray's"
        );
        let dray: Vec<&str> = STREAMING_REQUESTS
            .iter()
            .copied()
            .filter(|p| p.starts_with("/dray."))
            .collect();
        assert_eq!(streaming, dray);
    }
}
