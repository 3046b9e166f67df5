//! The web dashboard (`--http-listen ADDR`): a page served by the coordinator that
//! shows the jobs (state, progress, ETA, statistics, the image), the workers and their
//! domains, and submits and cancels jobs. Plain HTML, CSS and JavaScript embedded in the
//! binary ([`assets`]), JSON endpoints ([`api`]) and server-sent events ([`events`])
//! served with axum.
//!
//! Every endpoint calls the coordinator's RenderService methods in process, so what
//! the page can do, and what it is refused, is exactly what a gRPC client can do and
//! is refused. Who may call them is [`auth`]: the API token (as a bearer header or a
//! login cookie), and checks against cross-site requests. The endpoints are listed in
//! docs/dashboard.md.

pub mod api;
pub mod assets;
pub mod auth;
pub mod dto;
pub mod error;
pub mod events;

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use dray_net::Token;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

use crate::Coordinator;
use auth::Gate;
use error::ApiError;

/// Largest request body (a submission is a few hundred bytes).
const MAX_BODY: usize = 64 * 1024;
/// How long open connections (event streams) get to end after the stop signal.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(1);

/// What every handler shares: the coordinator, the credentials, the open event streams.
#[derive(Clone)]
pub struct Dashboard {
    pub coordinator: Coordinator,
    pub gate: Arc<Gate>,
    pub streams: Arc<Semaphore>,
}

/// Why the dashboard cannot start.
#[derive(Debug, thiserror::Error)]
pub enum DashboardError {
    #[error("cannot make the dashboard's session key")]
    Key,
    #[error("the dashboard server failed: {0}")]
    Serve(#[from] std::io::Error),
}

impl Dashboard {
    /// The dashboard of `coordinator`, requiring `api_token` when given (the one the
    /// gRPC API requires).
    pub fn new(coordinator: Coordinator, api_token: Option<Token>) -> Result<Self, DashboardError> {
        Ok(Dashboard {
            coordinator,
            gate: Arc::new(Gate::new(api_token).map_err(|_| DashboardError::Key)?),
            streams: Arc::new(Semaphore::new(events::MAX_STREAMS)),
        })
    }

    /// The routes: the page and its files (open: they hold no data), the session
    /// endpoints, and the API behind the gate.
    pub fn router(self) -> Router {
        let guarded = Router::new()
            .route("/api/jobs", get(api::list_jobs).post(api::submit))
            .route("/api/jobs/{id}", get(api::get_job))
            .route("/api/jobs/{id}/cancel", post(api::cancel))
            .route("/api/jobs/{id}/image.png", get(api::image))
            .route("/api/jobs/{id}/events", get(events::job_progress))
            .route("/api/workers", get(api::workers))
            .route("/api/events", get(events::snapshots))
            .route_layer(middleware::from_fn_with_state(self.clone(), guard));
        Router::new()
            .route("/", get(assets::index))
            .route("/app.js", get(assets::script))
            .route("/style.css", get(assets::style))
            .route("/api/session", get(api::session))
            .route("/api/login", post(api::login))
            .route("/api/logout", post(api::logout))
            .merge(guarded)
            .fallback(not_found)
            .layer(DefaultBodyLimit::max(MAX_BODY))
            .layer(middleware::from_fn(assets::security_headers))
            .with_state(self)
    }
}

/// Lets a request to the API through only with a credential, and a state-changing one
/// only from this page ([`auth`]).
async fn guard(State(d): State<Dashboard>, req: Request, next: Next) -> Response {
    let checked = d
        .gate
        .authenticate(req.headers(), SystemTime::now())
        .and_then(|c| Gate::check_csrf(req.method(), req.headers(), c));
    match checked {
        Ok(()) => next.run(req).await,
        Err(denied) => ApiError::from(denied).into_response(),
    }
}

async fn not_found() -> ApiError {
    ApiError::new(
        axum::http::StatusCode::NOT_FOUND,
        "NOT_FOUND",
        "no such page or endpoint",
    )
}

/// Serve `dashboard` on `listener` until `shutdown` completes (open event streams then
/// get [`SHUTDOWN_GRACE`] to end before they are cut).
pub async fn serve(
    listener: TcpListener,
    dashboard: Dashboard,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), DashboardError> {
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let app = dashboard.router();
    let server = axum::serve(listener, app).with_graceful_shutdown(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
    });
    let mut stopped = stop_rx;
    tokio::select! {
        r = server => r?,
        _ = async {
            let _ = stopped.wait_for(|s| *s).await;
            tokio::time::sleep(SHUTDOWN_GRACE).await;
        } => {}
    }
    Ok(())
}
