//! The quasi-Newton level: measure, learn the gradient, test for tuned, step.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::config::{ConfigError, InitialGradient, LevelKind, NewtonConfig};
use super::finite_difference::{FiniteDifference, Sample};
use super::level_forecast::LevelForecast;
use super::search::{SearchMemory, SearchMove};
use super::{Decision, LevelState, Op, Tuner};
use crate::estimator::{EstimatorKind, GradientEstimator};
use crate::kalman::{ProcessNoise, UpdateOutcome};
use crate::parameter::{ParameterSpec, Transform};
use crate::protocol::{
    EventKind, GradientReport, IterationRecord, ParameterReport, ParameterValue, ScanKind,
    ScanReport, ScanRequest, TunerEvent,
};
use crate::solver::{
    covariance_direction_step, expected_cost_step, newton_step, SolverConfig, StepRule,
};

/// After this many gated outliers in a row, the reference point is reset to
/// the newest measurement (the parameter really moved; stop comparing with
/// the old point) without learning from it.
const MAX_GATED_IN_A_ROW: u32 = 2;

/// Moves of at most the step limit one search probe may take (a probe
/// further than this many step limits goes only that far).
const MAX_SEARCH_MOVES: u32 = 32;

/// The last accepted measurement of one parameter: where and what.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Reference {
    voltages_mv: Vec<f64>,
    value: f64,
    variance: f64,
}

/// What the level measured at the start of the current round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Snapshot {
    voltages_mv: BTreeMap<String, f64>,
    level_voltages_mv: Vec<f64>,
    samples: Vec<Option<Sample>>,
    raw: Vec<Option<ParameterValue>>,
    tuned: bool,
    step_mv: Vec<f64>,
    /// The samples are a forecast ([`super::ParameterForecast`]), not a scan:
    /// the call ends after the correction without a confirming scan.
    #[serde(default)]
    from_forecast: bool,
}

/// Mutable state of one Newton level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct NewtonState {
    estimators: Option<Vec<GradientEstimator>>,
    references: Vec<Option<Reference>>,
    gated_in_a_row: Vec<u32>,
    measured: BTreeMap<String, ParameterValue>,
    scans: BTreeMap<ScanKind, ScanReport>,
    fd: Option<FiniteDifference>,
    pub(super) oracle: Option<(Vec<f64>, Vec<Vec<f64>>)>,
    pub(super) iterations_this_call: u32,
    pub(super) events: Vec<EventKind>,
    snapshot: Option<Snapshot>,
    targets_held: bool,
    /// The last measured values, in parameter order (parameter units);
    /// `None` where the last scan gave none.
    #[serde(default)]
    last_raw: Vec<Option<ParameterValue>>,
    /// Filter consistency per parameter (parameter order).
    #[serde(default)]
    consistency: Vec<Consistency>,
    /// The level's gate voltages (mV) at the last evaluation that gave every
    /// targeted parameter: where a failed evaluation retreats toward.
    #[serde(default)]
    last_good_mv: Option<Vec<f64>>,
    /// The learned forecast of a child level's parameters (`Some` iff the
    /// level has `forecast`; set by the tuner, which knows every gate).
    #[serde(default)]
    pub(super) forecast: Option<LevelForecast>,
    /// What the level remembers for re-finding lost parameters (used iff
    /// the level has `search`).
    #[serde(default)]
    search: SearchMemory,
}

/// Running statistics of a filter's normalised innovations squared (NIS),
/// `(z − Δv·g)² / (Δv C Δvᵀ + Δz²)`, over every update it was offered
/// (gated outliers included). For a consistent filter the mean is 1 and
/// 4.6 % of the innovations lie beyond 2σ.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Consistency {
    /// Number of innovations.
    pub count: u64,
    /// Sum of the NIS values (dimensionless).
    pub nis_sum: f64,
    /// Innovations beyond 2 predicted standard deviations.
    pub beyond_2sigma: u64,
}

impl Consistency {
    /// Add one innovation (estimator units) with its predicted standard deviation.
    /// Ignored unless both are finite and the standard deviation is > 0.
    pub fn add(&mut self, innovation: f64, innovation_sigma: f64) {
        if innovation.is_finite() && innovation_sigma.is_finite() && innovation_sigma > 0.0 {
            let r = innovation / innovation_sigma;
            self.count += 1;
            self.nis_sum += r * r;
            self.beyond_2sigma += u64::from(r.abs() > 2.0);
        }
    }

    /// Merge another set of statistics.
    pub fn merge(&mut self, other: &Consistency) {
        self.count += other.count;
        self.nis_sum += other.nis_sum;
        self.beyond_2sigma += other.beyond_2sigma;
    }

    /// Mean NIS (`None` without innovations).
    pub fn nis_mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.nis_sum / self.count as f64)
    }

    /// Fraction of innovations beyond 2σ (`None` without innovations).
    pub fn beyond_2sigma_fraction(&self) -> Option<f64> {
        (self.count > 0).then(|| self.beyond_2sigma as f64 / self.count as f64)
    }
}

impl NewtonState {
    pub(super) fn new(cfg: &NewtonConfig) -> Result<Self, ConfigError> {
        let m = cfg.parameters.len();
        let estimators = match &cfg.initial_gradient {
            InitialGradient::FiniteDifference { .. } => None,
            InitialGradient::Given {
                gradient,
                covariance,
            } => {
                let k = cfg.gates.len();
                let rows = gradient
                    .iter()
                    .zip(covariance)
                    .map(|(g, c)| {
                        (
                            DVector::from_column_slice(g),
                            DMatrix::from_fn(k, k, |r, s| c[r][s]),
                        )
                    })
                    .collect();
                Some(build_estimators(cfg, rows)?)
            }
            InitialGradient::RoughGuess {
                gradient,
                relative_std,
            } => {
                let rows = gradient
                    .iter()
                    .map(|g| {
                        let g = DVector::from_column_slice(g);
                        let c = DMatrix::from_diagonal(&g.map(|x| (relative_std * x).powi(2)));
                        (g, c)
                    })
                    .collect();
                Some(build_estimators(cfg, rows)?)
            }
        };
        Ok(Self {
            estimators,
            references: vec![None; m],
            gated_in_a_row: vec![0; m],
            measured: BTreeMap::new(),
            scans: BTreeMap::new(),
            fd: None,
            oracle: None,
            iterations_this_call: 0,
            events: Vec::new(),
            snapshot: None,
            targets_held: false,
            last_raw: vec![None; m],
            consistency: vec![Consistency::default(); m],
            last_good_mv: None,
            forecast: None,
            search: SearchMemory::default(),
        })
    }

