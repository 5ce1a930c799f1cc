//! Per-gate limits and per-gate maximal step. The run session's guard
//! ([`crate::session::guard`]) applies them against the instrument's last
//! read-back (ARCHITECTURE.md, invariant 5); the tuner applies them to its
//! own plans as well.
//!
//! All voltages in mV.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// A DC gate with its hard limits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GateSpec {
    /// Gate name, e.g. `"SB"`.
    pub name: String,
    /// Lowest voltage ever allowed, mV.
    pub min_mv: f64,
    /// Highest voltage ever allowed, mV.
    pub max_mv: f64,
    /// Largest change of this gate in one set command, mV.
    #[serde(default = "default_max_step_mv")]
    pub max_step_mv: f64,
    /// Voltage at the start of a run, mV.
    pub initial_mv: f64,
}

fn default_max_step_mv() -> f64 {
    10.0
}

/// Why a set of voltages was refused. Nothing is sent when this is returned.
#[derive(Debug, Clone, PartialEq, thiserror::Error, Serialize, Deserialize)]
pub enum SafetyError {
    /// The gate is not configured.
    #[error("unknown gate {0:?}")]
    UnknownGate(String),
    /// A wait that is not a finite number of seconds in
    /// `(0, protocol::MAX_WAIT_SECONDS]`.
    #[error("a wait of {0} s (allowed: more than 0, at most 600 s)")]
    InvalidWait(f64),
    /// A batch that is too long, nested, or touches a gate twice (its
    /// requests run at the same time, so each gate may be moved by one only).
    #[error("batch refused: {0}")]
    Batch(String),
    /// NaN or infinite voltage.
    #[error("gate {gate}: voltage {value_mv} mV is not a finite number")]
    NotFinite {
        /// Gate name.
        gate: String,
        /// Requested value, mV.
        value_mv: f64,
    },
    /// Outside `[min_mv, max_mv]`.
    #[error("gate {gate}: {value_mv} mV is outside its limits [{min_mv}, {max_mv}] mV")]
    OutOfLimits {
        /// Gate name.
        gate: String,
        /// Requested value, mV.
        value_mv: f64,
        /// Lower limit, mV.
        min_mv: f64,
        /// Upper limit, mV.
        max_mv: f64,
    },
    /// The gate's present voltage has not been read back from the instrument,
    /// so no step from it can be checked.
    #[error("gate {0}: present voltage unknown (not read back from the instrument)")]
    PositionUnknown(String),
    /// A sweep has too few or too many points.
    #[error("gate {gate}: a sweep of {points} points (allowed 2 to {max_points})")]
    SweepPoints {
        /// Swept gate.
        gate: String,
        /// Requested number of points.
        points: usize,
        /// Upper bound.
        max_points: usize,
    },
    /// The change from the present voltage exceeds the gate's maximal step.
    #[error("gate {gate}: step of {step_mv} mV exceeds its maximal step {max_step_mv} mV")]
    StepTooLarge {
        /// Gate name.
        gate: String,
        /// Requested change, mV.
        step_mv: f64,
        /// Configured maximum, mV.
        max_step_mv: f64,
    },
}

/// The configured gates and their limits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SafetyLimits {
    gates: BTreeMap<String, GateSpec>,
}

impl SafetyLimits {
    /// Limits for the given gates.
    pub fn new(gates: &[GateSpec]) -> Self {
        Self {
            gates: gates.iter().map(|g| (g.name.clone(), g.clone())).collect(),
        }
    }

    /// The spec of a gate.
    pub fn gate(&self, name: &str) -> Option<&GateSpec> {
        self.gates.get(name)
    }

    /// Check `requested` (gate → mV) against the limits and against the step from
    /// `present` (gate → mV). A gate absent from `present` is checked only
    /// against its limits.
    pub fn check(
        &self,
        present: &BTreeMap<String, f64>,
        requested: &BTreeMap<String, f64>,
    ) -> Result<(), SafetyError> {
        for (name, &v) in requested {
            let spec = self
                .gates
                .get(name)
                .ok_or_else(|| SafetyError::UnknownGate(name.clone()))?;
            if !v.is_finite() {
                return Err(SafetyError::NotFinite {
                    gate: name.clone(),
                    value_mv: v,
                });
            }
            if v < spec.min_mv || v > spec.max_mv {
                return Err(SafetyError::OutOfLimits {
                    gate: name.clone(),
                    value_mv: v,
                    min_mv: spec.min_mv,
                    max_mv: spec.max_mv,
                });
            }
            if let Some(&now) = present.get(name) {
                let step = (v - now).abs();
                // a tiny tolerance for rounding of clipped steps
                if step > spec.max_step_mv * (1.0 + 1e-9) + 1e-12 {
                    return Err(SafetyError::StepTooLarge {
                        gate: name.clone(),
                        step_mv: step,
                        max_step_mv: spec.max_step_mv,
                    });
                }
            }
        }
        Ok(())
    }

    /// Clip `target` for gate `name` to its limits and to its maximal step from `present_mv`.
    /// Unknown gates are returned unchanged (the check refuses them later).
    pub fn clip(&self, name: &str, present_mv: f64, target_mv: f64) -> f64 {
        match self.gates.get(name) {
            Some(spec) => target_mv
                .clamp(present_mv - spec.max_step_mv, present_mv + spec.max_step_mv)
                .clamp(spec.min_mv, spec.max_mv),
            None => target_mv,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> SafetyLimits {
        SafetyLimits::new(&[GateSpec {
            name: "T".into(),
            min_mv: -1000.0,
            max_mv: 0.0,
            max_step_mv: 10.0,
            initial_mv: -500.0,
        }])
    }

    #[test]
    fn refuses_out_of_limits_steps_nan_unknown() {
        let l = limits();
        let present = BTreeMap::from([("T".to_string(), -5.0)]);
        let req = |v: f64| BTreeMap::from([("T".to_string(), v)]);
        assert!(l.check(&present, &req(-10.0)).is_ok());
        assert!(matches!(
            l.check(&present, &req(1.0)),
            Err(SafetyError::OutOfLimits { .. })
        ));
        assert!(matches!(
            l.check(&present, &req(-20.0)),
            Err(SafetyError::StepTooLarge { .. })
        ));
        assert!(matches!(
            l.check(&present, &req(f64::NAN)),
            Err(SafetyError::NotFinite { .. })
        ));
        let unknown = BTreeMap::from([("X".to_string(), 0.0)]);
        assert!(matches!(
            l.check(&present, &unknown),
            Err(SafetyError::UnknownGate(_))
        ));
        let msg = l.check(&present, &req(1.0)).unwrap_err().to_string();
        assert!(msg.contains("T") && msg.contains("mV"), "{msg}");
    }

    #[test]
    fn clip_respects_both() {
        let l = limits();
        assert_eq!(l.clip("T", -5.0, 50.0), 0.0);
        assert_eq!(l.clip("T", -500.0, -600.0), -510.0);
    }
}
