//! [`Ramp`]: bring every gate from where the instrument says it is to a
//! working point, in steps within the limits, before a run starts (e.g. from
//! a DAC's reset state, 0 V, into the tuning window).
//!
//! A sans-IO loop like [`super::RunSession`], through the same choke point
//! ([`Guard`], invariant 5): it reads every gate first, then sets all gates
//! together along straight lines, each set checked by [`Guard::check`]
//! against the last **read-back** (limits, `max_step_mv`), each answer by
//! [`Guard::accept_set`] (exactly the requested gates, within the read-back
//! tolerance). The next step is always planned from the read-back, never
//! from the plan. A refused answer, a device error or a read-back outside
//! the limits ends the ramp with a [`RampError`]; nothing more is sent.
//!
//! The limits given to a ramp are the range a gate may *travel* through
//! (e.g. the instrument's or the sample's safe range), which usually is
//! wider than the tuning window; the target must lie inside them. All
//! voltages in mV.
//!
//! ```
//! use std::collections::BTreeMap;
//! use spintune::protocol::{Request, Response};
//! use spintune::safety::GateSpec;
//! use spintune::session::ramp::{Ramp, RampOutput};
//!
//! let gates = [GateSpec { name: "SD1".into(), min_mv: -1000.0, max_mv: 0.0, max_step_mv: 30.0, initial_mv: -600.0 }];
//! let target = BTreeMap::from([("SD1".to_string(), -600.0)]);
//! let mut ramp = Ramp::new(&gates, &target, 0.05).unwrap();
//! let mut dac = 0.0; // the instrument, reset to 0 mV
//! let mut sets = 0;
//! loop {
//!     match ramp.poll().unwrap() {
//!         RampOutput::Execute(Request::ReadVoltages { .. }) => ramp
//!             .feed(Response::VoltagesRead { voltages_mv: BTreeMap::from([("SD1".into(), dac)]), lab_seconds: 0.0 })
//!             .unwrap(),
//!         RampOutput::Execute(Request::SetVoltages { voltages_mv }) => {
//!             assert!((voltages_mv["SD1"] - dac).abs() <= 30.0); // one step at most
//!             dac = voltages_mv["SD1"];
//!             sets += 1;
//!             ramp.feed(Response::VoltagesSet { voltages_mv, lab_seconds: 0.0 }).unwrap();
//!         }
//!         RampOutput::Execute(_) => unreachable!(),
//!         RampOutput::Done => break,
//!     }
//! }
//! assert_eq!((dac, sets), (-600.0, 20));
//! ```

use std::collections::BTreeMap;

use crate::protocol::{Request, Response};
use crate::safety::{GateSpec, SafetyError, SafetyLimits};

use super::guard::{Guard, ReadbackError};

/// What the driver of a [`Ramp`] must do next.
#[derive(Debug, Clone, PartialEq)]
pub enum RampOutput {
    /// Execute this request on the instrument and [`Ramp::feed`] the answer
    /// (a read of every gate first, then sets; each passed the guard).
    Execute(Request),
    /// Every gate is at its target (within the read-back tolerance).
    Done,
}

/// Why a ramp was refused or ended. Nothing is sent after it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RampError {
    /// A target names a gate without limits.
    #[error("gate {0}: not a gate of the ramp (no limits given)")]
    UnknownGate(String),
    /// A target is not a finite number or lies outside the gate's limits.
    #[error("gate {gate}: target {target_mv} mV is outside [{min_mv}, {max_mv}] mV")]
    TargetOutside {
        /// Gate name.
        gate: String,
        /// Requested target, mV.
        target_mv: f64,
        /// Lower limit, mV.
        min_mv: f64,
        /// Upper limit, mV.
        max_mv: f64,
    },
    /// A gate reads outside the range a ramp may travel: it cannot be
    /// stepped from there without leaving the limits.
    #[error("{gate} reads {read_mv} mV, outside [{min_mv}, {max_mv}] mV (the range it may be ramped through); nothing was moved: bring it inside by hand")]
    ReadOutside {
        /// Gate name.
        gate: String,
        /// Read-back, mV.
        read_mv: f64,
        /// Lower limit, mV.
        min_mv: f64,
        /// Upper limit, mV.
        max_mv: f64,
    },
    /// The instrument's answer was refused by the guard.
    #[error("read-back refused: {0}")]
    Readback(ReadbackError),
    /// A set the ramp planned was refused by the guard (a bug, never sent).
    #[error("step refused by the safety guard: {0}")]
    Refused(SafetyError),
    /// The instrument reported an error, or answered with the wrong kind.
    #[error("the instrument failed: {0}")]
    Device(String),
    /// The ramp did not arrive within its bound of steps.
    #[error("no arrival after {0} steps (the read-backs do not approach the target)")]
    NoProgress(usize),
    /// `feed` without an outstanding request.
    #[error("no request is outstanding")]
    NothingOutstanding,
}

