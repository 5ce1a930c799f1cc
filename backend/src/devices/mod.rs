//! The async device interface a run task drives its run session through,
//! and the three drivers behind it.
//!
//! A driver executes [`Request`]s and returns [`Response`]s. Every request
//! has passed the run session's guard against the instrument's last
//! read-back before it reaches [`Device::execute`] (ARCHITECTURE.md,
//! invariant 5); a driver may check again (the SCPI driver does, against
//! its own read-back) but never relaxes. A driver that can be checkpointed
//! (the simulator: its RNG, drift and lab clock) returns its state from
//! [`Device::checkpoint`]; resuming from that state continues bit-identically.
//!
//! Drivers: [`SimulatorDevice`] (default), [`scpi::ScpiDevice`] (SCPI DC
//! source over TCP; measurements from the simulator or the bridge) and
//! [`bridge::BridgeDevice`] (an external lab script over WebSocket).
//! A driver reports faults as [`Response::Error`]: the run then pauses with
//! the message and keeps the request, which is re-issued on resume.

use std::future::Future;
use std::pin::Pin;

use serde_json::Value;
use spintune::protocol::{Request, Response};

use std::sync::Arc;

pub(crate) mod bridge;
mod driver_kind;
pub mod scpi;
mod simulator;

pub use driver_kind::DriverKind;
pub use simulator::SimulatorDevice;

use bridge::{BridgeDevice, BridgeLink};
use scpi::{MeasureSource, ScpiDevice, ScpiSource};
use spintune::safety::GateSpec;

/// Why a driver could not carry out a request (or could not be opened).
///
/// On the wire a device fault is a [`Response::Error`] whose message is this
/// error's text ([`DeviceError::into_response`]), prefixed by the driver
/// where it helps (`SCPI source 192.168.8.40:5025: …`). Every message says
/// whether anything was sent and what happens on resume.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeviceError {
    /// A safety check refused the request before anything was sent
    /// (`reason` names the gate and the limit).
    #[error("{0}; refused, nothing sent")]
    Refused(String),
    /// The gate has no instrument channel; refused before anything was sent.
    #[error("gate {gate:?} has no channel in `scpi.channels`; refused, nothing sent")]
    Unmapped {
        /// The gate.
        gate: String,
    },
    /// The driver has no open connection.
    #[error("not connected")]
    NotConnected,
    /// Opening the connection failed.
    #[error("cannot connect to {address}: {error}")]
    Connect {
        /// `host:port`.
        address: String,
        /// The operating system's reason.
        error: String,
    },
    /// An I/O operation failed; the connection was dropped.
    #[error("{what} failed: {error}")]
    Io {
        /// What was being done, e.g. ``sending `sour4:volt?` ``.
        what: String,
        /// Why it failed.
        error: String,
    },
    /// An operation did not complete in time; the connection was dropped.
    #[error("{what} timed out after {ms} ms")]
    Timeout {
        /// What was being done, e.g. `connecting to 10.0.0.2:5025`.
        what: String,
        /// The time allowed, ms.
        ms: u64,
    },
    /// The instrument did not answer a query in time; the connection was
    /// dropped (a late answer would desynchronise the line protocol).
    #[error("no answer to `{query}` within {ms} ms")]
    NoAnswer {
        /// The query.
        query: String,
        /// The time allowed, ms.
        ms: u64,
    },
    /// A message that does not fit the device protocol: an instrument's
    /// answer that is not a number (the connection was dropped), a request
    /// that cannot be encoded for the bridge.
    #[error("{0}")]
    Protocol(String),
    /// The instrument's read-back after a move differs from the target.
    #[error(
        "read-back mismatch on {gate} (channel {channel}): set {set_mv:.6} mV, instrument reads {read_mv:.6} mV \
(tolerance {tolerance_mv} mV); nothing was re-sent, the connection was dropped and every channel is re-read before the next command"
    )]
    ReadbackMismatch {
        /// The gate.
        gate: String,
        /// Its channel.
        channel: u32,
        /// The target, mV.
        set_mv: f64,
        /// What the instrument reads, mV.
        read_mv: f64,
        /// The accepted difference, mV.
        tolerance_mv: f64,
    },
    /// A gate leaks: the current its channel sources after a move exceeds
    /// `scpi.max_leakage_na` or the gate's `scpi.max_leakage_na_by_gate`
    /// (QDAC-II profile). The run pauses; nothing further is set.
    #[error(
        "leakage on {gate} (channel {channel}): {current_na:.3} nA exceeds {limit} = {max_na} nA after the move; nothing further was set (check the gate for a leak into the 2DEG before resuming)"
    )]
    Leakage {
        /// The gate.
        gate: String,
        /// Its channel.
        channel: u32,
        /// The current read, nA (absolute value).
        current_na: f64,
        /// The config key of the limit (`max_leakage_na` or
        /// `max_leakage_na_by_gate.GATE`).
        limit: String,
        /// The configured limit, nA.
        max_na: f64,
    },
    /// Sending one increment of a ramp failed: the instrument state is unknown.
    #[error(
        "{error} during increment {increment} of {increments} (gate {gate}, channel {channel}); the instrument state is unknown, \
the connection was dropped and the step was NOT re-sent; on resume the driver reconnects, reads every channel back and ramps from there"
    )]
    RampInterrupted {
        /// What failed.
        error: Box<DeviceError>,
        /// 1-based increment.
        increment: usize,
        /// Increments planned.
        increments: usize,
        /// The gate being set.
        gate: String,
        /// Its channel.
        channel: u32,
    },
    /// Reading a channel back after a move failed.
    #[error(
        "read-back after setting {gate} (channel {channel}) failed: {error}; the connection was dropped and nothing was re-sent"
    )]
    ReadbackFailed {
        /// The gate.
        gate: String,
        /// Its channel.
        channel: u32,
        /// What failed.
        error: Box<DeviceError>,
    },
    /// No lab bridge is connected to the run.
    #[error(
        "no lab bridge is connected to run {run}: connect a bridge client to /api/runs/{run}/bridge \
(e.g. examples/bridge_client.py); the run continues when it has authenticated"
    )]
    NoBridge {
        /// The run.
        run: u64,
    },
    /// The lab bridge disconnected while a request was outstanding.
    #[error(
        "the lab bridge disconnected while request {id} ({request}) was outstanding; the run continues when a bridge reconnects"
    )]
    BridgeDisconnected {
        /// Request id.
        id: u64,
        /// The request, briefly (`set_voltages SB,T`).
        request: String,
    },
    /// The lab bridge did not answer in time (a later answer is refused).
    #[error(
        "the lab bridge did not answer request {id} ({request}) within {timeout_s} s; resume to re-issue it (or reconnect the bridge)"
    )]
    BridgeTimeout {
        /// Request id.
        id: u64,
        /// The request, briefly.
        request: String,
        /// The time allowed, s.
        timeout_s: f64,
    },
    /// The lab bridge answered a request with an error of its own.
    #[error("lab bridge, request {id} ({request}): the bridge reported an error: {message}")]
    BridgeReported {
        /// Request id.
        id: u64,
        /// The request, briefly.
        request: String,
        /// The bridge's message.
        message: String,
    },
    /// An answer from the bridge to a request that is not outstanding.
    #[error(
        "request {id} is not outstanding (answered already, timed out, or sent to another connection); answer ignored"
    )]
    NotOutstanding {
        /// The id the answer named.
        id: u64,
    },
    /// The device cannot be opened (settings or checkpoint unusable).
    #[error("{0}")]
    Open(String),
}

