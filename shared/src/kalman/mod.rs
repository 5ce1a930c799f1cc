//! Kalman-filter tracking of one parameter's gradient over the tuning gates.
//!
//! This is exactly the filter of Teske et al. (APL 2019), main text eqs. 2–4:
//!
//! * observation model `H = Δv` (1×n, the last voltage step, mV),
//! * measured change `z = p(k) − p(k−1)` (parameter units),
//! * measurement variance `Δz² = δp(k)² + δp(k−1)²`,
//! * gain `K = C Hᵀ / (H C Hᵀ + Δz²)`,
//! * `g ← g + K (z − H g)`, `C ← (I − K H) C + Q`.
//!
//! The covariance update uses the Joseph form
//! `C ← (I − K H) C (I − K H)ᵀ + K Δz² Kᵀ + Q`, which equals the paper's form
//! for the optimal gain but is insensitive (to first order) to errors in the
//! gain, so it stays symmetric positive semi-definite under rounding. It is
//! evaluated as rank-one corrections, `C − K uᵀ − u Kᵀ + s K Kᵀ + Q` with
//! `u = C Hᵀ` and `s = H C Hᵀ + Δz²`: O(n²) per update, in place, no n×n
//! temporaries. `C` stays exactly symmetric: the correction is symmetric
//! float for float, and `Q` is symmetrised once, when the filter is built.
//! The two sweeps over `C` (the product `C Hᵀ` and the correction) are in
//! `kernels.rs`: vectorised, the same floats on every CPU.
//!
//! Units: gradients are in parameter units per mV (e.g. ns/mV, µV/mV); `C` and
//! `Q` in (parameter units / mV)².

mod kernels;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// How the process noise `Q` (the growth of gradient uncertainty per step) is chosen.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ProcessNoise {
    /// The paper's choice: the same `Q` after every update, (unit/mV)².
    Constant {
        /// n×n matrix, (parameter unit / mV)².
        q: DMatrix<f64>,
    },
    /// The paper's proposed improvement: `Q(k) = Q_ref · (|Δv(k)| / reference_step_mv)²`,
    /// so a full reference step adds `Q_ref` and a small step adds little.
    StepScaled {
        /// n×n matrix added for a step of `reference_step_mv`, (unit/mV)².
        q_ref: DMatrix<f64>,
        /// Step norm (mV) at which `q_ref` is added; must be > 0.
        reference_step_mv: f64,
    },
}

impl ProcessNoise {
    /// The paper's isotropic constant `Q = σ² I` for `n` gates, `sigma` in unit/mV.
    pub fn isotropic(n: usize, sigma_per_mv: f64) -> Self {
        ProcessNoise::Constant {
            q: DMatrix::identity(n, n) * sigma_per_mv * sigma_per_mv,
        }
    }

    /// Isotropic step-scaled `Q`: adds `(sigma_per_mv)² I` for a step of `reference_step_mv`.
    pub fn isotropic_step_scaled(n: usize, sigma_per_mv: f64, reference_step_mv: f64) -> Self {
        ProcessNoise::StepScaled {
            q_ref: DMatrix::identity(n, n) * sigma_per_mv * sigma_per_mv,
            reference_step_mv,
        }
    }

    /// The matrix to add after a step `dv` (mV).
    pub fn for_step(&self, dv: &DVector<f64>) -> DMatrix<f64> {
        match self {
            ProcessNoise::Constant { q } => q.clone(),
            ProcessNoise::StepScaled {
                q_ref,
                reference_step_mv,
            } => {
                let ratio = dv.norm() / reference_step_mv;
                q_ref * (ratio * ratio)
            }
        }
    }

    /// The matrix and the factor whose product [`ProcessNoise::for_step`]
    /// returns, without forming it: `(Q, 1)` or `(Q_ref, (|Δv|/reference)²)`.
    fn matrix_and_factor(&self, dv: &DVector<f64>) -> (&DMatrix<f64>, f64) {
        match self {
            ProcessNoise::Constant { q } => (q, 1.0),
            ProcessNoise::StepScaled {
                q_ref,
                reference_step_mv,
            } => {
                let ratio = dv.norm() / reference_step_mv;
                (q_ref, ratio * ratio)
            }
        }
    }

    /// The same policy with its matrix replaced by `(Q + Qᵀ)/2` (a no-op,
    /// bit for bit, for a symmetric matrix).
    fn symmetrised(self) -> Self {
        match self {
            ProcessNoise::Constant { q } => ProcessNoise::Constant { q: symmetrise(q) },
            ProcessNoise::StepScaled {
                q_ref,
                reference_step_mv,
            } => ProcessNoise::StepScaled {
                q_ref: symmetrise(q_ref),
                reference_step_mv,
            },
        }
    }

    /// Diagonal, symmetric or neither (exact comparisons).
    fn shape(&self) -> QShape {
        let (ProcessNoise::Constant { q } | ProcessNoise::StepScaled { q_ref: q, .. }) = self;
        let n = q.nrows();
        let mut shape = QShape::Diagonal;
        for j in 0..n {
            for i in 0..j {
                let (upper, lower) = (q[(i, j)], q[(j, i)]);
                if upper != lower {
                    return QShape::Asymmetric;
                }
                if upper != 0.0 {
                    shape = QShape::Symmetric;
                }
            }
        }
        shape
    }