    /// The last measured values (parameter order, parameter units).
    pub(super) fn last_measured(&self) -> &[Option<ParameterValue>] {
        &self.last_raw
    }

    /// Filter consistency per parameter (parameter order).
    pub(super) fn consistency(&self) -> &[Consistency] {
        &self.consistency
    }

    /// The level's round is a forecast instead of a scan (`samples`:
    /// estimator space, parameter order; `tuned`: every target inside its
    /// band), taken at `voltages_mv` with the level's gates at `level_mv`.
    pub(super) fn set_forecast_snapshot(
        &mut self,
        voltages_mv: BTreeMap<String, f64>,
        level_mv: Vec<f64>,
        samples: Vec<Option<Sample>>,
        tuned: bool,
    ) {
        let n = level_mv.len();
        self.snapshot = Some(Snapshot {
            voltages_mv,
            level_voltages_mv: level_mv,
            raw: vec![None; samples.len()],
            samples,
            tuned,
            step_mv: vec![0.0; n],
            from_forecast: true,
        });
    }

    /// A child level's parent moved since its last call: a fresh baseline
    /// ([`NewtonState::forget_references`]) and no point to retreat toward.
    pub(super) fn parent_moved(&mut self) {
        self.forget_references();
        self.last_good_mv = None;
    }

    /// Drop every reference point: the next measurement is a new baseline.
    pub(super) fn forget_references(&mut self) {
        self.references.iter_mut().for_each(|r| *r = None);
        self.gated_in_a_row.iter_mut().for_each(|g| *g = 0);
    }

    pub(super) fn is_initialised(&self) -> bool {
        self.estimators.is_some()
    }

    pub(super) fn gradients(&self) -> Option<Vec<super::GradientRow>> {
        self.estimators.as_ref().map(|es| {
            es.iter()
                .map(|e| (e.gradient().clone(), e.covariance().cloned()))
                .collect()
        })
    }

    pub(super) fn absorb(&mut self, values: Vec<ParameterValue>, report: Option<ScanReport>) {
        for v in values {
            self.measured.insert(v.name.clone(), v);
        }
        if let Some(r) = report {
            self.scans.insert(r.raw.kind, r);
        }
    }

    /// Take this round's measurements as estimator-space samples, in parameter order.
    fn take_samples(
        &mut self,
        cfg: &NewtonConfig,
    ) -> (Vec<Option<Sample>>, Vec<Option<ParameterValue>>) {
        let measured = std::mem::take(&mut self.measured);
        let raw: Vec<Option<ParameterValue>> = cfg
            .parameters
            .iter()
            .map(|p| measured.get(&p.name).cloned())
            .collect();
        self.last_raw = raw.clone();
        let mut samples = Vec::with_capacity(raw.len());
        for (p, v) in cfg.parameters.iter().zip(&raw) {
            let s = v
                .as_ref()
                .and_then(|v| p.transform.forward(v.value, v.variance));
            if v.is_some() && s.is_none() {
                self.events.push(EventKind::NotRepresentable {
                    parameter: p.name.clone(),
                    transform: format!("{:?}", p.transform),
                });
            }
            samples.push(s);
        }
        (samples, raw)
    }
}

fn build_estimators(
    cfg: &NewtonConfig,
    rows: Vec<(DVector<f64>, DMatrix<f64>)>,
) -> Result<Vec<GradientEstimator>, ConfigError> {
    let n = cfg.gates.len();
    cfg.parameters
        .iter()
        .zip(rows)
        .enumerate()
        .map(|(i, (p, (g, c)))| {
            GradientEstimator::new(
                cfg.estimator,
                g,
                c,
                &ProcessNoise::isotropic(n, p.process_noise_per_mv),
                cfg.solver.max_step_mv,
                cfg.outlier_sigma,
                cfg.min_step_mv,
            )
            .map_err(|e| ConfigError::new(format!("parameters[{i}]"), e.to_string()))
        })
        .collect()
}

fn scan_ops(cfg: &NewtonConfig) -> Vec<Op> {
    let mut kinds: Vec<ScanKind> = Vec::new();
    for p in &cfg.parameters {
        if !kinds.contains(&p.scan) {
            kinds.push(p.scan);
        }
    }
    kinds
        .into_iter()
        .map(|kind| {
            Op::Measure(ScanRequest {
                kind,
                sweep: None,
                cell: None,
            })
        })
        .collect()
}

fn gradient_unit(p: &ParameterSpec) -> String {
    match p.transform {
        Transform::Linear => format!("{}/mV", p.unit),
        Transform::Log => "1/mV (log space)".to_string(),
    }
}

impl Tuner {
    fn newton(&self, level: usize) -> (&NewtonConfig, &NewtonState) {
        match (&self.config.levels[level].kind, &self.levels[level]) {
            (LevelKind::Newton(c), LevelState::Newton(s)) => (c, s),
            _ => unreachable!("level {level} is a Newton level"),
        }
    }

    fn newton_mut(&mut self, level: usize) -> (&mut NewtonConfig, &mut NewtonState) {
        match (&mut self.config.levels[level].kind, &mut self.levels[level]) {
            (LevelKind::Newton(c), LevelState::Newton(s)) => (c, s),
            _ => unreachable!("level {level} is a Newton level"),
        }
    }

    /// Keep mode: the top level's measured samples and values of a check
    /// (estimator space and parameter units, config order).
    pub(super) fn take_check_samples(
        &mut self,
    ) -> (Vec<Option<Sample>>, Vec<Option<ParameterValue>>) {
        let cfg = self.newton(0).0.clone();
        let (_, state) = self.newton_mut(0);
        state.take_samples(&cfg)
    }

