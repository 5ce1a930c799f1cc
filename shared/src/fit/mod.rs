//! Parameter extraction from raw scans by Levenberg–Marquardt fits
//! (the `levenberg-marquardt` crate on nalgebra).
//!
//! | scan | fit | parameters |
//! |---|---|---|
//! | [`ScanKind::TransitionWidth`] | [`tanh::fit_tanh_step`] | `w` (µV) = 1000 × fitted width (mV) |
//! | [`ScanKind::ReloadTime`] | [`exponential::fit_exponential`] | `t_sr` (ns) = τ |
//! | [`ScanKind::SensingDot`] | [`peak::fit_highest_peak`] | `sd_flank_mv` (mV), `sd_contrast` (0..1) |
//! | [`ScanKind::ChemicalPotential`] | [`tanh::fit_tanh_step`] per line | `mu_a_mv`, `mu_b_mv` (mV) |
//!
//! Variances: `w` and `t_sr` by the rule of [`uncertainty`] (default: fit
//! covariance scaled by the residual, inflated for correlated residuals, plus
//! a calibrated relative floor; or the paper's residual rule), with reference constants the caller passes in (a
//! lab's own calibration; the tuner takes them from
//! [`crate::tuner::TunerConfig::fit_references`]); the others from the fit
//! covariance. A fit that does not converge or whose result is implausible
//! is an `Err`, never a value. All model functions use [`crate::detmath`],
//! so fits are bit-reproducible across targets.
//!
//! This module knows nothing about the simulator: it fits whatever raw scans
//! it is given, from the simulator or from instruments.

pub mod exponential;
pub(crate) mod lm;
pub mod peak;
pub mod tanh;
pub mod uncertainty;

use crate::protocol::{ParameterValue, RawScan, ScanKind, Trace};
use uncertainty::{scaled_residual_sum, References, UncertaintyRule};

/// Why a scan could not be evaluated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// Not enough data points for the model.
    #[error("too few points: got {got}, need at least {need}")]
    TooFewPoints {
        /// Points supplied.
        got: usize,
        /// Points needed.
        need: usize,
    },
    /// Levenberg–Marquardt did not converge.
    #[error("fit did not converge: {0}")]
    NotConverged(String),
    /// The data are malformed or the fit result is implausible.
    #[error("bad data: {0}")]
    BadData(String),
    /// No usable Coulomb peak in a sensing-dot sweep.
    #[error("no usable peak: {0}")]
    NoPeak(String),
}

/// Parameters extracted from one scan, with the fitted curves for display.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// Fitted parameters with variances (unit²).
    pub values: Vec<ParameterValue>,
    /// Fitted curves (label `"fit"` or `"fit <trace label>"`), on the data's x.
    pub fit: Vec<Trace>,
    /// Parameters of this scan that could not be evaluated while others
    /// could, with why: a line scan's two traces are fitted one by one, so
    /// a line outside the window leaves the other's value (the tuner counts
    /// the scan as failed and still uses what it gave). Empty for every
    /// other kind (one failure fails the scan).
    pub missing: Vec<(String, FitError)>,
}