    fn dimension(&self) -> (usize, usize) {
        match self {
            ProcessNoise::Constant { q } => q.shape(),
            ProcessNoise::StepScaled { q_ref, .. } => q_ref.shape(),
        }
    }

    fn validate(&self, n: usize) -> Result<(), FilterError> {
        if self.dimension() != (n, n) {
            return Err(FilterError::Dimension {
                what: "process noise Q",
                expected: n,
                got: self.dimension().0,
            });
        }
        let m = match self {
            ProcessNoise::Constant { q } => q,
            ProcessNoise::StepScaled {
                q_ref,
                reference_step_mv,
            } => {
                if !(reference_step_mv.is_finite() && *reference_step_mv > 0.0) {
                    return Err(FilterError::Invalid {
                        what: "reference_step_mv",
                        value: *reference_step_mv,
                    });
                }
                q_ref
            }
        };
        validate_covariance(m, "process noise Q")
    }
}

/// Why an update could not be applied. The filter state is unchanged whenever
/// one of these is returned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// A value was NaN or infinite, or a variance negative.
    #[error("{what} must be finite{}, got {value}", if what.contains("variance") { " and non-negative" } else { "" })]
    Invalid {
        /// Which input was rejected.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A vector or matrix had the wrong size.
    #[error("{what} has dimension {got}, expected {expected}")]
    Dimension {
        /// Which input was rejected.
        what: &'static str,
        /// The filter's number of gates.
        expected: usize,
        /// The size that was passed.
        got: usize,
    },
    /// A covariance matrix was not symmetric positive semi-definite.
    #[error("{what} must be symmetric positive semi-definite")]
    NotPsd {
        /// Which matrix was rejected.
        what: &'static str,
    },
}

/// What an accepted call to [`KalmanGradient::update`] did.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum UpdateOutcome {
    /// The gradient and covariance were updated.
    Updated {
        /// Innovation `z − H g` before the update (parameter units).
        innovation: f64,
        /// Predicted standard deviation of the innovation, `√(H C Hᵀ + Δz²)`.
        innovation_sigma: f64,
    },
    /// `|Δv|` was below the filter's minimum step: nothing was learned or changed.
    SkippedSmallStep {
        /// The step norm, mV.
        step_norm_mv: f64,
    },
    /// The innovation was further than `outlier_sigma` predicted standard
    /// deviations from zero: the gradient was not moved. `Q` was still added,
    /// since the gates did move.
    Gated {
        /// Innovation `z − H g` (parameter units).
        innovation: f64,
        /// Predicted standard deviation of the innovation.
        innovation_sigma: f64,
    },
}

/// Gradient estimate `g` (1×n) of one parameter and its covariance `C` (n×n).
///
/// ```
/// use nalgebra::{DMatrix, DVector};
/// use spintune::kalman::{KalmanGradient, ProcessNoise};
///
/// // One parameter over two gates; rough prior.
/// let mut f = KalmanGradient::new(
///     DVector::from_vec(vec![1.0, 0.0]),
///     DMatrix::identity(2, 2),
///     ProcessNoise::isotropic(2, 0.0),
/// ).unwrap();
/// // A 1 mV step on gate 0 changed the parameter by 2.0 (noise-free).
/// f.update(&DVector::from_vec(vec![1.0, 0.0]), 2.0, 0.0).unwrap();
/// assert!((f.gradient()[0] - 2.0).abs() < 1e-12);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KalmanGradient {
    gradient: DVector<f64>,
    covariance: DMatrix<f64>,
    process_noise: ProcessNoise,
    /// Steps with `|Δv|` (mV) below this are skipped. Default 1e-6 mV.
    min_step_mv: f64,
    /// Gate innovations beyond this many predicted standard deviations; `None` = never gate.
    outlier_sigma: Option<f64>,
    /// The shape of `Q` (cached; not part of the state).
    #[serde(skip)]
    noise_shape: NoiseShape,
}

impl KalmanGradient {
    /// A filter with initial gradient `g0` (unit/mV), covariance `c0` ((unit/mV)²) and
    /// process noise `q`. No outlier gating, minimum step 1e-6 mV.
    pub fn new(g0: DVector<f64>, c0: DMatrix<f64>, q: ProcessNoise) -> Result<Self, FilterError> {
        let n = g0.len();
        validate_estimate(&g0, &c0, n, ("initial gradient", "initial covariance"))?;
        q.validate(n)?;
        Ok(Self {
            gradient: g0,
            covariance: symmetrise(c0),
            process_noise: q.symmetrised(),
            min_step_mv: 1e-6,
            outlier_sigma: None,
            noise_shape: NoiseShape::default(),
        })
    }

    /// Set the minimum step norm (mV) below which updates are skipped.
    pub fn with_min_step_mv(mut self, min_step_mv: f64) -> Result<Self, FilterError> {
        if !(min_step_mv.is_finite() && min_step_mv >= 0.0) {
            return Err(FilterError::Invalid {
                what: "min_step_mv",
                value: min_step_mv,
            });
        }
        self.min_step_mv = min_step_mv;
        Ok(self)
    }

