//! The sensing dot's flank as a learned function of the other gates
//! ([`super::FlankPrediction`]): what lets the sensing-dot level skip a sweep.
//!
//! Model: the flank (mV of the swept gate) is `f_ref + g·(v − v_ref)`, where
//! `v` are the other gates' voltages (mV), `(v_ref, f_ref)` the last sweep's
//! and `g` (mV per mV) a [`GateRow`] learned from consecutive sweeps with a
//! zero-mean prior. The prediction's variance is
//! `Δvᵀ C Δv + var(f_ref) + noise²`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::config::FlankPrediction;
use super::gate_row::GateRow;
use super::Consistency;

/// The last sweep the model starts from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct SweepReference {
    /// The other gates' voltages at the sweep, mV (the row's column order).
    voltages_mv: Vec<f64>,
    /// The flank found, mV of the swept gate.
    flank_mv: f64,
    /// Its variance from the fit, mV².
    variance: f64,
}

/// Online model of the flank's position; plain data (part of the tuner's state).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct FlankModel {
    /// Levers of every configured gate but the swept one.
    row: GateRow,
    reference: Option<SweepReference>,
    /// Sweeps skipped since the last one taken.
    pub(super) skips: u32,
    /// The tuner's failed evaluations when the last sweep was taken.
    pub(super) failed_at_sweep: u64,
    /// Every sweep that followed skipped ones, against the flank the model
    /// predicted for it: the parks the level acted on, checked by the next
    /// real sweep.
    #[serde(default)]
    consistency: Consistency,
}

/// A predicted flank, mV of the swept gate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct FlankForecast {
    pub(super) flank_mv: f64,
    pub(super) std_mv: f64,
}

impl FlankModel {
    /// A model over `gates` (the swept gate excluded by the caller) with an
    /// isotropic prior of `prior_lever_per_mv` per gate.
    pub(super) fn new(gates: Vec<String>, p: &FlankPrediction) -> Self {
        Self {
            row: GateRow::new(gates, p.prior_lever_per_mv),
            reference: None,
            skips: 0,
            failed_at_sweep: 0,
            consistency: Consistency::default(),
        }
    }

    /// A sweep found the flank at `flank_mv` ± `variance.sqrt()` with the
    /// other gates at `voltages_mv`: learn the levers from the change since
    /// the last sweep, then start from this one. `noise_mv` is the scatter
    /// between sweeps no gate explains. Non-finite values are ignored.
    pub(super) fn observe(
        &mut self,
        voltages_mv: &BTreeMap<String, f64>,
        flank_mv: f64,
        variance: f64,
        noise_mv: f64,
    ) {
        if !(flank_mv.is_finite() && variance.is_finite() && variance >= 0.0) {
            return;
        }
        if self.skips > 0 {
            if let Some(f) = self.predict(voltages_mv, noise_mv) {
                let sigma = (f.std_mv * f.std_mv + variance).sqrt();
                self.consistency.add(flank_mv - f.flank_mv, sigma);
            }
        }
        if let Some(r) = &self.reference {
            let dv = self.row.delta(&r.voltages_mv, voltages_mv);
            self.row.learn(
                &dv,
                flank_mv - r.flank_mv,
                variance + r.variance + noise_mv * noise_mv,
            );
        }
        self.reference = Some(SweepReference {
            voltages_mv: self.row.inputs(voltages_mv),
            flank_mv,
            variance,
        });
        self.skips = 0;
    }

    /// Skipped sweeps, checked by the sweep that followed them.
    pub(super) fn consistency(&self) -> Consistency {
        self.consistency
    }

