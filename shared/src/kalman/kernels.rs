//! The filter's two O(n²) loops over the n×n covariance `C` (column-major,
//! `c[j·n + i] = C_ij`), written over contiguous slices so that the compiler
//! vectorises them, and compiled a second time for AVX2, which runs when
//! the CPU reports it at run time (x86-64; the portable build elsewhere,
//! e.g. wasm32, and on older CPUs). AVX-512 measured no faster here: at
//! 64 gates the sweeps wait on memory, not on arithmetic.
//!
//! **Every build gives the same floats.** Each output element is computed
//! by the same sequence of IEEE operations, in the same order, whatever the
//! vector width: vectorisation only computes several `i` at once, Rust never
//! fuses a multiply and an add (no FMA contraction), and neither loop
//! reduces across `i`. So the instruction set changes the speed, never a
//! gradient, a covariance or a figure in the docs (the tests pin every build
//! against the scalar reference bit for bit).
//!
//! Units are the caller's: `C` in (unit/mV)², `h` in mV, `u` in (unit/mV)²·mV.

/// Below this many gates (a single cell's 4) the portable build runs: the
/// run-time feature check would cost more than the wider vectors save.
/// A speed choice only: every build gives the same floats.
#[cfg(target_arch = "x86_64")]
const WIDE_FROM_GATES: usize = 8;

/// `u ← C h` by columns, `u = Σⱼ C[:, j] hⱼ` summed in `j = 0, 1, …, n−1`:
/// float for float what nalgebra's `&DMatrix * &DVector` computes for a
/// dynamic matrix times a vector (its `gemv` is the same column sweep), only
/// without the strided indexing that keeps that loop scalar.
///
/// Invariant (checked): `c.len() == n²`, `h.len() == u.len() == n`.
pub(super) fn covariance_times(c: &[f64], h: &[f64], u: &mut [f64]) {
    let n = h.len();
    assert!(c.len() == n * n && u.len() == n, "covariance_times: shapes");
    #[cfg(target_arch = "x86_64")]
    if n >= WIDE_FROM_GATES && std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU reports AVX2, checked just above.
        return unsafe { x86::covariance_times_avx2(c, h, u) };
    }
    covariance_times_body(c, h, u);
}

/// `C ← C − k wᵀ − w kᵀ`, then `Cⱼⱼ += q_diagonal[j]·q_factor` on the
/// diagonal, column by column: the rank-two Joseph correction plus a
/// diagonal process noise (the tuner's `Q = σ² I`), in one sweep.
///
/// Element for element `C_ij − (kᵢwⱼ + wᵢkⱼ)`, which is the same float as
/// `C_ji − (kⱼwᵢ + wⱼkᵢ)`: an exactly symmetric `C` stays exactly symmetric.
///
/// Invariant (checked): `c.len() == n²`, `k`, `w`, `q_diagonal` of length `n`.
pub(super) fn rank_two_update_plus_diagonal(
    c: &mut [f64],
    k: &[f64],
    w: &[f64],
    q_diagonal: &[f64],
    q_factor: f64,
) {
    let n = k.len();
    assert!(
        c.len() == n * n && w.len() == n && q_diagonal.len() == n,
        "rank_two_update_plus_diagonal: shapes"
    );
    #[cfg(target_arch = "x86_64")]
    if n >= WIDE_FROM_GATES && std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU reports AVX2, checked just above.
        return unsafe { x86::rank_two_avx2(c, k, w, q_diagonal, q_factor) };
    }
    rank_two_body(c, k, w, q_diagonal, q_factor);
}

#[inline(always)]
fn covariance_times_body(c: &[f64], h: &[f64], u: &mut [f64]) {
    let n = h.len();
    if n == 0 {
        return;
    }
    let mut columns = c.chunks_exact(n).zip(h);
    if let Some((c0, &h0)) = columns.next() {
        for (u_i, &c_i0) in u.iter_mut().zip(c0) {
            *u_i = c_i0 * h0;
        }
    }
    for (cj, &hj) in columns {
        for (u_i, &c_ij) in u.iter_mut().zip(cj) {
            *u_i += c_ij * hj;
        }
    }
}