/// Evaluates a raw scan: fits the model of its [`ScanKind`] and returns the
/// parameters with variances. `references` are the `σ₀`, `δp₀` constants of
/// the `w` and `t_sr` uncertainties ([`uncertainty`]): a lab's own
/// calibration from repeated scans at a fixed operating point.
/// [`References::default`] is the calibration of the default simulated
/// device ([`uncertainty::SIMULATED_DEVICE_REFERENCES`]) and is wrong for
/// any other device.
///
/// ```
/// use spintune::fit::{evaluate_with, uncertainty::{Reference, References}};
/// use spintune::protocol::{RawScan, ScanKind, Trace};
/// let x: Vec<f64> = (0..100).map(|i| -2.0 + 4.0 * f64::from(i) / 99.0).collect();
/// let y: Vec<f64> = x.iter().map(|&x| 0.5 * ((x + 0.4) / 0.25).tanh()).collect();
/// let scan = RawScan {
///     kind: ScanKind::TransitionWidth,
///     x_label: "detuning (mV)".into(),
///     y_label: "signal".into(),
///     traces: vec![Trace { label: "data".into(), x, y }],
/// };
/// let lab = References {
///     w: Reference { sigma0: 0.02, delta_p0: 5.0, relative_floor: 0.0 },
///     t_sr: Reference { sigma0: 0.01, delta_p0: 0.5, relative_floor: 0.01 },
///     rule: Default::default(),
/// };
/// let eval = evaluate_with(&scan, &lab).unwrap();
/// assert_eq!(eval.values[0].name, "w");
/// assert!((eval.values[0].value - 250.0).abs() < 1e-6); // µV
/// ```
pub fn evaluate_with(scan: &RawScan, references: &References) -> Result<Evaluation, FitError> {
    match scan.kind {
        ScanKind::TransitionWidth => {
            let t = single_trace(scan)?;
            let f = tanh::fit_tanh_step(&t.x, &t.y)?;
            let delta = match references.rule {
                UncertaintyRule::Paper => references
                    .w
                    .delta(scaled_residual_sum(&f.residuals, f.height.abs())),
                UncertaintyRule::FitCovariance => references.w.delta_from_fit(
                    1000.0 * f.width,
                    1000.0 * f.width_std,
                    &f.residuals,
                ),
            };
            Ok(Evaluation {
                values: vec![value("w", 1000.0 * f.width, delta * delta)?],
                fit: vec![curve("fit", &t.x, |x| f.value(x))],
                missing: Vec::new(),
            })
        }
        ScanKind::ReloadTime => {
            let t = single_trace(scan)?;
            let f = exponential::fit_exponential(&t.x, &t.y)?;
            let (lo, hi) =
                t.y.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                        (l.min(v), h.max(v))
                    });
            let delta = match references.rule {
                UncertaintyRule::Paper => references
                    .t_sr
                    .delta(scaled_residual_sum(&f.residuals, hi - lo)),
                UncertaintyRule::FitCovariance => {
                    references
                        .t_sr
                        .delta_from_fit(f.tau, f.tau_std, &f.residuals)
                }
            };
            Ok(Evaluation {
                values: vec![value("t_sr", f.tau, delta * delta)?],
                fit: vec![curve("fit", &t.x, |x| f.value(x))],
                missing: Vec::new(),
            })
        }
        ScanKind::SensingDot => {
            let t = single_trace(scan)?;
            let p = peak::fit_highest_peak(&t.x, &t.y)?;
            let n = t.x.len();
            let centre = 0.5 * (t.x[0] + t.x[n - 1]);
            let (slope, slope_var) = peak::local_slope(&t.x, &t.y, centre, 0.3 * p.width);
            let contrast = (slope.abs() / p.max_slope).min(1.0);
            let contrast_var = slope_var / (p.max_slope * p.max_slope);
            Ok(Evaluation {
                values: vec![
                    value("sd_flank_mv", p.flank, p.flank_variance)?,
                    value("sd_contrast", contrast, contrast_var)?,
                ],
                fit: vec![curve("fit", &p.window_x, |x| p.value(x))],
                missing: Vec::new(),
            })
        }
        ScanKind::ChemicalPotential => {
            let mut values = Vec::new();
            let mut fit = Vec::new();
            let mut missing = Vec::new();
            for (name, prefix) in LEAD_LINES {
                let t = line_trace(scan, prefix)?;
                let line = tanh::fit_tanh_step(&t.x, &t.y)
                    .and_then(|f| Ok((value(name, f.center, f.center_std * f.center_std)?, f)));
                match line {
                    Ok((v, f)) => {
                        values.push(v);
                        fit.push(curve(&format!("fit {}", t.label), &t.x, |x| f.value(x)));
                    }
                    Err(e) => missing.push((name.to_string(), e)),
                }
            }
            if values.is_empty() {
                // neither line: the scan failed (the first line's reason)
                let (_, e) = missing.swap_remove(0);
                return Err(e);
            }
            Ok(Evaluation {
                values,
                fit,
                missing,
            })
        }
    }
}

/// The lead transitions of a [`ScanKind::ChemicalPotential`] scan: the value
/// each line gives and the label its trace starts with.
const LEAD_LINES: [(&str, &str); 2] = [("mu_a_mv", "RFA"), ("mu_b_mv", "RFB")];

fn line_trace<'a>(scan: &'a RawScan, prefix: &str) -> Result<&'a Trace, FitError> {
    scan.traces
        .iter()
        .find(|t| t.label.starts_with(prefix))
        .ok_or_else(|| FitError::BadData(format!("no trace labelled {prefix:?}…")))
}

