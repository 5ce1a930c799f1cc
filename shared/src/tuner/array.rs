//! [`JointArrayTuner`]: the joint estimate and step of an array's qubit
//! parameters (issue 24, first slice). Plain data, no IO: the caller
//! measures, feeds values and applies the moves it returns (invariant 2's
//! spirit: this never calls a device).
//!
//! * **Rows.** One Kalman row ([`KalmanGradient`]) per parameter and cell,
//!   over the tuning gates of its *neighbourhood*: the cells within
//!   `radius` of its own (own cell + nearest neighbours for radius 1).
//!   Parameters are tuned in log space (`y = ln p`), as the recommended
//!   single-cell tuner does, or, for a parameter with a floor (`w` over
//!   its thermal floor with [`JointConfig::thermal_floor`],
//!   [`CellKnowledge::floors`]), as the log of its excess over the floor
//!   ([`FloorLog`]); residuals, predictions and the band are taken in the
//!   same `y`.
//! * **Prior.** The own-cell block is the cell's initial measurement (its
//!   learned gradient and covariance), `g_own` and `P_own` (with
//!   [`JointConfig::lockstep_correction`], off by default, divided by the
//!   cell's [`lockstep_factor`] and its square: the cells measured in
//!   lockstep, so each saw its neighbours' crosstalk copies of its own
//!   gradient too). A neighbour's block
//!   follows the lab's cross-cell virtual-gate calibration `λ̂` (the same
//!   that feeds the compensation): a neighbour at distance `d` moving gate
//!   `X` acts on this cell like `λ̂(d)` times the cell's own `X`. So the
//!   neighbour's gradient is `λ̂(d)·g_own(X) + e` with an independent
//!   deviation `e` of variance `(f·|g_own(X)|)² + (f/10·max|g_own|)²`, `f` =
//!   [`JointConfig::neighbour_prior_fraction`] (an assumption of the lab,
//!   not the simulator's crosstalk). With the map `T` (own gate → every
//!   column of the row: 1 on the own block, `λ̂(d)` on a neighbour's same
//!   gate), the row's prior is mean `T·g_own` and covariance
//!   `T·P_own·Tᵀ + diag(var e)`, and its process noise `σ²·T·Tᵀ`: an own
//!   gradient and the crosstalk it implies are learned together
//!   ([`JointConfig::correlated_prior`]; without it the blocks are
//!   independent, `Q = σ²·I`; with [`JointConfig::calibrated_prior_mean`]
//!   off the neighbours' mean is zero and their blocks independent).
//! * **Step.** Residuals `y − ln target` of the cells the caller aims, 0 for
//!   the cells it holds (kept where they are, so the step compensates the
//!   crosstalk the filter predicts onto them), one step over every tuning
//!   gate of the array with each cell's part within the cell's step limit
//!   (mV, Euclidean over its tuning gates): by default the trust-region
//!   step on the expected residual ([`JointConfig::trust_region`],
//!   [`super::block_trust_region`]), otherwise the paper's minimum-norm
//!   Newton step `−J⁺Δ` ([`newton_step`]) scaled per cell to its limit;
//!   then clipped per gate to `max_step_mv` and the limits
//!   ([`SafetyLimits::clip`]). A cell whose step is cut to its limit
//!   spends [`JointConfig::excitation`] of it along the null space of its
//!   own rows ([`super::excitation`]). Compensation gates follow with the cell's
//!   virtual-gate matrix applied to its own move plus the lab's cross-cell
//!   calibration `λ̂` times its neighbours' moves
//!   ([`JointConfig::cross_compensation`]), clipped the same way.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::config_error::ConfigError;
use crate::description::layout::{CellGrid, Layout};
use crate::kalman::{FilterError, KalmanGradient, ProcessNoise, UpdateOutcome};
use crate::safety::SafetyLimits;
use crate::solver::{newton_step, SolverConfig, StepRule};
use crate::tuner::block_trust_region::block_trust_region_step;
use crate::tuner::curvature::{Curvature, MAX_CURVATURE_PRIOR_PER_MV2};
use crate::tuner::excitation::null_space_direction;
use crate::tuner::miss_cusum::MissCusum;
use crate::tuner::newton::{retreat_target, Consistency};
use crate::tuner::thermal_floor::FloorLog;

/// Largest [`JointConfig::trust_region_covariance`].
pub const MAX_TRUST_REGION_COVARIANCE: f64 = 10.0;

