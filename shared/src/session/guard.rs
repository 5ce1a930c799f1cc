//! The one safety choke point (ARCHITECTURE.md, invariant 5): every request
//! is checked against the gate limits and against the instrument's last
//! **read-back**, never against the tuner's plan.
//!
//! * A gate's position is known only from a read-back: the answer to a
//!   [`Request::ReadVoltages`] or an accepted answer to a
//!   [`Request::SetVoltages`]. Nothing is known at construction or after a
//!   restore from a checkpoint (the read-backs are not serialized), after a
//!   fault, or for a swept gate after its sweep.
//! * A set answer is accepted only if it carries exactly the requested gates,
//!   every value finite and within `readback_tolerance_mv` of the set value.
//! * A read answer is **plausible** or refused: exactly the requested gates,
//!   every value finite and inside the gate's limits (± the read-back
//!   tolerance), and within `moved_tolerance_mv` of where the run left the
//!   gate. "Where the run left it" is a range per gate, serialized with the
//!   checkpoint (unlike the read-backs): the last accepted read-back, widened
//!   to every voltage a request sent since may have visited (a sweep's range,
//!   the path of a move whose answer was refused or lost). A gate that reads
//!   outside that range is a [`ReadbackError::Moved`], which a person clears
//!   ([`Guard::accept_positions`]); a new run (nothing left yet) trusts a
//!   plausible first read-back.
//! * Every voltage a request can visit is checked: each gate of a move and
//!   every point of a sweep lies within the gate's limits; a move's step and
//!   a sweep's first point lie within `max_step_mv` of the read-back; the
//!   spacing of sweep points is at most `max_step_mv`.
//!
//! All voltages in mV.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::protocol::{MovedGate, Request, Sweep, MAX_BATCH_REQUESTS};
use crate::safety::{SafetyError, SafetyLimits};
use crate::tuner::MAX_SWEEP_POINTS;

/// Why a read-back was refused. The gates concerned are forgotten (their
/// position is unknown until read again).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReadbackError {
    /// The answer reports gates that were not requested (and so cannot have moved).
    #[error("the answer reports gates that were not requested: {}", .0.join(", "))]
    Unrequested(Vec<String>),
    /// The answer lacks gates that were requested.
    #[error("the answer lacks the read-back of {}", .0.join(", "))]
    Missing(Vec<String>),
    /// A read-back value is NaN or infinite.
    #[error("gate {gate}: read-back {value_mv} mV is not a finite number")]
    NotFinite {
        /// Gate name.
        gate: String,
        /// Reported value, mV.
        value_mv: f64,
    },
    /// A read-back lies outside the gate's limits (an instrument that reports
    /// this is faulty, or the gate was moved outside them by hand).
    #[error(
        "gate {gate} reads {value_mv} mV, outside its limits [{min_mv}, {max_mv}] mV: nothing was moved; ramp it into its limits first"
    )]
    OutOfLimits {
        /// Gate name.
        gate: String,
        /// Reported value, mV.
        value_mv: f64,
        /// Lower limit, mV.
        min_mv: f64,
        /// Upper limit, mV.
        max_mv: f64,
    },
    /// Gates read farther than the moved tolerance from where the run left
    /// them: a person must confirm the new positions (or move them back).
    #[error("{}", moved_message(.moved, *.tolerance_mv))]
    Moved {
        /// Every such gate with both positions.
        moved: Vec<MovedGate>,
        /// The allowed distance, mV.
        tolerance_mv: f64,
    },
    /// The read-back differs from the set value by more than the tolerance.
    #[error(
        "gate {gate}: set {set_mv:.6} mV, read back {read_mv:.6} mV (tolerance {tolerance_mv} mV)"
    )]
    Mismatch {
        /// Gate name.
        gate: String,
        /// Value that was set, mV.
        set_mv: f64,
        /// Value read back, mV.
        read_mv: f64,
        /// Allowed difference, mV.
        tolerance_mv: f64,
    },
}

