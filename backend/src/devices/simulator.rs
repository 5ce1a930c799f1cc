//! The embedded simulator as a [`Device`]: one simulated double dot, or a
//! simulated array of them (which answers `batch` requests, its readout
//! groups in parallel).

use serde_json::Value;
use spintune::protocol::{Request, Response};
use spintune::sim::array::ArrayDevice;
use spintune::sim::SimulatedDevice;

use super::{BoxFuture, Device};

/// The embedded simulator.
pub struct SimulatorDevice {
    device: Simulated,
}

enum Simulated {
    Cell(Box<SimulatedDevice>),
    Array(Box<ArrayDevice>),
}

impl SimulatorDevice {
    /// Wrap a simulated double dot.
    pub fn new(device: SimulatedDevice) -> Self {
        Self {
            device: Simulated::Cell(Box::new(device)),
        }
    }

    /// Wrap a simulated array.
    pub fn array(device: ArrayDevice) -> Self {
        Self {
            device: Simulated::Array(Box::new(device)),
        }
    }

    /// Restore from a value produced by [`Device::checkpoint`] (`array`:
    /// the state is an array's).
    pub fn restore(state: Value, array: bool) -> Result<Self, serde_json::Error> {
        Ok(if array {
            Self::array(serde_json::from_value(state)?)
        } else {
            Self::new(serde_json::from_value(state)?)
        })
    }
}

impl Device for SimulatorDevice {
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response> {
        // The simulator is synchronous and fast (it generates raw traces; the
        // tuner fits them): run it inline.
        let response = match &mut self.device {
            Simulated::Cell(d) => d.execute(&request),
            Simulated::Array(d) => d.execute(&request),
        };
        Box::pin(std::future::ready(response))
    }

    fn checkpoint(&self) -> Result<Value, serde_json::Error> {
        match &self.device {
            Simulated::Cell(d) => serde_json::to_value(d),
            Simulated::Array(d) => serde_json::to_value(d),
        }
    }
}
