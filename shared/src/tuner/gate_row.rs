//! A scalar's linear response to a set of gates, learned online: the one
//! model behind both predictions that let a lower level skip a scan (the
//! sensing dot's flank, [`super::flank`], and a child level's parameters,
//! [`super::level_forecast`]).
//!
//! Model: `Δz = g·Δv + ε`, with `Δv` the gates' moves (mV), `g` (unit per
//! mV) a [`KalmanGradient`] row with a zero-mean isotropic prior, learned
//! from consecutive observations. The row never sees a scalar's absolute
//! value: its callers keep their own reference point.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::kalman::{KalmanGradient, ProcessNoise};

/// One learned row over `gates`; plain data (part of the tuner's state).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct GateRow {
    /// Input gates, in column order.
    gates: Vec<String>,
    filter: KalmanGradient,
}

impl GateRow {
    /// A row over `gates` with prior `g ~ N(0, prior_per_mv² · I)`
    /// (`prior_per_mv` > 0, finite: validated by the configs).
    pub(super) fn new(gates: Vec<String>, prior_per_mv: f64) -> Self {
        let n = gates.len();
        Self::centred(gates, DVector::zeros(n), prior_per_mv)
    }

    /// A row over `gates` with prior `g ~ N(mean, prior_per_mv² · I)`
    /// (`mean`: one value per gate; non-finite entries count as 0).
    pub(super) fn centred(gates: Vec<String>, mean: DVector<f64>, prior_per_mv: f64) -> Self {
        let n = gates.len();
        let mean = DVector::from_iterator(
            n,
            (0..n).map(|i| {
                mean.get(i)
                    .copied()
                    .filter(|x| x.is_finite())
                    .unwrap_or(0.0)
            }),
        );
        let filter = KalmanGradient::new(
            mean,
            DMatrix::identity(n, n) * prior_per_mv.powi(2),
            ProcessNoise::isotropic(n, 0.0),
        )
        .expect("a finite prior with a positive variance is a valid filter");
        Self { gates, filter }
    }

    /// The input gates, in column order.
    pub(super) fn gates(&self) -> &[String] {
        &self.gates
    }

    /// The input gates' voltages (mV, column order); a gate missing from
    /// `voltages_mv` counts as 0 mV.
    pub(super) fn inputs(&self, voltages_mv: &BTreeMap<String, f64>) -> Vec<f64> {
        self.gates
            .iter()
            .map(|g| voltages_mv.get(g).copied().unwrap_or(0.0))
            .collect()
    }

    /// The move from `from` (inputs, as [`GateRow::inputs`]) to `voltages_mv`, mV.
    pub(super) fn delta(&self, from: &[f64], voltages_mv: &BTreeMap<String, f64>) -> DVector<f64> {
        let to = self.inputs(voltages_mv);
        DVector::from_iterator(to.len(), to.iter().zip(from).map(|(a, b)| a - b))
    }

    /// Learn from a change `dz` after the move `dv` with total variance
    /// `var` (both observations' and the unexplained scatter's). A failed
    /// update leaves the row as it was: it then only predicts less well,
    /// never something invalid.
    pub(super) fn learn(&mut self, dv: &DVector<f64>, dz: f64, var: f64) {
        if dz.is_finite() && var.is_finite() && var >= 0.0 {
            let _ = self.filter.update(dv, dz, var);
        }
    }

    /// The predicted change after the move `dv` and its variance from the
    /// row's uncertainty, `(g·Δv, Δvᵀ C Δv)`.
    pub(super) fn predict(&self, dv: &DVector<f64>) -> (f64, f64) {
        let mean = dv.dot(self.filter.gradient());
        let var = (self.filter.covariance() * dv).dot(dv);
        (mean, var.max(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(g, v)| (g.to_string(), *v)).collect()
    }

    #[test]
    fn before_learning_the_spread_is_the_prior_times_the_move() {
        let row = GateRow::new(vec!["A".into(), "B".into()], 0.1);
        let dv = row.delta(&[0.0, 0.0], &at(&[("A", 3.0), ("B", 4.0)]));
        let (mean, var) = row.predict(&dv);
        assert_eq!(mean, 0.0);
        // σ = 0.1 mV/mV · |(3, 4)| mV = 0.5
        assert!((var.sqrt() - 0.5).abs() < 1e-12);
    }

    #[test]
    fn noise_free_moves_along_each_gate_determine_the_row() {
        let mut row = GateRow::new(vec!["A".into(), "B".into()], 0.1);
        // true levers 0.05 and −0.08 per mV
        row.learn(&DVector::from_vec(vec![10.0, 0.0]), 0.5, 1e-12);
        row.learn(&DVector::from_vec(vec![0.0, 10.0]), -0.8, 1e-12);
        let (mean, var) = row.predict(&DVector::from_vec(vec![-5.0, 20.0]));
        assert!((mean - (-0.25 - 1.6)).abs() < 1e-4, "{mean}");
        assert!(var.sqrt() < 1e-3, "{var}");
    }

    #[test]
    fn non_finite_observations_teach_nothing() {
        let mut row = GateRow::new(vec!["A".into()], 0.1);
        let before = row.clone();
        row.learn(&DVector::from_vec(vec![1.0]), f64::NAN, 0.01);
        row.learn(&DVector::from_vec(vec![1.0]), 0.1, f64::INFINITY);
        assert_eq!(row, before);
    }
}
