//! The sans-IO tuner state machine (ARCHITECTURE.md, invariant 2).
//!
//! The tuner never calls a device. [`Tuner::poll`] returns the next
//! [`Action`]: a [`Request`] for the driver to execute (and answer with
//! [`Tuner::feed`]), a finished top-level [`IterationRecord`], or
//! [`Action::Finished`]. The same machine is driven by the async backend,
//! the in-browser simulator and the benchmarks.
//!
//! # Hierarchy
//! A tuner is a list of levels (`levels[0]` is the top). After each move of a
//! level, the levels named in its `after_move` run to completion, in order —
//! the paper's structure: move N/SA/SB/T (with a linear virtual-gate correction
//! on PA/PB), re-tune the sensing dot, compensate the chemical potentials with
//! a Kalman-tuned PA/PB level (which itself re-tunes the sensing dot after each
//! of its moves), then measure w and t_sr again.
//!
//! Internally every active level is an entry on a stack (`ActiveLevel`) holding a queue of
//! micro-operations (move, measure, run child, decide); the whole machine is
//! plain data and serde-serializable, so a checkpoint taken after any
//! [`Action::Iteration`] resumes bit-identically (invariant 4).
//!
//! ```
//! use spintune::driver::{SimulationConfig, SimulationRun};
//! let mut cfg = SimulationConfig::paper_default();
//! cfg.tuner.max_iterations = Some(2);
//! let mut run = SimulationRun::new(cfg).unwrap();
//! let first = run.next_iteration().unwrap().unwrap();
//! assert_eq!(first.iteration, 0);
//! assert_eq!(first.gates, ["N", "SA", "SB", "T"]);
//! ```

pub mod array;
pub mod array_run;
pub mod array_run_settings;
pub mod block_trust_region;
pub mod borrowed_gradient;
mod config;
pub mod curvature;
pub mod excitation;
pub mod finite_difference;
mod flank;
pub mod flat_reset;
mod gate_row;
pub mod in_band;
mod keep;
mod keep_tally;
pub mod lagging;
pub(crate) mod level_forecast;
pub mod line_steps;
pub mod miss_cusum;
mod newton;
pub mod pooled_gradient;
mod search;
pub mod shrink;
pub mod stall;
pub mod thermal_floor;

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

pub use config::{check_magnitudes, MAX_GATE_MV, MAX_INTEGER, MAX_MAGNITUDE};
pub use config::{
    Compensation, ConfigError, FlankPrediction, InitialGradient, LevelConfig, LevelKind,
    NewtonConfig, ParameterForecast, ScheduledTargets, SensingDotConfig, SensingDotFallback,
    TunerConfig, MAX_FALLBACK_SWEEPS, MAX_FLANK_SKIPS, MAX_SWEEP_POINTS,
};
use flank::{FlankForecast, FlankModel};
pub use keep::{DriftModel, KeepConfig, KeepSchedule, MAX_KEEP_SECONDS, MIN_CHECK_INTERVAL_S};
use keep::{KeepNext, KeepState};
pub use keep_tally::KeepTally;
use level_forecast::LevelForecast;
pub use newton::Consistency;
use newton::NewtonState;
pub use search::{ParameterSearch, MAX_SEARCH_PROBES};

use crate::parameter::Tolerance;
use crate::protocol::{
    EventKind, IterationRecord, ParameterValue, Request, Response, ScanKind, ScanOutcome,
    ScanReport, ScanRequest, Sweep, TunerEvent,
};
use crate::safety::SafetyLimits;

/// One Jacobian row (unit/mV, estimator space) and its covariance, if the estimator has one.
pub type GradientRow = (DVector<f64>, Option<DMatrix<f64>>);

/// What the driver should do next.
#[derive(Debug, Clone, PartialEq)]
// An iteration record is handed out once per iteration (not per request):
// moving it is cheaper than an allocation per record.
#[allow(clippy::large_enum_variant)]
pub enum Action {
    /// Execute this request and [`Tuner::feed`] the response.
    Request(Request),
    /// A top-level iteration finished: persist / display it, then poll again.
    Iteration(IterationRecord),
    /// The tuner is done (tuned with `stop_when_tuned`, or `max_iterations` reached).
    Finished,
}

