//! The async device interface the run task drives the tuner through, and the
//! embedded simulator as its default implementation.
//!
//! A driver executes [`Request`]s and returns [`Response`]s; the run task has
//! already passed every `SetVoltages` through [`spintune::safety::SafetyLimits::check`]
//! before it reaches [`Device::execute`]. A driver that can be checkpointed
//! (the simulator: its RNG, drift and lab clock) returns its state from
//! [`Device::checkpoint`]; resuming from that state continues bit-identically.

use std::future::Future;
use std::pin::Pin;

use serde_json::Value;
use spintune::protocol::{Request, Response};
use spintune::sim::SimulatedDevice;

use crate::config::DriverKind;

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
}

/// The embedded simulated double dot.
pub struct SimulatorDevice {
    device: SimulatedDevice,
}

impl SimulatorDevice {
    /// Wrap a simulated device.
    pub fn new(device: SimulatedDevice) -> Self {
        Self { device }
    }

    /// Restore from a value produced by [`Device::checkpoint`].
    pub fn restore(state: Value) -> Result<Self, serde_json::Error> {
        Ok(Self {
            device: serde_json::from_value(state)?,
        })
    }
}

impl Device for SimulatorDevice {
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response> {
        // The simulator is synchronous and fast (it generates raw traces; the
        // tuner fits them): run it inline.
        let response = self.device.execute(&request);
        Box::pin(std::future::ready(response))
    }

    fn checkpoint(&self) -> Result<Value, serde_json::Error> {
        serde_json::to_value(&self.device)
    }

    fn driver(&self) -> DriverKind {
        DriverKind::Simulator
    }
}

/// Restore a device of kind `driver` from its checkpoint.
pub fn restore(driver: DriverKind, state: Value) -> Result<Box<dyn Device>, serde_json::Error> {
    match driver {
        DriverKind::Simulator => Ok(Box::new(SimulatorDevice::restore(state)?)),
    }
}
