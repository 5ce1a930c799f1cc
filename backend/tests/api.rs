//! Integration tests against a real server on an ephemeral loopback port with
//! real WebSocket clients (tokio-tungstenite).

mod common;

use common::*;
use serde_json::{json, Value};
use spintune::protocol::{IterationRecord, RunStatus, ServerMessage, PROTOCOL_VERSION};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_viewers_receive_identical_streams_and_late_viewer_gets_history() {
    let dir = TempDir::new("viewers");
    let srv = server(&dir, 256).await;
    let n = 6;
    // Start paused so both viewers are connected before anything happens.
    // Paced, so that the pause lands before the run is over.
    let run = create_run(srv.addr, &small_config("viewers", n, 100)).await;
    let (s, b) = control(srv.addr, run.id, r#"{"action":"pause"}"#).await;
    assert_eq!(s, 200, "{b}");
    let mut a = connect(srv.addr, run.id, None).await;
    let mut b = connect(srv.addr, run.id, None).await;
    for ws in [&mut a, &mut b] {
        match next_msg(ws).await {
            ServerMessage::Hello { version, run: r } => {
                assert_eq!(version, PROTOCOL_VERSION);
                assert_eq!(r.id, run.id);
            }
            other => panic!("expected hello, got {other:?}"),
        }
    }
    let (s, body) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let ra = collect(&mut a, n as usize).await;
    let rb = collect(&mut b, n as usize).await;
    assert_eq!(ra.len(), n as usize);
    assert_eq!(ra, rb, "two viewers saw different streams");
    for (k, r) in ra.iter().enumerate() {
        assert_eq!(r.iteration, k as u64, "out of order or duplicated");
    }
    let done = wait_status(srv.addr, run.id, is_finished).await;
    assert_eq!(done.iterations, n);

    // The stream is the store's records as summaries (scans on request).
    let stored: Vec<IterationRecord> =
        serde_json::from_value(Value::Array(records(srv.addr, run.id).await)).unwrap();
    assert!(stored.iter().all(|r| !r.scans.is_empty()));
    let summaries: Vec<IterationRecord> = stored.iter().map(IterationRecord::summary).collect();
    assert_eq!(ra, summaries);
    let (s, body) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}/iterations?scans=false", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200, "{body}");
    assert_eq!(
        serde_json::from_str::<Vec<IterationRecord>>(&body).unwrap(),
        summaries
    );

    // A late viewer gets the history (shorter than a page) first.
    let mut late = connect(srv.addr, run.id, None).await;
    assert!(matches!(
        next_msg(&mut late).await,
        ServerMessage::Hello { .. }
    ));
    match next_msg(&mut late).await {
        ServerMessage::History { records, .. } => assert_eq!(records, ra),
        other => panic!("expected history, got {other:?}"),
    }
    // ... and `from` skips what it already has.
    let mut partial = connect(srv.addr, run.id, Some(4)).await;
    assert!(matches!(
        next_msg(&mut partial).await,
        ServerMessage::Hello { .. }
    ));
    match next_msg(&mut partial).await {
        ServerMessage::History { records, .. } => assert_eq!(records, ra[4..].to_vec()),
        other => panic!("expected history, got {other:?}"),
    }
}