#[derive(Debug, Clone, PartialEq)]
enum State {
    Read,
    Step,
    InFlight(Request),
    Done,
    Failed(RampError),
}

/// A ramp of several gates to a target (see the module docs).
#[derive(Debug, Clone)]
pub struct Ramp {
    guard: Guard,
    target_mv: BTreeMap<String, f64>,
    tolerance_mv: f64,
    state: State,
    steps_done: usize,
    max_steps: usize,
}

impl Ramp {
    /// A ramp of the gates in `target_mv` (gate → mV) within `gates`' limits
    /// (`min_mv`, `max_mv`, `max_step_mv`; `initial_mv` is not used).
    /// `readback_tolerance_mv`: largest accepted |read-back − set value|, mV.
    pub fn new(
        gates: &[GateSpec],
        target_mv: &BTreeMap<String, f64>,
        readback_tolerance_mv: f64,
    ) -> Result<Self, RampError> {
        let limits = SafetyLimits::new(gates);
        let mut max_steps = 1usize;
        for (gate, &t) in target_mv {
            let spec = limits
                .gate(gate)
                .ok_or_else(|| RampError::UnknownGate(gate.clone()))?;
            if !(t.is_finite() && spec.min_mv <= t && t <= spec.max_mv) {
                return Err(RampError::TargetOutside {
                    gate: gate.clone(),
                    target_mv: t,
                    min_mv: spec.min_mv,
                    max_mv: spec.max_mv,
                });
            }
            // the longest possible ramp of this gate, plus slack for read-backs
            let span = (spec.max_mv - spec.min_mv) / spec.max_step_mv.max(1e-9);
            max_steps = max_steps.max(span.ceil().min(1e7) as usize * 2 + 10);
        }
        let tolerance_mv = if readback_tolerance_mv.is_finite() {
            readback_tolerance_mv.max(0.0)
        } else {
            0.0
        };
        Ok(Self {
            guard: Guard::new(limits, tolerance_mv, f64::INFINITY),
            target_mv: target_mv.clone(),
            tolerance_mv,
            state: State::Read,
            steps_done: 0,
            max_steps,
        })
    }

    /// The next request, or [`RampOutput::Done`]; `Err` once the ramp failed.
    /// Polling again without feeding returns the same request.
    pub fn poll(&mut self) -> Result<RampOutput, RampError> {
        match &self.state {
            State::Done => return Ok(RampOutput::Done),
            State::Failed(e) => return Err(e.clone()),
            State::InFlight(r) => return Ok(RampOutput::Execute(r.clone())),
            State::Read => {
                let request = Request::ReadVoltages {
                    gates: self.target_mv.keys().cloned().collect(),
                };
                return self.issue(request);
            }
            State::Step => {}
        }
        let remaining = self.remaining_steps();
        if remaining == 0 {
            self.state = State::Done;
            return Ok(RampOutput::Done);
        }
        if self.steps_done >= self.max_steps {
            return self.fail(RampError::NoProgress(self.steps_done));
        }
        let readback = self.guard.readback_mv();
        let mut set = BTreeMap::new();
        for (gate, &t) in &self.target_mv {
            let now = readback[gate];
            if (t - now).abs() > self.tolerance_mv {
                let next = if remaining == 1 {
                    t
                } else {
                    now + (t - now) / remaining as f64
                };
                set.insert(gate.clone(), next);
            }
        }
        self.issue(Request::SetVoltages { voltages_mv: set })
    }

