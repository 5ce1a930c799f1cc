//! Finite-difference gradient measurement with repetitions (paper supplement,
//! "Initial conditions"): `g(0)` is the mean of the repeated one-sided
//! estimates, `C(0)` diagonal with their sample variances.
//!
//! Values are in estimator space (after the parameter's transform); voltages in mV.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// A measured value and its variance.
pub type Sample = (f64, f64);

/// One offset point: the actual offset of the gate (mV) and a sample per parameter.
type Point = (f64, Vec<Option<Sample>>);

/// Accumulates base and offset measurements over repetitions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FiniteDifference {
    /// Number of parameters (rows).
    params: usize,
    /// Number of gates (columns).
    gates: usize,
    /// Base voltages over the level's gates, mV.
    pub base_mv: Vec<f64>,
    /// Offset per gate, mV.
    pub step_mv: f64,
    /// `base[rep][param]`.
    base: Vec<Vec<Option<Sample>>>,
    /// `points[rep][gate][param]` with the actual voltage offset (mV) of that gate.
    points: Vec<Vec<Option<Point>>>,
}

impl FiniteDifference {
    /// Start a measurement around `base_mv` with `repetitions` repetitions.
    pub fn new(params: usize, base_mv: Vec<f64>, step_mv: f64, repetitions: usize) -> Self {
        let gates = base_mv.len();
        Self {
            params,
            gates,
            base_mv,
            step_mv,
            base: vec![vec![None; params]; repetitions],
            points: vec![vec![None; gates]; repetitions],
        }
    }

    /// Number of repetitions.
    pub fn repetitions(&self) -> usize {
        self.base.len()
    }

    /// Record the base measurement of repetition `rep`.
    pub fn record_base(&mut self, rep: usize, samples: Vec<Option<Sample>>) {
        self.base[rep] = samples;
    }

    /// Record the measurement with gate `gate` offset by `actual_offset_mv`.
    pub fn record_point(
        &mut self,
        rep: usize,
        gate: usize,
        actual_offset_mv: f64,
        samples: Vec<Option<Sample>>,
    ) {
        self.points[rep][gate] = Some((actual_offset_mv, samples));
    }

    /// Gradient rows and diagonal covariances; `None` for a parameter with a
    /// gate that has no usable estimate at all.
    pub fn result(&self) -> Vec<Option<(DVector<f64>, DMatrix<f64>)>> {
        (0..self.params)
            .map(|i| {
                let mut g = DVector::zeros(self.gates);
                let mut var = DVector::zeros(self.gates);
                for j in 0..self.gates {
                    let mut estimates = Vec::new();
                    let mut propagated = Vec::new();
                    for rep in 0..self.repetitions() {
                        let (Some((y0, v0)), Some((dv, samples))) =
                            (self.base[rep][i], &self.points[rep][j])
                        else {
                            continue;
                        };
                        let Some((y1, v1)) = samples[i] else { continue };
                        if dv.abs() < 1e-12 {
                            continue;
                        }
                        estimates.push((y1 - y0) / dv);
                        propagated.push((v0 + v1) / (dv * dv));
                    }
                    if estimates.is_empty() {
                        return None;
                    }
                    let n = estimates.len() as f64;
                    let mean = estimates.iter().sum::<f64>() / n;
                    let variance = if estimates.len() >= 2 {
                        estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1.0)
                    } else {
                        propagated[0]
                    };
                    g[j] = mean;
                    var[j] = variance;
                }
                Some((g, DMatrix::from_diagonal(&var)))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_sample_variance() {
        let mut fd = FiniteDifference::new(1, vec![0.0, 0.0], 1.0, 2);
        // rep 0: base 0, gate0 +1 → 2.0, gate1 +1 → -1.0
        fd.record_base(0, vec![Some((0.0, 0.0))]);
        fd.record_point(0, 0, 1.0, vec![Some((2.0, 0.0))]);
        fd.record_point(0, 1, 1.0, vec![Some((-1.0, 0.0))]);
        // rep 1: base 1, gate0 → 5 (slope 4), gate1 → 0 (slope -1)
        fd.record_base(1, vec![Some((1.0, 0.0))]);
        fd.record_point(1, 0, 1.0, vec![Some((5.0, 0.0))]);
        fd.record_point(1, 1, 1.0, vec![Some((0.0, 0.0))]);
        let (g, c) = fd.result()[0].clone().unwrap();
        assert_eq!(g.as_slice(), &[3.0, -1.0]);
        assert_eq!(c[(0, 0)], 2.0);
        assert_eq!(c[(1, 1)], 0.0);
        assert_eq!(c[(0, 1)], 0.0);
    }

    #[test]
    fn single_repetition_propagates_measurement_error() {
        let mut fd = FiniteDifference::new(1, vec![0.0], 2.0, 1);
        fd.record_base(0, vec![Some((0.0, 1.0))]);
        fd.record_point(0, 0, 2.0, vec![Some((4.0, 3.0))]);
        let (g, c) = fd.result()[0].clone().unwrap();
        assert_eq!(g[0], 2.0);
        assert_eq!(c[(0, 0)], 1.0);
    }

    #[test]
    fn missing_gate_gives_none() {
        let mut fd = FiniteDifference::new(1, vec![0.0, 0.0], 1.0, 1);
        fd.record_base(0, vec![Some((0.0, 0.0))]);
        fd.record_point(0, 0, 1.0, vec![Some((1.0, 0.0))]);
        fd.record_point(0, 1, 1.0, vec![None]);
        assert!(fd.result()[0].is_none());
    }
}
