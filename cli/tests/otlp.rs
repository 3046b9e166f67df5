//! OpenTelemetry export against a real OTLP/gRPC receiver: the official protocol
//! definitions (`opentelemetry-proto`'s generated `TraceService` and `MetricsService`)
//! served by tonic in this test, recording every span and metric it is sent.
//!
//! `dray cluster --workers 2 --otlp-endpoint URL` runs one job. Then:
//! - the coordinator's `job` span and the workers' `job` spans are in one trace, each
//!   worker's job span a child of the coordinator's (the context crossed processes), and
//!   the workers' `tile` and `load` spans are children of their job span;
//! - a job with ray caches: the coordinator's OpenWalls calls to the cache hosts in the
//!   worker processes carry the job's trace context in their gRPC metadata, and each
//!   host's span for the call is a child of the coordinator's job span;
//! - every process names itself: `service.name` dray-coordinator / dray-worker and a
//!   `service.instance.id` of its own;
//! - after SIGTERM the processes flush: the metrics (exported every 60 s by default, so
//!   they come from the flush on shutdown) arrive — rays traced by kind, rays and bytes
//!   sent, domain loads, queue depth from the workers, job durations from the coordinator.
//!
//! The test waits for events (with generous limits that only catch hangs), never for
//! elapsed time.

mod common;
mod support;

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use opentelemetry_proto::tonic::collector::metrics::v1::metrics_service_server::{
    MetricsService, MetricsServiceServer,
};
use opentelemetry_proto::tonic::collector::metrics::v1::{
    ExportMetricsServiceRequest, ExportMetricsServiceResponse,
};
use opentelemetry_proto::tonic::collector::trace::v1::trace_service_server::{
    TraceService, TraceServiceServer,
};
use opentelemetry_proto::tonic::collector::trace::v1::{
    ExportTraceServiceRequest, ExportTraceServiceResponse,
};
use opentelemetry_proto::tonic::common::v1::any_value::Value;
use opentelemetry_proto::tonic::resource::v1::Resource;

/// Slot of this binary's one cluster (see support::cluster_base_port).
const SLOT: u16 = 3;

/// A span as received, with the resource that sent it.
#[derive(Clone, Debug)]
struct Got {
    service: String,
    instance: String,
    name: String,
    trace_id: Vec<u8>,
    span_id: Vec<u8>,
    parent: Vec<u8>,
}

#[derive(Default)]
struct Received {
    spans: Vec<Got>,
    /// (service.name, service.instance.id, metric name)
    metrics: Vec<(String, String, String)>,
}

#[derive(Clone, Default)]
struct Receiver(Arc<Mutex<Received>>);

impl Receiver {
    fn with<T>(&self, f: impl FnOnce(&Received) -> T) -> T {
        f(&dray_sync::lock(&self.0))
    }
}

fn attr(resource: &Option<Resource>, key: &str) -> String {
    resource
        .as_ref()
        .and_then(|r| r.attributes.iter().find(|kv| kv.key == key))
        .and_then(|kv| kv.value.as_ref())
        .and_then(|v| match &v.value {
            Some(Value::StringValue(s)) => Some(s.clone()),
            _ => None,
        })
        .unwrap_or_default()
}

#[tonic::async_trait]
impl TraceService for Receiver {
    async fn export(
        &self,
        request: tonic::Request<ExportTraceServiceRequest>,
    ) -> Result<tonic::Response<ExportTraceServiceResponse>, tonic::Status> {
        let mut got = dray_sync::lock(&self.0);
        for rs in request.into_inner().resource_spans {
            let service = attr(&rs.resource, "service.name");
            let instance = attr(&rs.resource, "service.instance.id");
            for ss in rs.scope_spans {
                for s in ss.spans {
                    got.spans.push(Got {
                        service: service.clone(),
                        instance: instance.clone(),
                        name: s.name,
                        trace_id: s.trace_id,
                        span_id: s.span_id,
                        parent: s.parent_span_id,
                    });
                }
            }
        }
        Ok(tonic::Response::new(ExportTraceServiceResponse::default()))
    }
}

