//! The flags that say how dray processes authenticate and encrypt their gRPC calls,
//! shared by every command that serves or calls (see dray-net for what they do).
//!
//! - `--auth-token-file FILE` (or `DRAY_AUTH_TOKEN` holding the token itself): the
//!   **API token** the coordinator requires on `RenderService`, and that `dray submit`,
//!   `dray sweep --coordinator` and grpcurl (`-H "authorization: Bearer TOKEN"`) present.
//! - `--cluster-token-file FILE` (or `DRAY_CLUSTER_TOKEN`): the **cluster token** every
//!   member presents and requires on the cluster's own services. API clients never hold
//!   it. `dray cluster` and `dray render` make one for their own processes.
//! - `--tls-cert`, `--tls-key`, `--tls-ca` (PEM files): TLS on every server and client;
//!   with `--tls-ca` on a server, clients must present a certificate it signed.
//! - `--emulate-link SPEC` (members only): shape every connection the member's servers
//!   accept as a link of a real cluster (`dray_net::emulate`), for experiments that
//!   price communication on one machine.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use dray_net::{ClientOptions, LinkEmulation, ServerOptions, TlsFiles, Token};

/// The environment variable holding the API token itself.
pub const API_TOKEN_ENV: &str = "DRAY_AUTH_TOKEN";
/// The environment variable holding the cluster token itself.
pub const CLUSTER_TOKEN_ENV: &str = "DRAY_CLUSTER_TOKEN";

/// TLS certificate files.
#[derive(Args, Debug, Clone, Default)]
pub struct TlsArgs {
    /// This process's TLS certificate chain (PEM). With --tls-key, servers speak TLS.
    #[arg(long, value_name = "FILE", env = "DRAY_TLS_CERT")]
    pub tls_cert: Option<PathBuf>,
    /// The private key of --tls-cert (PEM).
    #[arg(long, value_name = "FILE", env = "DRAY_TLS_KEY")]
    pub tls_key: Option<PathBuf>,
    /// The certificate authority to trust (PEM). Clients check servers against it; a
    /// server given it requires client certificates it signed (mutual TLS).
    #[arg(long, value_name = "FILE", env = "DRAY_TLS_CA")]
    pub tls_ca: Option<PathBuf>,
}

impl TlsArgs {
    pub fn files(&self) -> TlsFiles {
        TlsFiles {
            cert: self.tls_cert.clone(),
            key: self.tls_key.clone(),
            ca: self.tls_ca.clone(),
        }
    }

    /// The flags again, for a child process.
    pub fn to_args(&self) -> Vec<String> {
        let mut v = Vec::new();
        for (flag, path) in [
            ("--tls-cert", &self.tls_cert),
            ("--tls-key", &self.tls_key),
            ("--tls-ca", &self.tls_ca),
        ] {
            if let Some(p) = path {
                v.push(flag.to_string());
                v.push(p.display().to_string());
            }
        }
        v
    }
}

/// The API token (coordinator, and the clients of its public API).
#[derive(Args, Debug, Clone, Default)]
pub struct ApiTokenArgs {
    /// File holding the API token: the coordinator requires it on RenderService, clients
    /// present it. Without it (and without DRAY_AUTH_TOKEN) the API is open.
    #[arg(long, value_name = "FILE", env = "DRAY_AUTH_TOKEN_FILE")]
    pub auth_token_file: Option<PathBuf>,
}

impl ApiTokenArgs {
    /// The token, from the file or from `DRAY_AUTH_TOKEN`.
    pub fn token(&self) -> Result<Option<Token>> {
        token(
            self.auth_token_file.as_deref(),
            API_TOKEN_ENV,
            "--auth-token-file",
        )
    }
}

/// The cluster token (every member).
#[derive(Args, Debug, Clone, Default)]
pub struct ClusterTokenArgs {
    /// File holding the cluster token: members present it to each other and require it
    /// on the cluster's own services. Without it (and without DRAY_CLUSTER_TOKEN) those
    /// services are open to anyone who can reach the ports.
    #[arg(long, value_name = "FILE", env = "DRAY_CLUSTER_TOKEN_FILE")]
    pub cluster_token_file: Option<PathBuf>,
}