/// Settings of the joint array tuner.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointConfig {
    /// Neighbourhood radius in cells, 0..=2 (1: own cell + nearest neighbours).
    pub radius: u32,
    /// Prior standard deviation of a neighbour's gradient around its mean,
    /// as a fraction of the own gradient of the same gate, 0 < f ≤ 2.
    /// Default 0.1 with the correlated prior (chosen on random arrays,
    /// docs/array-history.md "The neighbours' prior follows the own gradient");
    /// 0.5 suits the independent prior.
    pub neighbour_prior_fraction: f64,
    /// Kalman outlier gate, σ (1..=100). Default 5.
    pub outlier_sigma: f64,
    /// Smallest step the filter learns from, mV (0..=1). Default 0.01.
    pub min_step_mv: f64,
    /// Prior mean of a neighbour's gradient: `true` (default) the lab's
    /// cross-cell calibration `λ̂(d)` times the own gradient of the same
    /// gate; `false` zero (crosstalk learned from nothing; measured worse on
    /// random arrays, docs/array-history.md).
    #[serde(default = "yes")]
    pub calibrated_prior_mean: bool,
    /// Whether the plungers also follow `λ̂` times the neighbours' tuning
    /// moves (cross-cell virtual gates). Default `false`: with the default
    /// crosstalk, plungers couple like the tuning gates, so each cell's own
    /// compensation already cancels most of its neighbours' line shift.
    #[serde(default)]
    pub cross_compensation: bool,
    /// Whether a neighbour's block is correlated with the own block through
    /// the calibration `λ̂` (module docs, "Prior"). Default `true`: the
    /// lockstep moves of an array cannot tell an own gradient from its
    /// neighbours' copies, and independent blocks learned them apart badly
    /// (docs/array-history.md).
    #[serde(default = "yes")]
    pub correlated_prior: bool,
    /// Whether each cell's initial gradient is divided by its lockstep
    /// factor ([`lockstep_factor`]) and its covariance by the factor's
    /// square: the cells' initial finite differences run in every cell at
    /// once, each moving the same gate by the same step, so a cell measured
    /// its own gradient plus its neighbours' crosstalk copies of it.
    /// Default `false`: the corrected prior is unbiased, and faster on the
    /// development sets, but its larger first steps got whole runs stuck on
    /// random arrays; the biased gradients' damping is kept (docs/array-history.md
    /// "Initial measurements in lockstep").
    #[serde(default)]
    pub lockstep_correction: bool,
    /// Fraction of a cell's step spent exploring, 0 ≤ β ≤ 0.9 (0: off): a
    /// cell whose step is cut to its step limit (far from its targets) moves
    /// `√(1−β²)` of the limit along its planned step and `β` of it along the
    /// null space of its own rows, where the filter is least sure
    /// ([`super::excitation`]), the sign alternating per measurement and
    /// between neighbouring cells. Cells within their limit, near their
    /// targets, move as planned; the oracle never explores. Default 0.5,
    /// chosen on 132 runs of random development arrays (0, 0.3, 0.5, each
    /// with and without a rule sparing cells next to near ones) and checked
    /// on fresh ones (docs/array-history.md "Steps that also teach").
    #[serde(default = "default_excitation")]
    pub excitation: f64,
    /// Whether a cell's `w` is learned over its thermal floor, measured
    /// from the lead transitions of its initial measurement
    /// ([`super::thermal_floor`]): `y = ½·ln(w² − f²)`, which follows the
    /// tunnel coupling where `ln w` bends. Without a measured floor (a
    /// lab's own evaluation of its scans) or with `false`, `y = ln w`. The
    /// oracle's Jacobian is log-space and never uses it. Default `false`:
    /// on 132 runs of random development arrays it shortened the cold
    /// start but left more phases unconverged and more neighbours out of
    /// band (docs/array-history.md "`w` over its thermal floor").
    #[serde(default)]
    pub thermal_floor: bool,
    /// Threshold `h` (σ) of the CUSUM that detects a row whose predictions
    /// keep missing on one side ([`super::miss_cusum`]); when it fires,
    /// the row's covariance is multiplied by
    /// [`JointConfig::persistent_miss_inflation`] (a shorter memory for a
    /// gradient that turns faster than its process noise allows). 0: off;
    /// otherwise 1 ≤ h ≤ 50. Default 0: on 132 runs of random development
    /// arrays neither `h` = 4 nor 6 (nor 4 on `w` rows alone, a hand patch)
    /// left fewer phases unconverged (docs/array-history.md "Persistent misses").
    #[serde(default)]
    pub persistent_miss_sigma: f64,
    /// The factor a row's covariance is multiplied by when its misses
    /// persist, 1 ≤ factor ≤ 100 (default 4: the row's σ doubles).
    #[serde(default = "default_persistent_miss_inflation")]
    pub persistent_miss_inflation: f64,
    /// How a cell's step is kept within its `max_step_mv`: `true` (default)
    /// the step that minimises the model's expected residual with every
    /// cell inside its limit ([`super::block_trust_region`]:
    /// Levenberg–Marquardt with one damping per cell, the rows' covariance
    /// weighted by [`JointConfig::trust_region_covariance`]); `false` the
    /// paper's rule (the joint minimum-norm Newton step, each cell's part
    /// scaled down to its limit). With `trust_region_covariance` 0 only a
    /// step that would leave a cell's limit changes; the oracle keeps the
    /// paper's rule. Default `true`,
    /// chosen on 132 runs of random development arrays and checked on
    /// fresh ones (docs/array-history.md "Steps inside a trust region per cell").
    #[serde(default = "yes")]
    pub trust_region: bool,
    /// Weight `κ` of the rows' covariance in the trust-region step's cost
    /// `‖Δ + ĴΔv‖² + κ·Σ_rows Δvᵀ C Δv` (0 ≤ κ ≤ 10): an uncertain gradient
    /// (the neighbours' crosstalk, a `w` row that lags) is leaned on less.
    /// Default 0.5, chosen on the same runs among 0, 0.25, 0.5, 1 and 4.
    #[serde(default = "default_trust_region_covariance")]
    pub trust_region_covariance: f64,
    /// Measurements of a row after it was widened (a stalled parameter,
    /// [`JointArrayTuner::widen_row`]) during which its covariance is left
    /// out of the trust-region step's `κ` term, 0..=[`MAX_WIDENED_ROW_EXPLORES`]:
    /// the widened row is meant to learn from the next moves, and counting
    /// its new uncertainty would steer the step away from the very gates it
    /// must learn about. 0: off (the widened covariance counts at once).
    #[serde(default)]
    pub widened_row_explores: u32,
    /// Prior σ of each curvature coefficient of a row's scale over its
    /// cell's own gates, 1/mV² (0: off, rows learn a gradient only;
    /// otherwise up to [`MAX_CURVATURE_PRIOR_PER_MV2`]): the row learns how
    /// its gradient bends ([`super::curvature`]). Default 0: on random
    /// development arrays the rows came barely nearer the truth and more
    /// phases were left unconverged (docs/array-history.md, "A row that
    /// learns its bend").
    #[serde(default)]
    pub curvature_prior_per_mv2: f64,
}

/// Largest [`JointConfig::widened_row_explores`].
pub const MAX_WIDENED_ROW_EXPLORES: u32 = 30;

fn yes() -> bool {
    true
}

fn default_excitation() -> f64 {
    0.5
}

fn default_persistent_miss_inflation() -> f64 {
    4.0
}

fn default_trust_region_covariance() -> f64 {
    0.5
}

impl Default for JointConfig {
    fn default() -> Self {
        Self {
            radius: 1,
            neighbour_prior_fraction: 0.1,
            outlier_sigma: 5.0,
            min_step_mv: 0.01,
            calibrated_prior_mean: true,
            cross_compensation: false,
            correlated_prior: true,
            lockstep_correction: false,
            excitation: default_excitation(),
            thermal_floor: false,
            persistent_miss_sigma: 0.0,
            persistent_miss_inflation: default_persistent_miss_inflation(),
            trust_region: true,
            trust_region_covariance: default_trust_region_covariance(),
            widened_row_explores: 0,
            curvature_prior_per_mv2: 0.0,
        }
    }
}

impl JointConfig {
    /// `Err` naming the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, v: f64, range: &str| {
            Err(ConfigError::new(field, format!("{v} outside {range}")))
        };
        if self.radius > 2 {
            return bad("joint.radius", f64::from(self.radius), "0..=2");
        }
        let f = self.neighbour_prior_fraction;
        if !(f.is_finite() && f > 0.0 && f <= 2.0) {
            return bad("joint.neighbour_prior_fraction", f, "(0, 2]");
        }
        if !(self.outlier_sigma.is_finite() && (1.0..=100.0).contains(&self.outlier_sigma)) {
            return bad("joint.outlier_sigma", self.outlier_sigma, "[1, 100]");
        }
        if !(self.min_step_mv.is_finite() && (0.0..=1.0).contains(&self.min_step_mv)) {
            return bad("joint.min_step_mv", self.min_step_mv, "[0, 1]");
        }
        if !(self.excitation.is_finite() && (0.0..=0.9).contains(&self.excitation)) {
            return bad("joint.excitation", self.excitation, "[0, 0.9]");
        }
        let h = self.persistent_miss_sigma;
        if !(h == 0.0 || (h.is_finite() && (1.0..=50.0).contains(&h))) {
            return bad("joint.persistent_miss_sigma", h, "0 (off) or [1, 50]");
        }
        let m = self.persistent_miss_inflation;
        if !(m.is_finite() && (1.0..=100.0).contains(&m)) {
            return bad("joint.persistent_miss_inflation", m, "[1, 100]");
        }
        let k = self.trust_region_covariance;
        if !(k.is_finite() && (0.0..=MAX_TRUST_REGION_COVARIANCE).contains(&k)) {
            return bad("joint.trust_region_covariance", k, "[0, 10]");
        }
        let c = self.curvature_prior_per_mv2;
        if !(c.is_finite() && (0.0..=MAX_CURVATURE_PRIOR_PER_MV2).contains(&c)) {
            let range = format!("[0, {MAX_CURVATURE_PRIOR_PER_MV2}]");
            return bad("joint.curvature_prior_per_mv2", c, &range);
        }
        if self.widened_row_explores > MAX_WIDENED_ROW_EXPLORES {
            return bad(
                "joint.widened_row_explores",
                f64::from(self.widened_row_explores),
                "0..=30",
            );
        }
        Ok(())
    }
}

