//! Core numerics of one tuner iteration: `m` Kalman filter updates (one per
//! parameter) plus one quasi-Newton step, for `n` gates × `m` parameters =
//! 4×2 (the paper's qubit level: N, SA, SB, T → t_sr, w), 16×8 and 64×32.
//!
//! ```sh
//! cargo bench -p spintune --bench filter_solve -- --warm-up-time 1 --measurement-time 3
//! ```
//!
//! Group `filter_update_plus_newton_step`, one benchmark id per part and size
//! (`<part>/<n>x<m>`):
//!
//! * `filter_plus_newton` — what one iteration does numerically: `m` calls of
//!   [`KalmanGradient::update`] with the step `Δv` and the measured changes
//!   `Δz` (with variances), the Jacobian assembled from the `m` gradients, and
//!   one [`newton_step`] (minimum-norm pseudo-inverse step: normal equations
//!   with one correction for a provably well-conditioned `J`, as here; QR of
//!   `Jᵀ` or SVD otherwise) with the paper's 10 mV limit;
//! * `filter_only` — the `m` filter updates alone;
//! * `newton_only` — [`newton_step`] alone on the updated Jacobian;
//! * `baseline_normal_eq` — the same limited step from the normal equations
//!   `Δv = −Jᵀ (J Jᵀ)⁻¹ Δ` by Cholesky (no rank handling, no condition
//!   check, no correction). A yardstick for the solver's cost measured in
//!   the same run, not a replacement: it fails on rank-deficient `J` and
//!   loses accuracy as `κ(J)²` on ill-conditioned ones, which `newton_step`
//!   handles.
//!
//! Units, as in the crate: gate voltages and steps `Δv` in mV; parameter values,
//! changes `Δz` and offsets `Δ = p − p*` in parameter units (ns for the
//! t_sr-like rows, µV for the w-like rows); gradients (Jacobian rows) in
//! parameter unit/mV; covariances `C` and process noise `Q` in
//! (parameter unit/mV)²; measurement variances in (parameter unit)².
//!
//! Setup is deterministic (seeded `ChaCha8Rng`) and outside the timed code;
//! the filter benchmarks start every timed call from a fresh clone of the same
//! filter state (`iter_batched_ref`), so each call does identical work.

#[cfg(not(target_arch = "wasm32"))]
criterion::criterion_main!(native::benches);

/// Benchmarks are native only (criterion is not a wasm32 dev-dependency).
#[cfg(target_arch = "wasm32")]
fn main() {}

#[cfg(not(target_arch = "wasm32"))]
mod native {
    use std::hint::black_box;

