//! [`ArrayRun`]: the joint array loop as a sans-IO state machine
//! (invariant 2). It never calls a device: [`ArrayRun::poll`] hands out a
//! **batch** of requests (run "at the same time": scans of cells in
//! different readout groups in parallel, the lab clock charging the
//! longest group) and [`ArrayRun::feed`] takes the batch's answers, in
//! order. Between batches it says when an iteration ended
//! ([`ArrayAction::Iteration`]) and when every cell was measured in band,
//! or it gave up after [`ArrayRunSettings::max_iterations`]
//! ([`ArrayAction::Idle`], until a target changes).
//!
//! # The loop
//! 1. **Initial measurements**: one single-cell [`RunSession`] per cell
//!    (gates renamed `c{k}.…`, `max_iterations = 0`), stepped in parallel,
//!    one request per cell and batch, each through its own session's guard,
//!    in lockstep: a move of a cell's tuning gates waits until no other cell
//!    has a scan pending, so the cells' finite differences move together
//!    (`initial_sent`; the prior's lockstep factor assumes it).
//!    Then every gate is read once and the lab's knowledge of each cell
//!    (learned gradient and covariance, virtual-gate matrix, line Jacobian,
//!    sensing-dot sweep) starts the [`JointArrayTuner`].
//! 2. **Iteration**: `t_sr` and `w` of every cell (one batch; a held cell
//!    that shares its sensor and is predicted in band with margin is
//!    skipped, [`ArrayRunSettings::skip_confident_sigma`]); values with
//!    an error bar wider than the band are not acted on; the filter rows
//!    learn; if every cell is in band the iteration ends there and the run
//!    idles (as it does after [`ArrayRunSettings::max_iterations`]), once
//!    the parameters of cells that just entered their band near its edge
//!    read in band in a second scan ([`ArrayRunSettings::confirm_entry_sigma`]).
//!    Otherwise one joint limited move per cell (cells in band aimed at
//!    their targets like the others, or held with
//!    [`ArrayRunSettings::hold_in_band`]; skipped cells held;
//!    a cell whose evaluation failed retreats half-way to the voltages of
//!    its last good evaluation, [`ArrayRunSettings::retreat`]), then the lower levels of the moved cells,
//!    their neighbours and every uncertain cell: sensing dots swept and
//!    parked on the fitted flank, lines corrected from their forecast when
//!    it puts them beyond [`ArrayRunSettings::precorrect_lines_mv`], then
//!    up to [`ArrayRunSettings::line_rounds`] line scans with a plunger
//!    correction each, at most [`ArrayRunSettings::line_max_step_mv`]
//!    (and a re-park of the cells moved). With
//!    [`ArrayRunSettings::slack_readings`] the cells that wait in a line
//!    round scan `t_sr` and `w` in its batch where their group has the
//!    time, pooled with the next measurement ([`slack`]).
//!
//! The run's voltages are what the instrument answered: every gate is read
//! after the initial measurements, and each accepted set's read-back
//! replaces the set gates (a scan leaves its gates where they were). Moves
//! are clipped to each gate's limits and `max_step_mv` from those voltages
//! ([`SafetyLimits::clip`]); the caller's guard checks them again against
//! the instrument.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

pub use super::array_run_settings::{ArrayRunSettings, Retreat};
use super::flank::FlankModel;
use super::flat_reset::FlatResetWatch;
use super::lagging::LagCount;
use super::search::SearchMemory;
use super::stall::StallWatch;
use crate::config_error::ConfigError;
use crate::description::layout::{CellGrid, Layout};
use crate::fit::uncertainty::References;
use crate::protocol::{GradientReport, IterationRecord, Request, Response, ScanKind, ScanRequest};
use crate::safety::{GateSpec, SafetyLimits};
use crate::session::{RunSession, SessionConfig};
use crate::sim::array::{parameter_name, split_gate};
use crate::tuner::array::{JointArrayTuner, Measured};
use crate::tuner::level_forecast::LevelForecast;
use crate::tuner::{Consistency, InitialGradient, ParameterSearch, TunerConfig, MAX_SEARCH_PROBES};

mod initial;
mod lines;
mod measure;
mod sensors;
pub mod slack;

use lines::line_scan_requests;

/// The array's parameters per cell, in order.
pub const CELL_PARAMETERS: [&str; 2] = ["t_sr", "w"];

/// The scan that measures each of [`CELL_PARAMETERS`], in order.
const CELL_SCANS: [ScanKind; 2] = [ScanKind::ReloadTime, ScanKind::TransitionWidth];

/// Whether cell `cell` mirrors its initial repetition `rep`
/// ([`ArrayRunSettings::staggered_differences`]): repetition 0 (mod 3)
/// nobody, 1 the odd cells, 2 cells 2, 3 (mod 4). Against cell `c`, its
/// nearest neighbours move the same way in repetition 0, the other way in
/// 1 and one each way in 2; its next-nearest the same way in 0 and 1 and
/// the other way in 2.
///
/// ```
/// use spintune::tuner::array_run::staggered_mirror;
/// let pattern = |rep| (0..6).map(|c| staggered_mirror(c, rep)).collect::<Vec<_>>();
/// assert_eq!(pattern(0), [false; 6]);
/// assert_eq!(pattern(1), [false, true, false, true, false, true]);
/// assert_eq!(pattern(2), [false, false, true, true, false, false]);
/// assert_eq!(pattern(3), pattern(0));
/// ```
pub fn staggered_mirror(cell: usize, rep: u32) -> bool {
    match rep % 3 {
        1 => cell % 2 == 1,
        2 => (cell / 2) % 2 == 1,
        _ => false,
    }
}

/// Lines checked against their forecast (two per line scan) before a cell
/// may act on a forecast instead of scanning
/// ([`ArrayRunSettings::line_forecast`]): three scans, so that the scale of
/// its spread ([`Consistency::nis_mean`]) rests on more than one.
pub const MIN_LINE_CHECKS: u64 = 6;

/// Most iterations in a row a cell's scans are skipped
/// ([`ArrayRunSettings::skip_confident_sigma`]): it is measured at least
/// every third iteration.
pub const MAX_SKIPS_IN_A_ROW: u32 = 2;

/// What the driver does next.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayAction {
    /// Run these requests as one batch and [`ArrayRun::feed`] the answers in
    /// order. Polling again without feeding returns the same batch.
    Execute(Vec<Request>),
    /// An iteration ended (the record of its measurement and move).
    Iteration(Box<IterationRecord>),
    /// Every cell was measured in band, or the run gave up
    /// ([`ArrayRunSettings::max_iterations`]): nothing to do until a target
    /// changes.
    Idle,
}

/// Why the run cannot go on.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArrayRunError {
    /// A configuration the core refused.
    #[error("invalid configuration: {0}")]
    Config(#[from] ConfigError),
    /// A cell's initial measurement halted (its session faulted or waits).
    #[error("cell {cell}: initial measurement halted: {message}")]
    Halted {
        /// The cell.
        cell: u32,
        /// What happened.
        message: String,
    },
    /// `feed` without an outstanding batch, or with the wrong number of answers.
    #[error("{0}")]
    Protocol(String),
}

