//! Null-space excitation: where a cell's limited step can also teach its
//! filter something, at no cost to its parameters as the filter sees them.
//!
//! A cell with more tuning gates than parameters (4 gates, `t_sr` and `w`)
//! has directions its learned rows say change nothing: the null space of its
//! own block `J_own` (parameters × gates). The minimum-norm step never moves
//! there, and the array's cells all move alike (one target change for all),
//! so the filter sees the same few directions again and again and learns the
//! gradient only along them. When the true gradient differs along the rest
//! (it bends as the gates move), the steps that follow are planned on stale
//! numbers. A step along the null space is free if the filter is right
//! (neither the cell's parameters nor, through the crosstalk prior
//! `λ̂·J_own`, its neighbours' move) and informative if it is wrong.
//!
//! [`null_space_direction`] picks, inside that null space and orthogonal to
//! the planned step, the direction the rows are least sure about (largest
//! summed prior variance of the own-gate gradients along it). The joint
//! tuner spends a fraction of a full-length step there
//! ([`super::array::JointConfig::excitation`]), alternating its sign from one
//! measurement to the next and between neighbouring cells so the gates do
//! not drift and a cell's own gradient is told apart from its neighbours'.

use nalgebra::{DMatrix, DVector};

use crate::decomposition::symmetric_eigen;