impl DeviceError {
    /// Whether the device could not be reached (the lab bridge is absent,
    /// dropped or silent): the only errors whose fault may clear when the
    /// device reconnects (the fault policy, `FaultKind::cleared_by`). Every
    /// other error — leakage, a read-back mismatch, an instrument's I/O
    /// failure mid-ramp, a refusal — waits for a person.
    pub fn is_disconnection(&self) -> bool {
        matches!(
            self,
            DeviceError::NoBridge { .. }
                | DeviceError::BridgeDisconnected { .. }
                | DeviceError::BridgeTimeout { .. }
        )
    }

    /// The fault as the device's answer to a request.
    pub fn into_response(self) -> Response {
        if self.is_disconnection() {
            Response::disconnected(self.to_string())
        } else {
            Response::error(self.to_string())
        }
    }
}

/// A boxed, `Send` future (keeps [`Device`] usable as `Box<dyn Device>`).
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// An instrument (or simulator) a run drives.
pub trait Device: Send + Sync {
    /// Execute one request. Errors are reported as [`Response::Error`].
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response>;

    /// Serialized device state to store with each iteration; `Value::Null`
    /// for a device without restorable state (a real instrument).
    fn checkpoint(&self) -> Result<Value, serde_json::Error>;

    /// After a fault ([`Response::Error`]) paused the run: resolves when the
    /// device may work again without a user's `resume` (the lab bridge
    /// reconnected). Called at the time of the fault. Default: never.
    fn recovered(&self) -> BoxFuture<'static, ()> {
        Box::pin(std::future::pending())
    }
}

/// What [`open`] needs of a run config (the backend settings and the gates).
#[derive(Debug, Clone, Copy)]
pub struct DeviceSettings<'a> {
    /// The driver.
    pub driver: DriverKind,
    /// SCPI source settings (required for [`DriverKind::Scpi`]).
    pub scpi: Option<&'a scpi::ScpiConfig>,
    /// Lab bridge settings.
    pub bridge: &'a bridge::BridgeConfig,
    /// The gates with their limits.
    pub gates: &'a [GateSpec],
    /// The simulator's state is an array's.
    pub array: bool,
}

