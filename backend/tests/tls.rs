//! Optional TLS (`spintune serve --tls-cert FILE --tls-key FILE`), against
//! the real binary: HTTPS and WSS work with a client that trusts the
//! certificate (a fresh self-signed one per test, made by rcgen), a
//! plain-HTTP request to the TLS port gets no HTTP answer, and bad
//! certificate flags fail at start with an error naming the flag.

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use common::raw_http::exchange;
use common::{Serve, Served, TempDir};
use futures_util::StreamExt;
use spintune::protocol::{ServerMessage, PROTOCOL_VERSION};
use tokio::net::TcpStream;
use tokio_rustls::rustls;
use tokio_tungstenite::tungstenite::Message;

/// A self-signed certificate for `localhost` and its key, as PEM files in `dir`.
fn write_cert(dir: &TempDir) -> (PathBuf, PathBuf, rcgen::CertifiedKey) {
    let ck = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    let cert = dir.0.join("cert.pem");
    let key = dir.0.join("key.pem");
    std::fs::write(&cert, ck.cert.pem()).unwrap();
    std::fs::write(&key, ck.key_pair.serialize_pem()).unwrap();
    (cert, key, ck)
}

/// `serve` with a demo run (paced, so it is live while the test runs) and
/// the given TLS flags.
fn serve_cmd(dir: &TempDir, tls: &[&std::ffi::OsStr]) -> Serve {
    Serve::new(&dir.0.join("tls.db"))
        .demo("always")
        .args(["--iteration-delay-ms", "50"])
        .args(tls)
}

/// Start `serve` over TLS (it prints `Dashboard: https://…`).
fn spawn_tls(dir: &TempDir, cert: &Path, key: &Path) -> Served {
    serve_cmd(
        dir,
        &[
            "--tls-cert".as_ref(),
            cert.as_os_str(),
            "--tls-key".as_ref(),
            key.as_os_str(),
        ],
    )
    .https()
    .spawn()
}

/// A TLS connection to `addr` as `localhost`, trusting only `ck`'s certificate.
async fn tls_connect(
    addr: SocketAddr,
    ck: &rcgen::CertifiedKey,
) -> tokio_rustls::client::TlsStream<TcpStream> {
    let mut roots = rustls::RootCertStore::empty();
    roots.add(ck.cert.der().clone()).unwrap();
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots)
    .with_no_client_auth();
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    let tcp = TcpStream::connect(addr).await.unwrap();
    let name = rustls::pki_types::ServerName::try_from("localhost").unwrap();
    tokio::time::timeout(Duration::from_secs(10), connector.connect(name, tcp))
        .await
        .expect("TLS handshake timed out")
        .expect("TLS handshake")
}

