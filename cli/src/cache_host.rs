//! A cache host in this process: `dray_cache`'s CacheService on its own listener, the
//! way `dray worker` (by default), the embedded mode (for jobs with ray caches) and
//! `dray cache` run one. The coordinator places cache actors on it and workers in
//! other processes reach it over gRPC; a worker in this process is handed the host
//! itself ([`LocalCacheHost::host`]) and reaches its actors through their mailboxes.

use std::net::SocketAddr;

use anyhow::{Context, Result, anyhow};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::JoinHandle;

/// How long a cache host gets to stop serving before it is abandoned (a worker's
/// stream to it may still be open).
const STOP_GRACE: std::time::Duration = std::time::Duration::from_secs(2);

/// A running cache host; stop it with [`LocalCacheHost::stop`] (dropping it aborts it).
pub struct LocalCacheHost {
    /// Where it listens.
    pub addr: SocketAddr,
    /// Where workers and the coordinator reach it.
    pub endpoint: String,
    /// The host it serves, for a worker in this process.
    pub host: dray_cache::CacheHost,
    stop: watch::Sender<bool>,
    task: Option<JoinHandle<Result<(), dray_cache::ServeError>>>,
}

impl LocalCacheHost {
    /// Bind `listen` and serve a new cache host there, advertised at `endpoint` when
    /// given, else at `http://` + its host beside `advertised_host` (or the bound
    /// address) and the bound port.
    pub async fn start(
        listen: &str,
        endpoint: Option<String>,
        advertised_host: Option<&str>,
        options: &dray_net::ServerOptions,
    ) -> Result<LocalCacheHost> {
        let listener = TcpListener::bind(listen)
            .await
            .with_context(|| format!("cannot listen on {listen} for the cache host"))?;
        let addr = listener
            .local_addr()
            .context("cannot read the cache host's bound address")?;
        let endpoint = endpoint.unwrap_or_else(|| match advertised_host {
            Some(h) => format!("http://{h}:{}", addr.port()),
            None => format!("http://{addr}"),
        });
        let (stop, mut stopped) = watch::channel(false);
        let options = options.clone();
        let host = dray_cache::CacheHost::new();
        let serving = host.clone();
        let task = tokio::spawn(async move {
            serving
                .serve_with(&options, listener, async move {
                    let _ = stopped.wait_for(|s| *s).await;
                })
                .await
        });
        Ok(LocalCacheHost {
            addr,
            endpoint,
            host,
            stop,
            task: Some(task),
        })
    }

    /// Completes if the server stops on its own (it failed), with why.
    pub async fn ended(&mut self) -> anyhow::Error {
        let Some(task) = self.task.as_mut() else {
            return std::future::pending().await;
        };
        let r = task.await;
        self.task = None;
        match r {
            Ok(Ok(())) => anyhow!("the cache host at {} stopped", self.endpoint),
            Ok(Err(e)) => anyhow!("the cache host at {} failed: {e}", self.endpoint),
            Err(e) => anyhow!("the cache host at {} died: {e}", self.endpoint),
        }
    }

    /// Stop serving (gracefully, for at most a short grace time).
    pub async fn stop(mut self) {
        let _ = self.stop.send(true);
        if let Some(task) = self.task.take() {
            let abort = task.abort_handle();
            match tokio::time::timeout(STOP_GRACE, task).await {
                Ok(Ok(Err(e))) => tracing::warn!("cache host: {e}"),
                Ok(_) => {}
                Err(_) => abort.abort(),
            }
        }
    }
}

impl Drop for LocalCacheHost {
    fn drop(&mut self) {
        if let Some(t) = &self.task {
            t.abort();
        }
    }
}

/// The host part of an advertised URL such as `http://10.0.0.7:7001` (`10.0.0.7`;
/// `[::1]` for an IPv6 address), so a cache host beside a worker is advertised at the
/// worker's host with its own port.
pub fn advertised_host(url: &str) -> Option<String> {
    let rest = url.trim();
    let rest = rest
        .strip_prefix("http://")
        .or_else(|| rest.strip_prefix("https://"))
        .unwrap_or(rest);
    let authority = rest.split('/').next().unwrap_or_default();
    let host = if authority.starts_with('[') {
        authority.find(']').map(|i| &authority[..=i])?
    } else {
        match authority.rsplit_once(':') {
            Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) => h,
            _ => authority,
        }
    };
    (!host.is_empty()).then(|| host.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_of_urls() {
        assert_eq!(
            advertised_host("http://10.0.0.7:7001").as_deref(),
            Some("10.0.0.7")
        );
        assert_eq!(
            advertised_host("https://node-3/x").as_deref(),
            Some("node-3")
        );
        assert_eq!(
            advertised_host("http://[::1]:7001").as_deref(),
            Some("[::1]")
        );
        assert_eq!(
            advertised_host("worker.svc:80").as_deref(),
            Some("worker.svc")
        );
        assert_eq!(advertised_host("http://"), None);
        assert_eq!(advertised_host("http://[::1"), None);
    }

    #[tokio::test]
    async fn serves_and_stops() {
        let h = LocalCacheHost::start(
            "127.0.0.1:0",
            None,
            Some("example"),
            &dray_net::ServerOptions::default(),
        )
        .await
        .unwrap();
        assert_eq!(h.endpoint, format!("http://example:{}", h.addr.port()));
        // It answers gRPC health.
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", h.addr))
            .unwrap()
            .connect()
            .await
            .unwrap();
        let r = tonic_health::pb::health_client::HealthClient::new(channel)
            .check(tonic_health::pb::HealthCheckRequest {
                service: "dray.v1.CacheService".into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            r.status,
            tonic_health::pb::health_check_response::ServingStatus::Serving as i32
        );
        h.stop().await;
        let busy = LocalCacheHost::start(
            "256.0.0.1:0",
            None,
            None,
            &dray_net::ServerOptions::default(),
        )
        .await;
        assert!(busy.is_err());
    }
}
