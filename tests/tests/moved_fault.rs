//! Browser end-to-end test of the confirm-positions flow (issue 20): a run
//! driven by a scripted lab bridge is paused, gate N is moved 50 mV by hand,
//! the resumed run faults (`moved`); the dashboard shows the kind, what
//! clears it and N's old → new position; with the control token, "Accept
//! positions" leaves the run paused on the server, and Resume continues it.
//!
//! Inputs as for `browser.rs` (`SPINTUNE_BIN`, `SPINTUNE_DIST`, `CHROMEDRIVER`).
//! The bridge is a minimal synchronous WebSocket client over a `TcpStream`
//! (this crate has no WebSocket library) answering from a simulated device.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use spintune::driver::SimulationRun;
use spintune::protocol::{
    BridgeClientMessage, BridgeServerMessage, Request, RunStatus, RunSummary, PROTOCOL_VERSION,
};
use spintune::sim::SimulatedDevice;
use spintune_server::config::RunConfig;

mod support;
use support::*;

/// A WebSocket client connection (RFC 6455, text frames only).
struct Ws {
    reader: BufReader<TcpStream>,
    writer: TcpStream,
}

impl Ws {
    fn connect(port: u16, path: &str) -> Self {
        let mut writer = TcpStream::connect(("127.0.0.1", port)).expect("connect the bridge");
        writer
            .set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        write!(
            writer,
            "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        .unwrap();
        let mut reader = BufReader::new(writer.try_clone().unwrap());
        let mut head = String::new();
        loop {
            let mut line = String::new();
            match reader.read_line(&mut line) {
                Ok(0) => panic!("bridge handshake: connection closed after {head:?}"),
                Ok(_) => {}
                Err(e) if is_timeout(&e) => continue,
                Err(e) => panic!("bridge handshake: {e}"),
            }
            head.push_str(&line);
            if line == "\r\n" {
                break;
            }
        }
        assert!(head.starts_with("HTTP/1.1 101"), "bridge handshake: {head}");
        Ws { reader, writer }
    }

    fn send_frame(&mut self, opcode: u8, payload: &[u8]) {
        let mask = [0x5a, 0x13, 0xc7, 0x21];
        let mut frame = vec![0x80 | opcode];
        match payload.len() {
            n if n < 126 => frame.push(0x80 | n as u8),
            n if n < 65_536 => {
                frame.push(0x80 | 126);
                frame.extend_from_slice(&(n as u16).to_be_bytes());
            }
            n => {
                frame.push(0x80 | 127);
                frame.extend_from_slice(&(n as u64).to_be_bytes());
            }
        }
        frame.extend_from_slice(&mask);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        self.writer.write_all(&frame).unwrap();
    }

    fn send(&mut self, msg: &BridgeClientMessage) {
        self.send_frame(0x1, serde_json::to_string(msg).unwrap().as_bytes());
    }

    fn read_exact(&mut self, buf: &mut [u8]) {
        let mut done = 0;
        while done < buf.len() {
            match self.reader.read(&mut buf[done..]) {
                Ok(0) => panic!("bridge socket closed"),
                Ok(n) => done += n,
                Err(e) if is_timeout(&e) => continue,
                Err(e) => panic!("bridge socket: {e}"),
            }
        }
    }

    /// The next text message, answering pings; `None` when nothing arrives
    /// within the read timeout.
    fn next(&mut self) -> Option<BridgeServerMessage> {
        let mut message = Vec::new();
        loop {
            let mut b0 = [0u8; 1];
            match self.reader.read(&mut b0) {
                Ok(0) => panic!("bridge socket closed"),
                Ok(_) => {}
                Err(e) if is_timeout(&e) && message.is_empty() => return None,
                Err(e) if is_timeout(&e) => continue,
                Err(e) => panic!("bridge socket: {e}"),
            }
            let mut b1 = [0u8; 1];
            self.read_exact(&mut b1);
            let len = match b1[0] & 0x7f {
                126 => {
                    let mut l = [0u8; 2];
                    self.read_exact(&mut l);
                    u16::from_be_bytes(l) as usize
                }
                127 => {
                    let mut l = [0u8; 8];
                    self.read_exact(&mut l);
                    u64::from_be_bytes(l) as usize
                }
                n => n as usize,
            };
            assert_eq!(b1[0] & 0x80, 0, "the server masks no frames");
            let mut payload = vec![0u8; len];
            self.read_exact(&mut payload);
            match b0[0] & 0x0f {
                0x9 => self.send_frame(0xa, &payload),
                0xa => {}
                0x8 => panic!("the server closed the bridge socket: {payload:?}"),
                _ => {
                    message.extend_from_slice(&payload);
                    if b0[0] & 0x80 != 0 {
                        let text = String::from_utf8(message).unwrap();
                        return Some(
                            serde_json::from_str(&text)
                                .unwrap_or_else(|e| panic!("bad bridge frame {text}: {e}")),
                        );
                    }
                }
            }
        }
    }

    fn next_within(&mut self, secs: u64) -> BridgeServerMessage {
        let start = std::time::Instant::now();
        loop {
            if let Some(m) = self.next() {
                return m;
            }
            assert!(
                start.elapsed() < Duration::from_secs(secs),
                "no bridge frame within {secs} s"
            );
        }
    }
}

fn is_timeout(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
    )
}

