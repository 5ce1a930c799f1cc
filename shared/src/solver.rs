//! Quasi-Newton step: `Δv = −J⁺ Δ` with the minimum-norm pseudo-inverse,
//! limited in Euclidean norm (paper: 10 mV).
//!
//! `J` is m×n (parameters × gates, unit/mV), `Δ = p − p*` (parameter units),
//! `Δv` in mV. Works for under-determined (m < n) and rank-deficient `J`:
//! singular values below `rank_tolerance · σ_max` are treated as zero.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Solver settings for one tuner level.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolverConfig {
    /// Maximal Euclidean norm of one step over the level's gates, mV (paper: 10 mV).
    pub max_step_mv: f64,
    /// Relative singular-value cut-off for the pseudo-inverse.
    pub rank_tolerance: f64,
}

impl Default for SolverConfig {
    fn default() -> Self {
        Self {
            max_step_mv: 10.0,
            rank_tolerance: 1e-9,
        }
    }
}

/// The step a solver proposes, before gate limits are applied.
#[derive(Debug, Clone, PartialEq)]
pub struct NewtonStep {
    /// Proposed voltage change, mV (already limited to `max_step_mv`).
    pub dv_mv: DVector<f64>,
    /// Norm of the full Newton step before limiting, mV.
    pub unlimited_norm_mv: f64,
    /// Numerical rank of `J` used.
    pub rank: usize,
}

/// Minimum-norm Newton step `−J⁺ Δ`, scaled down to `cfg.max_step_mv` if longer.
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::solver::{newton_step, SolverConfig};
/// // One parameter, two gates: p = 2 v0 (unit/mV). p is 1 above target.
/// let j = DMatrix::from_row_slice(1, 2, &[2.0, 0.0]);
/// let step = newton_step(&j, &DVector::from_vec(vec![1.0]), &SolverConfig::default());
/// assert!((step.dv_mv[0] + 0.5).abs() < 1e-12);
/// assert_eq!(step.dv_mv[1], 0.0);
/// ```
pub fn newton_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    cfg: &SolverConfig,
) -> NewtonStep {
    let n = jacobian.ncols();
    if jacobian.nrows() == 0 || n == 0 || jacobian.iter().any(|x| !x.is_finite()) {
        return NewtonStep {
            dv_mv: DVector::zeros(n),
            unlimited_norm_mv: 0.0,
            rank: 0,
        };
    }
    let svd = jacobian.clone().svd(true, true);
    let smax = svd.singular_values.max();
    let eps = (cfg.rank_tolerance * smax).max(f64::MIN_POSITIVE);
    let rank = svd.singular_values.iter().filter(|&&s| s > eps).count();
    let dv = if rank == 0 {
        DVector::zeros(n)
    } else {
        match svd.solve(delta, eps) {
            Ok(x) => -x,
            Err(_) => DVector::zeros(n),
        }
    };
    let norm = dv.norm();
    let dv = if norm > cfg.max_step_mv && norm > 0.0 {
        dv * (cfg.max_step_mv / norm)
    } else {
        dv
    };
    NewtonStep {
        dv_mv: dv,
        unlimited_norm_mv: norm,
        rank,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn underdetermined_is_minimum_norm() {
        // 2 parameters, 4 gates
        let j = DMatrix::from_row_slice(2, 4, &[1.0, 2.0, 0.0, 1.0, 0.0, 1.0, 3.0, -1.0]);
        let delta = DVector::from_vec(vec![0.5, -0.2]);
        let cfg = SolverConfig {
            max_step_mv: 1e9,
            ..Default::default()
        };
        let s = newton_step(&j, &delta, &cfg);
        assert_eq!(s.rank, 2);
        // solves J dv = −Δ exactly
        assert!((&j * &s.dv_mv + &delta).norm() < 1e-12);
        // and lies in the row space of J (minimum norm)
        let proj = j.transpose() * (&j * j.transpose()).try_inverse().unwrap() * &j;
        assert!((&proj * &s.dv_mv - &s.dv_mv).norm() < 1e-12);
    }

    #[test]
    fn rank_deficient_does_not_blow_up() {
        let j = DMatrix::from_row_slice(2, 3, &[1.0, 1.0, 0.0, 2.0, 2.0, 0.0]);
        let s = newton_step(
            &j,
            &DVector::from_vec(vec![1.0, 2.0]),
            &SolverConfig::default(),
        );
        assert_eq!(s.rank, 1);
        assert!((&j * &s.dv_mv + DVector::from_vec(vec![1.0, 2.0])).norm() < 1e-9);
        assert_eq!(s.dv_mv[2], 0.0);
    }

    #[test]
    fn zero_jacobian_gives_zero_step() {
        let s = newton_step(
            &DMatrix::zeros(2, 4),
            &DVector::from_vec(vec![1.0, 1.0]),
            &SolverConfig::default(),
        );
        assert_eq!(s.dv_mv, DVector::zeros(4));
    }

    proptest! {
        #[test]
        fn step_never_exceeds_limit(
            jv in proptest::collection::vec(-5.0f64..5.0, 8),
            d in proptest::collection::vec(-1e3f64..1e3, 2),
            limit in 0.1f64..20.0,
        ) {
            let j = DMatrix::from_row_slice(2, 4, &jv);
            let cfg = SolverConfig { max_step_mv: limit, ..Default::default() };
            let s = newton_step(&j, &DVector::from_vec(d), &cfg);
            prop_assert!(s.dv_mv.norm() <= limit * (1.0 + 1e-12));
            prop_assert!(s.dv_mv.iter().all(|x| x.is_finite()));
        }
    }
}
