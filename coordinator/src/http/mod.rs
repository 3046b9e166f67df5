//! The web dashboard (`--http-listen ADDR`): a page served by the coordinator that
//! shows the jobs (state, progress, ETA, statistics, the image), the workers and their
//! domains, and submits and cancels jobs. Plain HTML, CSS and JavaScript embedded in the
//! binary ([`assets`]), JSON endpoints ([`api`]) and server-sent events ([`events`])
//! served with axum.
//!
//! Every endpoint calls the coordinator's RenderService methods in process, so what
//! the page can do, and what it is refused, is exactly what a gRPC client can do and
//! is refused. Who may call them is [`auth`]: the API token (as a bearer header or a
//! login cookie), and checks against cross-site requests. What a client may hold at
//! once is bounded: calls in progress ([`calls`], `--max-calls`) and event streams
//! ([`streams`], per client: [`client`]). The endpoints are listed in
//! docs/dashboard.md.

pub mod actions;
pub mod api;
pub mod assets;
pub mod auth;
pub mod calls;
pub mod client;
pub mod dto;
pub mod error;
pub mod events;
pub mod streams;

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
use tokio_stream::StreamExt;
use tonic::transport::server::TcpIncoming;

use crate::Coordinator;
use auth::Gate;
use calls::CallBudget;
use client::{Client, SourceAddress};
use error::ApiError;
use streams::StreamSlots;

/// Largest request body (a submission is a few hundred bytes).
const MAX_BODY: usize = 64 * 1024;
/// How long open connections (event streams) get to end after the stop signal.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(1);

/// What every handler shares: the coordinator, the credentials, the calls in progress
/// and the open event streams.
#[derive(Clone)]
pub struct Dashboard {
    pub coordinator: Coordinator,
    pub gate: Arc<Gate>,
    pub calls: Arc<CallBudget>,
    pub streams: Arc<StreamSlots>,
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
    /// gRPC API requires), with the gRPC servers' default bound on calls in progress.
    pub fn new(coordinator: Coordinator, api_token: Option<Token>) -> Result<Self, DashboardError> {
        Ok(Dashboard {
            coordinator,
            gate: Arc::new(Gate::new(api_token).map_err(|_| DashboardError::Key)?),
            calls: Arc::new(CallBudget::new(dray_net::server::DEFAULT_MAX_CALLS)),
            streams: Arc::new(StreamSlots::new(
                streams::MAX_STREAMS,
                streams::MAX_STREAMS_PER_CLIENT,
            )),
        })
    }

    /// At most `max_calls` API calls in progress at once (`--max-calls`, the gRPC
    /// servers' bound per class of caller), in a budget of the dashboard's own.
    pub fn with_max_calls(mut self, max_calls: usize) -> Self {
        self.calls = Arc::new(CallBudget::new(max_calls));
        self
    }

    /// The routes: the page and its files (open: they hold no data), the session
    /// endpoints, and the API behind the gate.
    pub fn router(self) -> Router {
        let guarded = Router::new()
            .route("/api/jobs", get(api::list_jobs).post(api::submit))
            .route("/api/jobs/{id}", get(api::get_job))
            .route("/api/jobs/{id}/cancel", post(api::cancel))
            .route("/api/jobs/{id}/image.png", get(api::image))
            .route("/api/jobs/{id}/retry", post(actions::retry))
            .route("/api/jobs/{id}/requeue", post(actions::requeue))
            .route("/api/jobs/{id}/pause", post(actions::pause))
            .route("/api/jobs/{id}/resume", post(actions::resume))
            .route("/api/jobs/{id}/download/{file}", get(actions::download))
            .route("/api/jobs/{id}/events", get(events::job_progress))
            .route("/api/workers", get(api::workers))
            .route("/api/events", get(events::snapshots))
            // Layers run last-added first: the credential, then a place among the calls.
            .route_layer(middleware::from_fn_with_state(self.clone(), calls::admit))
            .route_layer(middleware::from_fn_with_state(self.clone(), guard));
        Router::new()
            .route("/", get(assets::index))
            .route("/app.js", get(assets::script))
            .route("/operator.js", get(assets::operator_script))
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
/// only from this page ([`auth`]); tells the handlers which [`Client`] it is from.
async fn guard(State(d): State<Dashboard>, mut req: Request, next: Next) -> Response {
    let checked = d
        .gate
        .authenticate(req.headers(), SystemTime::now())
        .and_then(|c| Gate::check_csrf(req.method(), req.headers(), c).map(|()| c));
    match checked {
        Ok(credential) => {
            let source = req.extensions().get::<SourceAddress>().copied();
            req.extensions_mut().insert(Client::of(credential, source));
            next.run(req).await
        }
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
                    let service = TowerToHyperService::new(FromSource {
                        app: app.clone(),
                        source: io.source().map(SourceAddress),
                    });
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

/// The router, with each request told the source address of its connection.
#[derive(Clone)]
struct FromSource {
    app: Router,
    source: Option<SourceAddress>,
}

impl<B> tower::Service<axum::http::Request<B>> for FromSource
where
    Router: tower::Service<axum::http::Request<B>>,
{
    type Response = <Router as tower::Service<axum::http::Request<B>>>::Response;
    type Error = <Router as tower::Service<axum::http::Request<B>>>::Error;
    type Future = <Router as tower::Service<axum::http::Request<B>>>::Future;

    fn poll_ready(
        &mut self,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Result<(), Self::Error>> {
        tower::Service::<axum::http::Request<B>>::poll_ready(&mut self.app, cx)
    }

    fn call(&mut self, mut req: axum::http::Request<B>) -> Self::Future {
        if let Some(source) = self.source {
            req.extensions_mut().insert(source);
        }
        tower::Service::call(&mut self.app, req)
    }
}

/// Serve one connection until it ends, or until `stop` (then it ends gracefully: the
/// response in progress completes, nothing more is read).
async fn connection(
    io: Guarded,
    service: TowerToHyperService<FromSource>,
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