/// The JSON value in an HTTP body (which may be chunked).
fn json_body(body: &str) -> serde_json::Value {
    let start = body
        .find('{')
        .unwrap_or_else(|| panic!("no JSON in {body:?}"));
    let end = body.rfind('}').unwrap();
    serde_json::from_str(&body[start..=end]).unwrap_or_else(|e| panic!("{e}: {body}"))
}

fn get_run(port: u16, id: u64) -> RunSummary {
    let (status, body) = http(port, "GET", &format!("/api/runs/{id}"), None, "");
    assert_eq!(status, 200, "{body}");
    serde_json::from_value(json_body(&body)).unwrap()
}

fn control(port: u16, id: u64, command: &str) -> (u16, String) {
    http(
        port,
        "POST",
        &format!("/api/runs/{id}/control"),
        Some(TOKEN),
        command,
    )
}

/// Poll the run until `ok` holds (or fail after `secs`).
async fn wait_run(
    port: u16,
    run: u64,
    what: &str,
    secs: u64,
    ok: impl Fn(&RunSummary) -> bool,
) -> RunSummary {
    wait(what, secs, async || Some(get_run(port, run)).filter(&ok)).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_moved_gate_is_shown_and_its_position_accepted_in_the_dashboard() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-moved-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let _server = start_server(port, &tmp.join("runs.db"));

    // A run measured through a lab bridge: the "lab" is the simulated dot of
    // the same config, answered by a bridge thread.
    let config = serde_json::json!({
        "name": "lab bridge",
        "seed": 5,
        "iteration_delay_ms": 100,
        "driver": "bridge",
        "bridge": { "request_timeout_s": 30.0 },
        "tuner": { "max_iterations": 10_000, "stop_when_tuned": false }
    });
    let parsed = RunConfig::from_json_str(&config.to_string()).unwrap();
    let device: Arc<Mutex<SimulatedDevice>> = Arc::new(Mutex::new(
        SimulationRun::new(parsed.simulation)
            .unwrap()
            .device()
            .clone(),
    ));
    let (status, body) = http(port, "POST", "/api/runs", Some(TOKEN), &config.to_string());
    assert_eq!(status, 201, "{body}");
    let run = json_body(&body)["id"].as_u64().unwrap();

    let done = Arc::new(AtomicBool::new(false));
    let bridge = {
        let (device, done) = (device.clone(), done.clone());
        std::thread::spawn(move || {
            let mut ws = Ws::connect(
                port,
                &format!("/api/runs/{run}/bridge?protocol={PROTOCOL_VERSION}"),
            );
            assert!(matches!(
                ws.next_within(10),
                BridgeServerMessage::Hello { .. }
            ));
            ws.send(&BridgeClientMessage::Auth {
                token: TOKEN.into(),
            });
            assert_eq!(ws.next_within(10), BridgeServerMessage::AuthOk);
            while !done.load(Ordering::Relaxed) {
                match ws.next() {
                    Some(BridgeServerMessage::Request { id, request, .. }) => {
                        let response = device.lock().unwrap().execute(&request);
                        ws.send(&BridgeClientMessage::Response { id, response });
                    }
                    Some(other) => panic!("unexpected bridge frame {other:?}"),
                    None => {}
                }
            }
        })
    };
    wait_run(port, run, "two iterations over the bridge", 120, |r| {
        r.iterations >= 2
    })
    .await;

    // Pause; someone moves N 50 mV by hand; resume: the run reads every gate
    // and faults with nothing moved.
    let (s, b) = control(port, run, r#"{"action":"pause"}"#);
    assert_eq!(s, 200, "{b}");
    wait_run(port, run, "paused", 30, |r| r.status == RunStatus::Paused).await;
    let (left, moved_to) = {
        let mut d = device.lock().unwrap();
        let left = d.voltages_mv()["N"];
        d.execute(&Request::SetVoltages {
            voltages_mv: [("N".to_string(), left - 50.0)].into(),
        });
        (left, d.voltages_mv()["N"])
    };
    assert!((moved_to - (left - 50.0)).abs() < 1e-9);
    let (s, b) = control(port, run, r#"{"action":"resume"}"#);
    assert_eq!(s, 200, "{b}");
    let faulted = wait_run(
        port,
        run,
        "a moved fault",
        30,
        |r| matches!(&r.status, RunStatus::Faulted { fault } if !fault.moved.is_empty()),
    )
    .await;
    let iterations = faulted.iterations;

    // The dashboard: kind, what clears it, N's old → new position.
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    c.goto(&format!("http://127.0.0.1:{port}/#live/{run}"))
        .await
        .unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    wait_text(&c, "[data-testid=run-status]", "Gates moved", 30).await;
    let clears = wait_text(
        &c,
        "[data-testid=fault-clears]",
        "confirm the new positions",
        10,
    )
    .await;
    eprintln!("fault clears: {clears}");
    assert_eq!(
        attr(&c, "[data-testid=fault]", "data-fault")
            .await
            .as_deref(),
        Some("moved")
    );
    let row = wait_text(
        &c,
        "[data-testid=moved-gates] tr[data-gate=N]",
        &format!("{moved_to:.2}"),
        10,
    )
    .await;
    assert!(
        row.contains(&format!("{left:.2}")) && row.contains("-50.00"),
        "N's row: {row}"
    );
    // Read-only until the token is entered: no accept button.
    wait_text(&c, "[data-testid=readonly]", "Read-only view", 10).await;
    assert!(c
        .find(fantoccini::Locator::Css("[data-testid=accept-positions]"))
        .await
        .is_err());
    type_into(&c, "[data-testid=token]", TOKEN).await;
    click(&c, "[data-testid=unlock]").await;
    wait_text(&c, "[data-testid=accept-positions]", "Accept positions", 10).await;
    screenshot(&c, "moved-fault").await;

    // Accept: the server's run is paused, nothing more iterated.
    click(&c, "[data-testid=accept-positions]").await;
    wait_text(&c, "[data-testid=run-status]", "paused", 20).await;
    let r = get_run(port, run);
    assert_eq!(r.status, RunStatus::Paused);
    assert_eq!(r.iterations, iterations);
    assert!(c
        .find(fantoccini::Locator::Css("[data-testid=moved-gates]"))
        .await
        .is_err());

    // Resume from the dashboard: the run continues from the accepted positions.
    click(&c, "[data-testid=resume]").await;
    wait_run(port, run, "iterations after accepting", 120, |r| {
        r.status == RunStatus::Running && r.iterations >= iterations + 2
    })
    .await;
    wait_text(&c, "[data-testid=run-status]", "running", 20).await;

    // The bridge stops answering first (the server may close its socket on stop).
    done.store(true, Ordering::Relaxed);
    bridge.join().expect("bridge thread");
    let (s, b) = control(port, run, r#"{"action":"stop"}"#);
    assert_eq!(s, 200, "{b}");
    let _ = c.close().await;
    let _ = std::fs::remove_dir_all(&tmp);
}