    /// Gate innovations beyond `sigma` predicted standard deviations (`None`: never).
    pub fn with_outlier_sigma(mut self, sigma: Option<f64>) -> Result<Self, FilterError> {
        if let Some(s) = sigma {
            if !(s.is_finite() && s > 0.0) {
                return Err(FilterError::Invalid {
                    what: "outlier_sigma",
                    value: s,
                });
            }
        }
        self.outlier_sigma = sigma;
        Ok(self)
    }

    /// Current gradient estimate, unit/mV.
    pub fn gradient(&self) -> &DVector<f64> {
        &self.gradient
    }

    /// Current covariance, (unit/mV)²; symmetric PSD.
    pub fn covariance(&self) -> &DMatrix<f64> {
        &self.covariance
    }

    /// The process-noise policy.
    pub fn process_noise(&self) -> &ProcessNoise {
        &self.process_noise
    }

    /// Number of gates.
    pub fn dimension(&self) -> usize {
        self.gradient.len()
    }

    /// One filter step: the gates moved by `dv` (mV), the parameter changed by
    /// `z`, and `dz2 = δp(k)² + δp(k−1)²` is the variance of that change.
    ///
    /// Invalid inputs (NaN, ±∞, negative variance, wrong dimension) return an
    /// error and leave the state untouched.
    pub fn update(
        &mut self,
        dv: &DVector<f64>,
        z: f64,
        dz2: f64,
    ) -> Result<UpdateOutcome, FilterError> {
        let n = self.dimension();
        check_update_inputs(n, dv, z, dz2)?;
        let step_norm_mv = dv.norm();
        if step_norm_mv < self.min_step_mv || step_norm_mv == 0.0 {
            return Ok(UpdateOutcome::SkippedSmallStep { step_norm_mv });
        }
        let h = dv; // as a column; H = hᵀ
        let mut u = DVector::zeros(n); // u = C Hᵀ (n), (unit/mV)²·mV
        kernels::covariance_times(self.covariance.as_slice(), h.as_slice(), u.as_mut_slice());
        let s = h.dot(&u) + dz2; // H C Hᵀ + Δz², (unit)²
        let innovation = z - h.dot(&self.gradient);
        if s <= 0.0 || !s.is_finite() {
            // No uncertainty in prediction or measurement: nothing sensible to learn.
            // Treat as an exact Broyden step in the limit.
            let hh = h.dot(h);
            self.gradient += h * (innovation / hh);
            self.add_process_noise(dv);
            return Ok(UpdateOutcome::Updated {
                innovation,
                innovation_sigma: 0.0,
            });
        }
        let innovation_sigma = s.sqrt();
        if let Some(limit) = self.outlier_sigma {
            if innovation.abs() > limit * innovation_sigma {
                self.add_process_noise(dv);
                return Ok(UpdateOutcome::Gated {
                    innovation,
                    innovation_sigma,
                });
            }
        }
        let k = &u / s; // Kalman gain (n), unit/mV per unit
        for (g, k) in self.gradient.iter_mut().zip(k.iter()) {
            *g += k * innovation; // g ← g + K (z − H g)
        }
        self.joseph_update_plus_noise(&k, &u, s, dv);
        Ok(UpdateOutcome::Updated {
            innovation,
            innovation_sigma,
        })
    }

    /// Replace the estimate: gradient `g` (unit/mV) and covariance `c`
    /// ((unit/mV)², symmetric PSD), keeping the process noise, the minimum
    /// step and the outlier gate (a row that borrows what other rows
    /// learned, [`crate::tuner::array::JointArrayTuner::borrow_row`]).
    /// Invalid input (wrong dimension, a non-finite entry, a covariance that
    /// is not PSD) is an error and leaves the state untouched.
    ///
    /// ```
    /// use nalgebra::{DMatrix, DVector};
    /// use spintune::kalman::{KalmanGradient, ProcessNoise};
    /// let mut f = KalmanGradient::new(
    ///     DVector::from_vec(vec![1.0, 0.0]),
    ///     DMatrix::identity(2, 2) * 0.01,
    ///     ProcessNoise::isotropic(2, 0.001),
    /// ).unwrap();
    /// f.set_estimate(DVector::from_vec(vec![0.0, 2.0]), DMatrix::identity(2, 2) * 0.04).unwrap();
    /// assert_eq!(f.gradient()[1], 2.0);
    /// assert_eq!(f.covariance()[(0, 0)], 0.04);
    /// assert!(f.set_estimate(DVector::from_vec(vec![f64::NAN, 0.0]), DMatrix::identity(2, 2)).is_err());
    /// assert!(f.set_estimate(DVector::from_vec(vec![1.0]), DMatrix::identity(1, 1)).is_err());
    /// assert_eq!(f.gradient()[1], 2.0);
    /// ```
    pub fn set_estimate(&mut self, g: DVector<f64>, c: DMatrix<f64>) -> Result<(), FilterError> {
        validate_estimate(&g, &c, self.gradient.len(), ("gradient", "covariance"))?;
        self.gradient = g;
        self.covariance = symmetrise(c);
        Ok(())
    }

