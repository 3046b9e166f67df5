//! The dashboard's operator endpoints (issue 42), each one RenderService call in process
//! as the rest of the API: retry, requeue, pause and resume a job, and download its
//! finished image as a file (PNG or EXR, with `Content-Disposition: attachment`). Behind
//! the same gate as every other endpoint (`super::guard`: the API token, and a
//! state-changing call only from the page).

use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use dray_proto::v1::render_service_server::RenderService;
use dray_proto::v1::{GetImageRequest, ImageFormat, PauseJobRequest, RetryJobRequest};
use serde::{Deserialize, Serialize};
use tonic::Request;

use super::Dashboard;
use super::dto::JobDetail;
use super::error::ApiError;

/// The body of a retry or requeue: an optional new priority.
#[derive(Deserialize, Debug, Default)]
#[serde(deny_unknown_fields)]
pub struct RetryForm {
    #[serde(default)]
    pub priority: Option<i32>,
}

/// What a retry or requeue answers: the new job and the old one.
#[derive(Serialize, Debug)]
pub struct Retried {
    pub id: String,
    pub job: JobDetail,
    pub previous: Option<JobDetail>,
}

/// RetryJob (`requeue` false) or RequeueJob, answered as [`Retried`].
async fn rerun(
    d: Dashboard,
    id: String,
    form: Option<Json<RetryForm>>,
    requeue: bool,
) -> Result<Json<Retried>, ApiError> {
    let r = Request::new(RetryJobRequest {
        job_id: id,
        priority: form.and_then(|f| f.0.priority),
    });
    let (r, method) = if requeue {
        (d.coordinator.requeue_job(r).await?, "RequeueJob")
    } else {
        (d.coordinator.retry_job(r).await?, "RetryJob")
    };
    let r = r.into_inner();
    let job = r.job.ok_or_else(|| {
        ApiError::from(tonic::Status::internal(format!("{method} answered no job")))
    })?;
    Ok(Json(Retried {
        id: job.job_id.clone(),
        job: JobDetail::from(&job),
        previous: r.previous.as_ref().map(JobDetail::from),
    }))
}

/// `POST /api/jobs/{id}/retry` (body optional: `{"priority": N}`): RetryJob.
pub async fn retry(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
    form: Option<Json<RetryForm>>,
) -> Result<Json<Retried>, ApiError> {
    rerun(d, id, form, false).await
}

/// `POST /api/jobs/{id}/requeue` (body optional: `{"priority": N}`): RequeueJob.
pub async fn requeue(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
    form: Option<Json<RetryForm>>,
) -> Result<Json<Retried>, ApiError> {
    rerun(d, id, form, true).await
}

/// PauseJob (`pause`) or ResumeJob, answered as the job after it.
async fn hold(d: Dashboard, id: String, pause: bool) -> Result<Json<JobDetail>, ApiError> {
    let r = Request::new(PauseJobRequest { job_id: id });
    let r = if pause {
        d.coordinator.pause_job(r).await?
    } else {
        d.coordinator.resume_job(r).await?
    };
    let job = r.into_inner().job.ok_or_else(|| {
        ApiError::from(tonic::Status::internal(
            "PauseJob or ResumeJob answered no job",
        ))
    })?;
    Ok(Json(JobDetail::from(&job)))
}

/// `POST /api/jobs/{id}/pause`: PauseJob.
pub async fn pause(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Json<JobDetail>, ApiError> {
    hold(d, id, true).await
}

/// `POST /api/jobs/{id}/resume`: ResumeJob.
pub async fn resume(
    State(d): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Json<JobDetail>, ApiError> {
    hold(d, id, false).await
}

/// `GET /api/jobs/{id}/download/{file}` with `file` `image.png` or `image.exr`: the
/// finished image as GetImage gives it (PNG with the default display transform, EXR
/// linear with its AOVs) as an attachment named after the job. 409 while the job has
/// not SUCCEEDED (a running job's pass image is `/api/jobs/{id}/image.png`).
pub async fn download(
    State(d): State<Dashboard>,
    Path((id, file)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let (format, ext) = match file.as_str() {
        "image.png" => (ImageFormat::Png, "png"),
        "image.exr" => (ImageFormat::Exr, "exr"),
        _ => {
            return Err(ApiError::new(
                StatusCode::NOT_FOUND,
                "NOT_FOUND",
                "no such download: image.png or image.exr",
            ));
        }
    };
    let r = d
        .coordinator
        .get_image(Request::new(GetImageRequest {
            job_id: id.clone(),
            format: format as i32,
            exposure: None,
            tonemap: String::new(),
        }))
        .await?
        .into_inner();
    if !r.r#final {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "FAILED_PRECONDITION",
            format!("job {id:?} has not finished: only a finished image is downloaded"),
        ));
    }
    tracing::info!(job = %id, format = ext, bytes = r.data.len(), "image downloaded");
    let name: String = id
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        .collect();
    let disposition = HeaderValue::from_str(&format!("attachment; filename=\"{name}.{ext}\""))
        .map_err(|e| ApiError::bad_request(format!("cannot name the file: {e}")))?;
    let content_type = HeaderValue::from_str(&r.content_type)
        .unwrap_or_else(|_| HeaderValue::from_static("application/octet-stream"));
    let mut resp = r.data.into_response();
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, content_type);
    h.insert(header::CONTENT_DISPOSITION, disposition);
    Ok(resp)
}
