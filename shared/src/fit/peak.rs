//! Coulomb peak `y = b + h·sech²((x − x₀)/γ)`: the sensing-dot sweep →
//! steepest flank of the highest peak (`sd_flank_mv`) and `sd_contrast`.

use nalgebra::{DMatrix, DVector};

use super::lm::{self, Model};
use super::tanh::check_axis;
use super::FitError;
use crate::detmath;
use crate::detmath::{MAX_SECH2_SLOPE, STEEPEST_SECH2_OFFSET};

struct PeakModel;

impl Model for PeakModel {
    const N: usize = 4;
    fn eval(&self, p: &[f64], x: f64, g: &mut [f64]) -> f64 {
        let (b, h, x0, gamma) = (p[0], p[1], p[2], p[3]);
        let z = (x - x0) / gamma;
        let t = detmath::tanh(z);
        let s = 1.0 - t * t;
        g[0] = 1.0;
        g[1] = s;
        g[2] = 2.0 * h * s * t / gamma;
        g[3] = 2.0 * h * s * t * z / gamma;
        b + h * s
    }
}

/// The highest peak of a sweep, fitted. Units of the data (x: gate mV).
#[derive(Debug, Clone, PartialEq)]
pub struct Peak {
    /// Background `b`, y units.
    pub background: f64,
    /// Height `h > 0`, y units.
    pub height: f64,
    /// Centre `x₀`, x units.
    pub center: f64,
    /// Width `γ > 0`, x units.
    pub width: f64,
    /// Steepest point of the lower-x flank, `x₀ − atanh(1/√3)·γ`, x units.
    pub flank: f64,
    /// Variance of `flank` from the fit covariance, x units².
    pub flank_variance: f64,
    /// Largest |slope| of the peak, `h·4/(3√3)/γ`, y per x.
    pub max_slope: f64,
    /// The x values of the fit window.
    pub window_x: Vec<f64>,
    /// Residuals `f(x_i) − y_i` on the window.
    pub residuals: Vec<f64>,
}

impl Peak {
    /// The fitted curve at `x`.
    pub fn value(&self, x: f64) -> f64 {
        PeakModel.value(&[self.background, self.height, self.center, self.width], x)
    }
}