    fn issue(&mut self, request: Request) -> Result<RampOutput, RampError> {
        if let Err(e) = self.guard.check(&request) {
            return self.fail(RampError::Refused(e));
        }
        self.state = State::InFlight(request.clone());
        Ok(RampOutput::Execute(request))
    }

    fn fail<T>(&mut self, e: RampError) -> Result<T, RampError> {
        self.state = State::Failed(e.clone());
        Err(e)
    }

    /// Sets still needed from the present read-backs: the largest
    /// ⌈|target − read-back| / max_step⌉ over the gates not yet within the
    /// read-back tolerance (0: arrived).
    fn remaining_steps(&self) -> usize {
        let readback = self.guard.readback_mv();
        self.target_mv
            .iter()
            .filter_map(|(gate, &t)| {
                let d = (t - readback[gate]).abs();
                let step = self.guard.limits().gate(gate)?.max_step_mv;
                (d > self.tolerance_mv).then(|| ((d / step) * (1.0 - 1e-12)).ceil().max(1.0))
            })
            .fold(0.0f64, f64::max) as usize
    }

    /// The instrument's answer to the outstanding request. `Err` ends the
    /// ramp (nothing more is sent).
    pub fn feed(&mut self, response: Response) -> Result<(), RampError> {
        let request = match std::mem::replace(&mut self.state, State::Step) {
            State::InFlight(r) => r,
            other => {
                self.state = other;
                return Err(RampError::NothingOutstanding);
            }
        };
        let result = match (&request, response) {
            (Request::ReadVoltages { gates }, Response::VoltagesRead { voltages_mv, .. }) => self
                .guard
                .accept_read(gates, &voltages_mv)
                .map_err(|e| match e {
                    ReadbackError::OutOfLimits {
                        gate,
                        value_mv,
                        min_mv,
                        max_mv,
                    } => RampError::ReadOutside {
                        gate,
                        read_mv: value_mv,
                        min_mv,
                        max_mv,
                    },
                    other => RampError::Readback(other),
                }),
            (
                Request::SetVoltages { voltages_mv: set },
                Response::VoltagesSet { voltages_mv, .. },
            ) => {
                self.steps_done += 1;
                self.guard
                    .accept_set(set, &voltages_mv)
                    .map_err(RampError::Readback)
            }
            (_, Response::Error { message, .. }) => Err(RampError::Device(message)),
            (_, other) => Err(RampError::Device(format!(
                "an answer of the wrong kind: {}",
                serde_json::to_string(&other).unwrap_or_default()
            ))),
        };
        match result {
            Ok(()) => Ok(()),
            Err(e) => self.fail(e),
        }
    }

    /// Sets sent so far.
    pub fn steps_done(&self) -> usize {
        self.steps_done
    }

    /// Sets planned in all: those sent plus those still needed from the
    /// present read-backs (known after the first read).
    pub fn steps_planned(&self) -> Option<usize> {
        let known = self
            .target_mv
            .keys()
            .all(|g| self.guard.readback_mv().contains_key(g));
        let in_flight = matches!(self.state, State::InFlight(Request::SetVoltages { .. }));
        known.then(|| self.steps_done + usize::from(in_flight) + self.remaining_steps())
    }

    /// The last accepted read-backs, gate → mV.
    pub fn readback_mv(&self) -> &BTreeMap<String, f64> {
        self.guard.readback_mv()
    }

