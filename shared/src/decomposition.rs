//! Eigen- and singular-value decompositions that always return.
//!
//! nalgebra's `svd`, `symmetric_eigen` and `symmetric_eigenvalues` iterate
//! until they converge, with no limit (`max_niter = 0`), and panic on an
//! empty matrix. A non-finite entry, or an overflow inside the iteration,
//! never converges: the call never returns, and a server thread hangs. Every
//! decomposition of the crate's own code goes through this module instead:
//!
//! * the same tolerances as nalgebra's defaults (`ε` for the symmetric
//!   eigendecomposition, `5ε` for the SVD), so a decomposition that
//!   converges is bit-identical to nalgebra's unbounded one;
//! * at most [`MAX_ITERATIONS`] sweeps;
//! * `None` for an empty or non-finite matrix, or one that did not converge.
//!
//! The caller decides what `None` means (a zero step, a refused covariance).

use nalgebra::{DMatrix, DVector, Dyn, SymmetricEigen, SVD};

/// Most QR sweeps one decomposition may take. Converging ones take a few
/// per dimension (tens for the crate's matrices of at most 64×64); the bound
/// only ends one that would never converge.
pub const MAX_ITERATIONS: usize = 10_000;

fn usable(m: &DMatrix<f64>) -> bool {
    !m.is_empty() && m.iter().all(|x| x.is_finite())
}

/// The eigendecomposition of the symmetric matrix `m` (its lower triangle is
/// read), eigenvalues unordered, as nalgebra's `symmetric_eigen`; `None` if
/// `m` is empty, not square, non-finite or it did not converge.
///
/// ```
/// use nalgebra::DMatrix;
/// use spintune::decomposition::symmetric_eigen;
/// let m = DMatrix::from_row_slice(2, 2, &[2.0, 1.0, 1.0, 2.0]);
/// let mut l: Vec<f64> = symmetric_eigen(m).unwrap().eigenvalues.iter().copied().collect();
/// l.sort_by(f64::total_cmp);
/// assert!((l[0] - 1.0).abs() < 1e-12 && (l[1] - 3.0).abs() < 1e-12);
/// assert!(symmetric_eigen(DMatrix::from_element(2, 2, f64::NAN)).is_none());
/// assert!(symmetric_eigen(DMatrix::zeros(0, 0)).is_none());
/// ```
pub fn symmetric_eigen(m: DMatrix<f64>) -> Option<SymmetricEigen<f64, Dyn>> {
    if !usable(&m) || !m.is_square() {
        return None;
    }
    SymmetricEigen::try_new(m, f64::EPSILON, MAX_ITERATIONS)
}

/// The eigenvalues of the symmetric matrix `m`, unordered
/// ([`symmetric_eigen`]'s, the same values as nalgebra's
/// `symmetric_eigenvalues`).
///
/// ```
/// use nalgebra::DMatrix;
/// use spintune::decomposition::symmetric_eigenvalues;
/// let l = symmetric_eigenvalues(DMatrix::from_diagonal_element(3, 3, 2.0)).unwrap();
/// assert_eq!(l.as_slice(), &[2.0, 2.0, 2.0]);
/// assert!(symmetric_eigenvalues(DMatrix::from_element(1, 1, f64::INFINITY)).is_none());
/// ```
pub fn symmetric_eigenvalues(m: DMatrix<f64>) -> Option<DVector<f64>> {
    symmetric_eigen(m).map(|e| e.eigenvalues)
}

/// The SVD of `m`, singular values in descending order, as nalgebra's
/// `svd(compute_u, compute_v)`; `None` if `m` is empty, non-finite or it did
/// not converge.
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::decomposition::svd;
/// let j = DMatrix::from_row_slice(2, 3, &[1.0, 0.0, 0.0, 0.0, 2.0, 0.0]);
/// let s = svd(j, true, true).unwrap();
/// assert_eq!(s.singular_values.as_slice(), &[2.0, 1.0]);
/// let x = s.solve(&DVector::from_vec(vec![1.0, 4.0]), 1e-12).unwrap();
/// assert_eq!(x.as_slice(), &[1.0, 2.0, 0.0]);
/// assert!(svd(DMatrix::from_element(2, 2, f64::NAN), false, false).is_none());
/// ```
pub fn svd(m: DMatrix<f64>, compute_u: bool, compute_v: bool) -> Option<SVD<f64, Dyn, Dyn>> {
    let mut s = svd_unordered(m, compute_u, compute_v)?;
    // nalgebra's `SVD::try_new`: the unordered decomposition, then sorted
    s.sort_by_singular_values();
    Some(s)
}

/// [`svd`] with the singular values in no particular order (nalgebra's
/// `svd_unordered`): a caller whose results must stay bit-identical to an
/// unordered decomposition's.
pub fn svd_unordered(
    m: DMatrix<f64>,
    compute_u: bool,
    compute_v: bool,
) -> Option<SVD<f64, Dyn, Dyn>> {
    if !usable(&m) {
        return None;
    }
    SVD::try_new_unordered(m, compute_u, compute_v, 5.0 * f64::EPSILON, MAX_ITERATIONS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Where nalgebra's unbounded decompositions converge, the bounded
        /// ones give the same bits.
        #[test]
        fn converging_decompositions_match_nalgebra_bit_for_bit(
            rows in 1usize..=6,
            cols in 1usize..=6,
            v in proptest::collection::vec(-1e3f64..1e3, 36),
        ) {
            let m = DMatrix::from_column_slice(rows, cols, &v[..rows * cols]);
            let ours = svd(m.clone(), true, true).unwrap();
            let theirs = m.clone().svd(true, true);
            prop_assert_eq!(&ours.singular_values, &theirs.singular_values);
            prop_assert_eq!(&ours.u, &theirs.u);
            prop_assert_eq!(&ours.v_t, &theirs.v_t);
            let ours = svd_unordered(m.clone(), false, true).unwrap();
            prop_assert_eq!(&ours.singular_values, &m.clone().svd_unordered(false, true).singular_values);
            let s = &m.transpose() * &m;
            let ours = symmetric_eigen(s.clone()).unwrap();
            let theirs = s.clone().symmetric_eigen();
            prop_assert_eq!(&ours.eigenvalues, &theirs.eigenvalues);
            prop_assert_eq!(&ours.eigenvectors, &theirs.eigenvectors);
            prop_assert_eq!(&symmetric_eigenvalues(s.clone()).unwrap(), &s.symmetric_eigenvalues());
        }

        /// A non-finite entry anywhere: `None`, at once.
        #[test]
        fn a_non_finite_entry_is_refused(
            n in 1usize..=5,
            at in 0usize..25,
            bad in prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY)],
        ) {
            let mut m = DMatrix::from_element(n, n, 1.0);
            m[at % (n * n)] = bad;
            prop_assert!(svd(m.clone(), true, true).is_none());
            prop_assert!(svd_unordered(m.clone(), true, true).is_none());
            prop_assert!(symmetric_eigen(m.clone()).is_none());
            prop_assert!(symmetric_eigenvalues(m).is_none());
        }
    }

    #[test]
    fn empty_and_non_square_matrices_are_refused_not_a_panic() {
        assert!(svd(DMatrix::zeros(0, 3), true, true).is_none());
        assert!(svd_unordered(DMatrix::zeros(2, 0), true, true).is_none());
        assert!(symmetric_eigen(DMatrix::zeros(2, 3)).is_none());
    }
}