/// Why a response could not be taken. The tuner state is unchanged; polling
/// again re-issues the same request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TunerError {
    /// A response arrived although no request is outstanding.
    #[error("no request is outstanding")]
    NothingPending,
    /// The response does not answer the outstanding request.
    #[error("response does not answer the outstanding {expected} request")]
    UnexpectedResponse {
        /// What was expected.
        expected: &'static str,
    },
    /// The device reported an error.
    #[error("device error: {0}")]
    Device(String),
    /// Unknown parameter in [`Tuner::set_target`].
    #[error("unknown parameter {0:?}")]
    UnknownParameter(String),
    /// Invalid target or tolerance.
    #[error("invalid target for {parameter}: {message}")]
    InvalidTarget {
        /// Parameter name.
        parameter: String,
        /// What is wrong.
        message: String,
    },
}

/// One micro-operation of a level's queue.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Op {
    /// Move the level's gates to these absolute voltages (mV), with compensation.
    Move(Vec<f64>),
    /// Set one gate to an absolute voltage (mV).
    SetGate(String, f64),
    /// Run a scan; the result is absorbed into the level's state.
    Measure(ScanRequest),
    /// Ask the device for the true Jacobian (oracle).
    QueryJacobian,
    /// Run a child level to completion.
    Child(usize),
    /// Let the level decide what comes next.
    Decide(Decision),
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
enum Decision {
    /// Base measurement of a finite-difference repetition is in.
    FdBase(usize),
    /// Offset measurement (repetition, gate) is in.
    FdPoint(usize, usize),
    /// All finite-difference measurements are in.
    FdFinish,
    /// Parameters measured: update the estimator, test for tuned.
    Evaluate,
    /// Compute and queue the Newton step.
    Step,
    /// The level's round is complete.
    EndIteration,
    /// Sensing-dot sweep is in: park the gate on the flank.
    SdPark,
    /// A sweep of the 2-D fallback is in (`base_mv`: the second gate's voltage
    /// before the fallback): park on a flank if found and stop the raster.
    SdFallbackPoint { base_mv: f64 },
    /// No sweep of the fallback found a flank: the second gate goes back to `base_mv`.
    SdFallbackFinish { base_mv: f64 },
    /// Keep mode: a check's scans are in.
    KeepCheck,
    /// A child level corrects from its forecast instead of scanning.
    Forecast,
}

/// A level that is running: its queue of micro-operations (one entry of
/// the tuner's stack; the serialized shape is unchanged from when this was
/// called `Frame`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ActiveLevel {
    level: usize,
    ops: VecDeque<Op>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Pending {
    /// A set request, with the operation (and its level) that planned it, so
    /// it can be re-planned when the instrument reads back elsewhere.
    Set(Request, Op),
    Measure(Request, usize),
    Jacobian(Request, usize),
    /// Keep mode lets lab time pass.
    Wait(Request),
}