    /// Keep mode: a check's measurements are the top level's round (no step):
    /// its record shows them, `tuned` as decided by the check.
    pub(super) fn set_check_snapshot(
        &mut self,
        samples: Vec<Option<Sample>>,
        raw: Vec<Option<ParameterValue>>,
        tuned: bool,
    ) {
        let v_now = self.level_voltages(0);
        let all_v = self.voltages_mv.clone();
        let (_, state) = self.newton_mut(0);
        state.snapshot = Some(Snapshot {
            voltages_mv: all_v,
            step_mv: vec![0.0; v_now.len()],
            level_voltages_mv: v_now,
            samples,
            raw,
            tuned,
            from_forecast: false,
        });
    }

    /// The top level's samples of its last round (estimator space).
    pub(super) fn top_snapshot_samples(&self) -> Vec<Option<Sample>> {
        let (_, state) = self.newton(0);
        state
            .snapshot
            .as_ref()
            .map(|s| s.samples.clone())
            .unwrap_or_default()
    }

    /// Keep mode: a check that starts a re-tune hands its trusted values to
    /// the re-tune's first round (so it measures only what the check did not).
    pub(super) fn restore_top_measurements(&mut self, values: Vec<ParameterValue>) {
        let (_, state) = self.newton_mut(0);
        for v in values {
            state.measured.insert(v.name.clone(), v);
        }
    }

    /// The top level's round, measuring only the scans whose parameters are
    /// not yet measured this round (all of them after a normal round).
    pub(super) fn top_round_ops_for_missing(&self) -> Vec<Op> {
        let (cfg, state) = self.newton(0);
        let mut kinds: Vec<ScanKind> = Vec::new();
        for p in &cfg.parameters {
            if !state.measured.contains_key(&p.name) && !kinds.contains(&p.scan) {
                kinds.push(p.scan);
            }
        }
        let mut ops: Vec<Op> = kinds
            .into_iter()
            .map(|kind| {
                Op::Measure(ScanRequest {
                    kind,
                    sweep: None,
                    cell: None,
                })
            })
            .collect();
        ops.push(Op::Decide(Decision::Evaluate));
        ops
    }

    /// Keep mode: [`Tuner::prediction_after_step`] of the top level.
    pub(super) fn top_prediction_after_step(&self) -> Option<Vec<Option<Sample>>> {
        self.prediction_after_step(0)
    }

    /// After a level's step, the filter's prediction of every parameter
    /// (estimator space: `y + g·Δv`, variance `Δv C Δvᵀ + δy²`), `None` per
    /// parameter without a sample or with a non-finite prediction; `None`
    /// if there was no step.
    fn prediction_after_step(&self, level: usize) -> Option<Vec<Option<Sample>>> {
        let (cfg, state) = self.newton(level);
        let snapshot = state.snapshot.as_ref()?;
        let es = state.estimators.as_ref()?;
        if snapshot.tuned || snapshot.step_mv.iter().all(|d| *d == 0.0) {
            return None;
        }
        let dv = DVector::from_column_slice(&snapshot.step_mv);
        Some(
            cfg.parameters
                .iter()
                .enumerate()
                .map(|(i, _)| {
                    let (y, var_y) = snapshot.samples.get(i).copied().flatten()?;
                    let e = es.get(i)?;
                    let predicted = y + e.gradient().dot(&dv);
                    let var_g = e
                        .covariance()
                        .map_or(0.0, |c| (dv.transpose() * c * &dv)[(0, 0)]);
                    let var = var_g + var_y;
                    (predicted.is_finite() && var.is_finite()).then_some((predicted, var))
                })
                .collect(),
        )
    }

    /// Keep mode starts a re-tune: the top level's references are hours old
    /// (the device drifted without a move), so the next round starts a
    /// fresh baseline instead of learning the drift as a gradient.
    pub(super) fn forget_top_references(&mut self) {
        let (_, state) = self.newton_mut(0);
        state.forget_references();
    }

    /// Operations that measure the initial gradient, if the level still needs one.
    pub(super) fn init_ops(&mut self, level: usize) -> std::collections::VecDeque<Op> {
        let LevelState::Newton(state) = &self.levels[level] else {
            return Default::default();
        };
        if state.is_initialised() || state.fd.is_some() {
            return Default::default();
        }
        self.fd_ops(level).unwrap_or_default()
    }

    /// Operations that measure the level's gradient by finite differences
    /// (its `initial_gradient`), from where its gates are now; `None` if the
    /// level's initial gradient is not measured.
    fn fd_ops(&mut self, level: usize) -> Option<std::collections::VecDeque<Op>> {
        let mut ops = std::collections::VecDeque::new();
        let (cfg, _) = self.newton(level);
        let InitialGradient::FiniteDifference {
            step_mv,
            repetitions,
            recentre_between_offsets,
            central,
            ref mirrored,
        } = cfg.initial_gradient
        else {
            return None;
        };
        let diagonal_ok = std::f64::consts::SQRT_2 * step_mv <= cfg.solver.max_step_mv;
        let base = self.level_voltages(level);
        let children = self.after_move_ops(level);
        let scans = scan_ops(cfg);
        let reps = repetitions as usize;
        ops.extend(children.iter().cloned());
        for rep in 0..reps {
            if rep > 0 {
                ops.push_back(Op::Move(base.clone()));
                if recentre_between_offsets {
                    ops.extend(children.iter().cloned());
                }
            }
            ops.extend(scans.iter().cloned());
            ops.push_back(Op::Decide(Decision::FdBase(rep)));
            let mut previous: Option<usize> = None;
            let sign = if mirrored.get(rep).copied().unwrap_or(false) {
                -1.0
            } else {
                1.0
            };
            for (j, offset) in offset_order(base.len(), sign * step_mv, central) {
                let mut v = base.clone();
                v[j] += offset;
                // from the last point straight only to another gate's
                // offset (√2·step_mv), and only within one step
                if central && !previous.is_none_or(|i| i != j && diagonal_ok) {
                    ops.push_back(Op::Move(base.clone()));
                }
                previous = Some(j);
                ops.push_back(Op::Move(v));
                if recentre_between_offsets {
                    ops.extend(children.iter().cloned());
                }
                ops.extend(scans.iter().cloned());
                ops.push_back(Op::Decide(Decision::FdPoint(rep, j)));
            }
        }
        ops.push_back(Op::Move(base.clone()));
        ops.extend(children.iter().cloned());
        ops.push_back(Op::Decide(Decision::FdFinish));
        let m = cfg.parameters.len();
        let (_, state) = self.newton_mut(level);
        state.fd = Some(FiniteDifference::new(m, base, step_mv, reps));
        Some(ops)
    }