#[inline(always)]
fn rank_two_body(c: &mut [f64], k: &[f64], w: &[f64], q_diagonal: &[f64], q_factor: f64) {
    let n = k.len();
    if n == 0 {
        return;
    }
    for (j, cj) in c.chunks_exact_mut(n).enumerate() {
        let (kj, wj) = (k[j], w[j]);
        for ((c_ij, &k_i), &w_i) in cj.iter_mut().zip(k).zip(w) {
            *c_ij -= k_i * wj + w_i * kj;
        }
        cj[j] += q_diagonal[j] * q_factor;
    }
}

/// The same bodies compiled for AVX2 (256-bit vectors, 4 `f64` at once).
/// Callers must have checked the feature at run time.
#[cfg(target_arch = "x86_64")]
mod x86 {
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn covariance_times_avx2(c: &[f64], h: &[f64], u: &mut [f64]) {
        super::covariance_times_body(c, h, u);
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn rank_two_avx2(
        c: &mut [f64],
        k: &[f64],
        w: &[f64],
        q_diagonal: &[f64],
        q_factor: f64,
    ) {
        super::rank_two_body(c, k, w, q_diagonal, q_factor);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use proptest::prelude::*;

    fn entries(n: usize) -> impl Strategy<Value = Vec<f64>> {
        proptest::collection::vec(-1e3f64..1e3, n)
    }

    /// `u = C h` from every build this CPU can run: the dispatched entry
    /// point, the portable body and each x86 variant the CPU reports.
    fn products_of_every_build(c: &[f64], h: &[f64]) -> Vec<Vec<f64>> {
        let n = h.len();
        let mut out = Vec::new();
        let mut run = |f: &dyn Fn(&mut [f64])| {
            let mut u = vec![f64::NAN; n];
            f(&mut u);
            out.push(u);
        };
        run(&|u| covariance_times(c, h, u));
        run(&|u| covariance_times_body(c, h, u));
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU reports AVX2.
                run(&|u| unsafe { x86::covariance_times_avx2(c, h, u) });
            }
        }
        out
    }

    /// The updated `C` from every build this CPU can run.
    fn updates_of_every_build(
        c: &[f64],
        k: &[f64],
        w: &[f64],
        q: &[f64],
        q_factor: f64,
    ) -> Vec<Vec<f64>> {
        let mut out = Vec::new();
        let mut run = |f: &dyn Fn(&mut [f64])| {
            let mut updated = c.to_vec();
            f(&mut updated);
            out.push(updated);
        };
        run(&|c| rank_two_update_plus_diagonal(c, k, w, q, q_factor));
        run(&|c| rank_two_body(c, k, w, q, q_factor));
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU reports AVX2.
                run(&|c| unsafe { x86::rank_two_avx2(c, k, w, q, q_factor) });
            }
        }
        out
    }

    proptest! {
        /// Every build equals nalgebra's product bit for bit (below and above
        /// [`WIDE_FROM_GATES`]).
        #[test]
        fn covariance_times_is_nalgebras_product_bit_for_bit(
            (n, c, h) in (1usize..40).prop_flat_map(|n| (Just(n), entries(n * n), entries(n)))
        ) {
            let reference = DMatrix::from_column_slice(n, n, &c) * DVector::from_column_slice(&h);
            for u in products_of_every_build(&c, &h) {
                for i in 0..n {
                    prop_assert_eq!(u[i].to_bits(), reference[i].to_bits());
                }
            }
        }

        /// Every build equals the element-by-element scalar formula bit for bit.
        #[test]
        fn rank_two_update_is_the_scalar_formula_bit_for_bit(
            (n, c, k, w, q) in (1usize..40).prop_flat_map(|n| {
                (Just(n), entries(n * n), entries(n), entries(n), entries(n))
            }),
            q_factor in 0.0f64..4.0,
        ) {
            let mut reference = c.clone();
            for j in 0..n {
                for i in 0..n {
                    let x = reference[j * n + i];
                    reference[j * n + i] = x - (k[i] * w[j] + w[i] * k[j]);
                }
                reference[j * n + j] += q[j] * q_factor;
            }
            for updated in updates_of_every_build(&c, &k, &w, &q, q_factor) {
                for e in 0..n * n {
                    prop_assert_eq!(updated[e].to_bits(), reference[e].to_bits());
                }
            }
        }
    }

    #[test]
    #[should_panic(expected = "shapes")]
    fn mismatched_shapes_are_refused() {
        let mut u = vec![0.0; 2];
        covariance_times(&[1.0; 3], &[1.0, 2.0], &mut u);
    }
}
