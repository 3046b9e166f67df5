//! `dray health [ADDR]`: ask a dray server (coordinator, worker, cache host) for its
//! status through the standard gRPC health protocol (`grpc.health.v1.Health/Check`), as a
//! Docker `HEALTHCHECK` or a script would.
//!
//! Exit status 0 when the server reports SERVING; 1 with one line saying why otherwise
//! (unreachable, NOT_SERVING, a service it does not know, no answer in time). Health is
//! open on every dray server, so no token is needed; the TLS flags (`--tls-ca`, and
//! `--tls-cert`/`--tls-key` where the server requires client certificates) apply as for
//! every other client, with the same environment variables.

use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use clap::Args;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

use crate::net_flags::TlsArgs;

/// The address checked when none is given: the coordinator's conventional port
/// ([`dray_net::DEFAULT_PORT`]) on this host (the image sets `DRAY_HEALTH_ADDR`; a
/// worker's container sets it to its port).
pub fn default_addr() -> String {
    format!("127.0.0.1:{}", dray_net::DEFAULT_PORT)
}

#[derive(Args, Debug)]
pub struct HealthArgs {
    /// The server: host:port, http://host:port or https://host:port.
    #[arg(value_name = "ADDR", env = "DRAY_HEALTH_ADDR", default_value_t = default_addr())]
    pub addr: String,
    /// The service whose status to ask for, e.g. dray.v1.RenderService (default: the
    /// server as a whole).
    #[arg(long, value_name = "NAME", default_value = "")]
    pub service: String,
    /// Seconds to wait for the connection and the answer, each.
    #[arg(long, value_name = "SECONDS", default_value_t = 5.0)]
    pub timeout: f64,
    /// Print nothing on success.
    #[arg(short, long)]
    pub quiet: bool,
    #[command(flatten)]
    pub tls: TlsArgs,
}

/// How a status reads to a person.
fn status_name(status: i32) -> String {
    match ServingStatus::try_from(status) {
        Ok(s) => s.as_str_name().to_string(),
        Err(_) => format!("status {status}"),
    }
}

/// The target as a person reads it: the address, and the service when one was asked for.
fn target(addr: &str, service: &str) -> String {
    if service.is_empty() {
        addr.to_string()
    } else {
        format!("{addr} (service {service})")
    }
}

/// Check once; Ok(()) only when SERVING.
async fn check(a: &HealthArgs, timeout: Duration) -> Result<()> {
    let net = crate::net_flags::client_options(None, &a.tls)?;
    let what = target(&a.addr, &a.service);
    let endpoint = net
        .endpoint(&a.addr)?
        .connect_timeout(timeout)
        .timeout(timeout);
    let channel = match tokio::time::timeout(timeout, endpoint.connect()).await {
        Ok(Ok(c)) => c,
        Ok(Err(e)) => {
            // The transport error's own text is "transport error"; its source says why.
            let mut why = Vec::new();
            let mut source: Option<&dyn std::error::Error> = std::error::Error::source(&e);
            while let Some(s) = source {
                why.push(s.to_string());
                source = s.source();
            }
            let why = if why.is_empty() {
                e.to_string()
            } else {
                why.join(": ")
            };
            bail!("{} is unreachable: {why}", a.addr);
        }
        Err(_) => bail!(
            "{} is unreachable: no connection within {:.1} s",
            a.addr,
            timeout.as_secs_f64()
        ),
    };
    let request = HealthCheckRequest {
        service: a.service.clone(),
    };
    let reply = HealthClient::new(channel).check(request).await;
    match reply {
        Ok(r) => {
            let status = r.into_inner().status;
            if status == ServingStatus::Serving as i32 {
                if !a.quiet {
                    println!("{what}: SERVING");
                }
                Ok(())
            } else {
                Err(anyhow!("{what} is not serving: {}", status_name(status)))
            }
        }
        Err(s) if s.code() == tonic::Code::NotFound => Err(anyhow!(
            "{} does not know the service {:?} (NOT_FOUND)",
            a.addr,
            a.service
        )),
        Err(s) if s.code() == tonic::Code::Unimplemented => Err(anyhow!(
            "{} answers gRPC but has no health service (UNIMPLEMENTED)",
            a.addr
        )),
        Err(s)
            if s.code() == tonic::Code::DeadlineExceeded || s.code() == tonic::Code::Cancelled =>
        {
            Err(anyhow!(
                "{what} did not answer within {:.1} s",
                timeout.as_secs_f64()
            ))
        }
        Err(s) if s.code() == tonic::Code::Unavailable => {
            Err(anyhow!("{} is unreachable: {}", a.addr, s.message()))
        }
        Err(s) => Err(anyhow!(
            "the health check of {what} failed: {:?}: {}",
            s.code(),
            s.message()
        )),
    }
}

pub fn run(a: HealthArgs) -> Result<()> {
    if !(a.timeout.is_finite() && a.timeout > 0.0 && a.timeout <= 3600.0) {
        bail!("--timeout {}: give seconds between 0 and 3600", a.timeout);
    }
    let timeout = Duration::from_secs_f64(a.timeout);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(check(&a, timeout))
}