/// What a lab knows about one cell after its initial measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellKnowledge {
    /// The cell's tuning gates (array names), in gradient order.
    pub gates: Vec<String>,
    /// Parameter names (unprefixed, e.g. `t_sr`, `w`).
    pub parameters: Vec<String>,
    /// Learned gradient of each parameter's `y` ([`FloorLog`] over its
    /// floor: `ln p` without one) over `gates`, 1/mV.
    pub gradient: Vec<Vec<f64>>,
    /// Its covariance per parameter, (1/mV)².
    pub covariance: Vec<Vec<Vec<f64>>>,
    /// Process noise σ per parameter, (1/mV) per mV of step.
    pub process_noise_per_mv: Vec<f64>,
    /// Step limit of the cell's tuning gates (Euclidean), mV.
    pub max_step_mv: f64,
    /// Virtual-gate compensation: (gates, matrix rows × `gates`), mV/mV.
    pub compensation: Option<(Vec<String>, Vec<Vec<f64>>)>,
    /// Floor per parameter, its unit (0 or missing: learned as `ln p`;
    /// [`FloorLog`]). Empty in runs saved before floors.
    #[serde(default)]
    pub floors: Vec<f64>,
}

impl CellKnowledge {
    /// Whether the cell has `gates` gates and `parameters` rows, each row
    /// and covariance over all of them: the cells whose rows can be
    /// compared gate by gate (`borrowed_gradient`, `pooled_gradient`).
    pub fn has_shape(&self, gates: usize, parameters: usize) -> bool {
        self.gates.len() == gates
            && self.gradient.len() == parameters
            && self.gradient.iter().all(|g| g.len() == gates)
            && self.covariance.len() == parameters
            && self
                .covariance
                .iter()
                .all(|m| m.len() == gates && m.iter().all(|r| r.len() == gates))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Row {
    cell: usize,
    parameter: usize,
    /// Indices into the array's gate list.
    columns: Vec<usize>,
    filter: KalmanGradient,
    /// Last accepted (y, var y, voltages of `columns`).
    last: Option<(f64, f64, Vec<f64>)>,
    /// The row as it started (its prior), for [`JointArrayTuner::reset_row`]
    /// (`None` in runs saved before it).
    #[serde(default)]
    prior: Option<KalmanGradient>,
    /// The scale the row learns its parameter in (plain log in runs saved
    /// before floors).
    #[serde(default)]
    scale: FloorLog,
    /// Whether the row's misses persist ([`JointConfig::persistent_miss_sigma`]).
    #[serde(default)]
    misses: MissCusum,
    /// How well the row's predictions matched the measurements (every
    /// update's normalised innovation), for [`JointArrayTuner::estimate`].
    #[serde(default)]
    checks: Consistency,
    /// Measurements left during which the row's covariance stays out of
    /// the step's uncertainty term ([`JointConfig::widened_row_explores`]).
    #[serde(default)]
    explores_left: u32,
    /// The row's second-order part ([`JointConfig::curvature_prior_per_mv2`];
    /// `None`: a gradient only, the filter's state is the gradient).
    #[serde(default)]
    curvature: Option<Curvature>,
}

impl Row {
    /// What the filter learns from at `v` (the row's columns, mV): `v`
    /// itself, or the curvature's features.
    fn features(&self, v: &[f64]) -> DVector<f64> {
        match &self.curvature {
            Some(c) => c.features(v),
            None => DVector::from_column_slice(v),
        }
    }

    /// `A` at the row's last value ([`Curvature::local_map`]); `None`
    /// without curvature or a last value.
    fn local_map(&self) -> Option<DMatrix<f64>> {
        let c = self.curvature.as_ref()?;
        let (_, _, v) = self.last.as_ref()?;
        Some(c.local_map(v))
    }

    /// The row's gradient where it last measured, over its columns, 1/mV.
    fn gradient(&self) -> DVector<f64> {
        let g = self.filter.gradient();
        match self.local_map() {
            Some(a) => a * g,
            None => g.rows(0, self.columns.len()).into_owned(),
        }
    }

    /// That gradient's covariance, (1/mV)².
    fn covariance(&self) -> DMatrix<f64> {
        let c = self.filter.covariance();
        let n = self.columns.len();
        match self.local_map() {
            Some(a) => &a * c * a.transpose(),
            None => c.view((0, 0), (n, n)).into_owned(),
        }
    }
}

/// The joint tuner (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JointArrayTuner {
    cells: Vec<CellKnowledge>,
    /// Where the cells sit ([`JointArrayTuner::with_grid`]; a chain in
    /// runs saved before it).
    #[serde(default)]
    layout: Layout,
    /// Every tuning gate, cell by cell.
    gates: Vec<String>,
    rows: Vec<Row>,
    /// Kalman updates that were rejected (outlier gate, invalid input).
    pub rejected_updates: u64,
    /// The lab's cross-cell virtual-gate calibration: the fraction of a
    /// nearest / next-nearest cell's tuning move its compensation gates see
    /// (dimensionless; default 0 = none).
    neighbour_compensation: [f64; 2],
    /// [`JointConfig::excitation`] (0 in runs saved before it).
    #[serde(default)]
    excitation: f64,
    /// Per cell, the sign of its next excitation: flipped at each of its
    /// measurements ([`JointArrayTuner::observe`]); cells not yet measured
    /// (or runs saved before it) start at `false`.
    #[serde(default)]
    excitation_flipped: Vec<bool>,
    /// [`JointConfig::persistent_miss_sigma`] and
    /// [`JointConfig::persistent_miss_inflation`] (off in runs saved
    /// before them).
    #[serde(default)]
    persistent_miss: (f64, f64),
    /// How often a row's covariance was widened after persistent misses.
    #[serde(default)]
    pub persistent_misses: u64,
    /// [`JointConfig::trust_region`] (off in runs saved before it).
    #[serde(default)]
    trust_region: bool,
    /// [`JointConfig::trust_region_covariance`].
    #[serde(default)]
    trust_region_covariance: f64,
    /// [`JointConfig::widened_row_explores`] (off in runs saved before it).
    #[serde(default)]
    widened_row_explores: u32,
}

/// `Err` naming the field unless each of the lab's cross-cell calibration
/// fractions `λ̂` (nearest, next) is in [0, [`crate::sim::array::MAX_CROSSTALK`]].
pub fn check_cross_calibration(lambda: [f64; 2]) -> Result<(), ConfigError> {
    for (i, l) in lambda.iter().enumerate() {
        if !(l.is_finite() && (0.0..=crate::sim::array::MAX_CROSSTALK).contains(l)) {
            return Err(ConfigError::new(
                format!("cross_calibration[{i}]"),
                format!("{l} outside [0, {}]", crate::sim::array::MAX_CROSSTALK),
            ));
        }
    }
    Ok(())
}

/// A measured value (parameter unit) and its variance (unit²).
pub type Measured = (f64, f64);

/// Updates a row needs before its predictions' consistency scales the
/// prediction in [`JointArrayTuner::estimate`].
pub const MIN_CHECKS_FOR_ESTIMATE: u64 = 3;

/// How much larger cell `cell`'s initial gradient comes out when all
/// `cells` take their finite differences in lockstep (every cell moving
/// the same gate by the same step at once) than its own gradient:
/// `1 + Σ_{k ≠ cell} λ̂(|cell − k|)`, `λ̂ = cross_calibration` (nearest,
/// next; 0 beyond). A neighbour moving gate X acts on the cell like `λ̂`
/// times the cell's own X (the crosstalk model of the prior), so a
/// lockstep step δ moves the cell as its own gate would by `factor·δ`.
///
/// ```
/// use spintune::description::layout::{CellGrid, Layout};
/// use spintune::tuner::array::lockstep_factor;
/// // an end cell of three sees one nearest and one next neighbour,
/// // the middle cell two nearest
/// let chain = CellGrid::chain(3);
/// assert!((lockstep_factor(&chain, 0, [0.3, 0.05]) - 1.35).abs() < 1e-12);
/// assert!((lockstep_factor(&chain, 1, [0.3, 0.05]) - 1.6).abs() < 1e-12);
/// assert_eq!(lockstep_factor(&CellGrid::chain(1), 0, [0.3, 0.05]), 1.0);
/// // a corner of a 2×4 ladder: two nearest (along the row, across
/// // the rung), two next (the diagonal, two along the row)
/// let ladder = CellGrid::new(Layout::Ladder, 8).unwrap();
/// assert!((lockstep_factor(&ladder, 0, [0.3, 0.05]) - 1.7).abs() < 1e-12);
/// ```
pub fn lockstep_factor(grid: &CellGrid, cell: usize, cross_calibration: [f64; 2]) -> f64 {
    1.0 + (0..grid.cells())
        .filter(|&k| k != cell)
        .map(|k| calibrated_fraction(cross_calibration, grid.distance(cell, k)))
        .sum::<f64>()
}

/// `λ̂(d)`: the fraction of a gate's own-cell effect that the lab's
/// cross-cell calibration (`cross_calibration` = nearest, next) expects a
/// cell `distance` cells away to feel: 1 for the cell itself, 0 beyond
/// the next neighbour.
///
/// ```
/// use spintune::tuner::array::calibrated_fraction;
/// let l = [0.3, 0.05];
/// assert_eq!([0, 1, 2, 3].map(|d| calibrated_fraction(l, d)), [1.0, 0.3, 0.05, 0.0]);
/// ```
pub fn calibrated_fraction(cross_calibration: [f64; 2], distance: usize) -> f64 {
    match distance {
        0 => 1.0,
        1 => cross_calibration[0],
        2 => cross_calibration[1],
        _ => 0.0,
    }
}

/// The index in `own_gates` of the gate named like `gate` (array names,
/// compared without their cell prefix).
fn same_gate(own_gates: &[String], gate: &str) -> Option<usize> {
    let local = crate::sim::array::split_gate(gate).map(|(_, l)| l);
    own_gates
        .iter()
        .position(|o| crate::sim::array::split_gate(o).map(|(_, l)| l) == local)
}

/// One row's prior (module docs, "Prior"): mean `T_mean·g_own`,
/// covariance `T·P_own·Tᵀ + diag(deviation)` and process noise
/// `σ²·(T·Tᵀ + U)`, `σ` = `sigma_per_mv`. `T_mean` (columns × own gates) is
/// 1 from each own column to its gate and `λ̂(d)` from a neighbour's column
/// to the same own gate; `T` is `T_mean` with the neighbours' entries kept
/// only when `correlated` (the own block is rows `own_at..own_at + own
/// gates`). `U` is 1 on the diagonal of a column `T` leaves empty (an
/// independent neighbour column).
fn row_prior(
    g_own: &[f64],
    own_covariance: &[Vec<f64>],
    t_mean: &DMatrix<f64>,
    own_at: usize,
    deviation: &[f64],
    sigma_per_mv: f64,
    correlated: bool,
) -> (DVector<f64>, DMatrix<f64>, ProcessNoise) {
    let (n, no) = t_mean.shape();
    let p_own = DMatrix::from_fn(no, no, |r, s| {
        own_covariance
            .get(r)
            .and_then(|row| row.get(s))
            .copied()
            .unwrap_or(0.0)
    });
    let g0 = t_mean * DVector::from_column_slice(g_own);
    let mut t = t_mean.clone();
    if !correlated {
        for a in (0..n).filter(|a| !(own_at..own_at + no).contains(a)) {
            t.row_mut(a).fill(0.0);
        }
    }
    let c0 =
        &t * p_own * t.transpose() + DMatrix::from_diagonal(&DVector::from_column_slice(deviation));
    let mut q = &t * t.transpose();
    for a in 0..n {
        if t.row(a).iter().all(|&x| x == 0.0) {
            q[(a, a)] = 1.0;
        }
    }
    let s2 = sigma_per_mv * sigma_per_mv;
    (g0, c0, ProcessNoise::Constant { q: q * s2 })
}

/// A row's prior `(g0, c0, q)` extended by `terms` curvature coefficients
/// ([`super::curvature`]): mean 0, independent prior σ `sigma_per_mv2`
/// (1/mV²), no process noise (a device's curvature does not drift).
fn with_curvature(
    g0: DVector<f64>,
    c0: DMatrix<f64>,
    q: ProcessNoise,
    terms: usize,
    sigma_per_mv2: f64,
) -> (DVector<f64>, DMatrix<f64>, ProcessNoise) {
    let n = g0.len();
    let m = n + terms;
    let g = DVector::from_fn(m, |i, _| if i < n { g0[i] } else { 0.0 });
    let c = DMatrix::from_fn(m, m, |i, j| match (i < n, j < n) {
        (true, true) => c0[(i, j)],
        (false, false) if i == j => sigma_per_mv2 * sigma_per_mv2,
        _ => 0.0,
    });
    let extend = |q: &DMatrix<f64>| {
        DMatrix::from_fn(m, m, |i, j| if i < n && j < n { q[(i, j)] } else { 0.0 })
    };
    let q = match q {
        ProcessNoise::Constant { q } => ProcessNoise::Constant { q: extend(&q) },
        ProcessNoise::StepScaled {
            q_ref,
            reference_step_mv,
        } => ProcessNoise::StepScaled {
            q_ref: extend(&q_ref),
            reference_step_mv,
        },
    };
    (g, c, q)
}

impl JointArrayTuner {
    /// Rows and priors from each cell's knowledge (module docs), the cells
    /// in a chain.
    pub fn new(
        cells: Vec<CellKnowledge>,
        config: &JointConfig,
        cross_calibration: [f64; 2],
    ) -> Result<Self, ConfigError> {
        let chain = CellGrid::chain(cells.len());
        Self::with_grid(chain, cells, config, cross_calibration)
    }

