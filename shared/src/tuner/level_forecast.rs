//! A child level's parameters as a learned function of every gate
//! ([`super::ParameterForecast`]): what lets the chemical-potential level
//! correct the transition lines after a parent's move without scanning.
//!
//! Model, per parameter (estimator space):
//! `y = y_ref + g_own·(v_own − v_own,ref) + g_other·(v_other − v_other,ref)`.
//! `g_own` is the level's own Jacobian (its estimator, which the level keeps
//! learning from its own steps); `g_other` is a [`GateRow`] over every gate
//! outside the level (the parents' gates and the sensor's), learned from
//! consecutive scans. Its prior is centred where a parent's virtual-gate
//! compensation says it is: the compensation moves this level's gates by
//! `M·Δv_parent` so that the parameters stay put, i.e. `g_other ≈ −g_own·M`
//! on the parent's gates (0 elsewhere), with `prior_lever_per_mv` of spread
//! for what the matrix gets wrong. `(v_ref, y_ref)` is the level's last scan. The
//! prediction's variance is
//! `var(y_ref) + Δv_ownᵀ C_own Δv_own + Δv_otherᵀ C_other Δv_other + noise²`.

use std::collections::BTreeMap;

use nalgebra::DVector;
use serde::{Deserialize, Serialize};

use super::config::LevelKind;
use super::finite_difference::Sample;
use super::gate_row::GateRow;
use super::{Consistency, GradientRow, LevelState, ParameterForecast, Tuner};
use crate::protocol::EventKind;

/// The last scan the model starts from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ScanReference {
    /// The level's own gates, mV (level order).
    own_mv: Vec<f64>,
    /// Every other gate, mV (the rows' column order).
    other_mv: Vec<f64>,
    /// Estimator-space value and variance per parameter (`None`: not measured).
    samples: Vec<Option<Sample>>,
}

/// Online model of a child level's parameters; plain data (tuner state).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct LevelForecast {
    /// One row per parameter (config order) over the gates outside the level.
    rows: Vec<GateRow>,
    reference: Option<ScanReference>,
    /// Calls corrected from the forecast since the last scan.
    pub(super) skips: u32,
    /// The tuner's failed evaluations when the level last scanned.
    failed_at_scan: u64,
    /// The tuner's lab time at the level's last scan, s.
    scanned_at_s: f64,
    /// Every scan that followed forecast calls, against what the model
    /// predicted for it (per parameter, config order): the forecasts the
    /// level acted on, checked by the next real scan.
    #[serde(default)]
    consistency: Vec<Consistency>,
    /// Per parent gate compensated onto this level's gates: that gate and
    /// this level's gate moves per mV of it (own-gate order).
    compensation: Vec<(String, Vec<f64>)>,
    /// Prior spread of the rows, per mV (kept to centre them).
    prior_per_mv: f64,
    /// Whether the rows' priors were centred on the compensation (done at
    /// the first scan with a known own Jacobian).
    centred: bool,
}

/// The columns of a virtual-gate matrix that move `onto` (a lower level's
/// gates): per compensated gate (`gates[j]`, e.g. a qubit gate), that gate
/// and the moves of `onto` (mV, in their order) per mV of it; `rows` are
/// the matrix's gates (e.g. the plungers), `matrix[r][j]` mV per mV. Gates
/// whose column leaves `onto` alone are left out.
pub(crate) fn compensation_columns(
    gates: &[String],
    rows: &[String],
    matrix: &[Vec<f64>],
    onto: &[String],
) -> Vec<(String, Vec<f64>)> {
    gates
        .iter()
        .enumerate()
        .filter_map(|(j, gate)| {
            let column: Vec<f64> = onto
                .iter()
                .map(|g| {
                    rows.iter()
                        .position(|r| r == g)
                        .and_then(|r| matrix.get(r)?.get(j).copied())
                        .unwrap_or(0.0)
                })
                .collect();
            column
                .iter()
                .any(|x| *x != 0.0)
                .then(|| (gate.clone(), column))
        })
        .collect()
}

