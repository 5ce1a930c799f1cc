//! The array benchmark (issue 24, first slice): K double-dot cells
//! ([`crate::sim::array`]) tuned by four strategies from the same world.
//!
//! # Protocol
//! 1. **Cold start**: every cell from its start to the first set point,
//!    initial measurements included; minutes from lab time 0 until every
//!    cell measured in band.
//! 2. **Set-point cycle**: the paper's set points after the first
//!    ([`crate::benchmark::BenchmarkProtocol::default`]`.set_points[1..]`)
//!    applied to all cells at once; minutes per change until every cell
//!    measured in band.
//! 3. **Single-cell changes**: one cell's targets change
//!    ([`ArrayProtocol::single_cell_target`]; cells K/2, then 0, …); the
//!    change is done when every cell is measured in band; then the world
//!    counts the changed cell's neighbours whose *true* values are out of
//!    band ([`ArrayRunResult::neighbours_left_out_of_band`]).
//!
//! "In band" is the lab's measurement: both `t_sr` and `w` within
//! [`ArrayRunSettings::relative_tolerance`] of their targets in the latest
//! evaluation after the change.
//!
//! # Strategies
//! * `serial`: the recommended single-cell [`Tuner`] per cell (gates renamed
//!   `c{k}.…`) in its own [`RunSession`] (so through its guard), one cell at
//!   a time until it is in band, then a check pass (one iteration per cell,
//!   serial); passes repeat over the cells found out of band.
//! * `independent`: the same per-cell sessions all at once; every round
//!   batches one request per cell ([`ArrayDevice::execute_batch`]), so
//!   different readout groups run in parallel. Crosstalk is ignored.
//! * `joint`: the per-cell sessions' initial measurements in parallel (as
//!   `independent`), then [`JointArrayTuner`]: one Kalman row per
//!   parameter over the neighbourhood's tuning gates, a joint step with
//!   per-cell step limits, the lower levels (sensing dot re-park, lines
//!   re-centred with the cell's learned line Jacobian) per cell, everything
//!   batched across readout groups.
//! * `oracle`: `joint` with the true full Jacobian each iteration
//!   (the only strategy whose array is not sealed).
//!
//! # World and lab (invariant 7)
//! [`Lab`] is the world: the array and the checks of every move against
//! the gate limits and each gate's `max_step_mv` from the present
//! (commanded) voltage, counted in `limit_violations` and refused. The
//! strategies see only responses.

use std::collections::BTreeMap;

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

use super::array_timeline::{band_entry, before_band, TimelinePoint, MAX_TIMELINE_POINTS};
use super::cell_trace::CellTrace;
use super::row_agreement::RowAgreement;
use super::{quantiles, Quantiles, PAPER_SET_POINTS};
use crate::config_error::ConfigError;
use crate::description::layout::CellGrid;
use crate::parameter::Tolerance;
use crate::protocol::{ControlCommand, IterationRecord, Request, Response, ScanKind};
use crate::safety::SafetyLimits;
use crate::session::{Output, RunSession, SessionConfig};
use crate::sim::array::{parameter_name, ArrayConfig, ArrayDevice};
use crate::sim::DeviceConfig;
use crate::tuner::array::JointArrayTuner;
use crate::tuner::array_run::{
    ArrayAction, ArrayRun, ArrayRunError, ArrayRunSettings, CELL_PARAMETERS,
};
use crate::tuner::in_band::within_band;
use crate::tuner::{Tuner, TunerConfig};

/// A strategy of the array benchmark (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ArrayStrategy {
    /// Cell by cell, then passes over disturbed cells.
    Serial,
    /// All cells at once, each its own tuner, crosstalk ignored.
    Independent,
    /// The joint array tuner (the product default).
    Joint,
    /// The joint loop with the true Jacobian.
    Oracle,
}

impl ArrayStrategy {
    /// All strategies in report order.
    pub const ALL: [ArrayStrategy; 4] = [
        ArrayStrategy::Serial,
        ArrayStrategy::Independent,
        ArrayStrategy::Joint,
        ArrayStrategy::Oracle,
    ];

    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            ArrayStrategy::Serial => "serial",
            ArrayStrategy::Independent => "independent",
            ArrayStrategy::Joint => "joint",
            ArrayStrategy::Oracle => "oracle",
        }
    }

    /// Parse a command-line name.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }
}

/// Bounds of the protocol's counts (invariant 8).
pub const MAX_ROUNDS: u32 = 200;

/// Protocol settings (bounded; [`ArrayProtocol::validate`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayProtocol {
    /// Set points `(t_sr ns, w µV)`: the first is the cold start's, the
    /// rest the cycle applied to all cells.
    pub set_points: Vec<(f64, f64)>,
    /// Iterations per cell and change before a change counts as not
    /// converged (`independent`, `joint`, `oracle`; cold start twice this), 1..=[`MAX_ROUNDS`].
    pub iterations_per_change: u32,
    /// `serial`: iterations per cell and pass, 1..=[`MAX_ROUNDS`].
    pub serial_iterations_per_cell: u32,
    /// `serial`: passes per change, 1..=10. Default 10, the most: every
    /// pass re-checks each cell, and with crosstalk a pass rarely finds all
    /// 9 cells in band at once (4 passes converged no 9-cell phase); a
    /// larger budget only makes the baseline stronger.
    pub serial_passes: u32,
    /// Number of single-cell changes, 0..=16.
    pub single_cell_changes: u32,
    /// Target `(t_sr ns, w µV)` of a single-cell change.
    pub single_cell_target: (f64, f64),
    /// Relative error of the lab's cross-cell virtual-gate calibration
    /// ([`lab_cross_calibration`]), 0..=1. Default 0.2.
    pub cross_compensation_error: f64,
    /// The lab's cross-cell calibration `λ̂` (nearest, next) taken as given
    /// whatever the world's crosstalk (a calibration that is wrong; each
    /// 0..=[`crate::sim::array::MAX_CROSSTALK`]); `None`: the world's with
    /// `cross_compensation_error` ([`lab_cross_calibration`]).
    #[serde(default)]
    pub cross_calibration: Option<[f64; 2]>,
    /// The joint loop's settings (`joint`, `oracle`; the band also for
    /// `serial` and `independent`).
    #[serde(default)]
    pub tuning: ArrayRunSettings,
    /// A cell the joint loop's timeline follows in detail (`joint`,
    /// `oracle`; [`CellTrace`] per point, world side), below
    /// [`crate::sim::array::MAX_CELLS`] and the array's cell count;
    /// `None` (default): none.
    #[serde(default)]
    pub trace_cell: Option<u32>,
}