/// The joint loop's per-cell lab knowledge beyond the top level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct CellLower {
    sd_gate: String,
    sd_half_width_mv: f64,
    sd_points: usize,
    line_gates: Vec<String>,
    /// Learned ∂(mu_a, mu_b)/∂(line gates), mV/mV.
    line_jacobian: [[f64; 2]; 2],
    line_max_step_mv: f64,
    references: References,
    /// The lines as a learned function of the neighbourhood's gates
    /// ([`LevelForecast`], centred on the cell's virtual-gate matrix): where
    /// a move took them, so that a far shift is corrected before the scan.
    lines: LevelForecast,
    /// The sensing dot's flank as a learned function of the neighbourhood's
    /// gates (`None`: no sensing-dot level).
    #[serde(default)]
    flank: Option<FlankModel>,
    /// An evaluation of the cell failed since its last sweep (the sensor
    /// may be off its flank: the next park sweeps).
    #[serde(default)]
    failed_since_sweep: bool,
    /// How the cell's line level searches for lines its scans lost (the
    /// single-cell line level's [`ParameterSearch`]; `None`: no search).
    #[serde(default)]
    line_search: Option<ParameterSearch>,
    /// The line search's memory (failures in a row, last seen, probes).
    #[serde(default)]
    search: SearchMemory,
    /// Evaluations of the cell that failed (any scan): a line forecast is
    /// not acted on after one since the last line scan.
    #[serde(default)]
    failed_evaluations: u64,
    /// Every line scan against the forecast for it made just before (both
    /// lines): how honest the forecast's spread is. A forecast acted on
    /// has its variance scaled by the mean NIS when that is above 1.
    #[serde(default)]
    line_checks: Consistency,
    /// A search probe's plunger move not yet sent (mV per line gate).
    #[serde(default)]
    probe_mv: Option<Vec<f64>>,
    /// The cell's last line scan lost a line, or found one farther from its
    /// centre than [`ArrayRunSettings::verify_lines_above_mv`]: its lines
    /// are scanned again before the run stops.
    #[serde(default)]
    lines_unverified: bool,
}

impl CellLower {
    /// A cell with no sensing-dot or line level yet (filled in from its
    /// tuner's levels), evaluating its scans with `references`.
    fn empty(references: References) -> Self {
        Self {
            sd_gate: String::new(),
            sd_half_width_mv: 0.0,
            sd_points: 0,
            line_gates: Vec::new(),
            line_jacobian: [[0.0; 2]; 2],
            line_max_step_mv: 0.0,
            references,
            lines: LevelForecast::new(Vec::new(), 2, 0.1, Vec::new()),
            flank: None,
            failed_since_sweep: false,
            line_search: None,
            search: SearchMemory::default(),
            probe_mv: None,
            lines_unverified: false,
            failed_evaluations: 0,
            line_checks: Consistency::default(),
        }
    }

    /// Whether the cell's lines count as lost by its line search's rule
    /// (the failures in a row that start a search, a search under way, or
    /// one that gave up, until a scan finds both lines again). Its lines'
    /// forecast then starts from a scan made before they were lost, where
    /// they no longer are: nothing acts on it. A single failed fit (noise)
    /// does not count.
    fn lines_missing(&self) -> bool {
        self.line_search.as_ref().is_some_and(|cfg| {
            self.search.active.is_some()
                || self.search.exhausted
                || self.search.lost_in_a_row >= cfg.after_failures
        })
    }

    /// The cell's line gates at `v`, mV (their order; a missing gate as 0).
    fn line_mv(&self, v: &BTreeMap<String, f64>) -> Vec<f64> {
        self.line_gates
            .iter()
            .map(|g| v.get(g).copied().unwrap_or(0.0))
            .collect()
    }
}

/// After a batch of sensor sets: what comes next.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum AfterPark {
    /// The line pre-correction, then the first line round, of these cells.
    Lines(Vec<u32>),
    /// Line round `round` (0-based) of these cells.
    LineRound(Vec<u32>, u32),
    /// The confirming scans of [`Step::Confirm`].
    Confirm(Vec<(u32, usize)>),
}

/// Where the loop is; what the outstanding batch (if any) is for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Step {
    /// The cells' initial measurements (their sessions).
    Initial,
    /// Every gate read once after them.
    ReadAll,
    /// `t_sr` and `w` of every cell.
    Measure,
    /// Every cell measured in band: these parameters (cell, index into
    /// [`CELL_PARAMETERS`]) of cells that just entered their band near its
    /// edge are scanned once more before the run stops
    /// ([`ArrayRunSettings::confirm_entry_sigma`]).
    Confirm(Vec<(u32, usize)>),
    /// Every cell measured in band: the line scans of these cells, whose
    /// last line scan found their lines off
    /// ([`ArrayRunSettings::verify_lines_above_mv`]), then the scans of
    /// [`Step::Confirm`] (these pending).
    VerifyLines(Vec<u32>, Vec<(u32, usize)>),
    /// The corrections of the cells [`Step::VerifyLines`] found off ((cell,
    /// lines mV); the cells that move), then these confirming scans.
    VerifySet(Vec<(u32, [f64; 2])>, Vec<u32>, Vec<(u32, usize)>),
    /// The oracle's true Jacobian.
    Oracle,
    /// Joint move `m` (0-based).
    Move(u32),
    /// Park the sensors of these cells (sweep or predict), then `next`.
    ParkSweep(Vec<u32>, AfterPark),
    /// Sensor sweeps of these cells are out; the flanks (gate, mV) of the
    /// cells parked from their prediction; then `next`.
    Sweeping(Vec<u32>, Vec<(String, f64)>, AfterPark),
    /// Sensor sets to these flanks (gate, mV), from the voltages when the
    /// batch is handed out, then `next`.
    ParkSet(Vec<(String, f64)>, AfterPark),
    /// Line corrections from the forecast, then the first line round.
    Precorrect(Vec<u32>),
    /// The corrections of [`Step::Precorrect`]'s cells (first) are out:
    /// the cells that scan, and those that act on their forecast instead
    /// (cell, forecast lines as (mV, variance mV²)).
    Precorrecting(Vec<u32>, LinePlan),
    /// Line scans of these cells, round `round`.
    LineScan(Vec<u32>, u32),
    /// Line corrections of the cells that moved in round `round`.
    /// (cell, lines mV) to correct, from the voltages when the batch is
    /// handed out; the cells that move; the round.
    LineSet(Vec<(u32, [f64; 2])>, Vec<u32>, u32),
    /// The iteration is over: hand out its record.
    Boundary,
    /// Every cell in band: nothing to do until a target changes.
    Idle,
}

