//! Exponential decay `y = y∞ + B·exp(−t/τ)`: the load curve → `t_sr = τ`.

use super::lm::{self, Model};
use super::tanh::check_axis;
use super::FitError;
use crate::detmath;

struct ExpModel;

impl Model for ExpModel {
    const N: usize = 3;
    fn eval(&self, p: &[f64], t: f64, g: &mut [f64]) -> f64 {
        let (y_inf, b, tau) = (p[0], p[1], p[2]);
        let e = detmath::exp(-t / tau);
        g[0] = 1.0;
        g[1] = e;
        g[2] = b * e * t / (tau * tau);
        y_inf + b * e
    }
}

/// A fitted exponential. Units are those of the data.
#[derive(Debug, Clone, PartialEq)]
pub struct Exponential {
    /// `y∞`: asymptote, y units.
    pub asymptote: f64,
    /// `B`: signed amplitude at t = 0, y units.
    pub amplitude: f64,
    /// `τ > 0`: decay time, t units.
    pub tau: f64,
    /// Standard error of `tau` from the fit covariance `s²·(JᵀJ)⁻¹`
    /// (`s²` the reduced residual sum of squares), t units; ∞ if singular.
    pub tau_std: f64,
    /// Residuals `f(t_i) − y_i`.
    pub residuals: Vec<f64>,
}

impl Exponential {
    /// The fitted curve at `t`.
    pub fn value(&self, t: f64) -> f64 {
        ExpModel.value(&[self.asymptote, self.amplitude, self.tau], t)
    }
}

/// Fits `y∞ + B·exp(−t/τ)` to `(t, y)` (t strictly increasing, ≥ 10 points)
/// by Levenberg–Marquardt. Initial guess: asymptote from the last tenth,
/// amplitude from the first points, τ from the 1/e crossing of the smoothed
/// data. `Err` unless the decay is significant (|B| ≥ 3 residual std) and
/// `τ` lies between a fifth of a sample spacing and three scan lengths.
///
/// ```
/// use spintune::fit::exponential::fit_exponential;
/// let t: Vec<f64> = (0..101).map(|i| 5.0 * i as f64).collect();
/// let y: Vec<f64> = t.iter().map(|&t| 2.0 - 0.7 * (-t / 45.0).exp()).collect();
/// let f = fit_exponential(&t, &y).unwrap();
/// assert!((f.tau - 45.0).abs() < 1e-8);
/// ```
pub fn fit_exponential(t: &[f64], y: &[f64]) -> Result<Exponential, FitError> {
    check_axis(t, y)?;
    let n = t.len();
    if n < 10 {
        return Err(FitError::TooFewPoints { got: n, need: 10 });
    }
    let ys = lm::smooth(y, 1);
    let q = (n / 10).max(3);
    let y_inf = lm::mean(&ys[n - q..]);
    let b0 = ys[0] - y_inf;
    let range = t[n - 1] - t[0];
    let dt = range / (n - 1) as f64;
    let tau0 = ys
        .iter()
        .zip(t)
        .find(|(v, _)| (*v - y_inf).abs() < b0.abs() / std::f64::consts::E)
        .map(|(_, &ti)| (ti - t[0]).max(dt))
        .unwrap_or(range / 3.0);
    // Amplitude at t = 0 when the scan starts later.
    let b0 = b0 * detmath::exp(t[0] / tau0);
    let guesses: Vec<Vec<f64>> = [1.0, 2.5, 0.4]
        .iter()
        .map(|s| vec![y_inf, b0, tau0 * s])
        .collect();
    let f = lm::fit_with_restarts(&ExpModel, t, y, &guesses, "exponential")?;
    let (asymptote, amplitude, tau) = (f.params[0], f.params[1], f.params[2]);
    if !(tau >= 0.2 * dt && tau <= 3.0 * range) {
        return Err(FitError::BadData(format!(
            "decay time {tau:.4e} outside [{:.4e}, {:.4e}]",
            0.2 * dt,
            3.0 * range
        )));
    }
    let visible = amplitude * detmath::exp(-t[0] / tau);
    let noise = f.residual_std();
    if visible.abs() < 3.0 * noise {
        return Err(FitError::BadData(format!(
            "no significant decay: amplitude {visible:.3e} vs residual std {noise:.3e}"
        )));
    }
    Ok(Exponential {
        asymptote,
        amplitude,
        tau,
        tau_std: f.std_err(2),
        residuals: f.residuals,
    })
}