fn moved_message(moved: &[MovedGate], tolerance_mv: f64) -> String {
    let gates: Vec<String> = moved
        .iter()
        .map(|m| {
            let left = if m.left_from_mv == m.left_to_mv {
                format!("{:.3} mV", m.left_from_mv)
            } else {
                format!("[{:.3}, {:.3}] mV", m.left_from_mv, m.left_to_mv)
            };
            format!("{} was left at {left}, reads {:.3} mV", m.gate, m.read_mv)
        })
        .collect();
    format!(
        "{} (more than {tolerance_mv} mV away); nothing was moved: confirm the new positions (accept_positions) or put the gates back and resume",
        gates.join("; ")
    )
}

/// Where the run left a gate: a range of voltages, mV (`lo_mv == hi_mv` for
/// an accepted read-back).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Span {
    /// Lower end, mV.
    pub lo_mv: f64,
    /// Upper end, mV.
    pub hi_mv: f64,
}

impl Span {
    /// The single voltage `mv`.
    pub fn point(mv: f64) -> Self {
        Self {
            lo_mv: mv,
            hi_mv: mv,
        }
    }

    /// The smallest range holding this one and `mv`.
    pub fn with(self, mv: f64) -> Self {
        Self {
            lo_mv: self.lo_mv.min(mv),
            hi_mv: self.hi_mv.max(mv),
        }
    }

    /// Distance of `mv` from the range, mV (0 inside).
    pub fn distance_mv(self, mv: f64) -> f64 {
        (self.lo_mv - mv).max(mv - self.hi_mv).max(0.0)
    }
}

/// Default of [`Guard`]'s moved tolerance for checkpoints written before it
/// existed, mV.
fn default_moved_tolerance_mv() -> f64 {
    1.0
}

/// Gate limits plus the instrument's last read-back of each gate and where
/// the run left each gate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Guard {
    limits: SafetyLimits,
    /// Largest accepted |read-back − set value|, mV.
    tolerance_mv: f64,
    /// Largest accepted distance of a read-back from where the run left the
    /// gate, mV.
    #[serde(default = "default_moved_tolerance_mv")]
    moved_tolerance_mv: f64,
    /// Where the run left each gate (serialized: a restored run compares the
    /// instrument with it). Empty for a new run.
    #[serde(default)]
    left_mv: BTreeMap<String, Span>,
    /// Last accepted read-back per gate, mV. Not serialized: after a restore
    /// the instrument must be asked again.
    #[serde(skip)]
    readback_mv: BTreeMap<String, f64>,
}

impl Guard {
    /// A guard that knows no gate's position yet. `tolerance_mv`: largest
    /// |read-back − set value|; `moved_tolerance_mv`: largest distance of a
    /// read-back from where the run left the gate (both mV).
    pub fn new(limits: SafetyLimits, tolerance_mv: f64, moved_tolerance_mv: f64) -> Self {
        Self {
            limits,
            tolerance_mv,
            moved_tolerance_mv,
            left_mv: BTreeMap::new(),
            readback_mv: BTreeMap::new(),
        }
    }

    /// Where the run left each gate (gates never read are absent).
    pub fn left_mv(&self) -> &BTreeMap<String, Span> {
        &self.left_mv
    }

    /// A person confirmed these positions (the gates of a
    /// [`ReadbackError::Moved`]): the run left the gates there. They are read
    /// again before anything moves.
    pub fn accept_positions(&mut self, moved: &[MovedGate]) {
        for m in moved {
            self.left_mv.insert(m.gate.clone(), Span::point(m.read_mv));
            self.readback_mv.remove(&m.gate);
        }
    }

    /// `request` is being answered: every voltage it may have set is where
    /// the run may have left its gates (until an answer says exactly where).
    pub fn may_have_visited(&mut self, request: &Request) {
        let mut widen = |gate: &str, mv: f64| {
            if !mv.is_finite() {
                return;
            }
            let span = match self.left_mv.get(gate) {
                Some(s) => s.with(mv),
                None => match self.readback_mv.get(gate) {
                    Some(&r) => Span::point(r).with(mv),
                    None => Span::point(mv),
                },
            };
            self.left_mv.insert(gate.to_string(), span);
        };
        match request {
            Request::SetVoltages { voltages_mv } => {
                for (g, &v) in voltages_mv {
                    widen(g, v);
                }
            }
            Request::Measure { scan } => {
                if let Some(s) = &scan.sweep {
                    widen(&s.gate, s.from_mv);
                    widen(&s.gate, s.to_mv);
                }
            }
            Request::ReadVoltages { .. } | Request::TrueJacobian { .. } | Request::Wait { .. } => {}
            Request::Batch { requests } => {
                for r in requests {
                    self.may_have_visited(r);
                }
            }
        }
    }