/// This iteration's measurement and what follows from it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
struct Scratch {
    /// Per cell: ln(value/target) of a cell out of band, 0 in band, `None` unknown.
    residual: Vec<Vec<Option<f64>>>,
    /// Per cell: a value is missing (measured, not skipped): it retreats.
    failed: Vec<bool>,
    /// Per cell: a value is missing or its error bar wider than its band:
    /// its lower levels re-tune ([`Retreat::TuningGatesWhenUncertain`]:
    /// it retreats too).
    unsure: Vec<bool>,
    /// The Jacobian used for this iteration's moves (log space, rows cell by cell).
    jacobian: Option<DMatrix<f64>>,
    moved_cells: Vec<u32>,
    /// Cells corrected from their line forecast before this line round:
    /// their sensors are parked again with the cells that move after it.
    #[serde(default)]
    forecast_moved: Vec<u32>,
    /// Voltages before the present move, mV.
    before_move: BTreeMap<String, f64>,
    /// Voltages before the present line round's corrections, mV.
    #[serde(default)]
    before_lines: BTreeMap<String, f64>,
    /// Cells whose lines [`Step::VerifyLines`] found off and corrected:
    /// their confirming scans replace this iteration's readings.
    #[serde(default)]
    lines_verified: Vec<u32>,
    /// The confirming round under way (0-based) and, per parameter
    /// rechecked so far (cell, index), its readings pooled
    /// ([`ArrayRunSettings::pool_confirmations`]).
    #[serde(default)]
    confirm_round: u32,
    #[serde(default)]
    pooled: Vec<((u32, usize), Measured)>,
    record: Option<Box<IterationRecord>>,
}

/// A park's plan: the cells that sweep, and the sensing gates parked on
/// their predicted flank (gate, mV).
type Parks = (Vec<u32>, Vec<(String, f64)>);

/// A line round's outcome: (cell, its lines in mV) to correct, and the
/// cells that move.
type LineCorrections = (Vec<(u32, [f64; 2])>, Vec<u32>);

/// Before the line scan: the cells that scan, and the cells that act on
/// their lines' forecast instead ((mV, variance mV²) per line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LinePlan {
    scan: Vec<u32>,
    forecast: Vec<(u32, [Measured; 2])>,
}

/// The joint state after the initial measurements.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Joint {
    tuner: JointArrayTuner,
    lower: Vec<CellLower>,
    /// Per cell: its gates' voltages at its last evaluation that worked, mV.
    last_good: Vec<BTreeMap<String, f64>>,
    /// Per cell: its last measurement was in band.
    #[serde(default)]
    in_band: Vec<bool>,
    /// Per cell: the present measurement skips its scans.
    #[serde(default)]
    skip: Vec<bool>,
    /// Per cell: measurements skipped in a row.
    #[serde(default)]
    skips_in_a_row: Vec<u32>,
    /// Per cell and parameter: its stall watch
    /// ([`ArrayRunSettings::reset_stalled_row_after`]).
    #[serde(default)]
    stalls: Vec<[StallWatch; 2]>,
    /// Per cell and parameter: its flat-row resets
    /// ([`ArrayRunSettings::flat_reset_refuted_sigma`]).
    #[serde(default)]
    flat_resets: Vec<[FlatResetWatch; 2]>,
    /// Per cell and parameter: measurements in a row out of band on one
    /// side ([`ArrayRunSettings::repeat_lagging_scans`]).
    #[serde(default)]
    lags: Vec<[LagCount; 2]>,
    /// The extra scans (cell, index into [`CELL_PARAMETERS`]) of the
    /// measurement under way, in the order of its batch after every
    /// measured cell's two.
    #[serde(default)]
    repeats: Vec<(u32, usize)>,
    /// The lab time per scan seen so far ([`ArrayRunSettings::slack_readings`]).
    #[serde(default)]
    clock: slack::ScanClock,
    /// The cells scanning `t_sr` and `w` in the outstanding line round's
    /// slack, after its line scans.
    #[serde(default)]
    slack: Vec<u32>,
    /// Readings taken in this iteration's line rounds' slack, for the next
    /// measurement.
    #[serde(default)]
    early: Vec<slack::EarlyReading>,
}

/// The joint array loop (module docs). Serializable as a whole.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArrayRun {
    settings: ArrayRunSettings,
    cross_calibration: [f64; 2],
    oracle: bool,
    limits: SafetyLimits,
    gates: Vec<GateSpec>,
    gate_names: Vec<String>,
    /// Per cell: the initial measurement's session (`None` once done).
    sessions: Vec<Option<RunSession>>,
    /// Per cell: the request its session handed out (initial phase).
    session_pending: Vec<Option<Request>>,
    /// Failed evaluations of the initial sessions, per cell, when they ended.
    initial_failed: Vec<u64>,
    targets: Vec<(f64, f64)>,
    joint: Option<Joint>,
    /// The instrument's voltages as answered, mV.
    voltages_mv: BTreeMap<String, f64>,
    step: Step,
    scratch: Scratch,
    outstanding: Option<Vec<Request>>,
    iteration: u64,
    /// Iterations since the start or the last target change.
    #[serde(default)]
    iterations_since_change: u64,
    /// Per cell: its targets were set since the run last stopped with every
    /// cell in band (all cells at the start). A cell that is not is a
    /// bystander of the present change
    /// ([`ArrayRunSettings::confirm_bystander_sigma`]; next to a changed
    /// cell, a disturbed one: [`ArrayRunSettings::disturbed_margin_sigma`]).
    /// Empty (a checkpoint
    /// from before this field): every cell counts as changed.
    #[serde(default)]
    changed_since_stop: Vec<bool>,
    /// Per cell: its readout group (empty: one sensor per cell).
    #[serde(default)]
    readout_group: Vec<usize>,
    /// Where the cells sit (which are neighbours; a checkpoint from before
    /// this field: a chain). Checked against the number of cells by
    /// [`ArrayRun::set_grid`].
    #[serde(default)]
    layout: Layout,
    lab_seconds: f64,
    failed_fits: u64,
    measurements: u64,
    /// Per cell: the lead-transition widths its initial measurement's
    /// scans gave (mV, standard error), at most
    /// [`thermal_floor::MAX_LEAD_WIDTHS`](crate::tuner::thermal_floor::MAX_LEAD_WIDTHS): the thermal floor of its `w`.
    #[serde(default)]
    lead_widths_mv: Vec<Vec<(f64, f64)>>,
}

