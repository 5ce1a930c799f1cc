//! Tuned parameters: what is measured, its unit, its target and tolerance, and
//! the optional log transform (tune `ln p` instead of `p`, the paper's proposal
//! for tunnel-coupling-like quantities).

use serde::{Deserialize, Serialize};

use crate::config_error::ConfigError;

/// The measurements a device can be asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanKind {
    /// 1-D sweep of a sensing-dot gate over Coulomb peaks → `sd_flank_mv`
    /// (steepest flank of the highest peak, mV) and `sd_contrast`.
    SensingDot,
    /// Lead-transition scans in the RFA/RFB plane → `mu_a_mv`, `mu_b_mv`
    /// (transition-line positions, mV on RFA and RFB).
    ChemicalPotential,
    /// Detuning line scan across the inter-dot transition → `w` (µV).
    TransitionWidth,
    /// Load curve (signal vs. wait time) → `t_sr` (ns).
    ReloadTime,
}

impl ScanKind {
    /// Whether the parameters this scan gives are positive quantities (a
    /// width, a time): `w` and `t_sr` are, line and flank positions (mV) are not.
    pub fn gives_positive_values(self) -> bool {
        matches!(self, ScanKind::TransitionWidth | ScanKind::ReloadTime)
    }

    /// All kinds.
    pub const ALL: [ScanKind; 4] = [
        ScanKind::SensingDot,
        ScanKind::ChemicalPotential,
        ScanKind::TransitionWidth,
        ScanKind::ReloadTime,
    ];
}

/// Space in which the estimator and solver see a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Transform {
    /// `p` itself.
    #[default]
    Linear,
    /// `ln p` (requires `p > 0`); the variance maps as `δ(ln p)² = δp² / p²`.
    Log,
}

impl Transform {
    /// Map a value and its variance into estimator space. `None` if not representable
    /// (non-positive value under `Log`, or non-finite input).
    ///
    /// ```
    /// use spintune::parameter::Transform;
    /// let (y, var) = Transform::Log.forward(20.0, 4.0).unwrap();
    /// assert!((y - 20f64.ln()).abs() < 1e-15);
    /// assert!((var - 0.01).abs() < 1e-15);
    /// assert!(Transform::Log.forward(-1.0, 1.0).is_none());
    /// ```
    pub fn forward(self, value: f64, variance: f64) -> Option<(f64, f64)> {
        if !value.is_finite() || !variance.is_finite() || variance < 0.0 {
            return None;
        }
        match self {
            Transform::Linear => Some((value, variance)),
            Transform::Log => (value > 0.0).then(|| (value.ln(), variance / (value * value))),
        }
    }

    /// Back from estimator space: a value and its variance in the
    /// parameter's unit (first order: `δp = p·δ(ln p)` under `Log`).
    ///
    /// ```
    /// use spintune::parameter::Transform;
    /// let (p, var) = Transform::Log.inverse(20f64.ln(), 0.01);
    /// assert!((p - 20.0).abs() < 1e-12 && (var - 4.0).abs() < 1e-12);
    /// assert_eq!(Transform::Linear.inverse(1.5, 0.2), (1.5, 0.2));
    /// ```
    pub fn inverse(self, y: f64, variance: f64) -> (f64, f64) {
        match self {
            Transform::Linear => (y, variance),
            Transform::Log => {
                let p = y.exp();
                (p, p * p * variance)
            }
        }
    }

    /// Map a value alone into estimator space (targets).
    pub fn forward_value(self, value: f64) -> Option<f64> {
        self.forward(value, 0.0).map(|x| x.0)
    }

    /// Chain rule for a gradient: `∂(ln p)/∂v = (∂p/∂v) / p`.
    pub fn forward_gradient_factor(self, value: f64) -> f64 {
        match self {
            Transform::Linear => 1.0,
            Transform::Log => 1.0 / value,
        }
    }
}

/// Tolerance band around a target.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Tolerance {
    /// `|p − p*| ≤ value` (parameter units).
    Absolute(f64),
    /// `|p − p*| ≤ fraction · |p*|` (e.g. 0.1 for ±10 %).
    Relative(f64),
}

impl Default for Tolerance {
    fn default() -> Self {
        Tolerance::Relative(0.1)
    }
}

impl Tolerance {
    /// Half-width of the band around `target`, in parameter units.
    pub fn half_width(self, target: f64) -> f64 {
        match self {
            Tolerance::Absolute(a) => a.abs(),
            Tolerance::Relative(r) => (r * target).abs(),
        }
    }

    /// Whether `value` lies inside the band around `target`.
    pub fn contains(self, target: f64, value: f64) -> bool {
        (value - target).abs() <= self.half_width(target)
    }

