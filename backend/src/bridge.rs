//! The lab bridge: an external measurement script (e.g. QCoDeS in Python)
//! serves as a run's device over the WebSocket `/api/runs/{id}/bridge`.
//!
//! Wire protocol (JSON text frames, [`BridgeServerMessage`] /
//! [`BridgeClientMessage`]; see `docs/instruments.md` for examples):
//!
//! 1. server → `hello {version, run}`;
//! 2. client → `auth {token}` (the control token) within 10 s → `auth_ok`
//!    (wrong token or a run that does not use the bridge: `error`, socket closed);
//! 3. server → `request {id, request, timeout_s}`; client → `response {id, response}`,
//!    one at a time.
//!
//! Faults pause the run (status `failed` with the reason; the tuner keeps the
//! request and re-issues it on resume, so no data is lost):
//! * no bridge connected when a request is due;
//! * no answer within [`BridgeConfig::request_timeout_s`] (a later answer is refused);
//! * the bridge disconnecting while a request is outstanding;
//! * an answer of the wrong kind, or read-back voltages that differ from the
//!   request by more than [`BridgeConfig::readback_tolerance_mv`].
//!
//! A run paused by a bridge fault resumes by itself when a bridge
//! (re)connects and authenticates; other pauses need `resume`.
//! A newer bridge connection for the same run replaces the older one.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::{Message, Utf8Bytes, WebSocket};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::protocol::{
    BridgeClientMessage, BridgeServerMessage, Request, Response, PROTOCOL_VERSION,
};
use tokio::sync::{mpsc, oneshot, watch};

use crate::config::DriverKind;
use crate::device::{BoxFuture, Device};
use crate::server::{parse_strict, token_eq, AppState};

/// Time a freshly connected bridge has to authenticate, s.
pub const AUTH_TIMEOUT_S: u64 = 10;

/// `[bridge]` table of a run config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BridgeConfig {
    /// Wall-clock time the bridge has to answer one request, s (lab scans
    /// take up to minutes: paper supplement, SD 2-D scan 100 s).
    #[serde(default = "default_request_timeout_s")]
    pub request_timeout_s: f64,
    /// Largest accepted difference between a requested voltage and the one
    /// the bridge reports as applied, mV.
    #[serde(default = "default_readback_tolerance_mv")]
    pub readback_tolerance_mv: f64,
}

fn default_request_timeout_s() -> f64 {
    300.0
}
fn default_readback_tolerance_mv() -> f64 {
    0.05
}

impl Default for BridgeConfig {
    fn default() -> Self {
        Self {
            request_timeout_s: default_request_timeout_s(),
            readback_tolerance_mv: default_readback_tolerance_mv(),
        }
    }
}

impl BridgeConfig {
    /// Check the settings; `Err((field, message))`.
    pub fn validate(&self) -> Result<(), (String, String)> {
        if !(self.request_timeout_s.is_finite()
            && self.request_timeout_s > 0.0
            && self.request_timeout_s <= 86_400.0)
        {
            return Err((
                "request_timeout_s".into(),
                "must be a positive number of seconds (at most one day)".into(),
            ));
        }
        if !(self.readback_tolerance_mv.is_finite() && self.readback_tolerance_mv >= 0.0) {
            return Err((
                "readback_tolerance_mv".into(),
                "must be a non-negative number of mV".into(),
            ));
        }
        Ok(())
    }
}

struct Waiting {
    id: u64,
    generation: u64,
    reply: oneshot::Sender<Response>,
}

#[derive(Default)]
struct LinkInner {
    /// The connected bridge: its generation and its outgoing frames.
    conn: Option<(u64, mpsc::UnboundedSender<Utf8Bytes>)>,
    next_generation: u64,
    next_id: u64,
    waiting: Option<Waiting>,
}

/// The meeting point of one run's bridge socket (server side) and its
/// [`BridgeDevice`] (run task side). Outlives both.
pub struct BridgeLink {
    run: u64,
    inner: Mutex<LinkInner>,
    /// Generation of the connected bridge, 0 when none.
    connected: watch::Sender<u64>,
}