    use criterion::{criterion_group, BatchSize, BenchmarkId, Criterion};
    use nalgebra::{DMatrix, DVector};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};
    use spintune::kalman::{KalmanGradient, ProcessNoise, UpdateOutcome};
    use spintune::solver::{newton_step, SolverConfig};

    /// (gates n, parameters m).
    const SIZES: [(usize, usize); 3] = [(4, 2), (16, 8), (64, 32)];

    /// The paper's step limit, mV.
    const MAX_STEP_MV: f64 = 10.0;

    /// Scales of one parameter row, after the paper's two qubit parameters.
    struct Kind {
        /// Typical gradient entry, parameter unit/mV.
        gradient: f64,
        /// Process noise σ_Q, parameter unit/mV (`Q = σ_Q² I`, paper values).
        q_sigma: f64,
        /// Standard deviation of one measured value, parameter unit.
        meas_sigma: f64,
        /// Typical distance from the target, parameter unit.
        offset: f64,
    }

    /// t_sr-like (ns) for even rows, w-like (µV) for odd rows.
    fn kind(row: usize) -> Kind {
        if row % 2 == 0 {
            Kind {
                gradient: 1.0,
                q_sigma: 0.075,
                meas_sigma: 1.0,
                offset: 10.0,
            }
        } else {
            Kind {
                gradient: 4.0,
                q_sigma: 0.3,
                meas_sigma: 4.0,
                offset: 40.0,
            }
        }
    }

    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        StandardNormal.sample(rng)
    }

    /// Everything one iteration consumes, built before timing.
    struct Case {
        n: usize,
        m: usize,
        /// One filter per parameter, in a realistic mid-run state.
        filters: Vec<KalmanGradient>,
        /// The last step, mV (the previous limited Newton step).
        dv_mv: DVector<f64>,
        /// Measured change of each parameter over that step, parameter units.
        dz: Vec<f64>,
        /// Variance of each change, `δp(k)² + δp(k−1)²`, (parameter unit)².
        dz2: Vec<f64>,
        /// `p − p*` after the step, parameter units.
        delta: DVector<f64>,
        /// Jacobian (m×n, unit/mV) assembled from the updated filters.
        jacobian_after: DMatrix<f64>,
        cfg: SolverConfig,
    }

    fn assemble(filters: &[KalmanGradient], n: usize) -> DMatrix<f64> {
        DMatrix::from_fn(filters.len(), n, |r, c| filters[r].gradient()[c])
    }

    fn case(n: usize, m: usize) -> Case {
        let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_0000 + (n * 1000 + m) as u64);
        // The device's true Jacobian (unit/mV): every gate acts on every parameter.
        let j_true = DMatrix::from_fn(m, n, |r, _| kind(r).gradient * normal(&mut rng));
        // Initial estimate as from finite differences (4 mV offsets, 3 repetitions):
        // per-entry σ = √2 δp / (4 mV √3); diagonal C(0).
        let mut filters: Vec<KalmanGradient> = (0..m)
            .map(|r| {
                let k = kind(r);
                let fd_sigma = k.meas_sigma * 2f64.sqrt() / (4.0 * 3f64.sqrt());
                let g0 = DVector::from_fn(n, |c, _| j_true[(r, c)] + fd_sigma * normal(&mut rng));
                let c0 = DMatrix::identity(n, n) * fd_sigma * fd_sigma;
                KalmanGradient::new(g0, c0, ProcessNoise::isotropic(n, k.q_sigma))
                    .and_then(|f| f.with_outlier_sigma(Some(5.0)))
                    .and_then(|f| f.with_min_step_mv(0.01))
                    .expect("valid filter")
            })
            .collect();
        let cfg = SolverConfig {
            max_step_mv: MAX_STEP_MV,
            ..SolverConfig::default()
        };
        // A few earlier iterations with random steps (2–10 mV), so C is dense.
        let measure = |j: &DMatrix<f64>, dv: &DVector<f64>, rng: &mut ChaCha8Rng| {
            let dz: Vec<f64> = (0..m)
                .map(|r| {
                    let s = kind(r).meas_sigma;
                    j.row(r).transpose().dot(dv) + s * 2f64.sqrt() * normal(rng)
                })
                .collect();
            let dz2: Vec<f64> = (0..m).map(|r| 2.0 * kind(r).meas_sigma.powi(2)).collect();
            (dz, dz2)
        };
        for _ in 0..5 {
            let dir = DVector::from_fn(n, |_, _| normal(&mut rng));
            let dv = dir.normalize() * rng.gen_range(2.0..MAX_STEP_MV);
            let (dz, dz2) = measure(&j_true, &dv, &mut rng);
            for (f, (z, v)) in filters.iter_mut().zip(dz.iter().zip(&dz2)) {
                f.update(&dv, *z, *v).expect("valid update");
            }
        }
        // The step under test: the limited Newton step from the current estimate.
        let delta_before = DVector::from_fn(m, |r, _| kind(r).offset * normal(&mut rng));
        let dv_mv = newton_step(&assemble(&filters, n), &delta_before, &cfg).dv_mv;
        let (dz, dz2) = measure(&j_true, &dv_mv, &mut rng);
        let delta = &delta_before + DVector::from_column_slice(&dz);

        // Check that the timed code takes the path it should: every update is a
        // full update (not skipped or gated), J has full rank, and the baseline
        // agrees with the solver's step.
        let mut updated = filters.clone();
        for (f, (z, v)) in updated.iter_mut().zip(dz.iter().zip(&dz2)) {
            let out = f.update(&dv_mv, *z, *v).expect("valid update");
            assert!(
                matches!(out, UpdateOutcome::Updated { .. }),
                "{n}x{m}: {out:?}"
            );
        }
        let jacobian_after = assemble(&updated, n);
        let svd = newton_step(&jacobian_after, &delta, &cfg);
        assert_eq!(svd.rank, m, "{n}x{m}: rank");
        let base = normal_equations_step(&jacobian_after, &delta, cfg.max_step_mv);
        assert!(
            (&svd.dv_mv - &base).norm() <= 1e-8 * svd.dv_mv.norm().max(1e-12),
            "{n}x{m}: baseline disagrees"
        );
        Case {
            n,
            m,
            filters,
            dv_mv,
            dz,
            dz2,
            delta,
            jacobian_after,
            cfg,
        }
    }

    /// Baseline solver: `Δv = −Jᵀ (J Jᵀ)⁻¹ Δ` (mV) by Cholesky of the m×m
    /// `J Jᵀ`, scaled to `max_step_mv`. Needs full row rank; zero step otherwise.
    fn normal_equations_step(
        jacobian: &DMatrix<f64>,
        delta: &DVector<f64>,
        max_step_mv: f64,
    ) -> DVector<f64> {
        let jjt = jacobian * jacobian.transpose();
        let dv = match jjt.cholesky() {
            Some(ch) => -(jacobian.transpose() * ch.solve(delta)),
            None => return DVector::zeros(jacobian.ncols()),
        };
        let norm = dv.norm();
        if norm > max_step_mv {
            dv * (max_step_mv / norm)
        } else {
            dv
        }
    }

    /// The `m` filter updates of one iteration.
    fn update_all(filters: &mut [KalmanGradient], c: &Case) {
        for (f, (z, v)) in filters.iter_mut().zip(c.dz.iter().zip(&c.dz2)) {
            let out = f.update(black_box(&c.dv_mv), black_box(*z), black_box(*v));
            black_box(out.ok());
        }
    }

    fn filter_solve(crit: &mut Criterion) {
        let mut group = crit.benchmark_group("filter_update_plus_newton_step");
        for (n, m) in SIZES {
            let c = case(n, m);
            let size = format!("{}x{}", c.n, c.m);
            group.bench_with_input(BenchmarkId::new("filter_plus_newton", &size), &c, |b, c| {
                b.iter_batched_ref(
                    || c.filters.clone(),
                    |filters| {
                        update_all(filters, c);
                        let j = assemble(filters, c.n);
                        newton_step(&j, black_box(&c.delta), &c.cfg)
                    },
                    BatchSize::SmallInput,
                )
            });
            group.bench_with_input(BenchmarkId::new("filter_only", &size), &c, |b, c| {
                b.iter_batched_ref(
                    || c.filters.clone(),
                    |filters| update_all(filters, c),
                    BatchSize::SmallInput,
                )
            });
            group.bench_with_input(BenchmarkId::new("newton_only", &size), &c, |b, c| {
                b.iter(|| newton_step(black_box(&c.jacobian_after), black_box(&c.delta), &c.cfg))
            });
            group.bench_with_input(BenchmarkId::new("baseline_normal_eq", &size), &c, |b, c| {
                b.iter(|| {
                    normal_equations_step(
                        black_box(&c.jacobian_after),
                        black_box(&c.delta),
                        c.cfg.max_step_mv,
                    )
                })
            });
        }
        group.finish();
    }

    criterion_group!(benches, filter_solve);
}