#[tonic::async_trait]
impl MetricsService for Receiver {
    async fn export(
        &self,
        request: tonic::Request<ExportMetricsServiceRequest>,
    ) -> Result<tonic::Response<ExportMetricsServiceResponse>, tonic::Status> {
        let mut got = dray_sync::lock(&self.0);
        for rm in request.into_inner().resource_metrics {
            let service = attr(&rm.resource, "service.name");
            let instance = attr(&rm.resource, "service.instance.id");
            for sm in rm.scope_metrics {
                for m in sm.metrics {
                    got.metrics
                        .push((service.clone(), instance.clone(), m.name));
                }
            }
        }
        Ok(tonic::Response::new(ExportMetricsServiceResponse::default()))
    }
}

/// Serve the receiver on a free loopback port, on a runtime of its own; its address.
fn start_receiver(r: Receiver) -> (tokio::runtime::Runtime, String) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("receiver runtime");
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .expect("bind the receiver");
    let addr = listener.local_addr().expect("receiver address");
    rt.spawn(
        tonic::transport::Server::builder()
            .add_service(TraceServiceServer::new(r.clone()))
            .add_service(MetricsServiceServer::new(r))
            .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener)),
    );
    (rt, format!("http://{addr}"))
}

#[test]
fn one_job_is_one_trace_across_processes_and_metrics_arrive() {
    let receiver = Receiver::default();
    let (_rt, url) = start_receiver(receiver.clone());
    let dir = common::tmp("otlp");
    let cluster = support::WorkerCluster::start(2, SLOT, &dir, &["--otlp-endpoint", &url]);
    let log = cluster.log();
    // The members share one stderr pipe, so their lines may interleave: count the
    // announcements' tails (a coordinator's and two workers').
    assert!(
        log.contains("coordinator: exporting traces and metrics to")
            && log
                .matches("worker: exporting traces and metrics to")
                .count()
                >= 2
            && log
                .matches(&format!("exporting traces and metrics to {url}"))
                .count()
                >= 3,
        "every member exports: {log}"
    );

    let png = dir.join("job.png");
    let mut submit = support::dray();
    submit
        .args(["submit", "--coordinator", &cluster.addr, "cornell"])
        .args([
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "4",
            "--domains",
            "4",
            "-q",
        ])
        .arg("--output")
        .arg(&png)
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT");
    let out = submit.output().expect("run dray submit");
    assert!(
        out.status.success(),
        "dray submit: {}\ncluster log:\n{}",
        String::from_utf8_lossy(&out.stderr),
        cluster.log()
    );

    // The coordinator's job span, and both workers' job spans in its trace as its
    // children. (Spans are exported every few seconds while the cluster runs.)
    let joined = |r: &Received| -> Option<(Got, Vec<Got>)> {
        let job = r
            .spans
            .iter()
            .find(|s| s.service == "dray-coordinator" && s.name == "job")?;
        let workers: Vec<Got> = r
            .spans
            .iter()
            .filter(|s| s.service == "dray-worker" && s.name == "job")
            .filter(|s| s.trace_id == job.trace_id && s.parent == job.span_id)
            .cloned()
            .collect();
        let instances: HashSet<&str> = workers.iter().map(|s| s.instance.as_str()).collect();
        (instances.len() == 2).then(|| (job.clone(), workers))
    };
    let ok = support::eventually(120.0, || receiver.with(|r| joined(r).is_some()));
    let summary = |r: &Received| {
        r.spans
            .iter()
            .map(|s| format!("{} {} parent={}", s.service, s.name, !s.parent.is_empty()))
            .collect::<Vec<_>>()
            .join("\n")
    };
    assert!(
        ok,
        "no connected trace: the coordinator's job span with both workers' job spans as \
         children; spans received:\n{}\ncluster log:\n{}",
        receiver.with(summary),
        cluster.log()
    );
    let (job, worker_jobs) = receiver.with(|r| joined(r)).expect("checked above");
    assert_eq!(job.trace_id.len(), 16);
    assert!(job.trace_id.iter().any(|&b| b != 0));

    // The workers' tile batches and domain loads are in the same trace, under their job.
    let worker_job_ids: HashMap<&[u8], &str> = worker_jobs
        .iter()
        .map(|s| (s.span_id.as_slice(), s.instance.as_str()))
        .collect();
    let ok = support::eventually(60.0, || {
        receiver.with(|r| {
            let under = |name: &str| {
                r.spans.iter().any(|s| {
                    s.name == name
                        && s.service == "dray-worker"
                        && s.trace_id == job.trace_id
                        && worker_job_ids.get(s.parent.as_slice()) == Some(&s.instance.as_str())
                })
            };
            under("tile") && under("load")
        })
    });
    assert!(
        ok,
        "no tile or load spans under the workers' job spans; spans received:\n{}",
        receiver.with(summary)
    );
    // Every span of the trace comes from the cluster's processes, and none is a root but
    // the coordinator's job span (or the call that started it).
    receiver.with(|r| {
        let in_trace: Vec<&Got> = r
            .spans
            .iter()
            .filter(|s| s.trace_id == job.trace_id)
            .collect();
        let services: HashSet<&str> = in_trace.iter().map(|s| s.service.as_str()).collect();
        assert_eq!(
            services,
            HashSet::from(["dray-coordinator", "dray-worker"]),
            "{}",
            summary(r)
        );
        let roots: Vec<&&Got> = in_trace.iter().filter(|s| s.parent.is_empty()).collect();
        assert!(
            roots.len() <= 1 && roots.iter().all(|s| s.span_id == job.span_id),
            "more than one root in the job's trace: {roots:?}"
        );
    });

    // Through gRPC metadata: a job with ray caches has the coordinator open its walls on
    // the cache hosts in the worker processes, from within the job's span; each host's
    // `grpc request` span continues that trace, its parent the coordinator's job span.
    let out = support::dray()
        .args(["submit", "--coordinator", &cluster.addr, "cornell"])
        .args([
            "--width",
            "32",
            "--height",
            "24",
            "--spp",
            "1",
            "--domains",
            "4",
            "-q",
        ])
        .args(["--ray-cache", "radius=0", "--label", "cached"])
        .arg("--output")
        .arg(dir.join("cached.png"))
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .output()
        .expect("run dray submit");
    assert!(
        out.status.success(),
        "dray submit --ray-cache: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let via_metadata = |r: &Received| {
        r.spans.iter().any(|call| {
            call.service == "dray-worker"
                && call.name == "dray.v1.CacheService/OpenWalls"
                && r.spans.iter().any(|j| {
                    j.service == "dray-coordinator"
                        && j.name == "job"
                        && j.span_id == call.parent
                        && j.trace_id == call.trace_id
                        && j.span_id != job.span_id
                })
        })
    };
    let ok = support::eventually(120.0, || receiver.with(via_metadata));
    assert!(
        ok,
        "no OpenWalls call span in a worker process under the second job's span; spans \
         received:\n{}",
        receiver.with(summary)
    );

    // SIGTERM: every member stops in order and flushes its exporters. The metrics are
    // exported every 60 s by default, so they arrive through that flush.
    drop(cluster);
    let want_worker = [
        "dray.worker.rays.traced",
        "dray.worker.domain.loads",
        "dray.worker.domain.load_time",
        "dray.worker.rays.queued",
    ];
    let want_coordinator = [
        "dray.coordinator.job.duration",
        "dray.coordinator.jobs.active",
    ];
    let arrived = |r: &Received| {
        let have =
            |service: &str, name: &str| r.metrics.iter().any(|(s, _, n)| s == service && n == name);
        want_worker.iter().all(|n| have("dray-worker", n))
            && want_coordinator.iter().all(|n| have("dray-coordinator", n))
    };
    let ok = support::eventually(60.0, || receiver.with(arrived));
    assert!(
        ok,
        "metrics missing after the cluster stopped; received: {:?}",
        receiver.with(|r| r.metrics.clone())
    );
    receiver.with(|r| {
        let instances: HashSet<(&str, &str)> = r
            .metrics
            .iter()
            .map(|(s, i, _)| (s.as_str(), i.as_str()))
            .collect();
        assert_eq!(
            instances.len(),
            3,
            "one coordinator and two workers, each with its own service.instance.id: {instances:?}"
        );
        assert!(
            instances.iter().all(|(_, i)| i.len() == 36),
            "{instances:?}"
        );
    });
    receiver.with(|r| {
        let in_trace = r.spans.iter().filter(|s| s.trace_id == job.trace_id);
        let mut names: Vec<String> = in_trace
            .map(|s| format!("{}/{}", s.service, s.name))
            .collect();
        names.sort();
        names.dedup();
        eprintln!(
            "received {} spans ({} in the job's trace: {}), {} metric points",
            r.spans.len(),
            r.spans
                .iter()
                .filter(|s| s.trace_id == job.trace_id)
                .count(),
            names.join(", "),
            r.metrics.len()
        );
    });
    let _ = std::fs::remove_dir_all(&dir);
}