impl Default for ArrayProtocol {
    fn default() -> Self {
        Self {
            set_points: PAPER_SET_POINTS.to_vec(),
            iterations_per_change: 30,
            serial_iterations_per_cell: 21,
            serial_passes: 10,
            single_cell_changes: 2,
            single_cell_target: (70.0, 180.0),
            cross_compensation_error: 0.2,
            cross_calibration: None,
            tuning: ArrayRunSettings::default(),
            trace_cell: None,
        }
    }
}

impl ArrayProtocol {
    /// `Err` naming the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let check = ConfigError::check;
        check(
            !self.set_points.is_empty() && self.set_points.len() <= 16,
            "set_points",
            format!("{} set points (1..=16)", self.set_points.len()),
        )?;
        for (i, &(t, w)) in self
            .set_points
            .iter()
            .chain([&self.single_cell_target])
            .enumerate()
        {
            check(
                t.is_finite()
                    && (1.0..=1000.0).contains(&t)
                    && w.is_finite()
                    && (10.0..=2000.0).contains(&w),
                &format!("set_points[{i}]"),
                format!("({t} ns, {w} µV) (t_sr 1..=1000 ns, w 10..=2000 µV)"),
            )?;
        }
        for (field, v) in [
            ("iterations_per_change", self.iterations_per_change),
            (
                "serial_iterations_per_cell",
                self.serial_iterations_per_cell,
            ),
        ] {
            check((1..=MAX_ROUNDS).contains(&v), field, v.to_string())?;
        }
        check(
            (1..=10).contains(&self.serial_passes),
            "serial_passes",
            self.serial_passes.to_string(),
        )?;
        check(
            self.single_cell_changes <= 16,
            "single_cell_changes",
            self.single_cell_changes.to_string(),
        )?;
        let e = self.cross_compensation_error;
        check(
            e.is_finite() && (0.0..=1.0).contains(&e),
            "cross_compensation_error",
            e.to_string(),
        )?;
        if let Some(l) = self.cross_calibration {
            crate::tuner::array::check_cross_calibration(l)?;
        }
        if let Some(c) = self.trace_cell {
            check(
                c < crate::sim::array::MAX_CELLS,
                "trace_cell",
                format!("{c} (0..{})", crate::sim::array::MAX_CELLS),
            )?;
        }
        self.tuning.validate().map_err(|e| e.within("tuning"))
    }

    /// The joint loop's settings ([`ArrayRun`]) of this protocol.
    pub fn run_settings(&self) -> ArrayRunSettings {
        self.tuning.clone()
    }
}

/// One strategy on one array and seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArrayRunResult {
    /// Strategy.
    pub strategy: ArrayStrategy,
    /// Noise seed.
    pub seed: u64,
    /// Device population (0: cells 1.. drawn with `device_seed` 0 too; see `sim::array`).
    pub device: u64,
    /// Lab minutes from 0 until every cell measured in band at the first set point.
    pub cold_start_lab_minutes: Option<f64>,
    /// Lab minutes per set-point change of all cells (`None`: not converged).
    pub changes: Vec<Option<f64>>,
    /// Lab minutes per single-cell change (`None`: not converged).
    pub single_cell_changes: Vec<Option<f64>>,
    /// Neighbours of a changed cell truly out of band after its change (world side).
    pub neighbours_left_out_of_band: u64,
    /// Moves refused by the world (limits or a step above `max_step_mv`).
    pub limit_violations: u64,
    /// Requests for the truth.
    pub truth_queries: u64,
    /// Failed or rejected evaluations.
    pub failed_fits: u64,
    /// Scans run.
    pub measurements: u64,
    /// Lab minutes of the whole protocol by request kind (sensing_dot,
    /// chemical_potential, transition_width, reload_time, set_voltages, …).
    #[serde(default)]
    pub lab_minutes_by_kind: BTreeMap<String, f64>,
    /// `joint` and `oracle`: every iteration, cells × lab time, in band or
    /// not (at most [`MAX_TIMELINE_POINTS`]); empty for the per-cell strategies.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub timeline: Vec<TimelinePoint>,
}

