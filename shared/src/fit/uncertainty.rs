//! Measurement uncertainty of fitted `w` and `t_sr`.
//!
//! Two rules ([`UncertaintyRule`]); the default is
//! [`UncertaintyRule::FitCovariance`]:
//!
//! `δp² = (κ·s_p)² + (r·p)²`
//!
//! with `s_p` the fit's standard error from `s²·(JᵀJ)⁻¹` (`s²` the reduced
//! residual sum of squares, so it follows the noise of *this* scan), `κ =
//! √((1+ρ)/(1−ρ))` the inflation for residuals correlated by drift (`ρ` the
//! lag-1 autocorrelation of the residuals, clamped to 0..0.9) and `r` a
//! relative floor ([`Reference::relative_floor`]) for scatter that no single
//! scan can see (in the simulator: the line-B detuning that drifts between
//! scans multiplies the apparent reload time, `τ = t_sr·(1 + k·b²)`).
//! Measured on the default device over 300 scans at the start point and at
//! the paper's set points, this rule covers 60–70 % of the true values
//! within 1σ everywhere, whereas the paper's rule below, calibrated at the
//! start point only, reported 0.55 ns at t_sr = 20 ns against 0.27 ns actual
//! scatter and 0.55 ns at 70 ns against 0.87 ns (see `docs/benchmarks.md`
//! and `shared/tests/error_bars.rs`).
//!
//! The paper's procedure (supplement, "Measurement Uncertainty",
//! [`UncertaintyRule::Paper`]):
//!
//! `σ = Σ_i ((f(x_i) − y_i)/Θ_p)²`, `δp ≈ δp₀ · σ/σ₀`,
//!
//! with `Θ_w` the fitted step height of the inter-dot transition and `Θ_tsr`
//! the range of the load-curve data. `σ₀` is the mean of `σ` and `δp₀` the
//! standard deviation of `p` over many repeated measurements at a fixed
//! operating point.
//!
//! The references belong to a measurement setup, not to this module: a lab
//! calibrates its own (repeated scans at a fixed operating point) and passes
//! them in, e.g. as [`crate::tuner::TunerConfig::fit_references`].
//! [`SIMULATED_DEVICE_REFERENCES`] (also [`References::default`]) is the
//! calibration of the default simulated device.
//!
//! Note that `σ` is a sum of squares, so `δp` grows with the square of the
//! noise-to-signal ratio: at half the sensing-dot contrast `δp` is about
//! four times `δp₀`, roughly twice the true scatter. The paper's rule is
//! conservative there, which is what a tuner wants from a degraded scan.

use serde::{Deserialize, Serialize};

/// Reference constants of one parameter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reference {
    /// Mean scaled residual sum `σ₀` of the reference scans (dimensionless).
    pub sigma0: f64,
    /// Standard deviation `δp₀` of the parameter over the reference scans
    /// (parameter unit: µV for `w`, ns for `t_sr`).
    pub delta_p0: f64,
    /// Relative floor `r` of [`UncertaintyRule::FitCovariance`]: scatter
    /// between scans that a single scan's residuals cannot show, as a
    /// fraction of the value (dimensionless, 0 ≤ r < 1; default 0). The
    /// joint array loop raises `t_sr`'s to at least
    /// [`ArrayRunSettings::t_sr_floor`](crate::tuner::array_run::ArrayRunSettings::t_sr_floor).
    #[serde(default)]
    pub relative_floor: f64,
}

/// How `δp` of `w` and `t_sr` is derived from a fitted scan (see the module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UncertaintyRule {
    /// `δp² = (κ·s_p)² + (r·p)²`: the fit covariance scaled by the residual,
    /// inflated for correlated residuals, plus a relative floor.
    #[default]
    FitCovariance,
    /// The paper's `δp ≈ δp₀·σ/σ₀` (valid near the calibration point only).
    Paper,
}

impl Reference {
    /// `δp = δp₀·σ/σ₀`, parameter unit.
    ///
    /// ```
    /// use spintune::fit::uncertainty::Reference;
    /// let r = Reference { sigma0: 2.0, delta_p0: 5.0, relative_floor: 0.0 };
    /// assert_eq!(r.delta(4.0), 10.0);
    /// ```
    pub fn delta(&self, sigma: f64) -> f64 {
        self.delta_p0 * sigma / self.sigma0
    }

    /// [`UncertaintyRule::FitCovariance`]: `√((κ·s_p)² + (r·p)²)` for a fitted
    /// `value` with standard error `std_err` (both in the parameter unit) and
    /// the fit's `residuals`.
    ///
    /// ```
    /// use spintune::fit::uncertainty::Reference;
    /// let r = Reference { sigma0: 1.0, delta_p0: 1.0, relative_floor: 0.01 };
    /// // uncorrelated residuals: κ = 1
    /// let d = r.delta_from_fit(100.0, 3.0, &[1.0, -1.0, 1.0, -1.0]);
    /// assert!((d - (9.0f64 + 1.0).sqrt()).abs() < 1e-12);
    /// ```
    pub fn delta_from_fit(&self, value: f64, std_err: f64, residuals: &[f64]) -> f64 {
        // basic IEEE operations only (bit-identical on wasm32 and native)
        let fit = correlation_inflation(residuals) * std_err;
        let floor = self.relative_floor * value;
        (fit * fit + floor * floor).sqrt()
    }

