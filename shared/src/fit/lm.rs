//! Generic 1-D curve fitting with the `levenberg-marquardt` crate.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{storage::Owned, DMatrix, DVector, Dyn};

use super::FitError;

/// A model `f(x; p)` with an analytic gradient in the parameters.
pub(crate) trait Model {
    /// Number of parameters.
    const N: usize;
    /// `f(x; p)`; writes `∂f/∂p` into `grad` (length [`Self::N`]).
    fn eval(&self, p: &[f64], x: f64, grad: &mut [f64]) -> f64;
    /// `f(x; p)` without the gradient.
    fn value(&self, p: &[f64], x: f64) -> f64 {
        let mut g = [0.0; 8];
        self.eval(p, x, &mut g[..Self::N])
    }
}

/// Result of a converged fit.
#[derive(Debug, Clone)]
pub(crate) struct Fitted {
    /// Best-fit parameters.
    pub params: Vec<f64>,
    /// `f(x_i) − y_i`.
    pub residuals: Vec<f64>,
    /// Asymptotic covariance `s²·(JᵀJ)⁻¹`, `s² = Σr²/(n − p)`; `None` if singular.
    pub covariance: Option<DMatrix<f64>>,
}

impl Fitted {
    /// Sum of squared residuals.
    pub fn ssr(&self) -> f64 {
        self.residuals.iter().map(|r| r * r).sum()
    }

    /// Residual standard deviation `√(Σr²/(n − p))`.
    pub fn residual_std(&self) -> f64 {
        let dof = self
            .residuals
            .len()
            .saturating_sub(self.params.len())
            .max(1);
        (self.ssr() / dof as f64).sqrt()
    }

    /// Standard error of parameter `i` (∞ if the covariance is singular).
    pub fn std_err(&self, i: usize) -> f64 {
        self.covariance
            .as_ref()
            .map(|c| c[(i, i)].max(0.0).sqrt())
            .unwrap_or(f64::INFINITY)
    }
}

struct Problem<'a, M> {
    model: &'a M,
    x: &'a [f64],
    y: &'a [f64],
    p: DVector<f64>,
}

impl<M: Model> LeastSquaresProblem<f64, Dyn, Dyn> for Problem<'_, M> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, p: &DVector<f64>) {
        self.p.copy_from(p);
    }

    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let p = self.p.as_slice();
        let r = DVector::from_iterator(
            self.x.len(),
            self.x
                .iter()
                .zip(self.y)
                .map(|(&x, &y)| self.model.value(p, x) - y),
        );
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let p = self.p.as_slice();
        let mut j = DMatrix::zeros(self.x.len(), M::N);
        let mut g = [0.0; 8];
        for (i, &x) in self.x.iter().enumerate() {
            self.model.eval(p, x, &mut g[..M::N]);
            for k in 0..M::N {
                j[(i, k)] = g[k];
            }
        }
        j.iter().all(|v| v.is_finite()).then_some(j)
    }
}

/// Fit from `guesses[0]`; only if that fails, try the other starts and keep the
/// converged fit with the smallest residual sum. `what` names the model in errors.
pub(crate) fn fit_with_restarts<M: Model>(
    model: &M,
    x: &[f64],
    y: &[f64],
    guesses: &[Vec<f64>],
    what: &str,
) -> Result<Fitted, FitError> {
    let mut best: Option<Fitted> = None;
    let mut last_err = None;
    for (i, p0) in guesses.iter().enumerate() {
        match fit(model, x, y, p0) {
            Ok(f) => {
                if best.as_ref().is_none_or(|b| f.ssr() < b.ssr()) {
                    best = Some(f);
                }
                if i == 0 {
                    break;
                }
            }
            Err(e) => last_err = Some(e),
        }
    }
    best.ok_or_else(|| last_err.unwrap_or(FitError::NotConverged(what.into())))
}

/// Least-squares fit of `model` to `(x, y)` from the start `p0`.
/// `Err(NotConverged)` unless LM reports success and all parameters are finite.
pub(crate) fn fit<M: Model>(
    model: &M,
    x: &[f64],
    y: &[f64],
    p0: &[f64],
) -> Result<Fitted, FitError> {
    debug_assert_eq!(p0.len(), M::N);
    if x.len() != y.len() {
        return Err(FitError::BadData(format!(
            "x has {} points but y has {}",
            x.len(),
            y.len()
        )));
    }
    if x.len() <= M::N + 2 {
        return Err(FitError::TooFewPoints {
            got: x.len(),
            need: M::N + 3,
        });
    }
    let problem = Problem {
        model,
        x,
        y,
        p: DVector::from_column_slice(p0),
    };
    let (problem, report) = LevenbergMarquardt::new()
        .with_patience(200)
        .minimize(problem);
    if !report.termination.was_successful() {
        return Err(FitError::NotConverged(format!("{:?}", report.termination)));
    }
    let params: Vec<f64> = problem.p.iter().copied().collect();
    if params.iter().any(|v| !v.is_finite()) {
        return Err(FitError::NotConverged("non-finite parameters".into()));
    }
    let residuals: Vec<f64> = problem
        .residuals()
        .ok_or_else(|| FitError::NotConverged("non-finite residuals".into()))?
        .iter()
        .copied()
        .collect();
    let covariance = problem.jacobian().and_then(|j| {
        let dof = x.len().saturating_sub(M::N).max(1) as f64;
        let s2 = residuals.iter().map(|r| r * r).sum::<f64>() / dof;
        (j.transpose() * &j).try_inverse().map(|c| c * s2)
    });
    Ok(Fitted {
        params,
        residuals,
        covariance,
    })
}

/// Centred moving average over `2·half + 1` points (shorter at the ends).
pub(crate) fn smooth(y: &[f64], half: usize) -> Vec<f64> {
    (0..y.len())
        .map(|i| {
            let lo = i.saturating_sub(half);
            let hi = (i + half + 1).min(y.len());
            y[lo..hi].iter().sum::<f64>() / (hi - lo) as f64
        })
        .collect()
}

/// Robust white-noise estimate from successive differences: `MAD(Δy)·1.4826/√2`.
pub(crate) fn noise_estimate(y: &[f64]) -> f64 {
    let mut d: Vec<f64> = y.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    if d.is_empty() {
        return 0.0;
    }
    d.sort_by(f64::total_cmp);
    let med = d[d.len() / 2];
    med * 1.4826 / std::f64::consts::SQRT_2
}

/// Mean of a slice (0 for an empty one).
pub(crate) fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}