    /// `C ← factor · C`: widen the gradient's uncertainty in every direction
    /// (a shorter memory after the row's predictions kept missing;
    /// [`crate::tuner::miss_cusum`]). `C` stays exactly symmetric and PSD.
    /// A `factor` that is not finite or below 1 is an error and leaves the
    /// state untouched.
    ///
    /// ```
    /// use nalgebra::{DMatrix, DVector};
    /// use spintune::kalman::{KalmanGradient, ProcessNoise};
    /// let mut f = KalmanGradient::new(
    ///     DVector::from_vec(vec![1.0, 0.0]),
    ///     DMatrix::identity(2, 2) * 0.01,
    ///     ProcessNoise::isotropic(2, 0.0),
    /// ).unwrap();
    /// f.inflate_covariance(4.0).unwrap();
    /// assert_eq!(f.covariance()[(1, 1)], 0.04);
    /// assert!(f.inflate_covariance(0.5).is_err());
    /// ```
    pub fn inflate_covariance(&mut self, factor: f64) -> Result<(), FilterError> {
        if !(factor.is_finite() && factor >= 1.0) {
            return Err(FilterError::Invalid {
                what: "covariance inflation",
                value: factor,
            });
        }
        self.covariance *= factor;
        Ok(())
    }

    /// `C ← (I − K H) C (I − K H)ᵀ + K Δz² Kᵀ + Q`, in place and in O(n²).
    ///
    /// With `u = C Hᵀ` and `s = H C Hᵀ + Δz²` (the values the gain was
    /// computed from, `K = u / s`), the Joseph form expands into rank-one
    /// corrections, `C − K uᵀ − u Kᵀ + s K Kᵀ`, i.e. the symmetric rank-two
    /// update `C − K wᵀ − w Kᵀ` with `w = u − (s/2) K`. Like the product form
    /// it is stationary in `K` (an error in the gain changes `C` only to
    /// second order); it needs no n×n×n product and no n×n temporary.
    fn joseph_update_plus_noise(
        &mut self,
        k: &DVector<f64>,
        u: &DVector<f64>,
        s: f64,
        dv: &DVector<f64>,
    ) {
        let half_s = 0.5 * s;
        let w = DVector::from_fn(k.len(), |i, _| u[i] - half_s * k[i]);
        self.update_in_place(k.as_slice(), w.as_slice(), dv);
    }

    /// `C ← C + Q` in place (the gated and the exact-Broyden paths).
    fn add_process_noise(&mut self, dv: &DVector<f64>) {
        self.update_in_place(&[], &[], dv);
    }

    /// `C ← C − K wᵀ − w Kᵀ + Q` in place (`k`, `w` of length n, or both
    /// empty for `C ← C + Q`), column by column over contiguous memory.
    ///
    /// Exactly symmetric: `C` is exactly symmetric on entry (an invariant:
    /// [`KalmanGradient::new`] symmetrises `C(0)`), `kᵢwⱼ + wᵢkⱼ` is the same
    /// float as `kⱼwᵢ + wⱼkᵢ`, and `Q` is symmetric (`new` symmetrises it;
    /// a deserialised asymmetric `Q` gets the result symmetrised, as the
    /// dense form did). A diagonal `Q` (the tuner's `σ² I`) is read on the
    /// diagonal only, which saves reading n² entries per update.
    fn update_in_place(&mut self, k: &[f64], w: &[f64], dv: &DVector<f64>) {
        let n = self.dimension();
        if n == 0 {
            return;
        }
        let process_noise = &self.process_noise;
        let (shape, q_diagonal) = self.noise_shape.0.get_or_insert_with(|| {
            let q = process_noise.matrix_and_factor(dv).0;
            (process_noise.shape(), q.diagonal().as_slice().to_vec())
        });
        let shape = *shape;
        let (q, q_factor) = process_noise.matrix_and_factor(dv);
        let q = q.as_slice();
        let c = self.covariance.as_mut_slice();
        // Column-major: column j is c[j·n .. (j+1)·n].
        match (k.is_empty(), shape == QShape::Diagonal) {
            // The tuner's update (`Q = σ² I`): one vectorised sweep.
            (false, true) => kernels::rank_two_update_plus_diagonal(c, k, w, q_diagonal, q_factor),
            (true, true) => {
                for (j, &q_jj) in q_diagonal.iter().enumerate() {
                    c[j * n + j] += q_jj * q_factor;
                }
            }
            (true, false) => {
                for (c_ij, &q_ij) in c.iter_mut().zip(q) {
                    *c_ij += q_ij * q_factor;
                }
            }
            (false, false) => {
                for (j, (cj, qj)) in c.chunks_exact_mut(n).zip(q.chunks_exact(n)).enumerate() {
                    let (kj, wj) = (k[j], w[j]);
                    for (((c_ij, &q_ij), &k_i), &w_i) in cj.iter_mut().zip(qj).zip(k).zip(w) {
                        *c_ij = (*c_ij - (k_i * wj + w_i * kj)) + q_ij * q_factor;
                    }
                }
            }
        }
        if shape == QShape::Asymmetric {
            symmetrise_in_place(&mut self.covariance);
        }
    }
}