    /// Measure every parameter, then evaluate.
    pub(super) fn round_ops(&self, level: usize) -> Vec<Op> {
        let (cfg, _) = self.newton(level);
        let mut ops = scan_ops(cfg);
        ops.push(Op::Decide(Decision::Evaluate));
        ops
    }

    pub(super) fn decide_newton(&mut self, level: usize, d: Decision) -> Option<IterationRecord> {
        match d {
            Decision::FdBase(rep) => {
                let cfg = self.newton(level).0.clone();
                let (_, state) = self.newton_mut(level);
                let (samples, _) = state.take_samples(&cfg);
                if let Some(fd) = &mut state.fd {
                    fd.record_base(rep, samples);
                }
                None
            }
            Decision::FdPoint(rep, j) => {
                let cfg = self.newton(level).0.clone();
                let v = self.level_voltages(level);
                let (_, state) = self.newton_mut(level);
                let (samples, _) = state.take_samples(&cfg);
                if let Some(fd) = &mut state.fd {
                    let offset = v[j] - fd.base_mv[j];
                    fd.record_point(rep, j, offset, samples);
                }
                None
            }
            Decision::FdFinish => {
                self.finish_fd(level);
                None
            }
            Decision::Evaluate => {
                self.evaluate(level);
                None
            }
            Decision::Step => {
                self.step(level);
                None
            }
            Decision::EndIteration => self.end_iteration(level),
            Decision::Forecast => {
                self.correct_from_forecast(level);
                None
            }
            Decision::SdPark
            | Decision::SdFallbackPoint { .. }
            | Decision::SdFallbackFinish { .. }
            | Decision::KeepCheck => None,
        }
    }

    fn finish_fd(&mut self, level: usize) {
        let cfg = self.newton(level).0.clone();
        let n = cfg.gates.len();
        let (_, state) = self.newton_mut(level);
        let Some(fd) = state.fd.take() else { return };
        let rows: Vec<(DVector<f64>, DMatrix<f64>)> = fd
            .result()
            .into_iter()
            .zip(&cfg.parameters)
            .map(|(r, p)| {
                r.unwrap_or_else(|| {
                    state.events.push(EventKind::FiniteDifferenceFailed {
                        parameter: p.name.clone(),
                    });
                    (DVector::zeros(n), DMatrix::identity(n, n))
                })
            })
            .collect();
        match &mut state.estimators {
            Some(es) => {
                for (e, (g, c)) in es.iter_mut().zip(rows) {
                    e.remeasured(g, c);
                }
            }
            None => match build_estimators(&cfg, rows) {
                Ok(es) => state.estimators = Some(es),
                Err(e) => {
                    // An FD result that the filter refuses (e.g. non-finite) — start from zero.
                    state.events.push(EventKind::InitialGradientRejected {
                        reason: e.to_string(),
                    });
                    let zero = (0..cfg.parameters.len())
                        .map(|_| (DVector::zeros(n), DMatrix::identity(n, n)))
                        .collect();
                    state.estimators = build_estimators(&cfg, zero).ok();
                }
            },
        }
    }