    /// Checks the tolerance is a finite, non-negative number. The error's
    /// field is the variant's key (`absolute` or `relative`, as in
    /// `{ relative = 0.1 }`); prefix it with [`ConfigError::within`].
    ///
    /// ```
    /// use spintune::parameter::Tolerance;
    /// let e = Tolerance::Relative(-1.0).validate().unwrap_err().within("tolerances.w");
    /// assert_eq!(e.field, "tolerances.w.relative");
    /// ```
    pub fn validate(self) -> Result<(), ConfigError> {
        let (field, x) = match self {
            Tolerance::Absolute(a) => ("absolute", a),
            Tolerance::Relative(r) => ("relative", r),
        };
        if x.is_finite() && x >= 0.0 {
            Ok(())
        } else {
            Err(ConfigError::new(
                field,
                format!("must be finite and non-negative, got {x}"),
            ))
        }
    }
}

/// One tuned (or merely observed) parameter of a tuner level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParameterSpec {
    /// Name as reported by the evaluation of its scan, e.g. `"t_sr"`.
    pub name: String,
    /// Display unit, e.g. `"ns"`, `"µV"`, `"mV"`.
    pub unit: String,
    /// The scan that measures it.
    pub scan: ScanKind,
    /// Target value (parameter units). `None`: observed but not driven anywhere.
    #[serde(default)]
    pub target: Option<f64>,
    /// Tolerance band around the target.
    #[serde(default)]
    pub tolerance: Tolerance,
    /// Estimator space.
    #[serde(default)]
    pub transform: Transform,
    /// Isotropic process noise σ_Q added to every gradient element per update,
    /// in (estimator-space unit)/mV: `Q = σ_Q² I` (paper: 0.075 ns/mV for t_sr,
    /// 0.3 µV/mV for w). In log space the unit is 1/mV.
    #[serde(default)]
    pub process_noise_per_mv: f64,
}

/// Largest |target| of any parameter, in its unit (ns, µV, mV): the
/// config's magnitude bound ([`crate::tuner::MAX_MAGNITUDE`]).
pub const MAX_TARGET_MAGNITUDE: f64 = 1e6;

impl ParameterSpec {
    /// The one check of a target for this parameter (config, schedule,
    /// `set_target` from the API, the dashboard and Python): finite, at most
    /// [`MAX_TARGET_MAGNITUDE`] in magnitude, and > 0 for a positive quantity
    /// (`w`, `t_sr`: [`ScanKind::gives_positive_values`]) or a log-space
    /// parameter. The error's field is `target`.
    ///
    /// ```
    /// use spintune::driver::SimulationConfig;
    /// let t_sr = SimulationConfig::paper_default().tuner.top().parameters[0].clone();
    /// assert_eq!(t_sr.name, "t_sr");
    /// assert!(t_sr.check_target(70.0).is_ok());
    /// assert!(t_sr.check_target(-50.0).unwrap_err().to_string().contains("must be > 0"));
    /// assert!(t_sr.check_target(1e8).unwrap_err().to_string().contains("at most"));
    /// ```
    pub fn check_target(&self, target: f64) -> Result<(), ConfigError> {
        if !target.is_finite() {
            return Err(ConfigError::new("target", "must be a finite number"));
        }
        if target.abs() > MAX_TARGET_MAGNITUDE {
            return Err(ConfigError::new(
                "target",
                format!(
                    "must be at most {MAX_TARGET_MAGNITUDE:e} {} in magnitude, got {target}",
                    self.unit
                ),
            ));
        }
        let positive = self.scan.gives_positive_values() || self.transform == Transform::Log;
        if positive && target <= 0.0 {
            let why = if self.transform == Transform::Log {
                "a log-transformed parameter"
            } else {
                "a width or time"
            };
            return Err(ConfigError::new(
                "target",
                format!(
                    "must be > 0 for {} ({why}), got {target} {}",
                    self.name, self.unit
                ),
            ));
        }
        Ok(())
    }

    /// Whether the parameter is inside its band (true when it has no target).
    pub fn in_band(&self, value: f64) -> bool {
        match self.target {
            Some(t) => self.tolerance.contains(t, value),
            None => true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tolerance_bands() {
        assert!(Tolerance::Relative(0.1).contains(20.0, 21.9));
        assert!(!Tolerance::Relative(0.1).contains(20.0, 22.1));
        assert!(Tolerance::Absolute(5.0).contains(270.0, 266.0));
        assert_eq!(
            Tolerance::Absolute(-1.0).validate().unwrap_err().field,
            "absolute"
        );
        assert_eq!(
            Tolerance::Relative(f64::NAN).validate().unwrap_err().field,
            "relative"
        );
        assert!(Tolerance::Relative(0.0).validate().is_ok());
    }

    #[test]
    fn log_gradient_factor() {
        assert_eq!(Transform::Log.forward_gradient_factor(4.0), 0.25);
        assert_eq!(Transform::Linear.forward_gradient_factor(4.0), 1.0);
    }
}
