//! Derivation of the reference constants `σ₀`, `δp₀` of the paper's
//! uncertainty rule from repeated simulated scans.

use super::{DeviceConfig, SimulatedDevice};
use crate::fit::tanh::fit_tanh_step;
use crate::fit::uncertainty::{scaled_residual_sum, Reference, References};
use crate::fit::{exponential::fit_exponential, FitError};
use crate::protocol::{Request, Response, ScanKind, ScanOutcome, ScanRequest};
use crate::safety::GateSpec;

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
/// the fitted values (µV for `w`, ns for `t_sr`). Failed fits are skipped;
/// Charge jumps are switched off for the reference series. `Err` if fewer
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
) -> Result<References, String> {
    if scans < 10 {
        return Err(format!("need at least 10 scans, got {scans}"));
    }
    // The reference set is taken on a quiet, well-tuned device: no charge
    // jumps (they would knock the sensing dot off its flank for the rest of
    // the series, which nobody would accept as a reference).
    let mut quiet = config.clone();
    quiet.noise.charge_jump_rate_per_s = 0.0;
    let mut device = SimulatedDevice::new(quiet, gates, seed)?;
    let (mut w, mut w_sigma, mut t, mut t_sigma) = (vec![], vec![], vec![], vec![]);
    for _ in 0..scans {
        for kind in [ScanKind::TransitionWidth, ScanKind::ReloadTime] {
            let request = Request::Measure {
                scan: ScanRequest { kind, sweep: None },
            };
            let Response::Scanned {
                outcome: ScanOutcome::Raw { scan },
                ..
            } = device.execute(&request)
            else {
                return Err(format!("{kind:?} scan failed"));
            };
            let trace = &scan.traces[0];
            let fitted: Result<(), FitError> = match kind {
                ScanKind::TransitionWidth => fit_tanh_step(&trace.x, &trace.y).map(|f| {
                    w.push(1000.0 * f.width);
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
                    t_sigma.push(scaled_residual_sum(&f.residuals, hi - lo));
                }),
            };
            // A failed fit is simply not part of the reference set.
            let _ = fitted;
        }
    }
    if 2 * w.len() < scans || 2 * t.len() < scans {
        return Err(format!(
            "too many failed fits: w {}/{scans}, t_sr {}/{scans}",
            w.len(),
            t.len()
        ));
    }
    let reference = |values: &[f64], sigmas: &[f64]| Reference {
        sigma0: mean_std(sigmas).0,
        delta_p0: mean_std(values).1,
    };
    Ok(References {
        w: reference(&w, &w_sigma),
        t_sr: reference(&t, &t_sigma),
    })
}
