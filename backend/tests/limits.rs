//! Connection and viewer limits, against the real binary as a process
//! (`spintune serve` with short timeouts given by flags): a viewer that never
//! reads is dropped after the send timeout while another keeps receiving; a
//! viewer that never answers pings is dropped; a connection that never
//! finishes its headers is closed; the per-IP connection cap refuses the
//! 65th connection; server memory stays bounded under stalled viewers.

mod common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::*;
use futures_util::StreamExt;
use spintune::protocol::{ServerMessage, PROTOCOL_VERSION};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message;

/// `spintune serve` with the store in `dir` and `extra` flags.
fn spawn(dir: &TempDir, extra: &[&str]) -> Served {
    Serve::new(&dir.0.join("limits.db")).args(extra).spawn()
}

/// VmRSS of a process, KiB.
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .expect("VmRSS in /proc/PID/status")
}

/// A viewer whose TCP receive buffer is tiny, so that a reader that stalls
/// backs up the server at once.
async fn stalled_viewer(addr: SocketAddr, id: u64) -> Ws {
    let sock = tokio::net::TcpSocket::new_v4().unwrap();
    sock.set_recv_buffer_size(4096).unwrap();
    let stream = sock.connect(addr).await.unwrap();
    let url = format!("ws://{addr}/api/runs/{id}/ws?protocol={PROTOCOL_VERSION}");
    let (ws, _) = tokio::time::timeout(
        STEP,
        tokio_tungstenite::client_async(url, tokio_tungstenite::MaybeTlsStream::Plain(stream)),
    )
    .await
    .expect("handshake timed out")
    .expect("websocket handshake");
    ws
}

