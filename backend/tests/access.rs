//! Who may talk to the server, against the real binary: Origin checks on
//! WebSocket upgrades and state-changing requests, Host checks (DNS
//! rebinding), where the token comes from, failed-auth throttling, and the
//! redacted `/config`.

mod common;

use std::net::{IpAddr, SocketAddr};

use common::*;
use serde_json::{json, Value};
use spintune::protocol::{ServerMessage, PROTOCOL_VERSION};
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

/// `spintune serve` with `args` and the token from the environment (no `--token`).
fn spawn_with_env_token(db: &std::path::Path, args: &[&str]) -> Served {
    Serve::new(db)
        .without_token_flag()
        .env("SPINTUNE_TOKEN", TOKEN)
        .args(args)
        .spawn()
}

/// One raw request with a JSON body ([`raw_request`]), from `from` if given.
async fn raw(addr: SocketAddr, from: Option<IpAddr>, head: &str, body: &str) -> (u16, String) {
    raw_request(
        addr,
        from,
        &format!("{head}\r\nContent-Type: application/json"),
        body,
    )
    .await
}

/// A WebSocket upgrade to the viewer socket with `Origin: origin` (if any):
/// the socket, or the refusal's status and body.
async fn ws_with_origin(
    addr: SocketAddr,
    id: u64,
    origin: Option<&str>,
) -> Result<Ws, (u16, String)> {
    let url = format!("ws://{addr}/api/runs/{id}/ws?protocol={PROTOCOL_VERSION}");
    let mut req = url.into_client_request().unwrap();
    if let Some(o) = origin {
        req.headers_mut().insert("Origin", o.parse().unwrap());
    }
    match tokio::time::timeout(STEP, tokio_tungstenite::connect_async(req))
        .await
        .expect("connect timed out")
    {
        Ok((ws, _)) => Ok(ws),
        Err(tokio_tungstenite::tungstenite::Error::Http(resp)) => Err((
            resp.status().as_u16(),
            String::from_utf8_lossy(resp.body().as_deref().unwrap_or_default()).to_string(),
        )),
        Err(e) => panic!("unexpected WebSocket error {e}"),
    }
}

