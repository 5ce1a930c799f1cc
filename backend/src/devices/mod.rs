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

pub mod bridge;
pub mod scpi;
mod simulator;

pub use simulator::SimulatorDevice;

use crate::config::{DriverKind, RunConfig};
use bridge::{BridgeDevice, BridgeLink};
use scpi::{MeasureSource, ScpiDevice, ScpiSource};

/// A boxed, `Send` future (keeps [`Device`] usable as `Box<dyn Device>`).
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// An instrument (or simulator) a run drives.
pub trait Device: Send + Sync {
    /// Execute one request. Errors are reported as [`Response::Error`].
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response>;

    /// Serialized device state to store with each iteration; `Value::Null`
    /// for a device without restorable state (a real instrument).
    fn checkpoint(&self) -> Result<Value, serde_json::Error>;

    /// Which driver this is.
    fn driver(&self) -> DriverKind;

    /// After a fault ([`Response::Error`]) paused the run: resolves when the
    /// device may work again without a user's `resume` (the lab bridge
    /// reconnected). Called at the time of the fault. Default: never.
    fn recovered(&self) -> BoxFuture<'static, ()> {
        Box::pin(std::future::pending())
    }
}

/// Open the device of `config` from its checkpoint `state` (the simulator's
/// state for the simulator and for SCPI with simulated measurements; ignored
/// otherwise). `bridge` is the run's bridge link (needed when
/// [`crate::config::BackendSettings::uses_bridge`]).
pub fn open(
    config: &RunConfig,
    state: Value,
    bridge: Option<Arc<BridgeLink>>,
) -> Result<Box<dyn Device>, String> {
    let b = &config.backend;
    let bridge_device = || {
        bridge
            .clone()
            .map(|link| BridgeDevice::new(link, b.bridge.clone()))
            .ok_or_else(|| {
                "internal: the run uses the lab bridge but has no bridge link".to_string()
            })
    };
    match b.driver {
        DriverKind::Simulator => Ok(Box::new(
            SimulatorDevice::restore(state).map_err(|e| e.to_string())?,
        )),
        DriverKind::Bridge => Ok(Box::new(bridge_device()?)),
        DriverKind::Scpi => {
            let scpi = b
                .scpi
                .clone()
                .ok_or_else(|| "driver = \"scpi\" needs a [scpi] table".to_string())?;
            let measure = scpi.measure;
            let source = ScpiSource::new(scpi, &config.simulation.tuner.gates);
            match measure {
                MeasureSource::Simulator => Ok(Box::new(ScpiDevice::with_simulator(
                    source,
                    SimulatorDevice::restore(state).map_err(|e| e.to_string())?,
                ))),
                MeasureSource::Bridge => {
                    Ok(Box::new(ScpiDevice::with_bridge(source, bridge_device()?)))
                }
            }
        }
    }
}
