//! Helpers shared by the integration tests: a real server on an ephemeral
//! loopback port (in this process, [`server`]; or the binary as a process,
//! [`serve`]), a raw HTTP/1.1 client ([`raw_http`]), and WebSocket helpers.
//! Everything is bounded in time.
#![allow(dead_code)]

pub mod bridge_client;
pub mod raw_http;
pub mod serve;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use serde_json::Value;
use spintune::protocol::{IterationRecord, RunStatus, RunSummary, ServerMessage, PROTOCOL_VERSION};
use spintune_server::cli::{start_server, DemoMode, ServeArgs, Server};
use tokio_tungstenite::tungstenite::Message;

#[allow(unused_imports)]
pub use raw_http::{raw_request, read_until_closed};
#[allow(unused_imports)]
pub use serve::{spawn_server, spintune, Proc, Serve, Served};

pub const TOKEN: &str = "test-token";
pub const STEP: Duration = Duration::from_secs(20);

pub type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A fresh temporary directory (removed on drop).
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        use std::sync::atomic::{AtomicU32, Ordering};
        static N: AtomicU32 = AtomicU32::new(0);
        let p = std::env::temp_dir().join(format!(
            "spintune-test-{tag}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Self(p)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub async fn server(dir: &TempDir, viewer_buffer: usize) -> Server {
    start_server(&ServeArgs {
        bind: "127.0.0.1:0".parse().unwrap(),
        db: dir.0.join("test.db"),
        dist: dir.0.join("dist"),
        token: Some(TOKEN.into()),
        iteration_delay_ms: 0,
        viewer_buffer,
        demo: DemoMode::Never,
        demo_config: None,
        alert_webhook: None,
        limits: Default::default(),
        security: Default::default(),
    })
    .await
    .unwrap_or_else(|e| panic!("server: {}", e.message))
}

/// Minimal HTTP/1.1 request (`Content-Type: application/json`); returns (status, body).
pub async fn http(
    addr: SocketAddr,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: Option<&str>,
) -> (u16, String) {
    http_typed(addr, method, path, token, Some("application/json"), body).await
}

/// [`http`] with the given `Content-Type` header (`None`: no such header).
pub async fn http_typed(
    addr: SocketAddr,
    method: &str,
    path: &str,
    token: Option<&str>,
    content_type: Option<&str>,
    body: Option<&str>,
) -> (u16, String) {
    let auth = token
        .map(|t| format!("\r\nAuthorization: Bearer {t}"))
        .unwrap_or_default();
    let ctype = content_type
        .map(|t| format!("\r\nContent-Type: {t}"))
        .unwrap_or_default();
    let head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}{auth}{ctype}");
    raw_request(addr, None, &head, body.unwrap_or("")).await
}

pub async fn create_run(addr: SocketAddr, config: &Value) -> RunSummary {
    let (status, body) = http(
        addr,
        "POST",
        "/api/runs",
        Some(TOKEN),
        Some(&config.to_string()),
    )
    .await;
    assert_eq!(status, 201, "{body}");
    serde_json::from_str(&body).unwrap()
}