/// Unit vector (over the cell's own gates) in the null space of `j_own`
/// (rows: the cell's parameters; columns: its tuning gates, log space 1/mV),
/// orthogonal to `step` (mV), along which `uncertainty` (the sum of the rows'
/// own-gate covariance blocks, (1/mV)², symmetric) is largest. `None` when
/// there is no such direction: as many parameters as gates (no null space),
/// the null space spanned by the step alone, or non-finite input. The sign
/// is arbitrary (the caller picks it).
///
/// The null space is taken as the eigenvectors of `J_ownᵀ·J_own` beyond the
/// number of rows, i.e. the cell's rows are assumed independent (a rank
/// deficient block only makes some "null" directions slightly active).
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::tuner::excitation::null_space_direction;
/// // one parameter over three gates, sensitive to gate 0 only
/// let j = DMatrix::from_row_slice(1, 3, &[0.02, 0.0, 0.0]);
/// // the filter is least sure along gate 2
/// let p = DMatrix::from_diagonal(&DVector::from_vec(vec![1e-4, 1e-6, 4e-6]));
/// let step = DVector::from_vec(vec![-5.0, 0.0, 0.0]);
/// let e = null_space_direction(&j, &p, &step).unwrap();
/// assert!(e[0].abs() < 1e-12 && e[1].abs() < 1e-12 && (e[2].abs() - 1.0).abs() < 1e-12);
/// ```
pub fn null_space_direction(
    j_own: &DMatrix<f64>,
    uncertainty: &DMatrix<f64>,
    step: &DVector<f64>,
) -> Option<DVector<f64>> {
    let n = j_own.ncols();
    let m = j_own.nrows();
    if m >= n
        || uncertainty.shape() != (n, n)
        || step.len() != n
        || j_own
            .iter()
            .chain(uncertainty.iter())
            .chain(step.iter())
            .any(|x| !x.is_finite())
    {
        return None;
    }
    // null-space basis: eigenvectors of JᵀJ with the n − m smallest eigenvalues
    let eig = symmetric_eigen(j_own.transpose() * j_own)?;
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let mut basis = DMatrix::from_fn(n, n - m, |r, c| eig.eigenvectors[(r, order[c])]);
    // …and within it orthogonal to the step: the null-space combinations
    // `c` with `(N c)·step = 0`, i.e. `c ⟂ a = Nᵀ·step`
    let a = basis.transpose() * step;
    let a_norm = a.norm();
    if a_norm > 1e-12 * step.norm().max(1.0) {
        let a = a / a_norm;
        let k = a.len();
        let keep = symmetric_eigen(DMatrix::identity(k, k) - &a * a.transpose())?;
        let rest: Vec<usize> = (0..k).filter(|&i| keep.eigenvalues[i] > 0.5).collect();
        if rest.is_empty() {
            return None;
        }
        let b = DMatrix::from_fn(k, rest.len(), |r, c| keep.eigenvectors[(r, rest[c])]);
        basis = &basis * b;
    }
    // the basis direction the rows are least sure about
    let projected = basis.transpose() * uncertainty * &basis;
    let small = symmetric_eigen(projected)?;
    let top = (0..small.eigenvalues.len())
        .max_by(|&a, &b| small.eigenvalues[a].total_cmp(&small.eigenvalues[b]))?;
    let e = &basis * small.eigenvectors.column(top);
    let norm = e.norm();
    (norm > 1e-9 && e.iter().all(|x| x.is_finite())).then(|| e / norm)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two parameters over four gates (the simulated cell's shape).
    fn two_by_four() -> DMatrix<f64> {
        DMatrix::from_row_slice(
            2,
            4,
            &[
                -0.004, 0.002, -0.027, -0.015, // t_sr
                -0.002, 0.001, 0.010, -0.001, // w
            ],
        )
    }

    #[test]
    fn direction_is_a_unit_null_vector_orthogonal_to_the_step() {
        let j = two_by_four();
        let p = DMatrix::from_diagonal(&DVector::from_vec(vec![1e-5, 4e-5, 2e-5, 3e-5]));
        let step = DVector::from_vec(vec![1.0, 8.0, 2.0, -3.0]);
        let e = null_space_direction(&j, &p, &step).unwrap();
        assert!((e.norm() - 1.0).abs() < 1e-12);
        assert!((&j * &e).norm() < 1e-12, "J e = {}", &j * &e);
        assert!(e.dot(&step).abs() < 1e-9, "e·step = {}", e.dot(&step));
    }

    #[test]
    fn picks_the_most_uncertain_null_direction() {
        // J sees gates 0 and 1 only: the null space is gates 2 and 3, and
        // the step (gates 0, 1) is orthogonal to it, so the answer is the
        // top eigenvector of P's (2, 3) block: here gate 3 alone
        let j = DMatrix::from_row_slice(2, 4, &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
        let p = DMatrix::from_diagonal(&DVector::from_vec(vec![9.0, 9.0, 1.0, 5.0]));
        let step = DVector::from_vec(vec![3.0, -4.0, 0.0, 0.0]);
        let e = null_space_direction(&j, &p, &step).unwrap();
        assert!(
            e[2].abs() < 1e-12 && (e[3].abs() - 1.0).abs() < 1e-12,
            "{e}"
        );
        // a correlated block: P = [[3, 2], [2, 3]] on gates 2, 3 has its top
        // eigenvector (1, 1)/√2 (eigenvalue 5 against 1)
        let mut p = DMatrix::from_diagonal(&DVector::from_vec(vec![9.0, 9.0, 3.0, 3.0]));
        p[(2, 3)] = 2.0;
        p[(3, 2)] = 2.0;
        let e = null_space_direction(&j, &p, &step).unwrap();
        let h = 0.5f64.sqrt();
        assert!(
            (e[2].abs() - h).abs() < 1e-12 && (e[3] - e[2]).abs() < 1e-12,
            "{e}"
        );
    }

    #[test]
    fn a_step_inside_the_null_space_leaves_the_rest_of_it() {
        // null space = gates 1, 2; the step along gate 1 leaves gate 2
        let j = DMatrix::from_row_slice(1, 3, &[1.0, 0.0, 0.0]);
        let p = DMatrix::from_diagonal(&DVector::from_vec(vec![1.0, 100.0, 1.0]));
        let step = DVector::from_vec(vec![0.0, 2.0, 0.0]);
        let e = null_space_direction(&j, &p, &step).unwrap();
        assert!((e[2].abs() - 1.0).abs() < 1e-12, "{e}");
    }

    #[test]
    fn no_direction_without_a_null_space_or_with_bad_input() {
        let square = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.0, 1.0]);
        let p2 = DMatrix::identity(2, 2);
        let s2 = DVector::from_vec(vec![1.0, 0.0]);
        assert!(null_space_direction(&square, &p2, &s2).is_none());
        // null space of one dimension, spanned by the step itself
        let j = DMatrix::from_row_slice(1, 2, &[1.0, 0.0]);
        assert!(null_space_direction(&j, &p2, &DVector::from_vec(vec![0.0, 1.0])).is_none());
        // non-finite input
        let mut bad = two_by_four();
        bad[(0, 0)] = f64::NAN;
        let p4 = DMatrix::identity(4, 4);
        let s4 = DVector::from_vec(vec![1.0, 0.0, 0.0, 0.0]);
        assert!(null_space_direction(&bad, &p4, &s4).is_none());
        // wrong shapes
        assert!(null_space_direction(&two_by_four(), &p2, &s4).is_none());
    }
}
