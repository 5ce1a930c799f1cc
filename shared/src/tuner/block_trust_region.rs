//! The joint array step inside one trust region per cell: the
//! Levenberg–Marquardt step with a damping `λ_c` per block of gates,
//! optionally on the expected residual under the gradients' uncertainty.
//!
//! The paper's rule takes the minimum-norm Newton step `−J⁺Δ` and scales it
//! down to the step limit. Where `J` is nearly singular (two rows of a cell
//! pointing almost the same way over its gates) that step is long, and
//! scaling it shrinks the well-determined part of the move with the rest: a
//! cell far from its targets then creeps (docs/array-history.md "Steps inside a trust
//! region per cell"). The trust-region step instead minimises
//!
//! `‖Δ + J·Δv‖² + Δvᵀ U Δv` subject to `‖Δv_c‖ ≤ r_c` for every block `c`
//!
//! (`U` PSD: the expected extra squared residual of an uncertain `J`,
//! `Σ_rows κ·C_row`; `U = 0` the plain model residual). With Lagrange
//! multipliers `λ_c ≥ 0`,
//!
//! `Δv(λ) = −(JᵀJ + U + diag(λ_c·I_c) + ε·I)⁻¹ JᵀΔ`,
//!
//! `λ_c = 0` where the block is inside its radius, otherwise the `λ_c` with
//! `‖Δv_c‖ = r_c`. Its direction bends from Newton's toward steepest descent
//! in the blocks that are limited, so at the optimum it does no worse on
//! that cost than the scaled step of the same lengths (the search is capped;
//! should it stop short, the cheaper of the two is taken).

use nalgebra::{DMatrix, DVector};

use crate::solver::bisect_falling;

/// Relative ridge `ε / max diag(JᵀJ)` that makes the normal matrix
/// invertible where `J` has fewer rows than columns (it leaves the step of
/// an unlimited block equal to the minimum-norm one to ~1e-9 relative).
const RIDGE: f64 = 1e-10;
/// Most sweeps over the blocks (the multipliers usually settle in a few;
/// strongly coupled blocks can take hundreds).
const MAX_SWEEPS: usize = 1_000;
/// The sweeps stop when no multiplier changed by more than this, relative.
const SETTLED: f64 = 1e-6;

