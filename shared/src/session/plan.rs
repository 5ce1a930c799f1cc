//! [`Plan`]: what a [`super::RunSession`] drives — the single-cell
//! [`Tuner`] or an array's [`crate::tuner::array_run::ArrayRun`]. The
//! session owns the lifecycle and the guard (invariants 5 and 6); a plan
//! only decides the next request and takes its answer.

use std::collections::BTreeMap;

use crate::parameter::Tolerance;
use crate::protocol::Response;
use crate::safety::GateSpec;
use crate::tuner::{Action, Tuner, TunerError};

/// A sans-IO planner a run session can drive (invariant 2).
pub trait Plan {
    /// The next action; polling again without feeding re-issues the same
    /// request. `Err`: the plan cannot go on (the session faults the run).
    fn next_action(&mut self) -> Result<Action, String>;
    /// The answer to the request handed out last.
    fn take_response(&mut self, response: Response) -> Result<(), TunerError>;
    /// Every gate of the device with its limits (read on start and resume).
    fn gate_specs(&self) -> &[GateSpec];
    /// Lab time spent outside the plan's requests (the session's reads), s.
    fn charge_time(&mut self, seconds: f64);
    /// The instrument read back these voltages (mV): plan from them.
    fn adopt_voltages(&mut self, readback: &BTreeMap<String, f64>, tolerance_mv: f64);
    /// `Err` unless `parameter` may get this target and tolerance.
    fn check_target(
        &self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(), TunerError>;
    /// Apply a target change (validated with [`Plan::check_target`] first).
    fn change_target(
        &mut self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(), TunerError>;
    /// Whether the plan has nothing left to do (until a target changes).
    fn done(&self) -> bool;
}

impl Plan for Tuner {
    fn next_action(&mut self) -> Result<Action, String> {
        Ok(self.poll())
    }

    fn take_response(&mut self, response: Response) -> Result<(), TunerError> {
        self.feed(response)
    }

    fn gate_specs(&self) -> &[GateSpec] {
        &self.config().gates
    }

    fn charge_time(&mut self, seconds: f64) {
        self.charge_lab_time(seconds);
    }

    fn adopt_voltages(&mut self, readback: &BTreeMap<String, f64>, tolerance_mv: f64) {
        self.adopt_readback(readback, tolerance_mv);
    }

    fn check_target(
        &self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(), TunerError> {
        self.validate_target(parameter, target, tolerance)
            .map(|_| ())
    }

    fn change_target(
        &mut self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(), TunerError> {
        self.set_target(parameter, target, tolerance)
    }

    fn done(&self) -> bool {
        self.is_finished()
    }
}
