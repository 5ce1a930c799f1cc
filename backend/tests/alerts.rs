//! Alerts against the real binary (issue 23; docs/alerts.md): `spintune
//! serve --alert-webhook URL` POSTs a small JSON object to a local listener
//! (a tokio `TcpListener` in the test) when a run finishes or faults, tries
//! a 5xx answer again (exactly three attempts), never lets a webhook that
//! does not answer hold a run up, and logs an unreachable URL; viewers that
//! subscribed with `alerts: true` get the alert over the WebSocket.

mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use common::bridge_client::*;
use common::*;
use serde_json::{json, Value};
use spintune::driver::SimulationRun;
use spintune::protocol::{AlertKind, FaultKind, Response, RunStatus, ServerMessage};
use spintune_server::config::RunConfig;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Mutex};

/// How the test's webhook listener answers its n-th request.
#[derive(Debug, Clone, Copy)]
enum Answer {
    /// With this HTTP status.
    Status(u16),
    /// Never (the connection is held open, nothing is written).
    Never,
}

/// One request the listener received.
#[derive(Debug)]
struct Received {
    at: Instant,
    head: String,
    body: Value,
}

/// A webhook listener on an ephemeral loopback port answering its n-th
/// request with `script[n]` (the last entry for every later one).
struct Hook {
    url: String,
    received: mpsc::UnboundedReceiver<Received>,
}

impl Hook {
    async fn start(script: Vec<Answer>) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!(
            "http://{}/lab/alerts?source=spintune",
            listener.local_addr().unwrap()
        );
        let (tx, received) = mpsc::unbounded_channel();
        let held = Arc::new(Mutex::new(Vec::<TcpStream>::new()));
        tokio::spawn(async move {
            for n in 0.. {
                let Ok((mut stream, _)) = listener.accept().await else {
                    return;
                };
                let answer = script[n.min(script.len() - 1)];
                let tx = tx.clone();
                let held = held.clone();
                tokio::spawn(async move {
                    let Some((head, body)) = read_request(&mut stream).await else {
                        return;
                    };
                    let body = serde_json::from_slice(&body)
                        .unwrap_or_else(|e| panic!("webhook body is not JSON ({e}): {body:?}"));
                    let _ = tx.send(Received {
                        at: Instant::now(),
                        head,
                        body,
                    });
                    match answer {
                        Answer::Status(s) => {
                            let reply = format!(
                                "HTTP/1.1 {s} Whatever\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                            );
                            let _ = stream.write_all(reply.as_bytes()).await;
                            let _ = stream.shutdown().await;
                        }
                        Answer::Never => held.lock().await.push(stream),
                    }
                });
            }
        });
        Self { url, received }
    }

    /// The next request, within `within`.
    async fn next(&mut self, within: Duration) -> Received {
        tokio::time::timeout(within, self.received.recv())
            .await
            .expect("no webhook request in time")
            .expect("listener gone")
    }
}

