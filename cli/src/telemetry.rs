//! Logging and, when asked, OpenTelemetry export: the one place where this process's
//! `tracing` subscriber is made.
//!
//! Always: human-readable logs on stderr, filtered by `DRAY_LOG` (default `warn`).
//!
//! With `--otlp-endpoint URL` (or `OTEL_EXPORTER_OTLP_ENDPOINT`) on `coordinator`,
//! `worker` or `render` (`cluster` passes it to its members), also:
//! - **traces** over OTLP/gRPC: the `tracing` spans for a job (coordinator and worker),
//!   a tile's batch of camera rays (`tile`), a domain load (`load`) and a gRPC call that
//!   continues a caller's trace (`grpc request`), with warnings and errors inside them as
//!   span events. The W3C trace context crosses processes in gRPC metadata and in a job's
//!   setup message (`dray_net::trace`), so one job is one trace. Other spans (the
//!   per-ray-batch ones, per-report ones) are not exported: they would be thousands a
//!   second.
//! - **metrics** over OTLP/gRPC: the workers' rays traced by kind, rays and bytes sent,
//!   domain loads and their time, rays queued; the coordinator's job durations and jobs
//!   in progress.
//! - a resource naming the process: `service.name` (`OTEL_SERVICE_NAME`, else
//!   `dray-coordinator`, `dray-worker` or `dray-render`), `service.instance.id` (a random
//!   UUID per process), `service.version`, `dray.role`; `OTEL_RESOURCE_ATTRIBUTES` adds
//!   more. The SDK's other standard variables apply too (`OTEL_BSP_SCHEDULE_DELAY`,
//!   `OTEL_METRIC_EXPORT_INTERVAL`, `OTEL_TRACES_SAMPLER`, ...).
//!
//! An `https://` endpoint needs the authority to trust in `OTEL_EXPORTER_OTLP_CERTIFICATE`
//! (a PEM file), as the OpenTelemetry specification names it.
//!
//! Without an endpoint no exporter, propagator or OpenTelemetry layer is installed at all:
//! the subscriber is the plain log one, and the hooks in the actors are no-ops.
//!
//! The exporters run on a small runtime of their own (tonic needs one), so they work
//! whatever runtime the command uses. [`Telemetry::shutdown`] (also on drop) flushes
//! what is still buffered: `main` calls it after the command returns, which the commands
//! do on Ctrl-C and SIGTERM too.

use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args;
use opentelemetry::KeyValue;
use opentelemetry::trace::TracerProvider as _;
use opentelemetry_otlp::{WithExportConfig, WithTonicConfig};
use opentelemetry_sdk::Resource;
use opentelemetry_sdk::metrics::SdkMeterProvider;
use opentelemetry_sdk::trace::{IdGenerator, RandomIdGenerator, SdkTracerProvider};
use tracing_subscriber::Layer;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

/// The environment variable naming the OTLP endpoint (the OpenTelemetry standard one).
pub const ENDPOINT_ENV: &str = "OTEL_EXPORTER_OTLP_ENDPOINT";
/// The environment variable naming the service (overrides the role's name).
pub const SERVICE_NAME_ENV: &str = "OTEL_SERVICE_NAME";
/// The CA certificate (PEM) an https endpoint is checked against.
pub const CERTIFICATE_ENV: &str = "OTEL_EXPORTER_OTLP_CERTIFICATE";

/// How long an export may take before it is abandoned (a collector that does not answer
/// must not hold a stopping process for long: `dray cluster` kills members that take
/// more than 5 s to stop).
const EXPORT_TIMEOUT: Duration = Duration::from_secs(3);

/// `--otlp-endpoint`.
#[derive(Args, Debug, Clone, Default)]
pub struct OtlpArgs {
    /// Export traces and metrics over OTLP/gRPC to this collector, e.g.
    /// http://127.0.0.1:4317 (without it nothing is exported).
    #[arg(long, value_name = "URL", env = ENDPOINT_ENV)]
    pub otlp_endpoint: Option<String>,
}

impl OtlpArgs {
    /// The endpoint, if one was given (an empty one counts as none).
    pub fn endpoint(&self) -> Option<&str> {
        self.otlp_endpoint
            .as_deref()
            .map(str::trim)
            .filter(|e| !e.is_empty())
    }