impl BridgeLink {
    /// A link for run `run`, with no bridge connected.
    pub fn new(run: u64) -> Arc<Self> {
        Arc::new(Self {
            run,
            inner: Mutex::new(LinkInner {
                next_generation: 1,
                next_id: 1,
                ..LinkInner::default()
            }),
            connected: watch::channel(0).0,
        })
    }

    fn inner(&self) -> std::sync::MutexGuard<'_, LinkInner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether a bridge is connected.
    pub fn is_connected(&self) -> bool {
        *self.connected.borrow() != 0
    }

    /// Register a newly authenticated bridge; an older one is replaced (its
    /// outgoing channel closes and its outstanding request fails). Returns the
    /// connection's generation and its outgoing frames.
    pub fn attach(&self) -> (u64, mpsc::UnboundedReceiver<Utf8Bytes>) {
        let (tx, rx) = mpsc::unbounded_channel();
        let generation = {
            let mut inner = self.inner();
            let generation = inner.next_generation;
            inner.next_generation += 1;
            inner.conn = Some((generation, tx));
            // A request outstanding on the old connection fails (the sender
            // is dropped) and is re-issued after the run resumes.
            inner.waiting = None;
            generation
        };
        self.connected.send_replace(generation);
        (generation, rx)
    }

    /// The bridge of generation `generation` went away.
    pub fn detach(&self, generation: u64) {
        let mut inner = self.inner();
        if inner.conn.as_ref().is_some_and(|(g, _)| *g == generation) {
            inner.conn = None;
            if inner
                .waiting
                .as_ref()
                .is_some_and(|w| w.generation == generation)
            {
                inner.waiting = None;
            }
            drop(inner);
            self.connected.send_replace(0);
        }
    }

    /// An answer from the bridge of generation `generation`.
    pub fn answer(&self, generation: u64, id: u64, response: Response) -> Result<(), String> {
        let mut inner = self.inner();
        match inner.waiting.take() {
            Some(w) if w.id == id && w.generation == generation => {
                // The run task may have given up in this very moment; then the
                // request is re-issued anyway.
                let _ = w.reply.send(response);
                Ok(())
            }
            other => {
                inner.waiting = other;
                Err(format!(
                    "request {id} is not outstanding (answered already, timed out, or sent to another connection); answer ignored"
                ))
            }
        }
    }

    /// Send `request` to the connected bridge.
    fn send(
        &self,
        request: &Request,
        timeout_s: f64,
    ) -> Result<(u64, oneshot::Receiver<Response>), String> {
        let mut inner = self.inner();
        let Some((generation, tx)) = inner.conn.clone() else {
            return Err(format!(
                "no lab bridge is connected to run {}: connect a bridge client to /api/runs/{}/bridge \
(e.g. examples/bridge_client.py); the run continues when it has authenticated",
                self.run, self.run
            ));
        };
        let id = inner.next_id;
        inner.next_id += 1;
        let text = serde_json::to_string(&BridgeServerMessage::Request {
            id,
            request: request.clone(),
            timeout_s,
        })
        .map_err(|e| format!("cannot serialize request: {e}"))?;
        let (reply, rx) = oneshot::channel();
        inner.waiting = Some(Waiting {
            id,
            generation,
            reply,
        });
        if tx.send(Utf8Bytes::from(text)).is_err() {
            inner.waiting = None;
            return Err(format!(
                "the lab bridge of run {} went away before request {id} could be sent",
                self.run
            ));
        }
        Ok((id, rx))
    }

    /// Forget request `id` (timed out).
    fn cancel(&self, id: u64) {
        let mut inner = self.inner();
        if inner.waiting.as_ref().is_some_and(|w| w.id == id) {
            inner.waiting = None;
        }
    }

    /// Resolves when a bridge connection newer than the present one (if any)
    /// is established: after a disconnect, the reconnection; after a timeout
    /// on a live connection, only a fresh connection.
    pub fn recovered(&self) -> BoxFuture<'static, ()> {
        let now = *self.connected.borrow();
        let mut rx = self.connected.subscribe();
        Box::pin(async move {
            if rx.wait_for(|g| *g != 0 && *g != now).await.is_err() {
                std::future::pending::<()>().await;
            }
        })
    }
}