    /// The variance (unit²) a value `value` evaluated under `rule` with
    /// variance `variance` would have had with this reference's relative
    /// floor raised to `floor`: under [`UncertaintyRule::FitCovariance`] the
    /// floor adds in quadrature ([`Self::delta_from_fit`]), so `variance +
    /// (floor² − r²)·value²` when `floor > r`; unchanged otherwise, and
    /// under [`UncertaintyRule::Paper`], which has no floor.
    ///
    /// ```
    /// use spintune::fit::uncertainty::{Reference, UncertaintyRule};
    /// let r = Reference { sigma0: 1.0, delta_p0: 1.0, relative_floor: 0.01 };
    /// let d = r.delta_from_fit(100.0, 3.0, &[1.0, -1.0, 1.0, -1.0]);
    /// let raised = Reference { relative_floor: 0.05, ..r };
    /// let e = raised.delta_from_fit(100.0, 3.0, &[1.0, -1.0, 1.0, -1.0]);
    /// let v = r.variance_with_floor(UncertaintyRule::FitCovariance, 100.0, d * d, 0.05);
    /// assert!((v - e * e).abs() < 1e-9);
    /// assert_eq!(r.variance_with_floor(UncertaintyRule::Paper, 100.0, 4.0, 0.05), 4.0);
    /// assert_eq!(r.variance_with_floor(UncertaintyRule::FitCovariance, 100.0, 4.0, 0.0), 4.0);
    /// ```
    pub fn variance_with_floor(
        &self,
        rule: UncertaintyRule,
        value: f64,
        variance: f64,
        floor: f64,
    ) -> f64 {
        let r = self.relative_floor;
        match rule {
            UncertaintyRule::FitCovariance if floor > r => {
                variance + (floor * floor - r * r) * value * value
            }
            _ => variance,
        }
    }
}

/// `κ = √((1+ρ)/(1−ρ))`, `ρ` the lag-1 autocorrelation of `residuals`
/// clamped to 0..0.9 (the variance inflation of a mean of AR(1) noise);
/// 1 for white or anti-correlated residuals.
///
/// ```
/// use spintune::fit::uncertainty::correlation_inflation;
/// assert_eq!(correlation_inflation(&[1.0, -1.0, 1.0, -1.0]), 1.0);
/// assert!(correlation_inflation(&[1.0, 1.0, 1.0, -1.0, -1.0, -1.0]) > 1.5);
/// ```
pub fn correlation_inflation(residuals: &[f64]) -> f64 {
    let c0: f64 = residuals.iter().map(|r| r * r).sum();
    if !(c0 > 0.0 && c0.is_finite()) {
        return 1.0;
    }
    let c1: f64 = residuals.windows(2).map(|p| p[0] * p[1]).sum();
    let rho = (c1 / c0).clamp(0.0, 0.9);
    ((1.0 + rho) / (1.0 - rho)).sqrt()
}

/// Reference constants for every parameter evaluated this way.
///
/// [`References::default`] is [`SIMULATED_DEVICE_REFERENCES`], the
/// calibration of the default simulated device; a real device needs its own.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct References {
    /// For `w` (µV).
    pub w: Reference,
    /// For `t_sr` (ns).
    pub t_sr: Reference,
    /// Which rule derives `δp` (default [`UncertaintyRule::FitCovariance`];
    /// `sigma0`/`delta_p0` are used only by [`UncertaintyRule::Paper`]).
    #[serde(default)]
    pub rule: UncertaintyRule,
}

/// Reference constants of the default simulated device (its default
/// configuration, `DeviceConfig::default()`, at the start point of
/// `default_gates()`, both in the simulator module), from
/// `spintune::sim::calibrate_reference(&DeviceConfig::default(), &default_gates(), 2024, 400)`
/// (400 scans of each kind, seed 2024), rounded to three significant digits.
/// The test `reference_constants_match_calibration` in `shared/tests/sim_fits.rs`
/// re-derives them and checks agreement within 1 %.
///
/// Only valid for that simulated device; it is the default of
/// [`References`] so that simulated runs need no calibration step.
pub const SIMULATED_DEVICE_REFERENCES: References = References {
    w: Reference {
        sigma0: 0.0116,
        delta_p0: 4.67,
        relative_floor: W_FLOOR,
    },
    t_sr: Reference {
        sigma0: 0.005_33,
        delta_p0: 0.546,
        relative_floor: T_SR_FLOOR,
    },
    rule: UncertaintyRule::FitCovariance,
};
const W_FLOOR: f64 = 0.006_55;
const T_SR_FLOOR: f64 = 0.009_14;

impl Default for References {
    /// [`SIMULATED_DEVICE_REFERENCES`].
    fn default() -> Self {
        SIMULATED_DEVICE_REFERENCES
    }
}

/// `σ = Σ (r_i/Θ)²` for residuals `r` and scale `Θ` (must be > 0).
///
/// ```
/// assert_eq!(spintune::fit::uncertainty::scaled_residual_sum(&[1.0, -2.0], 2.0), 1.25);
/// ```
pub fn scaled_residual_sum(residuals: &[f64], theta: f64) -> f64 {
    residuals.iter().map(|r| (r / theta).powi(2)).sum()
}
