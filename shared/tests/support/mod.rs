//! What the world-side tests of the tuner's scan scheduling share: a run
//! session on a sealed simulated device, stepped one event at a time, with
//! the test in the driver's seat (it executes each request on the device,
//! may look at the world's truth around it or answer in the device's place).

#![allow(dead_code)] // each test file uses what it needs

pub mod array;

use spintune::driver::SimulationConfig;
use spintune::protocol::{ControlCommand, IterationRecord, Request, Response};
use spintune::session::{Output, RunSession, SessionConfig};
use spintune::sim::SimulatedDevice;
use spintune::tuner::Tuner;

/// The next thing the session wants from its driver.
pub enum Next {
    /// Execute this request and [`Lab::feed`] the answer.
    Request(Request),
    /// A top-level iteration was committed.
    Record(Box<IterationRecord>),
    /// The run finished.
    Done,
}

/// A recommended-config session on its simulated device (truth sealed).
pub struct Lab {
    pub session: RunSession,
    pub device: SimulatedDevice,
    seed: u64,
}

impl Lab {
    /// The recommended config on `seed` for at most `iterations`
    /// iterations, after `edit` (e.g. a level's option turned off).
    pub fn recommended(
        seed: u64,
        iterations: u64,
        edit: impl FnOnce(&mut SimulationConfig),
    ) -> Self {
        let mut cfg = SimulationConfig::recommended();
        cfg.seed = seed;
        cfg.tuner.max_iterations = Some(iterations);
        edit(&mut cfg);
        let mut device = cfg.simulated_device().unwrap();
        device.seal_truth();
        let session =
            RunSession::from_tuner(Tuner::new(cfg.tuner).unwrap(), SessionConfig::default());
        Self {
            session,
            device,
            seed,
        }
    }

    /// Poll until the session needs the driver (saves, frames and sleeps
    /// are nothing to a test); a run that stops waiting is a test failure.
    pub fn next(&mut self) -> Next {
        loop {
            match self.session.poll() {
                Output::Execute(request) => return Next::Request(request),
                Output::Commit(record) => return Next::Record(record),
                Output::Done(_) => return Next::Done,
                Output::Wait => panic!(
                    "seed {}: the run stopped: {:?}",
                    self.seed,
                    self.session.status()
                ),
                Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
            }
        }
    }

    /// The device's answer to `request`.
    pub fn execute(&mut self, request: &Request) -> Response {
        self.device.execute(request)
    }

    /// Hand the answer to the session.
    pub fn feed(&mut self, response: Response) {
        self.session.feed(response).unwrap();
    }

    /// New targets for t_sr (ns) and w (µV), as an operator sets them.
    pub fn set_targets(&mut self, t_sr_ns: f64, w_uv: f64) {
        for (p, t) in [("t_sr", t_sr_ns), ("w", w_uv)] {
            self.session
                .control(&ControlCommand::SetTarget {
                    parameter: p.into(),
                    target: Some(t),
                    tolerance: None,
                })
                .unwrap();
        }
    }
}

/// Arithmetic mean (NaN for no values).
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}