    /// [`JointArrayTuner::new`] for cells on `grid`: a row's neighbourhood
    /// is the cells within [`JointConfig::radius`] of its own on the grid,
    /// and the priors' `λ̂` follow the grid's distance. `Err` naming
    /// `layout` for a grid of another number of cells.
    pub fn with_grid(
        grid: CellGrid,
        cells: Vec<CellKnowledge>,
        config: &JointConfig,
        cross_calibration: [f64; 2],
    ) -> Result<Self, ConfigError> {
        config.validate()?;
        if grid.cells() != cells.len() {
            return Err(ConfigError::new(
                "layout",
                format!("a grid of {} cells for {} cells", grid.cells(), cells.len()),
            ));
        }
        check_cross_calibration(cross_calibration)?;
        let n_cells = cells.len();
        let mut gates = Vec::new();
        let mut offsets = Vec::new();
        for c in &cells {
            offsets.push(gates.len());
            gates.extend(c.gates.iter().cloned());
        }
        let mut rows = Vec::new();
        let f = config.neighbour_prior_fraction;
        for (ci, c) in cells.iter().enumerate() {
            let neighbourhood: Vec<usize> = grid.within(ci, config.radius as usize).collect();
            let lockstep = if config.lockstep_correction {
                lockstep_factor(&grid, ci, cross_calibration)
            } else {
                1.0
            };
            for (pi, measured) in c.gradient.iter().enumerate() {
                let field = format!("cells[{ci}].gradient[{pi}]");
                if measured.len() != c.gates.len() || measured.iter().any(|x| !x.is_finite()) {
                    return Err(ConfigError::new(field, "one finite value per gate"));
                }
                let g_own: Vec<f64> = measured.iter().map(|g| g / lockstep).collect();
                let g_own = &g_own;
                let own_covariance: Vec<Vec<f64>> = c
                    .covariance
                    .get(pi)
                    .map(|p| p.iter())
                    .into_iter()
                    .flatten()
                    .map(|row| row.iter().map(|x| x / (lockstep * lockstep)).collect())
                    .collect();
                let lambda = |d: usize| -> f64 {
                    if !config.calibrated_prior_mean {
                        return 0.0;
                    }
                    calibrated_fraction(cross_calibration, d)
                };
                let scale = g_own.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                let n = neighbourhood.iter().map(|&nj| cells[nj].gates.len()).sum();
                let mut t_mean = DMatrix::zeros(n, c.gates.len());
                let (mut columns, mut deviation) = (Vec::with_capacity(n), Vec::with_capacity(n));
                let mut own_at = 0;
                for (nj, nc) in neighbourhood.iter().map(|&nj| (nj, &cells[nj])) {
                    if nj == ci {
                        own_at = columns.len();
                    }
                    for (gi, gname) in nc.gates.iter().enumerate() {
                        let col = columns.len();
                        columns.push(offsets[nj] + gi);
                        if nj == ci {
                            t_mean[(col, gi)] = 1.0;
                            deviation.push(0.0);
                            continue;
                        }
                        // the same gate of the own block (prefix stripped)
                        let own = same_gate(&c.gates, gname);
                        if let Some(k) = own {
                            t_mean[(col, k)] = lambda(grid.distance(ci, nj));
                        }
                        let size = own.map_or(scale, |k| g_own[k].abs());
                        deviation.push((f * size).powi(2) + (0.1 * f * scale).powi(2));
                    }
                }
                let (g0, c0, q) = row_prior(
                    g_own,
                    &own_covariance,
                    &t_mean,
                    own_at,
                    &deviation,
                    c.process_noise_per_mv[pi],
                    config.correlated_prior,
                );
                let curvature = (config.curvature_prior_per_mv2 > 0.0).then(|| {
                    Curvature::new(columns.len(), (own_at..own_at + c.gates.len()).collect())
                });
                let (g0, c0, q) = match &curvature {
                    Some(k) => with_curvature(g0, c0, q, k.terms(), config.curvature_prior_per_mv2),
                    None => (g0, c0, q),
                };
                let filter = KalmanGradient::new(g0, c0, q)
                    .and_then(|k| k.with_outlier_sigma(Some(config.outlier_sigma)))
                    .and_then(|k| k.with_min_step_mv(config.min_step_mv))
                    .map_err(|e: FilterError| ConfigError::new(field, e.to_string()))?;
                rows.push(Row {
                    cell: ci,
                    parameter: pi,
                    columns,
                    prior: Some(filter.clone()),
                    filter,
                    last: None,
                    scale: FloorLog::new(c.floors.get(pi).copied().unwrap_or(0.0)),
                    misses: MissCusum::default(),
                    checks: Consistency::default(),
                    explores_left: 0,
                    curvature,
                });
            }
        }
        Ok(Self {
            layout: grid.layout(),
            cells,
            gates,
            rows,
            rejected_updates: 0,
            excitation: config.excitation,
            trust_region: config.trust_region,
            trust_region_covariance: config.trust_region_covariance,
            widened_row_explores: config.widened_row_explores,
            excitation_flipped: vec![false; n_cells],
            persistent_miss: (
                config.persistent_miss_sigma,
                config.persistent_miss_inflation,
            ),
            persistent_misses: 0,
            neighbour_compensation: if config.cross_compensation {
                cross_calibration
            } else {
                [0.0; 2]
            },
        })
    }

