//! Gradient estimators behind one interface: the paper's Kalman filter and the
//! baselines it is compared against (Broyden, fixed Jacobian, finite-difference
//! Newton, and the simulator's true Jacobian as an oracle).
//!
//! One estimator tracks one row of the Jacobian (one parameter over the gates of
//! its tuner). Units: parameter units per mV.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::kalman::{
    check_update_inputs, FilterError, KalmanGradient, ProcessNoise, UpdateOutcome,
};

/// Which estimator a tuner level uses, as written in a run config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EstimatorKind {
    /// The paper's Kalman filter with constant `Q`.
    Kalman,
    /// Kalman filter with `Q` growing as `|Δv|²`.
    KalmanAdaptiveQ,
    /// Broyden's ("good") rank-one update, no noise model.
    Broyden,
    /// The initial gradient, never updated.
    FixedJacobian,
    /// Gradient re-measured by finite differences every iteration.
    FdNewton,
    /// The device's true Jacobian (simulator only): the practical lower bound.
    Oracle,
}

impl EstimatorKind {
    /// All kinds, in the order benchmarks list them.
    pub const ALL: [EstimatorKind; 6] = [
        EstimatorKind::Kalman,
        EstimatorKind::KalmanAdaptiveQ,
        EstimatorKind::Broyden,
        EstimatorKind::FixedJacobian,
        EstimatorKind::FdNewton,
        EstimatorKind::Oracle,
    ];

    /// Name as used on the command line and in configs.
    pub fn name(self) -> &'static str {
        match self {
            EstimatorKind::Kalman => "kalman",
            EstimatorKind::KalmanAdaptiveQ => "kalman-adaptive-q",
            EstimatorKind::Broyden => "broyden",
            EstimatorKind::FixedJacobian => "fixed-jacobian",
            EstimatorKind::FdNewton => "fd-newton",
            EstimatorKind::Oracle => "oracle",
        }
    }

    /// Parse a name as produced by [`EstimatorKind::name`].
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }

    /// Whether the gradient must be re-measured (or queried) before every step.
    pub fn remeasures_each_iteration(self) -> bool {
        matches!(self, EstimatorKind::FdNewton | EstimatorKind::Oracle)
    }
}

/// The state of one gradient estimator (one Jacobian row).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum GradientEstimator {
    /// Kalman filter (constant or step-scaled `Q`).
    Kalman(KalmanGradient),
    /// Broyden rank-one update: `g ← g + (z − H g) Hᵀ / (H Hᵀ)`.
    Broyden {
        /// Gradient, unit/mV.
        gradient: DVector<f64>,
        /// Steps below this norm (mV) are skipped.
        min_step_mv: f64,
    },
    /// Never updated by steps; replaced only by a (re-)measurement.
    /// Used for `fixed-jacobian`, `fd-newton` and `oracle`.
    Measured {
        /// Gradient, unit/mV.
        gradient: DVector<f64>,
        /// Covariance of the last measurement, (unit/mV)²; zero if unknown.
        covariance: DMatrix<f64>,
    },
}

impl GradientEstimator {
    /// Build the estimator of `kind` from an initial gradient and covariance.
    ///
    /// `q` is the process noise used by the Kalman kinds (the step-scaled kind
    /// turns a constant `Q` into `Q · (|Δv|/reference_step_mv)²`).
    pub fn new(
        kind: EstimatorKind,
        g0: DVector<f64>,
        c0: DMatrix<f64>,
        q: &ProcessNoise,
        reference_step_mv: f64,
        outlier_sigma: Option<f64>,
        min_step_mv: f64,
    ) -> Result<Self, FilterError> {
        Ok(match kind {
            EstimatorKind::Kalman | EstimatorKind::KalmanAdaptiveQ => {
                let q = if kind == EstimatorKind::KalmanAdaptiveQ {
                    match q {
                        ProcessNoise::Constant { q } => ProcessNoise::StepScaled {
                            q_ref: q.clone(),
                            reference_step_mv,
                        },
                        other => other.clone(),
                    }
                } else {
                    q.clone()
                };
                GradientEstimator::Kalman(
                    KalmanGradient::new(g0, c0, q)?
                        .with_outlier_sigma(outlier_sigma)?
                        .with_min_step_mv(min_step_mv)?,
                )
            }
            EstimatorKind::Broyden => GradientEstimator::Broyden {
                gradient: g0,
                min_step_mv,
            },
            EstimatorKind::FixedJacobian | EstimatorKind::FdNewton | EstimatorKind::Oracle => {
                GradientEstimator::Measured {
                    gradient: g0,
                    covariance: c0,
                }
            }
        })
    }