pub async fn get_run(addr: SocketAddr, id: u64) -> RunSummary {
    let (status, body) = http(addr, "GET", &format!("/api/runs/{id}"), None, None).await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

pub async fn control(addr: SocketAddr, id: u64, cmd: &str) -> (u16, String) {
    http(
        addr,
        "POST",
        &format!("/api/runs/{id}/control"),
        Some(TOKEN),
        Some(cmd),
    )
    .await
}

pub async fn records(addr: SocketAddr, id: u64) -> Vec<Value> {
    let (status, body) = http(
        addr,
        "GET",
        &format!("/api/runs/{id}/iterations"),
        None,
        None,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Poll until the run's status satisfies `f`.
pub async fn wait_status(addr: SocketAddr, id: u64, f: impl Fn(&RunSummary) -> bool) -> RunSummary {
    tokio::time::timeout(STEP, async {
        loop {
            let r = get_run(addr, id).await;
            if f(&r) {
                return r;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
    .expect("run did not reach the expected state in time")
}

pub fn is_finished(r: &RunSummary) -> bool {
    r.status == RunStatus::Finished
}

/// A small run config: paper default, `n` iterations, given pacing.
pub fn small_config(name: &str, n: u64, delay_ms: u64) -> Value {
    serde_json::json!({
        "name": name,
        "seed": 7,
        "iteration_delay_ms": delay_ms,
        "tuner": { "max_iterations": n }
    })
}

pub async fn connect(addr: SocketAddr, id: u64, from: Option<u64>) -> Ws {
    let q = from.map(|f| format!("&from={f}")).unwrap_or_default();
    let url = format!("ws://{addr}/api/runs/{id}/ws?protocol={PROTOCOL_VERSION}{q}");
    let (ws, _) = tokio::time::timeout(STEP, tokio_tungstenite::connect_async(url))
        .await
        .expect("connect timed out")
        .expect("connect");
    ws
}

pub async fn next_msg(ws: &mut Ws) -> ServerMessage {
    loop {
        let m = tokio::time::timeout(STEP, ws.next())
            .await
            .expect("no message in time")
            .expect("socket closed")
            .expect("socket error");
        match m {
            Message::Text(t) => {
                return serde_json::from_str(t.as_str())
                    .unwrap_or_else(|e| panic!("bad server frame {t}: {e}"))
            }
            Message::Ping(_) | Message::Pong(_) => continue,
            other => panic!("unexpected frame {other:?}"),
        }
    }
}

pub async fn send(ws: &mut Ws, text: &str) {
    ws.send(Message::Text(text.into())).await.unwrap();
}

/// Collect iteration records (history + live) until `n` records are in.
pub async fn collect(ws: &mut Ws, n: usize) -> Vec<IterationRecord> {
    let mut out = Vec::new();
    while out.len() < n {
        match next_msg(ws).await {
            ServerMessage::History { records, .. } => out.extend(records),
            ServerMessage::Iteration { record } => out.push(record),
            _ => {}
        }
    }
    out
}

/// `spintune serve` arguments as the command line would give them (every
/// flag not named here at its default): loopback, ephemeral port, a fresh
/// store in `dir`, no demo, no pacing, the given viewer buffer.
pub fn serve_args(dir: &TempDir, viewer_buffer: usize) -> ServeArgs {
    #[derive(clap::Parser)]
    struct Cmd {
        #[command(flatten)]
        serve: ServeArgs,
    }
    let db = dir.0.join("test.db");
    let dist = dir.0.join("dist");
    let buffer = viewer_buffer.to_string();
    <Cmd as clap::Parser>::parse_from([
        "serve".as_ref(),
        "--bind".as_ref(),
        "127.0.0.1:0".as_ref(),
        "--db".as_ref(),
        db.as_os_str(),
        "--dist".as_ref(),
        dist.as_os_str(),
        "--token".as_ref(),
        TOKEN.as_ref(),
        "--iteration-delay-ms".as_ref(),
        "0".as_ref(),
        "--viewer-buffer".as_ref(),
        buffer.as_ref(),
        "--demo".as_ref(),
        "never".as_ref(),
    ] as [&std::ffi::OsStr; 15])
    .serve
}

/// Every node of a JSON document as (path as config errors write it, e.g.
/// `tuner.levels[0].name`; JSON pointer; the value), children before their
/// parent, the document itself last (path and pointer empty).
pub fn json_nodes(v: &Value) -> Vec<(String, String, &Value)> {
    fn walk<'a>(
        v: &'a Value,
        path: String,
        pointer: String,
        out: &mut Vec<(String, String, &'a Value)>,
    ) {
        match v {
            Value::Object(m) => {
                for (k, x) in m {
                    let p = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    walk(x, p, format!("{pointer}/{k}"), out);
                }
            }
            Value::Array(a) => {
                for (i, x) in a.iter().enumerate() {
                    walk(x, format!("{path}[{i}]"), format!("{pointer}/{i}"), out);
                }
            }
            _ => {}
        }
        out.push((path, pointer, v));
    }
    let mut out = Vec::new();
    walk(v, String::new(), String::new(), &mut out);
    out
}
