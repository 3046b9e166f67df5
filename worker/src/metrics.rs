//! This worker's counters as OpenTelemetry metrics, through the global meter: a no-op
//! unless the process installed a meter provider (`dray worker --otlp-endpoint`).
//!
//! Recorded where the counters are already gathered for the coordinator (each
//! `ReportContributions`, see `reporter.rs`), so the two always agree.

use std::sync::OnceLock;

use dray_core::integrator::RayKind;
use opentelemetry::KeyValue;
use opentelemetry::metrics::{Counter, Gauge};

struct Instruments {
    rays_traced: Counter<u64>,
    rays_sent: Counter<u64>,
    bytes_sent: Counter<u64>,
    domain_loads: Counter<u64>,
    domain_load_seconds: Counter<f64>,
    rays_queued: Gauge<u64>,
    kinds: [KeyValue; 6],
}

fn instruments() -> &'static Instruments {
    static I: OnceLock<Instruments> = OnceLock::new();
    I.get_or_init(|| {
        let m = opentelemetry::global::meter("dray-worker");
        let kind = |k: &'static str| KeyValue::new("kind", k);
        Instruments {
            rays_traced: m
                .u64_counter("dray.worker.rays.traced")
                .with_description("Rays traced by this worker, by kind")
                .with_unit("{ray}")
                .build(),
            rays_sent: m
                .u64_counter("dray.worker.rays.sent")
                .with_description("Rays sent to other workers")
                .with_unit("{ray}")
                .build(),
            bytes_sent: m
                .u64_counter("dray.worker.bytes.sent")
                .with_description("Bytes of ray batches sent to other workers")
                .with_unit("By")
                .build(),
            domain_loads: m
                .u64_counter("dray.worker.domain.loads")
                .with_description("Domains loaded")
                .with_unit("{load}")
                .build(),
            domain_load_seconds: m
                .f64_counter("dray.worker.domain.load_time")
                .with_description("Time spent loading domains")
                .with_unit("s")
                .build(),
            rays_queued: m
                .u64_gauge("dray.worker.rays.queued")
                .with_description("Rays queued at this worker, over all jobs and domains")
                .with_unit("{ray}")
                .build(),
            kinds: RayKind::NAMES.map(kind),
        }
    })
}

/// One report's counters: rays traced per kind (indexed by `RayKind`), rays and bytes
/// sent, domain loads and the time they took.
pub(crate) fn record_report(
    traced: &[u64],
    rays_sent: u64,
    bytes_sent: u64,
    loads: u64,
    load_seconds: f64,
) {
    let i = instruments();
    for (kind, attr) in [
        RayKind::Camera,
        RayKind::Shadow,
        RayKind::Reflection,
        RayKind::Refraction,
        RayKind::Diffuse,
        RayKind::AmbientOcclusion,
    ]
    .into_iter()
    .zip(&i.kinds)
    {
        let n = traced.get(kind as usize).copied().unwrap_or(0);
        if n > 0 {
            i.rays_traced.add(n, std::slice::from_ref(attr));
        }
    }
    if rays_sent > 0 {
        i.rays_sent.add(rays_sent, &[]);
    }
    if bytes_sent > 0 {
        i.bytes_sent.add(bytes_sent, &[]);
    }
    if loads > 0 {
        i.domain_loads.add(loads, &[]);
        i.domain_load_seconds.add(load_seconds, &[]);
    }
}

/// Rays queued here now.
pub(crate) fn record_queued(rays: u64) {
    instruments().rays_queued.record(rays, &[]);
}
