//! Derivation of the reference constants `σ₀`, `δp₀` of the paper's
//! uncertainty rule from repeated simulated scans.

use super::{DeviceConfig, SimulatedDevice};
use crate::config_error::ConfigError;
use crate::fit::tanh::fit_tanh_step;
use crate::fit::uncertainty::{
    correlation_inflation, scaled_residual_sum, Reference, References, UncertaintyRule,
};
use crate::fit::{exponential::fit_exponential, FitError};
use crate::protocol::{Request, Response, ScanKind, ScanOutcome, ScanRequest};
use crate::safety::GateSpec;

/// Why [`calibrate_reference`] could not derive the references.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// The device config or the gates are invalid (see
    /// [`SimulatedDevice::new`] for the field paths).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// Fewer than 10 scans of each kind were asked for.
    #[error("need at least 10 scans, got {0}")]
    TooFewScans(usize),
    /// The simulated device did not return a raw scan.
    #[error("{kind:?} scan failed: {reason}")]
    ScanFailed {
        /// The scan.
        kind: ScanKind,
        /// What the device answered instead.
        reason: String,
    },
    /// Fewer than half of the fits of either kind succeeded.
    #[error("too many failed fits: w {w}/{scans}, t_sr {t_sr}/{scans}")]
    TooManyFailedFits {
        /// Successful `w` fits.
        w: usize,
        /// Successful `t_sr` fits.
        t_sr: usize,
        /// Scans of each kind.
        scans: usize,
    },
}

/// Mean and (sample) standard deviation.
fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

/// The paper's calibration: at the start voltages, measure `w` and `t_sr`
/// `scans` times each (alternating, as a tuner would), fit each scan, and
/// take `σ₀` = mean scaled residual sum and `δp₀` = standard deviation of
/// the fitted values (µV for `w`, ns for `t_sr`), and the relative floor
/// `r = √max(0, δp₀² − mean((κ·s_p)²)) / mean(p)` of
/// [`crate::fit::uncertainty::UncertaintyRule::FitCovariance`] (the scatter the
/// fits' own errors do not explain). Failed fits are skipped;
/// Charge jumps and the slow drift of t_c and Γ are switched off for the
/// reference series. `Err` if fewer
/// than half of either kind succeed or `scans < 10`.
///
/// ```
/// use spintune::sim::{calibrate_reference, default_gates, DeviceConfig};
/// let r = calibrate_reference(&DeviceConfig::default(), &default_gates(), 1, 20).unwrap();
/// assert!(r.w.delta_p0 > 0.0 && r.t_sr.sigma0 > 0.0);
/// ```
pub fn calibrate_reference(
    config: &DeviceConfig,
    gates: &[GateSpec],
    seed: u64,
    scans: usize,
) -> Result<References, CalibrationError> {
    if scans < 10 {
        return Err(CalibrationError::TooFewScans(scans));
    }
    // The reference set is taken on a quiet, well-tuned device: no charge
    // jumps (they would knock the sensing dot off its flank for the rest of
    // the series, which nobody would accept as a reference).
    let mut quiet = config.clone();
    quiet.noise.charge_jump_rate_per_s = 0.0;
    // nor the slow drift of t_c and Γ: a reference is one scan's scatter
    // at a fixed device state, not the device's drift over the series
    quiet.noise.slow = super::config::SlowDrift::none();
    let mut device = SimulatedDevice::new(quiet, gates, seed)?;
    let (mut w, mut w_sigma, mut t, mut t_sigma) = (vec![], vec![], vec![], vec![]);
    // (κ·s_p)² of each fit: the part of the scatter a single scan shows
    let (mut w_fit_var, mut t_fit_var) = (vec![], vec![]);
    for _ in 0..scans {
        for kind in [ScanKind::TransitionWidth, ScanKind::ReloadTime] {
            let request = Request::Measure {
                scan: ScanRequest {
                    kind,
                    sweep: None,
                    cell: None,
                },
            };
            let scan = match device.execute(&request) {
                Response::Scanned {
                    outcome: ScanOutcome::Raw { scan },
                    ..
                } => scan,
                other => {
                    let reason = match other {
                        Response::Error { message, .. } => message,
                        Response::Scanned {
                            outcome: ScanOutcome::Failed { reason },
                            ..
                        } => reason,
                        _ => "the device answered without a raw scan".into(),
                    };
                    return Err(CalibrationError::ScanFailed { kind, reason });
                }
            };
            let trace = &scan.traces[0];
            let fitted: Result<(), FitError> = match kind {
                ScanKind::TransitionWidth => fit_tanh_step(&trace.x, &trace.y).map(|f| {
                    w.push(1000.0 * f.width);
                    w_fit_var
                        .push((1000.0 * f.width_std * correlation_inflation(&f.residuals)).powi(2));
                    w_sigma.push(scaled_residual_sum(&f.residuals, f.height.abs()));
                }),
                _ => fit_exponential(&trace.x, &trace.y).map(|f| {
                    let (lo, hi) = trace
                        .y
                        .iter()
                        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                            (l.min(v), h.max(v))
                        });
                    t.push(f.tau);
                    t_fit_var.push((f.tau_std * correlation_inflation(&f.residuals)).powi(2));
                    t_sigma.push(scaled_residual_sum(&f.residuals, hi - lo));
                }),
            };
            // A failed fit is simply not part of the reference set.
            let _ = fitted;
        }
    }
    if 2 * w.len() < scans || 2 * t.len() < scans {
        return Err(CalibrationError::TooManyFailedFits {
            w: w.len(),
            t_sr: t.len(),
            scans,
        });
    }
    let reference = |values: &[f64], sigmas: &[f64], fit_var: &[f64]| {
        let (mean, sd) = mean_std(values);
        // What the fits' own errors do not explain, relative to the value.
        let unexplained = sd * sd - mean_std(fit_var).0;
        Reference {
            sigma0: mean_std(sigmas).0,
            delta_p0: sd,
            relative_floor: unexplained.max(0.0).sqrt() / mean.abs(),
        }
    };
    Ok(References {
        w: reference(&w, &w_sigma, &w_fit_var),
        t_sr: reference(&t, &t_sigma, &t_fit_var),
        rule: UncertaintyRule::FitCovariance,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::default_gates;

    #[test]
    fn errors_name_the_problem() {
        let gates = default_gates();
        assert_eq!(
            calibrate_reference(&DeviceConfig::default(), &gates, 1, 3),
            Err(CalibrationError::TooFewScans(3))
        );
        let mut bad = DeviceConfig::default();
        bad.scans.load_points = 3;
        match calibrate_reference(&bad, &gates, 1, 10) {
            Err(CalibrationError::Config(e)) => assert_eq!(e.field, "scans.load_points"),
            other => panic!("{other:?}"),
        }
        let e = CalibrationError::TooManyFailedFits {
            w: 2,
            t_sr: 9,
            scans: 10,
        };
        assert_eq!(e.to_string(), "too many failed fits: w 2/10, t_sr 9/10");
    }
}
