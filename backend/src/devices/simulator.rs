//! The embedded simulated double dot as a [`Device`].

use serde_json::Value;
use spintune::protocol::{Request, Response};
use spintune::sim::SimulatedDevice;

use super::{BoxFuture, Device};

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
}
