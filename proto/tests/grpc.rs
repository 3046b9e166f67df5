//! The generated protocol as a client sees it: the descriptor set names the services and
//! methods, and a tonic server with reflection and health answers a reflection client
//! (what grpcurl does) without any .proto file.

use std::collections::BTreeMap;

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::render_service_server::{RenderService, RenderServiceServer};
use dray_proto::v1::{
    CancelJobRequest, CancelJobResponse, GetImageRequest, GetImageResponse, GetJobRequest,
    GetJobResponse, JobProgress, ListJobsRequest, ListJobsResponse, ListWorkersRequest,
    ListWorkersResponse, PauseJobRequest, PauseJobResponse, RetryJobRequest, RetryJobResponse,
    SubmitJobRequest, SubmitJobResponse, WatchImageRequest, WatchJobRequest,
};
use prost::Message;
use prost_types::FileDescriptorSet;
use tonic::{Code, Request, Response, Status};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_reflection::pb::v1::ServerReflectionRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

/// (method name, client streaming, server streaming) of every method of `service`.
fn methods(fds: &FileDescriptorSet, service: &str) -> Option<Vec<(String, bool, bool)>> {
    let (pkg, name) = service.rsplit_once('.')?;
    fds.file
        .iter()
        .filter(|f| f.package() == pkg)
        .flat_map(|f| &f.service)
        .find(|s| s.name() == name)
        .map(|s| {
            s.method
                .iter()
                .map(|m| {
                    (
                        m.name().to_string(),
                        m.client_streaming(),
                        m.server_streaming(),
                    )
                })
                .collect()
        })
}

#[test]
fn descriptor_set_has_the_services() {
    let fds = FileDescriptorSet::decode(dray_proto::FILE_DESCRIPTOR_SET).unwrap();
    let render = methods(&fds, dray_proto::RENDER_SERVICE).expect("RenderService");
    let names: Vec<&str> = render.iter().map(|m| m.0.as_str()).collect();
    assert_eq!(
        names,
        [
            "SubmitJob",
            "WatchJob",
            "GetJob",
            "ListJobs",
            "CancelJob",
            "GetImage",
            "WatchImage",
            "ListWorkers",
            "RetryJob",
            "RequeueJob",
            "PauseJob",
            "ResumeJob",
        ]
    );
    let streaming: BTreeMap<&str, (bool, bool)> =
        render.iter().map(|m| (m.0.as_str(), (m.1, m.2))).collect();
    assert_eq!(streaming["WatchJob"], (false, true));
    assert_eq!(streaming["GetJob"], (false, false));

    let rays = methods(&fds, dray_proto::RAY_EXCHANGE_SERVICE).expect("RayExchangeService");
    assert_eq!(rays, [("RayStream".to_string(), true, true)]);

    let cluster = methods(&fds, dray_proto::CLUSTER_SERVICE).expect("ClusterService");
    assert!(cluster.len() >= 6, "{cluster:?}");

    // The well-known types are included, so the set is self-contained for reflection.
    assert!(
        fds.file
            .iter()
            .any(|f| f.name() == "google/protobuf/duration.proto")
    );
    // Comments are kept, so `grpcurl describe` documents the protocol; the ray layout
    // table is in them.
    let rays_file = fds
        .file
        .iter()
        .find(|f| f.name() == "dray/v1/rays.proto")
        .unwrap();
    let comments: String = rays_file
        .source_code_info
        .as_ref()
        .expect("source info")
        .location
        .iter()
        .flat_map(|l| [l.leading_comments(), l.trailing_comments()])
        .collect();
    assert!(
        comments.contains("Ray record layout, format 2"),
        "{comments}"
    );
    assert!(comments.contains("Cumulative grant"), "{comments}");
}

/// A RenderService that knows no jobs: enough to exercise the generated server and
/// client; the real one lives in the coordinator.
struct NoJobs;

fn not_found(id: &str) -> Status {
    Status::not_found(format!("no job {id:?}"))
}

#[tonic::async_trait]
impl RenderService for NoJobs {
    async fn submit_job(
        &self,
        _: Request<SubmitJobRequest>,
    ) -> Result<Response<SubmitJobResponse>, Status> {
        Err(Status::unimplemented("test server"))
    }

    type WatchJobStream = tokio_stream::Empty<Result<JobProgress, Status>>;

    async fn watch_job(
        &self,
        r: Request<WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        Err(not_found(&r.get_ref().job_id))
    }