    /// The target, gate → mV.
    pub fn target_mv(&self) -> &BTreeMap<String, f64> {
        &self.target_mv
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(name: &str, max_step_mv: f64) -> GateSpec {
        GateSpec {
            name: name.into(),
            min_mv: -1000.0,
            max_mv: 100.0,
            max_step_mv,
            initial_mv: 0.0,
        }
    }

    /// Drive a ramp against an instrument that adds `offset` to every read-back.
    fn drive(
        ramp: &mut Ramp,
        dac: &mut BTreeMap<String, f64>,
        offset: f64,
    ) -> Result<usize, RampError> {
        let mut sets = 0;
        loop {
            match ramp.poll()? {
                RampOutput::Done => return Ok(sets),
                RampOutput::Execute(Request::ReadVoltages { gates }) => {
                    let v = gates.iter().map(|g| (g.clone(), dac[g])).collect();
                    ramp.feed(Response::VoltagesRead {
                        voltages_mv: v,
                        lab_seconds: 0.0,
                    })?;
                }
                RampOutput::Execute(Request::SetVoltages { voltages_mv }) => {
                    for (g, &v) in &voltages_mv {
                        let step = (v - dac[g]).abs();
                        let max = ramp.guard.limits().gate(g).unwrap().max_step_mv;
                        assert!(step <= max + 1e-9, "{g}: step {step} > {max}");
                        dac.insert(g.clone(), v + offset);
                    }
                    sets += 1;
                    let back = voltages_mv.keys().map(|g| (g.clone(), dac[g])).collect();
                    ramp.feed(Response::VoltagesSet {
                        voltages_mv: back,
                        lab_seconds: 0.0,
                    })?;
                }
                RampOutput::Execute(other) => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn all_gates_move_together_within_their_steps() {
        let gates = [spec("A", 10.0), spec("B", 30.0)];
        let target = BTreeMap::from([("A".to_string(), -95.0), ("B".to_string(), -600.0)]);
        let mut ramp = Ramp::new(&gates, &target, 0.05).unwrap();
        let mut dac = BTreeMap::from([("A".to_string(), 0.0), ("B".to_string(), 0.0)]);
        assert_eq!(ramp.steps_planned(), None);
        let sets = drive(&mut ramp, &mut dac, 0.0).unwrap();
        assert_eq!(sets, 20); // B needs 600/30 = 20, A rides along
        assert_eq!(dac["A"], -95.0);
        assert_eq!(dac["B"], -600.0);
        assert_eq!(ramp.steps_planned(), Some(20));
    }

    #[test]
    fn read_back_noise_never_makes_a_step_too_long() {
        let gates = [spec("A", 10.0)];
        let target = BTreeMap::from([("A".to_string(), -500.0)]);
        let mut ramp = Ramp::new(&gates, &target, 0.05).unwrap();
        let mut dac = BTreeMap::from([("A".to_string(), 0.0)]);
        // every set lands 0.04 mV off: the next step is planned from there
        drive(&mut ramp, &mut dac, 0.04).unwrap();
        assert!((dac["A"] + 500.0).abs() <= 0.05);
    }

    #[test]
    fn refusals_name_gate_read_back_and_range() {
        let gates = [spec("SD1", 30.0)];
        let target = BTreeMap::from([("SD1".to_string(), -600.0)]);
        let mut ramp = Ramp::new(&gates, &target, 0.05).unwrap();
        let mut dac = BTreeMap::from([("SD1".to_string(), 500.0)]);
        let e = drive(&mut ramp, &mut dac, 0.0).unwrap_err().to_string();
        assert!(
            e.starts_with("SD1 reads 500 mV, outside [-1000, 100] mV"),
            "{e}"
        );
        assert!(matches!(ramp.poll(), Err(RampError::ReadOutside { .. })));
        let e = Ramp::new(&gates, &BTreeMap::from([("SD1".to_string(), 200.0)]), 0.05).unwrap_err();
        assert!(matches!(e, RampError::TargetOutside { .. }), "{e}");
        let e = Ramp::new(&gates, &BTreeMap::from([("X".to_string(), 0.0)]), 0.05).unwrap_err();
        assert_eq!(e, RampError::UnknownGate("X".into()));
    }

    #[test]
    fn a_lying_set_answer_ends_the_ramp() {
        let gates = [spec("A", 10.0)];
        let target = BTreeMap::from([("A".to_string(), -100.0)]);
        let mut ramp = Ramp::new(&gates, &target, 0.05).unwrap();
        let mut dac = BTreeMap::from([("A".to_string(), 0.0)]);
        let e = drive(&mut ramp, &mut dac, 1.0).unwrap_err();
        assert!(
            matches!(e, RampError::Readback(ReadbackError::Mismatch { .. })),
            "{e}"
        );
        assert_eq!(ramp.steps_done(), 1);
        assert!(ramp.poll().is_err());
    }
}
