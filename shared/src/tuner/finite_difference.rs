//! Finite-difference gradient measurement with repetitions (paper supplement,
//! "Initial conditions"): `g(0)` is the mean of the repeated one-sided
//! estimates, `C(0)` diagonal with their sample variances.
//!
//! A gate measured on both sides of the base (offsets `+δ` and `−δ`) gives
//! the central estimate `(y₊ − y₋)/(δ₊ − δ₋)` instead: every effect even in
//! the offset cancels (a transition line left off by `a·δ` reads an
//! apparent `t_sr·(1 + c·a²δ²)` in both directions), and the noise is
//! half the one-sided estimate's for the same `δ`.
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
    /// The points below the base (negative offsets), as `points`; empty
    /// for one-sided differences.
    #[serde(default)]
    below: Vec<Vec<Option<Point>>>,
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
            below: vec![vec![None; gates]; repetitions],
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

    /// Record the measurement with gate `gate` offset by `actual_offset_mv`
    /// (negative: the point below the base of a central difference).
    pub fn record_point(
        &mut self,
        rep: usize,
        gate: usize,
        actual_offset_mv: f64,
        samples: Vec<Option<Sample>>,
    ) {
        let side = if actual_offset_mv < 0.0 {
            if self.below.len() < self.points.len() {
                self.below = vec![vec![None; self.gates]; self.points.len()];
            }
            &mut self.below
        } else {
            &mut self.points
        };
        side[rep][gate] = Some((actual_offset_mv, samples));
    }

    /// One repetition's estimate of `∂p_param/∂v_gate` and its propagated
    /// variance: central where both sides were measured, else one-sided
    /// from the base.
    fn estimate(&self, rep: usize, param: usize, gate: usize) -> Option<(f64, f64)> {
        let sample = |side: &Vec<Vec<Option<Point>>>| {
            let (dv, samples) = side.get(rep)?.get(gate)?.as_ref()?;
            samples[param].map(|y| (*dv, y))
        };
        let (above, below) = (sample(&self.points), sample(&self.below));
        let (base, far) = match (above, below) {
            (Some(a), Some(b)) => (b, a),
            (Some(far), None) | (None, Some(far)) => ((0.0, self.base[rep][param]?), far),
            (None, None) => return None,
        };
        let ((d0, (y0, v0)), (d1, (y1, v1))) = (base, far);
        let dv = d1 - d0;
        if dv.abs() < 1e-12 {
            return None;
        }
        Some(((y1 - y0) / dv, (v0 + v1) / (dv * dv)))
    }

    /// Gradient rows and diagonal covariances; `None` for a parameter with a
    /// gate that has no usable estimate at all.
    pub fn result(&self) -> Vec<Option<(DVector<f64>, DMatrix<f64>)>> {
        (0..self.params)
            .map(|i| {
                let mut g = DVector::zeros(self.gates);
                let mut var = DVector::zeros(self.gates);
                for j in 0..self.gates {
                    let (estimates, propagated): (Vec<f64>, Vec<f64>) = (0..self.repetitions())
                        .filter_map(|rep| self.estimate(rep, i, j))
                        .unzip();
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
    fn both_sides_give_the_central_difference_and_cancel_an_even_term() {
        // y = 0.02·δ + 0.01·δ² (an even term, e.g. a line left off by ∝ δ)
        let y = |d: f64| 0.02 * d + 0.01 * d * d;
        let mut fd = FiniteDifference::new(1, vec![0.0], 6.0, 1);
        fd.record_base(0, vec![Some((0.0, 1e-4))]);
        fd.record_point(0, 0, 6.0, vec![Some((y(6.0), 1e-4))]);
        let one_sided = fd.result()[0].clone().unwrap();
        assert!((one_sided.0[0] - 0.08).abs() < 1e-12); // 0.02 + 0.01·6: biased
        fd.record_point(0, 0, -6.0, vec![Some((y(-6.0), 1e-4))]);
        let (g, c) = fd.result()[0].clone().unwrap();
        assert!((g[0] - 0.02).abs() < 1e-12);
        // (1e-4 + 1e-4)/12², a quarter of the one-sided variance
        assert!((c[(0, 0)] - 2e-4 / 144.0).abs() < 1e-18);
        assert!((one_sided.1[(0, 0)] - 4.0 * c[(0, 0)]).abs() < 1e-15);
    }

    #[test]
    fn a_failed_side_falls_back_to_the_base() {
        let mut fd = FiniteDifference::new(1, vec![0.0], 2.0, 1);
        fd.record_base(0, vec![Some((1.0, 0.0))]);
        fd.record_point(0, 0, 2.0, vec![None]);
        fd.record_point(0, 0, -2.0, vec![Some((0.0, 0.0))]);
        assert_eq!(fd.result()[0].clone().unwrap().0[0], 0.5);
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