    /// The cells on their grid.
    fn grid(&self) -> CellGrid {
        let n = self.cells.len();
        CellGrid::or_chain(self.layout, n)
    }

    /// `cell`'s row of `parameter`.
    fn row(&self, cell: usize, parameter: usize) -> Option<&Row> {
        self.rows
            .iter()
            .find(|r| r.cell == cell && r.parameter == parameter)
    }

    /// `cell`'s row of `parameter`, to change.
    fn row_mut(&mut self, cell: usize, parameter: usize) -> Option<&mut Row> {
        self.rows
            .iter_mut()
            .find(|r| r.cell == cell && r.parameter == parameter)
    }

    /// Euclidean norm of a row's learned gradient (log space, 1/mV); `None`
    /// for an unknown row.
    pub fn row_norm(&self, cell: usize, parameter: usize) -> Option<f64> {
        self.row(cell, parameter).map(|r| r.gradient().norm())
    }

    /// Return a row's estimate to its prior (the cell's initial measurement
    /// and the calibrated crosstalk, module docs): what was learned since is
    /// dropped; the next update starts from the row's last accepted value.
    /// Whether the row exists (and has a prior to return to).
    pub fn reset_row(&mut self, cell: usize, parameter: usize) -> bool {
        let Some(row) = self.row_mut(cell, parameter) else {
            return false;
        };
        match &row.prior {
            Some(prior) => {
                row.filter = prior.clone();
                true
            }
            None => false,
        }
    }

    /// Widen `cell`'s row of `parameter`: its covariance gains its prior's
    /// (the learned gradient is kept, but the row is again as unsure as it
    /// started, so the next moves teach it as much as the first did).
    /// Whether the row exists and has a prior.
    pub fn widen_row(&mut self, cell: usize, parameter: usize) -> bool {
        let explores = self.widened_row_explores;
        let Some(row) = self.row_mut(cell, parameter) else {
            return false;
        };
        let Some(prior) = &row.prior else {
            return false;
        };
        let c = row.filter.covariance() + prior.covariance();
        let g = row.filter.gradient().clone();
        let widened = row.filter.set_estimate(g, c).is_ok();
        if widened {
            row.explores_left = explores;
        }
        widened
    }

    /// Give `cell`'s row of `parameter` the own-gate gradient the rows of
    /// the cells `from` learned (each of their own gates matched to the
    /// cell's gate of the same name): mean, and per gate a variance of the
    /// rows' own variance (mean) plus the spread between them (the sample
    /// variance; the mean's square from a single row), uncorrelated with the
    /// row's other gates. The row's neighbour columns keep what they
    /// learned. The cells of an array are alike, but a cell may sit where
    /// its gradient is not the others': for a stalled row
    /// ([`super::stall`]) this measured worse than widening it
    /// ([`Self::widen_row`]; docs/array-history.md). Rows in a scale over a thermal floor
    /// are not comparable between cells (each has its own floor): only rows
    /// in plain log take part. Whether the row exists, `from` held at least
    /// one other cell's plain row, and the estimate was replaced.
    ///
    /// ```
    /// use spintune::tuner::array::{CellKnowledge, JointArrayTuner, JointConfig};
    /// let cell = |k: u32, g: [f64; 2]| CellKnowledge {
    ///     gates: vec![format!("c{k}.A"), format!("c{k}.B")],
    ///     parameters: vec!["t_sr".into()],
    ///     gradient: vec![g.to_vec()],
    ///     covariance: vec![vec![vec![1e-6, 0.0], vec![0.0, 1e-6]]],
    ///     process_noise_per_mv: vec![0.0],
    ///     floors: vec![0.0],
    ///     max_step_mv: 10.0,
    ///     compensation: None,
    /// };
    /// let cells = vec![cell(0, [0.01, 0.0]), cell(1, [0.0, 0.02]), cell(2, [0.0, 0.04])];
    /// let mut tuner = JointArrayTuner::new(cells, &JointConfig::default(), [0.0; 2]).unwrap();
    /// assert!(tuner.borrow_row(0, 0, &[1, 2]));
    /// let own: Vec<f64> = tuner.row_gradient(0, 0).iter()
    ///     .filter(|(g, _)| g.starts_with("c0.")).map(|(_, x)| *x).collect();
    /// assert!((own[0] - 0.0).abs() < 1e-12 && (own[1] - 0.03).abs() < 1e-12);
    /// assert!(!tuner.borrow_row(0, 0, &[0]), "a row does not borrow from itself");
    /// ```
    pub fn borrow_row(&mut self, cell: usize, parameter: usize, from: &[usize]) -> bool {
        let own_gates = |r: &Row| -> Vec<(usize, String)> {
            r.columns
                .iter()
                .enumerate()
                .filter_map(|(a, &col)| {
                    let (c, local) = crate::sim::array::split_gate(&self.gates[col])?;
                    (c as usize == r.cell).then(|| (a, local.to_string()))
                })
                .collect()
        };
        let Some(target) = self
            .rows
            .iter()
            .position(|r| r.cell == cell && r.parameter == parameter)
        else {
            return false;
        };
        if self.rows[target].scale != FloorLog::default() {
            return false;
        }
        let gates = own_gates(&self.rows[target]);
        // per own gate of the target: the peers' (gradient, variance)
        let mut samples: Vec<Vec<(f64, f64)>> = vec![Vec::new(); gates.len()];
        for r in self.rows.iter().filter(|r| {
            r.parameter == parameter
                && r.cell != cell
                && from.contains(&r.cell)
                && r.scale == FloorLog::default()
        }) {
            for (a, local) in own_gates(r) {
                if let Some(i) = gates.iter().position(|(_, l)| *l == local) {
                    samples[i].push((r.gradient()[a], r.covariance()[(a, a)]));
                }
            }
        }
        if samples.iter().any(Vec::is_empty) || samples.is_empty() {
            return false;
        }
        let row = &mut self.rows[target];
        let mut g = row.filter.gradient().clone();
        let mut c = row.filter.covariance().clone();
        for ((a, _), peers) in gates.iter().zip(&samples) {
            let n = peers.len() as f64;
            let mean = peers.iter().map(|p| p.0).sum::<f64>() / n;
            let own = peers.iter().map(|p| p.1).sum::<f64>() / n;
            let spread = if peers.len() >= 2 {
                peers.iter().map(|p| (p.0 - mean).powi(2)).sum::<f64>() / (n - 1.0)
            } else {
                mean * mean
            };
            g[*a] = mean;
            c.row_mut(*a).fill(0.0);
            c.column_mut(*a).fill(0.0);
            c[(*a, *a)] = own + spread;
        }
        row.filter.set_estimate(g, c).is_ok()
    }