/// The step (mV) that minimises `‖Δ + J·Δv‖² + Δvᵀ U Δv` (`U` =
/// `uncertainty`, n×n PSD in (unit/mV)², or zero) with every block `c` of
/// gates (consecutive columns, `blocks[c] = (columns, radius r_c mV)`, in
/// column order, covering every column) within `‖Δv_c‖ ≤ r_c`. `None` when
/// there is no `U` and the minimum-norm step `unlimited` already keeps every
/// block within its radius (then it is the answer), when the input is not
/// finite, or when the blocks or `U` do not match `J`'s columns.
///
/// The multipliers are found by coordinate ascent on the dual: with the
/// others fixed, `Δv_c(λ_c) = −(I + λ_c·X_c)⁻¹ x_c` (`x = M⁻¹JᵀΔ` and `X_c`
/// block `c` of `M⁻¹`, `M` the normal matrix with `λ_c = 0`), whose length
/// falls monotonically, so each `λ_c` is the root of one scalar equation
/// (or 0); sweeps repeat until no multiplier moves. The dual is concave,
/// so the sweeps converge to the constrained optimum.
///
/// Invariants: every block of the answer has `‖Δv_c‖ ≤ r_c`, every element
/// is finite; without `U`, a block whose unlimited step fits and that is not
/// pulled by a limited neighbour keeps (nearly) its Newton step.
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::tuner::block_trust_region::block_trust_region_step;
/// // two parameters, two gates; the second row differs from the first by
/// // a gate that acts 100× weaker: J is nearly singular
/// let j = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 1.0, 0.01]);
/// let delta = DVector::from_vec(vec![1.0, 1.02]);
/// // Newton: Δv = (−1, −2), of which the first gate alone fixes nearly all
/// let unlimited = DVector::from_vec(vec![-1.0, -2.0]);
/// let limited = block_trust_region_step(&j, &delta, &unlimited, &[(2, 1.0)], None).unwrap();
/// assert!((limited.norm() - 1.0).abs() < 1e-9);
/// // the scaled Newton step (−0.45, −0.89) leaves ‖Δ + JΔv‖ ≈ 0.79;
/// // the trust-region step leans on gate 0 and leaves far less
/// let left = (&delta + &j * &limited).norm();
/// let scaled = &unlimited / unlimited.norm();
/// assert!(left < 0.1 && (&delta + &j * scaled).norm() > 0.7);
/// ```
pub fn block_trust_region_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    unlimited: &DVector<f64>,
    blocks: &[(usize, f64)],
    uncertainty: Option<&DMatrix<f64>>,
) -> Option<DVector<f64>> {
    let n = jacobian.ncols();
    let finite = |x: &f64| x.is_finite();
    if blocks.iter().map(|b| b.0).sum::<usize>() != n
        || unlimited.len() != n
        || delta.len() != jacobian.nrows()
        || !jacobian.iter().all(finite)
        || !delta.iter().all(finite)
        || !unlimited.iter().all(finite)
        || blocks.iter().any(|b| !(b.1.is_finite() && b.1 >= 0.0))
    {
        return None;
    }
    let starts: Vec<usize> = blocks
        .iter()
        .scan(0, |at, b| {
            let s = *at;
            *at += b.0;
            Some(s)
        })
        .collect();
    let block_norm = |dv: &DVector<f64>, c: usize| dv.rows(starts[c], blocks[c].0).norm();
    if uncertainty.is_none() && (0..blocks.len()).all(|c| block_norm(unlimited, c) <= blocks[c].1) {
        return None;
    }
    let mut a = jacobian.transpose() * jacobian;
    if let Some(u) = uncertainty {
        if u.shape() != (n, n) || !u.iter().all(finite) {
            return None;
        }
        a += (u + u.transpose()) * 0.5;
    }
    let b = jacobian.transpose() * delta;
    let scale = (0..n).map(|i| a[(i, i)]).fold(0.0, f64::max);
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    let ridge = RIDGE * scale;
    // the normal matrix with the multipliers `lambda`, block `skip`'s left out
    let normal = |lambda: &[f64], skip: Option<usize>| {
        let mut m = a.clone();
        for (c, &(len, _)) in blocks.iter().enumerate() {
            let l = if skip == Some(c) { 0.0 } else { lambda[c] };
            for i in starts[c]..starts[c] + len {
                m[(i, i)] += l + ridge;
            }
        }
        m.cholesky()
    };
    let mut lambda = vec![0.0; blocks.len()];
    for _ in 0..MAX_SWEEPS {
        let mut moved = false;
        for (c, &(len, r)) in blocks.iter().enumerate() {
            let chol = normal(&lambda, Some(c))?;
            let x = chol.solve(&b);
            let mut unit = DMatrix::zeros(n, len);
            for i in 0..len {
                unit[(starts[c] + i, i)] = 1.0;
            }
            let inv_cols = chol.solve(&unit);
            let x_c = inv_cols.rows(starts[c], len).clone_owned();
            let x_c = (&x_c + x_c.transpose()) * 0.5;
            if !x_c.iter().chain(x.iter()).all(finite) {
                return None;
            }
            let eig = crate::decomposition::symmetric_eigen(x_c)?;
            let comps: Vec<(f64, f64)> = (0..len)
                .map(|k| {
                    let p = eig.eigenvectors.column(k).dot(&x.rows(starts[c], len));
                    (eig.eigenvalues[k].max(0.0), p)
                })
                .collect();
            let length = |l: f64| {
                comps
                    .iter()
                    .map(|(s, p)| (p / (1.0 + l * s)).powi(2))
                    .sum::<f64>()
                    .sqrt()
            };
            let new = if length(0.0) <= r {
                0.0
            } else {
                // bracket the root: the length falls as 1/λ once λ·σ ≫ 1
                let s_max = comps.iter().map(|c| c.0).fold(0.0, f64::max);
                if !(s_max.is_finite() && s_max > 0.0) {
                    return None;
                }
                let (mut lo, mut hi) = (0.0, 1.0 / s_max);
                let mut grow = 0;
                while length(hi) > r && grow < 200 {
                    lo = hi;
                    hi *= 4.0;
                    grow += 1;
                }
                bisect_falling(length, r, lo, hi, 1e-13)
            };
            if (new - lambda[c]).abs() > SETTLED * new.max(lambda[c]) {
                moved = true;
            }
            lambda[c] = new;
        }
        if !moved {
            break;
        }
    }
    let dv = -normal(&lambda, None)?.solve(&b);
    if !dv.iter().all(finite) {
        return None;
    }
    // the multipliers' tolerance may leave a block a hair long: onto its radius
    let onto_radii = |mut dv: DVector<f64>| {
        for (c, &(len, r)) in blocks.iter().enumerate() {
            let norm = block_norm(&dv, c);
            if norm > r && norm > 0.0 {
                dv.rows_mut(starts[c], len).scale_mut(r / norm);
            }
        }
        dv
    };
    let dv = onto_radii(dv);
    // sweeps cut short by `MAX_SWEEPS` can leave the optimum unreached:
    // never worse on the cost than the scaled Newton step
    let cost = |dv: &DVector<f64>| {
        let spread = uncertainty.map_or(0.0, |u| (dv.transpose() * u * dv)[(0, 0)]);
        (delta + jacobian * dv).norm_squared() + spread
    };
    let scaled = onto_radii(unlimited.clone());
    Some(if cost(&scaled) < cost(&dv) {
        scaled
    } else {
        dv
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The scaled Newton step of the same blocks (the paper's rule, per cell).
    fn scaled(unlimited: &DVector<f64>, blocks: &[(usize, f64)]) -> DVector<f64> {
        let mut dv = unlimited.clone();
        let mut at = 0;
        for &(len, r) in blocks {
            let norm = dv.rows(at, len).norm();
            if norm > r {
                dv.rows_mut(at, len).scale_mut(r / norm);
            }
            at += len;
        }
        dv
    }

    fn min_norm(j: &DMatrix<f64>, delta: &DVector<f64>) -> DVector<f64> {
        -j.clone().svd(true, true).solve(delta, 1e-12).unwrap()
    }

    #[test]
    fn one_block_matches_the_closed_form_levenberg_marquardt_step() {
        // J = diag(2, 0.1): the step along each gate is −2Δ₀/(4+λ), −0.1Δ₁/(0.01+λ)
        let j = DMatrix::from_diagonal(&DVector::from_vec(vec![2.0, 0.1]));
        let delta = DVector::from_vec(vec![1.0, 1.0]);
        let unlimited = min_norm(&j, &delta); // (−0.5, −10)
        let dv = block_trust_region_step(&j, &delta, &unlimited, &[(2, 1.0)], None).unwrap();
        assert!((dv.norm() - 1.0).abs() < 1e-9);
        // solve ‖Δv(λ)‖ = 1 for λ by bisection, independently
        let len = |l: f64| ((2.0 / (4.0 + l)).powi(2) + (0.1 / (0.01 + l)).powi(2)).sqrt();
        let (mut lo, mut hi) = (0.0, 10.0);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if len(mid) > 1.0 {
                lo = mid
            } else {
                hi = mid
            }
        }
        let expected = [-2.0 / (4.0 + lo), -0.1 / (0.01 + lo)];
        assert!(
            (dv[0] - expected[0]).abs() < 1e-6 * expected[0].abs(),
            "{dv}"
        );
        assert!(
            (dv[1] - expected[1]).abs() < 1e-6 * expected[1].abs(),
            "{dv}"
        );
    }

    #[test]
    fn an_uncertain_gate_is_leaned_on_less() {
        // one row over two gates acting equally; gate 1's element is
        // uncertain (variance 4 /mV², U = diag(0, 4)): within the radius 10
        // the cost ‖Δ + JΔv‖² + ΔvᵀUΔv is least at the closed form
        // Δv = −(JᵀJ + U)⁻¹JᵀΔ
        let j = DMatrix::from_row_slice(1, 2, &[1.0, 1.0]);
        let delta = DVector::from_vec(vec![1.0]);
        let unlimited = min_norm(&j, &delta); // (−0.5, −0.5)
        let u = DMatrix::from_diagonal(&DVector::from_vec(vec![0.0, 4.0]));
        let dv = block_trust_region_step(&j, &delta, &unlimited, &[(2, 10.0)], Some(&u)).unwrap();
        // (JᵀJ + U) = [[1, 1], [1, 5]], JᵀΔ = (1, 1): Δv = −(1, 0)
        assert!((dv[0] + 1.0).abs() < 1e-6 && dv[1].abs() < 1e-6, "{dv}");
        // a U that does not match J's columns: no step
        let small = DMatrix::zeros(1, 1);
        assert!(
            block_trust_region_step(&j, &delta, &unlimited, &[(2, 10.0)], Some(&small)).is_none()
        );
    }

    #[test]
    fn a_step_that_fits_is_left_to_newton() {
        let j = DMatrix::from_row_slice(1, 2, &[1.0, 1.0]);
        let delta = DVector::from_vec(vec![0.5]);
        let unlimited = min_norm(&j, &delta);
        assert!(
            block_trust_region_step(&j, &delta, &unlimited, &[(1, 1.0), (1, 1.0)], None).is_none()
        );
    }

    #[test]
    fn bad_input_gives_no_step() {
        let j = DMatrix::from_row_slice(1, 2, &[1.0, f64::NAN]);
        let delta = DVector::from_vec(vec![5.0]);
        let unlimited = DVector::from_vec(vec![-5.0, 0.0]);
        assert!(block_trust_region_step(&j, &delta, &unlimited, &[(2, 1.0)], None).is_none());
        let j = DMatrix::from_row_slice(1, 2, &[1.0, 1.0]);
        // blocks that do not cover the columns
        assert!(block_trust_region_step(&j, &delta, &unlimited, &[(1, 1.0)], None).is_none());
    }

    proptest! {
        /// Every block within its radius, and the model's residual never
        /// above the per-block scaled Newton step's (the rule it replaces).
        #[test]
        fn within_every_radius_and_no_worse_than_scaling(
            rows in 1usize..5,
            elements in proptest::collection::vec(-3.0f64..3.0, 5 * 6),
            d in proptest::collection::vec(-2.0f64..2.0, 5),
            radii in proptest::collection::vec(0.05f64..2.0, 3),
        ) {
            let j = DMatrix::from_fn(rows, 6, |r, c| elements[r * 6 + c]);
            let delta = DVector::from_iterator(rows, d.iter().copied().take(rows));
            let blocks = [(2, radii[0]), (2, radii[1]), (2, radii[2])];
            let unlimited = min_norm(&j, &delta);
            if let Some(dv) = block_trust_region_step(&j, &delta, &unlimited, &blocks, None) {
                let mut at = 0;
                for &(len, r) in &blocks {
                    prop_assert!(dv.rows(at, len).norm() <= r * (1.0 + 1e-12));
                    at += len;
                }
                let left = (&delta + &j * &dv).norm();
                let old = (&delta + &j * scaled(&unlimited, &blocks)).norm();
                prop_assert!(left <= old * (1.0 + 1e-6) + 1e-9, "{left} > {old}");
            }
        }
    }
}
