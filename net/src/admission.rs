//! Load shedding: at most N calls in progress on a server; beyond that a call is
//! refused at once with RESOURCE_EXHAUSTED instead of waiting in a queue that only
//! grows under overload. A call holds its place while its handler runs (for a
//! streaming call: until the handler has returned its stream).
//!
//! Public API calls ([`Access::Api`]) also end with DEADLINE_EXCEEDED when their
//! handler runs longer than the API timeout; the cluster's own calls are not timed
//! (some are client streams that live as long as a job).

use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::sync::Semaphore;
use tonic::Status;
use tower::{Layer, Service};

use crate::auth::{Access, access_of};

/// The tower layer; see the module.
#[derive(Clone, Debug)]
pub struct AdmissionLayer {
    permits: Arc<Semaphore>,
    limit: usize,
    api_timeout: Duration,
}

impl AdmissionLayer {
    /// At most `limit` calls in progress (at least 1); API calls end after
    /// `api_timeout`.
    pub fn new(limit: usize, api_timeout: Duration) -> AdmissionLayer {
        let limit = limit.max(1);
        AdmissionLayer {
            permits: Arc::new(Semaphore::new(limit)),
            limit,
            api_timeout,
        }
    }
}

impl<S> Layer<S> for AdmissionLayer {
    type Service = Admission<S>;
    fn layer(&self, inner: S) -> Admission<S> {
        Admission {
            inner,
            permits: self.permits.clone(),
            limit: self.limit,
            api_timeout: self.api_timeout,
        }
    }
}

/// See [`AdmissionLayer`].
#[derive(Clone, Debug)]
pub struct Admission<S> {
    inner: S,
    permits: Arc<Semaphore>,
    limit: usize,
    api_timeout: Duration,
}

impl<S, B, R> Service<http::Request<B>> for Admission<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    R: Default + Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = std::pin::Pin<
        Box<dyn std::future::Future<Output = Result<http::Response<R>, S::Error>> + Send>,
    >;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        match self.permits.clone().try_acquire_owned() {
            Ok(permit) => {
                let timed = access_of(req.uri().path()) == Access::Api;
                let timeout = self.api_timeout;
                let fut = self.inner.call(req);
                Box::pin(async move {
                    let r = if timed {
                        match tokio::time::timeout(timeout, fut).await {
                            Ok(r) => r,
                            Err(_) => Ok(Status::deadline_exceeded(format!(
                                "the call took longer than the server's limit of {} s",
                                timeout.as_secs_f64()
                            ))
                            .into_http::<R>()),
                        }
                    } else {
                        fut.await
                    };
                    drop(permit);
                    r
                })
            }
            Err(_) => {
                let limit = self.limit;
                tracing::warn!(path = %req.uri().path(), limit, "shed: too many calls in progress");
                let response = Status::resource_exhausted(format!(
                    "the server has {limit} calls in progress, its limit: try again shortly"
                ))
                .into_http::<R>();
                Box::pin(async move { Ok(response) })
            }
        }
    }
}
