//! Clients: channels that speak TLS when configured and present a bearer token on
//! every call.

use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, ClientTlsConfig, Endpoint};
use tonic::{Request, Status};

use crate::credential::Token;
use crate::tls::{TlsError, TlsFiles};

/// A channel whose calls carry a token.
pub type AuthChannel = InterceptedService<Channel, Bearer>;

/// Adds `authorization: Bearer TOKEN` to every call (nothing without a token), and the
/// current span's W3C trace context when the process exports traces ([`crate::trace`]).
#[derive(Clone, Debug, Default)]
pub struct Bearer(Option<MetadataValue<Ascii>>);

impl Interceptor for Bearer {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        crate::trace::inject_current(req.metadata_mut());
        Ok(req)
    }
}

/// Why a client cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("{address:?} is not a valid address: {message}")]
    Address { address: String, message: String },
    #[error(transparent)]
    Tls(#[from] TlsError),
}

/// How this process reaches others: its token and TLS settings.
#[derive(Clone, Debug, Default)]
pub struct ClientOptions {
    token: Option<Token>,
    tls: Option<ClientTlsConfig>,
}

impl ClientOptions {
    /// Plaintext, no token.
    pub fn plain() -> ClientOptions {
        ClientOptions::default()
    }

    /// Present `token` (if any) and use TLS per `tls`.
    pub fn new(token: Option<Token>, tls: &TlsFiles) -> Result<ClientOptions, ClientError> {
        Ok(ClientOptions {
            token,
            tls: tls.client()?,
        })
    }

    /// The same TLS settings, presenting `token` instead.
    pub fn with_token(&self, token: Option<Token>) -> ClientOptions {
        ClientOptions {
            token,
            tls: self.tls.clone(),
        }
    }

    /// Whether calls go over TLS.
    pub fn tls(&self) -> bool {
        self.tls.is_some()
    }

    /// `address` (`host:port`, `http://host:port` or `https://host:port`) as a URL of
    /// the right scheme: with TLS every address is `https`, without it `http`.
    pub fn url(&self, address: &str) -> String {
        let rest = address
            .strip_prefix("http://")
            .or_else(|| address.strip_prefix("https://"))
            .unwrap_or(address);
        let scheme = if self.tls() { "https" } else { "http" };
        format!("{scheme}://{rest}")
    }

    /// An endpoint for `address` with TLS applied; callers add their own timeouts.
    pub fn endpoint(&self, address: &str) -> Result<Endpoint, ClientError> {
        let url = self.url(address);
        let e = Endpoint::from_shared(url.clone()).map_err(|e| ClientError::Address {
            address: address.to_string(),
            message: e.to_string(),
        })?;
        match &self.tls {
            Some(tls) => e.tls_config(tls.clone()).map_err(|e| ClientError::Address {
                address: address.to_string(),
                message: e.to_string(),
            }),
            None => Ok(e),
        }
    }

    /// `channel` presenting this token.
    pub fn wrap(&self, channel: Channel) -> AuthChannel {
        let value = self
            .token
            .as_ref()
            .and_then(|t| MetadataValue::try_from(t.header()).ok());
        InterceptedService::new(channel, Bearer(value))
    }
}