/// Ask for full live frames and `requests` history pages of `limit`
/// records, then never read.
async fn stall(ws: &mut Ws, requests: usize, limit: u32) {
    send(ws, r#"{"type":"subscribe","scans":true}"#).await;
    for _ in 0..requests {
        send(ws, &format!(r#"{{"type":"history","limit":{limit}}}"#)).await;
    }
}

/// A WebSocket handshake by hand on a raw TCP stream (this client never
/// answers a ping).
async fn raw_viewer(addr: SocketAddr, id: u64) -> TcpStream {
    let mut s = TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "GET /api/runs/{id}/ws?protocol={PROTOCOL_VERSION} HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        let n = tokio::time::timeout(STEP, s.read(&mut byte))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(n, 1, "closed during the handshake");
        head.push(byte[0]);
    }
    assert!(
        head.starts_with(b"HTTP/1.1 101"),
        "{}",
        String::from_utf8_lossy(&head)
    );
    s
}

const NOT_CLOSED: &str = "the server did not close the connection in time";

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_that_never_reads_is_disconnected_after_the_send_timeout_while_another_keeps_receiving(
) {
    let dir = TempDir::new("send-timeout");
    let send_timeout = Duration::from_millis(1000);
    let mut served = spawn(&dir, &["--viewer-send-timeout-ms", "1000"]);
    let addr = served.addr;
    let run = create_run(addr, &small_config("stall", 100_000, 20)).await;
    wait_status(addr, run.id, |r| r.iterations >= 50).await;

    // The healthy viewer reads everything and reports each live iteration.
    let mut healthy = connect(addr, run.id, None).await;
    let (seen_tx, mut seen_rx) = mpsc::unbounded_channel();
    let reader = tokio::spawn(async move {
        loop {
            match next_msg(&mut healthy).await {
                ServerMessage::Iteration { record } => {
                    let _ = seen_tx.send(record.iteration);
                }
                ServerMessage::Error { message } => panic!("healthy viewer: {message}"),
                _ => {}
            }
        }
    });
    seen_rx.recv().await.expect("the healthy viewer receives");

    let mut stalled = stalled_viewer(addr, run.id).await;
    stall(&mut stalled, 40, 2000).await;
    let stalled_at = Instant::now();
    let line = served
        .stderr_line(
            &format!("viewer of run {} disconnected: send timed out", run.id),
            send_timeout + Duration::from_secs(10),
        )
        .await;
    let after = stalled_at.elapsed();
    assert!(
        after < send_timeout + Duration::from_secs(4),
        "disconnected only after {after:?}: {line}"
    );
    // The other viewer keeps receiving, live, after the disconnect.
    while seen_rx.try_recv().is_ok() {}
    for _ in 0..5 {
        tokio::time::timeout(STEP, seen_rx.recv())
            .await
            .expect("the healthy viewer stopped receiving")
            .expect("the healthy viewer's reader ended");
    }
    // The stalled socket ends once its buffered frames are drained.
    let ended = tokio::time::timeout(STEP, async {
        while let Some(Ok(_)) = stalled.next().await {}
    })
    .await;
    assert!(ended.is_ok(), "the stalled viewer's socket did not end");
    reader.abort();
    drop(served.proc);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_that_never_answers_pings_is_disconnected_and_one_that_answers_stays() {
    let dir = TempDir::new("ping");
    let served = spawn(
        &dir,
        &[
            "--viewer-ping-interval-ms",
            "200",
            "--viewer-pong-timeout-ms",
            "1000",
        ],
    );
    let addr = served.addr;
    let run = create_run(addr, &small_config("ping", 2, 0)).await;
    wait_status(addr, run.id, is_finished).await;
    // tungstenite answers pings while it reads: this viewer reads all the
    // time and reports the pings it gets.
    let mut answering = connect(addr, run.id, None).await;
    let (ping_tx, mut ping_rx) = mpsc::unbounded_channel();
    let reader = tokio::spawn(async move {
        loop {
            match answering.next().await {
                Some(Ok(Message::Ping(_))) => {
                    let _ = ping_tx.send(Instant::now());
                }
                Some(Ok(Message::Close(c))) => panic!("answering viewer closed: {c:?}"),
                Some(Ok(_)) => {}
                other => panic!("answering viewer ended: {other:?}"),
            }
        }
    });
    let mut silent = raw_viewer(addr, run.id).await;
    let start = Instant::now();
    let bytes = read_until_closed(&mut silent, Duration::from_secs(10))
        .await
        .expect(NOT_CLOSED);
    let after = start.elapsed();
    assert!(
        contains(&bytes, b"no pong"),
        "no close reason in {:?}",
        String::from_utf8_lossy(&bytes)
    );
    assert!(
        after >= Duration::from_millis(900) && after < Duration::from_secs(5),
        "closed after {after:?}"
    );
    // The answering viewer is still served well past the pong timeout:
    // pings keep coming.
    let well_past = start + Duration::from_millis(2500);
    loop {
        let at = tokio::time::timeout(STEP, ping_rx.recv())
            .await
            .expect("no more pings for the answering viewer")
            .expect("the answering viewer's reader ended");
        if at > well_past {
            break;
        }
    }
    assert!(!reader.is_finished(), "the answering viewer was dropped");
    reader.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_that_never_finishes_its_headers_is_closed_after_the_header_timeout() {
    let dir = TempDir::new("headers");
    let served = spawn(&dir, &["--header-read-timeout-ms", "1000"]);
    let addr = served.addr;
    for partial in [&b"GET /api/version HTTP/1.1\r\nHost: x\r\n"[..], &b""[..]] {
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(partial).await.unwrap();
        let start = Instant::now();
        let bytes = read_until_closed(&mut s, Duration::from_secs(10))
            .await
            .expect(NOT_CLOSED);
        let after = start.elapsed();
        assert!(
            after >= Duration::from_millis(900) && after < Duration::from_secs(5),
            "closed after {after:?}"
        );
        assert!(
            !contains(&bytes, b"protocol_version"),
            "{}",
            String::from_utf8_lossy(&bytes)
        );
    }
    // A complete request is served.
    let (status, body) = http(addr, "GET", "/api/version", None, None).await;
    assert_eq!(status, 200, "{body}");
}

/// A keep-alive connection that has been served once (so the server has
/// accepted and counted it).
async fn served_connection(addr: SocketAddr) -> TcpStream {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET /api/version HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 1024];
    tokio::time::timeout(STEP, async {
        while !contains(&got, b"}") {
            let n = s.read(&mut buf).await.unwrap();
            assert!(n > 0, "closed: {}", String::from_utf8_lossy(&got));
            got.extend_from_slice(&buf[..n]);
        }
    })
    .await
    .expect("no answer");
    assert!(got.starts_with(b"HTTP/1.1 200"));
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_per_ip_connection_cap_refuses_the_65th_connection() {
    use spintune_server::server::listener::MAX_CONNECTIONS_PER_IP;
    assert_eq!(MAX_CONNECTIONS_PER_IP, 64);
    let dir = TempDir::new("per-ip");
    let served = spawn(&dir, &["--header-read-timeout-ms", "60000"]);
    let addr = served.addr;
    let mut open = Vec::new();
    for _ in 0..MAX_CONNECTIONS_PER_IP {
        open.push(served_connection(addr).await);
    }
    // The 65th is closed without an answer.
    let mut extra = TcpStream::connect(addr).await.unwrap();
    let _ = extra
        .write_all(format!("GET /api/version HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await;
    let bytes = read_until_closed(&mut extra, STEP).await.expect(NOT_CLOSED);
    assert!(bytes.is_empty(), "{}", String::from_utf8_lossy(&bytes));
    // Closing one makes room again.
    drop(open.pop());
    let room = tokio::time::timeout(STEP, async {
        loop {
            let mut s = TcpStream::connect(addr).await.unwrap();
            let _ = s
                .write_all(
                    format!(
                        "GET /api/version HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
                    )
                    .as_bytes(),
                )
                .await;
            let bytes = read_until_closed(&mut s, STEP).await.expect(NOT_CLOSED);
            if bytes.starts_with(b"HTTP/1.1 200") {
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    assert!(room.is_ok(), "a closed connection's place was not freed");
}

/// Server RSS bound with [`STALLED`] stalled viewers (each asking for full
/// live frames and 20 default history pages, never reading) on a live run of
/// some hundreds of iterations: the send timeout and bounded pages keep each
/// such viewer at most one frame. Measured: ~22 MiB before the viewers, peak
/// ~63 MiB with them (2 cores, debug build); the bench measures 200 viewers
/// (backend/BENCHMARKS.md).
const RSS_BOUND_MIB: u64 = 160;
const STALLED: usize = 100;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_memory_stays_bounded_with_100_stalled_viewers_and_all_are_dropped_after_the_send_timeout(
) {
    let dir = TempDir::new("rss");
    let mut served = spawn(
        &dir,
        &[
            "--viewer-send-timeout-ms",
            "3000",
            "--max-connections-per-ip",
            "1000",
        ],
    );
    let addr = served.addr;
    let pid = served.proc.0.id();
    let run = create_run(addr, &small_config("rss", 100_000, 10)).await;
    wait_status(addr, run.id, |r| r.iterations >= 300).await;
    let baseline = rss_kib(pid);
    let mut viewers = Vec::new();
    for _ in 0..STALLED {
        let mut ws = stalled_viewer(addr, run.id).await;
        stall(&mut ws, 20, spintune::protocol::DEFAULT_HISTORY_PAGE).await;
        viewers.push(ws);
    }
    let mut peak = 0;
    let mut dropped = 0;
    let deadline = Instant::now() + Duration::from_secs(90);
    while dropped < STALLED {
        peak = peak.max(rss_kib(pid));
        assert!(
            Instant::now() < deadline,
            "only {dropped} stalled viewers were dropped"
        );
        if let Ok(Some(line)) =
            tokio::time::timeout(Duration::from_millis(100), served.stderr.recv()).await
        {
            if line.contains("disconnected: send timed out") {
                dropped += 1;
            }
        }
    }
    peak = peak.max(rss_kib(pid));
    eprintln!(
        "server RSS: {} MiB before, peak {} MiB with {STALLED} stalled viewers",
        baseline / 1024,
        peak / 1024
    );
    assert!(
        peak < RSS_BOUND_MIB * 1024,
        "server RSS {} MiB exceeds {RSS_BOUND_MIB} MiB",
        peak / 1024
    );
    // The run went on.
    let before = get_run(addr, run.id).await.iterations;
    wait_status(addr, run.id, |r| r.iterations > before).await;
}
