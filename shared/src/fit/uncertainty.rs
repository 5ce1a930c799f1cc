//! Measurement uncertainty of fitted parameters by the paper's procedure
//! (supplement, "Measurement Uncertainty"):
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
}

impl Reference {
    /// `δp = δp₀·σ/σ₀`, parameter unit.
    ///
    /// ```
    /// use spintune::fit::uncertainty::Reference;
    /// let r = Reference { sigma0: 2.0, delta_p0: 5.0 };
    /// assert_eq!(r.delta(4.0), 10.0);
    /// ```
    pub fn delta(&self, sigma: f64) -> f64 {
        self.delta_p0 * sigma / self.sigma0
    }
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
    },
    t_sr: Reference {
        sigma0: 0.005_33,
        delta_p0: 0.546,
    },
};

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