/// Why a run ended early.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArrayFailure {
    /// A configuration the core refused.
    #[error("invalid configuration: {0}")]
    Config(#[from] ConfigError),
    /// The joint loop stopped.
    #[error(transparent)]
    Run(#[from] ArrayRunError),
    /// A cell's session faulted or waits (a refused request, a device error).
    #[error("cell {cell}: session halted: {message}")]
    Halted {
        /// The cell.
        cell: u32,
        /// What happened.
        message: String,
    },
}

/// The world's side of the lab: the array and the world-side move checks.
pub struct Lab {
    /// The simulated array.
    pub device: ArrayDevice,
    limits: SafetyLimits,
    /// Moves refused (limits, step).
    pub violations: u64,
    /// Scans run.
    pub measurements: u64,
    /// Lab seconds by request kind ([`super::request_kind`]): a batch's
    /// time split over its requests in proportion to each one's own lab time.
    pub seconds_by_kind: BTreeMap<String, f64>,
}

impl Lab {
    /// A lab around `device`.
    pub fn new(device: ArrayDevice) -> Self {
        Self {
            limits: SafetyLimits::new(&device.gates()),
            device,
            violations: 0,
            measurements: 0,
            seconds_by_kind: BTreeMap::new(),
        }
    }

    /// The gate limits (also the lab's configuration).
    pub fn limits(&self) -> &SafetyLimits {
        &self.limits
    }

    /// Lab clock, minutes.
    pub fn minutes(&self) -> f64 {
        self.device.lab_seconds() / 60.0
    }

    /// One batch: every set is checked against the limits and each gate's
    /// step from the commanded voltage (refused and counted if it fails).
    pub fn batch(&mut self, requests: &[Request]) -> Vec<Response> {
        let now = self.device.voltages_mv();
        let mut allowed = Vec::with_capacity(requests.len());
        let mut refused = Vec::with_capacity(requests.len());
        for r in requests {
            match r {
                Request::SetVoltages { voltages_mv } => {
                    if let Err(e) = self.limits.check(&now, voltages_mv) {
                        self.violations += 1;
                        refused.push(Some(Response::error(e.to_string())));
                        continue;
                    }
                }
                Request::Measure { .. } => self.measurements += 1,
                _ => {}
            }
            refused.push(None);
            allowed.push(r.clone());
        }
        let before = self.device.lab_seconds();
        let answers = self.device.execute_batch(&allowed);
        let batch = self.device.lab_seconds() - before;
        let own: Vec<f64> = answers.iter().map(Response::lab_seconds).collect();
        let total: f64 = own.iter().sum();
        if total > 0.0 {
            for (r, s) in allowed.iter().zip(&own) {
                *self
                    .seconds_by_kind
                    .entry(super::request_kind(r).to_string())
                    .or_default() += batch * s / total;
            }
        }
        let mut answers = answers.into_iter();
        refused
            .into_iter()
            .map(|r| r.unwrap_or_else(|| answers.next().unwrap_or_else(|| Response::error("lost"))))
            .collect()
    }
}

/// The recommended single-cell tuner for cell `cell` at the protocol's
/// first set point and band ([`crate::driver::array::cell_tuner`]).
pub fn cell_tuner(cell: u32, protocol: &ArrayProtocol) -> TunerConfig {
    crate::driver::array::cell_tuner(
        cell,
        protocol.set_points[0],
        protocol.tuning.relative_tolerance,
    )
}

/// One cell's session and what the driver knows of it.
struct CellRun {
    cell: u32,
    session: RunSession,
    pending: Option<Request>,
    targets: (f64, f64),
    /// The latest record after the last change was in band.
    in_band: bool,
    /// Records since the last change.
    records: u32,
    done: bool,
}

impl CellRun {
    fn new(cell: u32, tuner: TunerConfig) -> Result<Self, ArrayFailure> {
        let targets = (
            tuner.top().parameters[0].target.unwrap_or(f64::NAN),
            tuner.top().parameters[1].target.unwrap_or(f64::NAN),
        );
        let tuner = Tuner::new(tuner)?;
        Ok(Self {
            cell,
            session: RunSession::from_tuner(tuner, SessionConfig::default()),
            pending: None,
            targets,
            in_band: false,
            records: 0,
            done: false,
        })
    }

    fn set_targets(&mut self, (t_sr, w): (f64, f64), band: f64) -> Result<(), ArrayFailure> {
        for (parameter, target) in [("t_sr", t_sr), ("w", w)] {
            self.session
                .control(&ControlCommand::SetTarget {
                    parameter: parameter.into(),
                    target: Some(target),
                    tolerance: Some(Tolerance::Relative(band)),
                })
                .map_err(|e| self.halted(e.to_string()))?;
        }
        self.targets = (t_sr, w);
        self.in_band = false;
        self.records = 0;
        Ok(())
    }

    fn halted(&self, message: String) -> ArrayFailure {
        ArrayFailure::Halted {
            cell: self.cell,
            message,
        }
    }

    /// A record counts as in band when it is tuned against the present targets.
    fn note(&mut self, rec: &IterationRecord) {
        let on_targets = rec.parameters.iter().all(|p| match p.name.as_str() {
            "t_sr" => p.target == Some(self.targets.0),
            "w" => p.target == Some(self.targets.1),
            _ => true,
        });
        self.in_band = rec.tuned && on_targets;
        if on_targets {
            self.records += 1;
        }
    }

    /// Poll until the session asks the device something; returns new records.
    fn next_request(&mut self) -> Result<u32, ArrayFailure> {
        let mut new = 0;
        while self.pending.is_none() && !self.done {
            match self.session.poll() {
                Output::Execute(mut request) => {
                    if let Request::Measure { scan } = &mut request {
                        scan.cell = Some(self.cell);
                    }
                    self.pending = Some(request);
                }
                Output::Commit(rec) => {
                    self.note(&rec);
                    new += 1;
                }
                Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
                Output::Wait => {
                    return Err(self.halted(format!("{:?}", self.session.status())));
                }
                Output::Done(_) => self.done = true,
            }
        }
        Ok(new)
    }
}

/// One round: every active run's next request in one batch. Returns the
/// number of records committed before the batch.
fn round(lab: &mut Lab, runs: &mut [CellRun], active: &[usize]) -> Result<u32, ArrayFailure> {
    let mut records = 0;
    for &i in active {
        records += runs[i].next_request()?;
    }
    let live: Vec<usize> = active
        .iter()
        .copied()
        .filter(|&i| runs[i].pending.is_some())
        .collect();
    let requests: Vec<Request> = live
        .iter()
        .filter_map(|&i| runs[i].pending.clone())
        .collect();
    let answers = lab.batch(&requests);
    for (i, answer) in live.into_iter().zip(answers) {
        runs[i].pending = None;
        let run = &mut runs[i];
        run.session
            .feed(answer)
            .map_err(|e| run.halted(e.to_string()))?;
    }
    Ok(records)
}

/// Run `active` cells in parallel until each is in band (records after the
/// change) or has `cap` records since; `Some(minutes)` when all cells of
/// `all` are in band at once.
fn parallel_until_in_band(
    lab: &mut Lab,
    runs: &mut [CellRun],
    cap: u32,
    t0: f64,
) -> Result<Option<f64>, ArrayFailure> {
    let all: Vec<usize> = (0..runs.len()).collect();
    loop {
        if runs.iter().all(|r| r.in_band) {
            return Ok(Some(lab.minutes() - t0));
        }
        if runs.iter().all(|r| r.in_band || r.done || r.records >= cap) {
            return Ok(None);
        }
        round(lab, runs, &all)?;
    }
}

/// Serial: tune each cell out of band alone, then check every cell (one
/// record each); repeat over the cells found out of band.
fn serial_until_in_band(
    lab: &mut Lab,
    runs: &mut [CellRun],
    protocol: &ArrayProtocol,
    t0: f64,
) -> Result<Option<f64>, ArrayFailure> {
    for _pass in 0..protocol.serial_passes {
        for i in 0..runs.len() {
            let start = runs[i].records;
            while !runs[i].in_band
                && !runs[i].done
                && runs[i].records - start < protocol.serial_iterations_per_cell
            {
                round(lab, runs, &[i])?;
            }
        }
        // the check pass: a fresh record of every cell
        for i in 0..runs.len() {
            let before = runs[i].records;
            while runs[i].records == before && !runs[i].done {
                round(lab, runs, &[i])?;
            }
        }
        if runs.iter().all(|r| r.in_band) {
            return Ok(Some(lab.minutes() - t0));
        }
    }
    Ok(None)
}

/// Cells of the single-cell changes: K/2, 0, K−1, K/4, … (distinct, at most `n`).
pub fn single_change_cells(cells: u32, n: u32) -> Vec<u32> {
    let mut out = Vec::new();
    for c in [
        cells / 2,
        0,
        cells.saturating_sub(1),
        cells / 4,
        3 * cells / 4,
    ]
    .into_iter()
    .chain(0..cells)
    {
        if out.len() as u32 >= n {
            break;
        }
        if !out.contains(&c) {
            out.push(c);
        }
    }
    out
}

fn truly_in_band(lab: &Lab, cell: u32, (t_sr, w): (f64, f64), band: f64) -> bool {
    lab.device
        .truth(cell)
        .is_some_and(|t| within_band(t.t_sr_ns, t_sr, band) && within_band(t.w_uv, w, band))
}

/// The world: an array of `cells` on population `device_seed`, noise `seed`.
pub fn world(
    base: &DeviceConfig,
    config: ArrayConfig,
    accept: impl Fn(&DeviceConfig) -> bool,
) -> Result<ArrayDevice, ConfigError> {
    let devices = crate::sim::array::cell_devices(base, config.cells, config.device_seed, accept);
    ArrayDevice::new(config, devices)
}

/// Run one strategy on `array` (a fresh world; sealed here unless the oracle).
pub fn run_strategy(
    strategy: ArrayStrategy,
    mut array: ArrayDevice,
    protocol: &ArrayProtocol,
) -> Result<ArrayRunResult, ArrayFailure> {
    protocol.validate()?;
    if strategy != ArrayStrategy::Oracle {
        array.seal_truth();
    }
    let seed = array.config().seed;
    let device = array.config().device_seed;
    let k = array.cells();
    if let Some(c) = protocol.trace_cell.filter(|&c| c >= k) {
        return Err(ConfigError::new("trace_cell", format!("{c}: the array has {k} cells")).into());
    }
    let mut lab = Lab::new(array);
    let band = protocol.tuning.relative_tolerance;
    let mut runs = (0..k)
        .map(|c| CellRun::new(c, cell_tuner(c, protocol)))
        .collect::<Result<Vec<_>, _>>()?;
    let mut result = ArrayRunResult {
        strategy,
        seed,
        device,
        cold_start_lab_minutes: None,
        changes: Vec::new(),
        single_cell_changes: Vec::new(),
        neighbours_left_out_of_band: 0,
        limit_violations: 0,
        truth_queries: 0,
        failed_fits: 0,
        measurements: 0,
        lab_minutes_by_kind: BTreeMap::new(),
        timeline: Vec::new(),
    };
    let mut targets = vec![protocol.set_points[0]; k as usize];
    let single: Vec<u32> = single_change_cells(k, protocol.single_cell_changes);
    let mut joint_failed = 0;
    match strategy {
        ArrayStrategy::Serial | ArrayStrategy::Independent => {
            let go = |lab: &mut Lab, runs: &mut [CellRun], cap: u32| {
                let t0 = lab.minutes();
                if strategy == ArrayStrategy::Serial {
                    serial_until_in_band(lab, runs, protocol, t0)
                } else {
                    parallel_until_in_band(lab, runs, cap, t0)
                }
            };
            result.cold_start_lab_minutes =
                go(&mut lab, &mut runs, 2 * protocol.iterations_per_change)?;
            for &sp in &protocol.set_points[1..] {
                for r in runs.iter_mut() {
                    r.set_targets(sp, band)?;
                }
                targets.iter_mut().for_each(|t| *t = sp);
                result
                    .changes
                    .push(go(&mut lab, &mut runs, protocol.iterations_per_change)?);
            }
            for &c in &single {
                let t = protocol.single_cell_target;
                runs[c as usize].set_targets(t, band)?;
                targets[c as usize] = t;
                // the others stay on target; their latest in-band state holds
                result.single_cell_changes.push(go(
                    &mut lab,
                    &mut runs,
                    protocol.iterations_per_change,
                )?);
                result.neighbours_left_out_of_band += neighbours_out(&lab, c, &targets, band);
            }
        }
        ArrayStrategy::Joint | ArrayStrategy::Oracle => {
            let lab_lambda = lab_cross_calibration(lab.device.config(), protocol, seed);
            let cells = (0..k).map(|c| cell_tuner(c, protocol)).collect();
            let gates = lab.device.gates();
            let mut run = ArrayRun::new(
                cells,
                &gates,
                protocol.run_settings(),
                lab_lambda,
                strategy == ArrayStrategy::Oracle,
            )?;
            run.set_readout_groups(lab.device.config().readout_groups.as_deref());
            run.set_grid(lab.device.config().grid()?)?;
            // the cold start counts from the run's start (initial measurements included)
            let mut timeline = Timeline {
                points: &mut result.timeline,
                phase: 0,
                band,
                at_move: None,
                trace: protocol.trace_cell,
            };
            result.cold_start_lab_minutes = joint_until_in_band(
                &mut lab,
                &mut run,
                2 * protocol.iterations_per_change,
                0.0,
                &mut timeline,
            )?;
            for &sp in &protocol.set_points[1..] {
                targets.iter_mut().for_each(|t| *t = sp);
                for c in 0..k as usize {
                    run.set_targets(c, sp)?;
                }
                let t0 = lab.minutes();
                timeline.phase += 1;
                result.changes.push(joint_until_in_band(
                    &mut lab,
                    &mut run,
                    protocol.iterations_per_change,
                    t0,
                    &mut timeline,
                )?);
            }
            for &c in &single {
                targets[c as usize] = protocol.single_cell_target;
                run.set_targets(c as usize, protocol.single_cell_target)?;
                let t0 = lab.minutes();
                timeline.phase += 1;
                result.single_cell_changes.push(joint_until_in_band(
                    &mut lab,
                    &mut run,
                    protocol.iterations_per_change,
                    t0,
                    &mut timeline,
                )?);
                result.neighbours_left_out_of_band += neighbours_out(&lab, c, &targets, band);
            }
            joint_failed = run.failed_evaluations();
        }
    }
    result.failed_fits = joint_failed
        + runs
            .iter()
            .map(|r| r.session.tuner().failed_evaluations())
            .sum::<u64>();
    result.limit_violations = lab.violations;
    result.truth_queries = lab.device.truth_queries();
    result.measurements = lab.measurements;
    result.lab_minutes_by_kind = lab
        .seconds_by_kind
        .iter()
        .map(|(k, s)| (k.clone(), s / 60.0))
        .collect();
    Ok(result)
}

/// Where [`joint_until_in_band`] notes its iterations.
struct Timeline<'a> {
    points: &'a mut Vec<TimelinePoint>,
    /// The protocol phase now run.
    phase: u32,
    /// Relative band of the world's check.
    band: f64,
    /// The learned rows against the truth where this iteration's move
    /// started ([`Timeline::before_batch`]), and the traced cell there,
    /// until the iteration is noted.
    at_move: Option<(Vec<Option<RowAgreement>>, Option<CellTrace>)>,
    /// The cell followed in detail ([`ArrayProtocol::trace_cell`]).
    trace: Option<u32>,
}