/// One HTTP/1.1 request: head and body (by its Content-Length).
async fn read_request(stream: &mut TcpStream) -> Option<(String, Vec<u8>)> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    let end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        let n = stream.read(&mut chunk).await.ok()?;
        if n == 0 || buf.len() > 64 * 1024 {
            return None;
        }
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&buf[..end]).to_string();
    let length: usize = head
        .lines()
        .find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.eq_ignore_ascii_case("content-length")
                .then(|| v.trim().parse().ok())?
        })
        .expect("the webhook POST has a Content-Length");
    while buf.len() < end + length {
        let n = stream.read(&mut chunk).await.ok()?;
        if n == 0 {
            return None;
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    Some((head, buf[end..end + length].to_vec()))
}

fn served_with_hook(dir: &TempDir, url: &str) -> Served {
    Serve::new(&dir.0.join("s.db"))
        .args(["--alert-webhook", url])
        .spawn()
}

/// The fields of a webhook body, checked for shape: exactly these keys.
fn check_body(body: &Value, run: u64, name: &str, kind: &str) {
    let keys: Vec<&str> = body
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    assert_eq!(
        keys,
        [
            "at",
            "iteration",
            "kind",
            "lab_seconds",
            "message",
            "name",
            "run"
        ],
        "{body}"
    );
    assert_eq!(body["run"], run, "{body}");
    assert_eq!(body["name"], name, "{body}");
    assert_eq!(body["kind"], kind, "{body}");
    let at = body["at"].as_str().unwrap();
    assert!(
        at.len() == 20 && at.ends_with('Z') && at.as_bytes()[10] == b'T' && at.starts_with("20"),
        "not RFC 3339 UTC: {at}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_run_is_posted_to_the_webhook_once() {
    let dir = TempDir::new("alert-finished");
    let mut hook = Hook::start(vec![Answer::Status(204)]).await;
    let served = served_with_hook(&dir, &hook.url);
    assert!(
        served
            .printed
            .contains("Alerts: POSTed to http://127.0.0.1:"),
        "{}",
        served.printed
    );
    assert!(
        !served.printed.contains("source=spintune"),
        "the URL's path may hold a secret: {}",
        served.printed
    );
    let run = create_run(served.addr, &small_config("alert me", 3, 0)).await;
    let done = wait_status(served.addr, run.id, is_finished).await;
    let got = hook.next(STEP).await;
    assert!(
        got.head
            .starts_with("POST /lab/alerts?source=spintune HTTP/1.1\r\n"),
        "{}",
        got.head
    );
    assert!(
        got.head
            .to_ascii_lowercase()
            .contains("content-type: application/json"),
        "{}",
        got.head
    );
    check_body(&got.body, run.id, "alert me", "finished");
    assert_eq!(got.body["lab_seconds"], done.lab_seconds);
    assert_eq!(got.body["iteration"], done.iterations - 1);
    assert!(
        got.body["message"]
            .as_str()
            .unwrap()
            .starts_with("finished after 3 iterations"),
        "{}",
        got.body
    );
    // Answered 204 at once: no second attempt, no second alert.
    assert!(
        tokio::time::timeout(Duration::from_millis(1500), hook.received.recv())
            .await
            .is_err(),
        "a second POST for one finished run"
    );
}

/// A dashboard opened after a run needed a person still says so: a viewer
/// that asks for alerts gets the run's recent ones first (the same frame
/// the webhook's alert was stamped with), one that does not ask gets none.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_that_asks_later_gets_the_runs_recent_alerts() {
    let dir = TempDir::new("alert-late");
    let mut hook = Hook::start(vec![Answer::Status(204)]).await;
    let served = served_with_hook(&dir, &hook.url);
    let run = create_run(served.addr, &small_config("seen later", 3, 0)).await;
    wait_status(served.addr, run.id, is_finished).await;
    let posted = hook.next(STEP).await;
    check_body(&posted.body, run.id, "seen later", "finished");

    let mut late = connect(served.addr, run.id, None).await;
    send(
        &mut late,
        r#"{"type":"subscribe","scans":false,"alerts":true}"#,
    )
    .await;
    let (alert, at) = loop {
        match next_msg(&mut late).await {
            ServerMessage::Alert { alert, at } => break (alert, at),
            ServerMessage::Hello { .. }
            | ServerMessage::Status { .. }
            | ServerMessage::History { .. }
            | ServerMessage::Iteration { .. } => {}
            other => panic!("unexpected {other:?}"),
        }
    };
    assert_eq!((alert.run, alert.kind), (run.id, AlertKind::Finished));
    assert_eq!(alert.message, posted.body["message"].as_str().unwrap());
    assert_eq!(at, posted.body["at"].as_str().unwrap());

    // A viewer that does not ask gets no alert: its history answer comes
    // and nothing else.
    let mut plain = connect(served.addr, run.id, None).await;
    send(&mut plain, r#"{"type":"history","limit":1}"#).await;
    let mut histories = 0;
    while histories < 2 {
        match next_msg(&mut plain).await {
            ServerMessage::History { .. } => histories += 1,
            ServerMessage::Alert { alert, .. } => panic!("not asked: {alert:?}"),
            _ => {}
        }
    }
    assert!(
        tokio::time::timeout(Duration::from_millis(500), next_msg(&mut plain))
            .await
            .map_or(true, |m| !matches!(m, ServerMessage::Alert { .. })),
        "an alert to a viewer that did not ask"
    );
}

fn bridge_config(name: &str) -> Value {
    json!({
        "name": name,
        "seed": 5,
        "iteration_delay_ms": 0,
        "driver": "bridge",
        "bridge": { "request_timeout_s": 5.0 },
        "tuner": { "max_iterations": 4, "stop_when_tuned": false }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fault_reaches_the_webhook_and_the_viewers_that_asked() {
    let dir = TempDir::new("alert-fault");
    let mut hook = Hook::start(vec![Answer::Status(200)]).await;
    let served = served_with_hook(&dir, &hook.url);
    let addr = served.addr;
    let cfg = bridge_config("leaky");
    let mut device = SimulationRun::new(
        RunConfig::from_json_str(&cfg.to_string())
            .unwrap()
            .simulation,
    )
    .unwrap()
    .device()
    .clone();
    let run = create_run(addr, &cfg).await;
    // A viewer that asks for alerts (the `history` answer shows that the
    // server has read the `subscribe` before it).
    let mut viewer = connect(addr, run.id, None).await;
    send(
        &mut viewer,
        r#"{"type":"subscribe","scans":false,"alerts":true}"#,
    )
    .await;
    send(&mut viewer, r#"{"type":"history","limit":1}"#).await;
    let mut histories = 0;
    while histories < 2 {
        if let ServerMessage::History { .. } = next_msg(&mut viewer).await {
            histories += 1;
        }
    }
    let mut ws = bridge(addr, run.id).await;
    serve(&mut ws, &mut device, 12).await;
    let (id, _) = next_request_reading(&mut ws, &mut device).await;
    answer(
        &mut ws,
        id,
        Response::error("leakage on SB: 500 nA exceeds 100 nA"),
    )
    .await;

    // A bridge run faults `disconnected` until its bridge connects (an
    // alert too); then the device's fault.
    let got = loop {
        let got = hook.next(STEP).await;
        check_body(&got.body, run.id, "leaky", "faulted");
        if !got.body["message"]
            .as_str()
            .unwrap()
            .starts_with("disconnected fault")
        {
            break got;
        }
    };
    let message = got.body["message"].as_str().unwrap();
    assert!(message.starts_with("device fault: "), "{message}");
    assert!(
        message.contains("leakage on SB: 500 nA exceeds 100 nA"),
        "{message}"
    );
    assert!(message.contains("a person resumes it"), "{message}");

    let (alert, at) = loop {
        match next_msg(&mut viewer).await {
            ServerMessage::Alert { alert, at } if !alert.message.starts_with("disconnected") => {
                break (alert, at)
            }
            ServerMessage::Alert { .. } => {}
            ServerMessage::Status { .. } | ServerMessage::Iteration { .. } => {}
            other => panic!("unexpected {other:?}"),
        }
    };
    assert_eq!(alert.kind, AlertKind::Faulted);
    assert_eq!((alert.run, alert.message.as_str()), (run.id, message));
    assert_eq!(at, got.body["at"].as_str().unwrap());
    let r = get_run(addr, run.id).await;
    assert!(
        matches!(&r.status, RunStatus::Faulted { fault } if fault.kind == FaultKind::Device),
        "{:?}",
        r.status
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_errors_are_tried_exactly_three_times_with_back_off() {
    let dir = TempDir::new("alert-retry");
    let mut hook = Hook::start(vec![
        Answer::Status(500),
        Answer::Status(503),
        Answer::Status(200),
        Answer::Status(200),
    ])
    .await;
    let mut served = served_with_hook(&dir, &hook.url);
    let run = create_run(served.addr, &small_config("flaky hook", 2, 0)).await;
    wait_status(served.addr, run.id, is_finished).await;
    let attempts = [
        hook.next(STEP).await,
        hook.next(STEP).await,
        hook.next(STEP).await,
    ];
    for a in &attempts {
        check_body(&a.body, run.id, "flaky hook", "finished");
        assert_eq!(
            a.body, attempts[0].body,
            "every attempt sends the same alert"
        );
    }
    // Back-off 1 s, then 2 s.
    let gaps = [
        attempts[1].at - attempts[0].at,
        attempts[2].at - attempts[1].at,
    ];
    assert!(gaps[0] >= Duration::from_millis(900), "{gaps:?}");
    assert!(gaps[1] >= Duration::from_millis(1900), "{gaps:?}");
    // The sender says it delivered on the third attempt, and stops there.
    served.stderr_line("on attempt 3 of 3", STEP).await;
    assert!(
        hook.received.try_recv().is_err(),
        "a fourth attempt after the 200"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_error_is_not_tried_again() {
    let dir = TempDir::new("alert-4xx");
    let mut hook = Hook::start(vec![Answer::Status(404), Answer::Status(200)]).await;
    let mut served = served_with_hook(&dir, &hook.url);
    let run = create_run(served.addr, &small_config("wrong path", 2, 0)).await;
    wait_status(served.addr, run.id, is_finished).await;
    check_body(
        &hook.next(STEP).await.body,
        run.id,
        "wrong path",
        "finished",
    );
    let line = served.stderr_line("alert webhook: gave up", STEP).await;
    assert!(
        line.contains("HTTP 404") && line.contains("not retried"),
        "{line}"
    );
    assert!(hook.received.try_recv().is_err(), "a 404 was tried again");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_webhook_that_never_answers_does_not_hold_runs_up() {
    let dir = TempDir::new("alert-silent");
    let mut hook = Hook::start(vec![Answer::Never]).await;
    let served = served_with_hook(&dir, &hook.url);
    let addr = served.addr;
    // Run 1 finishes: its alert's first attempt hangs at the listener (the
    // sender waits 5 s per attempt, 3 attempts, 1 s + 2 s between them).
    let first = create_run(addr, &small_config("first", 2, 0)).await;
    wait_status(addr, first.id, is_finished).await;
    let hanging = hook.next(STEP).await;
    check_body(&hanging.body, first.id, "first", "finished");
    // Run 2 runs and finishes meanwhile, every record stored.
    let started = Instant::now();
    let second = create_run(addr, &small_config("second", 5, 0)).await;
    let done = wait_status(addr, second.id, is_finished).await;
    let took = started.elapsed();
    assert_eq!(done.iterations, 5);
    let stored = records(addr, second.id).await;
    let numbers: Vec<u64> = stored
        .iter()
        .map(|r| r["iteration"].as_u64().unwrap())
        .collect();
    assert_eq!(numbers, [0, 1, 2, 3, 4]);
    // Everything the listener has seen so far is run 1's alert: run 2's
    // alert waits in the queue behind it (the sender is still trying run
    // 1's for ≥ 18 s after it began), and run 2 did not wait for it.
    let mut seen = vec![hanging];
    while let Ok(r) = hook.received.try_recv() {
        seen.push(r);
    }
    if took < Duration::from_secs(15) {
        assert!(
            seen.iter().all(|r| r.body["run"] == first.id),
            "run 2's alert went out before run 1's attempts ended: {seen:?}"
        );
    }
    assert!(
        seen.len() <= 3,
        "more than 3 attempts for one alert: {seen:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unreachable_webhook_is_logged_and_the_server_goes_on() {
    let dir = TempDir::new("alert-unreachable");
    // A port nobody listens on: bind one, note it, let it go.
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let url = format!("http://127.0.0.1:{port}/hook");
    let mut served = served_with_hook(&dir, &url);
    let run = create_run(served.addr, &small_config("nobody listens", 2, 0)).await;
    wait_status(served.addr, run.id, is_finished).await;
    let first = served.stderr_line("attempt 1 of 3", STEP).await;
    assert!(first.contains("cannot connect to 127.0.0.1"), "{first}");
    let last = served.stderr_line("alert webhook: gave up", STEP).await;
    assert!(last.contains("after 3 attempts"), "{last}");
    // The server still answers and takes new runs.
    let again = create_run(served.addr, &small_config("still here", 1, 0)).await;
    wait_status(served.addr, again.id, is_finished).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_webhook_urls_are_refused_naming_the_flag() {
    let dir = TempDir::new("alert-bad-url");
    for (url, says) in [
        (
            "https://lab.example/hook",
            "only http:// URLs are supported",
        ),
        ("localhost:9000", "--alert-webhook"),
        ("http://user:secret@lab/hook", "user names or passwords"),
    ] {
        let out = Serve::new(&dir.0.join("s.db"))
            .args(["--alert-webhook", url])
            .exit();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{url}: {stderr}");
        assert!(
            stderr.contains("--alert-webhook") && stderr.contains(says),
            "{url}: {stderr}"
        );
    }
    // The environment variable is the same setting.
    let out = Serve::new(&dir.0.join("s.db"))
        .env("SPINTUNE_ALERT_WEBHOOK", "ftp://x/")
        .exit();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--alert-webhook"));
}

/// A keep run (issue 23) that cannot get back into band within its
/// configured lab time raises `not_back_in_band` at the webhook, with the
/// core's own words, and then still finishes (the alert never holds it up).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_keep_run_not_back_in_band_in_time_is_posted_to_the_webhook() {
    let dir = TempDir::new("alert-keep");
    let mut hook = Hook::start(vec![Answer::Status(204)]).await;
    let served = served_with_hook(&dir, &hook.url);
    // 60 lab seconds out of band is too long: some re-tune of a 12 h keep takes longer
    let config = json!({
        "name": "keep alert",
        "seed": 2,
        "iteration_delay_ms": 0,
        "tuner": { "keep": { "duration_s": 43200.0, "alert_after_s": 60.0 } }
    });
    let run = create_run(served.addr, &config).await;
    let done = wait_status(served.addr, run.id, is_finished).await;
    let mut kinds = Vec::new();
    loop {
        let got = hook.next(STEP).await;
        let kind = got.body["kind"].as_str().unwrap().to_string();
        if kind == "not_back_in_band" {
            check_body(&got.body, run.id, "keep alert", "not_back_in_band");
            let message = got.body["message"].as_str().unwrap();
            assert!(message.contains("not back in band"), "{message}");
        }
        kinds.push(kind);
        if kinds.last().map(String::as_str) == Some("finished") {
            break;
        }
    }
    assert!(kinds.iter().any(|k| k == "not_back_in_band"), "{kinds:?}");
    // every alert in the stored records reached the webhook, in order
    let stored = records(served.addr, run.id)
        .await
        .iter()
        .flat_map(|r| r["events"].as_array().cloned().unwrap_or_default())
        .filter(|e| e["event"] == "not_back_in_band")
        .count();
    assert_eq!(
        kinds.iter().filter(|k| *k == "not_back_in_band").count(),
        stored
    );
    assert!(done.lab_seconds > 43200.0 * 0.5);
}
