//! The unlimited minimum-norm step `−J⁺Δ` (mV) for an m×n Jacobian `J`
//! (unit/mV) and offsets `Δ = p − p*` (unit), singular values at or below
//! `rank_tolerance · σ_max` treated as zero.
//!
//! Three factorisations compute it; [`unlimited_step`] takes the cheapest
//! whose accuracy is certain for the `J` at hand, from bounds that cost no
//! SVD:
//!
//! | path | taken when | cost (m ≤ n) |
//! |---|---|---|
//! | [`Path::NormalEquations`] | at least [`NORMAL_EQUATIONS_MIN_ROWS`] rows, full row rank and `κ(J)² ≤` [`NORMAL_EQUATIONS_MAX_CONDITION`], provably | `J Jᵀ` and its Cholesky, O(n·m²) in one matrix product |
//! | [`Path::Qr`] | full row rank, provably clear of the cut-off | Householder QR of `Jᵀ`, O(n·m²) |
//! | [`Path::Svd`] | anything else (rank deficient, near the cut-off, m > n) | SVD of `J` |
//!
//! All three give the same minimum-norm solution up to float rounding (the
//! tests below compare each with the SVD), so which path runs never changes
//! which singular values are kept: the two fast paths only run when every
//! singular value is at least twice the cut-off.

use nalgebra::{DMatrix, DVector};

/// Largest provable bound on `κ(J Jᵀ) = κ(J)²` for which the normal
/// equations are used (dimensionless). The first solve's relative error is
/// about `κ(J Jᵀ)·ε ≤ 1e6 · 1.1e-16 ≈ 1e-10`; one correction with the
/// residual multiplies it by about the same factor again, which leaves
/// rounding. The bound `‖L‖_F² ‖L⁻¹‖_F²` overestimates `κ(J Jᵀ)` by at most
/// `m²`: at 32 rows every `J` with `κ(J)` up to about 30 takes this path.
pub(super) const NORMAL_EQUATIONS_MAX_CONDITION: f64 = 1e6;

/// Fewest rows (parameters) for which the normal equations are tried. A
/// single double dot's levels have at most 2 rows (t_sr and w), where the
/// QR path costs well under a microsecond and the normal equations would
/// save nothing; they keep the QR path, so every single-cell figure in the
/// docs, measured on it, stays reproducible bit for bit. The saving is at
/// array size (a 9-cell array's joint step has 18 rows; the core bench's
/// 64×32: 41 → 20 µs, docs/core-benchmarks.md).
pub(super) const NORMAL_EQUATIONS_MIN_ROWS: usize = 3;

/// Which factorisation computed a step ([`unlimited_step`] reports it; the
/// tests pin which one runs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Path {
    /// Cholesky of `J Jᵀ`, one correction ([`normal_equations_step`]).
    NormalEquations,
    /// Householder QR of `Jᵀ` ([`qr_step`]).
    Qr,
    /// SVD with the rank cut-off ([`svd_step`]).
    Svd,
}

/// `−J⁺Δ` (mV), the rank kept and the path that computed it. `J` must be
/// non-empty and finite (the caller's check); a `Δ` of the wrong length
/// takes the SVD path, which returns a zero step for it.
pub(super) fn unlimited_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    rank_tolerance: f64,
) -> (DVector<f64>, usize, Path) {
    let (m, n) = jacobian.shape();
    if delta.len() == m && m <= n {
        if m >= NORMAL_EQUATIONS_MIN_ROWS {
            if let Some(dv) = normal_equations_step(jacobian, delta, rank_tolerance) {
                return (dv, m, Path::NormalEquations);
            }
        }
        if let Some(dv) = qr_step(jacobian, delta, rank_tolerance) {
            return (dv, m, Path::Qr);
        }
    }
    let (dv, rank) = svd_step(jacobian, delta, rank_tolerance);
    (dv, rank, Path::Svd)
}