    /// Every tuning gate of the array, cell by cell (array names).
    pub fn gates(&self) -> &[String] {
        &self.gates
    }

    /// The cells' knowledge.
    pub fn cells(&self) -> &[CellKnowledge] {
        &self.cells
    }

    /// The gradient of `cell`'s parameter `parameter` over its neighbourhood:
    /// (array gate name, log-space gradient 1/mV).
    pub fn row_gradient(&self, cell: usize, parameter: usize) -> Vec<(String, f64)> {
        self.row(cell, parameter)
            .map(|r| {
                r.columns
                    .iter()
                    .zip(r.gradient().iter())
                    .map(|(&c, &g)| (self.gates[c].clone(), g))
                    .collect()
            })
            .unwrap_or_default()
    }

    /// The filter's prediction of `cell`'s parameter `parameter` at
    /// `voltages_mv` (array names) from its last accepted value: `(y,
    /// variance of y)` in the row's scale ([`JointArrayTuner::scale`]; `ln
    /// p` without a floor) — the last value's variance, the gradient's
    /// uncertainty along the change and the process noise of that change.
    /// `None` before a first value or without every gate's voltage.
    pub fn predict(
        &self,
        cell: usize,
        parameter: usize,
        voltages_mv: &BTreeMap<String, f64>,
    ) -> Option<(f64, f64)> {
        let row = self.row(cell, parameter)?;
        let (y0, vy0, v0) = row.last.as_ref()?;
        let v: Vec<f64> = row
            .columns
            .iter()
            .map(|&c| voltages_mv.get(&self.gates[c]).copied())
            .collect::<Option<_>>()?;
        let dv = row.features(&v) - row.features(v0);
        let g = row.filter.gradient();
        let p = row.filter.covariance() + row.filter.process_noise().for_step(&dv);
        let var = vy0 + (dv.transpose() * p * &dv)[(0, 0)];
        let y = y0 + g.dot(&dv);
        (y.is_finite() && var.is_finite()).then_some((y, var))
    }

    /// A reading `measured` (value and variance, unit and unit²) of `cell`'s
    /// parameter `parameter` taken at `from_mv`, carried to `to_mv` along
    /// the row's learned gradient: `y + g·Δ` with the variance of `y` plus
    /// `Δᵀ(C + Q(Δ))Δ` (the gradient's uncertainty and process noise along
    /// the change `Δ` of the row's features), back in the parameter's
    /// unit. At equal voltages the reading itself. `None` for an unknown
    /// row, a value ≤ 0, a variance that is not finite, or a gate of the
    /// row missing from either map.
    pub fn carry(
        &self,
        cell: usize,
        parameter: usize,
        measured: Measured,
        from_mv: &BTreeMap<String, f64>,
        to_mv: &BTreeMap<String, f64>,
    ) -> Option<Measured> {
        let row = self.row(cell, parameter)?;
        let (x, var) = measured;
        if !(x > 0.0 && var.is_finite() && var >= 0.0) {
            return None;
        }
        let at = |m: &BTreeMap<String, f64>| -> Option<Vec<f64>> {
            row.columns
                .iter()
                .map(|&c| m.get(&self.gates[c]).copied())
                .collect()
        };
        let dv = row.features(&at(to_mv)?) - row.features(&at(from_mv)?);
        if dv.iter().all(|&d| d == 0.0) {
            return Some(measured);
        }
        let p = row.filter.covariance() + row.filter.process_noise().for_step(&dv);
        let s = row.scale;
        let y = s.y(x) + row.filter.gradient().dot(&dv);
        let vy = s.variance(x, var) + (dv.transpose() * p * &dv)[(0, 0)];
        let (value, std) = s.value_and_std(y, vy);
        (value.is_finite() && std.is_finite()).then_some((value, std * std))
    }

    /// The scale `cell`'s parameter `parameter` is learned in (`None` for an
    /// unknown row).
    pub fn scale(&self, cell: usize, parameter: usize) -> Option<FloorLog> {
        self.row(cell, parameter).map(|r| r.scale)
    }

    /// The step's residual of a value against its target, `y(value) −
    /// y(target)` in the row's scale (`ln(value/target)` without a floor);
    /// `None` for an unknown row or a value or target ≤ 0.
    pub fn residual(&self, cell: usize, parameter: usize, value: f64, target: f64) -> Option<f64> {
        let s = self.scale(cell, parameter)?;
        (value > 0.0 && target > 0.0).then(|| s.residual(value, target))
    }

    /// The filter's estimate of a value measured as `measured` (value and
    /// variance, unit and unit²) where the row predicted `prediction` (in its
    /// scale, from [`JointArrayTuner::predict`] before the measurement):
    /// their precision-weighted mean, back in the parameter's unit. The
    /// prediction's variance is first scaled by the mean NIS of the row's
    /// updates so far when above 1 (after [`MIN_CHECKS_FOR_ESTIMATE`]
    /// updates): a row whose predictions missed by more than they said is
    /// trusted as far as they came true. `None` for an unknown row, a value
    /// ≤ 0 or a variance that is not finite.
    ///
    /// The measurement alone is noisy at the band's edge (a `w` scan's σ is
    /// about 5 %, half the default band); the prediction carries what the
    /// earlier measurements and the learned rows know about the same cell.
    pub fn estimate(
        &self,
        cell: usize,
        parameter: usize,
        prediction: (f64, f64),
        measured: Measured,
    ) -> Option<f64> {
        let row = self.row(cell, parameter)?;
        let s = row.scale;
        let (x, var) = measured;
        let (yp, vp) = prediction;
        // a row whose predictions missed by more than they said is trusted less
        let vp = match row.checks.nis_mean() {
            Some(nis) if row.checks.count >= MIN_CHECKS_FOR_ESTIMATE => vp * nis.max(1.0),
            _ => vp,
        };
        if !(x > 0.0 && var.is_finite() && var >= 0.0 && yp.is_finite() && vp > 0.0) {
            return None;
        }
        let vy = s.variance(x, var);
        if vy <= 0.0 {
            return Some(x);
        }
        let y = (s.y(x) / vy + yp / vp) / (1.0 / vy + 1.0 / vp);
        Some(s.value(y)).filter(|v| v.is_finite())
    }