impl Timeline<'_> {
    /// Before `batch` runs: if it is the iteration's first to set a tuning
    /// gate (its move), note the rows the move was planned with against the
    /// truth at the voltages it starts from, those of the measurement.
    ///
    /// After the move, the traced cell's first line scan: where its lines
    /// truly sit as the scan starts ([`CellTrace::lines_at_line_scan_mv`]).
    fn before_batch(&mut self, lab: &Lab, run: &ArrayRun, batch: &[Request]) {
        let Some((_, trace)) = &mut self.at_move else {
            if let Some(t) = run.tuner() {
                if sets_any(batch, t.gates()) {
                    self.at_move = Some(self.rows_and_trace(lab, t));
                }
            }
            return;
        };
        if let Some(t) = trace.as_mut() {
            if t.lines_at_line_scan_mv.is_none() && scans_lines_of(batch, t.cell) {
                t.lines_at_line_scan_mv = lab.device.lines_now_mv(t.cell);
            }
        }
    }

    fn note(&mut self, lab: &Lab, run: &ArrayRun, record: &IterationRecord) {
        let at_move = self.at_move.take();
        if self.points.len() >= MAX_TIMELINE_POINTS {
            return;
        }
        // an iteration without a move: its rows against the truth at its end
        let (rows, mut trace) = at_move
            .or_else(|| run.tuner().map(|t| self.rows_and_trace(lab, t)))
            .unwrap_or_default();
        if let Some(t) = &mut trace {
            let c = t.cell as usize;
            for (p, m) in t.measured.iter_mut().enumerate() {
                *m = record
                    .parameters
                    .get(2 * c + p)
                    .and_then(|r| Some((r.value?, r.std.unwrap_or(f64::NAN))));
            }
            let target = |p: usize| record.parameters.get(2 * c + p).and_then(|r| r.target);
            t.targets = target(0).zip(target(1)).map(|(a, b)| [a, b]);
        }
        let truth = record
            .parameters
            .chunks(2)
            .enumerate()
            .map(|(c, p)| {
                let target = (
                    p[0].target.unwrap_or(f64::NAN),
                    p.get(1).and_then(|p| p.target).unwrap_or(f64::NAN),
                );
                truly_in_band(lab, c as u32, target, self.band)
            })
            .collect();
        let mut point =
            TimelinePoint::new(record.lab_seconds, &record.parameters, self.phase, truth);
        point.apply_rechecks(&record.events);
        point.rows = rows;
        point.trace = trace;
        self.points.push(point);
    }

    /// Every cell's rows against the truth at the present voltages, and the
    /// traced cell there (its measured values still to be filled in).
    fn rows_and_trace(
        &self,
        lab: &Lab,
        tuner: &JointArrayTuner,
    ) -> (Vec<Option<RowAgreement>>, Option<CellTrace>) {
        let k = tuner.cells().len();
        let Some(rows) = own_rows(lab, tuner) else {
            return (vec![None; k], None);
        };
        let trace = self.trace.and_then(|c| {
            let (learned, truth, values) = rows.get(c as usize)?.clone();
            let voltages = lab.device.voltages_mv();
            let gates = &tuner.cells().get(c as usize)?.gates;
            Some(CellTrace {
                cell: c,
                voltages_mv: gates
                    .iter()
                    .map(|g| (g.clone(), voltages.get(g).copied().unwrap_or(f64::NAN)))
                    .collect(),
                measured: [None, None],
                truth: values,
                learned_rows: learned,
                true_rows: truth,
                true_lines_mv: lab.device.lines_now_mv(c)?,
                lines_at_line_scan_mv: None,
                targets: None,
            })
        });
        let agreements = rows
            .iter()
            .map(|(learned, truth, _)| RowAgreement::new(learned, truth))
            .collect();
        (agreements, trace)
    }
}