async fn paused_run(addr: SocketAddr) -> u64 {
    let run = create_run(addr, &small_config("access", 1_000, 50)).await;
    let (s, b) = control(addr, run.id, r#"{"action":"pause"}"#).await;
    assert_eq!(s, 200, "{b}");
    run.id
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn websocket_from_a_foreign_origin_is_refused_same_origin_and_scripts_accepted() {
    let dir = TempDir::new("origin-ws");
    let served = spawn_with_env_token(&dir.0.join("s.db"), &[]);
    let addr = served.addr;
    let id = paused_run(addr).await;

    let (status, body) = ws_with_origin(addr, id, Some("https://evil.example"))
        .await
        .expect_err("a foreign origin's WebSocket was accepted");
    assert_eq!(status, 403, "{body}");
    assert!(
        body.contains("--allow-origin https://evil.example"),
        "{body}"
    );

    for origin in [Some(format!("http://{addr}")), None] {
        let mut ws = ws_with_origin(addr, id, origin.as_deref())
            .await
            .unwrap_or_else(|e| panic!("origin {origin:?} refused: {e:?}"));
        assert!(matches!(
            next_msg(&mut ws).await,
            ServerMessage::Hello { .. }
        ));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foreign_origin_cannot_change_state_even_with_the_token() {
    let dir = TempDir::new("origin-post");
    let served = spawn_with_env_token(&dir.0.join("s.db"), &[]);
    let addr = served.addr;
    let id = paused_run(addr).await;
    let head = format!(
        "POST /api/runs/{id}/control HTTP/1.1\r\nHost: {addr}\r\nOrigin: https://evil.example\r\nAuthorization: Bearer {TOKEN}"
    );
    let (status, body) = raw(addr, None, &head, r#"{"action":"stop"}"#).await;
    assert_eq!(status, 403, "{body}");
    assert!(body.contains("--allow-origin"), "{body}");
    assert_eq!(get_run(addr, id).await.status.name(), "paused");
    // Viewing stays open to anyone (GET is not a state change).
    let head =
        format!("GET /api/runs/{id} HTTP/1.1\r\nHost: {addr}\r\nOrigin: https://evil.example");
    assert_eq!(raw(addr, None, &head, "").await.0, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foreign_host_header_is_refused_naming_allow_host() {
    let dir = TempDir::new("host");
    let served = spawn_with_env_token(&dir.0.join("s.db"), &[]);
    let addr = served.addr;
    let (status, body) = raw(
        addr,
        None,
        "GET /api/runs HTTP/1.1\r\nHost: evil.example:8080",
        "",
    )
    .await;
    assert_eq!(status, 421, "{body}");
    assert!(body.contains("--allow-host evil.example"), "{body}");
    for host in [format!("localhost:{}", addr.port()), addr.to_string()] {
        let (status, body) = raw(
            addr,
            None,
            &format!("GET /api/runs HTTP/1.1\r\nHost: {host}"),
            "",
        )
        .await;
        assert_eq!(status, 200, "{host}: {body}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn allow_origin_and_allow_host_admit_the_named_page_and_name() {
    let dir = TempDir::new("allow");
    let served = spawn_with_env_token(
        &dir.0.join("s.db"),
        &[
            "--allow-origin",
            "https://dash.lab.example",
            "--allow-host",
            "spintune.lab.example",
        ],
    );
    let addr = served.addr;
    let id = paused_run(addr).await;
    let mut ws = ws_with_origin(addr, id, Some("https://dash.lab.example"))
        .await
        .expect("allowed origin refused");
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    // Same-origin through the allowed host name (as behind a reverse proxy).
    let head = format!(
        "POST /api/runs/{id}/control HTTP/1.1\r\nHost: spintune.lab.example\r\nOrigin: https://spintune.lab.example\r\nAuthorization: Bearer {TOKEN}"
    );
    let (status, body) = raw(addr, None, &head, r#"{"action":"pause"}"#).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(
        ws_with_origin(addr, id, Some("https://other.example"))
            .await
            .err()
            .map(|e| e.0),
        Some(403)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_from_the_environment_works_and_is_not_printed() {
    let dir = TempDir::new("tok-env");
    let secret = "env-secret-123";
    let served = Serve::new(&dir.0.join("s.db"))
        .without_token_flag()
        .env("SPINTUNE_TOKEN", secret)
        .spawn();
    let (addr, printed) = (served.addr, &served.printed);
    assert!(!printed.contains(secret), "{printed}");
    assert!(
        printed.contains("Control token: from SPINTUNE_TOKEN"),
        "{printed}"
    );
    let (s, b) = http(addr, "POST", "/api/runs", Some(secret), Some("{}")).await;
    assert_eq!(s, 201, "{b}");
    let (s, _) = http(addr, "POST", "/api/runs", Some(TOKEN), Some("{}")).await;
    assert_eq!(s, 403);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn token_from_a_file_is_trimmed_and_works() {
    let dir = TempDir::new("tok-file");
    let file = dir.0.join("token");
    std::fs::write(&file, "file-secret-456\n").unwrap();
    let served = Serve::new(&dir.0.join("s.db"))
        .without_token_flag()
        .args(["--token-file".as_ref(), file.as_os_str()])
        .spawn();
    let (addr, printed) = (served.addr, &served.printed);
    assert!(!printed.contains("file-secret-456"), "{printed}");
    let (s, b) = http(
        addr,
        "POST",
        "/api/runs",
        Some("file-secret-456"),
        Some("{}"),
    )
    .await;
    assert_eq!(s, 201, "{b}");
}

#[test]
fn an_empty_or_missing_token_file_stops_the_server_naming_the_path() {
    let dir = TempDir::new("tok-bad");
    let empty = dir.0.join("empty-token");
    std::fs::write(&empty, " \n").unwrap();
    let missing = dir.0.join("missing-token");
    for (path, what) in [(&empty, "empty"), (&missing, "cannot read")] {
        let out = Serve::new(&dir.0.join("s.db"))
            .without_token_flag()
            .args(["--token-file".as_ref(), path.as_os_str()])
            .exit();
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(&path.display().to_string()) && err.contains(what),
            "{err}"
        );
    }
}

#[tokio::test]
async fn the_token_flag_still_works_but_warns_that_ps_shows_it() {
    let dir = TempDir::new("tok-flag");
    let mut served = Serve::new(&dir.0.join("s.db")).spawn();
    let line = served.stderr_line("warning", STEP).await;
    assert!(
        line.contains("ps") && line.contains("SPINTUNE_TOKEN") && line.contains("--token-file"),
        "{line}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_tokens_are_throttled_per_address_on_rest_and_sockets() {
    let dir = TempDir::new("throttle");
    let served = spawn_with_env_token(&dir.0.join("s.db"), &[]);
    let addr = served.addr;
    let id = paused_run(addr).await;
    let head = |token: &str| {
        format!(
            "POST /api/runs/{id}/control HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}"
        )
    };
    let attacker: IpAddr = "127.0.0.1".parse().unwrap();
    let mut counts = std::collections::BTreeMap::new();
    for _ in 0..60 {
        let (s, _) = raw(addr, Some(attacker), &head("guess"), r#"{"action":"stop"}"#).await;
        *counts.entry(s).or_insert(0) += 1;
    }
    // The free failures answer 403; the block that follows answers 429 to all the rest.
    // (10 free failures, the 11th starts a 5 s block: far longer than these requests take.)
    assert_eq!(counts.get(&403), Some(&11), "{counts:?}");
    assert_eq!(counts.get(&429), Some(&49), "{counts:?}");
    // While blocked, even the right token is not compared.
    let (s, body) = raw(addr, Some(attacker), &head(TOKEN), r#"{"action":"pause"}"#).await;
    assert_eq!(s, 429, "{body}");
    assert!(body.contains("too many wrong tokens"), "{body}");
    // The same throttle answers the viewer socket's Auth from that address.
    let mut ws = connect(addr, id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    send(&mut ws, &json!({"type":"auth","token":TOKEN}).to_string()).await;
    loop {
        match next_msg(&mut ws).await {
            ServerMessage::Error { message } => {
                assert!(message.contains("too many wrong tokens"), "{message}");
                break;
            }
            ServerMessage::AuthOk => panic!("a throttled address was authenticated"),
            _ => {}
        }
    }
    // … and the bridge socket's.
    let url = format!("ws://{addr}/api/runs/{id}/bridge?protocol={PROTOCOL_VERSION}");
    let (mut bridge, _) = tokio::time::timeout(STEP, tokio_tungstenite::connect_async(url))
        .await
        .expect("connect timed out")
        .expect("bridge connect");
    send(
        &mut bridge,
        &json!({"type":"auth","token":TOKEN}).to_string(),
    )
    .await;
    let refusal = loop {
        let m = tokio::time::timeout(STEP, futures_util::StreamExt::next(&mut bridge))
            .await
            .expect("no bridge frame in time")
            .expect("bridge socket closed")
            .expect("bridge socket error");
        if let tokio_tungstenite::tungstenite::Message::Text(t) = m {
            let v: Value = serde_json::from_str(t.as_str()).unwrap();
            assert_ne!(
                v["type"], "auth_ok",
                "a throttled address was authenticated"
            );
            if v["type"] == "error" {
                break v["message"].as_str().unwrap().to_string();
            }
        }
    };
    assert!(refusal.contains("too many wrong tokens"), "{refusal}");
    // Another address is not affected.
    let other: IpAddr = "127.0.0.2".parse().unwrap();
    let (s, body) = raw(addr, Some(other), &head(TOKEN), r#"{"action":"pause"}"#).await;
    assert_eq!(s, 200, "{body}");
    assert_eq!(get_run(addr, id).await.status.name(), "paused");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn config_without_the_token_hides_the_instrument_address_and_channels() {
    let dir = TempDir::new("redact");
    let srv = server(&dir, 16).await;
    let config = json!({
        "name": "redact",
        "driver": "scpi",
        "scpi": {
            "address": "192.0.2.40:5025",
            "channels": spintune::sim::default_gates().iter().enumerate()
                .map(|(i, g)| (g.name.clone(), i + 1)).collect::<std::collections::BTreeMap<_, _>>(),
            "timeout_ms": 100,
            "measure": "simulator"
        },
        "tuner": { "max_iterations": 1 }
    });
    let run = create_run(srv.addr, &config).await;
    let path = format!("/api/runs/{}/config", run.id);
    let (s, open) = http(srv.addr, "GET", &path, None, None).await;
    assert_eq!(s, 200, "{open}");
    assert!(!open.contains("192.0.2.40"), "{open}");
    let v: Value = serde_json::from_str(&open).unwrap();
    assert_eq!(v["backend"]["scpi"]["address"], "<redacted>");
    assert_eq!(v["backend"]["scpi"]["channels"], "<redacted>");
    assert_eq!(
        v["backend"]["scpi"]["timeout_ms"], 100,
        "non-secret fields stay"
    );
    let (s, full) = http(srv.addr, "GET", &path, Some(TOKEN), None).await;
    assert_eq!(s, 200, "{full}");
    let v: Value = serde_json::from_str(&full).unwrap();
    assert_eq!(v["backend"]["scpi"]["address"], "192.0.2.40:5025");
    assert_eq!(v["backend"]["scpi"]["channels"]["N"], 1);
    let (s, _) = http(srv.addr, "GET", &path, Some("wrong"), None).await;
    assert_eq!(s, 403);
}

#[test]
fn both_token_sources_at_once_are_refused_with_a_clear_message() {
    let dir = TempDir::new("tok-both");
    let file = dir.0.join("token");
    std::fs::write(&file, "from-file").unwrap();
    let out = Serve::new(&dir.0.join("s.db"))
        .without_token_flag()
        .env("SPINTUNE_TOKEN", "from-env")
        .args(["--token-file".as_ref(), file.as_os_str()])
        .exit();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("SPINTUNE_TOKEN") && err.contains("--token-file") && err.contains("not both"),
        "{err}"
    );
}