    fn evaluate(&mut self, level: usize) {
        let band_scale = self.band_scale(level);
        let cfg = self.newton(level).0.clone();
        let v_now = self.level_voltages(level);
        let all_v = self.voltages_mv.clone();
        let (failed, now_s) = (self.failed_evaluations, self.lab_seconds);
        let (cfg_mut, state) = self.newton_mut(level);
        let (samples, raw) = state.take_samples(&cfg);
        // A scan: the forecast learns what the own Jacobian did not explain.
        if let (Some(f), Some(own_rows)) = (&cfg.forecast, state.gradients()) {
            if let Some(model) = &mut state.forecast {
                model.observe(&v_now, &all_v, &samples, &own_rows, f.noise);
                model.scanned(failed, now_s);
            }
        }
        // Targets held at their first measured values.
        if cfg.hold_initial_values && !state.targets_held && raw.iter().all(Option::is_some) {
            for (p, v) in cfg_mut.parameters.iter_mut().zip(&raw) {
                p.target = v.as_ref().map(|v| v.value);
            }
            state.targets_held = true;
        }
        let cfg = cfg_mut.clone();
        for (i, p) in cfg.parameters.iter().enumerate() {
            if raw[i].is_none() {
                state.events.push(EventKind::NoMeasurement {
                    parameter: p.name.clone(),
                });
            }
        }
        // A value whose error bar is wider than its tolerance band says nothing about
        // where the parameter is: the filter may learn from it (with its tiny gain), but
        // neither the tuned test nor the Newton step may rely on it.
        let trusted: Vec<Option<ParameterValue>> = cfg
            .parameters
            .iter()
            .zip(&raw)
            .map(|(p, v)| {
                let v = v.as_ref()?;
                match p.target {
                    Some(t) if v.variance.sqrt() > p.tolerance.half_width(t) => {
                        state.events.push(EventKind::TooUncertain {
                            parameter: p.name.clone(),
                            value: v.value,
                            std: v.variance.sqrt(),
                            unit: p.unit.clone(),
                        });
                        None
                    }
                    _ => Some(v.clone()),
                }
            })
            .collect();
        // Learn from the step since each parameter's reference point.
        if let Some(estimators) = &mut state.estimators {
            for (i, p) in cfg.parameters.iter().enumerate() {
                let Some((y, var)) = samples[i] else { continue };
                let Some(reference) = &state.references[i] else {
                    state.references[i] = Some(Reference {
                        voltages_mv: v_now.clone(),
                        value: y,
                        variance: var,
                    });
                    continue;
                };
                let dv = DVector::from_iterator(
                    v_now.len(),
                    v_now.iter().zip(&reference.voltages_mv).map(|(a, b)| a - b),
                );
                let z = y - reference.value;
                let dz2 = var + reference.variance;
                let new_ref = Some(Reference {
                    voltages_mv: v_now.clone(),
                    value: y,
                    variance: var,
                });
                let outcome = estimators[i].observe(&dv, z, dz2);
                if let Ok(
                    UpdateOutcome::Gated {
                        innovation,
                        innovation_sigma,
                    }
                    | UpdateOutcome::Updated {
                        innovation,
                        innovation_sigma,
                    },
                ) = outcome
                {
                    if state.consistency.len() != cfg.parameters.len() {
                        // a checkpoint from before these statistics existed
                        state.consistency = vec![Consistency::default(); cfg.parameters.len()];
                    }
                    state.consistency[i].add(innovation, innovation_sigma);
                }
                match outcome {
                    Ok(UpdateOutcome::Gated {
                        innovation,
                        innovation_sigma,
                    }) => {
                        state.gated_in_a_row[i] += 1;
                        state.events.push(EventKind::OutlierGated {
                            parameter: p.name.clone(),
                            innovation,
                            innovation_sigma,
                            unit: p.unit.clone(),
                        });
                        if state.gated_in_a_row[i] >= MAX_GATED_IN_A_ROW {
                            state.references[i] = new_ref;
                            state.gated_in_a_row[i] = 0;
                        }
                    }
                    Ok(_) => {
                        state.references[i] = new_ref;
                        state.gated_in_a_row[i] = 0;
                    }
                    Err(e) => state.events.push(EventKind::UpdateRejected {
                        parameter: p.name.clone(),
                        reason: e.to_string(),
                    }),
                }
            }
        }
        // keep mode settles the top level inside a narrower band (1 otherwise)
        let scale = band_scale;
        let tuned = cfg
            .parameters
            .iter()
            .zip(&trusted)
            .all(|(p, v)| match p.target {
                None => true,
                Some(t) => v
                    .as_ref()
                    .is_some_and(|v| (v.value - t).abs() <= scale * p.tolerance.half_width(t)),
            });
        let missing_targeted = cfg
            .parameters
            .iter()
            .zip(&trusted)
            .any(|(p, v)| p.target.is_some() && v.is_none());
        state.snapshot = Some(Snapshot {
            voltages_mv: all_v,
            level_voltages_mv: v_now.clone(),
            samples: samples.clone(),
            raw,
            tuned,
            step_mv: vec![0.0; v_now.len()],
            from_forecast: false,
        });
        if !missing_targeted {
            state.last_good_mv = Some(v_now.clone());
        }
        let mut remeasure = false;
        if cfg.search.is_some() {
            let seen: Vec<Option<f64>> = samples.iter().map(|s| s.map(|s| s.0)).collect();
            state.search.seen(&seen);
            if !missing_targeted {
                let unknown_rows = state.search.active.as_ref().is_some_and(|a| {
                    let es = state.estimators.as_ref();
                    a.signs.iter().enumerate().any(|(i, s)| {
                        s.is_some()
                            && es
                                .and_then(|es| es.get(i))
                                .is_some_and(|e| e.gradient().iter().all(|g| *g == 0.0))
                    })
                });
                if let Some(probes) = state.search.found() {
                    state.events.push(EventKind::SearchEnded {
                        probes,
                        found: true,
                    });
                    remeasure = unknown_rows
                        && matches!(
                            cfg.initial_gradient,
                            InitialGradient::FiniteDifference { .. }
                        );
                }
            }
        }
        if remeasure {
            // a line lost from the start has no gradient: measure the level's
            // gradient now that its scans work, then a new round
            let mut ops = self.fd_ops(level).unwrap_or_default();
            ops.extend(self.round_ops(level));
            self.push_ops(ops);
            return;
        }
        let top = level == 0;
        if tuned {
            if top {
                self.push_ops([Op::Decide(Decision::EndIteration)]);
            }
            return;
        }
        if missing_targeted {
            // Do not step blind. As qtune does, retreat half-way toward the last
            // point where the evaluation worked (within the step limit and the
            // gate limits; the move goes through the session's guard like any
            // other), re-tune the lower levels (sensor contrast, transition
            // lines — the usual reasons a scan fails) and measure again next round.
            let retreat = state
                .last_good_mv
                .clone()
                .and_then(|good| retreat_target(&v_now, &good, cfg.solver.max_step_mv));
            // A search under way goes on; with nothing to retreat to, the
            // parameters moved by themselves: search for them if configured.
            let searching = state.search.active.is_some();
            if searching || retreat.is_none() {
                let missing: Vec<bool> = cfg
                    .parameters
                    .iter()
                    .zip(&trusted)
                    .map(|(p, v)| p.target.is_some() && v.is_none())
                    .collect();
                if let Some(ops) = self.search_ops(level, &v_now, &missing) {
                    self.push_ops(ops);
                    return;
                }
                if searching {
                    // the search could not go on (no usable Jacobian): as without one
                    self.push_ops(
                        self.after_move_ops(level)
                            .into_iter()
                            .chain([Op::Decide(Decision::EndIteration)]),
                    );
                    return;
                }
            }
            let mut ops = Vec::new();
            if let Some(mut target) = retreat {
                for (j, g) in cfg.gates.iter().enumerate() {
                    if let Some(spec) = self.safety.gate(g) {
                        target[j] = target[j].clamp(spec.min_mv, spec.max_mv);
                    }
                }
                let (_, state) = self.newton_mut(level);
                if let Some(s) = &mut state.snapshot {
                    s.step_mv = target.iter().zip(&v_now).map(|(a, b)| a - b).collect();
                }
                ops.push(Op::Move(target));
            }
            ops.extend(self.after_move_ops(level));
            ops.push(Op::Decide(Decision::EndIteration));
            self.push_ops(ops);
            return;
        }
        match cfg.estimator {
            EstimatorKind::FdNewton => {
                let mut fd =
                    FiniteDifference::new(cfg.parameters.len(), v_now.clone(), cfg.fd_step_mv, 1);
                fd.record_base(0, samples);
                let (_, state) = self.newton_mut(level);
                state.fd = Some(fd);
                let children = self.after_move_ops(level);
                let scans = scan_ops(&cfg);
                let mut ops = Vec::new();
                for j in 0..v_now.len() {
                    let mut v = v_now.clone();
                    v[j] += cfg.fd_step_mv;
                    ops.push(Op::Move(v));
                    ops.extend(children.iter().cloned());
                    ops.extend(scans.iter().cloned());
                    ops.push(Op::Decide(Decision::FdPoint(0, j)));
                }
                // back to where the step is planned from: the step target is at
                // most `max_step_mv` from there, not from the last offset point
                ops.push(Op::Move(v_now.clone()));
                ops.push(Op::Decide(Decision::FdFinish));
                ops.push(Op::Decide(Decision::Step));
                self.push_ops(ops);
            }
            EstimatorKind::Oracle => {
                self.push_ops([Op::QueryJacobian, Op::Decide(Decision::Step)]);
            }
            _ => self.step(level),
        }
    }