/// Whether any request of `batch` (batches inside it included) sets one of
/// `gates`.
fn sets_any(batch: &[Request], gates: &[String]) -> bool {
    batch.iter().any(|r| match r {
        Request::SetVoltages { voltages_mv } => voltages_mv.keys().any(|g| gates.contains(g)),
        Request::Batch { requests } => sets_any(requests, gates),
        _ => false,
    })
}

/// Whether `batch` (batches inside it included) holds a line scan (the
/// chemical-potential scan) of cell `cell`.
fn scans_lines_of(batch: &[Request], cell: u32) -> bool {
    batch.iter().any(|r| match r {
        Request::Measure { scan } => {
            scan.kind == ScanKind::ChemicalPotential && scan.cell == Some(cell)
        }
        Request::Batch { requests } => scans_lines_of(requests, cell),
        _ => false,
    })
}

/// Per cell, its learned own-gate rows and the world's true ones at the
/// present voltages, log space (1/mV; `[t_sr, w]` each), and its true
/// values (world side); `None` if the world cannot tell.
type OwnRows = ([Vec<f64>; 2], [Vec<f64>; 2], [f64; 2]);

/// [`OwnRows`] of every cell.
fn own_rows(lab: &Lab, tuner: &JointArrayTuner) -> Option<Vec<OwnRows>> {
    let gates: Vec<&str> = tuner.gates().iter().map(String::as_str).collect();
    let k = tuner.cells().len();
    let names: Vec<String> = (0..k as u32)
        .flat_map(|c| CELL_PARAMETERS.map(|p| parameter_name(c, p)))
        .collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let values: Option<Vec<f64>> = (0..k as u32)
        .flat_map(|c| CELL_PARAMETERS.map(|p| lab.device.truth(c).and_then(|t| t.get(p))))
        .collect();
    let (Some(values), Ok(truth)) = (values, lab.device.true_jacobian(&gates, &names)) else {
        return None;
    };
    let learned = tuner.jacobian();
    let mut offset = 0;
    let rows = tuner
        .cells()
        .iter()
        .enumerate()
        .map(|(c, cell)| {
            let own = offset..offset + cell.gates.len();
            offset = own.end;
            let row = |m: &DMatrix<f64>, r: usize, scale: f64| -> Vec<f64> {
                own.clone().map(|g| m[(r, g)] / scale).collect()
            };
            let (t, w) = (2 * c, 2 * c + 1);
            (
                [row(&learned, t, 1.0), row(&learned, w, 1.0)],
                [row(&truth, t, values[t]), row(&truth, w, values[w])],
                [values[t], values[w]],
            )
        })
        .collect();
    Some(rows)
}