    async fn get_job(&self, r: Request<GetJobRequest>) -> Result<Response<GetJobResponse>, Status> {
        Err(not_found(&r.get_ref().job_id))
    }

    async fn list_jobs(
        &self,
        _: Request<ListJobsRequest>,
    ) -> Result<Response<ListJobsResponse>, Status> {
        Ok(Response::new(ListJobsResponse::default()))
    }

    async fn cancel_job(
        &self,
        r: Request<CancelJobRequest>,
    ) -> Result<Response<CancelJobResponse>, Status> {
        Err(not_found(&r.get_ref().job_id))
    }

    async fn get_image(
        &self,
        r: Request<GetImageRequest>,
    ) -> Result<Response<GetImageResponse>, Status> {
        Err(not_found(&r.get_ref().job_id))
    }

    type WatchImageStream = tokio_stream::Empty<Result<GetImageResponse, Status>>;

    async fn watch_image(
        &self,
        r: Request<WatchImageRequest>,
    ) -> Result<Response<Self::WatchImageStream>, Status> {
        Err(not_found(&r.get_ref().job_id))
    }

    async fn list_workers(
        &self,
        _: Request<ListWorkersRequest>,
    ) -> Result<Response<ListWorkersResponse>, Status> {
        Ok(Response::new(ListWorkersResponse::default()))
    }
    async fn retry_job(
        &self,
        _: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn requeue_job(
        &self,
        _: Request<RetryJobRequest>,
    ) -> Result<Response<RetryJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn pause_job(
        &self,
        _: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
    async fn resume_job(
        &self,
        _: Request<PauseJobRequest>,
    ) -> Result<Response<PauseJobResponse>, Status> {
        Err(Status::unimplemented("stub"))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflection_and_health_on_a_live_server() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();

    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    health_reporter
        .set_serving::<RenderServiceServer<NoJobs>>()
        .await;
    let reflection = dray_proto::reflection::reflection_v1().unwrap();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(health_service)
            .add_service(reflection)
            .add_service(RenderServiceServer::new(NoJobs))
            .serve_with_incoming_shutdown(
                tonic::transport::server::TcpIncoming::from(listener),
                async {
                    stop_rx.await.ok();
                },
            ),
    );

    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();

    // List services through reflection, as `grpcurl -plaintext ADDR list` does.
    let mut reflect = ServerReflectionClient::new(channel.clone());
    let requests = [
        MessageRequest::ListServices(String::new()),
        MessageRequest::FileContainingSymbol("dray.v1.RenderService".into()),
    ]
    .map(|m| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(m),
    });
    let mut replies = reflect
        .server_reflection_info(tokio_stream::iter(requests))
        .await
        .unwrap()
        .into_inner();
    let listed = match replies.message().await.unwrap().unwrap().message_response {
        Some(MessageResponse::ListServicesResponse(l)) => {
            l.service.into_iter().map(|s| s.name).collect::<Vec<_>>()
        }
        other => panic!("unexpected reflection reply {other:?}"),
    };
    for want in [
        "dray.v1.RenderService",
        "grpc.health.v1.Health",
        "grpc.reflection.v1.ServerReflection",
    ] {
        assert!(listed.iter().any(|s| s == want), "{want} not in {listed:?}");
    }
    let files = match replies.message().await.unwrap().unwrap().message_response {
        Some(MessageResponse::FileDescriptorResponse(f)) => f.file_descriptor_proto,
        other => panic!("unexpected reflection reply {other:?}"),
    };
    let names: Vec<String> = files
        .iter()
        .map(|b| {
            prost_types::FileDescriptorProto::decode(b.as_slice())
                .unwrap()
                .name()
                .to_string()
        })
        .collect();
    assert!(
        names.iter().any(|n| n == "dray/v1/render.proto"),
        "{names:?}"
    );

    // Health, as load balancers and `grpcurl ... grpc.health.v1.Health/Check` ask.
    let mut health = HealthClient::new(channel.clone());
    let status = health
        .check(HealthCheckRequest {
            service: dray_proto::RENDER_SERVICE.into(),
        })
        .await
        .unwrap()
        .into_inner()
        .status();
    assert_eq!(status, ServingStatus::Serving);

    // The generated client reaches the generated server.
    let mut render = RenderServiceClient::new(channel);
    let err = render
        .get_job(GetJobRequest {
            job_id: "nope".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::NotFound);
    assert!(err.message().contains("nope"));
    let listed = render
        .list_jobs(ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert!(listed.jobs.is_empty());

    stop_tx.send(()).unwrap();
    server.await.unwrap().unwrap();
}