impl Pending {
    fn request(&self) -> &Request {
        match self {
            Pending::Set(r, _)
            | Pending::Measure(r, _)
            | Pending::Jacobian(r, _)
            | Pending::Wait(r) => r,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[allow(clippy::large_enum_variant)]
enum LevelState {
    Newton(NewtonState),
    SensingDot {
        last: Option<ParameterValue>,
        /// The flank's learned model (`Some` iff the level has `prediction`).
        #[serde(default)]
        flank: Option<FlankModel>,
    },
}

/// The tuner: configuration, learned gradients, position in the hierarchy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Tuner {
    config: TunerConfig,
    safety: SafetyLimits,
    voltages_mv: BTreeMap<String, f64>,
    levels: Vec<LevelState>,
    stack: Vec<ActiveLevel>,
    pending: Option<Pending>,
    iteration: u64,
    lab_seconds: f64,
    scan_counts: BTreeMap<ScanKind, u64>,
    failed_evaluations: u64,
    finished: bool,
    /// Events since the last iteration record, oldest first.
    events: Vec<TunerEvent>,
    /// Keep mode's state (`None` unless the config has `keep`).
    #[serde(default)]
    keep: Option<KeepState>,
}

impl Tuner {
    /// A tuner at the configured initial voltages. The config is validated.
    pub fn new(config: TunerConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        let safety = SafetyLimits::new(&config.gates);
        let voltages_mv = config
            .gates
            .iter()
            .map(|g| (g.name.clone(), g.initial_mv))
            .collect();
        let mut levels = Vec::new();
        for (i, l) in config.levels.iter().enumerate() {
            levels.push(match &l.kind {
                LevelKind::Newton(n) => {
                    let mut state =
                        NewtonState::new(n).map_err(|e| e.within(&format!("levels[{i}]")))?;
                    state.forecast = n.forecast.as_ref().map(|f| {
                        let others = config.gates.iter().map(|g| g.name.clone());
                        LevelForecast::new(
                            others.filter(|g| !n.gates.contains(g)).collect(),
                            n.parameters.len(),
                            f.prior_lever_per_mv,
                            compensation_onto(&config, &n.gates),
                        )
                    });
                    LevelState::Newton(state)
                }
                LevelKind::SensingDot(sd) => LevelState::SensingDot {
                    last: None,
                    flank: sd.prediction.as_ref().map(|p| {
                        let others = config.gates.iter().map(|g| g.name.clone());
                        FlankModel::new(others.filter(|g| *g != sd.gate).collect(), p)
                    }),
                },
            });
        }
        Ok(Self {
            safety,
            voltages_mv,
            levels,
            stack: Vec::new(),
            pending: None,
            iteration: 0,
            lab_seconds: 0.0,
            scan_counts: BTreeMap::new(),
            failed_evaluations: 0,
            finished: false,
            events: Vec::new(),
            keep: config
                .keep
                .as_ref()
                .map(|_| KeepState::new(config.top().parameters.len())),
            config,
        })
    }

    /// The configuration, including targets as changed by [`Tuner::set_target`].
    pub fn config(&self) -> &TunerConfig {
        &self.config
    }

    /// The gate limits every request is checked against.
    pub fn safety(&self) -> &SafetyLimits {
        &self.safety
    }

    /// Voltages as last read back from the device, mV.
    pub fn voltages_mv(&self) -> &BTreeMap<String, f64> {
        &self.voltages_mv
    }

    /// Number of completed top-level iterations.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    /// Cumulative lab time reported by the device, s.
    pub fn lab_seconds(&self) -> f64 {
        self.lab_seconds
    }

    /// Scans run so far, per kind.
    pub fn scan_counts(&self) -> &BTreeMap<ScanKind, u64> {
        &self.scan_counts
    }

    /// Failed or rejected evaluations so far.
    pub fn failed_evaluations(&self) -> u64 {
        self.failed_evaluations
    }

    /// Whether [`Action::Finished`] has been reached.
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Allow further iterations after the tuner finished (e.g. after a target change).
    pub fn set_max_iterations(&mut self, max: Option<u64>) {
        self.config.max_iterations = max;
        self.finished = false;
    }

    /// Gradient rows (estimator space) and covariances of a Newton level, once initialised.
    pub fn gradients(&self, level: usize) -> Option<Vec<GradientRow>> {
        match self.levels.get(level)? {
            LevelState::Newton(n) => n.gradients(),
            LevelState::SensingDot { .. } => None,
        }
    }

    /// The last values a Newton level measured (its parameters in config
    /// order, parameter units; `None` where the last scan gave none), e.g.
    /// the start values of the initial finite-difference measurement.
    pub fn last_measured(&self, level: usize) -> Option<&[Option<ParameterValue>]> {
        match self.levels.get(level)? {
            LevelState::Newton(n) => Some(n.last_measured()),
            LevelState::SensingDot { .. } => None,
        }
    }

    /// How well a sensing-dot level's predicted flanks
    /// ([`FlankPrediction`]) matched the sweep that followed them:
    /// normalised innovations (mV); `None` for levels without a prediction.
    pub fn flank_consistency(&self, level: usize) -> Option<Consistency> {
        match self.levels.get(level)? {
            LevelState::SensingDot {
                flank: Some(model), ..
            } => Some(model.consistency()),
            _ => None,
        }
    }

    /// How well a child level's forecasts ([`ParameterForecast`]) predicted
    /// the scan that followed them: normalised innovations per parameter
    /// (config order); `None` for levels without a forecast.
    pub fn forecast_consistency(&self, level: usize) -> Option<&[Consistency]> {
        match self.levels.get(level)? {
            LevelState::Newton(n) => n.forecast.as_ref().map(|f| f.consistency()),
            LevelState::SensingDot { .. } => None,
        }
    }

    /// Filter consistency (normalised innovations squared) of a Newton
    /// level's estimators, per parameter in config order.
    pub fn consistency(&self, level: usize) -> Option<&[Consistency]> {
        match self.levels.get(level)? {
            LevelState::Newton(n) => Some(n.consistency()),
            LevelState::SensingDot { .. } => None,
        }
    }

    /// The config with every initialised Newton level's present gradient as
    /// [`InitialGradient::Given`]: start other tuners from what this one measured.
    pub fn config_with_learned_gradients(&self) -> TunerConfig {
        let mut cfg = self.config.clone();
        for (i, level) in cfg.levels.iter_mut().enumerate() {
            if let (LevelKind::Newton(n), Some(rows)) = (&mut level.kind, self.gradients(i)) {
                let k = n.gates.len();
                n.initial_gradient = InitialGradient::Given {
                    gradient: rows
                        .iter()
                        .map(|(g, _)| g.iter().copied().collect())
                        .collect(),
                    covariance: rows
                        .iter()
                        .map(|(_, c)| {
                            let c = c.clone().unwrap_or_else(|| DMatrix::zeros(k, k));
                            (0..k)
                                .map(|r| (0..k).map(|s| c[(r, s)]).collect())
                                .collect()
                        })
                        .collect(),
                };
            }
        }
        cfg
    }

    /// Change a parameter's target and/or tolerance; takes effect at its next evaluation.
    /// `tolerance: None` keeps the present tolerance.
    pub fn set_target(
        &mut self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(), TunerError> {
        let (level, index) = self.validate_target(parameter, target, tolerance)?;
        if let LevelKind::Newton(n) = &mut self.config.levels[level].kind {
            let p = &mut n.parameters[index];
            p.target = target;
            if let Some(tol) = tolerance {
                p.tolerance = tol;
            }
        }
        if self.config.stop_when_tuned || self.keep.is_some() {
            // a new target may need more work; max_iterations still applies
            self.finished = false;
        }
        if let Some(k) = &mut self.keep {
            if level == 0 {
                k.target_changed();
            }
        }
        Ok(())
    }

    /// Check a target change without applying it (as [`Tuner::set_target`]
    /// would); returns the (level, parameter index) it would change.
    pub fn validate_target(
        &self,
        parameter: &str,
        target: Option<f64>,
        tolerance: Option<Tolerance>,
    ) -> Result<(usize, usize), TunerError> {
        let invalid = |m: &str| TunerError::InvalidTarget {
            parameter: parameter.to_string(),
            message: m.to_string(),
        };
        if let Some(tol) = tolerance {
            tol.validate()
                .map_err(|e| invalid(&format!("tolerance {}", e.clause())))?;
        }
        for (level, l) in self.config.levels.iter().enumerate() {
            if let LevelKind::Newton(n) = &l.kind {
                if let Some(index) = n.parameters.iter().position(|p| p.name == parameter) {
                    let p = &n.parameters[index];
                    if let Some(t) = target {
                        p.check_target(t)
                            .map_err(|e| invalid(&format!("target {}", e.message)))?;
                    }
                    return Ok((level, index));
                }
            }
        }
        Err(TunerError::UnknownParameter(parameter.to_string()))
    }

    /// The request handed out by [`Tuner::poll`] and not yet answered.
    pub fn pending_request(&self) -> Option<&Request> {
        self.pending.as_ref().map(Pending::request)
    }

    /// The instrument read back `readback` (gate → mV): the tuner plans from
    /// these values from now on. A gate whose belief changes by more than
    /// `tolerance_mv` is reported as [`EventKind::InstrumentMoved`]. If an
    /// outstanding set request was planned from a belief that changed, it is
    /// withdrawn and re-planned from the read-back at the next [`Tuner::poll`]
    /// (same goal, step clipped from where the gates really are). Returns
    /// whether a request was withdrawn. Unknown gates and non-finite values
    /// are ignored (the session refuses such read-backs before they get here).
    pub fn adopt_readback(&mut self, readback: &BTreeMap<String, f64>, tolerance_mv: f64) -> bool {
        let mut changed = Vec::new();
        for (gate, &read) in readback {
            let Some(belief) = self.voltages_mv.get_mut(gate) else {
                continue;
            };
            if !read.is_finite() || *belief == read {
                continue;
            }
            if (*belief - read).abs() > tolerance_mv {
                let expected_mv = *belief;
                self.events.push(TunerEvent {
                    level: self.config.levels[0].name.clone(),
                    kind: EventKind::InstrumentMoved {
                        gate: gate.clone(),
                        expected_mv,
                        read_mv: read,
                    },
                });
            }
            *belief = read;
            changed.push(gate.clone());
        }
        let replan = matches!(
            &self.pending,
            Some(Pending::Set(Request::SetVoltages { voltages_mv }, _))
                if changed.iter().any(|g| voltages_mv.contains_key(g))
        );
        if replan {
            if let Some(Pending::Set(_, op)) = self.pending.take() {
                if let Some(active) = self.stack.last_mut() {
                    active.ops.push_front(op);
                }
            }
        }
        replan
    }

    /// The next thing to do. Calling it again without [`Tuner::feed`] returns the
    /// same outstanding request.
    pub fn poll(&mut self) -> Action {
        if let Some(p) = &self.pending {
            return Action::Request(p.request().clone());
        }
        loop {
            if self.finished {
                return Action::Finished;
            }
            let Some(active) = self.stack.last_mut() else {
                if let LevelState::Newton(top) = &self.levels[0] {
                    if !top.is_initialised() {
                        let ops = self.init_ops(0);
                        self.stack.push(ActiveLevel { level: 0, ops });
                        continue;
                    }
                }
                if self
                    .config
                    .max_iterations
                    .is_some_and(|m| self.iteration >= m)
                {
                    self.finished = true;
                    continue;
                }
                self.apply_schedule();
                match self.keep_next() {
                    None | Some(KeepNext::Tune) => self.push_level(0),
                    Some(KeepNext::Wait(req)) => {
                        self.pending = Some(Pending::Wait(req.clone()));
                        return Action::Request(req);
                    }
                    Some(KeepNext::Check(ops)) => self.stack.push(ActiveLevel {
                        level: 0,
                        ops: ops.into(),
                    }),
                    Some(KeepNext::Finish) => self.finished = true,
                }
                continue;
            };
            let level = active.level;
            let Some(op) = active.ops.pop_front() else {
                self.stack.pop();
                continue;
            };
            match op {
                Op::Move(target) => {
                    if let Some(req) = self.move_request(level, &target) {
                        self.pending = Some(Pending::Set(req.clone(), Op::Move(target)));
                        return Action::Request(req);
                    }
                }
                Op::SetGate(gate, v) => {
                    let present = self.voltages_mv.get(&gate).copied().unwrap_or(v);
                    let clipped = self.safety.clip(&gate, present, v);
                    let req = BTreeMap::from([(gate.clone(), clipped)]);
                    if self.safety.check(&self.voltages_mv, &req).is_ok() {
                        let req = Request::SetVoltages { voltages_mv: req };
                        self.pending = Some(Pending::Set(req.clone(), Op::SetGate(gate, v)));
                        return Action::Request(req);
                    }
                }
                Op::Measure(scan) => {
                    let req = Request::Measure { scan };
                    self.pending = Some(Pending::Measure(req.clone(), level));
                    return Action::Request(req);
                }
                Op::QueryJacobian => {
                    let req = self.jacobian_request(level);
                    self.pending = Some(Pending::Jacobian(req.clone(), level));
                    return Action::Request(req);
                }
                Op::Child(child) => self.push_level(child),
                Op::Decide(d) => {
                    if let Some(mut record) = self.decide(level, d) {
                        self.iteration += 1;
                        if self.keep.is_some() {
                            // keep mode decides when the run ends
                            self.keep_after_record(&mut record);
                        } else if self.config.stop_when_tuned && record.tuned {
                            self.finished = true;
                        }
                        return Action::Iteration(record);
                    }
                }
            }
        }
    }

    /// Answer the outstanding request. On error the state is unchanged and the
    /// same request will be polled again.
    pub fn feed(&mut self, response: Response) -> Result<(), TunerError> {
        let pending = self.pending.as_ref().ok_or(TunerError::NothingPending)?;
        if let Response::Error { message, .. } = &response {
            return Err(TunerError::Device(message.clone()));
        }
        match (pending, response) {
            (
                Pending::Set(..),
                Response::VoltagesSet {
                    voltages_mv,
                    lab_seconds,
                },
            ) => {
                for (g, v) in voltages_mv {
                    if v.is_finite() && self.voltages_mv.contains_key(&g) {
                        self.voltages_mv.insert(g, v);
                    }
                }
                self.add_lab_time(lab_seconds);
            }
            (
                Pending::Measure(req, level),
                Response::Scanned {
                    outcome,
                    lab_seconds,
                },
            ) => {
                let level = *level;
                let kind = match req {
                    Request::Measure { scan } => scan.kind,
                    _ => unreachable!("measure pending holds a measure request"),
                };
                *self.scan_counts.entry(kind).or_insert(0) += 1;
                self.add_lab_time(lab_seconds);
                let (values, failure, report) =
                    evaluate_outcome(outcome, &self.config.fit_references);
                if let Some(e) = failure {
                    // the scan (or a part of it: one line of two) gave no value
                    self.failed_evaluations += 1;
                    self.note(
                        level,
                        EventKind::EvaluationFailed {
                            scan: kind,
                            reason: e,
                        },
                    );
                }
                match &mut self.levels[level] {
                    LevelState::Newton(n) => n.absorb(values, report),
                    LevelState::SensingDot { last, .. } => {
                        *last = values.into_iter().find(|p| p.name == "sd_flank_mv");
                    }
                }
            }
            (Pending::Wait(_), Response::Waited { lab_seconds }) => {
                self.add_lab_time(lab_seconds);
            }
            (Pending::Wait(_), _) => {
                return Err(TunerError::UnexpectedResponse { expected: "waited" })
            }
            (Pending::Jacobian(_, level), Response::TrueJacobian { values, jacobian }) => {
                let level = *level;
                if let LevelState::Newton(n) = &mut self.levels[level] {
                    n.oracle = Some((values, jacobian));
                }
            }
            (Pending::Set(..), _) => {
                return Err(TunerError::UnexpectedResponse {
                    expected: "set_voltages",
                })
            }
            (Pending::Measure(..), _) => {
                return Err(TunerError::UnexpectedResponse {
                    expected: "measure",
                })
            }
            (Pending::Jacobian(..), _) => {
                return Err(TunerError::UnexpectedResponse {
                    expected: "true_jacobian",
                })
            }
        }
        self.pending = None;
        Ok(())
    }

    /// Targets scheduled for the iteration about to start (config already validated).
    fn apply_schedule(&mut self) {
        let due: Vec<(String, f64)> = self
            .config
            .schedule
            .iter()
            .filter(|s| s.at_iteration == self.iteration)
            .flat_map(|s| s.targets.iter().map(|(p, t)| (p.clone(), *t)))
            .collect();
        for (parameter, target) in due {
            if let Err(e) = self.set_target(&parameter, Some(target), None) {
                self.note(
                    0,
                    EventKind::ScheduledTargetNotApplied {
                        reason: e.to_string(),
                    },
                );
            }
        }
    }

    /// Add lab time spent outside the tuner's own requests (e.g. the session's
    /// read-backs), s. Non-finite or negative values are ignored.
    pub fn charge_lab_time(&mut self, seconds: f64) {
        self.add_lab_time(seconds);
    }

    fn add_lab_time(&mut self, s: f64) {
        if s.is_finite() && s > 0.0 {
            self.lab_seconds += s;
        }
    }

    /// Record an event of `level` for the next iteration record.
    fn note(&mut self, level: usize, kind: EventKind) {
        self.events.push(TunerEvent {
            level: self.config.levels[level].name.clone(),
            kind,
        });
    }

    /// The sensing-dot sweep of `sd` around its gate's present voltage.
    fn sd_sweep(&self, sd: &SensingDotConfig) -> Op {
        let present = self.voltages_mv.get(&sd.gate).copied().unwrap_or(0.0);
        let spec = self.safety.gate(&sd.gate);
        let lo = spec.map_or(f64::NEG_INFINITY, |s| s.min_mv);
        let hi = spec.map_or(f64::INFINITY, |s| s.max_mv);
        Op::Measure(ScanRequest {
            kind: ScanKind::SensingDot,
            sweep: Some(Sweep {
                gate: sd.gate.clone(),
                from_mv: (present - sd.half_width_mv).max(lo),
                to_mv: (present + sd.half_width_mv).min(hi),
                points: sd.points,
            }),
            cell: None,
        })
    }

    /// The flank predicted confidently enough to skip the sweep
    /// ([`SensingDotConfig::prediction`]); counts the skip.
    fn flank_forecast(&mut self, level: usize, sd: &SensingDotConfig) -> Option<FlankForecast> {
        let p = sd.prediction.as_ref()?;
        let failed = self.failed_evaluations;
        let spec = self.safety.gate(&sd.gate)?;
        let (lo, hi) = (spec.min_mv, spec.max_mv);
        let LevelState::SensingDot {
            flank: Some(model), ..
        } = &mut self.levels[level]
        else {
            return None;
        };
        if model.failed_at_sweep != failed {
            return None;
        }
        let parked = self.voltages_mv.get(&sd.gate).copied()?;
        let f = model.confident(&self.voltages_mv, p, (lo, hi), parked, sd.half_width_mv)?;
        model.skips += 1;
        Some(f)
    }

    /// A sweep found the flank: the flank model learns from it.
    fn observe_flank(&mut self, level: usize, sd: &SensingDotConfig, flank: &ParameterValue) {
        let failed = self.failed_evaluations;
        let noise = sd.prediction.as_ref().map_or(0.0, |p| p.noise_mv);
        if let LevelState::SensingDot {
            flank: Some(model), ..
        } = &mut self.levels[level]
        {
            model.observe(&self.voltages_mv, flank.value, flank.variance, noise);
            model.failed_at_sweep = failed;
        }
    }

    /// A sensing-dot call: park on the predicted flank, or sweep and park.
    fn sensing_dot_ops(&mut self, level: usize, sd: &SensingDotConfig) -> VecDeque<Op> {
        match self.flank_forecast(level, sd) {
            Some(f) => {
                self.note(
                    level,
                    EventKind::SweepSkipped {
                        gate: sd.gate.clone(),
                        predicted_mv: f.flank_mv,
                        std_mv: f.std_mv,
                    },
                );
                VecDeque::from([Op::SetGate(sd.gate.clone(), f.flank_mv)])
            }
            None => VecDeque::from([self.sd_sweep(sd), Op::Decide(Decision::SdPark)]),
        }
    }

    fn push_level(&mut self, level: usize) {
        let ops = match &self.config.levels[level].kind {
            LevelKind::SensingDot(sd) => {
                let sd = sd.clone();
                self.sensing_dot_ops(level, &sd)
            }
            LevelKind::Newton(_) => {
                let mut ops = self.init_ops(level);
                if let LevelState::Newton(n) = &mut self.levels[level] {
                    n.iterations_this_call = 0;
                    if level != 0 {
                        // The parent moved other gates since this level's last call: its
                        // observation model (only its own gates move) no longer links the
                        // old reference to the new measurement. Start a fresh baseline,
                        // and forget where its scans last worked: its own gates there
                        // go with the parent's old gates (a retreat toward them after a
                        // failed scan would undo the parent's compensation).
                        n.parent_moved();
                    }
                }
                if ops.is_empty() && self.confident_forecast(level).is_some() {
                    ops.push_back(Op::Decide(Decision::Forecast));
                } else {
                    ops.extend(self.round_ops(level));
                }
                ops
            }
        };
        self.stack.push(ActiveLevel { level, ops });
    }

    fn push_ops(&mut self, ops: impl IntoIterator<Item = Op>) {
        let active = self
            .stack
            .last_mut()
            .expect("decisions run inside an active level");
        // decisions queue their follow-ups before whatever the level still holds
        let mut new: VecDeque<Op> = ops.into_iter().collect();
        new.extend(active.ops.drain(..));
        active.ops = new;
    }

    fn after_move_ops(&self, level: usize) -> Vec<Op> {
        self.config.levels[level]
            .after_move
            .iter()
            .filter_map(|name| self.config.level_index(name))
            .map(Op::Child)
            .collect()
    }

    fn move_request(&mut self, level: usize, target: &[f64]) -> Option<Request> {
        let LevelKind::Newton(cfg) = &self.config.levels[level].kind else {
            return None;
        };
        let mut req = BTreeMap::new();
        let mut dv_actual = Vec::with_capacity(cfg.gates.len());
        for (g, &t) in cfg.gates.iter().zip(target) {
            let present = self.voltages_mv[g];
            let v = self.safety.clip(g, present, t);
            dv_actual.push(v - present);
            req.insert(g.clone(), v);
        }
        if let Some(comp) = &cfg.compensation {
            for (row, g) in comp.matrix.iter().zip(&comp.gates) {
                let present = self.voltages_mv[g];
                let shift: f64 = row.iter().zip(&dv_actual).map(|(m, d)| m * d).sum();
                req.insert(g.clone(), self.safety.clip(g, present, present + shift));
            }
        }
        // The choke point: never emit a request the limits refuse.
        if let Err(e) = self.safety.check(&self.voltages_mv, &req) {
            self.note(
                level,
                EventKind::MoveRefused {
                    reason: e.to_string(),
                },
            );
            return None;
        }
        Some(Request::SetVoltages { voltages_mv: req })
    }

    fn jacobian_request(&self, level: usize) -> Request {
        let LevelKind::Newton(cfg) = &self.config.levels[level].kind else {
            unreachable!("only Newton levels query Jacobians")
        };
        Request::TrueJacobian {
            gates: cfg.gates.clone(),
            parameters: cfg.parameters.iter().map(|p| p.name.clone()).collect(),
        }
    }

    fn level_voltages(&self, level: usize) -> Vec<f64> {
        match &self.config.levels[level].kind {
            LevelKind::Newton(cfg) => cfg.gates.iter().map(|g| self.voltages_mv[g]).collect(),
            LevelKind::SensingDot(_) => Vec::new(),
        }
    }

    fn decide(&mut self, level: usize, d: Decision) -> Option<IterationRecord> {
        if d == Decision::KeepCheck {
            return self.keep_check();
        }
        if let Decision::SdPark
        | Decision::SdFallbackPoint { .. }
        | Decision::SdFallbackFinish { .. } = d
        {
            let LevelKind::SensingDot(sd) = &self.config.levels[level].kind else {
                return None;
            };
            let sd = sd.clone();
            let flank = match &self.levels[level] {
                LevelState::SensingDot { last: Some(p), .. } => Some(p.clone()),
                _ => None,
            };
            if let (Decision::SdPark | Decision::SdFallbackPoint { .. }, Some(p)) = (d, &flank) {
                self.observe_flank(level, &sd, p);
            }
            let flank = flank.map(|p| p.value);
            match (d, flank) {
                (Decision::SdPark, Some(v)) => self.push_ops([Op::SetGate(sd.gate, v)]),
                (Decision::SdPark, None) => {
                    // No flank in the 1-D sweep: the 2-D raster, if configured.
                    if let Some(fb) = &sd.fallback {
                        let base_mv = self.voltages_mv.get(&fb.gate).copied().unwrap_or(0.0);
                        let mut ops = Vec::new();
                        for o in &fb.offsets_mv {
                            ops.push(Op::SetGate(fb.gate.clone(), base_mv + o));
                            ops.push(self.sd_sweep(&sd));
                            ops.push(Op::Decide(Decision::SdFallbackPoint { base_mv }));
                        }
                        ops.push(Op::Decide(Decision::SdFallbackFinish { base_mv }));
                        self.push_ops(ops);
                    }
                }
                (Decision::SdFallbackPoint { .. }, Some(v)) => {
                    // found: stop the raster here and park
                    if let Some(active) = self.stack.last_mut() {
                        active.ops.clear();
                    }
                    self.push_ops([Op::SetGate(sd.gate, v)]);
                }
                (Decision::SdFallbackFinish { base_mv }, _) => {
                    if let Some(fb) = &sd.fallback {
                        self.push_ops([Op::SetGate(fb.gate.clone(), base_mv)]);
                    }
                }
                _ => {}
            }
            return None;
        }
        self.decide_newton(level, d)
    }
}

/// Every gate whose moves some level compensates onto `gates` (a parent's
/// virtual-gate matrix): that gate and the moves of `gates` (mV, in their
/// order) per mV of it.
fn compensation_onto(config: &TunerConfig, gates: &[String]) -> Vec<(String, Vec<f64>)> {
    config
        .levels
        .iter()
        .filter_map(|l| match &l.kind {
            LevelKind::Newton(n) => n.compensation.as_ref().map(|c| (n, c)),
            LevelKind::SensingDot(_) => None,
        })
        .flat_map(|(n, c)| {
            level_forecast::compensation_columns(&n.gates, &c.gates, &c.matrix, gates)
        })
        .collect()
}

/// Turn a device's scan outcome into validated parameter values, why the
/// scan (or a part of it) gave no value, and a display report; raw scans
/// are fitted with the config's `fit_references`. A line scan whose one
/// line was found and the other not gives the found one's value *and* a
/// failure naming the other.
fn evaluate_outcome(
    outcome: ScanOutcome,
    references: &crate::fit::uncertainty::References,
) -> (Vec<ParameterValue>, Option<String>, Option<ScanReport>) {
    let checked =
        |values: Vec<ParameterValue>, failure: Option<String>| match validate_values(values) {
            Ok(values) => (values, failure),
            Err(e) => (Vec::new(), Some(e)),
        };
    match outcome {
        ScanOutcome::Raw { scan } => match crate::fit::evaluate_with(&scan, references) {
            Ok(ev) => {
                let failure = (!ev.missing.is_empty()).then(|| {
                    ev.missing
                        .iter()
                        .map(|(name, e)| format!("{name}: {e}"))
                        .collect::<Vec<_>>()
                        .join("; ")
                });
                let (values, failure) = checked(ev.values, failure);
                (
                    values,
                    failure,
                    Some(ScanReport {
                        raw: scan,
                        fit: ev.fit,
                    }),
                )
            }
            Err(e) => (
                Vec::new(),
                Some(e.to_string()),
                Some(ScanReport {
                    raw: scan,
                    fit: Vec::new(),
                }),
            ),
        },
        ScanOutcome::Evaluated { values } => {
            let (values, failure) = checked(values, None);
            (values, failure, None)
        }
        ScanOutcome::Failed { reason } => (Vec::new(), Some(reason), None),
    }
}

/// NaN, infinite or negative variances never reach an estimator.
fn validate_values(values: Vec<ParameterValue>) -> Result<Vec<ParameterValue>, String> {
    for v in &values {
        v.validate().map_err(|e| e.to_string())?;
    }
    Ok(values)
}
#[cfg(test)]
mod tests;