impl ArrayRun {
    /// A run over `gates` (every gate of the array, with limits) whose cell
    /// `k` starts with `cells[k]` (the recommended single-cell tuner with the
    /// cell's gate names; its top level's targets are the cell's first
    /// targets). `cross_calibration`: the lab's cross-cell virtual-gate
    /// calibration `λ̂` (nearest, next). `oracle`: ask the true Jacobian each
    /// iteration (simulator only).
    pub fn new(
        cells: Vec<TunerConfig>,
        gates: &[GateSpec],
        settings: ArrayRunSettings,
        cross_calibration: [f64; 2],
        oracle: bool,
    ) -> Result<Self, ArrayRunError> {
        settings.validate()?;
        super::array::check_cross_calibration(cross_calibration)?;
        if cells.is_empty() || cells.len() > crate::sim::array::MAX_CELLS as usize {
            return Err(ConfigError::new(
                "cells",
                format!(
                    "{} cells (1..={})",
                    cells.len(),
                    crate::sim::array::MAX_CELLS
                ),
            )
            .into());
        }
        let mut sessions = Vec::with_capacity(cells.len());
        let mut targets = Vec::with_capacity(cells.len());
        for (k, mut t) in cells.into_iter().enumerate() {
            let top = &t.top().parameters;
            let target = |name: &str| {
                top.iter()
                    .find(|p| p.name == name)
                    .and_then(|p| p.target)
                    .unwrap_or(f64::NAN)
            };
            targets.push((target("t_sr"), target("w")));
            t.max_iterations = Some(0);
            if let InitialGradient::FiniteDifference {
                central,
                step_mv,
                repetitions,
                mirrored,
                ..
            } = &mut t.top_mut().initial_gradient
            {
                *central = settings.central_differences;
                if let Some(h) = settings.finite_difference_step_mv {
                    *step_mv = step_mv.min(h);
                }
                if settings.staggered_differences {
                    *repetitions = (*repetitions).max(2);
                    *mirrored = (0..*repetitions).map(|r| staggered_mirror(k, r)).collect();
                }
            }
            let session = RunSession::new(t, SessionConfig::default())
                .map_err(|e| e.within(&format!("cells[{k}]")))?;
            sessions.push(Some(session));
        }
        let n = sessions.len();
        Ok(Self {
            settings,
            cross_calibration,
            oracle,
            limits: SafetyLimits::new(gates),
            gates: gates.to_vec(),
            gate_names: gates.iter().map(|g| g.name.clone()).collect(),
            sessions,
            session_pending: vec![None; n],
            initial_failed: vec![0; n],
            targets,
            joint: None,
            voltages_mv: BTreeMap::new(),
            step: Step::Initial,
            scratch: Scratch::default(),
            outstanding: None,
            iteration: 0,
            iterations_since_change: 0,
            changed_since_stop: vec![true; n],
            readout_group: Vec::new(),
            layout: Layout::Chain,
            lab_seconds: 0.0,
            failed_fits: 0,
            measurements: 0,
            lead_widths_mv: vec![Vec::new(); n],
        })
    }

    /// Set cell `cell`'s targets `(t_sr ns, w µV)`; an idle run starts again.
    /// Applied at the next measurement's evaluation.
    pub fn set_targets(&mut self, cell: usize, targets: (f64, f64)) -> Result<(), ArrayRunError> {
        let (t, w) = targets;
        if !(t.is_finite() && t > 0.0 && w.is_finite() && w > 0.0) {
            return Err(ConfigError::new(
                format!("targets[{cell}]"),
                format!("({t} ns, {w} µV): both must be finite and positive"),
            )
            .into());
        }
        let slot = self.targets.get_mut(cell).ok_or_else(|| {
            ArrayRunError::from(ConfigError::new(
                "cell",
                format!("{cell} outside 0..{}", self.sessions.len()),
            ))
        })?;
        *slot = targets;
        self.iterations_since_change = 0;
        if let Some(c) = self.changed_since_stop.get_mut(cell) {
            *c = true;
        }
        // measured in band (or stalled) against the old targets says nothing now
        if let Some(j) = self.joint.as_mut() {
            if let Some(b) = j.in_band.get_mut(cell) {
                *b = false;
            }
            if let Some(s) = j.stalls.get_mut(cell) {
                *s = Default::default();
            }
            if let Some(f) = j.flat_resets.get_mut(cell) {
                *f = Default::default();
            }
            if let Some(l) = j.lags.get_mut(cell) {
                *l = Default::default();
            }
        }
        if self.step == Step::Idle {
            self.step = Step::Measure;
        }
        Ok(())
    }

    /// The cells that share a sensor readout (every cell in one group,
    /// checked by the caller's config; `None`: one sensor per cell). Only
    /// cells that share their group have their scans skipped
    /// ([`ArrayRunSettings::skip_confident_sigma`]).
    pub fn set_readout_groups(&mut self, groups: Option<&[Vec<u32>]>) {
        self.readout_group = vec![usize::MAX; self.sessions.len()];
        match groups {
            Some(groups) => {
                for (i, g) in groups.iter().enumerate() {
                    for &c in g {
                        if let Some(slot) = self.readout_group.get_mut(c as usize) {
                            *slot = i;
                        }
                    }
                }
            }
            None => self.readout_group.clear(),
        }
    }

    /// Place the cells on `grid` (default: a chain), which decides which
    /// cells are neighbours: the joint tuner's neighbourhoods and priors,
    /// the lines and sensors re-checked after a move. Before the first
    /// batch only: `Err` once the joint tuner is built, or for a grid of
    /// another number of cells.
    pub fn set_grid(&mut self, grid: CellGrid) -> Result<(), ArrayRunError> {
        if grid.cells() != self.sessions.len() {
            return Err(ConfigError::new(
                "layout",
                format!(
                    "a grid of {} cells for {} cells",
                    grid.cells(),
                    self.sessions.len()
                ),
            )
            .into());
        }
        if self.joint.is_some() || self.outstanding.is_some() {
            return Err(ArrayRunError::Protocol(
                "the layout is set before the run starts".into(),
            ));
        }
        if grid.layout() == Layout::Ladder && self.settings.staggered_differences {
            return Err(ConfigError::new(
                "tuning.staggered_differences",
                "the mirrored initial repetitions are laid out for a chain; a ladder runs without them",
            )
            .into());
        }
        self.layout = grid.layout();
        Ok(())
    }

    /// The cells on their grid ([`ArrayRun::set_grid`]).
    pub fn grid(&self) -> CellGrid {
        let n = self.sessions.len();
        CellGrid::or_chain(self.layout, n)
    }

    /// Whether cell `c` shares its readout group with another cell.
    fn shares_readout(&self, c: usize) -> bool {
        let Some(&g) = self.readout_group.get(c) else {
            return false;
        };
        g != usize::MAX
            && self
                .readout_group
                .iter()
                .enumerate()
                .any(|(o, &h)| o != c && h == g)
    }

    /// The cells whose scans this measurement skips: sharing their readout,
    /// measured in band last, skipped fewer than [`MAX_SKIPS_IN_A_ROW`] times
    /// in a row, and both parameters predicted in band with
    /// `skip_confident_sigma` σ of margin at the present voltages.
    fn plan_skips(&self) -> Vec<bool> {
        let k = self.sessions.len();
        let (Some(sigma), Some(joint)) = (self.settings.skip_confident_sigma, &self.joint) else {
            return vec![false; k];
        };
        let band = self.settings.relative_tolerance;
        (0..k)
            .map(|c| {
                self.shares_readout(c)
                    && joint.in_band.get(c).copied().unwrap_or(false)
                    && joint.skips_in_a_row.get(c).copied().unwrap_or(0) < MAX_SKIPS_IN_A_ROW
                    && (0..CELL_PARAMETERS.len()).all(|p| {
                        let target = [self.targets[c].0, self.targets[c].1][p];
                        joint
                            .tuner
                            .predicted_in_band(c, p, &self.voltages_mv, target, band, sigma)
                    })
            })
            .collect()
    }

    /// Every cell's targets `(t_sr ns, w µV)`.
    pub fn targets(&self) -> &[(f64, f64)] {
        &self.targets
    }

    /// Lab time since the start as the batches' answers reported it, s.
    pub fn lab_seconds(&self) -> f64 {
        self.lab_seconds
    }