    /// The limits.
    pub fn limits(&self) -> &SafetyLimits {
        &self.limits
    }

    /// Last accepted read-backs (gate → mV); gates not listed are unknown.
    pub fn readback_mv(&self) -> &BTreeMap<String, f64> {
        &self.readback_mv
    }

    /// Forget every read-back: the next request reads the instrument first.
    pub fn forget_all(&mut self) {
        self.readback_mv.clear();
    }

    /// Gates that `request` touches (moves and sweeps) whose position is unknown.
    pub fn unknown_gates(&self, request: &Request) -> BTreeSet<String> {
        touched_gates(request)
            .into_iter()
            .filter(|g| !self.readback_mv.contains_key(g))
            .collect()
    }

    /// Check every voltage `request` can visit. `Err` means: do not send it.
    pub fn check(&self, request: &Request) -> Result<(), SafetyError> {
        match request {
            Request::SetVoltages { voltages_mv } => {
                for gate in voltages_mv.keys() {
                    self.require_known(gate)?;
                }
                self.limits.check(&self.readback_mv, voltages_mv)
            }
            Request::Measure { scan } => match &scan.sweep {
                Some(sweep) => self.check_sweep(sweep),
                None => Ok(()),
            },
            Request::ReadVoltages { gates } => {
                for g in gates {
                    if self.limits.gate(g).is_none() {
                        return Err(SafetyError::UnknownGate(g.clone()));
                    }
                }
                Ok(())
            }
            Request::TrueJacobian { .. } => Ok(()),
            Request::Batch { requests } => self.check_batch(requests),
            Request::Wait { seconds } => {
                if seconds.is_finite()
                    && *seconds > 0.0
                    && *seconds <= crate::protocol::MAX_WAIT_SECONDS
                {
                    Ok(())
                } else {
                    Err(SafetyError::InvalidWait(*seconds))
                }
            }
        }
    }

    /// A batch: at most [`MAX_BATCH_REQUESTS`], none nested, no gate moved
    /// or swept by two of its requests (they run at the same time), and
    /// every request passes on its own.
    fn check_batch(&self, requests: &[Request]) -> Result<(), SafetyError> {
        if requests.len() > MAX_BATCH_REQUESTS {
            return Err(SafetyError::Batch(format!(
                "{} requests (at most {MAX_BATCH_REQUESTS})",
                requests.len()
            )));
        }
        let mut touched = BTreeSet::new();
        for (i, r) in requests.iter().enumerate() {
            if matches!(r, Request::Batch { .. }) {
                return Err(SafetyError::Batch(format!("request {i} is itself a batch")));
            }
            for g in touched_gates(r) {
                if !touched.insert(g.clone()) {
                    return Err(SafetyError::Batch(format!(
                        "gate {g} is moved by more than one request (request {i})"
                    )));
                }
            }
            self.check(r)?;
        }
        Ok(())
    }

    fn require_known(&self, gate: &str) -> Result<(), SafetyError> {
        if self.limits.gate(gate).is_none() {
            return Err(SafetyError::UnknownGate(gate.to_string()));
        }
        if !self.readback_mv.contains_key(gate) {
            return Err(SafetyError::PositionUnknown(gate.to_string()));
        }
        Ok(())
    }

    fn check_sweep(&self, sweep: &Sweep) -> Result<(), SafetyError> {
        self.require_known(&sweep.gate)?;
        let spec = self
            .limits
            .gate(&sweep.gate)
            .ok_or_else(|| SafetyError::UnknownGate(sweep.gate.clone()))?;
        if !(2..=MAX_SWEEP_POINTS).contains(&sweep.points) {
            return Err(SafetyError::SweepPoints {
                gate: sweep.gate.clone(),
                points: sweep.points,
                max_points: MAX_SWEEP_POINTS,
            });
        }
        // The points lie on the segment [from, to]: both ends within limits
        // means every point is; the first point is one step from the read-back.
        let ends = BTreeMap::from([(sweep.gate.clone(), sweep.from_mv)]);
        self.limits.check(&self.readback_mv, &ends)?;
        let last = BTreeMap::from([(sweep.gate.clone(), sweep.to_mv)]);
        self.limits.check(&BTreeMap::new(), &last)?;
        let spacing_mv = (sweep.to_mv - sweep.from_mv).abs() / (sweep.points - 1) as f64;
        if spacing_mv > spec.max_step_mv * (1.0 + 1e-9) + 1e-12 {
            return Err(SafetyError::StepTooLarge {
                gate: sweep.gate.clone(),
                step_mv: spacing_mv,
                max_step_mv: spec.max_step_mv,
            });
        }
        Ok(())
    }