fn describe(request: &Request) -> String {
    match request {
        Request::SetVoltages { voltages_mv } => {
            let gates: Vec<&str> = voltages_mv.keys().map(String::as_str).collect();
            format!("set_voltages {}", gates.join(","))
        }
        Request::Measure { scan } => format!("measure {:?}", scan.kind),
        Request::TrueJacobian { .. } => "true_jacobian".into(),
    }
}

/// Check that `response` answers `request` plausibly.
fn check_answer(request: &Request, response: Response, id: u64, tolerance_mv: f64) -> Response {
    let fault = |message: String| Response::Error {
        message: format!(
            "lab bridge, request {id} ({}): {message}",
            describe(request)
        ),
    };
    match (request, response) {
        (_, Response::Error { message }) => {
            fault(format!("the bridge reported an error: {message}"))
        }
        (
            Request::SetVoltages { voltages_mv: want },
            Response::VoltagesSet {
                voltages_mv: got,
                lab_seconds,
            },
        ) => {
            for (gate, &v) in want {
                match got.get(gate) {
                    None => {
                        return fault(format!(
                            "the answer lacks the read-back voltage of {gate}"
                        ))
                    }
                    Some(&r) if !r.is_finite() || (r - v).abs() > tolerance_mv => {
                        return fault(format!(
                            "read-back mismatch on {gate}: set {v:.6} mV, bridge reports {r} mV (tolerance {tolerance_mv} mV)"
                        ))
                    }
                    Some(_) => {}
                }
            }
            Response::VoltagesSet {
                voltages_mv: got,
                lab_seconds,
            }
        }
        (Request::Measure { .. }, r @ Response::Scanned { .. }) => r,
        (Request::TrueJacobian { .. }, r @ Response::TrueJacobian { .. }) => r,
        (_, other) => {
            let kind = serde_json::to_value(&other)
                .ok()
                .and_then(|v| v.get("response").and_then(Value::as_str).map(String::from))
                .unwrap_or_default();
            fault(format!(
                "answered with `{kind}`, which does not fit the request"
            ))
        }
    }
}

/// The run task's side of the bridge.
pub struct BridgeDevice {
    link: Arc<BridgeLink>,
    config: BridgeConfig,
}

impl BridgeDevice {
    /// A device talking through `link`.
    pub fn new(link: Arc<BridgeLink>, config: BridgeConfig) -> Self {
        Self { link, config }
    }

    async fn execute_inner(&mut self, request: Request) -> Response {
        let timeout = Duration::from_secs_f64(self.config.request_timeout_s);
        let (id, rx) = match self.link.send(&request, self.config.request_timeout_s) {
            Ok(x) => x,
            Err(message) => return Response::Error { message },
        };
        match tokio::time::timeout(timeout, rx).await {
            Ok(Ok(response)) => {
                check_answer(&request, response, id, self.config.readback_tolerance_mv)
            }
            Ok(Err(_)) => Response::Error {
                message: format!(
                    "the lab bridge disconnected while request {id} ({}) was outstanding; the run continues when a bridge reconnects",
                    describe(&request)
                ),
            },
            Err(_) => {
                self.link.cancel(id);
                Response::Error {
                    message: format!(
                        "the lab bridge did not answer request {id} ({}) within {} s; resume to re-issue it (or reconnect the bridge)",
                        describe(&request),
                        self.config.request_timeout_s
                    ),
                }
            }
        }
    }
}

impl Device for BridgeDevice {
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response> {
        Box::pin(self.execute_inner(request))
    }

    fn checkpoint(&self) -> Result<Value, serde_json::Error> {
        Ok(Value::Null)
    }

    fn driver(&self) -> DriverKind {
        DriverKind::Bridge
    }

    fn recovered(&self) -> BoxFuture<'static, ()> {
        self.link.recovered()
    }
}

fn frame(msg: &BridgeServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).expect("BridgeServerMessage serializes"),
    ))
}

fn error_frame(message: impl Into<String>) -> Message {
    frame(&BridgeServerMessage::Error {
        message: message.into(),
    })
}