    /// A failed evaluation with a search configured: the next probe (or the
    /// way back after the last one) as moves of at most the step limit,
    /// clipped to the gate limits, then the lower levels, then the probe's
    /// scans and evaluation in the same round (the way back ends the round). `None`: no search this time (not configured, too few failures
    /// in a row, given up, or no usable Jacobian).
    fn search_ops(&mut self, level: usize, v_now: &[f64], missing: &[bool]) -> Option<Vec<Op>> {
        let cfg = self.newton(level).0.clone();
        let search = cfg.search.clone()?;
        let (_, state) = self.newton_mut(level);
        let es = state.estimators.as_ref()?;
        let n = v_now.len();
        let jacobian = DMatrix::from_fn(cfg.parameters.len(), n, |r, c| es[r].gradient()[c]);
        let targets: Vec<Option<f64>> = cfg
            .parameters
            .iter()
            .map(|p| p.target.and_then(|t| p.transform.forward_value(t)))
            .collect();
        let mv = state
            .search
            .lost(&search, missing, &targets, &jacobian, false)?;
        let probing = matches!(mv, SearchMove::Probe { .. });
        let (dv, event) = match mv {
            SearchMove::Probe {
                probe,
                offsets,
                dv_mv,
            } => {
                let (parameters, offsets) = cfg
                    .parameters
                    .iter()
                    .zip(&offsets)
                    .zip(missing)
                    .filter(|(_, &m)| m)
                    .map(|((p, o), _)| (p.name.clone(), *o))
                    .unzip();
                let event = EventKind::SearchProbe {
                    probe,
                    parameters,
                    offsets,
                };
                (dv_mv, event)
            }
            SearchMove::GiveUp { probes, dv_mv } => (
                dv_mv,
                EventKind::SearchEnded {
                    probes,
                    found: false,
                },
            ),
        };
        state.events.push(event);
        let norm = dv.iter().map(|d| d * d).sum::<f64>().sqrt();
        let max_moves = ((norm / cfg.solver.max_step_mv).ceil() as u32).clamp(1, MAX_SEARCH_MOVES);
        let mut ops: Vec<Op> = plan_moves(v_now, &dv, cfg.solver.max_step_mv, max_moves)
            .into_iter()
            .map(|mut t| {
                for (j, g) in cfg.gates.iter().enumerate() {
                    if let Some(spec) = self.safety.gate(g) {
                        t[j] = t[j].clamp(spec.min_mv, spec.max_mv);
                    }
                }
                Op::Move(t)
            })
            .collect();
        if let Some(Op::Move(last)) = ops.last() {
            let step: Vec<f64> = last.iter().zip(v_now).map(|(a, b)| a - b).collect();
            let (_, state) = self.newton_mut(level);
            if let Some(s) = &mut state.snapshot {
                s.step_mv = step;
            }
        }
        ops.extend(self.after_move_ops(level));
        if probing {
            // scan at the probe in the same round: the search is one
            // procedure, whatever the level's iterations per call
            ops.extend(self.round_ops(level));
        } else {
            ops.push(Op::Decide(Decision::EndIteration));
        }
        Some(ops)
    }

    pub(super) fn step(&mut self, level: usize) {
        let cfg = self.newton(level).0.clone();
        let (_, state) = self.newton_mut(level);
        let Some(snapshot) = state.snapshot.clone() else {
            return;
        };
        // The oracle's Jacobian replaces the estimate (in estimator space).
        if let (Some((values, jac)), Some(es)) = (state.oracle.take(), &mut state.estimators) {
            for (i, (e, p)) in es.iter_mut().zip(&cfg.parameters).enumerate() {
                if let (Some(row), Some(&val)) = (jac.get(i), values.get(i)) {
                    let f = p.transform.forward_gradient_factor(val);
                    let n = row.len();
                    e.remeasured(
                        DVector::from_iterator(n, row.iter().map(|x| x * f)),
                        DMatrix::zeros(n, n),
                    );
                }
            }
        }
        let Some(es) = &state.estimators else { return };
        let rows: Vec<usize> = (0..cfg.parameters.len())
            .filter(|&i| cfg.parameters[i].target.is_some() && snapshot.samples[i].is_some())
            .collect();
        let n = cfg.gates.len();
        let jac = DMatrix::from_fn(rows.len(), n, |r, c| es[rows[r]].gradient()[c]);
        let delta = DVector::from_iterator(
            rows.len(),
            rows.iter().map(|&i| {
                let p = &cfg.parameters[i];
                let target = p
                    .target
                    .and_then(|t| p.transform.forward_value(t))
                    .expect("validated target");
                snapshot.samples[i].expect("filtered").0 - target
            }),
        );
        let max_moves = cfg.solver.max_moves_per_iteration.max(1);
        // One iteration may travel up to `max_moves` moves of the step limit.
        let radius_mv = cfg.solver.max_step_mv * f64::from(max_moves);
        let step = match cfg.solver.rule {
            StepRule::PseudoInverse => newton_step(
                &jac,
                &delta,
                &SolverConfig {
                    max_step_mv: radius_mv,
                    ..cfg.solver
                },
            ),
            StepRule::ExpectedCost | StepRule::CovarianceDirection => {
                let covariances: Vec<Option<DMatrix<f64>>> =
                    rows.iter().map(|&i| es[i].covariance().cloned()).collect();
                let scale = DVector::from_iterator(
                    rows.len(),
                    rows.iter().map(|&i| row_scale(&cfg.parameters[i])),
                );
                let solve = if cfg.solver.rule == StepRule::ExpectedCost {
                    expected_cost_step
                } else {
                    covariance_direction_step
                };
                solve(&jac, &covariances, &delta, &scale, &cfg.solver, radius_mv)
            }
        };
        let base = snapshot.level_voltages_mv.clone();
        let plan = plan_moves(
            &base,
            step.dv_mv.as_slice(),
            cfg.solver.max_step_mv,
            max_moves,
        );
        let clamp = |tuner: &Tuner, mut v: Vec<f64>| {
            for (j, g) in cfg.gates.iter().enumerate() {
                if let Some(spec) = tuner.safety.gate(g) {
                    v[j] = v[j].clamp(spec.min_mv, spec.max_mv);
                }
            }
            v
        };
        let targets: Vec<Vec<f64>> = plan.into_iter().map(|t| clamp(self, t)).collect();
        let last = targets.last().cloned().unwrap_or_else(|| base.clone());
        let dv: Vec<f64> = last.iter().zip(&base).map(|(a, b)| a - b).collect();
        let (_, state) = self.newton_mut(level);
        if step.unlimited_norm_mv > radius_mv {
            state.events.push(EventKind::StepLimited {
                from_mv: step.unlimited_norm_mv,
                to_mv: step.dv_mv.norm(),
            });
        }
        if let Some(s) = &mut state.snapshot {
            s.step_mv = dv;
        }
        let children = self.after_move_ops(level);
        let mut ops = Vec::new();
        let moves = targets.len();
        for (k, t) in targets.into_iter().enumerate() {
            // every move goes through `move_request` (per-gate clip, compensation,
            // safety check); the lower levels follow every move, or the last only
            ops.push(Op::Move(t));
            if cfg.solver.lower_levels_between_moves || k + 1 == moves {
                ops.extend(children.iter().cloned());
            }
        }
        if ops.is_empty() {
            ops.push(Op::Move(last));
            ops.extend(children);
        }
        ops.push(Op::Decide(Decision::EndIteration));
        self.push_ops(ops);
    }