/// `(g·Δv, Δvᵀ C Δv)` of one own-gate row (no covariance: exact).
fn own_shift(row: &GradientRow, dv: &DVector<f64>) -> (f64, f64) {
    let mean = row.0.dot(dv);
    let var = row.1.as_ref().map_or(0.0, |c| (c * dv).dot(dv));
    (mean, var.max(0.0))
}

impl LevelForecast {
    /// A model of `parameters` parameters over `other_gates` with a prior
    /// lever of `prior_per_mv` (estimator units per mV) per gate, centred on
    /// `compensation` (see the module docs).
    pub(crate) fn new(
        other_gates: Vec<String>,
        parameters: usize,
        prior_per_mv: f64,
        compensation: Vec<(String, Vec<f64>)>,
    ) -> Self {
        Self {
            compensation,
            prior_per_mv,
            centred: false,
            rows: (0..parameters)
                .map(|_| GateRow::new(other_gates.clone(), prior_per_mv))
                .collect(),
            reference: None,
            skips: 0,
            failed_at_scan: 0,
            scanned_at_s: 0.0,
            consistency: vec![Consistency::default(); parameters],
        }
    }

    fn other_inputs(&self, voltages_mv: &BTreeMap<String, f64>) -> Vec<f64> {
        self.rows
            .first()
            .map_or_else(Vec::new, |r| r.inputs(voltages_mv))
    }

    /// The level scanned: `samples` (estimator space, parameter order) with
    /// its own gates at `own_mv` and every gate at `voltages_mv`. Learn the
    /// other gates' levers from what the own Jacobian `own_rows` does not
    /// explain since the last scan, then start from this one. `noise` is the
    /// scatter between scans no gate explains (estimator units).
    pub(crate) fn observe(
        &mut self,
        own_mv: &[f64],
        voltages_mv: &BTreeMap<String, f64>,
        samples: &[Option<Sample>],
        own_rows: &[GradientRow],
        noise: f64,
    ) {
        if !self.centred && self.reference.is_none() && own_rows.len() == self.rows.len() {
            self.centre(own_rows);
        }
        if self.skips > 0 {
            if let Some(predicted) = self.predict(own_mv, voltages_mv, own_rows, noise) {
                for ((c, p), s) in self.consistency.iter_mut().zip(&predicted).zip(samples) {
                    if let (Some((mean, var)), Some((y, var_y))) = (p, s) {
                        c.add(y - mean, (var + var_y).sqrt());
                    }
                }
            }
        }
        if let Some(r) = &self.reference {
            let d_own = DVector::from_iterator(
                own_mv.len(),
                own_mv.iter().zip(&r.own_mv).map(|(a, b)| a - b),
            );
            for (i, row) in self.rows.iter_mut().enumerate() {
                let (Some((y, var)), Some(Some((y0, var0))), Some(g)) = (
                    samples.get(i).copied().flatten(),
                    r.samples.get(i),
                    own_rows.get(i),
                ) else {
                    continue;
                };
                let (own, own_var) = own_shift(g, &d_own);
                let d_other = row.delta(&r.other_mv, voltages_mv);
                row.learn(&d_other, y - y0 - own, var + var0 + own_var + noise * noise);
            }
        }
        self.reference = Some(ScanReference {
            own_mv: own_mv.to_vec(),
            other_mv: self.other_inputs(voltages_mv),
            samples: samples.to_vec(),
        });
        self.skips = 0;
    }

    /// The level scanned at `lab_seconds` (s) with `failed_evaluations`
    /// counted so far: where [`Self::may_forecast`] measures age and failures from.
    pub(crate) fn scanned(&mut self, failed_evaluations: u64, lab_seconds: f64) {
        self.failed_at_scan = failed_evaluations;
        self.scanned_at_s = lab_seconds;
    }