/// Drive `run` until every cell is measured in band (`Some(lab minutes
/// since t0)`) or `cap` iterations end without it (`None`).
fn joint_until_in_band(
    lab: &mut Lab,
    run: &mut ArrayRun,
    cap: u32,
    t0: f64,
    timeline: &mut Timeline,
) -> Result<Option<f64>, ArrayFailure> {
    let mut iterations = 0;
    timeline.at_move = None;
    loop {
        match run.poll()? {
            ArrayAction::Execute(batch) => {
                timeline.before_batch(lab, run, &batch);
                let before = lab.device.lab_seconds();
                let answers = lab.batch(&batch);
                run.feed(answers, lab.device.lab_seconds() - before)?;
            }
            ArrayAction::Iteration(record) => {
                timeline.note(lab, run, &record);
                if record.tuned {
                    return Ok(Some(lab.minutes() - t0));
                }
                iterations += 1;
                if iterations >= cap {
                    return Ok(None);
                }
            }
            ArrayAction::Idle => return Ok(Some(lab.minutes() - t0)),
        }
    }
}

/// The lab's cross-cell virtual-gate calibration for one seed: the world's
/// `λ(1)`, `λ(2)` each times `1 + u`, `u` uniform in
/// `[−e, +e]` with `e` = [`ArrayProtocol::cross_compensation_error`], drawn
/// per seed (the array analogue of the single-cell benchmark's perturbed
/// virtual-gate matrix: configuration a lab calibrates, never exact).
pub fn lab_cross_calibration(array: &ArrayConfig, protocol: &ArrayProtocol, seed: u64) -> [f64; 2] {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x6372_6f73_7363_616c); // "crosscal"
    if let Some(given) = protocol.cross_calibration {
        return given;
    }
    let e = protocol.cross_compensation_error;
    let x = &array.crosstalk;
    [x.nearest, x.next].map(|l| {
        (l * (1.0 + e * rng.gen_range(-1.0..=1.0))).clamp(0.0, crate::sim::array::MAX_CROSSTALK)
    })
}