/// Finds the highest peak of a sweep (maximum of the smoothed data), fits a
/// `sech²` peak on a window of ±3 estimated widths around it by
/// Levenberg–Marquardt and returns its steepest lower-x flank.
///
/// `Err(NoPeak)` if the peak is not significant (height < 5× noise), its
/// centre or flank lies outside the sweep, or its width is not resolved.
///
/// ```
/// use spintune::fit::peak::fit_highest_peak;
/// let x: Vec<f64> = (0..201).map(|i| -10.0 + 0.1 * i as f64).collect();
/// let sech2 = |z: f64| 1.0 / z.cosh().powi(2);
/// let y: Vec<f64> = x.iter().map(|&x| 0.5 + 4.0 * sech2((x - 1.0) / 1.2) + 3.0 * sech2((x + 7.0) / 1.2)).collect();
/// let p = fit_highest_peak(&x, &y).unwrap();
/// assert!((p.center - 1.0).abs() < 1e-3);
/// assert!((p.flank - (1.0 - 0.658_478_948_462_408_4 * 1.2)).abs() < 1e-2);
/// ```
pub fn fit_highest_peak(x: &[f64], y: &[f64]) -> Result<Peak, FitError> {
    check_axis(x, y)?;
    let n = x.len();
    if n < 10 {
        return Err(FitError::TooFewPoints { got: n, need: 10 });
    }
    let ys = lm::smooth(y, 2);
    let (i_max, &y_max) = ys
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .expect("non-empty");
    let y_min = ys.iter().copied().fold(f64::INFINITY, f64::min);
    let noise = lm::noise_estimate(y);
    let h0 = y_max - y_min;
    if h0 < 5.0 * noise {
        return Err(FitError::NoPeak(format!(
            "no peak: signal range {h0:.3e} vs noise {noise:.3e}"
        )));
    }
    let half = y_min + 0.5 * h0;
    let mut lo = i_max;
    while lo > 0 && ys[lo] > half {
        lo -= 1;
    }
    let mut hi = i_max;
    while hi + 1 < n && ys[hi] > half {
        hi += 1;
    }
    // HWHM of sech² is atanh(1/√2)·γ = 0.8814·γ.
    let hwhm = 0.5 * (x[hi] - x[lo]);
    let dx = (x[n - 1] - x[0]) / (n - 1) as f64;
    let gamma0 = (hwhm / 0.881_373_587_019_543).max(dx);
    let x0 = x[i_max];
    let from = x.partition_point(|&v| v < x0 - 3.0 * gamma0);
    let to = x.partition_point(|&v| v <= x0 + 3.0 * gamma0);
    let (wx, wy) = (&x[from..to], &y[from..to]);
    if wx.len() < 10 {
        return Err(FitError::TooFewPoints {
            got: wx.len(),
            need: 10,
        });
    }
    let f = lm::fit(&PeakModel, wx, wy, &[y_min, h0, x0, gamma0])?;
    let (b, h, c) = (f.params[0], f.params[1], f.params[2]);
    let gamma = f.params[3].abs();
    if h < 5.0 * noise {
        return Err(FitError::NoPeak(format!(
            "fitted height {h:.3e} below 5× noise {noise:.3e}"
        )));
    }
    if gamma < 0.5 * dx || gamma > x[n - 1] - x[0] {
        return Err(FitError::NoPeak(format!(
            "peak width {gamma:.3e} not resolved"
        )));
    }
    let flank = c - STEEPEST_SECH2_OFFSET * gamma;
    if !(wx[0]..=wx[wx.len() - 1]).contains(&c) || flank < x[0] {
        return Err(FitError::NoPeak(format!(
            "highest peak at {c:.3} (flank {flank:.3}) not inside the sweep [{:.3}, {:.3}]",
            x[0],
            x[n - 1]
        )));
    }
    let k = STEEPEST_SECH2_OFFSET * f.params[3].signum();
    let flank_variance = f
        .covariance
        .as_ref()
        .map(|cv| (cv[(2, 2)] + k * k * cv[(3, 3)] - 2.0 * k * cv[(2, 3)]).max(0.0))
        .unwrap_or(f64::INFINITY);
    Ok(Peak {
        background: b,
        height: h,
        center: c,
        width: gamma,
        flank,
        flank_variance,
        max_slope: h * MAX_SECH2_SLOPE / gamma,
        window_x: wx.to_vec(),
        residuals: f.residuals,
    })
}

/// Local slope of the data at `x_c` from a cubic least-squares polynomial
/// through the points within ±`half_width` of it (at least the 7 points
/// nearest to `x_c`). Returns `(slope, variance of slope)` with the noise
/// estimated from the whole trace. The cubic makes the slope exact up to
/// fourth-order curvature terms, so a noiseless peak flank gives its true slope.
pub(crate) fn local_slope(x: &[f64], y: &[f64], x_c: f64, half_width: f64) -> (f64, f64) {
    let mut idx: Vec<usize> = (0..x.len())
        .filter(|&i| (x[i] - x_c).abs() <= half_width)
        .collect();
    if idx.len() < 7 {
        let mut all: Vec<usize> = (0..x.len()).collect();
        all.sort_by(|&a, &b| (x[a] - x_c).abs().total_cmp(&(x[b] - x_c).abs()));
        idx = all.into_iter().take(7).collect();
    }
    let h = idx
        .iter()
        .map(|&i| (x[i] - x_c).abs())
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let design = DMatrix::from_fn(idx.len(), 4, |r, c| ((x[idx[r]] - x_c) / h).powi(c as i32));
    let rhs = DVector::from_iterator(idx.len(), idx.iter().map(|&i| y[i]));
    let normal = design.transpose() * &design;
    let Some(inv) = normal.try_inverse() else {
        return (0.0, f64::INFINITY);
    };
    let coef = &inv * (design.transpose() * rhs);
    let noise = lm::noise_estimate(y);
    (coef[1] / h, noise * noise * inv[(1, 1)] / (h * h))
}