    /// Current gradient estimate, unit/mV.
    pub fn gradient(&self) -> &DVector<f64> {
        match self {
            GradientEstimator::Kalman(k) => k.gradient(),
            GradientEstimator::Broyden { gradient, .. } => gradient,
            GradientEstimator::Measured { gradient, .. } => gradient,
        }
    }

    /// Covariance of the estimate, (unit/mV)², if the estimator has one.
    pub fn covariance(&self) -> Option<&DMatrix<f64>> {
        match self {
            GradientEstimator::Kalman(k) => Some(k.covariance()),
            GradientEstimator::Broyden { .. } => None,
            GradientEstimator::Measured { covariance, .. } => Some(covariance),
        }
    }

    /// Learn from a step `dv` (mV) that changed the parameter by `z` with variance `dz2`.
    /// Inputs are validated for every kind, so a NaN never slips through a baseline either.
    pub fn observe(
        &mut self,
        dv: &DVector<f64>,
        z: f64,
        dz2: f64,
    ) -> Result<UpdateOutcome, FilterError> {
        match self {
            GradientEstimator::Kalman(k) => k.update(dv, z, dz2),
            GradientEstimator::Broyden {
                gradient,
                min_step_mv,
            } => {
                check_update_inputs(gradient.len(), dv, z, dz2)?;
                let hh = dv.dot(dv);
                if hh.sqrt() < *min_step_mv || hh == 0.0 {
                    return Ok(UpdateOutcome::SkippedSmallStep {
                        step_norm_mv: hh.sqrt(),
                    });
                }
                let innovation = z - dv.dot(gradient);
                *gradient += dv * (innovation / hh);
                Ok(UpdateOutcome::Updated {
                    innovation,
                    innovation_sigma: dz2.sqrt(),
                })
            }
            GradientEstimator::Measured { gradient, .. } => {
                check_update_inputs(gradient.len(), dv, z, dz2)?;
                Ok(UpdateOutcome::SkippedSmallStep {
                    step_norm_mv: dv.norm(),
                })
            }
        }
    }

    /// Replace the gradient by a fresh measurement (finite differences or oracle).
    /// Kalman and Broyden estimators ignore this (they learn from steps).
    pub fn remeasured(&mut self, g: DVector<f64>, c: DMatrix<f64>) {
        if let GradientEstimator::Measured {
            gradient,
            covariance,
        } = self
        {
            *gradient = g;
            *covariance = c;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn make(kind: EstimatorKind) -> GradientEstimator {
        GradientEstimator::new(
            kind,
            DVector::from_vec(vec![1.0, 0.0]),
            DMatrix::identity(2, 2),
            &ProcessNoise::isotropic(2, 0.1),
            10.0,
            None,
            1e-6,
        )
        .unwrap()
    }

    #[test]
    fn names_round_trip() {
        for k in EstimatorKind::ALL {
            assert_eq!(EstimatorKind::from_name(k.name()), Some(k));
        }
        assert_eq!(EstimatorKind::from_name("nope"), None);
    }

    #[test]
    fn broyden_reproduces_secant() {
        let mut e = make(EstimatorKind::Broyden);
        let dv = DVector::from_vec(vec![1.0, 2.0]);
        e.observe(&dv, 4.0, 0.0).unwrap();
        assert!((e.gradient().dot(&dv) - 4.0).abs() < 1e-12);
    }

    #[test]
    fn fixed_never_moves_but_validates() {
        let mut e = make(EstimatorKind::FixedJacobian);
        let g = e.gradient().clone();
        e.observe(&DVector::from_vec(vec![1.0, 2.0]), 4.0, 0.0)
            .unwrap();
        assert_eq!(e.gradient(), &g);
        assert!(e
            .observe(&DVector::from_vec(vec![1.0, 2.0]), 4.0, f64::NAN)
            .is_err());
        e.remeasured(DVector::from_vec(vec![3.0, 3.0]), DMatrix::zeros(2, 2));
        assert_eq!(e.gradient()[0], 3.0);
    }

    #[test]
    fn adaptive_kind_uses_step_scaled_q() {
        match make(EstimatorKind::KalmanAdaptiveQ) {
            GradientEstimator::Kalman(k) => {
                assert!(matches!(k.process_noise(), ProcessNoise::StepScaled { .. }))
            }
            other => panic!("{other:?}"),
        }
    }
}
