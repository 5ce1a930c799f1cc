//! Tanh step with linear background: `y = c + s·x + (A/2)·tanh((x − x₀)/w)`.
//!
//! Used for the inter-dot transition (width `w` → parameter `w`) and for the
//! lead transitions (position `x₀` → `mu_a_mv`, `mu_b_mv`).

use super::lm::{self, Model};
use super::FitError;
use crate::detmath;

struct TanhModel;

impl Model for TanhModel {
    const N: usize = 5;
    fn eval(&self, p: &[f64], x: f64, g: &mut [f64]) -> f64 {
        let (c, s, a, x0, w) = (p[0], p[1], p[2], p[3], p[4]);
        let z = (x - x0) / w;
        let t = detmath::tanh(z);
        let sech2 = 1.0 - t * t;
        g[0] = 1.0;
        g[1] = x;
        g[2] = 0.5 * t;
        g[3] = -0.5 * a * sech2 / w;
        g[4] = -0.5 * a * sech2 * z / w;
        c + s * x + 0.5 * a * t
    }
}

/// A fitted tanh step. Units are those of the data (`x` and `y`).
#[derive(Debug, Clone, PartialEq)]
pub struct TanhStep {
    /// `c`: signal at the step centre without the step, y units.
    pub offset: f64,
    /// `s`: linear background slope, y per x.
    pub slope: f64,
    /// `A`: signed step height (right minus left), y units.
    pub height: f64,
    /// `x₀`: step centre, x units.
    pub center: f64,
    /// `w > 0`: step width, x units (`tanh((x − x₀)/w)`).
    pub width: f64,
    /// Standard error of `center` from the fit covariance, x units.
    pub center_std: f64,
    /// Standard error of `width` from the fit covariance `s²·(JᵀJ)⁻¹`
    /// (`s²` the reduced residual sum of squares), x units; ∞ if singular.
    pub width_std: f64,
    /// Residuals `f(x_i) − y_i`.
    pub residuals: Vec<f64>,
}

impl TanhStep {
    /// The fitted curve at `x`.
    pub fn value(&self, x: f64) -> f64 {
        TanhModel.value(
            &[
                self.offset,
                self.slope,
                self.height,
                self.center,
                self.width,
            ],
            x,
        )
    }
}

/// Checks that `x` is strictly increasing and everything is finite.
pub(crate) fn check_axis(x: &[f64], y: &[f64]) -> Result<(), FitError> {
    if x.len() != y.len() {
        return Err(FitError::BadData(format!(
            "x has {} points but y has {}",
            x.len(),
            y.len()
        )));
    }
    if x.iter().chain(y).any(|v| !v.is_finite()) {
        return Err(FitError::BadData("non-finite sample".into()));
    }
    if x.windows(2).any(|w| w[1] <= w[0]) {
        return Err(FitError::BadData("x must be strictly increasing".into()));
    }
    Ok(())
}

/// Fits a tanh step with linear background to `(x, y)` (x strictly
/// increasing, ≥ 10 points) by Levenberg–Marquardt from a robust initial
/// guess (plateaus at both ends, centre at the steepest point of the
/// smoothed data). The step must be significant (|A| ≥ 3 residual std),
/// centred inside the scan, wider than half a grid step and narrower than
/// half the scan; otherwise `Err`.
///
/// ```
/// use spintune::fit::tanh::fit_tanh_step;
/// let x: Vec<f64> = (0..100).map(|i| -2.0 + 4.0 * i as f64 / 99.0).collect();
/// let y: Vec<f64> = x.iter().map(|&x| 1.0 + 0.1 * x - 0.4 * ((x - 0.3) / 0.2).tanh()).collect();
/// let f = fit_tanh_step(&x, &y).unwrap();
/// assert!((f.width - 0.2).abs() < 1e-9 && (f.center - 0.3).abs() < 1e-9);
/// assert!((f.height + 0.8).abs() < 1e-9);
/// ```
pub fn fit_tanh_step(x: &[f64], y: &[f64]) -> Result<TanhStep, FitError> {
    check_axis(x, y)?;
    let n = x.len();
    if n < 10 {
        return Err(FitError::TooFewPoints { got: n, need: 10 });
    }
    let ys = lm::smooth(y, 2);
    let q = (n / 10).max(3);
    let left = lm::mean(&ys[..q]);
    let right = lm::mean(&ys[n - q..]);
    let a0 = right - left;
    let sign = if a0 >= 0.0 { 1.0 } else { -1.0 };
    let (mut best_i, mut best_d) = (n / 2, f64::NEG_INFINITY);
    for i in 1..n - 1 {
        let d = sign * (ys[i + 1] - ys[i - 1]) / (x[i + 1] - x[i - 1]);
        if d > best_d {
            best_d = d;
            best_i = i;
        }
    }
    let range = x[n - 1] - x[0];
    let dx = range / (n - 1) as f64;
    let w0 = if best_d > 0.0 {
        (a0.abs() / (2.0 * best_d)).clamp(dx, range / 4.0)
    } else {
        range / 10.0
    };
    let x0 = x[best_i];
    let c0 = 0.5 * (left + right);
    let guesses: Vec<Vec<f64>> = [1.0, 3.0, 0.4]
        .iter()
        .map(|s| vec![c0, 0.0, a0, x0, w0 * s])
        .collect();
    let f = lm::fit_with_restarts(&TanhModel, x, y, &guesses, "tanh step")?;
    let p = &f.params;
    // tanh is odd: (A, w) and (−A, −w) are the same curve.
    let (height, width) = if p[4] < 0.0 {
        (-p[2], -p[4])
    } else {
        (p[2], p[4])
    };
    let noise = f.residual_std();
    if height.abs() < 3.0 * noise {
        return Err(FitError::BadData(format!(
            "no significant step: height {height:.3e} vs residual std {noise:.3e}"
        )));
    }
    if !(x[0]..=x[n - 1]).contains(&p[3]) {
        return Err(FitError::BadData(format!(
            "step centre {:.4} outside the scan [{:.4}, {:.4}]",
            p[3],
            x[0],
            x[n - 1]
        )));
    }
    if width < 0.5 * dx || width > range / 2.0 {
        return Err(FitError::BadData(format!(
            "step width {width:.4e} outside [{:.4e}, {:.4e}] (grid step, half scan)",
            0.5 * dx,
            range / 2.0
        )));
    }
    Ok(TanhStep {
        offset: p[0],
        slope: p[1],
        height,
        center: p[3],
        width,
        center_std: f.std_err(3),
        width_std: f.std_err(4),
        residuals: f.residuals,
    })
}