/// The inputs of one filter update, checked: `dv` of length `n` with
/// finite entries (mV), a finite measured change `z`, a finite variance
/// `dz2 ≥ 0`. The one rule for every filter of the crate
/// ([`KalmanGradient::update`], [`crate::estimator`]); an error names the
/// input and leaves the caller's state untouched.
pub(crate) fn check_update_inputs(
    n: usize,
    dv: &DVector<f64>,
    z: f64,
    dz2: f64,
) -> Result<(), FilterError> {
    if dv.len() != n {
        return Err(FilterError::Dimension {
            what: "voltage step",
            expected: n,
            got: dv.len(),
        });
    }
    if let Some(&bad) = dv.iter().find(|x| !x.is_finite()) {
        return Err(FilterError::Invalid {
            what: "voltage step",
            value: bad,
        });
    }
    if !z.is_finite() {
        return Err(FilterError::Invalid {
            what: "measured change",
            value: z,
        });
    }
    if !(dz2.is_finite() && dz2 >= 0.0) {
        return Err(FilterError::Invalid {
            what: "measurement variance",
            value: dz2,
        });
    }
    Ok(())
}

/// `M ← (M + Mᵀ)/2` in place, for a square `M`.
fn symmetrise_in_place(m: &mut DMatrix<f64>) {
    let n = m.nrows();
    let c = m.as_mut_slice();
    for j in 0..n {
        for i in 0..j {
            let v = (c[j * n + i] + c[i * n + j]) * 0.5;
            c[j * n + i] = v;
            c[i * n + j] = v;
        }
    }
}

/// The structure of a process-noise matrix, as far as the update uses it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum QShape {
    /// No non-zero entry off the diagonal.
    Diagonal,
    /// Exactly symmetric.
    Symmetric,
    /// Neither (only from deserialised state: `new` symmetrises `Q`).
    Asymmetric,
}

/// The [`QShape`] of the process noise and `Q`'s diagonal: a cache, not
/// state (skipped by serde, equal to any other in `PartialEq`), filled on
/// the first update (`Q` never changes after [`KalmanGradient::new`]). The
/// diagonal's own copy spares a diagonal `Q`'s update one cache line per
/// column of the n×n matrix.
#[derive(Debug, Clone, Default)]
struct NoiseShape(Option<(QShape, Vec<f64>)>);

