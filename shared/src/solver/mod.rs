//! Quasi-Newton step: `Δv = −J⁺ Δ` with the minimum-norm pseudo-inverse,
//! limited in Euclidean norm (paper: 10 mV).
//!
//! `J` is m×n (parameters × gates, unit/mV), `Δ = p − p*` (parameter units),
//! `Δv` in mV. Works for under-determined (m < n) and rank-deficient `J`:
//! singular values below `rank_tolerance · σ_max` are treated as zero.
//!
//! [`expected_cost_step`] is the covariance-aware alternative
//! ([`StepRule::ExpectedCost`]): it minimises the squared residual
//! *expected* under the filter's posterior of `J` and bends the step inside
//! the step limit (a Levenberg–Marquardt trust region) instead of scaling it.

mod minimum_norm;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// How a level turns its Jacobian estimate into a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepRule {
    /// The paper's rule: minimum-norm `−J⁺Δ`, scaled down to the step limit
    /// ([`newton_step`]). Ignores the gradient covariance.
    #[default]
    PseudoInverse,
    /// Minimise the expected squared residual under the filter's posterior
    /// of `J`, inside a trust region of the step limit
    /// ([`expected_cost_step`]).
    ExpectedCost,
    /// The direction of [`StepRule::ExpectedCost`] (uncertain directions
    /// avoided), its length from the mean model: the step along that
    /// direction minimising `‖S⁻¹(Δ + Ĵ Δv)‖²`, then scaled to the step
    /// limit ([`covariance_direction_step`]). The expected cost alone shrinks
    /// steps wherever the gradient is uncertain, and a filter learns only
    /// along the directions it moves.
    CovarianceDirection,
}

/// Largest [`SolverConfig::covariance_weight`].
pub const MAX_COVARIANCE_WEIGHT: f64 = 100.0;
/// Largest [`SolverConfig::max_moves_per_iteration`].
pub const MAX_MOVES_PER_ITERATION: u32 = 5;

/// Solver settings for one tuner level.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolverConfig {
    /// Maximal Euclidean norm of one move over the level's gates, mV (paper: 10 mV).
    pub max_step_mv: f64,
    /// Relative singular-value cut-off for the pseudo-inverse.
    pub rank_tolerance: f64,
    /// Step rule (default [`StepRule::PseudoInverse`], the paper's).
    pub rule: StepRule,
    /// [`StepRule::ExpectedCost`] / [`StepRule::CovarianceDirection`]: weight
    /// `κ` of the gradient covariance in the expected cost (dimensionless,
    /// 0 ≤ κ ≤ [`MAX_COVARIANCE_WEIGHT`]; 1 = the posterior expectation).
    /// Default 0: the plain least-squares (Levenberg–Marquardt) trust-region
    /// step. Measured on 50 random devices × 10 seeds (docs/benchmarks.md):
    /// κ = 1 left 37–63 of 2500 changes unconverged, κ = 0.1 5–10, κ = 0 3 —
    /// shrinking steps along poorly known directions stops the filter from
    /// learning them.
    pub covariance_weight: f64,
    /// Moves of at most `max_step_mv` each that one measure-and-decide
    /// iteration may make when the step is longer than one move, without
    /// measuring the parameters in between (the lower levels still run after
    /// every move); 1 ≤ x ≤ [`MAX_MOVES_PER_ITERATION`], default 1 (the paper's).
    pub max_moves_per_iteration: u32,
    /// With several moves per iteration: run the level's `after_move` levels
    /// (sensing dot, line re-centring) after every move (`true`, default) or
    /// only after the last one (`false`: the intermediate moves are bare set
    /// requests, each still within `max_step_mv` and through the guard; the
    /// lower levels then correct the accumulated offset once).
    pub lower_levels_between_moves: bool,
}