    /// The flag again, for a child process.
    pub fn to_args(&self) -> Vec<String> {
        match self.endpoint() {
            Some(e) => vec!["--otlp-endpoint".into(), e.to_string()],
            None => Vec::new(),
        }
    }
}

/// The exporters of this process; dropping it flushes and stops them.
pub struct Telemetry {
    tracer: Option<SdkTracerProvider>,
    meter: Option<SdkMeterProvider>,
    endpoint: String,
    /// Drives the exporters' gRPC connection; dropped last.
    runtime: Option<tokio::runtime::Runtime>,
}

impl Telemetry {
    /// Export what is buffered and stop (about [`EXPORT_TIMEOUT`] at most).
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        let (tracer, meter) = (self.tracer.take(), self.meter.take());
        // Both at once, so a slow collector costs one export timeout, not two.
        let (traces, metrics) = std::thread::scope(|s| {
            let traces = s.spawn(|| tracer.map(|t| t.shutdown_with_timeout(EXPORT_TIMEOUT)));
            let metrics = meter.map(|m| m.shutdown());
            (traces.join().ok().flatten(), metrics)
        });
        let mut failed = Vec::new();
        if let Some(Err(e)) = traces {
            failed.push(format!("traces: {e}"));
        }
        if let Some(Err(e)) = metrics {
            failed.push(format!("metrics: {e}"));
        }
        if !failed.is_empty() {
            eprintln!(
                "dray: warning: could not flush OpenTelemetry data to {}: {}",
                self.endpoint,
                failed.join("; ")
            );
        }
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_timeout(Duration::from_secs(1));
        }
    }
}

impl Drop for Telemetry {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The `DRAY_LOG` filter of the log on stderr.
fn log_filter() -> tracing_subscriber::EnvFilter {
    tracing_subscriber::EnvFilter::try_from_env("DRAY_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"))
}

/// Whether the log on stderr may carry colour codes: only when a person reads it on a
/// terminal. Redirected to a file, a pipe or a test harness it is plain text (escape
/// codes there are noise, and make warnings hard to grep).
fn stderr_is_terminal() -> bool {
    std::io::IsTerminal::is_terminal(&std::io::stderr())
}

/// Install the logger only (commands that export nothing, and errors before parsing).
pub fn init_logs() {
    let _ = tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(stderr_is_terminal())
                .with_filter(log_filter()),
        )
        .try_init();
}

/// Which spans and events go to OpenTelemetry (see the module doc).
fn exported(meta: &tracing::Metadata<'_>) -> bool {
    if meta.is_event() {
        return *meta.level() <= tracing::Level::WARN;
    }
    let target = meta.target();
    match meta.name() {
        "job" => {
            target == "dray_coordinator::dispatch"
                || target == "dray_coordinator::jobs"
                || target.starts_with("dray_worker")
                || target == "dray::render_cmd"
        }
        "tile" | "load" => target.starts_with("dray_worker"),
        "grpc request" => target.starts_with("dray_net"),
        _ => false,
    }
}

/// A random UUID (version 4) naming this process.
fn instance_id() -> String {
    let mut b = RandomIdGenerator::default().new_trace_id().to_bytes();
    b[6] = (b[6] & 0x0f) | 0x40;
    b[8] = (b[8] & 0x3f) | 0x80;
    let h: String = b.iter().map(|x| format!("{x:02x}")).collect();
    format!(
        "{}-{}-{}-{}-{}",
        &h[0..8],
        &h[8..12],
        &h[12..16],
        &h[16..20],
        &h[20..32]
    )
}

/// The endpoint, checked: http:// or https:// with a host.
fn check_endpoint(endpoint: &str) -> Result<()> {
    let rest = endpoint
        .strip_prefix("http://")
        .or_else(|| endpoint.strip_prefix("https://"));
    match rest {
        Some(r) if !r.is_empty() && !r.starts_with('/') => Ok(()),
        _ => bail!(
            "--otlp-endpoint {endpoint:?}: give the collector's OTLP/gRPC URL, e.g. \
             http://127.0.0.1:4317"
        ),
    }
}