impl PartialEq for NoiseShape {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// `(M + Mᵀ)/2`.
pub(crate) fn symmetrise(m: DMatrix<f64>) -> DMatrix<f64> {
    (&m + m.transpose()) * 0.5
}

/// Check that `m` is finite, symmetric (to 1e-9 relative) and PSD (eigenvalues ≥ −1e-9·max).
/// A gradient `g` of `n` finite entries and its covariance `c` (n×n,
/// finite, symmetric PSD); `what` names them in the error.
fn validate_estimate(
    g: &DVector<f64>,
    c: &DMatrix<f64>,
    n: usize,
    what: (&'static str, &'static str),
) -> Result<(), FilterError> {
    if g.len() != n {
        return Err(FilterError::Dimension {
            what: what.0,
            expected: n,
            got: g.len(),
        });
    }
    if let Some(&bad) = g.iter().find(|x| !x.is_finite()) {
        return Err(FilterError::Invalid {
            what: what.0,
            value: bad,
        });
    }
    if c.shape() != (n, n) {
        return Err(FilterError::Dimension {
            what: what.1,
            expected: n,
            got: c.nrows(),
        });
    }
    validate_covariance(c, what.1)
}

pub(crate) fn validate_covariance(m: &DMatrix<f64>, what: &'static str) -> Result<(), FilterError> {
    if let Some(&bad) = m.iter().find(|x| !x.is_finite()) {
        return Err(FilterError::Invalid {
            what: "covariance entry",
            value: bad,
        });
    }
    if !m.is_square() {
        return Err(FilterError::NotPsd { what });
    }
    let scale = m.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    if scale == 0.0 {
        return Ok(());
    }
    if (m - m.transpose()).iter().any(|x| x.abs() > 1e-9 * scale) {
        return Err(FilterError::NotPsd { what });
    }
    let Some(eig) = crate::decomposition::symmetric_eigenvalues(symmetrise(m.clone())) else {
        return Err(FilterError::NotPsd { what });
    };
    if eig.iter().any(|&l| l < -1e-9 * scale) {
        return Err(FilterError::NotPsd { what });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn filter(n: usize) -> KalmanGradient {
        KalmanGradient::new(
            DVector::zeros(n),
            DMatrix::identity(n, n),
            ProcessNoise::isotropic(n, 0.1),
        )
        .unwrap()
    }

    #[test]
    fn matches_paper_equations_by_hand() {
        // n = 2, C = diag(4, 1), g = (1, 2), Δv = (1, 1), z = 5, Δz² = 1, Q = 0.01 I.
        let mut f = KalmanGradient::new(
            DVector::from_vec(vec![1.0, 2.0]),
            DMatrix::from_diagonal(&DVector::from_vec(vec![4.0, 1.0])),
            ProcessNoise::isotropic(2, 0.1),
        )
        .unwrap();
        f.update(&DVector::from_vec(vec![1.0, 1.0]), 5.0, 1.0)
            .unwrap();
        // H C Hᵀ = 5, S = 6, K = (4/6, 1/6), innovation = 5 − 3 = 2.
        let g = f.gradient();
        assert!((g[0] - (1.0 + 8.0 / 6.0)).abs() < 1e-12);
        assert!((g[1] - (2.0 + 2.0 / 6.0)).abs() < 1e-12);
        // (I − K H) C = C − K (H C) = [[4 − 16/6, −4/6], [−4/6, 1 − 1/6]] (+ Q on the diagonal)
        let c = f.covariance();
        assert!((c[(0, 0)] - (4.0 - 16.0 / 6.0 + 0.01)).abs() < 1e-12);
        assert!((c[(0, 1)] - (-4.0 / 6.0)).abs() < 1e-12);
        assert!((c[(1, 1)] - (1.0 - 1.0 / 6.0 + 0.01)).abs() < 1e-12);
    }

    #[test]
    fn zero_measurement_noise_is_broyden() {
        let mut f = KalmanGradient::new(
            DVector::from_vec(vec![0.5, -0.5, 0.0]),
            DMatrix::identity(3, 3),
            ProcessNoise::isotropic(3, 0.0),
        )
        .unwrap();
        let dv = DVector::from_vec(vec![0.3, -1.0, 2.0]);
        let g0 = f.gradient().clone();
        f.update(&dv, 1.7, 0.0).unwrap();
        let broyden = &g0 + &dv * ((1.7 - dv.dot(&g0)) / dv.dot(&dv));
        assert!((f.gradient() - broyden).norm() < 1e-12);
        // and the new gradient reproduces the observed change exactly
        assert!((f.gradient().dot(&dv) - 1.7).abs() < 1e-12);
    }

    #[test]
    fn noisy_measurement_barely_moves_gradient() {
        let mut f = filter(2);
        f.update(&DVector::from_vec(vec![1.0, 0.0]), 10.0, 1e6)
            .unwrap();
        assert!(f.gradient().norm() < 1e-4);
    }

    #[test]
    fn invalid_inputs_rejected_state_unchanged() {
        let mut f = filter(2);
        let before = f.clone();
        let dv = DVector::from_vec(vec![1.0, 0.0]);
        for (z, dz2) in [
            (f64::NAN, 1.0),
            (f64::INFINITY, 1.0),
            (1.0, f64::NAN),
            (1.0, -1.0),
            (1.0, f64::INFINITY),
        ] {
            assert!(f.update(&dv, z, dz2).is_err(), "z={z}, dz2={dz2}");
            assert_eq!(f, before);
        }
        assert!(f
            .update(&DVector::from_vec(vec![f64::NAN, 0.0]), 1.0, 1.0)
            .is_err());
        assert!(f.update(&DVector::from_vec(vec![1.0]), 1.0, 1.0).is_err());
        assert_eq!(f, before);
        let err = f.update(&dv, 1.0, -2.0).unwrap_err();
        assert!(err.to_string().contains("non-negative"), "{err}");
    }

    #[test]
    fn small_step_skips() {
        let mut f = filter(2).with_min_step_mv(0.01).unwrap();
        let before = f.clone();
        let out = f
            .update(&DVector::from_vec(vec![0.001, 0.0]), 5.0, 0.0)
            .unwrap();
        assert!(matches!(out, UpdateOutcome::SkippedSmallStep { .. }));
        assert_eq!(f, before);
    }

    #[test]
    fn outlier_is_gated_and_gradient_unmoved() {
        let mut f = KalmanGradient::new(
            DVector::from_vec(vec![1.0, 1.0]),
            DMatrix::identity(2, 2) * 0.01,
            ProcessNoise::isotropic(2, 0.01),
        )
        .unwrap()
        .with_outlier_sigma(Some(5.0))
        .unwrap();
        let g = f.gradient().clone();
        // predicted change 1.0 ± ~0.1; measured 50 → far outside
        let out = f
            .update(&DVector::from_vec(vec![1.0, 0.0]), 50.0, 0.0)
            .unwrap();
        assert!(matches!(out, UpdateOutcome::Gated { .. }));
        assert_eq!(f.gradient(), &g);
        // a plausible change is learned
        let out = f
            .update(&DVector::from_vec(vec![1.0, 0.0]), 1.1, 0.0001)
            .unwrap();
        assert!(matches!(out, UpdateOutcome::Updated { .. }));
        assert!(f.gradient()[0] > 1.0);
    }

    #[test]
    fn step_scaled_q_grows_with_step() {
        let q = ProcessNoise::isotropic_step_scaled(2, 0.3, 10.0);
        let small = q.for_step(&DVector::from_vec(vec![1.0, 0.0]));
        let full = q.for_step(&DVector::from_vec(vec![6.0, 8.0]));
        assert!((full[(0, 0)] - 0.09).abs() < 1e-12);
        assert!((small[(0, 0)] - 0.0009).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_initial_state() {
        let bad_c = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.0, -1.0]);
        assert!(
            KalmanGradient::new(DVector::zeros(2), bad_c, ProcessNoise::isotropic(2, 0.1)).is_err()
        );
        assert!(KalmanGradient::new(
            DVector::zeros(2),
            DMatrix::identity(2, 2),
            ProcessNoise::isotropic(3, 0.1)
        )
        .is_err());
    }

    /// The textbook update with full matrix products (Joseph form, then `+ Q`):
    /// the reference for the O(n²) rank-one evaluation.
    fn dense_joseph(
        g: &DVector<f64>,
        c: &DMatrix<f64>,
        q: &DMatrix<f64>,
        h: &DVector<f64>,
        z: f64,
        dz2: f64,
    ) -> (DVector<f64>, DMatrix<f64>) {
        let n = h.len();
        let s = (h.transpose() * c * h)[(0, 0)] + dz2;
        let k = c * h / s;
        let g = g + &k * (z - h.dot(g));
        let ikh = DMatrix::identity(n, n) - &k * h.transpose();
        let c = &ikh * c * ikh.transpose() + &k * k.transpose() * dz2 + q;
        (g, c)
    }

    /// A random symmetric positive definite n×n matrix `(A Aᵀ + 0.01 I)·scale`.
    fn spd(entries: &[f64], n: usize, scale: f64) -> DMatrix<f64> {
        let a = DMatrix::from_column_slice(n, n, &entries[..n * n]);
        (&a * a.transpose() + DMatrix::identity(n, n) * 0.01) * scale
    }

    /// Smallest eigenvalue over the trace (≥ 0 for a PSD matrix, up to rounding).
    fn min_eigenvalue_over_trace(c: &DMatrix<f64>) -> f64 {
        let eig = c.clone().symmetric_eigenvalues();
        eig.min() / c.trace()
    }

    #[test]
    fn asymmetric_q_is_symmetrised_once_and_c_stays_exactly_symmetric() {
        let q =
            DMatrix::from_row_slice(3, 3, &[1.0, 0.2, 0.0, 0.2 + 1e-12, 1.0, 0.0, 0.0, 0.0, 2.0]);
        let mut f = KalmanGradient::new(
            DVector::zeros(3),
            DMatrix::identity(3, 3),
            ProcessNoise::Constant { q: q.clone() },
        )
        .unwrap();
        let ProcessNoise::Constant { q: stored } = f.process_noise().clone() else {
            panic!("constant Q expected");
        };
        assert_eq!(stored, symmetrise(q));
        for i in 0..20 {
            let dv = DVector::from_vec(vec![1.0, -0.5 * i as f64, 0.3]);
            f.update(&dv, 0.1 * i as f64, 0.5).unwrap();
            let c = f.covariance();
            assert_eq!(c, &c.transpose());
        }
    }

    #[test]
    fn deserialised_asymmetric_q_still_gives_a_symmetric_c() {
        // `new` symmetrises Q; a state written elsewhere may not have.
        let f = filter(2);
        let mut json: serde_json::Value = serde_json::to_value(&f).unwrap();
        // nalgebra writes a matrix as [column-major data, nrows, ncols]
        json["process_noise"]["q"][0] = serde_json::json!([0.01, 1e-12, 0.0, 0.01]);
        let mut f: KalmanGradient = serde_json::from_value(json).unwrap();
        let ProcessNoise::Constant { q } = f.process_noise().clone() else {
            panic!("constant Q expected");
        };
        assert_ne!(q, q.transpose());
        let before = f.covariance().clone();
        f.update(&DVector::from_vec(vec![1.0, 2.0]), 0.5, 0.1)
            .unwrap();
        let c = f.covariance();
        assert_eq!(c, &c.transpose());
        assert!(c != &before);
    }

    #[test]
    fn gated_update_adds_q_exactly_as_the_dense_form() {
        // Gated (and exact-Broyden) updates only add Q: bit for bit
        // `symmetrise(C + Q)`, for a diagonal and for a full Q.
        let c0 = spd(&[0.3, -1.0, 0.5, 0.2, 0.9, -0.4, 0.1, 0.7, -0.6], 3, 2.0);
        for q in [
            DMatrix::from_diagonal(&DVector::from_vec(vec![0.01, 0.02, 0.03])),
            spd(&[0.5, 0.1, -0.2, 0.3, 0.4, 0.1, -0.3, 0.2, 0.6], 3, 0.01),
        ] {
            let mut f = KalmanGradient::new(
                DVector::zeros(3),
                c0.clone(),
                ProcessNoise::Constant { q: q.clone() },
            )
            .unwrap()
            .with_outlier_sigma(Some(1.0))
            .unwrap();
            let before = f.covariance().clone();
            let out = f
                .update(&DVector::from_vec(vec![1.0, 0.0, 0.0]), 1e6, 0.0)
                .unwrap();
            assert!(matches!(out, UpdateOutcome::Gated { .. }));
            assert_eq!(f.covariance(), &symmetrise(&before + &q));
        }
    }

    #[test]
    fn serde_round_trip_continues_bit_identically() {
        // The diagonal-Q cache is not state: a restored filter recomputes it.
        let mut f = filter(4);
        let dv = DVector::from_vec(vec![1.0, 2.0, -1.0, 0.5]);
        f.update(&dv, 1.0, 0.1).unwrap();
        let mut restored: KalmanGradient =
            serde_json::from_str(&serde_json::to_string(&f).unwrap()).unwrap();
        assert_eq!(restored, f);
        f.update(&dv, -2.0, 0.3).unwrap();
        restored.update(&dv, -2.0, 0.3).unwrap();
        assert_eq!(restored.covariance(), f.covariance());
        assert_eq!(restored.gradient(), f.gradient());
    }

    proptest! {
        /// The in-place O(n²) update agrees with the textbook dense Joseph
        /// form (full matrix products) to 1e-9 relative, over several
        /// updates from random SPD covariances, with a full or a diagonal,
        /// constant or step-scaled Q.
        #[test]
        fn rank_one_update_matches_dense_joseph_form(
            n in 1usize..=12,
            c_entries in proptest::collection::vec(-1.0f64..1.0, 144),
            q_entries in proptest::collection::vec(-1.0f64..1.0, 144),
            c_scale in prop_oneof![1e-6f64..1e-3, 1e-3f64..1.0, 1.0f64..1e4],
            q_scale in prop_oneof![Just(0.0), 1e-8f64..1e-2],
            diagonal_q in any::<bool>(),
            step_scaled in any::<bool>(),
            steps in proptest::collection::vec(
                (proptest::collection::vec(-10.0f64..10.0, 12), -100.0f64..100.0, 0.0f64..100.0),
                1..8),
        ) {
            let c0 = spd(&c_entries, n, c_scale);
            let mut q = spd(&q_entries, n, q_scale);
            if diagonal_q {
                q = DMatrix::from_diagonal(&q.diagonal());
            }
            let reference_step_mv = 5.0;
            let noise = if step_scaled {
                ProcessNoise::StepScaled { q_ref: q.clone(), reference_step_mv }
            } else {
                ProcessNoise::Constant { q: q.clone() }
            };
            let g0 = DVector::from_fn(n, |i, _| c_entries[143 - i]);
            let mut f = KalmanGradient::new(g0.clone(), c0.clone(), noise.clone()).unwrap();
            let (mut g_ref, mut c_ref) = (g0, c0);
            for (dv, z, dz2) in steps {
                let dv = DVector::from_column_slice(&dv[..n]);
                prop_assume!(dv.norm() > 1e-3);
                let out = f.update(&dv, z, dz2).unwrap();
                prop_assert!(matches!(out, UpdateOutcome::Updated { .. }), "{out:?}");
                let q_step = noise.for_step(&dv);
                let (g_new, c_new) = dense_joseph(&g_ref, &c_ref, &q_step, &dv, z, dz2);
                // Rounding scale: the matrices that went into the update.
                let c_scale = c_ref.norm().max(c_new.norm()) + q_step.norm();
                let g_scale = g_ref.norm().max(g_new.norm()) + (g_new.clone() - &g_ref).norm();
                prop_assert!(
                    (f.covariance() - &c_new).norm() <= 1e-9 * c_scale,
                    "C: {} vs {}", f.covariance(), c_new
                );
                prop_assert!(
                    (f.gradient() - &g_new).norm() <= 1e-9 * g_scale,
                    "g: {} vs {}", f.gradient(), g_new
                );
                (g_ref, c_ref) = (g_new, c_new);
            }
        }

        /// Over many updates (including exact measurements, Δz² = 0, with
        /// process noise, and tiny Δz² without) `C` stays exactly symmetric
        /// and positive semi-definite: smallest eigenvalue ≥ −1e-12 · trace.
        #[test]
        fn covariance_stays_psd_over_many_updates(
            n in 2usize..=10,
            c_entries in proptest::collection::vec(-1.0f64..1.0, 100),
            c_scale in prop_oneof![1e-6f64..1e-2, 1e-2f64..1e4],
            q_sigma in prop_oneof![Just(0.0), 1e-4f64..0.3],
            steps in proptest::collection::vec(
                (proptest::collection::vec(-10.0f64..10.0, 10), -50.0f64..50.0,
                 prop_oneof![Just(0.0), 1e-8f64..1e-3, 1e-3f64..100.0]),
                100..200),
        ) {
            let mut f = KalmanGradient::new(
                DVector::zeros(n),
                spd(&c_entries, n, c_scale),
                ProcessNoise::isotropic(n, q_sigma),
            ).unwrap();
            for (dv, z, dz2) in steps {
                // An exact measurement with no process noise at all collapses C
                // to rounding noise, where no λ_min/trace bound can hold.
                let dz2 = if q_sigma == 0.0 { dz2.max(1e-8) } else { dz2 };
                f.update(&DVector::from_column_slice(&dv[..n]), z, dz2).unwrap();
                let c = f.covariance();
                prop_assert_eq!(c, &c.transpose());
                prop_assert!(c.iter().all(|x| x.is_finite()));
                if c.trace() > 0.0 {
                    let ratio = min_eigenvalue_over_trace(c);
                    prop_assert!(ratio >= -1e-12, "λ_min / trace = {ratio:e}");
                }
            }
        }
    }

    proptest! {
        #[test]
        fn covariance_stays_symmetric_psd(
            steps in proptest::collection::vec(
                (proptest::collection::vec(-10.0f64..10.0, 4), -100.0f64..100.0, 0.0f64..100.0),
                1..60)
        ) {
            let mut f = KalmanGradient::new(
                DVector::from_vec(vec![1.0, -2.0, 0.5, 3.0]),
                DMatrix::identity(4, 4) * 4.0,
                ProcessNoise::isotropic(4, 0.075),
            ).unwrap();
            for (dv, z, dz2) in steps {
                f.update(&DVector::from_vec(dv), z, dz2).unwrap();
                let c = f.covariance();
                prop_assert!((c - c.transpose()).norm() == 0.0);
                let eig = c.clone().symmetric_eigenvalues();
                let scale = c.amax().max(1e-300);
                prop_assert!(eig.iter().all(|&l| l >= -1e-9 * scale), "eigenvalues {:?}", eig);
                prop_assert!(f.gradient().iter().all(|x| x.is_finite()));
            }
        }
    }
}