    /// Whether the prediction at `voltages_mv` lies inside the band
    /// `target/(1 + tol) ..= target·(1 + tol)` with `sigma` standard
    /// deviations of margin on both sides (`false` without a prediction).
    pub fn predicted_in_band(
        &self,
        cell: usize,
        parameter: usize,
        voltages_mv: &BTreeMap<String, f64>,
        target: f64,
        relative_tolerance: f64,
        sigma: f64,
    ) -> bool {
        let (Some(s), Some((y, var))) = (
            self.scale(cell, parameter),
            self.predict(cell, parameter, voltages_mv),
        ) else {
            return false;
        };
        s.within_band(y, sigma * var.sqrt(), target, relative_tolerance)
    }

    /// A cell measured `values` (per parameter, unit and unit²; `None` where
    /// the fit failed) at `voltages_mv` (array names): each row learns from the
    /// change since its last value. Values ≤ 0 or non-finite are skipped.
    pub fn observe(
        &mut self,
        cell: usize,
        values: &[Option<Measured>],
        voltages_mv: &BTreeMap<String, f64>,
    ) {
        if let Some(f) = self.excitation_flipped.get_mut(cell) {
            *f = !*f;
        }
        for row in self.rows.iter_mut().filter(|r| r.cell == cell) {
            let Some(Some((p, var))) = values.get(row.parameter).copied() else {
                continue;
            };
            if !(p.is_finite() && p > 0.0 && var.is_finite() && var >= 0.0) {
                continue;
            }
            row.explores_left = row.explores_left.saturating_sub(1);
            let y = row.scale.y(p);
            let vy = row.scale.variance(p, var);
            let v: Vec<f64> = row
                .columns
                .iter()
                .map(|&c| voltages_mv.get(&self.gates[c]).copied().unwrap_or(f64::NAN))
                .collect();
            if let Some(c) = row.curvature.as_mut() {
                if v.iter().all(|x| x.is_finite()) {
                    c.anchor_at(&v);
                }
            }
            if let Some((y0, vy0, v0)) = &row.last {
                let dv = row.features(&v) - row.features(v0);
                match row.filter.update(&dv, y - y0, vy + vy0) {
                    Err(_) => self.rejected_updates += 1,
                    Ok(
                        UpdateOutcome::Updated {
                            innovation,
                            innovation_sigma,
                        }
                        | UpdateOutcome::Gated {
                            innovation,
                            innovation_sigma,
                        },
                    ) => {
                        row.checks.add(innovation, innovation_sigma);
                        let (h, factor) = self.persistent_miss;
                        if h > 0.0
                            && innovation_sigma > 0.0
                            && row.misses.observe(innovation / innovation_sigma, h)
                            && row.filter.inflate_covariance(factor).is_ok()
                        {
                            self.persistent_misses += 1;
                        }
                    }
                    Ok(UpdateOutcome::SkippedSmallStep { .. }) => {}
                }
            }
            row.last = Some((y, vy, v));
        }
    }

    /// The log-space Jacobian of every (cell, parameter) row over every
    /// tuning gate (zeros outside the neighbourhoods), rows cell by cell.
    pub fn jacobian(&self) -> DMatrix<f64> {
        let mut j = DMatrix::zeros(self.rows.len(), self.gates.len());
        for (i, r) in self.rows.iter().enumerate() {
            for (&c, &g) in r.columns.iter().zip(r.gradient().iter()) {
                j[(i, c)] = g;
            }
        }
        j
    }

    /// Cell `ci`'s excitation direction over its own gates (columns
    /// `offset..` of `jacobian`): [`null_space_direction`] of its own block,
    /// weighted by its rows' own-gate covariance.
    fn excitation_direction(
        &self,
        ci: usize,
        offset: usize,
        jacobian: &DMatrix<f64>,
        block: &DVector<f64>,
    ) -> Option<DVector<f64>> {
        let n = block.len();
        let rows: Vec<usize> = (0..self.rows.len())
            .filter(|&i| self.rows[i].cell == ci)
            .collect();
        let j_own = DMatrix::from_fn(rows.len(), n, |r, c| jacobian[(rows[r], offset + c)]);
        let mut uncertainty = DMatrix::zeros(n, n);
        for &ri in &rows {
            let row = &self.rows[ri];
            let cov = row.covariance();
            let at: Vec<Option<usize>> = (0..n)
                .map(|g| row.columns.iter().position(|&c| c == offset + g))
                .collect();
            for (a, pa) in at.iter().enumerate() {
                for (b, pb) in at.iter().enumerate() {
                    if let (Some(pa), Some(pb)) = (pa, pb) {
                        uncertainty[(a, b)] += cov[(*pa, *pb)];
                    }
                }
            }
        }
        null_space_direction(&j_own, &uncertainty, block)
    }

    /// `κ·Σ C` over the rows that steer this move (`picked`: row index and
    /// residual), each row's covariance (log space, 1/mV²) placed at its
    /// columns; `None` when `κ = 0`.
    fn step_uncertainty(&self, picked: &[(usize, f64)]) -> Option<DMatrix<f64>> {
        let kappa = self.trust_region_covariance;
        if kappa <= 0.0 {
            return None;
        }
        let n = self.gates.len();
        let mut u = DMatrix::zeros(n, n);
        for &(i, _) in picked {
            let row = &self.rows[i];
            if row.explores_left > 0 {
                continue;
            }
            let cov = row.covariance();
            for (a, &ca) in row.columns.iter().enumerate() {
                for (b, &cb) in row.columns.iter().enumerate() {
                    u[(ca, cb)] += kappa * cov[(a, b)];
                }
            }
        }
        Some(u)
    }

