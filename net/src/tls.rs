//! TLS for servers and clients, from PEM files: a server's certificate and key, and the
//! certificate authority both sides trust. With a CA on a server, clients must present
//! a certificate it signed (mutual TLS).
//!
//! Every file is read, parsed and checked when the options are made, before anything
//! listens or dials: a file that is not PEM, holds no certificate or key, or a key that
//! is not the certificate's is an error naming the file. (tonic only parses them when the
//! first connection's handshake runs, which printed "listening ... TLS" and then failed
//! every call with a transport error naming nothing.)

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
    #[error("{what} {path}: {message}")]
    Invalid {
        what: &'static str,
        path: String,
        message: String,
    },
    #[error("--tls-key {key} is not the private key of --tls-cert {cert}: {message}")]
    Mismatch {
        cert: String,
        key: String,
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

fn invalid(what: &'static str, path: &Path, message: impl Into<String>) -> TlsError {
    TlsError::Invalid {
        what,
        path: path.display().to_string(),
        message: message.into(),
    }
}

/// The certificates of a PEM file: at least one, every PEM certificate block valid.
fn certificates(what: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let pem = read(what, path)?;
    let mut count = 0usize;
    for cert in CertificateDer::pem_slice_iter(&pem) {
        let cert = cert.map_err(|e| invalid(what, path, format!("not a PEM certificate ({e})")))?;
        rustls::server::ParsedCertificate::try_from(&cert)
            .map_err(|e| invalid(what, path, format!("not a valid X.509 certificate ({e})")))?;
        count += 1;
    }
    if count == 0 {
        return Err(invalid(what, path, "holds no PEM certificate"));
    }
    Ok(pem)
}

/// Check that `key_pem` is a private key rustls can sign with and that it belongs to
/// the first certificate of `cert_pem`.
fn check_pair(cert: &Path, cert_pem: &[u8], key: &Path, key_pem: &[u8]) -> Result<(), TlsError> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    let what = "the private key";
    let der = PrivateKeyDer::from_pem_slice(key_pem)
        .map_err(|e| invalid(what, key, format!("holds no PEM private key ({e})")))?;
    let provider = rustls::crypto::ring::default_provider();
    let signing = provider
        .key_provider
        .load_private_key(der)
        .map_err(|e| invalid(what, key, format!("not a usable private key ({e})")))?;
    let chain = CertificateDer::pem_slice_iter(cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| {
            invalid(
                "the certificate",
                cert,
                format!("not a PEM certificate ({e})"),
            )
        })?;
    match rustls::sign::CertifiedKey::new(chain, signing).keys_match() {
        Ok(()) => Ok(()),
        // A key type whose public half rustls cannot derive: tonic will find out.
        Err(rustls::Error::InconsistentKeys(rustls::InconsistentKeys::Unknown)) => Ok(()),
        Err(e) => Err(TlsError::Mismatch {
            cert: cert.display().to_string(),
            key: key.display().to_string(),
            message: e.to_string(),
        }),
    }
}

impl TlsFiles {
    /// Whether any TLS file was given.
    pub fn enabled(&self) -> bool {
        self.cert.is_some() || self.key.is_some() || self.ca.is_some()
    }

    fn identity(&self) -> Result<Option<Identity>, TlsError> {
        match (&self.cert, &self.key) {
            (Some(c), Some(k)) => {
                let cert = certificates("the certificate", c)?;
                let key = read("the private key", k)?;
                check_pair(c, &cert, k, &key)?;
                Ok(Some(Identity::from_pem(cert, key)))
            }
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
            config = config.client_ca_root(Certificate::from_pem(certificates(
                "the CA certificate",
                ca,
            )?));
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
        let mut config = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(
            certificates("the CA certificate", ca)?,
        ));
        if let Some(identity) = self.identity()? {
            config = config.identity(identity);
        }
        Ok(Some(config))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rcgen::{CertificateParams, KeyPair};

    struct Dir(PathBuf);
    impl Drop for Dir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn dir(name: &str) -> Dir {
        let d = std::env::temp_dir().join(format!("dray-tls-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir(&d).unwrap();
        Dir(d)
    }

    /// A self-signed certificate and its key, as PEM.
    fn pair() -> (String, String) {
        let key = KeyPair::generate().unwrap();
        let cert = CertificateParams::new(vec!["127.0.0.1".into()])
            .unwrap()
            .self_signed(&key)
            .unwrap();
        (cert.pem(), key.serialize_pem())
    }

    fn files(d: &Path, cert: &str, key: &str) -> TlsFiles {
        std::fs::write(d.join("c.pem"), cert).unwrap();
        std::fs::write(d.join("k.pem"), key).unwrap();
        TlsFiles {
            cert: Some(d.join("c.pem")),
            key: Some(d.join("k.pem")),
            ca: None,
        }
    }

    #[test]
    fn a_matching_pair_serves() {
        let d = dir("ok");
        let (cert, key) = pair();
        assert!(files(&d.0, &cert, &key).server().unwrap().is_some());
    }

    #[test]
    fn a_key_of_another_certificate_is_refused_naming_both_files() {
        let d = dir("mismatch");
        let (cert, _) = pair();
        let (_, other_key) = pair();
        let e = files(&d.0, &cert, &other_key).server().unwrap_err();
        let text = e.to_string();
        assert!(matches!(e, TlsError::Mismatch { .. }), "{text}");
        assert!(text.contains("k.pem") && text.contains("c.pem"), "{text}");
    }

    #[test]
    fn files_that_are_not_pem_are_refused_naming_the_file() {
        let d = dir("garbage");
        let (cert, key) = pair();
        // Certificate and key swapped, a text file, an empty file, a truncated block.
        let truncated = &cert[..cert.len() / 2];
        let cases = [
            (key.as_str(), cert.as_str(), "c.pem"),
            ("hello\n", key.as_str(), "c.pem"),
            ("", key.as_str(), "c.pem"),
            (cert.as_str(), "", "k.pem"),
            (cert.as_str(), "hello\n", "k.pem"),
            (truncated, key.as_str(), "c.pem"),
        ];
        for (c, k, named) in cases {
            let e = files(&d.0, c, k).server().unwrap_err().to_string();
            assert!(e.contains(named), "{named}: {e}");
        }
    }

    #[test]
    fn a_ca_file_without_certificates_is_refused() {
        let d = dir("ca");
        let (cert, key) = pair();
        let mut f = files(&d.0, &cert, &key);
        std::fs::write(d.0.join("ca.pem"), "not a certificate").unwrap();
        f.ca = Some(d.0.join("ca.pem"));
        let e = f.server().unwrap_err().to_string();
        assert!(
            e.contains("ca.pem") && e.contains("the CA certificate"),
            "{e}"
        );
        let e = f.client().unwrap_err().to_string();
        assert!(e.contains("ca.pem"), "{e}");
    }
}