    /// Take the answer to a set request. On `Ok` the read-backs of exactly
    /// the requested gates are known; on `Err` those gates (and any reported
    /// extra gate) are forgotten.
    pub fn accept_set(
        &mut self,
        requested: &BTreeMap<String, f64>,
        answered: &BTreeMap<String, f64>,
    ) -> Result<(), ReadbackError> {
        let result = self.validate_set(requested, answered);
        self.settle(&result, answered, requested.keys().chain(answered.keys()));
        result
    }

    /// After a validated answer: adopt every answered read-back (the gate
    /// is now left exactly there); after a refused one: forget `gates`
    /// (unknown until read again).
    fn settle<'a>(
        &mut self,
        result: &Result<(), ReadbackError>,
        answered: &BTreeMap<String, f64>,
        gates: impl Iterator<Item = &'a String>,
    ) {
        match result {
            Ok(()) => {
                for (g, &v) in answered {
                    self.readback_mv.insert(g.clone(), v);
                    self.left_mv.insert(g.clone(), Span::point(v));
                }
            }
            Err(_) => {
                for g in gates {
                    self.readback_mv.remove(g);
                }
            }
        }
    }

    fn validate_set(
        &self,
        requested: &BTreeMap<String, f64>,
        answered: &BTreeMap<String, f64>,
    ) -> Result<(), ReadbackError> {
        same_gates(requested.keys(), answered)?;
        for (gate, &set_mv) in requested {
            let read_mv = answered[gate];
            if !read_mv.is_finite() {
                return Err(ReadbackError::NotFinite {
                    gate: gate.clone(),
                    value_mv: read_mv,
                });
            }
            if (read_mv - set_mv).abs() > self.tolerance_mv {
                return Err(ReadbackError::Mismatch {
                    gate: gate.clone(),
                    set_mv,
                    read_mv,
                    tolerance_mv: self.tolerance_mv,
                });
            }
        }
        Ok(())
    }

    /// Take the answer to a read request: exactly the requested gates, every
    /// value finite, inside the gate's limits (± the read-back tolerance) and
    /// within the moved tolerance of where the run left the gate. On `Err`
    /// nothing is adopted and the requested gates are unknown.
    pub fn accept_read(
        &mut self,
        requested: &[String],
        answered: &BTreeMap<String, f64>,
    ) -> Result<(), ReadbackError> {
        let result = self.validate_read(requested, answered);
        self.settle(&result, answered, requested.iter());
        result
    }

    fn validate_read(
        &self,
        requested: &[String],
        answered: &BTreeMap<String, f64>,
    ) -> Result<(), ReadbackError> {
        same_gates(requested.iter(), answered)?;
        for (gate, &v) in answered {
            if !v.is_finite() {
                return Err(ReadbackError::NotFinite {
                    gate: gate.clone(),
                    value_mv: v,
                });
            }
            if let Some(spec) = self.limits.gate(gate) {
                let slack = self.tolerance_mv;
                if v < spec.min_mv - slack || v > spec.max_mv + slack {
                    return Err(ReadbackError::OutOfLimits {
                        gate: gate.clone(),
                        value_mv: v,
                        min_mv: spec.min_mv,
                        max_mv: spec.max_mv,
                    });
                }
            }
        }
        let moved: Vec<MovedGate> = answered
            .iter()
            .filter_map(|(gate, &v)| {
                let span = *self.left_mv.get(gate)?;
                (span.distance_mv(v) > self.moved_tolerance_mv).then(|| MovedGate {
                    gate: gate.clone(),
                    left_from_mv: span.lo_mv,
                    left_to_mv: span.hi_mv,
                    read_mv: v,
                })
            })
            .collect();
        if !moved.is_empty() {
            return Err(ReadbackError::Moved {
                moved,
                tolerance_mv: self.moved_tolerance_mv,
            });
        }
        Ok(())
    }

    /// A request went to the device and came back (or failed): a swept gate's
    /// position is unknown until read again (the instrument may have left it
    /// at any point of the sweep).
    pub fn after_request(&mut self, request: &Request) {
        match request {
            Request::Measure { scan } => {
                if let Some(s) = &scan.sweep {
                    self.readback_mv.remove(&s.gate);
                }
            }
            Request::Batch { requests } => requests.iter().for_each(|r| self.after_request(r)),
            _ => {}
        }
    }
}