/// The nearest neighbours of cell `c` on the array's grid that are truly
/// out of band.
fn neighbours_out(lab: &Lab, c: u32, targets: &[(f64, f64)], band: f64) -> u64 {
    let config = lab.device.config();
    let grid = CellGrid::or_chain(config.layout, config.cells as usize);
    grid.within(c as usize, 1)
        .map(|n| n as u32)
        .filter(|&n| n != c)
        .filter(|&n| !truly_in_band(lab, n, targets[n as usize], band))
        .count() as u64
}

/// Summary of one strategy over runs (keys as in the JSON report).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArraySummary {
    /// Strategy name.
    pub name: String,
    /// Cold start, lab minutes: median, p90, max over converged runs.
    pub cold_start_lab_minutes: Quantiles,
    /// Set-point changes of all cells, lab minutes until all in band.
    pub lab_minutes_per_change: Quantiles,
    /// Single-cell changes, lab minutes until all in band.
    pub lab_minutes_per_single_cell_change: Quantiles,
    /// Changes (cold starts included) not converged.
    pub not_converged: u64,
    /// Of those, where the oracle on the same array and seed converged (`None` without oracle).
    pub not_converged_where_oracle_converged: Option<u64>,
    /// Neighbours of a changed cell truly out of band after its change.
    pub neighbours_left_out_of_band: u64,
    /// Moves the world refused.
    pub limit_violations: u64,
    /// Truth requests.
    pub truth_queries: u64,
    /// Failed fits.
    pub failed_fits: u64,
    /// Scans, all runs.
    pub measurements: u64,
    /// Runs (array × seed).
    pub runs: u64,
    /// Lab minutes of the whole protocol by request kind, mean per run.
    pub lab_minutes_by_kind: BTreeMap<String, f64>,
    /// The all-cell changes that converged: iterations until the first
    /// cell, half the cells and every cell were measured in band
    /// ([`band_entry`]), mean over the changes (`None`: no timeline, as
    /// for `serial` and `independent`, or no change converged).
    #[serde(default)]
    pub change_band_entry: Option<[f64; 3]>,
    /// The all-cell changes, each cell before it was first measured in band
    /// in its change: the medians of its learned own-gate rows' length
    /// against the truth's and of their cosine, `[[ratio, cosine] of t_sr,
    /// … of w]`, at the measurement each move was planned from
    /// ([`before_band`]; `None` without a learned tuner's timeline). For
    /// `oracle`, the rows its filter learns along its own trajectory: it
    /// plans with the true Jacobian instead.
    #[serde(default)]
    pub rows_before_band: Option<[[f64; 2]; 2]>,
}

/// Mean [`band_entry`] of the all-cell changes (phases 1…) of `runs`.
fn mean_band_entry(runs: &[&ArrayRunResult]) -> Option<[f64; 3]> {
    let entries: Vec<[usize; 3]> = runs
        .iter()
        .flat_map(|r| (1..=r.changes.len() as u32).filter_map(|ph| band_entry(&r.timeline, ph)))
        .collect();
    if entries.is_empty() {
        return None;
    }
    let n = entries.len() as f64;
    Some([0, 1, 2].map(|i| entries.iter().map(|e| e[i] as f64).sum::<f64>() / n))
}

/// [`before_band`] over the all-cell changes (phases 1…) of every run.
fn rows_before_band(runs: &[&ArrayRunResult]) -> Option<[[f64; 2]; 2]> {
    let timelines: Vec<&[TimelinePoint]> = runs.iter().map(|r| &r.timeline[..]).collect();
    let changes = runs.iter().map(|r| r.changes.len()).max().unwrap_or(0) as u32;
    let phases: Vec<u32> = (1..=changes).collect();
    before_band(&timelines, &phases)
}

/// A run's phases in order: the cold start, the all-cell changes, the
/// single-cell changes (lab minutes; `None`: not converged).
pub(crate) fn all_changes(r: &ArrayRunResult) -> Vec<Option<f64>> {
    std::iter::once(r.cold_start_lab_minutes)
        .chain(r.changes.iter().copied())
        .chain(r.single_cell_changes.iter().copied())
        .collect()
}