/// Serve one bridge socket of run `id` (the handler of `/api/runs/{id}/bridge`).
pub async fn serve_socket(state: AppState, id: u64, mut socket: WebSocket) {
    let _ = serve(&state, id, &mut socket).await;
    let _ = socket.send(Message::Close(None)).await;
}

async fn serve(state: &AppState, id: u64, socket: &mut WebSocket) -> Result<(), axum::Error> {
    let Ok(handle) = state.manager.get(id) else {
        return socket
            .send(error_frame(format!("no run with id {id}")))
            .await;
    };
    socket
        .send(frame(&BridgeServerMessage::Hello {
            version: PROTOCOL_VERSION,
            run: handle.summary(),
        }))
        .await?;
    drop(handle);
    // Authentication first.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(AUTH_TIMEOUT_S);
    loop {
        let incoming = match tokio::time::timeout_at(deadline, socket.recv()).await {
            Err(_) => {
                return socket
                    .send(error_frame(format!(
                        "no auth frame within {AUTH_TIMEOUT_S} s; send {{\"type\":\"auth\",\"token\":\"…\"}} first"
                    )))
                    .await
            }
            Ok(None) => return Ok(()),
            Ok(Some(m)) => m?,
        };
        let text = match incoming {
            Message::Text(t) => t,
            Message::Close(_) => return Ok(()),
            Message::Ping(_) | Message::Pong(_) => continue,
            Message::Binary(_) => {
                return socket
                    .send(error_frame(
                        "binary frames are not supported; send JSON text",
                    ))
                    .await
            }
        };
        match parse_strict::<BridgeClientMessage>(text.as_str()) {
            Ok(BridgeClientMessage::Auth { token }) if token_eq(&token, &state.token) => break,
            Ok(BridgeClientMessage::Auth { .. }) => {
                return socket.send(error_frame("invalid control token")).await
            }
            Ok(BridgeClientMessage::Response { .. }) => return socket
                .send(error_frame(
                    "the bridge must authenticate first: send {\"type\":\"auth\",\"token\":\"…\"}",
                ))
                .await,
            Err(message) => return socket.send(error_frame(message)).await,
        }
    }
    let link = match state.manager.bridge_link(id) {
        Ok(l) => l,
        Err(e) => return socket.send(error_frame(e.to_string())).await,
    };
    socket.send(frame(&BridgeServerMessage::AuthOk)).await?;
    let (generation, mut outbox) = link.attach();
    let result = pump(&link, generation, &mut outbox, socket).await;
    link.detach(generation);
    result
}

async fn pump(
    link: &BridgeLink,
    generation: u64,
    outbox: &mut mpsc::UnboundedReceiver<Utf8Bytes>,
    socket: &mut WebSocket,
) -> Result<(), axum::Error> {
    loop {
        tokio::select! {
            out = outbox.recv() => match out {
                Some(text) => socket.send(Message::Text(text)).await?,
                None => {
                    return socket
                        .send(error_frame("replaced by a newer bridge connection for this run"))
                        .await;
                }
            },
            incoming = socket.recv() => {
                let Some(incoming) = incoming else { return Ok(()) };
                let reply = match incoming? {
                    Message::Text(text) => match parse_strict::<BridgeClientMessage>(text.as_str()) {
                        Ok(BridgeClientMessage::Response { id, response }) => {
                            link.answer(generation, id, response).err().map(error_frame)
                        }
                        Ok(BridgeClientMessage::Auth { .. }) => {
                            Some(frame(&BridgeServerMessage::AuthOk))
                        }
                        Err(message) => Some(error_frame(message)),
                    },
                    Message::Binary(_) => {
                        Some(error_frame("binary frames are not supported; send JSON text"))
                    }
                    Message::Close(_) => return Ok(()),
                    Message::Ping(_) | Message::Pong(_) => None,
                };
                if let Some(reply) = reply {
                    socket.send(reply).await?;
                }
            }
        }
    }
}

/// Per-run links, kept by the manager so that they outlive run tasks.
#[derive(Default)]
pub struct Links(Mutex<BTreeMap<u64, Arc<BridgeLink>>>);