    /// The next move (array gate → absolute mV) from the present values.
    /// `residual[cell][parameter]` is `ln(value/target)` of a cell aimed at
    /// its targets, `Some(0)` for a cell held, `None` where unknown (the
    /// row is left out). `jacobian`: the log-space Jacobian to use (the
    /// filter's [`JointArrayTuner::jacobian`], or the oracle's). Gates that
    /// do not move are left out; steps below 1 µV dropped.
    pub fn plan_move(
        &self,
        residual: &[Vec<Option<f64>>],
        jacobian: &DMatrix<f64>,
        voltages_mv: &BTreeMap<String, f64>,
        limits: &SafetyLimits,
    ) -> BTreeMap<String, f64> {
        let picked: Vec<(usize, f64)> = self
            .rows
            .iter()
            .enumerate()
            .filter_map(|(i, r)| Some((i, residual.get(r.cell)?.get(r.parameter).copied()??)))
            .filter(|(_, d)| d.is_finite())
            .collect();
        let mut out = BTreeMap::new();
        if picked.is_empty() || picked.iter().all(|(_, d)| *d == 0.0) {
            return out;
        }
        let j = DMatrix::from_fn(picked.len(), self.gates.len(), |r, c| {
            jacobian[(picked[r].0, c)]
        });
        let delta = DVector::from_iterator(picked.len(), picked.iter().map(|(_, d)| *d));
        let cfg = SolverConfig {
            max_step_mv: 1e6,
            rule: StepRule::PseudoInverse,
            ..SolverConfig::default()
        };
        let step = newton_step(&j, &delta, &cfg).dv_mv;
        let limited = if self.trust_region {
            let blocks: Vec<(usize, f64)> = self
                .cells
                .iter()
                .map(|c| (c.gates.len(), c.max_step_mv))
                .collect();
            let uncertainty = self.step_uncertainty(&picked);
            block_trust_region_step(&j, &delta, &step, &blocks, uncertainty.as_ref())
        } else {
            None
        };
        let grid = self.grid();
        let mut offset = 0;
        let mut moved: Vec<Vec<f64>> = Vec::with_capacity(self.cells.len());
        for (ci, cell) in self.cells.iter().enumerate() {
            let n = cell.gates.len();
            // the step a cell would take unlimited; it explores only if limited
            let unlimited_norm = step.rows(offset, n).norm();
            let mut block = limited
                .as_ref()
                .unwrap_or(&step)
                .rows(offset, n)
                .clone_owned();
            let norm = block.norm();
            if self.excitation > 0.0 && unlimited_norm > cell.max_step_mv && norm > 0.0 {
                if let Some(e) = self.excitation_direction(ci, offset, jacobian, &block) {
                    let b = self.excitation;
                    let flipped = self.excitation_flipped.get(ci).copied().unwrap_or(false);
                    let sign = if flipped ^ grid.odd(ci) { -1.0 } else { 1.0 };
                    // same length, so the limit below scales it like the plan
                    block = (&block / norm * (1.0 - b * b).sqrt() + e * (b * sign)) * norm;
                }
            }
            let scale = if norm > cell.max_step_mv && norm > 0.0 {
                cell.max_step_mv / norm
            } else {
                1.0
            };
            let mut own = Vec::with_capacity(n);
            for (k, g) in cell.gates.iter().enumerate() {
                let Some(&now) = voltages_mv.get(g) else {
                    own.push(0.0);
                    continue;
                };
                let target = limits.clip(g, now, now + block[k] * scale);
                own.push(target - now);
                if (target - now).abs() > 1e-3 {
                    out.insert(g.clone(), target);
                }
            }
            moved.push(own);
            offset += n;
        }
        // virtual gates: the own move, and the neighbours' moves weighted by
        // the lab's cross-cell calibration
        for (j, cell) in self.cells.iter().enumerate() {
            let Some((comp_gates, matrix)) = &cell.compensation else {
                continue;
            };
            let mut seen = vec![0.0; cell.gates.len()];
            // (cells whose gate lists differ in length see no neighbour term)
            for (k, dv) in moved.iter().enumerate() {
                let w = match grid.distance(j, k) {
                    0 => 1.0,
                    1 => self.neighbour_compensation[0],
                    2 => self.neighbour_compensation[1],
                    _ => 0.0,
                };
                if w != 0.0 && dv.len() == seen.len() {
                    seen.iter_mut().zip(dv).for_each(|(s, d)| *s += w * d);
                }
            }
            compensate(comp_gates, matrix, &seen, voltages_mv, limits, &mut out);
        }
        out
    }

    /// The move that takes cell `cell` back after its evaluation failed:
    /// its tuning gates half-way toward `good` (where it last measured
    /// every parameter), the step capped at the cell's `max_step_mv`
    /// (the single-cell tuner's rule, `tuner::newton::retreat_target`), and its
    /// compensation gates following through its virtual-gate matrix, then
    /// clipped to the limits. Its plungers and sensor are otherwise left
    /// to the line and sensor levels, which re-centre them after the move
    /// (their old voltages are stale: lines and sensor also moved with the
    /// neighbours). Empty if there is nothing to retreat to (within
    /// 0.01 mV, or no such cell). The joint loop's rule with
    /// `ArrayRunSettings::retreat` = `tuning_gates` (not its default:
    /// measured no better for the learned model, docs/array-history.md).
    ///
    /// ```
    /// use std::collections::BTreeMap;
    /// use spintune::safety::SafetyLimits;
    /// use spintune::tuner::array::{CellKnowledge, JointArrayTuner, JointConfig};
    /// let cell = CellKnowledge {
    ///     gates: vec!["c0.N".into(), "c0.T".into()],
    ///     parameters: vec!["t_sr".into(), "w".into()],
    ///     gradient: vec![vec![0.02, 0.0], vec![0.0, 0.02]],
    ///     covariance: vec![vec![vec![1e-6, 0.0], vec![0.0, 1e-6]]; 2],
    ///     process_noise_per_mv: vec![1e-4; 2],
    ///     max_step_mv: 10.0,
    ///     // the plunger follows N with -0.5 mV/mV
    ///     compensation: Some((vec!["c0.PA".into()], vec![vec![-0.5, 0.0]])),
    ///     floors: Vec::new(),
    /// };
    /// let tuner = JointArrayTuner::new(vec![cell], &JointConfig::default(), [0.0, 0.0]).unwrap();
    /// let now = BTreeMap::from([("c0.N".to_string(), -700.0), ("c0.T".into(), -640.0), ("c0.PA".into(), -300.0)]);
    /// // where it last measured: N 4 mV lower, and the plunger elsewhere (the line level moved it since)
    /// let good = BTreeMap::from([("c0.N".to_string(), -704.0), ("c0.T".into(), -640.0), ("c0.PA".into(), -290.0)]);
    /// let no_limits = SafetyLimits::new(&[]); // (a run passes its gates' limits)
    /// let back = tuner.retreat_move(0, &good, &now, &no_limits);
    /// assert_eq!(back["c0.N"], -702.0); // half-way
    /// assert!(!back.contains_key("c0.T")); // did not move
    /// assert_eq!(back["c0.PA"], -299.0); // follows N's retreat, not good's plunger
    /// ```
    pub fn retreat_move(
        &self,
        cell: usize,
        good: &BTreeMap<String, f64>,
        voltages_mv: &BTreeMap<String, f64>,
        limits: &SafetyLimits,
    ) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        let Some(knowledge) = self.cells.get(cell) else {
            return out;
        };
        let (Some(now), Some(to)): (Option<Vec<f64>>, Option<Vec<f64>>) = (
            knowledge
                .gates
                .iter()
                .map(|g| voltages_mv.get(g).copied())
                .collect(),
            knowledge
                .gates
                .iter()
                .map(|g| good.get(g).copied())
                .collect(),
        ) else {
            return out;
        };
        let Some(target) = retreat_target(&now, &to, knowledge.max_step_mv) else {
            return out;
        };
        let mut delta = Vec::with_capacity(now.len());
        for ((g, &at), &t) in knowledge.gates.iter().zip(&now).zip(&target) {
            let back = limits.clip(g, at, t);
            delta.push(back - at);
            if (back - at).abs() > 1e-3 {
                out.insert(g.clone(), back);
            }
        }
        if let Some((comp_gates, matrix)) = &knowledge.compensation {
            compensate(comp_gates, matrix, &delta, voltages_mv, limits, &mut out);
        }
        out
    }
}

/// Virtual gates: each of `comp_gates` moves by its `matrix` row times the
/// tuning move `seen` (mV), clipped to the limits; moves below 1 µV are
/// left out of `out`.
fn compensate(
    comp_gates: &[String],
    matrix: &[Vec<f64>],
    seen: &[f64],
    voltages_mv: &BTreeMap<String, f64>,
    limits: &SafetyLimits,
    out: &mut BTreeMap<String, f64>,
) {
    for (g, row) in comp_gates.iter().zip(matrix) {
        let d: f64 = row.iter().zip(seen).map(|(m, dv)| m * dv).sum();
        if let Some(&now) = voltages_mv.get(g) {
            let target = limits.clip(g, now, now + d);
            if (target - now).abs() > 1e-3 {
                out.insert(g.clone(), target);
            }
        }
    }
}
