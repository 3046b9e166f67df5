//! The dashboard's JSON endpoints. Each one calls the coordinator's RenderService
//! method in process, as a gRPC call would, so a job submitted from the page is checked
//! against the same fields, limits and scene root, and an error says the same thing.

use std::time::SystemTime;

use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, Method, header};
use axum::response::{IntoResponse, Response};
use dray_proto::v1::render_service_server::RenderService;
use dray_proto::v1::{
    CancelJobRequest, GetImageRequest, GetJobRequest, ImageFormat, Job, ListJobsRequest,
    ListWorkersRequest, ListWorkersResponse, SubmitJobRequest,
};
use serde::{Deserialize, Serialize};
use tonic::Request;

use super::Dashboard;
use super::auth::{Credential, Gate};
use super::dto::{JobDetail, JobPage, SubmitForm, Submitted, Workers};
use super::error::ApiError;
use crate::worker_list::MAX_PAGE_SIZE;

/// `GET /api/session`: whether the token is required and this request has it, so the
/// page knows whether to show its login.
#[derive(Serialize)]
pub struct Session {
    pub auth_required: bool,
    pub authenticated: bool,
}

pub async fn session(State(d): State<Dashboard>, headers: HeaderMap) -> Json<Session> {
    Json(Session {
        auth_required: d.gate.requires_token(),
        authenticated: d.gate.authenticate(&headers, SystemTime::now()).is_ok(),
    })
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Login {
    pub token: String,
}

/// `POST /api/login {"token": "..."}`: a session cookie for the API token.
pub async fn login(
    State(d): State<Dashboard>,
    method: Method,
    headers: HeaderMap,
    Json(body): Json<Login>,
) -> Result<Response, ApiError> {
    // No credential yet, and none a browser adds by itself: held to the cross-site rules.
    Gate::check_csrf(&method, &headers, Credential::Open)?;
    let cookie = d.gate.login(&body.token, SystemTime::now())?;
    with_cookie(cookie)
}

/// `POST /api/logout`: ends the session (every copy of its cookie is refused from now
/// on) and clears the browser's cookie.
pub async fn logout(
    State(d): State<Dashboard>,
    method: Method,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    Gate::check_csrf(&method, &headers, Credential::Open)?;
    with_cookie(d.gate.logout(&headers))
}

fn with_cookie(cookie: String) -> Result<Response, ApiError> {
    let value = HeaderValue::from_str(&cookie)
        .map_err(|e| ApiError::bad_request(format!("cannot make the cookie: {e}")))?;
    let mut r = Json(serde_json::json!({ "ok": true })).into_response();
    r.headers_mut().insert(header::SET_COOKIE, value);
    Ok(r)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PageQuery {
    #[serde(default)]
    pub page_size: u32,
    #[serde(default)]
    pub page_token: String,
}

/// `GET /api/jobs?page_size=N&page_token=T`: ListJobs.
pub async fn list_jobs(
    State(d): State<Dashboard>,
    Query(q): Query<PageQuery>,
) -> Result<Json<JobPage>, ApiError> {
    Ok(Json(d.job_page(q.page_size, q.page_token).await?))
}

/// `POST /api/jobs` with a [`SubmitForm`]: SubmitJob.
pub async fn submit(
    State(d): State<Dashboard>,
    Json(form): Json<SubmitForm>,
) -> Result<Json<Submitted>, ApiError> {
    let r = d
        .coordinator
        .submit_job(Request::new(SubmitJobRequest {
            spec: Some(form.into()),
        }))
        .await?
        .into_inner();
    Ok(Json(Submitted {
        id: r.job_id,
        group_id: r.group_id,
    }))
}

/// `GET /api/jobs/{id}`: GetJob, with statistics.
pub async fn get_job(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Json<JobDetail>, ApiError> {
    let r = d
        .coordinator
        .get_job(Request::new(GetJobRequest { job_id: id }))
        .await?;
    detail(r.into_inner().job, "GetJob")
}

/// `POST /api/jobs/{id}/cancel`: CancelJob; answers the job after it.
pub async fn cancel(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Json<JobDetail>, ApiError> {
    let r = d
        .coordinator
        .cancel_job(Request::new(CancelJobRequest { job_id: id }))
        .await?;
    detail(r.into_inner().job, "CancelJob")
}

/// The job a call (`method`) answered, with its statistics.
fn detail(job: Option<Job>, method: &str) -> Result<Json<JobDetail>, ApiError> {
    let job = job.ok_or_else(|| {
        ApiError::from(tonic::Status::internal(format!("{method} answered no job")))
    })?;
    Ok(Json(JobDetail::from(&job)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageQuery {
    /// Stops; absent: automatic (GetImageRequest.exposure).
    #[serde(default)]
    pub exposure: Option<f32>,
    /// The tone curve; absent: the default (GetImageRequest.tonemap).
    #[serde(default)]
    pub tonemap: Option<String>,
    /// Ignored: lets the page ask again for a new image without a cached answer.
    #[serde(default, rename = "v")]
    pub _version: Option<String>,
}

/// `GET /api/jobs/{id}/image.png?exposure=EV&tonemap=NAME`: GetImage as PNG (409 while the job has no
/// image to give).
pub async fn image(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
    Query(q): Query<ImageQuery>,
) -> Result<Response, ApiError> {
    let r = d
        .coordinator
        .get_image(Request::new(GetImageRequest {
            job_id: id,
            format: ImageFormat::Png as i32,
            exposure: q.exposure,
            tonemap: q.tonemap.unwrap_or_default(),
        }))
        .await?
        .into_inner();
    let mut resp = r.data.into_response();
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    h.insert("x-dray-width", HeaderValue::from(r.width));
    h.insert("x-dray-height", HeaderValue::from(r.height));
    // A running job's image has the samples of its passes complete so far.
    h.insert("x-dray-samples", HeaderValue::from(r.samples));
    h.insert(
        "x-dray-final",
        HeaderValue::from_static(if r.r#final { "true" } else { "false" }),
    );
    Ok(resp)
}

/// `GET /api/workers`: ListWorkers, with the domain ownership of running jobs.
pub async fn workers(State(d): State<Dashboard>) -> Result<Json<Workers>, ApiError> {
    Ok(Json(d.workers().await?))
}

impl Dashboard {
    /// A page of jobs through ListJobs.
    pub async fn job_page(&self, page_size: u32, page_token: String) -> Result<JobPage, ApiError> {
        let r = self
            .coordinator
            .list_jobs(Request::new(ListJobsRequest {
                page_size,
                page_token,
                ..Default::default()
            }))
            .await?
            .into_inner();
        Ok(JobPage::from(&r))
    }

    /// Every worker and the running jobs' domain owners through ListWorkers, page after
    /// page: the page shows the whole cluster. The jobs' tables come with the first
    /// page; the later ones add workers.
    pub async fn workers(&self) -> Result<Workers, ApiError> {
        let mut all = ListWorkersResponse::default();
        loop {
            let page = self
                .coordinator
                .list_workers(Request::new(ListWorkersRequest {
                    omit_jobs: false,
                    page_size: MAX_PAGE_SIZE as u32,
                    page_token: std::mem::take(&mut all.next_page_token),
                }))
                .await?
                .into_inner();
            all.workers.extend(page.workers);
            all.jobs.extend(page.jobs);
            all.next_page_token = page.next_page_token;
            if all.next_page_token.is_empty() {
                return Ok(Workers::from(&all));
            }
        }
    }
}