    /// For a child level that just stepped, with
    /// [`NewtonConfig::skip_confirmation_sigma`] `k`: the events of a
    /// skipped confirmation if the filter predicts every targeted parameter
    /// inside its band after the step, `k` predicted standard deviations
    /// from either edge (estimator space: prediction `y + g·Δv`, variance
    /// `Δv C Δvᵀ + δy²`); `None` to measure again.
    fn confidently_in_band(&self, level: usize) -> Option<Vec<EventKind>> {
        let (cfg, _) = self.newton(level);
        let k = cfg.skip_confirmation_sigma?;
        let predictions = self.prediction_after_step(level)?;
        let mut events = Vec::new();
        for (i, p) in cfg.parameters.iter().enumerate() {
            let Some(target) = p.target else { continue };
            let (predicted, var) = predictions.get(i).copied().flatten()?;
            let std = var.sqrt();
            let h = p.tolerance.half_width(target);
            let lo = p.transform.forward_value(target - h)?;
            let hi = p.transform.forward_value(target + h)?;
            if !(predicted.is_finite() && std.is_finite())
                || predicted - k * std < lo
                || predicted + k * std > hi
            {
                return None;
            }
            // back in parameter units for the record (linear or log space)
            let (value, value_var) = p.transform.inverse(predicted, var);
            let value_std = value_var.sqrt();
            events.push(EventKind::ConfirmationSkipped {
                parameter: p.name.clone(),
                predicted: value,
                std: value_std,
                unit: p.unit.clone(),
            });
        }
        (!events.is_empty()).then_some(events)
    }

    pub(super) fn end_iteration(&mut self, level: usize) -> Option<IterationRecord> {
        if level != 0 {
            let (_, state) = self.newton_mut(level);
            if state.snapshot.as_ref().is_some_and(|s| s.from_forecast) {
                // corrected from a forecast: no confirming scan in this call
                state.iterations_this_call += 1;
                return None;
            }
            let max = self.newton(level).0.max_iterations_per_call;
            let skip = self.confidently_in_band(level);
            let (_, state) = self.newton_mut(level);
            state.iterations_this_call += 1;
            if let Some(events) = skip {
                state.events.extend(events);
                return None;
            }
            if state.iterations_this_call < max {
                let ops = self.round_ops(level);
                self.push_ops(ops);
            }
            return None;
        }
        let (cfg, state) = self.newton(0);
        let snapshot = state.snapshot.clone()?;
        let parameters = cfg
            .parameters
            .iter()
            .zip(&snapshot.raw)
            .map(|(p, v)| ParameterReport {
                name: p.name.clone(),
                unit: p.unit.clone(),
                value: v.as_ref().map(|v| v.value),
                std: v.as_ref().map(|v| v.variance.sqrt()),
                target: p.target,
                tolerance: p.target.map(|t| p.tolerance.half_width(t)),
            })
            .collect();
        let gradients = state
            .estimators
            .as_ref()
            .map(|es| {
                es.iter()
                    .zip(&cfg.parameters)
                    .map(|(e, p)| GradientReport {
                        parameter: p.name.clone(),
                        unit: gradient_unit(p),
                        gradient: e.gradient().iter().copied().collect(),
                        covariance: e.covariance().map(|c| {
                            (0..c.nrows())
                                .map(|r| (0..c.ncols()).map(|s| c[(r, s)]).collect())
                                .collect()
                        }),
                    })
                    .collect()
            })
            .unwrap_or_default();
        let record = IterationRecord {
            iteration: self.iteration,
            voltages_mv: snapshot.voltages_mv.clone(),
            gates: cfg.gates.clone(),
            parameters,
            gradients,
            step_mv: snapshot.step_mv.clone(),
            tuned: snapshot.tuned,
            lab_seconds: self.lab_seconds,
            scan_counts: self.scan_counts.clone(),
            failed_evaluations: self.failed_evaluations,
            scans: state.scans.values().cloned().collect(),
            events: Vec::new(),
            keep: None,
        };
        // Collect events of every level, attributed to their level.
        let mut events = std::mem::take(&mut self.events);
        for (i, l) in self.levels.iter_mut().enumerate() {
            if let LevelState::Newton(s) = l {
                let name = &self.config.levels[i].name;
                events.extend(
                    std::mem::take(&mut s.events)
                        .into_iter()
                        .map(|kind| TunerEvent {
                            level: name.clone(),
                            kind,
                        }),
                );
            }
        }
        let (_, state) = self.newton_mut(0);
        state.scans.clear();
        Some(IterationRecord { events, ..record })
    }
}

