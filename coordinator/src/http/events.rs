//! Live updates as server-sent events, at a bounded rate whatever the cluster does:
//!
//! - `GET /api/events?jobs=N&page_token=T&interval_ms=M`: a `snapshot` event (the
//!   jobs page, ListJobs, and the workers with the running jobs' domain owners,
//!   ListWorkers) at once and then at most every `interval_ms` (default 1000,
//!   250..=10000), only when something changed. Rows carry no statistics, so 100 jobs
//!   are a few tens of kilobytes.
//! - `GET /api/jobs/{id}/events`: WatchJob's messages for one job (with its
//!   statistics) as `progress` events, at most every 500 ms, ending after the terminal
//!   state; an error (an unknown job) is one `failed` event.
//!
//! At most [`MAX_STREAMS`] streams are open at once, and at most
//! [`MAX_STREAMS_PER_CLIENT`] of one client ([`super::streams`]); more are refused with
//! 503 (the page tries again later), so a crowd of open tabs cannot pile work on the
//! coordinator and one client cannot lock the others out. A stream a session opened
//! ends when the session does (logout).

use std::convert::Infallible;
use std::time::Duration;

use axum::Extension;
use axum::extract::{Path, Query, State};
use axum::response::sse::{Event, KeepAlive, KeepAliveStream, Sse};
use dray_proto::v1::WatchJobRequest;
use dray_proto::v1::render_service_server::RenderService;
use serde::{Deserialize, Serialize};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Request;

use super::Dashboard;
use super::client::Client;
use super::dto::{JobPage, Progress, Workers};
use super::error::ApiError;
pub use super::streams::{MAX_STREAMS, MAX_STREAMS_PER_CLIENT};
/// Default, least and largest time between two snapshots.
const SNAPSHOT_INTERVAL: Duration = Duration::from_millis(1000);
const MIN_SNAPSHOT_INTERVAL: Duration = Duration::from_millis(250);
const MAX_SNAPSHOT_INTERVAL: Duration = Duration::from_secs(10);
/// Least time between two progress events of one job.
const PROGRESS_INTERVAL: Duration = Duration::from_millis(500);
/// Most jobs in a snapshot.
const MAX_SNAPSHOT_JOBS: u32 = 200;
/// Default jobs in a snapshot.
const SNAPSHOT_JOBS: u32 = 100;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SnapshotQuery {
    #[serde(default)]
    pub jobs: Option<u32>,
    #[serde(default)]
    pub page_token: String,
    #[serde(default)]
    pub interval_ms: Option<u64>,
}

/// What a `snapshot` event holds.
#[derive(Serialize, PartialEq)]
pub struct Snapshot {
    pub jobs: JobPage,
    pub workers: Workers,
}

type Events = Sse<KeepAliveStream<ReceiverStream<Result<Event, Infallible>>>>;

/// The answer carrying what a stream's task sends on `rx`.
fn events(rx: tokio::sync::mpsc::Receiver<Result<Event, Infallible>>) -> Events {
    Sse::new(ReceiverStream::new(rx)).keep_alive(KeepAlive::default())
}

/// `GET /api/events`.
pub async fn snapshots(
    State(d): State<Dashboard>,
    Extension(client): Extension<Client>,
    Query(q): Query<SnapshotQuery>,
) -> Result<Events, ApiError> {
    let permit = d.streams.take(client)?;
    let jobs = q.jobs.unwrap_or(SNAPSHOT_JOBS).clamp(1, MAX_SNAPSHOT_JOBS);
    let interval = q
        .interval_ms
        .map_or(SNAPSHOT_INTERVAL, Duration::from_millis)
        .clamp(MIN_SNAPSHOT_INTERVAL, MAX_SNAPSHOT_INTERVAL);
    // The first snapshot is made here, so a bad page token is this request's error.
    let first = d.snapshot(jobs, q.page_token.clone()).await?;
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Event, Infallible>>(2);
    tokio::spawn(async move {
        let _permit = permit;
        let mut last = None;
        let mut next: Result<Snapshot, ApiError> = Ok(first);
        loop {
            match next {
                Ok(s) => {
                    let json = serde_json::to_string(&s).unwrap_or_default();
                    if last.as_ref() != Some(&json) {
                        let event = Event::default().event("snapshot").data(&json);
                        if tx.send(Ok(event)).await.is_err() {
                            return;
                        }
                        last = Some(json);
                    }
                }
                Err(e) => {
                    let event = Event::default().event("failed").data(e.message);
                    let _ = tx.send(Ok(event)).await;
                    return;
                }
            }
            tokio::select! {
                _ = tokio::time::sleep(interval) => {}
                _ = tx.closed() => return,
            }
            if let Some(ended) = d.session_ended(client) {
                let _ = tx.send(Ok(ended)).await;
                return;
            }
            next = d.snapshot(jobs, q.page_token.clone()).await;
        }
    });
    Ok(events(rx))
}

/// `GET /api/jobs/{id}/events`.
pub async fn job_progress(
    State(d): State<Dashboard>,
    Extension(client): Extension<Client>,
    Path(id): Path<String>,
) -> Result<Events, ApiError> {
    let permit = d.streams.take(client)?;
    let mut watch = d
        .coordinator
        .watch_job(Request::new(WatchJobRequest {
            job_id: id,
            min_interval: prost_types::Duration::try_from(PROGRESS_INTERVAL).ok(),
        }))
        .await?
        .into_inner();
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Event, Infallible>>(2);
    tokio::spawn(async move {
        let _permit = permit;
        loop {
            let item = tokio::select! {
                item = watch.next() => item,
                _ = tx.closed() => return,
            };
            if let Some(ended) = d.session_ended(client) {
                let _ = tx.send(Ok(ended)).await;
                return;
            }
            let event = match item {
                None => return,
                Some(Ok(p)) => {
                    let json = serde_json::to_string(&Progress::from(&p)).unwrap_or_default();
                    Event::default().event("progress").data(json)
                }
                Some(Err(status)) => Event::default().event("failed").data(status.message()),
            };
            if tx.send(Ok(event)).await.is_err() {
                return;
            }
        }
    });
    Ok(events(rx))
}

impl Dashboard {
    /// The last event of a stream whose session has ended (logged out, or expired), so
    /// a copied cookie's stream does not outlive the logout; `None` while it lives, and
    /// for a client that is no session.
    fn session_ended(&self, client: Client) -> Option<Event> {
        match client {
            Client::Session(id) if !self.gate.session_live(&id, std::time::SystemTime::now()) => {
                Some(
                    Event::default()
                        .event("failed")
                        .data("the session has ended: log in again"),
                )
            }
            _ => None,
        }
    }

    /// One snapshot: the first `jobs` jobs from `page_token`.
    async fn snapshot(&self, jobs: u32, page_token: String) -> Result<Snapshot, ApiError> {
        Ok(Snapshot {
            jobs: self.job_page(jobs, page_token).await?,
            workers: self.workers().await?,
        })
    }
}