/// The unlimited step `−J⁺Δ = −Jᵀ (J Jᵀ)⁻¹ Δ` (mV) for an m×n `J` with
/// m ≤ n, by the Cholesky factor `L` of `J Jᵀ`, plus one correction with
/// the residual `Δ − J x` (iterative refinement; `x` stays in the row space
/// of `J`, so it stays the minimum-norm solution). `None` unless
/// `J Jᵀ` is positive definite and provably well conditioned:
/// `κ(J Jᵀ) ≤ ‖L‖_F² ‖L⁻¹‖_F² ≤` [`NORMAL_EQUATIONS_MAX_CONDITION`], and
/// `σ_min/σ_max ≥ 1/√bound` at least twice `rank_tolerance` (so the SVD's
/// rule would keep every singular value).
fn normal_equations_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    rank_tolerance: f64,
) -> Option<DVector<f64>> {
    let m = jacobian.nrows();
    let gram = jacobian * jacobian.transpose();
    let cholesky = gram.cholesky()?;
    let l_transposed = cholesky.l().transpose();
    // σ_max(JJᵀ) = ‖L‖₂² ≤ ‖L‖_F², 1/σ_min(JJᵀ) = ‖L⁻¹‖₂² ≤ ‖L⁻¹‖_F²
    let bound = (l_transposed.norm() * upper_triangular_inverse_norm(&l_transposed, m)).powi(2);
    // (false for NaN too)
    let well_conditioned =
        bound <= NORMAL_EQUATIONS_MAX_CONDITION && 2.0 * rank_tolerance * bound.sqrt() < 1.0;
    if !well_conditioned {
        return None;
    }
    let solve = |b: &DVector<f64>| jacobian.tr_mul(&cholesky.solve(b));
    let mut x = solve(delta);
    x += solve(&(delta - jacobian * &x));
    let dv = -x;
    dv.iter().all(|x| x.is_finite()).then_some(dv)
}

/// The unlimited step `−J⁺Δ` (mV) by the SVD of `J`, singular values at or
/// below `rank_tolerance · σ_max` treated as zero; and the rank kept. Any
/// shape and rank; a zero step if nothing is kept.
fn svd_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    rank_tolerance: f64,
) -> (DVector<f64>, usize) {
    let n = jacobian.ncols();
    let Some(svd) = crate::decomposition::svd(jacobian.clone(), true, true) else {
        return (DVector::zeros(n), 0);
    };
    let smax = svd.singular_values.max();
    let eps = (rank_tolerance * smax).max(f64::MIN_POSITIVE);
    let rank = svd.singular_values.iter().filter(|&&s| s > eps).count();
    let dv = if rank == 0 {
        DVector::zeros(n)
    } else {
        match svd.solve(delta, eps) {
            Ok(x) => -x,
            Err(_) => DVector::zeros(n),
        }
    };
    (dv, rank)
}

/// The unlimited step `−J⁺Δ` (mV) for an m×n `J` with m ≤ n and full row
/// rank, by the QR decomposition `Jᵀ = Q R` (Q n×m orthonormal, R m×m upper
/// triangular): `J = Rᵀ Qᵀ`, so `J⁺ = Q R⁻ᵀ` and `Δv = −Q y` with `Rᵀ y = Δ`.
/// O(n·m²) instead of the SVD of `J` with both singular-vector sets; the
/// same minimum-norm solution up to float rounding (both are backward
/// stable: no normal equations, so no squared condition number).
///
/// `J` and `R` have the same singular values. `None` unless they are
/// provably all kept by the cut-off rule with a factor 2 to spare:
/// `1/‖R⁻¹‖_F ≤ σ_min` must exceed twice the cut-off computed from
/// `‖R‖_F ≥ σ_max` (O(m³/6), no SVD). Near the cut-off (within about 2·m of
/// it in condition number) and for any rank-deficient `J` [`unlimited_step`]
/// takes the SVD path, so rounding differences between the two factorisations
/// cannot change which singular values are kept.
fn qr_step(
    jacobian: &DMatrix<f64>,
    delta: &DVector<f64>,
    rank_tolerance: f64,
) -> Option<DVector<f64>> {
    let m = jacobian.nrows();
    let qr = jacobian.transpose().qr();
    let r = qr.r();
    // Bounds without an SVD: σ_max ≤ ‖R‖_F and σ_min = 1/‖R⁻¹‖₂ ≥ 1/‖R⁻¹‖_F.
    let sigma_max_bound = r.norm();
    let sigma_min_bound = 1.0 / upper_triangular_inverse_norm(&r, m);
    let eps_bound = (rank_tolerance * sigma_max_bound).max(f64::MIN_POSITIVE);
    // (false for NaN too)
    let clearly_full_rank =
        sigma_min_bound.partial_cmp(&(2.0 * eps_bound)) == Some(std::cmp::Ordering::Greater);
    if !clearly_full_rank {
        return None;
    }
    let y = r.tr_solve_upper_triangular(delta)?;
    let dv = -(qr.q() * y);
    dv.iter().all(|x| x.is_finite()).then_some(dv)
}