    /// Failed or rejected evaluations: the initial measurements', the
    /// loop's failed fits and the filter's rejected updates.
    pub fn failed_evaluations(&self) -> u64 {
        let initial: u64 = self
            .sessions
            .iter()
            .zip(&self.initial_failed)
            .map(|(s, f)| s.as_ref().map_or(*f, |s| s.tuner().failed_evaluations()))
            .sum();
        initial + self.failed_fits + self.joint.as_ref().map_or(0, |j| j.tuner.rejected_updates)
    }

    /// The joint tuner, once the initial measurements are done.
    pub fn tuner(&self) -> Option<&JointArrayTuner> {
        self.joint.as_ref().map(|j| &j.tuner)
    }

    /// Every cell's line scans checked against the lines' forecast made
    /// just before each (both lines; normalised innovations): how honest
    /// the forecast's spread is ([`ArrayRunSettings::line_forecast`] acts
    /// on it with its variance scaled by a cell's own mean NIS above 1).
    pub fn line_forecast_checks(&self) -> Consistency {
        let mut all = Consistency::default();
        for l in self.joint.iter().flat_map(|j| &j.lower) {
            all.merge(&l.line_checks);
        }
        all
    }

    /// The next thing to do.
    pub fn poll(&mut self) -> Result<ArrayAction, ArrayRunError> {
        loop {
            if let Some(b) = &self.outstanding {
                return Ok(ArrayAction::Execute(b.clone()));
            }
            if let Some(batch) = self.next_batch()? {
                if batch.is_empty() {
                    continue;
                }
                self.outstanding = Some(batch.clone());
                return Ok(ArrayAction::Execute(batch));
            }
            match self.step {
                Step::Boundary => {
                    let tuned = self.scratch.record.as_ref().is_some_and(|r| r.tuned);
                    self.iterations_since_change += 1;
                    let given_up = self
                        .settings
                        .max_iterations
                        .is_some_and(|m| self.iterations_since_change >= u64::from(m));
                    if tuned {
                        self.changed_since_stop.iter_mut().for_each(|c| *c = false);
                    }
                    self.step = if tuned || given_up {
                        Step::Idle
                    } else {
                        Step::Measure
                    };
                    let mut record = self.scratch.record.take().ok_or_else(|| {
                        ArrayRunError::Protocol("an iteration ended without its record".into())
                    })?;
                    self.complete(&mut record);
                    self.iteration += 1;
                    return Ok(ArrayAction::Iteration(record));
                }
                Step::Idle => return Ok(ArrayAction::Idle),
                _ => {}
            }
        }
    }

    /// The record at the iteration's end: the filter rows after this
    /// iteration's update (log space, 1/mV, over every tuning gate, zero
    /// outside a row's neighbourhood) and the step its moves made, mV.
    fn complete(&self, record: &mut IterationRecord) {
        let Some(joint) = &self.joint else {
            return;
        };
        let gates = joint.tuner.gates();
        let j = joint.tuner.jacobian();
        record.gradients = (0..j.nrows())
            .map(|r| GradientReport {
                parameter: parameter_name((r / 2) as u32, CELL_PARAMETERS[r % 2]),
                unit: "1/mV".into(),
                gradient: j.row(r).iter().copied().collect(),
                covariance: None,
            })
            .collect();
        record.step_mv = gates
            .iter()
            .map(|g| {
                let now = self.voltages_mv.get(g).copied().unwrap_or(0.0);
                now - record.voltages_mv.get(g).copied().unwrap_or(now)
            })
            .collect();
        record.lab_seconds = self.lab_seconds;
        record.failed_evaluations = self.failed_evaluations();
    }

    /// The batch of the present step (`Some(empty)`: nothing to send, step
    /// on; `None`: the step hands out no batch).
    fn next_batch(&mut self) -> Result<Option<Vec<Request>>, ArrayRunError> {
        Ok(Some(match self.step.clone() {
            Step::Initial => {
                for k in 0..self.sessions.len() {
                    self.step_session(k)?;
                }
                let sent = self.initial_sent();
                let batch: Vec<Request> = self
                    .session_pending
                    .iter()
                    .zip(&sent)
                    .filter(|(_, &s)| s)
                    .filter_map(|(r, _)| r.clone())
                    .collect();
                if batch.is_empty() {
                    self.step = Step::ReadAll;
                    vec![Request::ReadVoltages {
                        gates: self.gate_names.clone(),
                    }]
                } else {
                    batch
                }
            }
            Step::ReadAll => vec![Request::ReadVoltages {
                gates: self.gate_names.clone(),
            }],
            Step::Measure => {
                let mut skip = self.plan_skips();
                // (never an empty measurement: it would never be answered)
                if skip.iter().all(|&s| s) {
                    skip.iter_mut().for_each(|s| *s = false);
                }
                let repeats = self.lagging_repeats(&skip);
                if let Some(j) = self.joint.as_mut() {
                    j.skip = skip.clone();
                    j.repeats = repeats.clone();
                }
                let scan = |c: u32, kind: ScanKind| Request::Measure {
                    scan: ScanRequest {
                        kind,
                        sweep: None,
                        cell: Some(c),
                    },
                };
                (0..self.sessions.len() as u32)
                    .filter(|&c| !skip[c as usize])
                    .flat_map(|c| CELL_SCANS.map(|kind| scan(c, kind)))
                    .chain(repeats.iter().map(|&(c, p)| scan(c, CELL_SCANS[p])))
                    .collect()
            }
            Step::Confirm(pending) => pending
                .iter()
                .map(|&(c, p)| Request::Measure {
                    scan: ScanRequest {
                        kind: CELL_SCANS[p],
                        sweep: None,
                        cell: Some(c),
                    },
                })
                .collect(),
            Step::VerifyLines(cells, _) => line_scan_requests(&cells),
            Step::VerifySet(lines, moved, pending) => {
                let sets = self.line_set_requests(self.joint()?, &lines, &moved);
                if sets.is_empty() {
                    self.step = Step::ParkSweep(moved, AfterPark::Confirm(pending));
                }
                sets
            }
            Step::Oracle => {
                let joint = self.joint()?;
                let parameters = (0..joint.tuner.cells().len() as u32)
                    .flat_map(|c| CELL_PARAMETERS.map(|p| parameter_name(c, p)))
                    .collect();
                vec![Request::TrueJacobian {
                    gates: joint.tuner.gates().to_vec(),
                    parameters,
                }]
            }
            Step::Move(m) => {
                let batch = self.plan_moves(m)?;
                if batch.is_empty() {
                    self.after_moves()?;
                }
                batch
            }
            Step::ParkSweep(cells, next) => {
                // (a cell without a sensing-dot level has nothing to park)
                let joint = self.joint()?;
                let cells: Vec<u32> = cells
                    .into_iter()
                    .filter(|&c| !joint.lower[c as usize].sd_gate.is_empty())
                    .collect();
                if cells.is_empty() {
                    self.step = Self::after_park(next);
                    Vec::new()
                } else {
                    let (sweep, predicted) = self.plan_parks(&cells)?;
                    if sweep.is_empty() {
                        self.step = Step::ParkSet(predicted, next);
                        Vec::new()
                    } else {
                        let sweeps = self.sensor_sweeps(&sweep)?;
                        self.step = Step::Sweeping(sweep, predicted, next);
                        sweeps
                    }
                }
            }
            Step::Sweeping(cells, predicted, next) => {
                // the sweeps' batch was dropped unanswered (a read-back moved
                // the gates): plan the park of every one of its cells again
                let mut all = cells;
                all.extend(predicted.iter().filter_map(|(g, _)| Some(split_gate(g)?.0)));
                all.sort_unstable();
                all.dedup();
                self.step = Step::ParkSweep(all, next);
                Vec::new()
            }
            Step::ParkSet(flanks, next) => {
                if flanks.is_empty() {
                    self.step = Self::after_park(next);
                }
                flanks
                    .iter()
                    .map(|(gate, flank)| {
                        let now = self.voltages_mv.get(gate).copied().unwrap_or(*flank);
                        let to = self.limits.clip(gate, now, *flank);
                        Request::SetVoltages {
                            voltages_mv: [(gate.clone(), to)].into(),
                        }
                    })
                    .collect()
            }
            Step::Precorrect(cells) => {
                let (sets, plan) = self.plan_lines(&cells)?;
                if sets.is_empty() {
                    self.lines_planned(plan);
                } else {
                    self.step = Step::Precorrecting(cells, plan);
                }
                sets
            }
            Step::Precorrecting(cells, _) => {
                // the corrections' batch was dropped unanswered (a read-back
                // moved the gates): plan them again
                self.step = Step::Precorrect(cells);
                Vec::new()
            }
            Step::LineScan(cells, round) => {
                // (a cell without a line level has no lines to scan)
                let joint = self.joint()?;
                // (beyond the configured rounds, only a searching cell scans:
                // its probe is looked at in the iteration that made it)
                let extra = round >= self.settings.line_rounds;
                let cells: Vec<u32> = cells
                    .into_iter()
                    .filter(|&c| {
                        let l = &joint.lower[c as usize];
                        l.line_gates.len() == 2 && (!extra || l.search.active.is_some())
                    })
                    .collect();
                self.step = Step::LineScan(cells.clone(), round);
                if cells.is_empty() || round >= self.settings.line_rounds + MAX_SEARCH_PROBES {
                    self.step = Step::Boundary;
                    Vec::new()
                } else {
                    let slack = self.plan_slack(&cells, round);
                    if let Some(j) = self.joint.as_mut() {
                        j.slack = slack.clone();
                    }
                    let mut batch = line_scan_requests(&cells);
                    batch.extend(slack.iter().flat_map(|&c| {
                        CELL_SCANS.map(|kind| Request::Measure {
                            scan: ScanRequest {
                                kind,
                                sweep: None,
                                cell: Some(c),
                            },
                        })
                    }));
                    batch
                }
            }
            Step::LineSet(lines, moved, round) => {
                let sets = self.line_set_requests(self.joint()?, &lines, &moved);
                if sets.is_empty() {
                    self.step =
                        Step::ParkSweep(moved.clone(), AfterPark::LineRound(moved, round + 1));
                }
                self.scratch.before_lines = self.voltages_mv.clone();
                sets
            }
            Step::Boundary | Step::Idle => return Ok(None),
        }))
    }

