//! Bad input from the network (issue 20, item 8): a JSON body or frame is
//! exactly one value (trailing bytes are refused, never half-applied); JSON
//! bodies need a JSON Content-Type (415); a body that never completes is
//! answered 408 within `BODY_READ_TIMEOUT`; documented bounds are refused,
//! not clamped; symbolic links in `--dist` are not served; oversize
//! WebSocket messages close with 1009; a bridge answer nobody waits for
//! gets an `error` frame.

mod common;

use std::time::{Duration, Instant};

use common::bridge_client::next_bridge;
use common::*;
use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Value};
use spintune::protocol::{BridgeServerMessage, RunStatus, ServerMessage};
use spintune::session::SessionConfig;
use tokio_tungstenite::tungstenite::Message;

async fn run_count(addr: std::net::SocketAddr) -> usize {
    let (s, body) = http(addr, "GET", "/api/runs", None, None).await;
    assert_eq!(s, 200, "{body}");
    serde_json::from_str::<Vec<Value>>(&body).unwrap().len()
}

/// A run that keeps running for the length of a test (paced, many iterations).
fn long_config(name: &str) -> Value {
    small_config(name, 100_000, 50)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rest_bodies_are_one_json_value() {
    let dir = TempDir::new("strict-rest");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &long_config("strict")).await;
    let path = format!("/api/runs/{}/control", run.id);
    // Two commands in one body: neither is applied (the run is not paused).
    for body in [
        r#"{"action":"pause"}{"action":"stop"}"#,
        r#"{"action":"pause"} garbage"#,
        r#"{"action":"pause"},"#,
    ] {
        let (s, text) = http(srv.addr, "POST", &path, Some(TOKEN), Some(body)).await;
        assert_eq!(s, 400, "{body} → {text}");
        assert!(text.contains("trailing characters"), "{body} → {text}");
    }
    assert_eq!(get_run(srv.addr, run.id).await.status, RunStatus::Running);
    // Whitespace after the value is fine.
    let (s, text) = http(
        srv.addr,
        "POST",
        &path,
        Some(TOKEN),
        Some("{\"action\":\"pause\"} \r\n"),
    )
    .await;
    assert_eq!(s, 200, "{text}");
    // A run config followed by anything creates no run.
    let before = run_count(srv.addr).await;
    for body in [r#"{}{}"#, r#"{"seed":3} {"seed":4}"#, r#"{"seed":3}]"#] {
        let (s, text) = http(srv.addr, "POST", "/api/runs", Some(TOKEN), Some(body)).await;
        assert_eq!(s, 422, "{body} → {text}");
        assert!(text.contains("trailing characters"), "{body} → {text}");
    }
    assert_eq!(run_count(srv.addr).await, before);
    let (s, _) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_auth_frame_followed_by_garbage_is_refused() {
    let dir = TempDir::new("strict-viewer");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &long_config("viewer")).await;
    let mut ws = connect(srv.addr, run.id, None).await;
    send(
        &mut ws,
        &format!(r#"{{"type":"auth","token":"{TOKEN}"}}garbage"#),
    )
    .await;
    let error = next_error(&mut ws).await;
    assert!(error.contains("trailing characters"), "{error}");
    // Not authenticated: control is refused.
    send(
        &mut ws,
        r#"{"type":"control","command":{"action":"pause"}}"#,
    )
    .await;
    let error = next_error(&mut ws).await;
    assert!(error.contains("requires the token"), "{error}");
    // Two frames in one: nothing applied.
    send(&mut ws, &format!(r#"{{"type":"auth","token":"{TOKEN}"}}"#)).await;
    loop {
        match next_msg(&mut ws).await {
            ServerMessage::AuthOk => break,
            ServerMessage::Error { message } => panic!("auth refused: {message}"),
            _ => {}
        }
    }
    send(
        &mut ws,
        r#"{"type":"control","command":{"action":"pause"}}{"type":"control","command":{"action":"stop"}}"#,
    )
    .await;
    let error = next_error(&mut ws).await;
    assert!(error.contains("trailing characters"), "{error}");
    assert_eq!(get_run(srv.addr, run.id).await.status, RunStatus::Running);
    let (s, _) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
}

/// The next `Error` frame's message (iterations and statuses skipped).
async fn next_error(ws: &mut Ws) -> String {
    loop {
        match next_msg(ws).await {
            ServerMessage::Error { message } => return message,
            ServerMessage::AuthOk => panic!("unexpected auth_ok"),
            _ => {}
        }
    }
}

/// A bridge socket after the server's `hello` (the shared test client).
async fn bridge_connect(addr: std::net::SocketAddr, id: u64) -> Ws {
    let mut ws = common::bridge_client::bridge_connect(addr, id).await;
    assert!(matches!(
        next_bridge(&mut ws).await,
        BridgeServerMessage::Hello { .. }
    ));
    ws
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bridge_auth_frame_followed_by_garbage_gets_no_auth_ok() {
    let dir = TempDir::new("strict-bridge");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &json!({"driver": "bridge"})).await;
    let mut ws = bridge_connect(srv.addr, run.id).await;
    send(
        &mut ws,
        &format!(r#"{{"type":"auth","token":"{TOKEN}"}} xyz"#),
    )
    .await;
    match next_bridge(&mut ws).await {
        BridgeServerMessage::Error { message } => {
            assert!(message.contains("trailing characters"), "{message}")
        }
        other => panic!("expected an error frame, got {other:?}"),
    }
    let (s, _) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bridge_answer_after_stop_gets_an_error_frame() {
    let dir = TempDir::new("late-answer");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &json!({"driver": "bridge"})).await;
    let mut ws = bridge_connect(srv.addr, run.id).await;
    send(&mut ws, &format!(r#"{{"type":"auth","token":"{TOKEN}"}}"#)).await;
    assert_eq!(next_bridge(&mut ws).await, BridgeServerMessage::AuthOk);
    // The run's first request (the read-back of every gate), left unanswered.
    let id = match next_bridge(&mut ws).await {
        BridgeServerMessage::Request { id, .. } => id,
        other => panic!("expected a request, got {other:?}"),
    };
    let (s, text) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200, "{text}");
    wait_status(srv.addr, run.id, |r| r.status == RunStatus::Stopped).await;
    let answer = json!({
        "type": "response",
        "id": id,
        "response": {"response": "voltages_read", "voltages_mv": {}}
    });
    send(&mut ws, &answer.to_string()).await;
    match next_bridge(&mut ws).await {
        BridgeServerMessage::Error { message } => {
            assert!(
                message.contains(&format!("request {id} is not outstanding")),
                "{message}"
            )
        }
        other => panic!("expected an error frame, got {other:?}"),
    }
}

/// The close frame that ends `ws` (frames before it are skipped).
async fn close_code(ws: &mut Ws) -> Option<u16> {
    tokio::time::timeout(STEP, async {
        loop {
            match ws.next().await {
                Some(Ok(Message::Close(frame))) => return frame.map(|f| u16::from(f.code)),
                Some(Ok(_)) => continue,
                None | Some(Err(_)) => return None,
            }
        }
    })
    .await
    .expect("the socket did not close in time")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_websocket_messages_close_with_1009() {
    use spintune_server::server::{MAX_BRIDGE_MESSAGE, MAX_VIEWER_MESSAGE};
    let dir = TempDir::new("oversize");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &small_config("oversize", 2, 0)).await;
    let mut ws = connect(srv.addr, run.id, None).await;
    let huge = format!(
        r#"{{"type":"auth","token":"{}"}}"#,
        "x".repeat(MAX_VIEWER_MESSAGE)
    );
    let _ = ws.send(Message::Text(huge.into())).await;
    assert_eq!(close_code(&mut ws).await, Some(1009));

    let bridge_run = create_run(srv.addr, &json!({"driver": "bridge"})).await;
    let mut ws = bridge_connect(srv.addr, bridge_run.id).await;
    let huge = format!(
        r#"{{"type":"auth","token":"{}"}}"#,
        "x".repeat(MAX_BRIDGE_MESSAGE)
    );
    let _ = ws.send(Message::Text(huge.into())).await;
    assert_eq!(close_code(&mut ws).await, Some(1009));
    let (s, _) = control(srv.addr, bridge_run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_bodies_need_a_json_content_type() {
    let dir = TempDir::new("ctype");
    let srv = server(&dir, 64).await;
    let before = run_count(srv.addr).await;
    let body = Some(r#"{"tuner":{"max_iterations":1}}"#);
    for ctype in [
        "text/plain",
        "application/x-www-form-urlencoded",
        "multipart/form-data; boundary=x",
        "application/jsonx",
    ] {
        let (s, text) = http_typed(
            srv.addr,
            "POST",
            "/api/runs",
            Some(TOKEN),
            Some(ctype),
            body,
        )
        .await;
        assert_eq!(s, 415, "{ctype} → {text}");
        assert!(text.contains("application/json"), "{text}");
    }
    assert_eq!(run_count(srv.addr).await, before);
    // JSON with parameters, any case; and no Content-Type at all (scripts).
    for ctype in [
        Some("application/json"),
        Some("Application/JSON; charset=utf-8"),
        None,
    ] {
        let (s, text) = http_typed(srv.addr, "POST", "/api/runs", Some(TOKEN), ctype, body).await;
        assert_eq!(s, 201, "{ctype:?} → {text}");
    }
    let id =
        serde_json::from_str::<Vec<Value>>(&http(srv.addr, "GET", "/api/runs", None, None).await.1)
            .unwrap()[0]["id"]
            .as_u64()
            .unwrap();
    let path = format!("/api/runs/{id}/control");
    let (s, text) = http_typed(
        srv.addr,
        "POST",
        &path,
        Some(TOKEN),
        Some("text/plain"),
        Some(r#"{"action":"stop"}"#),
    )
    .await;
    assert_eq!(s, 415, "{text}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_iteration_delay_bound_is_enforced_over_the_api() {
    let dir = TempDir::new("delay");
    let srv = server(&dir, 64).await;
    let before = run_count(srv.addr).await;
    let max = SessionConfig::MAX_ITERATION_DELAY_MS;
    for ms in [max + 1, 1u64 << 40] {
        let (s, text) = http(
            srv.addr,
            "POST",
            "/api/runs",
            Some(TOKEN),
            Some(&json!({"iteration_delay_ms": ms}).to_string()),
        )
        .await;
        assert_eq!(s, 422, "{ms} → {text}");
        assert!(text.contains("`iteration_delay_ms`"), "{text}");
    }
    assert_eq!(run_count(srv.addr).await, before);
    let run = create_run(
        srv.addr,
        &json!({"iteration_delay_ms": max, "tuner": {"max_iterations": 1}}),
    )
    .await;
    let (s, _) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn symbolic_links_in_dist_are_not_served() {
    let dir = TempDir::new("dist-links");
    let dist = dir.0.join("dist");
    std::fs::create_dir_all(dist.join("assets")).unwrap();
    std::fs::write(dist.join("index.html"), "<html>dashboard</html>").unwrap();
    std::fs::write(dist.join("assets/app.js"), "console.log(1)").unwrap();
    std::fs::write(dir.0.join("secret.txt"), "SECRET").unwrap();
    let outside = TempDir::new("dist-outside");
    std::fs::write(outside.0.join("other.txt"), "OUTSIDE").unwrap();
    std::os::unix::fs::symlink(dir.0.join("secret.txt"), dist.join("secret.txt")).unwrap();
    std::os::unix::fs::symlink(dist.join("assets/app.js"), dist.join("alias.js")).unwrap();
    std::os::unix::fs::symlink(&outside.0, dist.join("outside")).unwrap();
    std::os::unix::fs::symlink(&outside.0, dist.join("assets/nested")).unwrap();
    let srv = server(&dir, 64).await;
    for (path, code) in [
        ("/", 200),
        ("/index.html", 200),
        ("/assets/app.js", 200),
        ("/assets/%61pp.js", 200),
        ("/secret.txt", 404),
        ("/alias.js", 404),
        ("/outside/other.txt", 404),
        ("/outside/", 404),
        ("/assets/nested/other.txt", 404),
        ("/%73ecret.txt", 404),
        ("/assets/../secret.txt", 404),
    ] {
        let (s, body) = http(srv.addr, "GET", path, None, None).await;
        assert_eq!(s, code, "{path} → {body}");
        assert!(
            !body.contains("SECRET") && !body.contains("OUTSIDE"),
            "{path} → {body}"
        );
    }
}

/// A body that never completes is answered 408 and closed within the real
/// `BODY_READ_TIMEOUT` (process-level, the binary's default flags).
#[test]
fn a_stalled_request_body_is_answered_408_within_the_body_read_timeout() {
    use spintune_server::server::listener::{BODY_READ_TIMEOUT, HEADER_READ_TIMEOUT};
    assert!(BODY_READ_TIMEOUT <= Duration::from_secs(10));
    let dir = TempDir::new("body-timeout");
    let (_proc, addr) = spawn_server(&dir.0.join("t.db"));
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let head = format!(
            "POST /api/runs HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{{\"seed\":1,"
        );
        let sent = Instant::now();
        // The server answers and closes; the client never sends the rest.
        let read = common::raw_http::exchange(
            &mut s,
            head.as_bytes(),
            BODY_READ_TIMEOUT + HEADER_READ_TIMEOUT / 2,
        )
        .await;
        let waited = sent.elapsed();
        let buf = read.unwrap_or_else(|| panic!("connection still open after {waited:?}"));
        let text = String::from_utf8_lossy(&buf);
        assert!(text.starts_with("HTTP/1.1 408"), "{text}");
        assert!(text.contains("did not arrive within"), "{text}");
        assert!(
            waited >= BODY_READ_TIMEOUT - Duration::from_millis(500),
            "answered after {waited:?}"
        );
        assert_eq!(run_count(addr).await, 0);
    });
}
