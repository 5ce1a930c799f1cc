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

/// Why TLS could not be set up; every message names the flag and the file.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// `--tls-cert` without `--tls-key`.
    #[error("--tls-cert needs --tls-key")]
    MissingKey,
    /// `--tls-key` without `--tls-cert`.
    #[error("--tls-key needs --tls-cert")]
    MissingCert,
    /// The file could not be read.
    #[error("{flag} {}: {error}", path.display())]
    Unreadable {
        flag: &'static str,
        path: PathBuf,
        error: std::io::Error,
    },
    /// Not a regular file, or larger than [`MAX_PEM_BYTES`].
    #[error("{flag} {}: not a PEM file of at most {MAX_PEM_BYTES} bytes", path.display())]
    NotPem { flag: &'static str, path: PathBuf },
    /// A malformed PEM certificate block.
    #[error("--tls-cert {}: {error}", path.display())]
    BadCertificate {
        path: PathBuf,
        error: rustls::pki_types::pem::Error,
    },
    /// The certificate file holds no certificate.
    #[error("--tls-cert {}: no certificate (expected a PEM `BEGIN CERTIFICATE` block)", path.display())]
    NoCertificate { path: PathBuf },
    /// The key file holds no usable private key.
    #[error("--tls-key {}: no private key ({error})", path.display())]
    NoKey {
        path: PathBuf,
        error: rustls::pki_types::pem::Error,
    },
    /// rustls refused the protocol versions (a build without TLS 1.2/1.3).
    #[error("TLS: {0}")]
    Config(rustls::Error),
    /// The key is not the certificate's.
    #[error("--tls-key {} does not fit --tls-cert {}: {error}", key.display(), cert.display())]
    KeyMismatch {
        key: PathBuf,
        cert: PathBuf,
        error: rustls::Error,
    },
}

impl TlsArgs {
    /// The acceptor, or `None` without TLS flags. Errors name the flag and
    /// the file.
    pub fn acceptor(&self) -> Result<Option<TlsAcceptor>, TlsError> {
        let (cert, key) = match (&self.tls_cert, &self.tls_key) {
            (None, None) => return Ok(None),
            (Some(c), Some(k)) => (c, k),
            (Some(_), None) => return Err(TlsError::MissingKey),
            (None, Some(_)) => return Err(TlsError::MissingCert),
        };
        acceptor(cert, key).map(Some)
    }
}

fn read_bounded(flag: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    let unreadable = |error| TlsError::Unreadable {
        flag,
        path: path.to_path_buf(),
        error,
    };
    let meta = std::fs::metadata(path).map_err(unreadable)?;
    if !meta.is_file() || meta.len() > MAX_PEM_BYTES {
        return Err(TlsError::NotPem {
            flag,
            path: path.to_path_buf(),
        });
    }
    std::fs::read(path).map_err(unreadable)
}

/// A TLS acceptor from a PEM certificate chain and private key.
pub fn acceptor(cert_path: &Path, key_path: &Path) -> Result<TlsAcceptor, TlsError> {
    let cert_pem = read_bounded("--tls-cert", cert_path)?;
    let key_pem = read_bounded("--tls-key", key_path)?;
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<_, _>>()
        .map_err(|error| TlsError::BadCertificate {
            path: cert_path.to_path_buf(),
            error,
        })?;
    if certs.is_empty() {
        return Err(TlsError::NoCertificate {
            path: cert_path.to_path_buf(),
        });
    }
    let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|error| TlsError::NoKey {
        path: key_path.to_path_buf(),
        error,
    })?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(TlsError::Config)?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|error| TlsError::KeyMismatch {
            key: key_path.to_path_buf(),
            cert: cert_path.to_path_buf(),
            error,
        })?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}
