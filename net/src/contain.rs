//! Panics in async code, contained.
//!
//! tokio ends a task that panics and says nothing unless someone awaits its handle, and
//! a panic inside a gRPC handler takes the whole HTTP/2 connection down with it (every
//! other stream on it too). Neither may happen on input a peer or a client sends: a
//! panic becomes an error with its message instead.
//!
//! - [`Contained`] / [`contained`]: a future whose panic becomes `Err(message)`, for
//!   tasks (a ray stream's receiver, the worker's reporter) that must say why they
//!   stopped.
//! - [`ContainLayer`]: the server builder's outermost handler layer; a handler that
//!   panics answers INTERNAL with the panic's message, and the connection lives on.

use std::future::Future;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::pin::Pin;
use std::task::{Context, Poll};

use tonic::Status;
use tower::{Layer, Service};

/// The longest panic message passed on (messages can carry input).
const MAX_MESSAGE: usize = 300;

/// A panic payload as text, cut to [`MAX_MESSAGE`] characters.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    let message = payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".to_string());
    message.chars().take(MAX_MESSAGE).collect()
}

/// See [`contained`].
pub struct Contained<F> {
    inner: Pin<Box<F>>,
}

/// `fut`, with a panic while it is polled turned into `Err(message)`.
pub fn contained<F: Future>(fut: F) -> Contained<F> {
    Contained {
        inner: Box::pin(fut),
    }
}

impl<F: Future> Future for Contained<F> {
    type Output = Result<F::Output, String>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let inner = self.inner.as_mut();
        match catch_unwind(AssertUnwindSafe(|| inner.poll(cx))) {
            Ok(Poll::Ready(v)) => Poll::Ready(Ok(v)),
            Ok(Poll::Pending) => Poll::Pending,
            Err(payload) => Poll::Ready(Err(panic_message(payload.as_ref()))),
        }
    }
}

/// The tower layer; see the module.
#[derive(Clone, Copy, Debug, Default)]
pub struct ContainLayer;

impl<S> Layer<S> for ContainLayer {
    type Service = Contain<S>;
    fn layer(&self, inner: S) -> Contain<S> {
        Contain { inner }
    }
}

/// See [`ContainLayer`].
#[derive(Clone, Debug)]
pub struct Contain<S> {
    inner: S,
}

impl<S, B, R> Service<http::Request<B>> for Contain<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    R: Default + Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<http::Response<R>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        // A cheap clone (shared bytes): the path is only read if the handler panics.
        let uri = req.uri().clone();
        // A panic while the call is being set up, before there is a future to poll.
        let fut = match catch_unwind(AssertUnwindSafe(|| self.inner.call(req))) {
            Ok(fut) => fut,
            Err(payload) => {
                let message = panic_message(payload.as_ref());
                return Box::pin(async move { Ok(internal(uri.path(), &message)) });
            }
        };
        Box::pin(async move {
            match contained(fut).await {
                Ok(r) => r,
                Err(message) => Ok(internal(uri.path(), &message)),
            }
        })
    }
}

fn internal<R: Default>(path: &str, message: &str) -> http::Response<R> {
    tracing::error!(%path, panic = %message, "a handler panicked; the call fails, the server goes on");
    Status::internal(format!(
        "internal error (a panic in the server, contained): {message}"
    ))
    .into_http::<R>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_panicking_future_becomes_its_message_and_others_pass_through() {
        assert_eq!(contained(async { 7 }).await, Ok(7));
        let e = contained(async {
            let v: Vec<u32> = Vec::new();
            v[3]
        })
        .await
        .unwrap_err();
        assert!(e.contains("index out of bounds"), "{e}");
        let long = "x".repeat(10_000);
        let e = contained(async move { panic!("{long}") })
            .await
            .unwrap_err();
        assert_eq!(e.len(), MAX_MESSAGE);
    }

    #[tokio::test]
    async fn a_panicking_handler_answers_internal() {
        use tower::ServiceExt;
        let panics = tower::service_fn(|req: http::Request<()>| async move {
            if req.uri().path() == "/boom" {
                panic!("handler bug");
            }
            Ok::<_, std::convert::Infallible>(http::Response::new(String::from("fine")))
        });
        let svc = ContainLayer.layer(panics);
        let ok = svc
            .clone()
            .oneshot(http::Request::get("/fine").body(()).unwrap())
            .await
            .unwrap();
        assert_eq!(ok.into_body(), "fine");
        let r = svc
            .oneshot(http::Request::get("/boom").body(()).unwrap())
            .await
            .unwrap();
        let status = Status::from_header_map(r.headers()).expect("a grpc-status");
        assert_eq!(status.code(), tonic::Code::Internal);
        assert!(
            status.message().contains("handler bug"),
            "{}",
            status.message()
        );
    }
}