/// `GET path` over HTTPS with `Host: host` (trusting only `ck`); the whole answer.
async fn https_get(addr: SocketAddr, ck: &rcgen::CertifiedKey, path: &str, host: &str) -> Vec<u8> {
    let mut s = tls_connect(addr, ck).await;
    let req = format!("GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
    exchange(&mut s, req.as_bytes(), Duration::from_secs(10))
        .await
        .expect("HTTPS answer timed out")
}

#[tokio::test]
async fn https_and_wss_are_served_with_the_given_certificate() {
    let dir = TempDir::new("tls");
    let (cert, key, ck) = write_cert(&dir);
    let served = spawn_tls(&dir, &cert, &key);
    let addr = served.addr;

    // HTTPS: GET /api/version.
    let body = https_get(
        addr,
        &ck,
        "/api/version",
        &format!("localhost:{}", addr.port()),
    )
    .await;
    let text = String::from_utf8_lossy(&body);
    assert!(text.starts_with("HTTP/1.1 200"), "answer: {text}");
    assert!(
        text.contains(&format!("\"protocol_version\":{PROTOCOL_VERSION}")),
        "answer: {text}"
    );

    // WSS: the demo run's socket says Hello over TLS, as a browser on an
    // https:// page would see it (Origin = the served origin).
    let s = tls_connect(addr, &ck).await;
    let url = format!(
        "wss://localhost:{}/api/runs/1/ws?protocol={PROTOCOL_VERSION}",
        addr.port()
    );
    let mut req = tokio_tungstenite::tungstenite::client::IntoClientRequest::into_client_request(
        url.as_str(),
    )
    .unwrap();
    req.headers_mut().insert(
        "Origin",
        format!("https://localhost:{}", addr.port())
            .parse()
            .unwrap(),
    );
    let (mut ws, _) = tokio::time::timeout(
        Duration::from_secs(10),
        tokio_tungstenite::client_async(req, s),
    )
    .await
    .expect("WSS upgrade timed out")
    .expect("WSS upgrade");
    let first = tokio::time::timeout(Duration::from_secs(10), ws.next())
        .await
        .expect("no frame over WSS")
        .expect("socket closed")
        .expect("socket error");
    let Message::Text(t) = first else {
        panic!("expected a text frame, got {first:?}")
    };
    let hello: ServerMessage = serde_json::from_str(t.as_str()).unwrap();
    assert!(
        matches!(hello, ServerMessage::Hello { version, ref run } if version == PROTOCOL_VERSION && run.id == 1),
        "first frame: {hello:?}"
    );
}

#[tokio::test]
async fn plain_http_to_the_tls_port_gets_no_http_answer_and_tls_still_works() {
    let dir = TempDir::new("tls-plain");
    let (cert, key, ck) = write_cert(&dir);
    let served = spawn_tls(&dir, &cert, &key);
    let addr = served.addr;
    let mut tcp = TcpStream::connect(addr).await.unwrap();
    // The server ends the connection after the failed handshake (a TLS
    // alert at most): never an HTTP response, never a run list.
    let answer = exchange(
        &mut tcp,
        b"GET /api/runs HTTP/1.1\r\nHost: localhost\r\n\r\n",
        Duration::from_secs(15),
    )
    .await
    .expect("the server kept a plain-HTTP connection open");
    assert!(
        !answer.starts_with(b"HTTP/"),
        "plain HTTP was answered: {}",
        String::from_utf8_lossy(&answer)
    );
    // The listener is unharmed.
    let body = https_get(addr, &ck, "/api/runs", "localhost").await;
    assert!(body.starts_with(b"HTTP/1.1 200"));
}

/// `serve` with these TLS flags exits 2 at once; returns its stderr.
fn refused(dir: &TempDir, tls: &[&std::ffi::OsStr]) -> String {
    let out = serve_cmd(dir, tls).exit();
    assert_eq!(out.status.code(), Some(2), "flags {tls:?} were accepted");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn bad_tls_flags_fail_at_start_naming_the_flag() {
    let dir = TempDir::new("tls-bad");
    let (cert, key, _) = write_cert(&dir);
    // One flag without the other.
    let err = refused(&dir, &["--tls-cert".as_ref(), cert.as_os_str()]);
    assert!(err.contains("--tls-key"), "{err}");
    // A missing file.
    let missing = dir.0.join("missing.pem");
    let err = refused(
        &dir,
        &[
            "--tls-cert".as_ref(),
            missing.as_os_str(),
            "--tls-key".as_ref(),
            key.as_os_str(),
        ],
    );
    assert!(
        err.contains("--tls-cert") && err.contains("missing.pem"),
        "{err}"
    );
    // A file without a certificate.
    let err = refused(
        &dir,
        &[
            "--tls-cert".as_ref(),
            key.as_os_str(),
            "--tls-key".as_ref(),
            key.as_os_str(),
        ],
    );
    assert!(
        err.contains("--tls-cert") && err.contains("no certificate"),
        "{err}"
    );
    // A key of another certificate.
    let other = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    let other_key = dir.0.join("other-key.pem");
    std::fs::write(&other_key, other.key_pair.serialize_pem()).unwrap();
    let err = refused(
        &dir,
        &[
            "--tls-cert".as_ref(),
            cert.as_os_str(),
            "--tls-key".as_ref(),
            other_key.as_os_str(),
        ],
    );
    assert!(err.contains("does not fit"), "{err}");
}