    /// Whether a call may act on the forecast instead of scanning, before
    /// its spread is looked at (the one rule of [`ParameterForecast`], with
    /// [`ParameterForecast::confident`]): fewer than `max_skips` forecast
    /// calls in a row, no failed evaluation since the last scan
    /// (`failed_evaluations`: the count now, as passed to [`Self::scanned`]),
    /// and that scan at most `max_age_s` old at `lab_seconds` (s).
    pub(crate) fn may_forecast(
        &self,
        f: &ParameterForecast,
        failed_evaluations: u64,
        lab_seconds: f64,
    ) -> bool {
        self.skips < f.max_skips
            && self.failed_at_scan == failed_evaluations
            && lab_seconds - self.scanned_at_s <= f.max_age_s
    }

    /// Centre every row's prior on `−g_own·M` (before any learning).
    fn centre(&mut self, own_rows: &[GradientRow]) {
        for (row, own) in self.rows.iter_mut().zip(own_rows) {
            let gates = row.gates().to_vec();
            let mean = DVector::from_iterator(
                gates.len(),
                gates.iter().map(|g| {
                    self.compensation
                        .iter()
                        .find(|(c, _)| c == g)
                        .map_or(0.0, |(_, m)| {
                            -own.0.iter().zip(m).map(|(a, b)| a * b).sum::<f64>()
                        })
                }),
            );
            *row = GateRow::centred(gates, mean, self.prior_per_mv);
        }
        self.centred = true;
    }

    /// Forecasts acted on, checked by the scan that followed them
    /// (normalised innovations per parameter, config order).
    pub(super) fn consistency(&self) -> &[Consistency] {
        &self.consistency
    }

    /// Every parameter predicted at `own_mv` / `voltages_mv` (estimator
    /// space, value and variance); `None` per parameter the last scan did
    /// not measure, and `None` before the first scan.
    pub(crate) fn predict(
        &self,
        own_mv: &[f64],
        voltages_mv: &BTreeMap<String, f64>,
        own_rows: &[GradientRow],
        noise: f64,
    ) -> Option<Vec<Option<Sample>>> {
        let r = self.reference.as_ref()?;
        let d_own = DVector::from_iterator(
            own_mv.len(),
            own_mv.iter().zip(&r.own_mv).map(|(a, b)| a - b),
        );
        Some(
            self.rows
                .iter()
                .enumerate()
                .map(|(i, row)| {
                    let (y0, var0) = r.samples.get(i).copied().flatten()?;
                    let (own, own_var) = own_shift(own_rows.get(i)?, &d_own);
                    let (other, other_var) = row.predict(&row.delta(&r.other_mv, voltages_mv));
                    let mean = y0 + own + other;
                    let var = var0 + own_var + other_var + noise * noise;
                    (mean.is_finite() && var.is_finite()).then_some((mean, var))
                })
                .collect(),
        )
    }
}

impl Tuner {
    /// Child level `level`'s forecast if it may replace the call's scan
    /// ([`super::ParameterForecast`]): every targeted parameter predicted within
    /// `skip_std`, fewer than `max_skips` forecast calls in a row, no
    /// failed evaluation since the level last scanned, and that scan at
    /// most `max_age_s` of lab time ago.
    pub(super) fn confident_forecast(&self, level: usize) -> Option<Vec<Option<Sample>>> {
        if level == 0 {
            return None;
        }
        let LevelKind::Newton(cfg) = &self.config.levels[level].kind else {
            return None;
        };
        let f = cfg.forecast.as_ref()?;
        let LevelState::Newton(state) = &self.levels[level] else {
            return None;
        };
        let model = state.forecast.as_ref()?;
        if !model.may_forecast(f, self.failed_evaluations, self.lab_seconds) {
            return None;
        }
        let own_rows = state.gradients()?;
        let own_mv = self.level_voltages(level);
        let forecast = model.predict(&own_mv, &self.voltages_mv, &own_rows, f.noise)?;
        for (p, s) in cfg.parameters.iter().zip(&forecast) {
            if p.target.is_some() && !f.confident(*s) {
                return None;
            }
        }
        Some(forecast)
    }

