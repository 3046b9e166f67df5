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
use dray_net::connections::{ConnectionLimits, Guarded, Limited};
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto::Builder;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_stream::StreamExt;
use tonic::transport::server::TcpIncoming;

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
///
/// Connections are bounded as the gRPC servers' are (`dray_net::connections`, with
/// `limits`, a budget of the dashboard's own): at most `limits.max_connections` open,
/// at most `limits.max_per_address` from one source address, more closed at once; the
/// first bytes within `limits.handshake_timeout`. Beyond that the dashboard speaks
/// HTTP/1 and its event streams read nothing from the client for as long as they last,
/// so there is no idle timeout below HTTP: hyper's header timer closes a connection
/// whose request head has not all arrived `limits.handshake_timeout` after it started
/// waiting for it (a slow-header client, or a kept-alive connection left idle).
pub async fn serve(
    listener: TcpListener,
    dashboard: Dashboard,
    limits: ConnectionLimits,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), DashboardError> {
    let app = dashboard.router();
    let head_timeout = limits.handshake_timeout;
    let mut incoming = Limited::new(
        TcpIncoming::from(listener).with_nodelay(Some(true)),
        ConnectionLimits {
            idle_timeout: None,
            emulate: None,
            ..limits
        },
    );
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut connections = tokio::task::JoinSet::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            next = incoming.next() => match next {
                Some(Ok(io)) => {
                    let service = TowerToHyperService::new(app.clone());
                    let stop = stop_rx.clone();
                    connections.spawn(connection(io, service, head_timeout, stop));
                }
                Some(Err(e)) => tracing::debug!(error = %e, "a dashboard connection failed"),
                None => break,
            },
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
        }
    }
    drop(incoming);
    let _ = stop_tx.send(true);
    let _ = tokio::time::timeout(SHUTDOWN_GRACE, async {
        while connections.join_next().await.is_some() {}
    })
    .await;
    // Dropping the set cuts what is still open.
    Ok(())
}

/// Serve one connection until it ends, or until `stop` (then it ends gracefully: the
/// response in progress completes, nothing more is read).
async fn connection(
    io: Guarded,
    service: TowerToHyperService<Router>,
    head_timeout: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let mut builder = Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(head_timeout);
    let conn = builder.serve_connection_with_upgrades(TokioIo::new(io), service);
    let mut conn = std::pin::pin!(conn);
    tokio::select! {
        r = conn.as_mut() => {
            if let Err(e) = r {
                tracing::debug!(error = %e, "a dashboard connection ended");
            }
            return;
        }
        _ = stop.wait_for(|s| *s) => conn.as_mut().graceful_shutdown(),
    }
    let _ = conn.await;
}
