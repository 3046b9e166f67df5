//! TLS for servers and clients, from PEM files: a server's certificate and key, and the
//! certificate authority both sides trust. With a CA on a server, clients must present
//! a certificate it signed (mutual TLS).

use std::path::{Path, PathBuf};

use tonic::transport::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};

/// Why TLS cannot be set up.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("cannot read {what} {path}: {message}")]
    Read {
        what: &'static str,
        path: String,
        message: String,
    },
    #[error("{0}")]
    Incomplete(String),
}

/// Certificate files, as given on the command line (`--tls-cert`, `--tls-key`,
/// `--tls-ca`).
#[derive(Clone, Debug, Default)]
pub struct TlsFiles {
    /// This process's certificate chain (PEM): needed to serve; with a key, also
    /// presented as a client certificate.
    pub cert: Option<PathBuf>,
    /// Its private key (PEM).
    pub key: Option<PathBuf>,
    /// The certificate authority to trust (PEM): clients check servers against it; a
    /// server with it requires client certificates it signed.
    pub ca: Option<PathBuf>,
}

/// Files larger than this are not certificates.
const MAX_PEM_BYTES: u64 = 1 << 20;

fn read(what: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    let err = |message: String| TlsError::Read {
        what,
        path: path.display().to_string(),
        message,
    };
    let meta = std::fs::metadata(path).map_err(|e| err(e.to_string()))?;
    if !meta.is_file() {
        return Err(err("not a regular file".into()));
    }
    if meta.len() > MAX_PEM_BYTES {
        return Err(err(format!("larger than {MAX_PEM_BYTES} bytes")));
    }
    std::fs::read(path).map_err(|e| err(e.to_string()))
}

impl TlsFiles {
    /// Whether any TLS file was given.
    pub fn enabled(&self) -> bool {
        self.cert.is_some() || self.key.is_some() || self.ca.is_some()
    }

    fn identity(&self) -> Result<Option<Identity>, TlsError> {
        match (&self.cert, &self.key) {
            (Some(c), Some(k)) => Ok(Some(Identity::from_pem(
                read("the certificate", c)?,
                read("the private key", k)?,
            ))),
            (None, None) => Ok(None),
            _ => Err(TlsError::Incomplete(
                "--tls-cert and --tls-key go together".into(),
            )),
        }
    }

    /// The server side: `None` when no file was given (plaintext).
    pub fn server(&self) -> Result<Option<ServerTlsConfig>, TlsError> {
        if !self.enabled() {
            return Ok(None);
        }
        let identity = self.identity()?.ok_or_else(|| {
            TlsError::Incomplete("a TLS server needs --tls-cert and --tls-key".into())
        })?;
        let mut config = ServerTlsConfig::new().identity(identity);
        if let Some(ca) = &self.ca {
            config = config.client_ca_root(Certificate::from_pem(read("the CA certificate", ca)?));
        }
        Ok(Some(config))
    }

    /// The client side: `None` when no file was given (plaintext).
    pub fn client(&self) -> Result<Option<ClientTlsConfig>, TlsError> {
        if !self.enabled() {
            return Ok(None);
        }
        // No system roots are built in: a cluster's certificates come from its own CA.
        let ca = self.ca.as_ref().ok_or_else(|| {
            TlsError::Incomplete(
                "a TLS client needs --tls-ca (the CA that signed the servers' certificates)".into(),
            )
        })?;
        let mut config = ClientTlsConfig::new()
            .ca_certificate(Certificate::from_pem(read("the CA certificate", ca)?));
        if let Some(identity) = self.identity()? {
            config = config.identity(identity);
        }
        Ok(Some(config))
    }
}