impl Links {
    /// The link of run `id`, created on first use.
    pub fn get(&self, id: u64) -> Arc<BridgeLink> {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(id)
            .or_insert_with(|| BridgeLink::new(id))
            .clone()
    }

    /// Forget run `id`'s link (run deleted).
    pub fn remove(&self, id: u64) {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).remove(&id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use spintune::protocol::{ScanKind, ScanRequest};

    #[tokio::test]
    async fn request_answer_timeout_and_disconnect() {
        let link = BridgeLink::new(3);
        let cfg = BridgeConfig {
            request_timeout_s: 0.2,
            readback_tolerance_mv: 0.05,
        };
        let mut dev = BridgeDevice::new(link.clone(), cfg);
        let req = Request::SetVoltages {
            voltages_mv: BTreeMap::from([("SB".to_string(), -780.0)]),
        };
        // nobody connected
        let r = dev.execute(req.clone()).await;
        assert!(
            matches!(&r, Response::Error { message } if message.contains("no lab bridge")),
            "{r:?}"
        );
        // connect; the recovery future fires
        let rec = link.recovered();
        let (generation, mut out) = link.attach();
        tokio::time::timeout(Duration::from_secs(1), rec)
            .await
            .expect("recovered on connect");
        // answered correctly
        let l2 = link.clone();
        let answer = tokio::spawn(async move {
            let text = out.recv().await.unwrap();
            let msg: BridgeServerMessage = serde_json::from_str(text.as_str()).unwrap();
            let BridgeServerMessage::Request { id, .. } = msg else {
                panic!()
            };
            l2.answer(
                generation,
                id,
                Response::VoltagesSet {
                    voltages_mv: BTreeMap::from([("SB".to_string(), -780.01)]),
                    lab_seconds: 0.1,
                },
            )
            .unwrap();
            // a second answer to the same id is refused
            assert!(l2
                .answer(
                    generation,
                    id,
                    Response::Error {
                        message: "x".into()
                    }
                )
                .is_err());
            out
        });
        let r = dev.execute(req.clone()).await;
        assert!(matches!(r, Response::VoltagesSet { .. }), "{r:?}");
        let mut out = answer.await.unwrap();
        // unanswered → timeout; the late answer is refused
        let r = dev.execute(req.clone()).await;
        assert!(
            matches!(&r, Response::Error { message } if message.contains("did not answer")),
            "{r:?}"
        );
        let text = out.recv().await.unwrap();
        let BridgeServerMessage::Request { id, .. } = serde_json::from_str(text.as_str()).unwrap()
        else {
            panic!()
        };
        assert!(link
            .answer(
                generation,
                id,
                Response::VoltagesSet {
                    voltages_mv: BTreeMap::new(),
                    lab_seconds: 0.0
                }
            )
            .is_err());
        // a wrong kind of answer and a read-back mismatch are errors
        let measure = Request::Measure {
            scan: ScanRequest {
                kind: ScanKind::ReloadTime,
                sweep: None,
            },
        };
        let bad = check_answer(
            &measure,
            Response::VoltagesSet {
                voltages_mv: BTreeMap::new(),
                lab_seconds: 0.0,
            },
            9,
            0.05,
        );
        assert!(
            matches!(&bad, Response::Error { message } if message.contains("voltages_set")),
            "{bad:?}"
        );
        let bad = check_answer(
            &req,
            Response::VoltagesSet {
                voltages_mv: BTreeMap::from([("SB".to_string(), -781.0)]),
                lab_seconds: 0.0,
            },
            9,
            0.05,
        );
        assert!(
            matches!(&bad, Response::Error { message } if message.contains("mismatch")),
            "{bad:?}"
        );
        // disconnect while outstanding
        let l3 = link.clone();
        tokio::spawn(async move {
            let _ = out.recv().await;
            l3.detach(generation);
        });
        let r = dev.execute(req).await;
        assert!(
            matches!(&r, Response::Error { message } if message.contains("disconnected")),
            "{r:?}"
        );
        assert!(!link.is_connected());
    }
}