impl Default for SolverConfig {
    fn default() -> Self {
        Self {
            max_step_mv: 10.0,
            rank_tolerance: 1e-9,
            rule: StepRule::PseudoInverse,
            covariance_weight: 0.0,
            max_moves_per_iteration: 1,
            lower_levels_between_moves: true,
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
/// `J` m×n (unit/mV), `Δ` (unit), step in mV; singular values
/// `≤ rank_tolerance · σ_max` are treated as zero. The cheapest of three
/// factorisations whose accuracy is certain for this `J` computes it
/// (normal equations with a correction for a provably well-conditioned
/// full-row-rank `J`, the QR of `Jᵀ` for a clearly full-row-rank one, the
/// SVD otherwise; `solver/minimum_norm.rs`): the same minimum-norm
/// solution up to float rounding.
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
    let (dv, rank, _) = minimum_norm::unlimited_step(jacobian, delta, cfg.rank_tolerance);
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

/// Covariance-aware step ([`StepRule::ExpectedCost`]).
///
/// With `J` the m×n gradient estimate (estimator units per mV), `C_i` the
/// n×n covariance of row `i` (`None`: exactly known), `Δ = p − p*` and a
/// per-row scale `s_i > 0` (estimator units, e.g. the tolerance half-width),
/// the step minimises the posterior expectation of the scaled squared
/// residual,
///
/// `E‖S⁻¹(Δ + J Δv)‖² = ‖S⁻¹(Δ + Ĵ Δv)‖² + κ Σ_i Δvᵀ C_i Δv / s_i²`,
///
/// i.e. `Δv(λ) = −(ĴᵀS⁻²Ĵ + κ Σ C_i/s_i² + λ I)⁻¹ ĴᵀS⁻²Δ` with `κ =
/// cfg.covariance_weight`. A direction the filter knows poorly costs its
/// variance and is shortened; a direction in which `Ĵ` is nearly singular but
/// uncertain is not followed. `λ = 0` unless `‖Δv(0)‖ > radius_mv`; then the
/// smallest `λ` with `‖Δv(λ)‖ = radius_mv` (the Levenberg–Marquardt
/// trust-region step: the direction bends toward steepest descent instead of
/// being scaled). Invariants: `‖dv_mv‖ ≤ radius_mv`, every element finite
/// (zero step for non-finite or empty input). With every `C_i = 0` and
/// `‖Δv(0)‖ ≤ radius_mv` it is the minimum-norm Newton step `−J⁺Δ`.
/// `unlimited_norm_mv` is `‖Δv(0)‖`.
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::solver::{expected_cost_step, SolverConfig};
/// let j = DMatrix::from_row_slice(1, 2, &[2.0, 1.0]);
/// let delta = DVector::from_vec(vec![1.0]);
/// let scale = DVector::from_vec(vec![1.0]);
/// let cfg = SolverConfig { covariance_weight: 1.0, ..SolverConfig::default() };
/// let exact = expected_cost_step(&j, &[None], &delta, &scale, &cfg, 10.0);
/// // without uncertainty: −J⁺Δ = −(2, 1)/5
/// assert!((exact.dv_mv[0] + 0.4).abs() < 1e-9 && (exact.dv_mv[1] + 0.2).abs() < 1e-9);
/// // gate 1's element is poorly known: the step leans on gate 0
/// let c = DMatrix::from_diagonal(&DVector::from_vec(vec![0.0, 4.0]));
/// let damped = expected_cost_step(&j, &[Some(c)], &delta, &scale, &cfg, 10.0);
/// assert!(damped.dv_mv[1].abs() < 0.1 * exact.dv_mv[1].abs());
/// ```
pub fn expected_cost_step(
    jacobian: &DMatrix<f64>,
    covariances: &[Option<DMatrix<f64>>],
    delta: &DVector<f64>,
    scale: &DVector<f64>,
    cfg: &SolverConfig,
    radius_mv: f64,
) -> NewtonStep {
    let (m, n) = jacobian.shape();
    let zero = NewtonStep {
        dv_mv: DVector::zeros(n),
        unlimited_norm_mv: 0.0,
        rank: 0,
    };
    let finite = |x: &f64| x.is_finite();
    if m == 0
        || n == 0
        || delta.len() != m
        || scale.len() != m
        || !jacobian.iter().all(finite)
        || !delta.iter().all(finite)
        || !scale.iter().all(|s| s.is_finite() && *s > 0.0)
        || radius_mv.is_nan()
        || radius_mv < 0.0
    {
        return zero;
    }
    let kappa = if cfg.covariance_weight.is_finite() {
        cfg.covariance_weight.max(0.0)
    } else {
        0.0
    };
    let mut js = jacobian.clone();
    let mut ds = delta.clone();
    for i in 0..m {
        js.row_mut(i).scale_mut(1.0 / scale[i]);
        ds[i] /= scale[i];
    }
    let mut a = js.transpose() * &js;
    for (i, c) in covariances.iter().enumerate().take(m) {
        if let Some(c) = c {
            if c.shape() == (n, n) && c.iter().all(finite) {
                // symmetrised; a covariance is PSD, its mean with its transpose too
                let cs = (c + c.transpose()) * (0.5 * kappa / (scale[i] * scale[i]));
                a += cs;
            }
        }
    }
    let b = js.transpose() * &ds;
    let Some(eig) = crate::decomposition::symmetric_eigen(a) else {
        return zero;
    };
    let mu_max = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    let cut = (cfg.rank_tolerance * cfg.rank_tolerance).max(1e-13) * mu_max;
    // coordinates of b in the eigenbasis, kept where A is not numerically singular
    let comps: Vec<(f64, f64, usize)> = (0..n)
        .filter(|&k| eig.eigenvalues[k] > cut && eig.eigenvalues[k] > 0.0)
        .map(|k| (eig.eigenvalues[k], eig.eigenvectors.column(k).dot(&b), k))
        .collect();
    if comps.is_empty() {
        return zero;
    }
    let norm_at = |lambda: f64| {
        comps
            .iter()
            .map(|(mu, c, _)| (c / (mu + lambda)).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let unlimited = norm_at(0.0);
    let mut lambda = 0.0;
    if unlimited > radius_mv {
        if radius_mv == 0.0 {
            return NewtonStep {
                unlimited_norm_mv: unlimited,
                rank: comps.len(),
                ..zero
            };
        }
        // ‖Δv(λ)‖ falls monotonically; ‖Δv(λ)‖ ≤ ‖b‖/λ bounds the bracket.
        lambda = bisect_falling(norm_at, radius_mv, 0.0, b.norm() / radius_mv, 1e-12);
    }
    let mut dv = DVector::zeros(n);
    for (mu, c, k) in &comps {
        dv -= eig.eigenvectors.column(*k) * (c / (mu + lambda));
    }
    let norm = dv.norm();
    if !dv.iter().all(finite) {
        return zero;
    }
    if norm > radius_mv && norm > 0.0 {
        dv *= radius_mv / norm; // rounding only
    }
    NewtonStep {
        dv_mv: dv,
        unlimited_norm_mv: unlimited,
        rank: comps.len(),
    }
}

/// The damping `λ ∈ [lo, hi]` at which a step length `length(λ)` that falls
/// monotonically in `λ` reaches `target`: bisection (at most 200 halvings,
/// until the bracket is within `rel_tol·hi`), returning the bracket's upper
/// end, so `length(λ) ≤ target` whenever `length(hi) ≤ target` held.
pub(crate) fn bisect_falling(
    length: impl Fn(f64) -> f64,
    target: f64,
    mut lo: f64,
    mut hi: f64,
    rel_tol: f64,
) -> f64 {
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if length(mid) > target {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= rel_tol * hi {
            break;
        }
    }
    hi
}

/// [`StepRule::CovarianceDirection`]: the direction `d` of the unlimited
/// [`expected_cost_step`], the length `α = −(Ĵd)ᵀS⁻²Δ / ‖S⁻¹Ĵd‖²` that
/// minimises the mean model's scaled residual along it (kept at `α = 1` if
/// that is not a positive finite number), scaled down to `radius_mv`.
/// Invariants as for [`expected_cost_step`]: `‖dv_mv‖ ≤ radius_mv`, finite;
/// with every `C_i = 0` it is the minimum-norm Newton step, limited.
/// `unlimited_norm_mv` is `‖α d‖`.
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::solver::{covariance_direction_step, SolverConfig};
/// let j = DMatrix::from_row_slice(1, 2, &[2.0, 1.0]);
/// let (delta, scale) = (DVector::from_vec(vec![1.0]), DVector::from_vec(vec![1.0]));
/// // gate 1's element is poorly known: the step leans on gate 0 and still
/// // reaches the target by the estimate (2·Δv₀ + Δv₁ = −1)
/// let c = DMatrix::from_diagonal(&DVector::from_vec(vec![0.0, 4.0]));
/// let cfg = SolverConfig { covariance_weight: 1.0, ..SolverConfig::default() };
/// let s = covariance_direction_step(&j, &[Some(c)], &delta, &scale, &cfg, 10.0);
/// assert!(s.dv_mv[1].abs() < 0.1 * s.dv_mv[0].abs());
/// assert!((2.0 * s.dv_mv[0] + s.dv_mv[1] + 1.0).abs() < 1e-9);
/// ```
pub fn covariance_direction_step(
    jacobian: &DMatrix<f64>,
    covariances: &[Option<DMatrix<f64>>],
    delta: &DVector<f64>,
    scale: &DVector<f64>,
    cfg: &SolverConfig,
    radius_mv: f64,
) -> NewtonStep {
    let d = expected_cost_step(jacobian, covariances, delta, scale, cfg, f64::INFINITY);
    let n = jacobian.ncols();
    if d.dv_mv.norm() == 0.0 || !(radius_mv.is_finite() && radius_mv >= 0.0) {
        return NewtonStep {
            dv_mv: DVector::zeros(n),
            ..d
        };
    }
    let mut jd = jacobian * &d.dv_mv;
    let mut ds = delta.clone();
    for i in 0..jd.len() {
        jd[i] /= scale[i];
        ds[i] /= scale[i];
    }
    let alpha = -jd.dot(&ds) / jd.norm_squared();
    let alpha = if alpha.is_finite() && alpha > 0.0 {
        alpha
    } else {
        1.0
    };
    let mut dv = d.dv_mv * alpha;
    let norm = dv.norm();
    if !(norm.is_finite() && dv.iter().all(|x| x.is_finite())) {
        return NewtonStep {
            dv_mv: DVector::zeros(n),
            unlimited_norm_mv: 0.0,
            rank: 0,
        };
    }
    if norm > radius_mv {
        dv *= radius_mv / norm;
    }
    NewtonStep {
        dv_mv: dv,
        unlimited_norm_mv: norm,
        rank: d.rank,
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

    /// A random symmetric positive semi-definite n×n matrix `L Lᵀ` from `n²` entries.
    fn psd(entries: &[f64], n: usize, scale: f64) -> DMatrix<f64> {
        let l = DMatrix::from_row_slice(n, n, entries);
        &l * l.transpose() * scale
    }

    /// The expected-cost rule with the full posterior weight κ = 1.
    fn damped_cfg() -> SolverConfig {
        SolverConfig {
            rule: StepRule::ExpectedCost,
            covariance_weight: 1.0,
            ..SolverConfig::default()
        }
    }

    #[test]
    fn expected_cost_shrinks_along_a_poorly_known_direction() {
        // two parameters, four gates; row 0's gate-2 element is poorly known
        let j = DMatrix::from_row_slice(2, 4, &[1.0, 0.5, 1.0, 0.0, 0.0, 1.0, 0.2, -0.8]);
        let delta = DVector::from_vec(vec![2.0, -1.0]);
        let scale = DVector::from_vec(vec![1.0, 1.0]);
        let none = [None, None];
        let exact = expected_cost_step(&j, &none, &delta, &scale, &damped_cfg(), 1e6);
        let mut c0 = DMatrix::zeros(4, 4);
        c0[(2, 2)] = 25.0;
        let unsure = [Some(c0), None];
        let damped = expected_cost_step(&j, &unsure, &delta, &scale, &damped_cfg(), 1e6);
        assert!(exact.dv_mv[2].abs() > 0.1);
        assert!(
            damped.dv_mv[2].abs() < 0.1 * exact.dv_mv[2].abs(),
            "gate 2: {} vs {}",
            damped.dv_mv[2],
            exact.dv_mv[2]
        );
        // the well-known directions carry the step instead: the predicted
        // residual stays small
        let residual = &j * &damped.dv_mv + &delta;
        assert!(residual.norm() < 0.2 * delta.norm(), "{residual}");
        // covariance weight 0 ignores the covariance again
        let cfg0 = SolverConfig {
            covariance_weight: 0.0,
            ..damped_cfg()
        };
        let unsure = [Some(DMatrix::identity(4, 4) * 25.0), None];
        let ignored = expected_cost_step(&j, &unsure, &delta, &scale, &cfg0, 1e6);
        assert!((ignored.dv_mv - exact.dv_mv).norm() < 1e-9);
    }

    #[test]
    fn ill_conditioned_learned_jacobian_does_not_step_along_its_null_direction() {
        // Rows almost parallel: the estimate's second singular direction
        // u = (0, 1, 0, 0) is known only to ±0.3 per element, but the
        // estimate says 1e-3. The pseudo-inverse follows u for hundreds of mV.
        let eps = 1e-3;
        let j = DMatrix::from_row_slice(2, 4, &[1.0, 0.0, 0.5, 0.0, 1.0, eps, 0.5, 0.0]);
        let delta = DVector::from_vec(vec![1.0, 1.5]);
        let scale = DVector::from_vec(vec![0.1, 0.1]);
        let u = DVector::from_vec(vec![0.0, 1.0, 0.0, 0.0]);
        let plain = newton_step(&j, &delta, &SolverConfig::default());
        assert!(plain.unlimited_norm_mv > 100.0);
        assert!(plain.dv_mv.dot(&u).abs() > 0.99 * plain.dv_mv.norm());
        let c = DMatrix::identity(4, 4) * 0.09;
        let covs = [Some(c.clone()), Some(c)];
        let damped = expected_cost_step(&j, &covs, &delta, &scale, &damped_cfg(), 10.0);
        assert!(damped.dv_mv.norm() > 0.1, "it still moves");
        assert!(
            damped.dv_mv.dot(&u).abs() < 0.05 * damped.dv_mv.norm(),
            "{}",
            damped.dv_mv
        );
        // and it moves toward the targets along the known direction
        let known = DVector::from_vec(vec![1.0, 0.0, 0.5, 0.0]);
        assert!(damped.dv_mv.dot(&known) < 0.0);
        // It is the covariance that does this: without it (κ = 0, the
        // default) the 10 mV trust region bends the step only a little here,
        // and it still goes mostly along u (a documented limitation).
        let lm = SolverConfig {
            covariance_weight: 0.0,
            ..damped_cfg()
        };
        let tr = expected_cost_step(&j, &covs, &delta, &scale, &lm, 10.0);
        assert!(tr.unlimited_norm_mv > 100.0);
        assert!((tr.dv_mv.norm() - 10.0).abs() < 1e-6);
        assert!(
            tr.dv_mv.dot(&u).abs() > 0.9 * tr.dv_mv.norm(),
            "{}",
            tr.dv_mv
        );
        // with a tight trust region it does bend toward steepest descent
        let tight = expected_cost_step(&j, &covs, &delta, &scale, &lm, 0.1);
        assert!(tight.dv_mv.dot(&u).abs() < 0.5 * tight.dv_mv.norm());
    }

    #[test]
    fn expected_cost_refuses_nonsense_with_a_zero_step() {
        let j = DMatrix::from_row_slice(1, 2, &[1.0, 1.0]);
        let d = DVector::from_vec(vec![1.0]);
        let bad_scale = DVector::from_vec(vec![0.0]);
        let s = expected_cost_step(&j, &[None], &d, &bad_scale, &damped_cfg(), 10.0);
        assert_eq!(s.dv_mv, DVector::zeros(2));
        let nan = DVector::from_vec(vec![f64::NAN]);
        let ones = DVector::from_vec(vec![1.0]);
        let s = expected_cost_step(&j, &[None], &nan, &ones, &damped_cfg(), 10.0);
        assert_eq!(s.dv_mv, DVector::zeros(2));
    }

    proptest! {
        #[test]
        fn expected_cost_step_never_exceeds_the_radius(
            jv in proptest::collection::vec(-5.0f64..5.0, 8),
            c0 in proptest::collection::vec(-2.0f64..2.0, 16),
            c1 in proptest::collection::vec(-2.0f64..2.0, 16),
            cscale in prop_oneof![Just(0.0), 1e-6f64..1e-3, 1e-3f64..1e3],
            d in proptest::collection::vec(-1e3f64..1e3, 2),
            s in proptest::collection::vec(1e-3f64..1e2, 2),
            radius in 0.0f64..20.0,
            weight in 0.0f64..100.0,
        ) {
            let j = DMatrix::from_row_slice(2, 4, &jv);
            let covs = [Some(psd(&c0, 4, cscale)), Some(psd(&c1, 4, cscale))];
            let cfg = SolverConfig { covariance_weight: weight, ..damped_cfg() };
            let st = expected_cost_step(
                &j, &covs, &DVector::from_vec(d), &DVector::from_vec(s), &cfg, radius,
            );
            prop_assert!(st.dv_mv.iter().all(|x| x.is_finite()));
            prop_assert!(st.dv_mv.norm() <= radius * (1.0 + 1e-12), "{} > {radius}", st.dv_mv.norm());
        }

        /// With a negligible covariance and room enough, the step is the
        /// minimum-norm Newton step, derived here independently as
        /// `−Jᵀ (J Jᵀ)⁻¹ Δ` (full row rank).
        #[test]
        fn expected_cost_reduces_to_the_newton_step_for_a_tiny_covariance(
            jv in proptest::collection::vec(-5.0f64..5.0, 8),
            c0 in proptest::collection::vec(-1.0f64..1.0, 16),
            d in proptest::collection::vec(-10.0f64..10.0, 2),
            s in proptest::collection::vec(0.1f64..10.0, 2),
        ) {
            let j = DMatrix::from_row_slice(2, 4, &jv);
            let sv = j.clone().svd(false, false).singular_values;
            prop_assume!(sv.min() > 0.2 * sv.max() && sv.min() > 0.5);
            let delta = DVector::from_vec(d);
            let gram_inv = (&j * j.transpose()).try_inverse().unwrap();
            let expected = -(j.transpose() * gram_inv * &delta);
            let tiny = psd(&c0, 4, 1e-14);
            let covs = [Some(tiny.clone()), Some(tiny)];
            let st = expected_cost_step(
                &j, &covs, &delta, &DVector::from_vec(s), &damped_cfg(), 1e6,
            );
            prop_assert!(
                (&st.dv_mv - &expected).norm() <= 1e-6 * (1.0 + expected.norm()),
                "{} vs {}", st.dv_mv, expected
            );
        }
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