impl ClusterTokenArgs {
    /// The token, from the file or from `DRAY_CLUSTER_TOKEN`.
    pub fn token(&self) -> Result<Option<Token>> {
        token(
            self.cluster_token_file.as_deref(),
            CLUSTER_TOKEN_ENV,
            "--cluster-token-file",
        )
    }
}

/// The token in `file`, else in the environment variable `env`, else none.
fn token(file: Option<&Path>, env: &str, flag: &str) -> Result<Option<Token>> {
    if let Some(f) = file {
        return Token::from_file(f)
            .map(Some)
            .with_context(|| flag.to_string());
    }
    match std::env::var(env) {
        Ok(v) => Token::parse(&v, &format!("in {env}"))
            .map(Some)
            .map_err(Into::into),
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(_)) => {
            anyhow::bail!("{env} is not valid UTF-8")
        }
    }
}

/// A cluster member's flags: its cluster token, TLS, and how many calls its servers
/// take at once.
#[derive(Args, Debug, Clone, Default)]
pub struct MemberArgs {
    #[command(flatten)]
    pub cluster_token: ClusterTokenArgs,
    #[command(flatten)]
    pub tls: TlsArgs,
    /// Calls in progress at once on this process's servers, in each class of caller
    /// (health, reflection, API, cluster; a stream counts until it ends); more are
    /// refused at once with RESOURCE_EXHAUSTED.
    #[arg(long, value_name = "N", default_value_t = dray_net::server::DEFAULT_MAX_CALLS)]
    pub max_calls: usize,
    /// An emulated interconnect, for experiments: every connection this process's
    /// servers accept behaves like a link of this bandwidth and latency, each way
    /// (`bandwidth=1gbit,latency=100us`; units bit/kbit/mbit/gbit/tbit and ns/us/ms/s;
    /// either key may be left out). Off by default.
    #[arg(long, value_name = "SPEC", value_parser = parse_link)]
    pub emulate_link: Option<LinkEmulation>,
}

/// `--emulate-link SPEC`.
pub fn parse_link(spec: &str) -> Result<LinkEmulation, String> {
    spec.parse()
        .map_err(|e: dray_net::emulate::LinkSpecError| e.to_string())
}

/// `--emulate-link SPEC` for a child process, when set.
pub fn link_args(link: Option<&LinkEmulation>) -> Vec<String> {
    link.map(|l| vec!["--emulate-link".to_string(), l.to_string()])
        .unwrap_or_default()
}

impl MemberArgs {
    /// How this member serves (requiring the cluster token) and calls (presenting it).
    pub fn options(&self) -> Result<(ServerOptions, ClientOptions)> {
        let token = self.cluster_token.token()?;
        let server = server_options(None, token.clone(), self)?;
        let client = client_options(token, &self.tls)?;
        Ok((server, client))
    }
}

/// Server options for a member requiring `api` (coordinator only) and `cluster`, with
/// its TLS, call bound and link emulation.
pub fn server_options(
    api: Option<Token>,
    cluster: Option<Token>,
    member: &MemberArgs,
) -> Result<ServerOptions> {
    let mut o = ServerOptions::new(api, cluster, &member.tls.files())?;
    o.max_calls = member.max_calls;
    o.emulate = member.emulate_link;
    Ok(o)
}

/// Client options presenting `token`, with TLS per `tls`.
pub fn client_options(token: Option<Token>, tls: &TlsArgs) -> Result<ClientOptions> {
    Ok(ClientOptions::new(token, &tls.files())?)
}

/// Write `token` to a new file only this user can read (0600), `name` in `dir`, for
/// child processes. `dir` must exist (a private directory: see
/// `dray_scene::private_fs`); the file must not: an existing file or a symlink there is
/// refused, never replaced or followed.
pub fn write_token_file(dir: &Path, name: &str, token: &Token) -> Result<PathBuf> {
    use std::io::Write;
    let path = dir.join(name);
    let mut f = dray_scene::private_fs::create_new(&path, 0o600)
        .with_context(|| format!("cannot create {}", path.display()))?;
    f.write_all(token.expose().as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}