    /// The flank predicted at `voltages_mv` if it may replace a sweep
    /// (the one rule of [`FlankPrediction`]): fewer than `max_skips` skips
    /// in a row, σ ≤ `skip_std_mv`, within the swept gate's limits
    /// `limits_mv` and within the sweep's reach (`half_width_mv` of the
    /// gate's present voltage `parked_mv`). Whether an evaluation failed
    /// since the last sweep is the caller's to check.
    pub(super) fn confident(
        &self,
        voltages_mv: &BTreeMap<String, f64>,
        p: &FlankPrediction,
        limits_mv: (f64, f64),
        parked_mv: f64,
        half_width_mv: f64,
    ) -> Option<FlankForecast> {
        if self.skips >= p.max_skips {
            return None;
        }
        let f = self.predict(voltages_mv, p.noise_mv)?;
        (f.std_mv <= p.skip_std_mv
            && (limits_mv.0..=limits_mv.1).contains(&f.flank_mv)
            && (f.flank_mv - parked_mv).abs() <= half_width_mv)
            .then_some(f)
    }

    /// The flank predicted at `voltages_mv` (`None` before the first sweep).
    pub(super) fn predict(
        &self,
        voltages_mv: &BTreeMap<String, f64>,
        noise_mv: f64,
    ) -> Option<FlankForecast> {
        let r = self.reference.as_ref()?;
        let (dz, var_g) = self
            .row
            .predict(&self.row.delta(&r.voltages_mv, voltages_mv));
        let mean = r.flank_mv + dz;
        let var = var_g + r.variance + noise_mv * noise_mv;
        (mean.is_finite() && var.is_finite()).then(|| FlankForecast {
            flank_mv: mean,
            std_mv: var.max(0.0).sqrt(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(g, v)| (g.to_string(), *v)).collect()
    }

    #[test]
    fn no_prediction_before_the_first_sweep() {
        let m = FlankModel::new(vec!["A".into()], &FlankPrediction::default());
        assert!(m.predict(&at(&[("A", 0.0)]), 0.05).is_none());
    }

    #[test]
    fn without_moves_the_prediction_is_the_last_sweep_with_its_noise() {
        let mut m = FlankModel::new(vec!["A".into(), "B".into()], &FlankPrediction::default());
        m.observe(
            &at(&[("A", 1.0), ("B", 2.0)]),
            -600.0,
            0.03f64.powi(2),
            0.04,
        );
        let f = m.predict(&at(&[("A", 1.0), ("B", 2.0)]), 0.04).unwrap();
        assert_eq!(f.flank_mv, -600.0);
        // independent: √(0.03² + 0.04²) = 0.05
        assert!((f.std_mv - 0.05).abs() < 1e-12);
    }

    #[test]
    fn a_move_before_learning_costs_the_prior_lever_times_the_step() {
        let p = FlankPrediction::default(); // prior 0.1 mV/mV
        let mut m = FlankModel::new(vec!["A".into(), "B".into()], &p);
        m.observe(&at(&[("A", 0.0), ("B", 0.0)]), 0.0, 0.0, 0.0);
        // 3 mV on A and 4 mV on B: σ = 0.1 · 5 = 0.5 mV
        let f = m.predict(&at(&[("A", 3.0), ("B", 4.0)]), 0.0).unwrap();
        assert_eq!(f.flank_mv, 0.0);
        assert!((f.std_mv - 0.5).abs() < 1e-12);
    }

    #[test]
    fn learned_levers_predict_the_next_sweep() {
        // true levers 0.05 and −0.08 mV/mV; noise-free sweeps after moves
        // along both gates determine them exactly
        let lever = |a: f64, b: f64| 0.05 * a - 0.08 * b;
        let mut m = FlankModel::new(vec!["A".into(), "B".into()], &FlankPrediction::default());
        for (a, b) in [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)] {
            m.observe(&at(&[("A", a), ("B", b)]), lever(a, b), 1e-12, 0.0);
        }
        let f = m.predict(&at(&[("A", -5.0), ("B", 20.0)]), 0.0).unwrap();
        assert!((f.flank_mv - lever(-5.0, 20.0)).abs() < 1e-4, "{f:?}");
        assert!(f.std_mv < 1e-3, "{f:?}");
    }
}
