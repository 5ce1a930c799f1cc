//! [`ScpiDevice`]: a run's device when `driver = "scpi"`: the gates through
//! the SCPI source, the measurements from the simulator or the lab bridge
//! (`scpi.measure`).

use std::time::Instant;

use serde_json::Value;
use spintune::protocol::{Request, Response};

use super::source::ScpiSource;
use crate::devices::bridge::BridgeDevice;
use crate::devices::{BoxFuture, Device, DeviceError, SimulatorDevice};

/// The measurement half of a SCPI run.
enum Measurer {
    Simulator(Box<SimulatorDevice>),
    Bridge(BridgeDevice),
}

/// A SCPI DC source for the gates plus a measurement device ([`MeasureSource`]).
pub struct ScpiDevice {
    source: ScpiSource,
    measurer: Measurer,
}

impl ScpiDevice {
    /// Gates through `source`, measurements from the simulator (whose state is
    /// the device checkpoint).
    pub fn with_simulator(source: ScpiSource, simulator: SimulatorDevice) -> Self {
        Self {
            source,
            measurer: Measurer::Simulator(Box::new(simulator)),
        }
    }

    /// Gates through `source`, measurements from the lab bridge.
    pub fn with_bridge(source: ScpiSource, bridge: BridgeDevice) -> Self {
        Self {
            source,
            measurer: Measurer::Bridge(bridge),
        }
    }

    /// A fault of the DC source as the device's answer, naming the source.
    fn source_fault(&self, e: DeviceError) -> Response {
        Response::error(format!("SCPI source {}: {e}", self.source.config().address))
    }

    async fn execute_inner(&mut self, request: Request) -> Response {
        match request {
            Request::SetVoltages { voltages_mv } => {
                let start = Instant::now();
                match self.source.set(&voltages_mv).await {
                    Ok(readback) => {
                        if let Measurer::Simulator(sim) = &mut self.measurer {
                            // The simulated device follows the real voltages.
                            if let Response::Error { message, .. } = sim
                                .execute(Request::SetVoltages {
                                    voltages_mv: readback.clone(),
                                })
                                .await
                            {
                                return Response::error(format!(
                                    "simulator refused the read-back voltages: {message}"
                                ));
                            }
                        }
                        Response::VoltagesSet {
                            voltages_mv: readback,
                            lab_seconds: start.elapsed().as_secs_f64(),
                        }
                    }
                    Err(e) => self.source_fault(e),
                }
            }
            Request::ReadVoltages { gates } => {
                // Mapped gates are read from the source; any other gate (not
                // settable through SCPI) from the measuring side.
                let start = Instant::now();
                let (mapped, other): (Vec<String>, Vec<String>) = gates
                    .into_iter()
                    .partition(|g| self.source.config().channels.contains_key(g));
                let mut voltages_mv = match self.source.read(&mapped).await {
                    Ok(v) => v,
                    Err(e) => return self.source_fault(e),
                };
                if !other.is_empty() {
                    let request = Request::ReadVoltages { gates: other };
                    let answer = match &mut self.measurer {
                        Measurer::Simulator(sim) => sim.execute(request).await,
                        Measurer::Bridge(bridge) => bridge.execute(request).await,
                    };
                    match answer {
                        Response::VoltagesRead { voltages_mv: v, .. } => voltages_mv.extend(v),
                        other => return other,
                    }
                }
                Response::VoltagesRead {
                    voltages_mv,
                    lab_seconds: start.elapsed().as_secs_f64(),
                }
            }
            other => match &mut self.measurer {
                Measurer::Simulator(sim) => sim.execute(other).await,
                Measurer::Bridge(bridge) => bridge.execute(other).await,
            },
        }
    }
}

impl Device for ScpiDevice {
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response> {
        Box::pin(self.execute_inner(request))
    }

    fn checkpoint(&self) -> Result<Value, serde_json::Error> {
        match &self.measurer {
            Measurer::Simulator(sim) => sim.checkpoint(),
            Measurer::Bridge(_) => Ok(Value::Null),
        }
    }

    fn recovered(&self) -> BoxFuture<'static, ()> {
        match &self.measurer {
            Measurer::Bridge(b) => b.recovered(),
            Measurer::Simulator(_) => Box::pin(std::future::pending()),
        }
    }
}
