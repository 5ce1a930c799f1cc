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
//! Requests are `set_voltages`, `read_voltages` (answer `voltages_read` with
//! exactly the requested gates: the run asks on connect, on every resume and
//! after each sweep) and `measure`.
//!
//! Faults pause the run (status `faulted` with the reason; the tuner keeps the
//! request and re-issues it on resume, so no data is lost):
//! * no bridge connected when a request is due;
//! * no answer within [`BridgeConfig::request_timeout_s`] (a later answer is refused);
//! * the bridge disconnecting while a request is outstanding;
//! * (checked by the run session's guard) an answer of the wrong kind, or
//!   read-backs of gates that were not requested, missing or non-finite
//!   read-backs, or read-back voltages that differ from the request by more
//!   than [`BridgeConfig::readback_tolerance_mv`].
//!
//! A run paused by a bridge fault resumes by itself when a bridge
//! (re)connects and authenticates; other pauses need `resume`.
//! A newer bridge connection for the same run replaces the older one.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::protocol::{BridgeServerMessage, Request, Response, MAX_WAIT_SECONDS};
use spintune::ConfigError;
use tokio::sync::{mpsc, oneshot, watch};

use super::{BoxFuture, Device, DeviceError};

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
    /// Check the settings. The error's field is relative to the `[bridge]`
    /// table; a run config prefixes it with `bridge`.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.request_timeout_s.is_finite()
            && self.request_timeout_s > 0.0
            && self.request_timeout_s <= 86_400.0)
        {
            return Err(ConfigError::new(
                "request_timeout_s",
                format!(
                    "must be a positive number of seconds (at most one day), got {}",
                    self.request_timeout_s
                ),
            ));
        }
        let max = spintune::session::SessionConfig::MAX_READBACK_TOLERANCE_MV;
        if !(self.readback_tolerance_mv.is_finite()
            && self.readback_tolerance_mv >= 0.0
            && self.readback_tolerance_mv <= max)
        {
            return Err(ConfigError::new(
                "readback_tolerance_mv",
                format!(
                    "must be a non-negative number of mV, at most {max}, got {}",
                    self.readback_tolerance_mv
                ),
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
    pub fn answer(&self, generation: u64, id: u64, response: Response) -> Result<(), DeviceError> {
        let mut inner = self.inner();
        match inner.waiting.take() {
            Some(w) if w.id == id && w.generation == generation => {
                // The run task may have given up on the request (a stop, a
                // timeout): then nobody takes the answer, and the bridge is
                // told so (an `error` frame) rather than left believing it
                // was used. A request given up is re-issued if the run resumes.
                w.reply
                    .send(response)
                    .map_err(|_| DeviceError::NotOutstanding { id })
            }
            other => {
                inner.waiting = other;
                Err(DeviceError::NotOutstanding { id })
            }
        }
    }

    /// Send `request` to the connected bridge.
    fn send(
        &self,
        request: &Request,
        timeout_s: f64,
    ) -> Result<(u64, oneshot::Receiver<Response>), DeviceError> {
        let mut inner = self.inner();
        let Some((generation, tx)) = inner.conn.clone() else {
            return Err(DeviceError::NoBridge { run: self.run });
        };
        let id = inner.next_id;
        inner.next_id += 1;
        let text = serde_json::to_string(&BridgeServerMessage::Request {
            id,
            request: request.clone(),
            timeout_s,
        })
        .map_err(|e| DeviceError::Protocol(format!("cannot serialize request {id}: {e}")))?;
        let (reply, rx) = oneshot::channel();
        inner.waiting = Some(Waiting {
            id,
            generation,
            reply,
        });
        if tx.send(Utf8Bytes::from(text)).is_err() {
            inner.waiting = None;
            return Err(DeviceError::Io {
                what: format!("sending request {id} to the lab bridge of run {}", self.run),
                error: "the bridge went away".into(),
            });
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

    /// Generation of the connected bridge, 0 when none.
    pub fn connection(&self) -> u64 {
        *self.connected.borrow()
    }

    /// Resolves when a bridge connection other than `failed` (the generation
    /// a request failed on, 0 for none) is established: after a disconnect,
    /// the reconnection; after a timeout on a live connection, only a fresh
    /// connection. A connection made *before* this is called counts (it
    /// resolves at once): the wake-up is not lost if the bridge reconnects
    /// while the run task is still storing the fault.
    pub fn recovered_after(&self, failed: u64) -> BoxFuture<'static, ()> {
        let mut rx = self.connected.subscribe();
        Box::pin(async move {
            if rx.wait_for(|g| *g != 0 && *g != failed).await.is_err() {
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
        Request::ReadVoltages { gates } => format!("read_voltages {}", gates.join(",")),
        Request::TrueJacobian { .. } => "true_jacobian".into(),
        Request::Wait { seconds } => format!("wait {seconds} s"),
        Request::Batch { requests } => format!("batch of {}", requests.len()),
    }
}

/// Attribute a bridge error to the request. Whether an answer fits its
/// request, and whether its read-backs are believable, is checked by the
/// run session's guard (the one choke point), not here.
fn attribute(request: &Request, response: Response, id: u64) -> Response {
    match response {
        Response::Error { message, cause } => {
            let text = DeviceError::BridgeReported {
                id,
                request: describe(request),
                message,
            }
            .to_string();
            // The script says whether its instrument is unreachable (clears
            // on reconnect) or reported a problem (needs a person; the default).
            Response::Error {
                message: text,
                cause,
            }
        }
        other => other,
    }
}

/// The run task's side of the bridge.
pub struct BridgeDevice {
    link: Arc<BridgeLink>,
    config: BridgeConfig,
    /// Connection generation the last failed request was sent on (0: none).
    failed_connection: u64,
}

impl BridgeDevice {
    /// A device talking through `link`.
    pub fn new(link: Arc<BridgeLink>, config: BridgeConfig) -> Self {
        Self {
            link,
            config,
            failed_connection: 0,
        }
    }

    async fn execute_inner(&mut self, request: Request) -> Response {
        if let Request::Wait { seconds } = request {
            // Lab time passes in the lab: the server waits itself (the run
            // task abandons the wait on stop); nothing reaches the bridge.
            let start = tokio::time::Instant::now();
            tokio::time::sleep(Duration::from_secs_f64(
                seconds.clamp(0.0, MAX_WAIT_SECONDS),
            ))
            .await;
            return Response::Waited {
                lab_seconds: start.elapsed().as_secs_f64(),
            };
        }
        let at_send = self.link.connection();
        let response = self.exchange(request).await;
        if matches!(response, Response::Error { .. }) {
            self.failed_connection = at_send;
        }
        response
    }

    async fn exchange(&mut self, request: Request) -> Response {
        let timeout = Duration::from_secs_f64(self.config.request_timeout_s);
        let (id, rx) = match self.link.send(&request, self.config.request_timeout_s) {
            Ok(x) => x,
            Err(e) => return e.into_response(),
        };
        match tokio::time::timeout(timeout, rx).await {
            Ok(Ok(response)) => attribute(&request, response, id),
            Ok(Err(_)) => DeviceError::BridgeDisconnected {
                id,
                request: describe(&request),
            }
            .into_response(),
            Err(_) => {
                self.link.cancel(id);
                DeviceError::BridgeTimeout {
                    id,
                    request: describe(&request),
                    timeout_s: self.config.request_timeout_s,
                }
                .into_response()
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

    fn recovered(&self) -> BoxFuture<'static, ()> {
        self.link.recovered_after(self.failed_connection)
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
            matches!(&r, Response::Error { message, .. } if message.contains("no lab bridge")),
            "{r:?}"
        );
        // connect; the recovery future fires
        let rec = link.recovered_after(0);
        let (generation, mut out) = link.attach();
        tokio::time::timeout(Duration::from_secs(1), rec)
            .await
            .expect("recovered on connect");
        // a bridge that connected before the run task waits (while it was
        // storing the fault) still wakes it: no lost wake-up
        tokio::time::timeout(Duration::from_secs(1), dev.recovered())
            .await
            .expect("a connection made before the wait counts");
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
            assert_eq!(
                l2.answer(generation, id, Response::error("x")),
                Err(DeviceError::NotOutstanding { id })
            );
            out
        });
        let r = dev.execute(req.clone()).await;
        assert!(matches!(r, Response::VoltagesSet { .. }), "{r:?}");
        let mut out = answer.await.unwrap();
        // unanswered → timeout; the late answer is refused
        let r = dev.execute(req.clone()).await;
        assert!(
            matches!(&r, Response::Error { message, .. } if message.contains("did not answer")),
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
        // (whether an answer fits and its read-backs are believable is the
        // session guard's job: see spintune::session::guard)
        // disconnect while outstanding
        let l3 = link.clone();
        tokio::spawn(async move {
            let _ = out.recv().await;
            l3.detach(generation);
        });
        let r = dev.execute(req).await;
        assert!(
            matches!(&r, Response::Error { message, .. } if message.contains("disconnected")),
            "{r:?}"
        );
        assert!(!link.is_connected());
    }
}
