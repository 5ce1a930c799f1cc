//! A scripted lab bridge client for the process-level tests: connect and
//! authenticate, take requests, answer them from a simulated device, and
//! check every request against the device's physical state.

use futures_util::{SinkExt, StreamExt};
use spintune::protocol::{
    BridgeClientMessage, BridgeServerMessage, Request, Response, PROTOCOL_VERSION,
};
use spintune::sim::SimulatedDevice;
use tokio_tungstenite::tungstenite::Message;

use super::{Ws, STEP, TOKEN};

pub async fn bridge_connect(addr: std::net::SocketAddr, id: u64) -> Ws {
    let url = format!("ws://{addr}/api/runs/{id}/bridge?protocol={PROTOCOL_VERSION}");
    let (ws, _) = tokio::time::timeout(STEP, tokio_tungstenite::connect_async(url))
        .await
        .expect("connect timed out")
        .expect("connect");
    ws
}

pub async fn next_bridge(ws: &mut Ws) -> BridgeServerMessage {
    loop {
        let m = tokio::time::timeout(STEP, ws.next())
            .await
            .expect("no bridge frame in time")
            .expect("socket closed")
            .expect("socket error");
        match m {
            Message::Text(t) => {
                return serde_json::from_str(t.as_str())
                    .unwrap_or_else(|e| panic!("bad bridge frame {t}: {e}"))
            }
            Message::Ping(_) | Message::Pong(_) => continue,
            other => panic!("unexpected frame {other:?}"),
        }
    }
}

pub async fn send_msg(ws: &mut Ws, msg: &BridgeClientMessage) {
    ws.send(Message::Text(serde_json::to_string(msg).unwrap().into()))
        .await
        .unwrap();
}

/// Connect and authenticate; panics unless `auth_ok` comes back.
pub async fn bridge(addr: std::net::SocketAddr, id: u64) -> Ws {
    let mut ws = bridge_connect(addr, id).await;
    match next_bridge(&mut ws).await {
        BridgeServerMessage::Hello { version, run } => {
            assert_eq!(version, PROTOCOL_VERSION);
            assert_eq!(run.id, id);
        }
        other => panic!("expected hello, got {other:?}"),
    }
    send_msg(
        &mut ws,
        &BridgeClientMessage::Auth {
            token: TOKEN.into(),
        },
    )
    .await;
    assert_eq!(next_bridge(&mut ws).await, BridgeServerMessage::AuthOk);
    ws
}

pub async fn next_any_request(ws: &mut Ws) -> (u64, Request) {
    match next_bridge(ws).await {
        BridgeServerMessage::Request { id, request, .. } => (id, request),
        other => panic!("expected a request, got {other:?}"),
    }
}

/// The next request that is not a read-back, answering read-backs from
/// `device` on the way (the run reads every gate on connect and resume, and
/// the swept gate after each sweep).
pub async fn next_request_reading(ws: &mut Ws, device: &mut SimulatedDevice) -> (u64, Request) {
    loop {
        let (id, req) = next_any_request(ws).await;
        if matches!(req, Request::ReadVoltages { .. }) {
            let resp = device.execute(&req);
            answer(ws, id, resp).await;
            continue;
        }
        return (id, req);
    }
}

pub async fn answer(ws: &mut Ws, id: u64, response: Response) {
    send_msg(ws, &BridgeClientMessage::Response { id, response }).await;
}

/// Serve `k` requests from `device`.
pub async fn serve(ws: &mut Ws, device: &mut SimulatedDevice, k: usize) {
    for _ in 0..k {
        let (id, req) = next_any_request(ws).await;
        let resp = device.execute(&req);
        answer(ws, id, resp).await;
    }
}

/// Checks one request against the physical state of the scripted lab device
/// (limits, and the step from where each gate really is). `Err` names the violation.
pub fn physical_violation(device: &SimulatedDevice, req: &Request) -> Option<String> {
    let gates = spintune::sim::default_gates();
    let spec = |g: &str| gates.iter().find(|s| s.name == g).cloned().unwrap();
    let check = |g: &str, v: f64, out: &mut Vec<String>| {
        let s = spec(g);
        let now = device.voltages_mv()[g];
        if v < s.min_mv || v > s.max_mv {
            out.push(format!("{g}: {v} mV outside its limits"));
        }
        if (v - now).abs() > s.max_step_mv + 1e-9 {
            out.push(format!(
                "{g}: physical step {} mV from {now} mV",
                (v - now).abs()
            ));
        }
    };
    let mut out = Vec::new();
    match req {
        Request::SetVoltages { voltages_mv } => {
            for (g, &v) in voltages_mv {
                check(g, v, &mut out);
            }
        }
        Request::Measure { scan } => {
            if let Some(s) = &scan.sweep {
                check(&s.gate, s.from_mv, &mut out);
            }
        }
        _ => {}
    }
    (!out.is_empty()).then(|| out.join("; "))
}

/// No request reaches the bridge for `ms`.
pub async fn silent_for(ws: &mut Ws, ms: u64) -> bool {
    loop {
        match tokio::time::timeout(std::time::Duration::from_millis(ms), next_bridge(ws)).await {
            Err(_) => return true,
            Ok(BridgeServerMessage::Request { .. }) => return false,
            Ok(_) => continue,
        }
    }
}

/// Wait until run `id` is faulted; its fault.
pub async fn faulted(addr: std::net::SocketAddr, id: u64) -> spintune::protocol::Fault {
    let r = super::wait_status(addr, id, |r| {
        matches!(r.status, spintune::protocol::RunStatus::Faulted { .. })
    })
    .await;
    match r.status {
        spintune::protocol::RunStatus::Faulted { fault } => fault,
        _ => unreachable!(),
    }
}

/// Serve requests with `serve` (which answers one request and notes what
/// it finds wrong with it) until run `id` has `iterations` committed or is
/// over; panics after 120 s.
pub async fn serve_until_with(
    ws: &mut Ws,
    addr: std::net::SocketAddr,
    id: u64,
    iterations: u64,
    mut serve: impl FnMut(&Request) -> Response,
) {
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(50));
    let done = tokio::time::timeout(std::time::Duration::from_secs(120), async {
        loop {
            tokio::select! {
                frame = next_bridge(ws) => {
                    if let BridgeServerMessage::Request { id, request, .. } = frame {
                        let resp = serve(&request);
                        answer(ws, id, resp).await;
                    }
                }
                _ = tick.tick() => {
                    let r = super::get_run(addr, id).await;
                    if r.iterations >= iterations || r.status.is_terminal() {
                        return;
                    }
                }
            }
        }
    })
    .await;
    assert!(
        done.is_ok(),
        "the run did not reach {iterations} iterations"
    );
}

/// Answer request `id` with `honest` (a read-back from the lab's device)
/// but `gate` reported at `lie_mv`; panics unless `honest` is a read-back
/// that holds `gate`.
pub async fn answer_lying(ws: &mut Ws, id: u64, honest: Response, gate: &str, lie_mv: f64) {
    let Response::VoltagesRead {
        mut voltages_mv,
        lab_seconds,
    } = honest
    else {
        panic!("not a read-back: {honest:?}")
    };
    assert!(voltages_mv.contains_key(gate), "{voltages_mv:?}");
    voltages_mv.insert(gate.into(), lie_mv);
    answer(
        ws,
        id,
        Response::VoltagesRead {
            voltages_mv,
            lab_seconds,
        },
    )
    .await;
}