/// The thermal widths of a [`ScanKind::ChemicalPotential`] scan's lead
/// transitions: `(width, standard error)` in mV of the swept RF gate, per
/// line whose tanh fit succeeded with a finite error (none for other
/// scans). A lead transition is broadened by temperature alone, so its
/// width is `2kT/α` (electron temperature over the lever arm): the floor
/// the inter-dot transition width `w` approaches as the tunnel coupling
/// vanishes ([`crate::tuner::thermal_floor`]).
///
/// ```
/// use spintune::fit::lead_widths_mv;
/// use spintune::protocol::{RawScan, ScanKind, Trace};
/// // a noiseless lead transition of width 0.15 mV on a linear background
/// let x: Vec<f64> = (0..201).map(|i| -4.0 + 0.04 * i as f64).collect();
/// let y = x.iter().map(|&x| 0.5 * (1.0 + (x / 0.15).tanh()) + 0.01 * x).collect();
/// let trace = |label: &str| Trace { label: label.into(), x: x.clone(), y: Vec::clone(&y) };
/// let scan = RawScan {
///     kind: ScanKind::ChemicalPotential,
///     x_label: "mV".into(),
///     y_label: "signal".into(),
///     traces: vec![trace("RFA sweep"), trace("RFB sweep")],
/// };
/// let widths = lead_widths_mv(&scan);
/// assert_eq!(widths.len(), 2);
/// assert!((widths[0].0 - 0.15).abs() < 1e-6);
/// ```
pub fn lead_widths_mv(scan: &RawScan) -> Vec<(f64, f64)> {
    if scan.kind != ScanKind::ChemicalPotential {
        return Vec::new();
    }
    LEAD_LINES
        .iter()
        .filter_map(|(_, prefix)| {
            let t = line_trace(scan, prefix).ok()?;
            let f = tanh::fit_tanh_step(&t.x, &t.y).ok()?;
            (f.width.is_finite() && f.width > 0.0 && f.width_std.is_finite())
                .then_some((f.width, f.width_std))
        })
        .collect()
}

fn single_trace(scan: &RawScan) -> Result<&Trace, FitError> {
    match scan.traces.as_slice() {
        [t] => Ok(t),
        ts => Err(FitError::BadData(format!(
            "{:?} scan needs exactly one trace, got {}",
            scan.kind,
            ts.len()
        ))),
    }
}

fn value(name: &str, value: f64, variance: f64) -> Result<ParameterValue, FitError> {
    let v = ParameterValue {
        name: name.into(),
        value,
        variance,
    };
    v.validate().map_err(|e| FitError::BadData(e.to_string()))?;
    Ok(v)
}

fn curve(label: &str, x: &[f64], f: impl Fn(f64) -> f64) -> Trace {
    Trace {
        label: label.into(),
        x: x.to_vec(),
        y: x.iter().map(|&x| f(x)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn evaluate(scan: &RawScan) -> Result<Evaluation, FitError> {
        evaluate_with(scan, &References::default())
    }

    fn scan(kind: ScanKind, x: Vec<f64>, y: Vec<f64>) -> RawScan {
        RawScan {
            kind,
            x_label: String::new(),
            y_label: String::new(),
            traces: vec![Trace {
                label: "t".into(),
                x,
                y,
            }],
        }
    }

    #[test]
    fn flat_or_malformed_data_are_errors() {
        let x: Vec<f64> = (0..100).map(f64::from).collect();
        // Alternating ±1e-3 "noise" with no step.
        let flat: Vec<f64> = (0..100)
            .map(|i| if i % 2 == 0 { 1e-3 } else { -1e-3 })
            .collect();
        for kind in ScanKind::ALL {
            assert!(
                evaluate(&scan(kind, x.clone(), flat.clone())).is_err(),
                "{kind:?}"
            );
        }
        let few = scan(ScanKind::TransitionWidth, vec![0.0, 1.0], vec![0.0, 1.0]);
        assert!(matches!(evaluate(&few), Err(FitError::TooFewPoints { .. })));
        let mut back = x.clone();
        back.reverse();
        let rev = scan(ScanKind::ReloadTime, back, flat.clone());
        assert!(matches!(evaluate(&rev), Err(FitError::BadData(_))));
        let nan = scan(ScanKind::ReloadTime, x.clone(), vec![f64::NAN; 100]);
        assert!(matches!(evaluate(&nan), Err(FitError::BadData(_))));
        let mut two = scan(ScanKind::TransitionWidth, x.clone(), flat);
        two.traces.push(two.traces[0].clone());
        assert!(matches!(evaluate(&two), Err(FitError::BadData(_))));
    }

    #[test]
    fn steps_of_either_sign_and_the_fitted_curves() {
        let x: Vec<f64> = (0..100).map(|i| -2.0 + 4.0 * f64::from(i) / 99.0).collect();
        for sign in [1.0, -1.0] {
            let y: Vec<f64> = x
                .iter()
                .map(|&x| 0.3 + sign * 0.5 * ((x + 0.4) / 0.25).tanh())
                .collect();
            let e = evaluate(&scan(ScanKind::TransitionWidth, x.clone(), y.clone())).unwrap();
            assert!((e.values[0].value - 250.0).abs() < 1e-6);
            let err: f64 = e.fit[0].y.iter().zip(&y).map(|(a, b)| (a - b).abs()).sum();
            assert!(err < 1e-8);
        }
    }

    #[test]
    fn error_messages_are_clear() {
        let e = FitError::TooFewPoints { got: 3, need: 10 };
        assert_eq!(e.to_string(), "too few points: got 3, need at least 10");
        assert!(FitError::NotConverged("LostPatience".into())
            .to_string()
            .contains("did not converge"));
    }
}