/// `Ok` if `answered` has exactly the gates in `requested`.
fn same_gates<'a>(
    requested: impl Iterator<Item = &'a String> + Clone,
    answered: &BTreeMap<String, f64>,
) -> Result<(), ReadbackError> {
    let want: BTreeSet<&String> = requested.collect();
    let extra: Vec<String> = answered
        .keys()
        .filter(|g| !want.contains(g))
        .cloned()
        .collect();
    if !extra.is_empty() {
        return Err(ReadbackError::Unrequested(extra));
    }
    let missing: Vec<String> = want
        .into_iter()
        .filter(|g| !answered.contains_key(*g))
        .cloned()
        .collect();
    if !missing.is_empty() {
        return Err(ReadbackError::Missing(missing));
    }
    Ok(())
}

/// Gates whose voltage a request changes (set gates, swept gate).
pub fn touched_gates(request: &Request) -> Vec<String> {
    match request {
        Request::SetVoltages { voltages_mv } => voltages_mv.keys().cloned().collect(),
        Request::Measure { scan } => scan.sweep.iter().map(|s| s.gate.clone()).collect(),
        Request::ReadVoltages { .. } | Request::TrueJacobian { .. } | Request::Wait { .. } => {
            Vec::new()
        }
        Request::Batch { requests } => requests.iter().flat_map(touched_gates).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{ScanKind, ScanRequest};
    use crate::safety::GateSpec;

    /// A guard that tolerates any move of a gate between reads (the moved
    /// check has its own test).
    fn guard() -> Guard {
        guard_with_moved_tolerance(100.0)
    }

    fn guard_with_moved_tolerance(moved_tolerance_mv: f64) -> Guard {
        let spec = |name: &str| GateSpec {
            name: name.into(),
            min_mv: -100.0,
            max_mv: 100.0,
            max_step_mv: 10.0,
            initial_mv: 0.0,
        };
        Guard::new(
            SafetyLimits::new(&[spec("A"), spec("B")]),
            0.05,
            moved_tolerance_mv,
        )
    }

    fn set(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(g, v)| (g.to_string(), *v)).collect()
    }

    fn sweep(from_mv: f64, to_mv: f64, points: usize) -> Request {
        Request::Measure {
            scan: ScanRequest {
                kind: ScanKind::SensingDot,
                sweep: Some(Sweep {
                    gate: "A".into(),
                    from_mv,
                    to_mv,
                    points,
                }),
                cell: None,
            },
        }
    }

    #[test]
    fn a_batch_is_checked_request_by_request_and_moves_each_gate_once() {
        let mut g = guard();
        g.accept_read(&["A".into(), "B".into()], &set(&[("A", 0.0), ("B", 0.0)]))
            .unwrap();
        let a = |mv| Request::SetVoltages {
            voltages_mv: set(&[("A", mv)]),
        };
        let b = |mv| Request::SetVoltages {
            voltages_mv: set(&[("B", mv)]),
        };
        let batch = |requests| Request::Batch { requests };
        assert_eq!(g.check(&batch(vec![a(5.0), b(-5.0)])), Ok(()));
        assert_eq!(g.check(&batch(Vec::new())), Ok(()));
        // one request over its step: the whole batch is refused
        assert!(matches!(
            g.check(&batch(vec![a(5.0), b(-15.0)])),
            Err(SafetyError::StepTooLarge { .. })
        ));
        // a gate set twice, or set and swept, in one batch
        for twice in [vec![a(5.0), a(6.0)], vec![sweep(0.0, 9.0, 10), a(1.0)]] {
            let e = g.check(&batch(twice)).unwrap_err();
            assert!(
                e.to_string()
                    .contains("gate A is moved by more than one request"),
                "{e}"
            );
        }
        let e = g.check(&batch(vec![batch(vec![a(1.0)])])).unwrap_err();
        assert!(e.to_string().contains("itself a batch"), "{e}");
        let long = vec![Request::Wait { seconds: 1.0 }; MAX_BATCH_REQUESTS + 1];
        let e = g.check(&batch(long)).unwrap_err();
        assert!(e.to_string().contains("at most 1024"), "{e}");
        // gates touched, and a swept gate forgotten after the batch
        let sw = batch(vec![sweep(0.0, 9.0, 10), b(2.0)]);
        assert_eq!(touched_gates(&sw), ["A".to_string(), "B".to_string()]);
        g.after_request(&sw);
        assert!(!g.readback_mv().contains_key("A"));
        assert!(g.readback_mv().contains_key("B"));
        // a batch's path widens where the run may have left its gates
        g.may_have_visited(&batch(vec![b(7.0)]));
        assert_eq!(
            g.left_mv()["B"],
            Span {
                lo_mv: 0.0,
                hi_mv: 7.0
            }
        );
    }

    #[test]
    fn a_move_needs_a_readback_and_is_checked_from_it() {
        let mut g = guard();
        let req = Request::SetVoltages {
            voltages_mv: set(&[("A", 5.0)]),
        };
        assert_eq!(g.check(&req), Err(SafetyError::PositionUnknown("A".into())));
        assert_eq!(g.unknown_gates(&req), BTreeSet::from(["A".to_string()]));
        g.accept_read(&["A".into()], &set(&[("A", -8.0)])).unwrap();
        // 13 mV from the read-back: refused although the plan started at 0 mV.
        assert!(matches!(
            g.check(&req),
            Err(SafetyError::StepTooLarge { .. })
        ));
        g.accept_read(&["A".into()], &set(&[("A", -4.0)])).unwrap();
        assert_eq!(g.check(&req), Ok(()));
    }

    #[test]
    fn set_answers_with_extra_missing_nonfinite_or_far_gates_are_refused() {
        let mut g = guard();
        g.accept_read(&["A".into(), "B".into()], &set(&[("A", 0.0), ("B", 0.0)]))
            .unwrap();
        let want = set(&[("A", 5.0)]);
        let err = g
            .accept_set(&want, &set(&[("A", 5.0), ("B", 80.0)]))
            .unwrap_err();
        assert_eq!(err, ReadbackError::Unrequested(vec!["B".into()]));
        // B's position is now unknown: its next move reads it first.
        assert!(!g.readback_mv().contains_key("B"));
        assert!(!g.readback_mv().contains_key("A"));
        g.accept_read(&["A".into(), "B".into()], &set(&[("A", 0.0), ("B", 0.0)]))
            .unwrap();
        assert_eq!(
            g.accept_set(&want, &BTreeMap::new()),
            Err(ReadbackError::Missing(vec!["A".into()]))
        );
        g.accept_read(&["A".into()], &set(&[("A", 0.0)])).unwrap();
        assert!(matches!(
            g.accept_set(&want, &set(&[("A", f64::NAN)])),
            Err(ReadbackError::NotFinite { .. })
        ));
        g.accept_read(&["A".into()], &set(&[("A", 0.0)])).unwrap();
        assert!(matches!(
            g.accept_set(&want, &set(&[("A", 5.2)])),
            Err(ReadbackError::Mismatch { .. })
        ));
        g.accept_read(&["A".into()], &set(&[("A", 0.0)])).unwrap();
        g.accept_set(&want, &set(&[("A", 5.01)])).unwrap();
        assert_eq!(g.readback_mv()["A"], 5.01);
        assert_eq!(g.readback_mv()["B"], 0.0);
    }

    #[test]
    fn sweeps_are_checked_point_by_point_and_forget_the_gate() {
        let mut g = guard();
        g.accept_read(&["A".into()], &set(&[("A", 0.0)])).unwrap();
        assert_eq!(g.check(&sweep(-10.0, 10.0, 21)), Ok(()));
        // first point 15 mV from the read-back
        assert!(matches!(
            g.check(&sweep(-15.0, 5.0, 21)),
            Err(SafetyError::StepTooLarge { .. })
        ));
        // last point outside the limits
        g.accept_read(&["A".into()], &set(&[("A", 95.0)])).unwrap();
        assert!(matches!(
            g.check(&sweep(90.0, 110.0, 21)),
            Err(SafetyError::OutOfLimits { .. })
        ));
        // points 20 mV apart
        assert!(matches!(
            g.check(&sweep(90.0, 50.0, 3)),
            Err(SafetyError::StepTooLarge { .. })
        ));
        assert!(matches!(
            g.check(&sweep(90.0, 80.0, 1)),
            Err(SafetyError::SweepPoints { .. })
        ));
        g.after_request(&sweep(90.0, 80.0, 11));
        assert!(!g.readback_mv().contains_key("A"));
    }

    #[test]
    fn read_backs_must_be_plausible_and_near_where_the_run_left_the_gate() {
        let mut g = guard_with_moved_tolerance(1.0);
        // a new run trusts a plausible first read
        g.accept_read(&["A".into(), "B".into()], &set(&[("A", 3.0), ("B", -2.0)]))
            .unwrap();
        for lie in [f64::NAN, f64::INFINITY, 1e308, 9.91e40, 100.1, -105.0] {
            let e = g
                .accept_read(&["A".into()], &set(&[("A", lie)]))
                .unwrap_err();
            assert!(
                matches!(
                    e,
                    ReadbackError::NotFinite { .. } | ReadbackError::OutOfLimits { .. }
                ),
                "{lie}: {e}"
            );
            assert!(
                !g.readback_mv().contains_key("A"),
                "a refused read is forgotten"
            );
        }
        // at the limit ± the read-back tolerance is fine (DAC rounding)
        let mut edge = guard_with_moved_tolerance(100.0);
        edge.accept_read(&["A".into()], &set(&[("A", 100.04)]))
            .unwrap();
        // 0.9 mV from where it was left: adopted; 1.5 mV: moved
        g.accept_read(&["A".into()], &set(&[("A", 3.9)])).unwrap();
        let e = g
            .accept_read(&["A".into(), "B".into()], &set(&[("A", 5.4), ("B", 40.0)]))
            .unwrap_err();
        let ReadbackError::Moved {
            moved,
            tolerance_mv,
        } = &e
        else {
            panic!("{e}")
        };
        assert_eq!(*tolerance_mv, 1.0);
        assert_eq!(
            moved
                .iter()
                .map(|m| (m.gate.as_str(), m.left_from_mv, m.read_mv))
                .collect::<Vec<_>>(),
            vec![("A", 3.9, 5.4), ("B", -2.0, 40.0)]
        );
        assert!(
            e.to_string()
                .contains("B was left at -2.000 mV, reads 40.000 mV"),
            "{e}"
        );
        // nothing adopted; confirming adopts the new positions as where the run left them
        assert!(g.readback_mv().is_empty());
        g.accept_positions(moved);
        assert_eq!(g.left_mv()["B"], Span::point(40.0));
        g.accept_read(&["A".into(), "B".into()], &set(&[("A", 5.4), ("B", 40.0)]))
            .unwrap();
        // a move whose answer was lost may have left the gate anywhere on its path
        let req = Request::SetVoltages {
            voltages_mv: set(&[("A", 12.0)]),
        };
        g.may_have_visited(&req);
        assert_eq!(
            g.left_mv()["A"],
            Span {
                lo_mv: 5.4,
                hi_mv: 12.0
            }
        );
        g.forget_all();
        g.accept_read(&["A".into()], &set(&[("A", 9.0)])).unwrap();
        assert_eq!(g.left_mv()["A"], Span::point(9.0));
        // and a restored guard still knows where the run left the gates
        let back: Guard = serde_json::from_str(&serde_json::to_string(&g).unwrap()).unwrap();
        assert_eq!(back.left_mv(), g.left_mv());
    }

    #[test]
    fn readbacks_are_not_serialized() {
        let mut g = guard();
        g.accept_read(&["A".into()], &set(&[("A", 1.0)])).unwrap();
        let back: Guard = serde_json::from_str(&serde_json::to_string(&g).unwrap()).unwrap();
        assert!(back.readback_mv().is_empty());
    }
}