/// Open the device described by `settings` from its checkpoint `state` (the simulator's
/// state for the simulator and for SCPI with simulated measurements; ignored
/// otherwise). `bridge` is the run's bridge link (needed when
/// [`crate::config::BackendSettings::uses_bridge`]).
pub fn open(
    settings: DeviceSettings<'_>,
    state: Value,
    bridge: Option<Arc<BridgeLink>>,
) -> Result<Box<dyn Device>, DeviceError> {
    let b = settings;
    let bridge_device = || {
        bridge
            .clone()
            .map(|link| BridgeDevice::new(link, b.bridge.clone()))
            .ok_or_else(|| {
                DeviceError::Open(
                    "internal: the run uses the lab bridge but has no bridge link".into(),
                )
            })
    };
    let simulator = |state| {
        SimulatorDevice::restore(state, b.array).map_err(|e| {
            DeviceError::Open(format!(
                "cannot restore the simulated device from its checkpoint: {e}"
            ))
        })
    };
    match b.driver {
        DriverKind::Simulator => Ok(Box::new(simulator(state)?)),
        DriverKind::Bridge => Ok(Box::new(bridge_device()?)),
        DriverKind::Scpi => {
            let scpi = b.scpi.cloned().ok_or_else(|| {
                DeviceError::Open("driver = \"scpi\" needs a [scpi] table".into())
            })?;
            let measure = scpi.measure;
            let source = ScpiSource::new(scpi, b.gates);
            match measure {
                MeasureSource::Simulator => Ok(Box::new(ScpiDevice::with_simulator(
                    source,
                    simulator(state)?,
                ))),
                MeasureSource::Bridge => {
                    Ok(Box::new(ScpiDevice::with_bridge(source, bridge_device()?)))
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_say_what_failed_and_what_was_sent() {
        assert_eq!(
            DeviceError::Refused("SB: -1000 mV is outside its limits".into()).to_string(),
            "SB: -1000 mV is outside its limits; refused, nothing sent"
        );
        assert_eq!(
            DeviceError::Unmapped { gate: "T".into() }.to_string(),
            "gate \"T\" has no channel in `scpi.channels`; refused, nothing sent"
        );
        let timeout = DeviceError::Timeout {
            what: "sending `sour4:volt -0.780000`".into(),
            ms: 300,
        };
        assert_eq!(
            timeout.to_string(),
            "sending `sour4:volt -0.780000` timed out after 300 ms"
        );
        let e = DeviceError::RampInterrupted {
            error: Box::new(timeout),
            increment: 2,
            increments: 3,
            gate: "SB".into(),
            channel: 4,
        };
        let text = e.to_string();
        assert!(
            text.starts_with(
                "sending `sour4:volt -0.780000` timed out after 300 ms during increment 2 of 3 (gate SB, channel 4);"
            ),
            "{text}"
        );
        assert!(text.contains("NOT re-sent"), "{text}");
        let e = DeviceError::ReadbackFailed {
            gate: "SB".into(),
            channel: 4,
            error: Box::new(DeviceError::NoAnswer {
                query: "sour4:volt?".into(),
                ms: 300,
            }),
        };
        assert_eq!(
            e.to_string(),
            "read-back after setting SB (channel 4) failed: no answer to `sour4:volt?` within 300 ms; \
the connection was dropped and nothing was re-sent"
        );
        let e = DeviceError::ReadbackMismatch {
            gate: "SB".into(),
            channel: 4,
            set_mv: -779.0,
            read_mv: -776.0,
            tolerance_mv: 0.05,
        };
        assert!(
            e.to_string().starts_with(
                "read-back mismatch on SB (channel 4): set -779.000000 mV, instrument reads -776.000000 mV (tolerance 0.05 mV);"
            ),
            "{e}"
        );
    }

    #[test]
    fn bridge_faults_become_error_responses() {
        let e = DeviceError::NoBridge { run: 7 };
        assert!(e
            .to_string()
            .starts_with("no lab bridge is connected to run 7:"));
        assert!(e.to_string().contains("/api/runs/7/bridge"));
        let e = DeviceError::BridgeTimeout {
            id: 3,
            request: "measure ReloadTime".into(),
            timeout_s: 0.2,
        };
        assert_eq!(
            e.clone().into_response(),
            Response::disconnected(
                "the lab bridge did not answer request 3 (measure ReloadTime) within 0.2 s; \
resume to re-issue it (or reconnect the bridge)"
            )
        );
        assert!(DeviceError::NotOutstanding { id: 9 }
            .to_string()
            .starts_with("request 9 is not outstanding"));
    }
}