/// The row scale of the expected-cost step: the parameter's tolerance
/// half-width at its target, in estimator units (log space: the band's
/// width in ln). Falls back to 1 where that is not a positive finite number.
fn row_scale(p: &ParameterSpec) -> f64 {
    let s = p
        .target
        .and_then(|t| {
            let hw = p.tolerance.half_width(t);
            Some((p.transform.forward_value(t + hw)? - p.transform.forward_value(t)?).abs())
        })
        .unwrap_or(1.0);
    if s.is_finite() && s > 0.0 {
        s
    } else {
        1.0
    }
}

/// Split a step `dv` (mV) from `base` (mV) into the fewest equal moves of at
/// most `max_step_mv` each, at most `max_moves` of them; returns the absolute
/// target of each move (the last one is `base + dv` when `‖dv‖ ≤
/// max_moves·max_step_mv`, else the step is scaled to that length). Empty for
/// a zero or non-finite step.
///
/// Invariant: consecutive targets (and `base` to the first) are at most
/// `max_step_mv` apart.
pub(super) fn plan_moves(
    base: &[f64],
    dv: &[f64],
    max_step_mv: f64,
    max_moves: u32,
) -> Vec<Vec<f64>> {
    let norm = dv.iter().map(|x| x * x).sum::<f64>().sqrt();
    if !(norm.is_finite() && norm > 0.0 && max_step_mv > 0.0) || base.len() != dv.len() {
        return Vec::new();
    }
    let max_moves = max_moves.max(1);
    let total = norm.min(max_step_mv * f64::from(max_moves));
    let moves = ((total / max_step_mv) * (1.0 - 1e-12)).ceil().max(1.0) as u32;
    let moves = moves.min(max_moves);
    let per_move = total / f64::from(moves);
    (1..=moves)
        .map(|k| {
            let f = per_move * f64::from(k) / norm;
            base.iter().zip(dv).map(|(b, d)| b + d * f).collect()
        })
        .collect()
}

/// Half-way from `now` toward `good` (mV, per gate), the step's norm capped
/// at `max_step_mv`; `None` if `good` is within 0.01 mV of `now` or the
/// inputs are not finite.
///
/// (qtune's rule after a failed evaluation: go back half-way toward the last
/// parameters that could be evaluated.)
pub(crate) fn retreat_target(now: &[f64], good: &[f64], max_step_mv: f64) -> Option<Vec<f64>> {
    if now.len() != good.len() {
        return None;
    }
    let half: Vec<f64> = now.iter().zip(good).map(|(a, b)| 0.5 * (b - a)).collect();
    let norm = half.iter().map(|d| d * d).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 0.005 {
        return None;
    }
    let scale = if norm > max_step_mv {
        max_step_mv / norm
    } else {
        1.0
    };
    Some(now.iter().zip(&half).map(|(a, d)| a + d * scale).collect())
}

/// The finite differences' offset points in order, `(gate, offset mV)`:
/// every gate at `+step_mv`, then (central) every gate at `−step_mv` (a
/// mirrored repetition passes a negative `step_mv`), so
/// consecutive points offset different gates where there are two gates or
/// more (`√2·step_mv` apart).
fn offset_order(gates: usize, step_mv: f64, central: bool) -> Vec<(usize, f64)> {
    let above = (0..gates).map(|j| (j, step_mv));
    let below = (0..gates).map(|j| (j, -step_mv)).filter(|_| central);
    above.chain(below).collect()
}

#[cfg(test)]
mod retreat_tests {
    use super::{plan_moves, retreat_target};
    use proptest::prelude::*;

    proptest! {
        /// Consecutive targets are within the step limit, there are at most
        /// `max_moves` of them, and they end at `base + dv` when that is
        /// reachable in `max_moves` moves.
        #[test]
        fn planned_moves_stay_within_the_step_limit(
            base in proptest::collection::vec(-100.0f64..100.0, 4),
            dv in proptest::collection::vec(-50.0f64..50.0, 4),
            limit in 0.5f64..15.0,
            max_moves in 1u32..=5,
        ) {
            let plan = plan_moves(&base, &dv, limit, max_moves);
            prop_assert!(!plan.is_empty() && plan.len() <= max_moves as usize);
            let mut from = base.clone();
            for t in &plan {
                let d = t.iter().zip(&from).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt();
                prop_assert!(d <= limit * (1.0 + 1e-9), "{d} > {limit}");
                from = t.clone();
            }
            let norm = dv.iter().map(|x| x * x).sum::<f64>().sqrt();
            if norm <= limit * f64::from(max_moves) {
                for ((t, b), d) in from.iter().zip(&base).zip(&dv) {
                    prop_assert!((t - (b + d)).abs() < 1e-9);
                }
                // the fewest moves that fit
                prop_assert!(plan.len() as f64 >= norm / limit - 1e-9);
                prop_assert!(plan.len() == 1 || (plan.len() as f64 - 1.0) * limit < norm);
            }
        }
    }

    #[test]
    fn no_moves_for_a_zero_or_non_finite_step() {
        assert!(plan_moves(&[0.0], &[0.0], 10.0, 2).is_empty());
        assert!(plan_moves(&[0.0], &[f64::NAN], 10.0, 2).is_empty());
    }

    #[test]
    fn retreat_goes_half_way_back_within_the_step_limit() {
        let t = retreat_target(&[0.0, 0.0], &[4.0, -2.0], 10.0).unwrap();
        assert_eq!(t, vec![2.0, -1.0]);
        // a long way back is capped at the step limit
        let t = retreat_target(&[0.0, 0.0], &[60.0, 80.0], 10.0).unwrap();
        assert!((t[0] - 6.0).abs() < 1e-12 && (t[1] - 8.0).abs() < 1e-12);
        // already there, or nonsense: no move
        assert!(retreat_target(&[1.0], &[1.0], 10.0).is_none());
        assert!(retreat_target(&[1.0], &[f64::NAN], 10.0).is_none());
        assert!(retreat_target(&[1.0], &[1.0, 2.0], 10.0).is_none());
    }
}