/// Install the logger and, with an endpoint, the OpenTelemetry exporters for a process
/// of `role` ("coordinator", "worker", "render").
pub fn init(otlp: &OtlpArgs, role: &str) -> Result<Option<Telemetry>> {
    let Some(endpoint) = otlp.endpoint() else {
        init_logs();
        return Ok(None);
    };
    check_endpoint(endpoint)?;
    let tls = if endpoint.starts_with("https://") {
        let Some(ca) = std::env::var_os(CERTIFICATE_ENV).filter(|v| !v.is_empty()) else {
            bail!(
                "--otlp-endpoint {endpoint}: an https endpoint needs {CERTIFICATE_ENV} (the \
                 PEM file of the authority to trust)"
            );
        };
        let pem = std::fs::read(&ca)
            .with_context(|| format!("{CERTIFICATE_ENV}: cannot read {}", ca.to_string_lossy()))?;
        Some(
            tonic::transport::ClientTlsConfig::new()
                .ca_certificate(tonic::transport::Certificate::from_pem(pem)),
        )
    } else {
        None
    };

    let mut resource = Resource::builder().with_attributes([
        KeyValue::new("service.instance.id", instance_id()),
        KeyValue::new("service.version", env!("CARGO_PKG_VERSION")),
        KeyValue::new("dray.role", role.to_string()),
    ]);
    let named = std::env::var(SERVICE_NAME_ENV).is_ok_and(|v| !v.trim().is_empty());
    if !named {
        resource = resource.with_service_name(format!("dray-{role}"));
    }
    let resource = resource.build();

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("dray-otlp")
        .enable_all()
        .build()
        .context("cannot start the OpenTelemetry exporters' runtime")?;
    // tonic's channel starts its tasks on the runtime current when it is made.
    let (spans, metrics) = {
        let _in_runtime = runtime.enter();
        let mut spans = opentelemetry_otlp::SpanExporter::builder()
            .with_tonic()
            .with_endpoint(endpoint)
            .with_timeout(EXPORT_TIMEOUT);
        let mut metrics = opentelemetry_otlp::MetricExporter::builder()
            .with_tonic()
            .with_endpoint(endpoint)
            .with_timeout(EXPORT_TIMEOUT);
        if let Some(tls) = tls {
            spans = spans.with_tls_config(tls.clone());
            metrics = metrics.with_tls_config(tls);
        }
        (
            spans.build().context("the OTLP trace exporter")?,
            metrics.build().context("the OTLP metric exporter")?,
        )
    };
    let tracer_provider = SdkTracerProvider::builder()
        .with_resource(resource.clone())
        .with_batch_exporter(spans)
        .build();
    let meter_provider = SdkMeterProvider::builder()
        .with_resource(resource)
        .with_periodic_exporter(metrics)
        .build();
    opentelemetry::global::set_text_map_propagator(
        opentelemetry_sdk::propagation::TraceContextPropagator::new(),
    );
    opentelemetry::global::set_tracer_provider(tracer_provider.clone());
    opentelemetry::global::set_meter_provider(meter_provider.clone());

    let tracer = tracer_provider.tracer("dray");
    let otel = tracing_opentelemetry::layer()
        .with_tracer(tracer)
        .with_threads(false)
        .with_filter(tracing_subscriber::filter::filter_fn(exported));
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(stderr_is_terminal())
                .with_filter(log_filter()),
        )
        .with(otel)
        .try_init()
        .context("cannot install the tracing subscriber")?;
    dray_net::trace::enable();
    eprintln!("dray {role}: exporting traces and metrics to {endpoint} (OTLP/gRPC)");
    Ok(Some(Telemetry {
        tracer: Some(tracer_provider),
        meter: Some(meter_provider),
        endpoint: endpoint.to_string(),
        runtime: Some(runtime),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_ids_are_uuids_and_differ() {
        let a = instance_id();
        let b = instance_id();
        assert_ne!(a, b);
        assert_eq!(a.len(), 36);
        assert_eq!(a.as_bytes()[14], b'4');
    }

    #[test]
    fn endpoints() {
        assert!(check_endpoint("http://127.0.0.1:4317").is_ok());
        assert!(check_endpoint("https://collector:4317").is_ok());
        assert!(check_endpoint("127.0.0.1:4317").is_err());
        assert!(check_endpoint("http://").is_err());
        let none = OtlpArgs {
            otlp_endpoint: Some("  ".into()),
        };
        assert!(none.endpoint().is_none() && none.to_args().is_empty());
    }
}
