//! A row that learns how its gradient bends: the second-order terms of a
//! parameter's scale `y` over the cell's own gates.
//!
//! The joint tuner's rows learn `y(v) ≈ y₀ + g·(v − v₀)` (`y = ln p`): one
//! gradient, followed as it turns by the filter's process noise. A device's
//! `ln t_c` and `ln Γ` bend over the tens of mV a set-point change crosses
//! (the gradient of `ln w` on a random array's cell can change sign between
//! two set points, docs/array-history.md "A row that learns its bend"), and a
//! gradient learned one rank-one update per move lags far behind. With
//! curvature the row learns
//!
//! `y(v) = y_a + g·(v − a) + Σ_{i≤j} h_ij·d_i·d_j`, `d = v_own − a_own`,
//!
//! with `a` the anchor (where the row first measured), `g` the gradient at
//! the anchor over every column of the row and `h` one coefficient per pair
//! of the cell's own gates. The model is linear in `θ = (g, h)`, so the same
//! Kalman filter learns it from the change between two measurements, with
//! the features `φ(v) = (v, d_i·d_j)` in place of the voltages. The
//! gradient at `v` (what the step plans with) is `∂y/∂v = A(v)·θ`,
//! `A(v) = [I | B(v)]`, `B`'s column of pair (i, j) being `d_j` at own gate
//! `i` plus `d_i` at own gate `j`; its covariance `A·C·Aᵀ`.
//!
//! ```
//! use spintune::tuner::curvature::Curvature;
//! // a row over 3 columns whose own gates are columns 1 and 2
//! let mut c = Curvature::new(3, vec![1, 2]);
//! assert_eq!(c.terms(), 3); // (1,1), (1,2), (2,2)
//! c.anchor_at(&[0.0, 10.0, 20.0]);
//! // 2 mV and 3 mV from the anchor on the own gates
//! let phi = c.features(&[5.0, 12.0, 23.0]);
//! assert_eq!(phi.as_slice(), &[5.0, 12.0, 23.0, 4.0, 6.0, 9.0]);
//! // y = 0.01·v₁ + 0.001·d₁² : the gradient at d₁ = 2 is 0.01 + 0.004
//! let theta = nalgebra::DVector::from_vec(vec![0.0, 0.01, 0.0, 0.001, 0.0, 0.0]);
//! let g = c.local_map(&[5.0, 12.0, 23.0]) * theta;
//! assert!((g[1] - 0.014).abs() < 1e-15 && g[0] == 0.0 && g[2] == 0.0);
//! ```

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Largest prior σ of a curvature coefficient
/// ([`super::array::JointConfig::curvature_prior_per_mv2`]), 1/mV².
pub const MAX_CURVATURE_PRIOR_PER_MV2: f64 = 0.01;

/// The second-order part of one row (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Curvature {
    /// Columns of the row (its gradient's length).
    columns: usize,
    /// The row's columns that are the cell's own gates.
    own: Vec<usize>,
    /// Pairs `(i, j)`, `i ≤ j`, of indices into `own`, one per coefficient.
    pairs: Vec<(usize, usize)>,
    /// The own gates' voltages where the row first measured, mV (empty
    /// until then).
    anchor: Vec<f64>,
}

impl Curvature {
    /// Curvature over `own` (indices below `columns`) of a row with
    /// `columns` columns, not yet anchored.
    pub fn new(columns: usize, own: Vec<usize>) -> Self {
        let mut pairs = Vec::new();
        for i in 0..own.len() {
            for j in i..own.len() {
                pairs.push((i, j));
            }
        }
        Self {
            columns,
            own,
            pairs,
            anchor: Vec::new(),
        }
    }

    /// Number of curvature coefficients: `k(k+1)/2` for `k` own gates.
    pub fn terms(&self) -> usize {
        self.pairs.len()
    }

    /// Whether the anchor is set.
    pub fn anchored(&self) -> bool {
        !self.anchor.is_empty()
    }

    /// Anchor at `v` (the row's columns, mV) unless anchored already.
    pub fn anchor_at(&mut self, v: &[f64]) {
        if !self.anchored() {
            self.anchor = self.own.iter().map(|&c| v[c]).collect();
        }
    }

    /// Own gates' deviations from the anchor at `v` (0 before it is set).
    fn deviations(&self, v: &[f64]) -> Vec<f64> {
        self.own
            .iter()
            .enumerate()
            .map(|(k, &c)| v[c] - self.anchor.get(k).copied().unwrap_or(v[c]))
            .collect()
    }

    /// The features `φ(v) = (v, d_i·d_j)` (length `columns + terms`).
    pub fn features(&self, v: &[f64]) -> DVector<f64> {
        let d = self.deviations(v);
        DVector::from_iterator(
            self.columns + self.terms(),
            v.iter()
                .copied()
                .chain(self.pairs.iter().map(|&(i, j)| d[i] * d[j])),
        )
    }

    /// `A(v)` (columns × (columns + terms)): the gradient at `v` is
    /// `A(v)·θ`, its covariance `A·C·Aᵀ`.
    pub fn local_map(&self, v: &[f64]) -> DMatrix<f64> {
        let d = self.deviations(v);
        let n = self.columns;
        let mut a = DMatrix::zeros(n, n + self.terms());
        for k in 0..n {
            a[(k, k)] = 1.0;
        }
        for (p, &(i, j)) in self.pairs.iter().enumerate() {
            a[(self.own[i], n + p)] += d[j];
            a[(self.own[j], n + p)] += d[i];
        }
        a
    }
}