/// A viewer that stalls (for less than the send timeout) lags: it is told
/// so, is sent the newest page, and by asking for the pages it missed it sees
/// every iteration exactly once; the run never waits for it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_viewer_is_told_it_lagged_and_can_page_back_to_every_iteration() {
    use std::collections::BTreeMap;
    let dir = TempDir::new("lag");
    // A buffer of one frame: any viewer that does not read at once lags. The
    // send timeout is long: this viewer stalls, it is not dead.
    let mut args = serve_args(&dir, 1);
    args.limits.viewer_send_timeout_ms = 120_000;
    let srv = spintune_server::cli::start_server(&args).await.unwrap();
    // Enough full frames (each ~15 kB with its scans: ~6 MB, beyond the 4 MB
    // ceiling of Linux's send-buffer autotuning) to fill the socket buffers of
    // a viewer that does not read, whatever the scheduling: the server's
    // forwarder then blocks and its one-frame buffer overflows for certain.
    let n = 400;
    let run = create_run(srv.addr, &small_config("lag", n, 0)).await;
    control(srv.addr, run.id, r#"{"action":"pause"}"#).await;
    let mut ws = connect_small_buffer(srv.addr, run.id).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    // Full records in live frames; the answer to the history request shows
    // the subscription was applied (messages are handled in order).
    send(&mut ws, r#"{"type":"subscribe","scans":true}"#).await;
    send(&mut ws, r#"{"type":"history","limit":1}"#).await;
    for _ in 0..2 {
        expect(&mut ws, |m| matches!(m, ServerMessage::History { .. })).await;
    }
    control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    // Do not read until the run is over: the viewer stalls, the run does not.
    wait_status(srv.addr, run.id, is_finished).await;
    let mut got: BTreeMap<u64, IterationRecord> = BTreeMap::new();
    let insert = |got: &mut BTreeMap<u64, IterationRecord>, r: IterationRecord| {
        let k = r.iteration;
        assert!(got.insert(k, r).is_none(), "iteration {k} sent twice");
    };
    let mut lagged = false;
    while !got.contains_key(&(n - 1)) {
        match next_msg(&mut ws).await {
            ServerMessage::History { records, .. } => {
                for r in records {
                    insert(&mut got, r);
                }
            }
            ServerMessage::Iteration { record } => insert(&mut got, record),
            ServerMessage::Lagged { skipped } => {
                assert!(skipped > 0);
                lagged = true;
            }
            _ => {}
        }
    }
    assert!(lagged, "the stalled viewer was not told it lagged");
    // Fill every gap with the pages it missed.
    let missing: Vec<u64> = (0..n).filter(|k| !got.contains_key(k)).collect();
    // (Whether anything is missing depends on when the socket buffers filled:
    // each `Lagged` is followed by up to a page of what was missed.)
    for k in missing {
        if got.contains_key(&k) {
            continue;
        }
        let end = (k..n).find(|j| got.contains_key(j)).unwrap();
        send(
            &mut ws,
            &format!(r#"{{"type":"history","before":{end},"limit":{}}}"#, end - k),
        )
        .await;
        match expect(&mut ws, |m| matches!(m, ServerMessage::History { .. })).await {
            ServerMessage::History { records, .. } => {
                let ks: Vec<u64> = records.iter().map(|r| r.iteration).collect();
                assert_eq!(ks, (k..end).collect::<Vec<_>>());
                for r in records {
                    assert!(r.scans.is_empty(), "pages carry summaries");
                    insert(&mut got, r);
                }
            }
            _ => unreachable!(),
        }
    }
    assert_eq!(
        got.keys().copied().collect::<Vec<_>>(),
        (0..n).collect::<Vec<_>>()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn control_needs_the_token_and_changes_nothing_without_it() {
    let dir = TempDir::new("auth");
    let srv = server(&dir, 256).await;
    let run = create_run(srv.addr, &small_config("auth", 1000, 100)).await;
    wait_status(srv.addr, run.id, |r| r.iterations >= 1).await;

    // REST without / with a wrong token.
    let path = format!("/api/runs/{}/control", run.id);
    let (s, body) = http(srv.addr, "POST", &path, None, Some(r#"{"action":"pause"}"#)).await;
    assert_eq!(s, 401, "{body}");
    assert!(body.contains("token"), "{body}");
    let (s, _) = http(
        srv.addr,
        "POST",
        &path,
        Some("wrong"),
        Some(r#"{"action":"stop"}"#),
    )
    .await;
    assert_eq!(s, 403);
    let (s, _) = http(srv.addr, "POST", "/api/runs", None, Some("{}")).await;
    assert_eq!(s, 401);
    let (s, _) = http(
        srv.addr,
        "DELETE",
        &format!("/api/runs/{}", run.id),
        Some("nope"),
        None,
    )
    .await;
    assert_eq!(s, 403);
    let (_, list) = http(srv.addr, "GET", "/api/runs", None, None).await;
    assert_eq!(serde_json::from_str::<Vec<Value>>(&list).unwrap().len(), 1);
    let before = get_run(srv.addr, run.id).await;
    assert_eq!(before.status, RunStatus::Running);
    // Still running: iterations keep coming.
    wait_status(srv.addr, run.id, |r| r.iterations > before.iterations).await;

    // WS: control before auth is refused, wrong token refused, socket stays.
    let mut ws = connect(srv.addr, run.id, None).await;
    let pause = r#"{"type":"control","command":{"action":"pause"}}"#;
    send(&mut ws, pause).await;
    expect_error(&mut ws, "token").await;
    send(&mut ws, r#"{"type":"auth","token":"wrong"}"#).await;
    expect_error(&mut ws, "invalid control token").await;
    assert_eq!(get_run(srv.addr, run.id).await.status, RunStatus::Running);

    // With the token it works.
    send(&mut ws, &format!(r#"{{"type":"auth","token":"{TOKEN}"}}"#)).await;
    expect(&mut ws, |m| matches!(m, ServerMessage::AuthOk)).await;
    send(&mut ws, pause).await;
    expect(
        &mut ws,
        |m| matches!(m, ServerMessage::Status { run } if run.status == RunStatus::Paused),
    )
    .await;
    let paused = get_run(srv.addr, run.id).await;
    assert_eq!(paused.status, RunStatus::Paused);
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    assert_eq!(
        get_run(srv.addr, run.id).await.iterations,
        paused.iterations,
        "paused run advanced"
    );

    // Single step: exactly one more iteration, then paused again.
    let (s, body) = control(srv.addr, run.id, r#"{"action":"step"}"#).await;
    assert_eq!(s, 200, "{body}");
    let r = wait_status(srv.addr, run.id, |r| {
        r.status == RunStatus::Paused && r.iterations == paused.iterations + 1
    })
    .await;
    assert_eq!(r.iterations, paused.iterations + 1);

    // Target change via REST shows up in the next record.
    let (s, body) = control(
        srv.addr,
        run.id,
        r#"{"action":"set_target","parameter":"t_sr","target":70.0,"tolerance":{"absolute":5.0}}"#,
    )
    .await;
    assert_eq!(s, 200, "{body}");
    control(srv.addr, run.id, r#"{"action":"step"}"#).await;
    wait_status(srv.addr, run.id, |x| {
        x.iterations == r.iterations + 1 && x.status == RunStatus::Paused
    })
    .await;
    let recs = records(srv.addr, run.id).await;
    let last = recs.last().unwrap();
    let t_sr = last["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "t_sr")
        .unwrap();
    assert_eq!(t_sr["target"], json!(70.0));
    assert_eq!(t_sr["tolerance"], json!(5.0));

    // Unknown parameter: clear error, nothing changes.
    let (s, body) = control(
        srv.addr,
        run.id,
        r#"{"action":"set_target","parameter":"nope","target":1.0}"#,
    )
    .await;
    assert_eq!(s, 422, "{body}");
    assert!(body.contains("nope"), "{body}");

    // Stop, then resume is refused; delete with the token works.
    let (s, _) = control(srv.addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200);
    wait_status(srv.addr, run.id, |r| r.status == RunStatus::Stopped).await;
    let (s, body) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 409, "{body}");
    let (s, _) = http(
        srv.addr,
        "DELETE",
        &format!("/api/runs/{}", run.id),
        Some(TOKEN),
        None,
    )
    .await;
    assert_eq!(s, 204);
    let (s, _) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 404);
}

async fn expect(ws: &mut Ws, f: impl Fn(&ServerMessage) -> bool) -> ServerMessage {
    loop {
        let m = next_msg(ws).await;
        if f(&m) {
            return m;
        }
        assert!(
            matches!(
                m,
                ServerMessage::Iteration { .. }
                    | ServerMessage::History { .. }
                    | ServerMessage::Hello { .. }
                    | ServerMessage::Status { .. }
            ),
            "unexpected {m:?}"
        );
    }
}

async fn expect_error(ws: &mut Ws, needle: &str) {
    match expect(ws, |m| matches!(m, ServerMessage::Error { .. })).await {
        ServerMessage::Error { message } => {
            assert!(
                message.contains(needle),
                "error {message:?} does not mention {needle:?}"
            )
        }
        _ => unreachable!(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_messages_get_clear_errors_and_the_socket_stays_open() {
    let dir = TempDir::new("malformed");
    let srv = server(&dir, 256).await;
    let run = create_run(srv.addr, &small_config("malformed", 2, 0)).await;
    let mut ws = connect(srv.addr, run.id, None).await;
    for (frame, needle) in [
        ("this is not json", "malformed"),
        (r#"{"type":"auth"}"#, "token"),
        (r#"{"type":"bogus"}"#, "bogus"),
        (r#"{"type":"auth","token":"x","extra":1}"#, "extra"),
        (
            r#"{"type":"control","command":{"action":"pause","extra":1}}"#,
            "extra",
        ),
        (r#"{"type":"control","command":{"action":"fly"}}"#, "fly"),
        (
            r#"{"type":"control","command":{"action":"set_target","parameter":"w","target":"high"}}"#,
            "high",
        ),
        (
            r#"{"type":"control","command":{"action":"set_target","parameter":"w","target":270,"tolerance":{"relative":-1}}}"#,
            "tolerance",
        ),
    ] {
        send(&mut ws, frame).await;
        expect_error(&mut ws, needle).await;
    }
    ws.send_binary().await;
    expect_error(&mut ws, "binary").await;
    // Still alive and usable.
    send(&mut ws, &format!(r#"{{"type":"auth","token":"{TOKEN}"}}"#)).await;
    expect(&mut ws, |m| matches!(m, ServerMessage::AuthOk)).await;

    // REST: malformed bodies and parameters name the problem.
    let path = format!("/api/runs/{}/control", run.id);
    for (body, needle) in [
        ("{", "malformed"),
        (r#"{"action":"pause","x":1}"#, "x"),
        (
            r#"{"action":"set_target","parameter":"w","target":1,"tolerance":{"absolute":-3}}"#,
            "tolerance",
        ),
    ] {
        let (s, text) = http(srv.addr, "POST", &path, Some(TOKEN), Some(body)).await;
        assert_eq!(s, 400, "{body} → {text}");
        assert!(text.contains(needle), "{body} → {text}");
        assert!(serde_json::from_str::<Value>(&text).unwrap()["error"].is_string());
    }
    for (body, needle) in [
        (r#"{"seed":"abc"}"#, "seed"),
        (r#"{"tuner":{"levels":[]}}"#, "levels"),
        (r#"{"device_typo":1}"#, "device_typo"),
        (r#"{"targets":{"t_sr":-5e400}}"#, "number out of range"),
        (r#"{"targets":{"t_sr":"high"}}"#, "targets.t_sr"),
        (
            r#"{"tuner":{"gates":[{"name":"N","min_mv":10,"max_mv":0,"initial_mv":5}]}}"#,
            "tuner.gates[0].min_mv",
        ),
    ] {
        let (s, text) = http(srv.addr, "POST", "/api/runs", Some(TOKEN), Some(body)).await;
        assert_eq!(s, 422, "{body} → {text}");
        assert!(text.contains(needle), "{body} → {text}");
    }
    let (s, text) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}/iterations?from=-1", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 400, "{text}");
    assert!(text.contains("from"));
    let (s, _) = http(srv.addr, "GET", "/api/runs/999/iterations", None, None).await;
    assert_eq!(s, 404);
    // No dashboard built: `/` explains how to build it.
    let (s, text) = http(srv.addr, "GET", "/", None, None).await;
    assert_eq!(s, 200);
    assert!(text.contains("trunk build"), "{text}");
    let (s, text) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}/export?format=csv", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200, "{text}");
    assert!(text.starts_with("seq,iteration,lab_seconds"), "{text}");
}

trait SendBinary {
    async fn send_binary(&mut self);
}

impl SendBinary for Ws {
    async fn send_binary(&mut self) {
        use futures_util::SinkExt;
        self.send(tokio_tungstenite::tungstenite::Message::Binary(
            vec![1u8, 2, 3].into(),
        ))
        .await
        .unwrap();
    }
}

/// A viewer whose TCP receive buffer is tiny, so a stalled reader backs up the server at once.
async fn connect_small_buffer(addr: std::net::SocketAddr, id: u64) -> common::Ws {
    let sock = tokio::net::TcpSocket::new_v4().unwrap();
    sock.set_recv_buffer_size(4096).unwrap();
    let stream = sock.connect(addr).await.unwrap();
    let url = format!(
        "ws://{addr}/api/runs/{id}/ws?protocol={}",
        spintune::protocol::PROTOCOL_VERSION
    );
    let (ws, _) =
        tokio_tungstenite::client_async(url, tokio_tungstenite::MaybeTlsStream::Plain(stream))
            .await
            .expect("websocket handshake");
    ws
}

/// A version-1 client (no `protocol` in the URL) and a client stating
/// another version get one error frame naming both versions; the socket
/// then closes. Bridges are held to the same rule.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_of_another_protocol_version_get_a_clear_version_error() {
    use futures_util::StreamExt;
    use tokio_tungstenite::tungstenite::Message;
    let dir = TempDir::new("version");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &small_config("v", 1, 0)).await;
    for path in [
        format!("/api/runs/{}/ws", run.id),
        format!("/api/runs/{}/ws?protocol=1&from=0", run.id),
        format!("/api/runs/{}/bridge", run.id),
    ] {
        let url = format!("ws://{}{path}", srv.addr);
        let (mut ws, _) = tokio::time::timeout(STEP, tokio_tungstenite::connect_async(url))
            .await
            .unwrap()
            .unwrap();
        let first = tokio::time::timeout(STEP, ws.next())
            .await
            .unwrap()
            .expect("an error frame")
            .unwrap();
        let Message::Text(text) = first else {
            panic!("{path}: expected a text frame, got {first:?}")
        };
        let v: Value = serde_json::from_str(text.as_str()).unwrap();
        assert_eq!(v["type"], "error", "{path}: {v}");
        let msg = v["message"].as_str().unwrap();
        assert!(
            msg.contains(&format!("protocol version {PROTOCOL_VERSION}")),
            "{path}: {msg}"
        );
        // then the server closes the socket
        let next = tokio::time::timeout(STEP, ws.next()).await.unwrap();
        assert!(
            matches!(next, None | Some(Ok(Message::Close(_))) | Some(Err(_))),
            "{path}: {next:?}"
        );
    }
}

/// Pages of `GET /iterations` are bounded (default and maximum), and a viewer
/// frame above the inbound cap ends that socket without harming the run.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn iteration_pages_and_inbound_frames_are_bounded() {
    use futures_util::{SinkExt, StreamExt};
    use spintune_server::server::{MAX_PAGE, MAX_VIEWER_MESSAGE};
    let dir = TempDir::new("bounds");
    let srv = server(&dir, 64).await;
    let run = create_run(srv.addr, &small_config("bounds", 3, 0)).await;
    wait_status(srv.addr, run.id, is_finished).await;
    let (s, body) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}/iterations?limit=2", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200);
    assert_eq!(serde_json::from_str::<Vec<Value>>(&body).unwrap().len(), 2);
    let (s, body) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{}/iterations?limit={}", run.id, MAX_PAGE + 1),
        None,
        None,
    )
    .await;
    assert_eq!(s, 400, "{body}");
    assert!(body.contains("largest page"), "{body}");

    let mut ws = connect(srv.addr, run.id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    let huge = format!(
        r#"{{"type":"auth","token":"{}"}}"#,
        "x".repeat(MAX_VIEWER_MESSAGE + 1)
    );
    let _ = ws
        .send(tokio_tungstenite::tungstenite::Message::Text(huge.into()))
        .await;
    // the server drops the socket instead of buffering the frame
    let closed = tokio::time::timeout(STEP, async {
        loop {
            match ws.next().await {
                None | Some(Err(_)) => return,
                Some(Ok(tokio_tungstenite::tungstenite::Message::Close(_))) => return,
                Some(Ok(_)) => continue,
            }
        }
    })
    .await;
    assert!(closed.is_ok(), "an oversized frame did not end the socket");
    // the server still serves
    assert_eq!(get_run(srv.addr, run.id).await.id, run.id);
}

/// Issue 21: a target out of bounds (−50 ns or 1e8 ns for t_sr) is refused
/// by the API naming the parameter, in a run config and in a control
/// command alike (the core's one check, `ParameterSpec::check_target`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn targets_out_of_bounds_are_refused_naming_the_parameter() {
    let dir = TempDir::new("target-bounds");
    let srv = server(&dir, 256).await;
    // (in a config, 1e8 is beyond every config number's bound already)
    for (target, needle) in [("-50", "> 0"), ("1e8", "within ±1e6")] {
        let body = format!(r#"{{"targets":{{"t_sr":{target}}}}}"#);
        let (s, text) = http(srv.addr, "POST", "/api/runs", Some(TOKEN), Some(&body)).await;
        assert_eq!(s, 422, "{body} → {text}");
        assert!(
            text.contains("targets.t_sr") && text.contains(needle),
            "{text}"
        );
    }
    let run = create_run(srv.addr, &small_config("bounds", 100_000, 20)).await;
    let path = format!("/api/runs/{}/control", run.id);
    for (target, needle) in [("-50", "> 0"), ("1e8", "at most")] {
        let body = format!(r#"{{"action":"set_target","parameter":"t_sr","target":{target}}}"#);
        let (s, text) = http(srv.addr, "POST", &path, Some(TOKEN), Some(&body)).await;
        assert_eq!(s, 422, "{body} → {text}");
        assert!(text.contains("t_sr") && text.contains(needle), "{text}");
    }
    let (s, text) = control(
        srv.addr,
        run.id,
        r#"{"action":"set_target","parameter":"t_sr","target":70}"#,
    )
    .await;
    assert_eq!(s, 200, "{text}");
}