    fn after_park(next: AfterPark) -> Step {
        match next {
            AfterPark::Lines(cells) => Step::Precorrect(cells),
            AfterPark::LineRound(cells, round) => Step::LineScan(cells, round),
            AfterPark::Confirm(pending) => Step::Confirm(pending),
        }
    }

    /// Answer the outstanding batch, in order.
    pub fn feed(&mut self, answers: Vec<Response>, lab_seconds: f64) -> Result<(), ArrayRunError> {
        let batch = self
            .outstanding
            .take()
            .ok_or_else(|| ArrayRunError::Protocol("no batch is outstanding".into()))?;
        if answers.len() != batch.len() {
            let message = format!("{} answers to a batch of {}", answers.len(), batch.len());
            self.outstanding = Some(batch);
            return Err(ArrayRunError::Protocol(message));
        }
        if lab_seconds.is_finite() && lab_seconds > 0.0 {
            self.lab_seconds += lab_seconds;
        }
        self.measurements += batch
            .iter()
            .filter(|r| matches!(r, Request::Measure { .. }))
            .count() as u64;
        // every accepted set's read-back is where the gates are now
        for (r, a) in batch.iter().zip(&answers) {
            if let (Request::SetVoltages { .. }, Response::VoltagesSet { voltages_mv, .. }) = (r, a)
            {
                self.voltages_mv
                    .extend(voltages_mv.iter().map(|(g, v)| (g.clone(), *v)));
            }
        }
        match self.step.clone() {
            Step::Initial => self.feed_sessions(&batch, answers)?,
            Step::ReadAll => {
                if let Some(Response::VoltagesRead { voltages_mv, .. }) = answers.first() {
                    self.voltages_mv = voltages_mv.clone();
                    self.start_joint()?;
                    self.step = Step::Measure;
                } else {
                    return Err(ArrayRunError::Protocol(format!(
                        "reading every gate was answered by {:?}",
                        answers.first()
                    )));
                }
            }
            Step::Measure => {
                self.measure_timed(lab_seconds);
                self.evaluate_measurement(&answers)?
            }
            Step::Confirm(pending) => self.confirm_entries(&pending, &answers)?,
            Step::VerifyLines(cells, pending) => self.lines_verified(&cells, pending, &answers)?,
            Step::VerifySet(_, moved, pending) => {
                if let Some(joint) = self.joint.as_mut() {
                    joint.lower.iter_mut().for_each(|l| l.probe_mv = None);
                }
                self.step = Step::ParkSweep(moved, AfterPark::Confirm(pending));
            }
            Step::Oracle => {
                let joint = self.joint()?;
                let cols = joint.tuner.gates().len();
                self.scratch.jacobian = match answers.first() {
                    Some(Response::TrueJacobian { values, jacobian }) => {
                        let rows = jacobian.len();
                        Some(DMatrix::from_fn(rows, cols, |i, j| {
                            jacobian[i][j] / values[i]
                        }))
                    }
                    _ => Some(joint.tuner.jacobian()),
                };
                self.step = Step::Move(0);
            }
            Step::Move(m) => self.moved(m)?,
            Step::Sweeping(cells, predicted, next) => {
                let mut flanks = self.sensor_flanks(&cells, &answers)?;
                flanks.extend(predicted);
                self.step = Step::ParkSet(flanks, next);
            }
            Step::ParkSweep(..) => {
                return Err(ArrayRunError::Protocol(
                    "a park answered before its sweeps were planned".into(),
                ))
            }
            Step::ParkSet(_, next) => self.step = Self::after_park(next),
            Step::Precorrecting(_, plan) => self.lines_planned(plan),
            Step::Precorrect(_) => {
                return Err(ArrayRunError::Protocol(
                    "line corrections answered before they were planned".into(),
                ))
            }
            Step::LineScan(cells, round) => {
                let (answers, extra) = answers.split_at(cells.len().min(answers.len()));
                self.slack_answered(&cells, extra, lab_seconds);
                let (lines, mut moved) = self.line_corrections(&cells, answers)?;
                for c in std::mem::take(&mut self.scratch.forecast_moved) {
                    if !moved.contains(&c) {
                        moved.push(c);
                    }
                }
                self.step = Step::LineSet(lines, moved, round);
            }
            Step::LineSet(lines, moved, round) => {
                if self.settings.retreat == Retreat::EveryGateLinesKept {
                    self.keep_line_corrections(&lines);
                }
                if let Some(joint) = self.joint.as_mut() {
                    joint.lower.iter_mut().for_each(|l| l.probe_mv = None);
                }
                self.step = Step::ParkSweep(moved.clone(), AfterPark::LineRound(moved, round + 1));
            }
            Step::Boundary | Step::Idle => {
                return Err(ArrayRunError::Protocol("no batch is outstanding".into()))
            }
        }
        Ok(())
    }