/// `‖R⁻¹‖_F` of an m×m upper-triangular `R`, column by column (`R x = e_j`
/// by back substitution, O(m³/6), no m×m temporary); `+∞` or NaN if `R` is
/// singular.
fn upper_triangular_inverse_norm(r: &DMatrix<f64>, m: usize) -> f64 {
    let mut x = vec![0.0; m];
    let mut sum = 0.0;
    for j in 0..m {
        x[..=j].fill(0.0);
        x[j] = 1.0;
        for k in (0..=j).rev() {
            let col = r.column(k);
            x[k] /= col[k];
            let xk = x[k];
            for (xi, &r_ik) in x[..k].iter_mut().zip(&col.as_slice()[..k]) {
                *xi -= xk * r_ik;
            }
        }
        sum += x[..=j].iter().map(|v| v * v).sum::<f64>();
    }
    sum.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    use crate::solver::{newton_step, SolverConfig};

    /// The benchmark's largest size: a dense, well-conditioned 32×64 `J`
    /// (uniform entries, κ ≈ 6) and offsets.
    fn dense_64x32() -> (DMatrix<f64>, DVector<f64>) {
        let (m, n) = (32, 64);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6432);
        let j = DMatrix::from_fn(m, n, |_, _| rng.gen_range(-1.0..1.0));
        let delta = DVector::from_fn(m, |_, _| rng.gen_range(-10.0..10.0));
        (j, delta)
    }

    /// `J` with rows scaled from 1 down to `10^-decades` (8×20).
    fn graded(decades: f64, seed: u64) -> (DMatrix<f64>, DVector<f64>) {
        let (m, n) = (8, 20);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let j = DMatrix::from_fn(m, n, |r, _| {
            rng.gen_range(-1.0..1.0) * 10f64.powf(-decades * r as f64 / (m - 1) as f64)
        });
        let delta = DVector::from_fn(m, |_, _| rng.gen_range(-1.0..1.0));
        (j, delta)
    }

    fn condition(j: &DMatrix<f64>) -> f64 {
        let sv = j.clone().svd(false, false).singular_values;
        sv.max() / sv.min()
    }

    /// Relative difference `‖a − b‖/‖b‖`.
    fn rel(a: &DVector<f64>, b: &DVector<f64>) -> f64 {
        (a - b).norm() / b.norm()
    }

    /// Backward error of a step: `‖J Δv + Δ‖ / (‖J‖·‖Δv‖)`.
    fn backward(j: &DMatrix<f64>, dv: &DVector<f64>, delta: &DVector<f64>) -> f64 {
        (j * dv + delta).norm() / (j.norm() * dv.norm())
    }

    #[test]
    fn every_path_agrees_at_64x32_and_the_normal_equations_run() {
        let (j, delta) = dense_64x32();
        let (svd, rank) = svd_step(&j, &delta, 1e-9);
        assert_eq!(rank, 32);
        let normal = normal_equations_step(&j, &delta, 1e-9).expect("well conditioned");
        let qr = qr_step(&j, &delta, 1e-9).expect("full row rank");
        for (name, dv) in [("normal equations", &normal), ("QR", &qr)] {
            assert!(rel(dv, &svd) <= 1e-10, "{name}: {:e}", rel(dv, &svd));
            assert!(backward(&j, dv, &delta) <= 1e-15, "{name}");
        }
        // the dispatch takes the cheapest path, and newton_step reports it all
        let (dv, rank, path) = unlimited_step(&j, &delta, 1e-9);
        assert_eq!((rank, path), (32, Path::NormalEquations));
        assert_eq!(dv, normal);
        let cfg = SolverConfig {
            max_step_mv: 1e12,
            ..SolverConfig::default()
        };
        let step = newton_step(&j, &delta, &cfg);
        assert_eq!((step.rank, &step.dv_mv), (32, &normal));
    }

    #[test]
    fn an_ill_conditioned_jacobian_takes_the_qr_path_and_stays_accurate() {
        // κ ≈ 10⁶, far above the 1e-9 cut-off: normal equations would lose
        // about κ²·ε ≈ 1e-4 relative, so they decline; the QR path agrees
        // with the SVD and solves J Δv = −Δ to a backward error of rounding.
        let (j, delta) = graded(6.0, 86);
        assert!(condition(&j) > 1e5, "κ {}", condition(&j));
        assert!(normal_equations_step(&j, &delta, 1e-9).is_none());
        let (dv, rank, path) = unlimited_step(&j, &delta, 1e-9);
        assert_eq!((rank, path), (8, Path::Qr));
        let (svd, _) = svd_step(&j, &delta, 1e-9);
        assert!(rel(&dv, &svd) <= 1e-9, "{:e}", rel(&dv, &svd));
        assert!(backward(&j, &dv, &delta) <= 1e-15);
    }

    #[test]
    fn the_normal_equations_decline_above_their_bound_and_just_below_it_stay_accurate() {
        // Around the bound's edge: rows graded over 2 to 3 decades give
        // κ(J) from about 10² to 10³, i.e. κ² from 10⁴ to 10⁶; the bound
        // overestimates κ² by at most m² = 64.
        let (mut taken, mut declined) = (0, 0);
        for seed in 0..20 {
            let (j, delta) = graded(2.0 + 0.05 * seed as f64, seed);
            let kappa = condition(&j);
            let (svd, _) = svd_step(&j, &delta, 1e-9);
            match normal_equations_step(&j, &delta, 1e-9) {
                Some(dv) => {
                    taken += 1;
                    // taken only where the bound allows it ...
                    assert!(kappa * kappa <= NORMAL_EQUATIONS_MAX_CONDITION);
                    // ... and then as accurate as the SVD
                    assert!(rel(&dv, &svd) <= 1e-10, "κ {kappa}: {:e}", rel(&dv, &svd));
                    assert!(backward(&j, &dv, &delta) <= 1e-15);
                }
                // declined: never below the bound's certain range
                None => {
                    declined += 1;
                    assert!(
                        64.0 * kappa * kappa > NORMAL_EQUATIONS_MAX_CONDITION,
                        "κ {kappa}"
                    );
                }
            }
        }
        assert!(
            taken > 0 && declined > 0,
            "taken {taken}, declined {declined}"
        );
    }

    #[test]
    fn a_large_rank_tolerance_sends_the_step_to_the_svd() {
        // singular values 1, 0.5, 0.25 with a cut-off of 0.3·σ_max: the
        // third is dropped, which only the SVD path does.
        let j = DMatrix::from_row_slice(
            3,
            4,
            &[1.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.25, 0.0],
        );
        let delta = DVector::from_vec(vec![1.0, 1.0, 1.0]);
        let (dv, rank, path) = unlimited_step(&j, &delta, 0.3);
        assert_eq!((rank, path), (2, Path::Svd));
        assert_eq!(dv[2], 0.0);
        assert!((dv[0] + 1.0).abs() < 1e-12 && (dv[1] + 2.0).abs() < 1e-12);
        // the same J with the default cut-off keeps all three, by the normal equations
        let (_, rank, path) = unlimited_step(&j, &delta, 1e-9);
        assert_eq!((rank, path), (3, Path::NormalEquations));
    }

    #[test]
    fn a_single_double_dot_s_two_rows_keep_the_qr_path() {
        // t_sr and w over N, SA, SB, T (ns/mV and µV/mV): well conditioned,
        // but below NORMAL_EQUATIONS_MIN_ROWS, so bit for bit the QR step.
        let j = DMatrix::from_row_slice(2, 4, &[0.8, -1.1, 0.4, 0.3, 3.0, 1.5, -4.2, 2.2]);
        let delta = DVector::from_vec(vec![12.0, -35.0]);
        let (dv, rank, path) = unlimited_step(&j, &delta, 1e-9);
        assert_eq!((rank, path), (2, Path::Qr));
        assert_eq!(Some(dv), qr_step(&j, &delta, 1e-9));
    }

    #[test]
    fn near_the_rank_cut_off_the_svd_path_decides() {
        // σ_min/σ_max = 1.5e-9: above the 1e-9 cut-off, below twice it. Both
        // fast paths decline; the SVD path keeps both singular values.
        let j = DMatrix::from_row_slice(2, 3, &[1.0, 0.0, 0.0, 0.0, 1.5e-9, 0.0]);
        let delta = DVector::from_vec(vec![1e-9, 1e-9]);
        assert!(normal_equations_step(&j, &delta, 1e-9).is_none());
        assert!(qr_step(&j, &delta, 1e-9).is_none());
        let (dv, rank, path) = unlimited_step(&j, &delta, 1e-9);
        assert_eq!((rank, path), (2, Path::Svd));
        assert!((dv[1] + 1.0 / 1.5).abs() < 1e-9, "{dv}");
    }

    proptest! {
        /// Both fast paths (full row rank, m ≤ n) give the minimum-norm step
        /// `−Jᵀ(JJᵀ)⁻¹Δ` to float rounding (1e-13·κ² relative, κ =
        /// σ_max/σ_min ≤ 30, where the reference from an LU of `JJᵀ` is
        /// itself accurate), and so does the SVD path, less tightly:
        /// nalgebra's SVD stops its iteration at ~1e-11 relative. The
        /// dispatch takes the normal equations from
        /// `NORMAL_EQUATIONS_MIN_ROWS` rows on wherever `m²κ²`, an upper
        /// bound of their condition bound, is within theirs, and the QR
        /// path below.
        #[test]
        fn every_path_matches_the_minimum_norm_step(
            m in 1usize..=8,
            extra in 0usize..=8,
            jv in proptest::collection::vec(-5.0f64..5.0, 128),
            d in proptest::collection::vec(-100.0f64..100.0, 8),
        ) {
            let n = m + extra;
            let j = DMatrix::from_column_slice(m, n, &jv[..m * n]);
            let kappa = condition(&j);
            prop_assume!(kappa <= 30.0);
            let delta = DVector::from_column_slice(&d[..m]);
            let exact = -(j.transpose() * (&j * j.transpose()).lu().solve(&delta).unwrap());
            let qr = qr_step(&j, &delta, 1e-9);
            prop_assert!(qr.is_some());
            let qr = qr.unwrap();
            let (svd, rank) = svd_step(&j, &delta, 1e-9);
            prop_assert_eq!(rank, m);
            prop_assert!(rel(&qr, &exact) <= 1e-13 * kappa * kappa, "QR: κ {kappa}, rel {:e}", rel(&qr, &exact));
            prop_assert!(rel(&svd, &exact) <= 1e-10, "SVD: κ {kappa}, rel {:e}", rel(&svd, &exact));
            let (dv, rank, path) = unlimited_step(&j, &delta, 1e-9);
            prop_assert_eq!(rank, m);
            prop_assert!(rel(&dv, &exact) <= 1e-13 * kappa * kappa, "{path:?}: κ {kappa}, rel {:e}", rel(&dv, &exact));
            if m < NORMAL_EQUATIONS_MIN_ROWS {
                prop_assert_eq!(path, Path::Qr);
            } else if (m * m) as f64 * kappa * kappa <= NORMAL_EQUATIONS_MAX_CONDITION {
                prop_assert_eq!(path, Path::NormalEquations);
            }
        }
    }
}
