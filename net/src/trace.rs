//! Trace context across processes: the W3C `traceparent` (and `tracestate`) of the
//! caller's current span travels in gRPC metadata, so one job is one trace across the
//! coordinator, the workers and the cache hosts.
//!
//! - Client side: [`crate::client::Bearer`], the interceptor on every [`crate::AuthChannel`],
//!   injects the current span's context into each call's metadata.
//! - Server side: [`TraceLayer`], the outermost layer of [`crate::server::serve`], makes
//!   a `grpc request` span for a call that carries a `traceparent`, with the caller's span
//!   as its parent, and runs the handler in it.
//! - Messages on long-lived streams (a job's setup on a worker's assignment stream, which
//!   was opened long before the job) carry the same fields in a map: [`inject`] and
//!   [`set_parent`].
//!
//! All of it is off until the process calls [`enable`] (the `dray` binary does when it
//! exports OpenTelemetry): without it nothing is read, written or allocated per call.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};

use opentelemetry::propagation::{Extractor, Injector};
use opentelemetry::trace::TraceContextExt;
use tower::{Layer, Service};
use tracing::Instrument;
use tracing_opentelemetry::OpenTelemetrySpanExt;

static ENABLED: AtomicBool = AtomicBool::new(false);

/// Start propagating trace context (call once the global propagator and the tracing
/// layer that exports spans are installed).
pub fn enable() {
    ENABLED.store(true, Ordering::Relaxed);
}

/// Whether trace context is propagated in this process.
pub fn enabled() -> bool {
    ENABLED.load(Ordering::Relaxed)
}

/// The trace context of `span` as W3C fields (`traceparent`, `tracestate`), for a
/// message; empty when propagation is off or the span is not in a trace.
pub fn inject(span: &tracing::Span) -> HashMap<String, String> {
    let mut out = HashMap::new();
    if !enabled() || span.is_disabled() {
        return out;
    }
    let cx = span.context();
    if !cx.span().span_context().is_valid() {
        return out;
    }
    opentelemetry::global::get_text_map_propagator(|p| p.inject_context(&cx, &mut out));
    out
}

/// Make the trace context in `fields` (from [`inject`]) the parent of `span`, which must
/// not have been entered yet. Nothing happens when propagation is off, the fields hold no
/// valid context, or the span is not exported.
pub fn set_parent(span: &tracing::Span, fields: &HashMap<String, String>) {
    if !enabled() || fields.is_empty() || span.is_disabled() {
        return;
    }
    let cx = opentelemetry::global::get_text_map_propagator(|p| p.extract(fields));
    if cx.span().span_context().is_valid() {
        // Fails only when the span is not exported or already started: then it simply
        // stays where it is.
        let _ = span.set_parent(cx);
    }
}

/// gRPC metadata as a carrier for the propagator.
struct MetadataInjector<'a>(&'a mut tonic::metadata::MetadataMap);

impl Injector for MetadataInjector<'_> {
    fn set(&mut self, key: &str, value: String) {
        if let (Ok(k), Ok(v)) = (
            tonic::metadata::MetadataKey::from_bytes(key.as_bytes()),
            tonic::metadata::MetadataValue::try_from(value.as_str()),
        ) {
            self.0.insert(k, v);
        }
    }
}

/// Put the current span's trace context into `metadata` (client side).
pub(crate) fn inject_current(metadata: &mut tonic::metadata::MetadataMap) {
    if !enabled() {
        return;
    }
    let span = tracing::Span::current();
    if span.is_disabled() {
        return;
    }
    let cx = span.context();
    if !cx.span().span_context().is_valid() {
        return;
    }
    opentelemetry::global::get_text_map_propagator(|p| {
        p.inject_context(&cx, &mut MetadataInjector(metadata))
    });
}

/// HTTP/2 headers as a carrier for the propagator.
struct HeaderExtractor<'a>(&'a http::HeaderMap);

impl Extractor for HeaderExtractor<'_> {
    fn get(&self, key: &str) -> Option<&str> {
        self.0.get(key).and_then(|v| v.to_str().ok())
    }
    fn keys(&self) -> Vec<&str> {
        self.0.keys().map(|k| k.as_str()).collect()
    }
}

/// The tower layer that continues a caller's trace in this server (see the module doc).
#[derive(Clone, Copy, Debug, Default)]
pub struct TraceLayer;

impl<S> Layer<S> for TraceLayer {
    type Service = Traced<S>;
    fn layer(&self, inner: S) -> Traced<S> {
        Traced { inner }
    }
}

/// See [`TraceLayer`].
#[derive(Clone, Debug)]
pub struct Traced<S> {
    inner: S,
}

impl<S, B> Service<http::Request<B>> for Traced<S>
where
    S: Service<http::Request<B>>,
    S::Future: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future =
        std::pin::Pin<Box<dyn std::future::Future<Output = Result<S::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        if !enabled() || !req.headers().contains_key("traceparent") {
            return Box::pin(self.inner.call(req));
        }
        let parent = opentelemetry::global::get_text_map_propagator(|p| {
            p.extract(&HeaderExtractor(req.headers()))
        });
        if !parent.span().span_context().is_valid() {
            return Box::pin(self.inner.call(req));
        }
        let path = req.uri().path();
        let (service, method) = path
            .trim_start_matches('/')
            .split_once('/')
            .unwrap_or((path, ""));
        let span = tracing::info_span!(
            "grpc request",
            otel.name = %path.trim_start_matches('/'),
            otel.kind = "server",
            rpc.system = "grpc",
            rpc.service = %service,
            rpc.method = %method,
        );
        let _ = span.set_parent(parent);
        let future = {
            let _entered = span.enter();
            self.inner.call(req)
        };
        Box::pin(future.instrument(span))
    }
}