/// Aggregate results per strategy (in `strategies` order).
pub fn summarize_array(
    results: &[ArrayRunResult],
    strategies: &[ArrayStrategy],
) -> Vec<ArraySummary> {
    strategies
        .iter()
        .map(|&s| {
            let mine: Vec<&ArrayRunResult> = results.iter().filter(|r| r.strategy == s).collect();
            let cold: Vec<f64> = mine
                .iter()
                .filter_map(|r| r.cold_start_lab_minutes)
                .collect();
            let changes: Vec<f64> = mine
                .iter()
                .flat_map(|r| r.changes.iter().flatten().copied())
                .collect();
            let single: Vec<f64> = mine
                .iter()
                .flat_map(|r| r.single_cell_changes.iter().flatten().copied())
                .collect();
            let not_converged = mine
                .iter()
                .map(|r| all_changes(r).iter().filter(|c| c.is_none()).count() as u64)
                .sum();
            let has_oracle = results.iter().any(|r| r.strategy == ArrayStrategy::Oracle);
            let where_oracle = has_oracle.then(|| {
                mine.iter()
                    .map(|r| {
                        let Some(o) = results.iter().find(|o| {
                            o.strategy == ArrayStrategy::Oracle
                                && o.seed == r.seed
                                && o.device == r.device
                        }) else {
                            return 0;
                        };
                        all_changes(r)
                            .iter()
                            .zip(all_changes(o))
                            .filter(|(a, b)| a.is_none() && b.is_some())
                            .count() as u64
                    })
                    .sum()
            });
            ArraySummary {
                name: s.name().into(),
                cold_start_lab_minutes: quantiles(&cold),
                lab_minutes_per_change: quantiles(&changes),
                lab_minutes_per_single_cell_change: quantiles(&single),
                not_converged,
                not_converged_where_oracle_converged: where_oracle,
                neighbours_left_out_of_band: mine
                    .iter()
                    .map(|r| r.neighbours_left_out_of_band)
                    .sum(),
                limit_violations: mine.iter().map(|r| r.limit_violations).sum(),
                truth_queries: mine.iter().map(|r| r.truth_queries).sum(),
                failed_fits: mine.iter().map(|r| r.failed_fits).sum(),
                measurements: mine.iter().map(|r| r.measurements).sum(),
                runs: mine.len() as u64,
                lab_minutes_by_kind: {
                    let mut by: BTreeMap<String, f64> = BTreeMap::new();
                    for r in &mine {
                        for (k, m) in &r.lab_minutes_by_kind {
                            *by.entry(k.clone()).or_default() += m / mine.len() as f64;
                        }
                    }
                    by
                },
                change_band_entry: mean_band_entry(&mine),
                rows_before_band: rows_before_band(&mine),
            }
        })
        .collect()
}

/// The summaries as a markdown table.
pub fn markdown(summaries: &[ArraySummary]) -> String {
    let f = |x: f64| {
        if x.is_finite() {
            format!("{x:.1}")
        } else {
            "–".into()
        }
    };
    let mut s = String::from(
        "| strategy | cold start lab min median | p90 | change (all cells) lab min median | p90 | single-cell change lab min median | p90 | not converged | not converged where the oracle converged | neighbours left out of band | limit violations | truth queries | failed fits | measurements | runs |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for x in summaries {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            x.name,
            f(x.cold_start_lab_minutes.median),
            f(x.cold_start_lab_minutes.p90),
            f(x.lab_minutes_per_change.median),
            f(x.lab_minutes_per_change.p90),
            f(x.lab_minutes_per_single_cell_change.median),
            f(x.lab_minutes_per_single_cell_change.p90),
            x.not_converged,
            x.not_converged_where_oracle_converged
                .map_or("–".into(), |n| n.to_string()),
            x.neighbours_left_out_of_band,
            x.limit_violations,
            x.truth_queries,
            x.failed_fits,
            x.measurements,
            x.runs,
        ));
    }
    // where the lab time goes
    let kinds = [
        "reload_time",
        "transition_width",
        "sensing_dot",
        "chemical_potential",
        "set_voltages",
    ];
    s.push_str("\nLab minutes of the whole protocol by request kind, mean per run (a batch's time split over its requests by their own lab time):\n\n| strategy | t_sr scans | w scans | sensing-dot sweeps | line scans | sets | other |\n|---|---|---|---|---|---|---|\n");
    for x in summaries {
        let get = |k: &str| x.lab_minutes_by_kind.get(k).copied().unwrap_or(0.0);
        let other: f64 = x
            .lab_minutes_by_kind
            .iter()
            .filter(|(k, _)| !kinds.contains(&k.as_str()))
            .map(|(_, m)| m)
            .sum::<f64>()
            + 0.0; // (an empty sum is −0)
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} |\n",
            x.name,
            f(get(kinds[0])),
            f(get(kinds[1])),
            f(get(kinds[2])),
            f(get(kinds[3])),
            f(get(kinds[4])),
            f(other)
        ));
    }
    if summaries.iter().any(|x| x.rows_before_band.is_some()) {
        s.push_str("\nLearned own-gate rows against the truth (world side) at the measurement each move was planned from, cells of the all-cell changes before they first came into band: medians of |learned|/|true| and of the cosine between them (log space; `oracle`: the rows its filter learns on its trajectory, it plans with the truth):\n\n| strategy | t_sr length | t_sr cosine | w length | w cosine |\n|---|---|---|---|---|\n");
        for x in summaries {
            if let Some([[tl, tc], [wl, wc]]) = x.rows_before_band {
                s.push_str(&format!(
                    "| {} | {tl:.2} | {tc:.2} | {wl:.2} | {wc:.2} |\n",
                    x.name
                ));
            }
        }
    }
    if summaries.iter().any(|x| x.change_band_entry.is_some()) {
        s.push_str("\nAll-cell changes that converged: iterations (mean) until cells were measured in band at once (a long tail: `every cell` far beyond `first cell`):\n\n| strategy | first cell | half the cells | every cell |\n|---|---|---|---|\n");
        for x in summaries {
            if let Some([first, half, every]) = x.change_band_entry {
                s.push_str(&format!(
                    "| {} | {} | {} | {} |\n",
                    x.name,
                    f(first),
                    f(half),
                    f(every)
                ));
            }
        }
    }
    s
}