    fn joint(&self) -> Result<&Joint, ArrayRunError> {
        self.joint
            .as_ref()
            .ok_or_else(|| ArrayRunError::Protocol("the initial measurements are not done".into()))
    }

    /// Cell `c`'s gates at the present voltages, mV.
    fn cell_voltages(&self, c: usize) -> BTreeMap<String, f64> {
        let prefix = format!("c{c}.");
        self.voltages_mv
            .iter()
            .filter(|(g, _)| g.starts_with(&prefix))
            .map(|(g, mv)| (g.clone(), *mv))
            .collect()
    }

    /// Joint move `m`: one set per cell (the first move also retreats the
    /// cells whose evaluation failed, [`ArrayRunSettings::retreat`]).
    fn plan_moves(&mut self, m: u32) -> Result<Vec<Request>, ArrayRunError> {
        let joint = self.joint()?;
        let now = self.voltages_mv.clone();
        let jacobian = self
            .scratch
            .jacobian
            .clone()
            .unwrap_or_else(|| joint.tuner.jacobian());
        let mut moves =
            joint
                .tuner
                .plan_move(&self.scratch.residual, &jacobian, &now, &self.limits);
        if m == 0 {
            for (c, good) in joint.last_good.iter().enumerate() {
                let rule = self.settings.retreat;
                let trigger = match rule {
                    Retreat::TuningGatesWhenUncertain => &self.scratch.unsure,
                    _ => &self.scratch.failed,
                };
                if !trigger.get(c).copied().unwrap_or(false) {
                    continue;
                }
                let prefix = format!("c{c}.");
                moves.retain(|g, _| !g.starts_with(&prefix));
                if matches!(
                    rule,
                    Retreat::TuningGates | Retreat::TuningGatesWhenUncertain
                ) {
                    moves.extend(joint.tuner.retreat_move(c, good, &now, &self.limits));
                    continue;
                }
                for (g, &to) in good {
                    let at = now.get(g).copied().unwrap_or(to);
                    let back = self.limits.clip(g, at, at + 0.5 * (to - at));
                    if (back - at).abs() > 1e-3 {
                        moves.insert(g.clone(), back);
                    }
                }
            }
        }
        let mut per_cell: BTreeMap<u32, BTreeMap<String, f64>> = BTreeMap::new();
        for (g, mv) in moves {
            if let Some((c, _)) = split_gate(&g) {
                per_cell.entry(c).or_default().insert(g, mv);
            }
        }
        self.scratch.moved_cells.extend(per_cell.keys().copied());
        self.scratch.before_move = now;
        Ok(per_cell
            .into_values()
            .map(|voltages_mv| Request::SetVoltages { voltages_mv })
            .collect())
    }

    /// After joint move `m` was answered: another move while a cell's
    /// predicted residual is still far, else the lower levels.
    fn moved(&mut self, m: u32) -> Result<(), ArrayRunError> {
        if m + 1 >= self.settings.moves_per_iteration {
            return self.after_moves();
        }
        let joint = self.joint()?;
        let band = self.settings.relative_tolerance;
        let now = &self.scratch.before_move;
        let after = &self.voltages_mv;
        let dv =
            DVector::from_iterator(
                joint.tuner.gates().len(),
                joint.tuner.gates().iter().map(|g| {
                    after.get(g).copied().unwrap_or(0.0) - now.get(g).copied().unwrap_or(0.0)
                }),
            );
        let jacobian = self
            .scratch
            .jacobian
            .clone()
            .unwrap_or_else(|| joint.tuner.jacobian());
        let predicted = &jacobian * dv;
        let mut far = false;
        for (c, row) in self.scratch.residual.iter_mut().enumerate() {
            for (p, r) in row.iter_mut().enumerate() {
                if let Some(r) = r {
                    let was_held = *r == 0.0;
                    *r += predicted[c * 2 + p];
                    far |= !was_held && r.abs() > 0.5 * band;
                }
            }
        }
        if far {
            self.step = Step::Move(m + 1);
            Ok(())
        } else {
            self.after_moves()
        }
    }

    /// The moved cells and their neighbours (crosstalk moved their lines
    /// and sensors too), and every cell whose evaluation failed or was too
    /// uncertain (e.g. a charge jump moved its sensor): their lower levels.
    fn after_moves(&mut self) -> Result<(), ArrayRunError> {
        let k = self.sessions.len();
        let grid = self.grid();
        let mut affected: Vec<u32> = self
            .scratch
            .moved_cells
            .iter()
            .flat_map(|&c| grid.within(c as usize, 1).map(|n| n as u32))
            .chain((0..k as u32).filter(|&c| self.scratch.unsure[c as usize]))
            .filter(|&c| (c as usize) < k)
            .collect();
        affected.sort_unstable();
        affected.dedup();
        self.step = Step::ParkSweep(affected.clone(), AfterPark::Lines(affected));
        Ok(())
    }
}

/// The cells of `cells` that scan in one batch: every cell that is not
/// `confident` (its scan cannot be replaced by a prediction), and each
/// confident cell whose readout group (`readout_group[c]`; empty: one
/// sensor per cell) has room below the busiest group's count of needed
/// scans: the batch lasts as long as its busiest group, so such a scan
/// costs no lab time.
///
/// ```text
/// one sensor per cell, cell 1 unsure: every cell scans (1 scan per group)
/// groups [0,1] [2,3], cell 1 unsure: cells 1 and 2 scan, 0 and 3 use their prediction
/// ```
fn who_scans(cells: &[u32], confident: &[bool], readout_group: &[usize]) -> Vec<u32> {
    let group = |c: u32| readout_group.get(c as usize).copied().unwrap_or(c as usize);
    let mut needed: BTreeMap<usize, usize> = BTreeMap::new();
    for (&c, &ok) in cells.iter().zip(confident) {
        if !ok {
            *needed.entry(group(c)).or_default() += 1;
        }
    }
    let busiest = needed.values().copied().max().unwrap_or(0);
    let mut scan = Vec::new();
    for (&c, &ok) in cells.iter().zip(confident) {
        let n = needed.entry(group(c)).or_default();
        if !ok {
            scan.push(c);
        } else if *n < busiest {
            *n += 1;
            scan.push(c);
        }
    }
    scan
}