    /// [`super::Decision::Forecast`]: take the forecast as the round's
    /// values and step on it (no step if every target is inside its band);
    /// the call then ends without a confirming scan. Without a confident
    /// forecast (it cannot have changed since the call began, but the
    /// machine does not rely on that) the level scans as usual.
    pub(super) fn correct_from_forecast(&mut self, level: usize) {
        let Some(forecast) = self.confident_forecast(level) else {
            let ops = self.round_ops(level);
            self.push_ops(ops);
            return;
        };
        let LevelKind::Newton(cfg) = &self.config.levels[level].kind else {
            return;
        };
        let mut events = Vec::new();
        let mut in_band = true;
        for (p, s) in cfg.parameters.iter().zip(&forecast) {
            let Some((y, var)) = *s else { continue };
            let (value, value_var) = p.transform.inverse(y, var);
            if let Some(t) = p.target {
                in_band &= (value - t).abs() <= p.tolerance.half_width(t);
            }
            events.push(EventKind::MeasurementSkipped {
                parameter: p.name.clone(),
                predicted: value,
                std: value_var.sqrt(),
                unit: p.unit.clone(),
            });
        }
        let level_mv = self.level_voltages(level);
        let all_mv = self.voltages_mv.clone();
        let LevelState::Newton(state) = &mut self.levels[level] else {
            return;
        };
        state.events.extend(events);
        if let Some(model) = &mut state.forecast {
            model.skips += 1;
        }
        state.set_forecast_snapshot(all_mv, level_mv, forecast, in_band);
        if !in_band {
            self.step(level);
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::DMatrix;

    use super::*;

    fn at(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(g, v)| (g.to_string(), *v)).collect()
    }

    /// One parameter over own gate P (exact lever 0.9) and other gate Q.
    fn own() -> Vec<GradientRow> {
        vec![(DVector::from_vec(vec![0.9]), Some(DMatrix::zeros(1, 1)))]
    }

    #[test]
    fn no_forecast_before_the_first_scan() {
        let m = LevelForecast::new(vec!["Q".into()], 1, 0.1, Vec::new());
        assert!(m.predict(&[0.0], &at(&[("Q", 0.0)]), &own(), 0.0).is_none());
    }

    #[test]
    fn own_moves_follow_the_level_jacobian_and_other_moves_the_prior() {
        let mut m = LevelForecast::new(vec!["Q".into()], 1, 0.1, Vec::new());
        m.observe(&[0.0], &at(&[("Q", 0.0)]), &[Some((1.0, 0.0))], &own(), 0.0);
        // own gate +2 mV: 1 + 0.9·2 = 2.8, exactly; other gate +5 mV: ±0.1·5
        let f = m.predict(&[2.0], &at(&[("Q", 5.0)]), &own(), 0.0).unwrap();
        let (mean, var) = f[0].unwrap();
        assert!((mean - 2.8).abs() < 1e-12);
        assert!((var.sqrt() - 0.5).abs() < 1e-12);
    }

    #[test]
    fn the_other_gates_lever_is_learned_from_what_the_own_jacobian_leaves() {
        // truth: y = 0.9·P + 0.2·Q; scans after moving both
        let truth = |p: f64, q: f64| 0.9 * p + 0.2 * q;
        let mut m = LevelForecast::new(vec!["Q".into()], 1, 0.1, Vec::new());
        for (p, q) in [(0.0, 0.0), (1.0, 10.0), (-2.0, 20.0)] {
            let y = truth(p, q);
            m.observe(&[p], &at(&[("Q", q)]), &[Some((y, 1e-12))], &own(), 0.0);
        }
        let f = m.predict(&[3.0], &at(&[("Q", 30.0)]), &own(), 0.0).unwrap();
        let (mean, var) = f[0].unwrap();
        assert!((mean - truth(3.0, 30.0)).abs() < 1e-3, "{mean}");
        assert!(var.sqrt() < 1e-2, "{var}");
    }
}
