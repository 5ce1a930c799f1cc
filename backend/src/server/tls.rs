//! Optional TLS for `spintune serve` (`--tls-cert`, `--tls-key`): rustls
//! with the *ring* crypto provider, TLS 1.2 and 1.3, HTTP/1.1 only.
//!
//! The certificate file is a PEM chain (leaf first); the key file a PEM
//! private key (PKCS#8, PKCS#1 or SEC1). Both are read once at start; a
//! missing, unreadable or malformed file, or a key that does not match the
//! certificate, is an error naming the flag. Files are bounded
//! ([`MAX_PEM_BYTES`]) so a wrong path (a disk image, `/dev/zero`) cannot
//! make the process allocate without bound.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

pub use tokio_rustls::TlsAcceptor;

/// Largest certificate or key file read, bytes.
pub const MAX_PEM_BYTES: u64 = 1024 * 1024;

/// `serve` flags of TLS.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TlsArgs {
    /// Serve HTTPS/WSS with this certificate chain (PEM, leaf first); needs --tls-key.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// Private key of --tls-cert (PEM: PKCS#8, PKCS#1 or SEC1).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
}

impl TlsArgs {
    /// The acceptor, or `None` without TLS flags. Errors name the flag and
    /// the file.
    pub fn acceptor(&self) -> Result<Option<TlsAcceptor>, String> {
        let (cert, key) = match (&self.tls_cert, &self.tls_key) {
            (None, None) => return Ok(None),
            (Some(c), Some(k)) => (c, k),
            (Some(_), None) => return Err("--tls-cert needs --tls-key".into()),
            (None, Some(_)) => return Err("--tls-key needs --tls-cert".into()),
        };
        acceptor(cert, key).map(Some)
    }
}

fn read_bounded(flag: &str, path: &Path) -> Result<Vec<u8>, String> {
    let meta = std::fs::metadata(path).map_err(|e| format!("{flag} {}: {e}", path.display()))?;
    if !meta.is_file() || meta.len() > MAX_PEM_BYTES {
        return Err(format!(
            "{flag} {}: not a PEM file of at most {MAX_PEM_BYTES} bytes",
            path.display()
        ));
    }
    std::fs::read(path).map_err(|e| format!("{flag} {}: {e}", path.display()))
}

/// A TLS acceptor from a PEM certificate chain and private key.
pub fn acceptor(cert_path: &Path, key_path: &Path) -> Result<TlsAcceptor, String> {
    let cert_pem = read_bounded("--tls-cert", cert_path)?;
    let key_pem = read_bounded("--tls-key", key_path)?;
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<_, _>>()
        .map_err(|e| format!("--tls-cert {}: {e}", cert_path.display()))?;
    if certs.is_empty() {
        return Err(format!(
            "--tls-cert {}: no certificate (expected a PEM `BEGIN CERTIFICATE` block)",
            cert_path.display()
        ));
    }
    let key = PrivateKeyDer::from_pem_slice(&key_pem)
        .map_err(|e| format!("--tls-key {}: no private key ({e})", key_path.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| format!("TLS: {e}"))?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| {
            format!(
                "--tls-key {} does not fit --tls-cert {}: {e}",
                key_path.display(),
                cert_path.display()
            )
        })?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}