/// `c{k}.t_sr` → (k, `t_sr`) for the array's parameters.
fn cell_parameter(parameter: &str) -> Option<(usize, usize)> {
    let (cell, name) = crate::sim::array::split_gate(parameter)?;
    let p = CELL_PARAMETERS.iter().position(|n| *n == name)?;
    Some((cell as usize, p))
}

impl crate::session::Plan for ArrayRun {
    fn next_action(&mut self) -> Result<crate::tuner::Action, String> {
        use crate::tuner::Action;
        match self.poll().map_err(|e| e.to_string())? {
            ArrayAction::Execute(requests) => Ok(Action::Request(Request::Batch { requests })),
            ArrayAction::Iteration(record) => Ok(Action::Iteration(*record)),
            ArrayAction::Idle => Ok(Action::Finished),
        }
    }

    fn take_response(&mut self, response: Response) -> Result<(), crate::tuner::TunerError> {
        match response {
            Response::Batch {
                responses,
                lab_seconds,
            } => self
                .feed(responses, lab_seconds)
                .map_err(|e| crate::tuner::TunerError::Device(e.to_string())),
            _ => Err(crate::tuner::TunerError::UnexpectedResponse { expected: "batch" }),
        }
    }

    fn gate_specs(&self) -> &[GateSpec] {
        &self.gates
    }

    fn charge_time(&mut self, seconds: f64) {
        if seconds.is_finite() && seconds > 0.0 {
            self.lab_seconds += seconds;
        }
    }

    /// Plans from the read-back from now on (a gate the run does not know
    /// is ignored). A batch handed out but not answered was planned from
    /// other voltages: it is planned again (the initial measurements'
    /// sessions keep theirs: each reads its own gates first).
    fn adopt_voltages(&mut self, readback: &BTreeMap<String, f64>, _tolerance_mv: f64) {
        let mut changed = false;
        for (g, &v) in readback {
            if v.is_finite() && self.limits.gate(g).is_some() {
                changed |= self.voltages_mv.insert(g.clone(), v) != Some(v);
            }
        }
        if changed && self.step != Step::Initial && self.step != Step::ReadAll {
            self.outstanding = None;
        }
    }

    fn check_target(
        &self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<crate::parameter::Tolerance>,
    ) -> Result<(), crate::tuner::TunerError> {
        use crate::tuner::TunerError;
        let invalid = |message: String| TunerError::InvalidTarget {
            parameter: parameter.into(),
            message,
        };
        cell_parameter(parameter)
            .filter(|(c, _)| *c < self.targets.len())
            .ok_or_else(|| TunerError::UnknownParameter(parameter.into()))?;
        match target {
            Some(t) if t.is_finite() && t > 0.0 => {}
            Some(t) => return Err(invalid(format!("{t} is not a finite positive value"))),
            None => {
                return Err(invalid(
                    "an array cell's parameter always has a target".into(),
                ))
            }
        }
        if tolerance.is_some() {
            return Err(invalid(format!(
                "the band of an array run is ±{} of the target for every cell",
                self.settings.relative_tolerance
            )));
        }
        Ok(())
    }

    fn change_target(
        &mut self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<crate::parameter::Tolerance>,
    ) -> Result<(), crate::tuner::TunerError> {
        self.check_target(parameter, target, tolerance)?;
        let (Some((cell, p)), Some(value)) = (cell_parameter(parameter), target) else {
            return Err(crate::tuner::TunerError::UnknownParameter(parameter.into()));
        };
        let (mut t, mut w) = self.targets[cell];
        if p == 0 {
            t = value;
        } else {
            w = value;
        }
        self.set_targets(cell, (t, w))
            .map_err(|e| crate::tuner::TunerError::InvalidTarget {
                parameter: parameter.into(),
                message: e.to_string(),
            })
    }

    fn done(&self) -> bool {
        self.step == Step::Idle
    }
}

#[cfg(test)]
mod tests {
    use super::lines::borrow_line_jacobians;
    use super::*;

    fn lower(line_gates: &[&str], line_jacobian: [[f64; 2]; 2]) -> CellLower {
        CellLower {
            line_gates: line_gates.iter().map(|g| g.to_string()).collect(),
            line_jacobian,
            line_max_step_mv: 2.0,
            ..CellLower::empty(References::default())
        }
    }

    #[test]
    fn a_confident_cell_scans_only_where_its_group_has_room() {
        // one sensor per cell: one unsure cell makes the batch a scan long,
        // so every cell scans
        assert_eq!(
            who_scans(&[0, 1, 2], &[true, false, true], &[]),
            vec![0, 1, 2]
        );
        // everybody confident: nobody scans
        assert!(who_scans(&[0, 1, 2], &[true; 3], &[]).is_empty());
        // groups [0, 1] and [2, 3]: cell 1's scan takes one slot of its
        // group; group [2, 3] has room for one of its confident cells
        assert_eq!(
            who_scans(&[0, 1, 2, 3], &[true, false, true, true], &[0, 0, 1, 1]),
            vec![1, 2]
        );
        // two unsure cells in group 0: group 1's two cells fit
        assert_eq!(
            who_scans(&[0, 1, 2, 3], &[false, false, true, true], &[0, 0, 1, 1]),
            vec![0, 1, 2, 3]
        );
    }

    /// A cell without a learned line Jacobian borrows the mean of the cells
    /// that learned one; a cell without lines and a learned one are left
    /// alone; with nothing learned nothing changes.
    #[test]
    fn a_cell_without_a_plausible_line_jacobian_borrows_the_mean_of_the_plausible_ones() {
        let plungers = ["PA", "PB"];
        let mut cells = vec![
            lower(&plungers, [[1.0, 0.2], [0.1, 0.9]]),
            lower(&plungers, [[0.0; 2]; 2]),
            lower(&plungers, [[0.8, 0.1], [0.3, 1.1]]),
            lower(&[], [[0.0; 2]; 2]),
            // measured while a line was lost: near-singular, line A moving most with PB
            lower(&plungers, [[-3.19, -17.98], [0.34, 1.90]]),
        ];
        borrow_line_jacobians(&mut cells);
        // by hand: ((1.0 + 0.8)/2, (0.2 + 0.1)/2; (0.1 + 0.3)/2, (0.9 + 1.1)/2),
        // the implausible one neither lent nor kept
        let want = [[0.9, 0.15], [0.2, 1.0]];
        for c in [1, 4] {
            for (r, row) in want.iter().enumerate() {
                for (s, w) in row.iter().enumerate() {
                    assert!(
                        (cells[c].line_jacobian[r][s] - w).abs() < 1e-12,
                        "cell {c}: {:?}",
                        cells[c].line_jacobian
                    );
                }
            }
        }
        assert_eq!(cells[0].line_jacobian, [[1.0, 0.2], [0.1, 0.9]]);
        assert_eq!(cells[3].line_jacobian, [[0.0; 2]; 2]);

        let mut none = vec![lower(&plungers, [[0.0; 2]; 2]); 2];
        borrow_line_jacobians(&mut none);
        assert!(none.iter().all(|l| l.line_jacobian == [[0.0; 2]; 2]));
    }
}
