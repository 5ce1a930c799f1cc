//! The paper's benchmark protocol on the simulator, for one seed at a time
//! (the CLI runs seeds in parallel and aggregates).
//!
//! Protocol (paper, main text): targets `(t_sr, w)` cycle
//! (20 ns, 270 µV) → (70 ns, 270 µV) → (70 ns, 180 µV) → (20 ns, 180 µV) →
//! (20 ns, 270 µV), 21 iterations at each, with the full hierarchy (sensing
//! dot, chemical-potential compensation) in the loop and the lab clock
//! running. Every strategy of a seed starts from the same device state and the
//! same initial finite-difference gradient measurement.
//!
//! # What a strategy may know (ARCHITECTURE.md invariant 7)
//! The benchmark plays two roles. As the *world* it builds the simulated
//! lab: the device, and the lab's imperfect configuration — the virtual-gate
//! (compensation) matrix is the device's first-order crosstalk perturbed per
//! seed ([`perturbed_compensation`], ±[`BenchmarkProtocol::compensation_error`]
//! relative, uniform, per element). As the *experimenter* it configures each
//! strategy from [`LabKnowledge`] only (the configuration and the initial
//! finite-difference measurement), in [`configure_strategy`], which has no
//! device in scope. Each non-oracle strategy then runs against a device
//! whose truth is sealed ([`SimulatedDevice::seal_truth`]): a request for the
//! true Jacobian would fault the run, and [`SeedResult::truth_queries`]
//! counts every such request (0 for every non-oracle strategy; the test
//! `non_oracle_strategies_never_query_the_truth` holds it).

pub mod array;
pub mod array_timeline;
pub mod cell_trace;
pub mod keep;
pub mod keep_goals;
pub mod oracle_twin;
pub mod row_agreement;

use std::collections::BTreeMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::driver::{SimulationConfig, SimulationRun};
use crate::estimator::EstimatorKind;
use crate::parameter::{ScanKind, Tolerance, Transform};
use crate::protocol::{
    ControlCommand, FaultKind, IterationRecord, ParameterValue, Request, Response, RunStatus,
};
use crate::session::Output;
use crate::session::{RunSession, SessionConfig};
use crate::sim::{DeviceConfig, SimulatedDevice};
use crate::solver::StepRule;
use crate::tuner::{Consistency, InitialGradient, LevelKind, Tuner, TunerConfig};

/// The paper's set-point cycle, `(t_sr ns, w µV)`.
pub const PAPER_SET_POINTS: [(f64, f64); 5] = [
    (20.0, 270.0),
    (70.0, 270.0),
    (70.0, 180.0),
    (20.0, 180.0),
    (20.0, 270.0),
];

/// The protocol's set points as a tuner schedule (`t_sr`, `w` change every
/// `iterations_per_set_point` iterations, starting at iteration 0), e.g. for a
/// live demo of the paper's Fig. 3.
///
/// ```
/// let s = spintune::benchmark::paper_schedule(21);
/// assert_eq!(s.len(), 5);
/// assert_eq!(s[1].at_iteration, 21);
/// assert_eq!(s[1].targets["t_sr"], 70.0);
/// ```
pub fn paper_schedule(iterations_per_set_point: u64) -> Vec<crate::tuner::ScheduledTargets> {
    PAPER_SET_POINTS
        .iter()
        .enumerate()
        .map(|(i, &(t_sr, w))| crate::tuner::ScheduledTargets {
            at_iteration: i as u64 * iterations_per_set_point,
            targets: [("t_sr".to_string(), t_sr), ("w".to_string(), w)].into(),
        })
        .collect()
}

/// Moves per iteration of [`Strategy::KalmanLogTrMulti`] (2: on 50 random
/// devices × 10 seeds, 3 moves left 9 of 2500 changes unconverged with the
/// lower levels after the last move only, 2 moves none; docs/benchmarks.md).
pub const MULTI_MOVES: u32 = 2;

/// A strategy: how the top level estimates its Jacobian and steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Strategy {
    /// Exactly what `spintune run` does with a config that has no `tuner`
    /// section ([`SimulationConfig::recommended`], or the tuner given to
    /// [`run_seed`]): its own cold start included, on the world's device.
    Default,
    /// The paper's filter, constant Q.
    Kalman,
    /// Q growing with the step.
    KalmanAdaptiveQ,
    /// `t_sr` and `w` tuned in log space.
    KalmanLog,
    /// [`Strategy::Kalman`] with the covariance-aware trust-region step
    /// ([`StepRule::ExpectedCost`]).
    KalmanTr,
    /// [`Strategy::KalmanLog`] with the covariance-aware trust-region step.
    KalmanLogTr,
    /// [`Strategy::KalmanLogTr`] allowed up to [`MULTI_MOVES`] limited moves
    /// per measure-and-decide iteration when the target is far.
    KalmanLogTrMulti,
    /// [`Strategy::KalmanLogTrMulti`] with the lower levels (sensing dot,
    /// line re-centring) run after the last move of an iteration only.
    KalmanLogTrMultiBare,
    /// Broyden rank-one update.
    Broyden,
    /// Initial Jacobian, never updated.
    FixedJacobian,
    /// Jacobian re-measured every iteration.
    FdNewton,
    /// The simulator's true Jacobian (linear space).
    Oracle,
    /// The simulator's true Jacobian with `t_sr` and `w` in log space: the
    /// strongest fair reference (same step limit).
    OracleLog,
    /// [`Strategy::OracleLog`] stepping as [`Strategy::KalmanLogTrMultiBare`]
    /// (trust region, [`MULTI_MOVES`] moves per iteration, lower levels after
    /// the last): the reference for the multi-move strategies.
    OracleLogMultiBare,
}

impl Strategy {
    /// All strategies in report order.
    pub const ALL: [Strategy; 14] = [
        Strategy::Default,
        Strategy::Kalman,
        Strategy::KalmanAdaptiveQ,
        Strategy::KalmanLog,
        Strategy::KalmanTr,
        Strategy::KalmanLogTr,
        Strategy::KalmanLogTrMulti,
        Strategy::KalmanLogTrMultiBare,
        Strategy::Broyden,
        Strategy::FixedJacobian,
        Strategy::FdNewton,
        Strategy::Oracle,
        Strategy::OracleLog,
        Strategy::OracleLogMultiBare,
    ];

    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Strategy::Default => "default",
            Strategy::Kalman => "kalman",
            Strategy::KalmanAdaptiveQ => "kalman-adaptive-q",
            Strategy::KalmanLog => "kalman-log",
            Strategy::KalmanTr => "kalman-tr",
            Strategy::KalmanLogTr => "kalman-log-tr",
            Strategy::KalmanLogTrMulti => "kalman-log-tr-multi",
            Strategy::KalmanLogTrMultiBare => "kalman-log-tr-multi-bare",
            Strategy::Broyden => "broyden",
            Strategy::FixedJacobian => "fixed-jacobian",
            Strategy::FdNewton => "fd-newton",
            Strategy::Oracle => "oracle",
            Strategy::OracleLog => "oracle-log",
            Strategy::OracleLogMultiBare => "oracle-log-multi-bare",
        }
    }

    /// Parse a command-line name.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }

    fn estimator(self) -> EstimatorKind {
        match self {
            Strategy::Default
            | Strategy::Kalman
            | Strategy::KalmanLog
            | Strategy::KalmanTr
            | Strategy::KalmanLogTr
            | Strategy::KalmanLogTrMulti
            | Strategy::KalmanLogTrMultiBare => EstimatorKind::Kalman,
            Strategy::KalmanAdaptiveQ => EstimatorKind::KalmanAdaptiveQ,
            Strategy::Broyden => EstimatorKind::Broyden,
            Strategy::FixedJacobian => EstimatorKind::FixedJacobian,
            Strategy::FdNewton => EstimatorKind::FdNewton,
            Strategy::Oracle | Strategy::OracleLog | Strategy::OracleLogMultiBare => {
                EstimatorKind::Oracle
            }
        }
    }

    /// Whether this strategy may read the simulator's truth (only the oracles).
    pub fn is_oracle(self) -> bool {
        matches!(
            self,
            Strategy::Oracle | Strategy::OracleLog | Strategy::OracleLogMultiBare
        )
    }

    /// Whether the top level runs a Kalman filter (consistency is reported).
    pub fn is_kalman(self) -> bool {
        matches!(
            self,
            Strategy::Default
                | Strategy::Kalman
                | Strategy::KalmanAdaptiveQ
                | Strategy::KalmanLog
                | Strategy::KalmanTr
                | Strategy::KalmanLogTr
                | Strategy::KalmanLogTrMulti
                | Strategy::KalmanLogTrMultiBare
        )
    }

    /// Whether `t_sr` and `w` are tuned in log space.
    pub fn log_space(self) -> bool {
        matches!(
            self,
            Strategy::KalmanLog
                | Strategy::OracleLog
                | Strategy::OracleLogMultiBare
                | Strategy::KalmanLogTr
                | Strategy::KalmanLogTrMulti
                | Strategy::KalmanLogTrMultiBare
        )
    }

    /// The top level's step rule: the covariance-aware trust region for the
    /// `-tr` strategies, the paper's pseudo-inverse for all others
    /// (independent of [`crate::solver::SolverConfig`]'s default).
    ///
    /// ```
    /// use spintune::benchmark::Strategy;
    /// use spintune::solver::StepRule;
    /// assert_eq!(Strategy::KalmanLog.step_rule(), StepRule::PseudoInverse);
    /// assert_eq!(Strategy::KalmanLogTr.step_rule(), StepRule::ExpectedCost);
    /// ```
    pub fn step_rule(self) -> StepRule {
        match self {
            Strategy::KalmanTr
            | Strategy::KalmanLogTr
            | Strategy::KalmanLogTrMulti
            | Strategy::KalmanLogTrMultiBare
            | Strategy::OracleLogMultiBare => StepRule::ExpectedCost,
            _ => StepRule::PseudoInverse,
        }
    }

    /// Limited moves per measure-and-decide iteration (1 but for the
    /// `-multi` strategies: [`MULTI_MOVES`], before the protocol's
    /// [`BenchmarkProtocol::multi_moves`] overrides it).
    ///
    /// ```
    /// use spintune::benchmark::{Strategy, MULTI_MOVES};
    /// assert_eq!(Strategy::KalmanLogTr.max_moves_per_iteration(), 1);
    /// assert_eq!(Strategy::KalmanLogTrMultiBare.max_moves_per_iteration(), MULTI_MOVES);
    /// ```
    pub fn max_moves_per_iteration(self) -> u32 {
        match self {
            Strategy::KalmanLogTrMulti
            | Strategy::KalmanLogTrMultiBare
            | Strategy::OracleLogMultiBare => MULTI_MOVES,
            _ => 1,
        }
    }
}

/// Protocol settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BenchmarkProtocol {
    /// Set points `(t_sr ns, w µV)`, visited in order.
    pub set_points: Vec<(f64, f64)>,
    /// Iterations at each set point, regardless of convergence.
    pub iterations_per_set_point: u32,
    /// Relative tolerance band of both parameters (0.1 = ±10 %).
    pub relative_tolerance: f64,
    /// Relative error of the lab's virtual-gate matrix: each element is the
    /// device's first-order value times `1 + u`, `u` uniform in
    /// `[−e, +e]` drawn per seed (0.2 = ±20 %; 0 = exact).
    #[serde(default = "default_compensation_error")]
    pub compensation_error: f64,
    /// Step rule of the `-tr` strategies.
    #[serde(default = "default_tr_rule")]
    pub tr_rule: StepRule,
    /// [`crate::solver::SolverConfig::covariance_weight`] of the `-tr` strategies.
    #[serde(default = "default_covariance_weight")]
    pub covariance_weight: f64,
    /// Moves per iteration of the `-multi` strategies.
    #[serde(default = "default_multi_moves")]
    pub multi_moves: u32,
}

fn default_tr_rule() -> StepRule {
    StepRule::ExpectedCost
}
fn default_covariance_weight() -> f64 {
    0.0
}
fn default_multi_moves() -> u32 {
    MULTI_MOVES
}

fn default_compensation_error() -> f64 {
    0.2
}

impl Default for BenchmarkProtocol {
    fn default() -> Self {
        Self {
            set_points: PAPER_SET_POINTS.to_vec(),
            iterations_per_set_point: 21,
            relative_tolerance: 0.1,
            compensation_error: default_compensation_error(),
            tr_rule: default_tr_rule(),
            covariance_weight: default_covariance_weight(),
            multi_moves: default_multi_moves(),
        }
    }
}

/// Outcome of one target change for one strategy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeResult {
    /// Measure-and-decide iterations (top-level records) after the change
    /// until one measured both parameters in their bands; `None` if not
    /// within the block.
    pub iterations: Option<u32>,
    /// Top-level moves (set requests changing a top-level gate, retreats
    /// included) from the change until then; `None` if not converged.
    #[serde(default)]
    pub moves: Option<u32>,
    /// Lab time from the change until then, minutes (`None` if not converged).
    pub lab_minutes: Option<f64>,
    /// The same lab time by request kind ([`request_kind`]), s of the
    /// device's clock (empty if not converged; the session's read-backs are
    /// under `read_voltages`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub lab_seconds_by_kind: BTreeMap<String, f64>,
}

/// One strategy on one seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeedResult {
    /// Strategy.
    pub strategy: Strategy,
    /// Seed.
    pub seed: u64,
    /// Which device (0: the base device; `k`: the random device drawn with seed `k`,
    /// see [`draw_devices`]). Set by the caller; [`run_seed`] leaves 0.
    #[serde(default)]
    pub device: u64,
    /// One entry per set point.
    pub changes: Vec<ChangeResult>,
    /// Lab minutes from the run's start (initial gradient and lower levels
    /// included) to the first record declared tuned at the first set point
    /// (`None` if the first change did not converge).
    #[serde(default)]
    pub cold_start_lab_minutes: Option<f64>,
    /// Records declared tuned (every change, every iteration).
    #[serde(default)]
    pub tuned_records: u64,
    /// Of those, the records whose device truly had both parameters in
    /// their bands (the world's truth, never seen by the tuner).
    #[serde(default)]
    pub truly_in_band: u64,
    /// Requests the safety limits refused, plus top-level moves above the
    /// step limit (each move checked on its way to the device).
    pub limit_violations: u64,
    /// Failed or rejected evaluations (all scans, all levels).
    pub failed_fits: u64,
    /// Requests for the simulator's truth this run made (0 unless an oracle).
    pub truth_queries: u64,
    /// Top-level filter consistency per parameter name (every strategy with
    /// innovations; meaningful for the Kalman strategies).
    pub consistency: BTreeMap<String, Consistency>,
    /// All top-level records (for plots); empty unless requested.
    pub records: Vec<IterationRecord>,
}

/// What a lab has after the initial finite-difference measurement, and all
/// that [`configure_strategy`] may use: the (lab's) configuration with the
/// learned gradients, and the values measured at the start.
#[derive(Debug, Clone, PartialEq)]
pub struct LabKnowledge {
    /// The tuner configuration, initial gradients as measured.
    pub config: TunerConfig,
    /// The top level's last measured values (config order, parameter units).
    pub start_values: Vec<Option<ParameterValue>>,
}

/// The configuration of one strategy, from what a lab knows only.
/// Log-space strategies rescale the measured gradient, its covariance and Q
/// by the measured start values (falling back to the target where a start
/// value is missing).
pub fn configure_strategy(
    strategy: Strategy,
    lab: &LabKnowledge,
    protocol: &BenchmarkProtocol,
) -> TunerConfig {
    let mut tcfg = lab.config.clone();
    tcfg.max_iterations = None;
    let top = tcfg.top_mut();
    top.estimator = strategy.estimator();
    top.solver.rule = strategy.step_rule();
    top.solver.max_moves_per_iteration = strategy.max_moves_per_iteration();
    if top.solver.rule == StepRule::ExpectedCost {
        top.solver.rule = protocol.tr_rule;
        top.solver.covariance_weight = protocol.covariance_weight;
    }
    if top.solver.max_moves_per_iteration > 1 {
        top.solver.max_moves_per_iteration = protocol.multi_moves;
    }
    top.solver.lower_levels_between_moves = !matches!(
        strategy,
        Strategy::KalmanLogTrMultiBare | Strategy::OracleLogMultiBare
    );
    if strategy.log_space() {
        let values: Vec<f64> = top
            .parameters
            .iter()
            .enumerate()
            .map(|(i, p)| {
                lab.start_values
                    .get(i)
                    .and_then(|v| v.as_ref())
                    .map(|v| v.value)
                    .filter(|v| v.is_finite() && *v > 0.0)
                    .or(p.target)
                    .unwrap_or(1.0)
            })
            .collect();
        for (p, typical) in top.parameters.iter_mut().zip(&values) {
            p.transform = Transform::Log;
            p.process_noise_per_mv /= typical;
        }
        if let InitialGradient::Given {
            gradient,
            covariance,
        } = &mut top.initial_gradient
        {
            for ((row, cov), value) in gradient.iter_mut().zip(covariance.iter_mut()).zip(&values) {
                row.iter_mut().for_each(|g| *g /= value);
                cov.iter_mut().flatten().for_each(|c| *c /= value * value);
            }
        }
    }
    tcfg
}

/// The lab's virtual-gate matrix for one seed: the device's first-order
/// compensation ([`DeviceConfig::nominal_compensation`], the world's truth)
/// with every element multiplied by `1 + u`, `u` uniform in
/// `[−relative_error, +relative_error]` from a ChaCha8 stream seeded by
/// `seed` (deterministic). Rows: `plungers`; columns: `tuning`.
///
/// ```
/// use spintune::benchmark::perturbed_compensation;
/// let d = spintune::sim::DeviceConfig::default();
/// let exact = d.nominal_compensation(&["N", "T"], &["PA", "PB"]);
/// let m = perturbed_compensation(&d, &["N", "T"], &["PA", "PB"], 0.2, 7);
/// for (r, e) in m.iter().flatten().zip(exact.iter().flatten()) {
///     assert!((r - e).abs() <= 0.2 * e.abs() + 1e-15);
/// }
/// assert_eq!(m, perturbed_compensation(&d, &["N", "T"], &["PA", "PB"], 0.2, 7));
/// ```
pub fn perturbed_compensation(
    device: &DeviceConfig,
    tuning: &[&str],
    plungers: &[&str],
    relative_error: f64,
    seed: u64,
) -> Vec<Vec<f64>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7669_7274_7561_6c67); // "virtualg"
    device
        .nominal_compensation(tuning, plungers)
        .into_iter()
        .map(|row| {
            row.into_iter()
                .map(|m| m * (1.0 + relative_error * rng.gen_range(-1.0..=1.0)))
                .collect()
        })
        .collect()
}

/// Why a seed could not be benchmarked: the seed, the strategy (if one
/// strategy failed) and the cause.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("seed {seed}: {}{cause}", strategy.map(|s| format!("{}: ", s.name())).unwrap_or_default())]
pub struct BenchmarkError {
    /// Seed.
    pub seed: u64,
    /// The strategy that failed (`None`: the shared initial measurement).
    pub strategy: Option<Strategy>,
    /// What went wrong.
    pub cause: SeedFailure,
}

/// What ended a seed's benchmark early.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SeedFailure {
    /// A configuration the core refused.
    #[error("invalid configuration: {0}")]
    Config(#[from] crate::config_error::ConfigError),
    /// The initial measurement asked for the simulator's truth.
    #[error("the initial measurement queried the truth")]
    TruthQueried,
    /// The simulated run halted (fault, pause, driver bug).
    #[error(transparent)]
    Halt(#[from] crate::driver::Halt),
    /// The benchmark's driver broke the session's protocol (a bug).
    #[error(transparent)]
    Session(#[from] crate::session::SessionError),
    /// A control command (a target change) was refused.
    #[error(transparent)]
    Control(#[from] crate::session::ControlError),
    /// The run faulted (the guard refusing a request counts as a limit violation).
    #[error("run faulted: {0}")]
    Faulted(crate::protocol::Fault),
    /// The run waits for something else (e.g. paused).
    #[error("run waiting ({0:?})")]
    Waiting(RunStatus),
    /// The tuner finished before the protocol did.
    #[error("tuner finished unexpectedly")]
    Finished,
    /// The simulated device gave an answer that does not fit the request.
    #[error("unexpected device answer: {0:?}")]
    Unexpected(crate::protocol::Response),
}

/// The world's configuration of one seed: `base` on seed `seed` with the
/// lab's imperfect virtual-gate matrix ([`perturbed_compensation`]) and the
/// protocol's tolerance band on the top level's parameters. The initial
/// measurement only (`max_iterations = 0`); the targets come with the
/// protocol's first change.
pub(crate) fn world_config(
    base: &SimulationConfig,
    protocol: &BenchmarkProtocol,
    seed: u64,
) -> SimulationConfig {
    let mut cfg = base.clone();
    cfg.seed = seed;
    cfg.tuner.max_iterations = Some(0);
    cfg.tuner.stop_when_tuned = false;
    cfg.tuner.schedule.clear();
    let device_config = cfg.device.clone();
    for level in &mut cfg.tuner.levels {
        if let LevelKind::Newton(n) = &mut level.kind {
            let tuning: Vec<&str> = n.gates.iter().map(String::as_str).collect();
            if let Some(c) = &mut n.compensation {
                let plungers: Vec<&str> = c.gates.iter().map(String::as_str).collect();
                c.matrix = perturbed_compensation(
                    &device_config,
                    &tuning,
                    &plungers,
                    protocol.compensation_error,
                    seed,
                );
                c.relative_uncertainty = protocol.compensation_error;
            }
        }
    }
    for p in &mut cfg.tuner.top_mut().parameters {
        p.tolerance = Tolerance::Relative(protocol.relative_tolerance);
    }
    cfg
}

/// Run a config's initial measurement (its cold start: the initial gradient
/// with the lower levels) on a sealed device; returns the run, ready to go on.
fn cold_start(cfg: SimulationConfig) -> Result<SimulationRun, SeedFailure> {
    let mut init = SimulationRun::new(cfg)?;
    init.device_mut().seal_truth();
    while init.next_iteration()?.is_some() {}
    if init.device().truth_queries() != 0 {
        return Err(SeedFailure::TruthQueried);
    }
    Ok(init)
}

/// Run every strategy on one seed. `keep_records` keeps the iteration records.
///
/// `base` is the paper's setup ([`SimulationConfig::paper_default`], its
/// device possibly replaced): every strategy but [`Strategy::Default`]
/// starts from one shared initial measurement of it. [`Strategy::Default`]
/// runs `product` (the tuner `spintune run` uses, e.g.
/// [`SimulationConfig::recommended`]'s) on the same device and seed from
/// its own cold start.
pub fn run_seed(
    base: &SimulationConfig,
    product: &TunerConfig,
    protocol: &BenchmarkProtocol,
    strategies: &[Strategy],
    seed: u64,
    keep_records: bool,
) -> Result<Vec<SeedResult>, BenchmarkError> {
    let err = |strategy: Option<Strategy>| {
        move |cause: SeedFailure| BenchmarkError {
            seed,
            strategy,
            cause,
        }
    };
    let classic = strategies.iter().any(|s| *s != Strategy::Default);
    // --- the world: the simulated lab and its imperfect configuration ---
    let mut cfg = world_config(base, protocol, seed);
    cfg.tuner.top_mut().estimator = EstimatorKind::Kalman;
    // --- the experimenter: the shared starting point, on a sealed device ---
    let shared = classic
        .then(|| cold_start(cfg))
        .transpose()
        .map_err(err(None))?;
    strategies
        .iter()
        .map(|&strategy| {
            let named = err(Some(strategy));
            if strategy == Strategy::Default {
                let mut world = base.clone();
                world.tuner = product.clone();
                let init = cold_start(world_config(&world, protocol, seed)).map_err(named)?;
                let start = init.tuner().lab_seconds();
                let mut tuner = init.tuner().clone();
                tuner.set_max_iterations(None);
                return run_protocol(
                    strategy,
                    seed,
                    tuner,
                    init.device().clone(),
                    protocol,
                    start,
                    keep_records,
                )
                .map_err(named);
            }
            let init = shared
                .as_ref()
                .expect("a classic strategy ran the shared start");
            let lab = LabKnowledge {
                config: init.tuner().config_with_learned_gradients(),
                start_values: init.tuner().last_measured(0).unwrap_or_default().to_vec(),
            };
            let tcfg = configure_strategy(strategy, &lab, protocol);
            let mut tuner = Tuner::new(tcfg).map_err(|e| named(e.into()))?;
            // The lab clock goes on from the shared initial measurement.
            tuner.charge_lab_time(init.tuner().lab_seconds());
            // The world hands on the device state after the initial
            // measurement (RNG, drifts, clock); only the oracles get it
            // with the truth unsealed.
            let mut dev = init.device().clone();
            dev.truth_sealed = !strategy.is_oracle();
            run_protocol(
                strategy,
                seed,
                tuner,
                dev,
                protocol,
                init.tuner().lab_seconds(),
                keep_records,
            )
            .map_err(named)
        })
        .collect()
}

fn run_protocol(
    strategy: Strategy,
    seed: u64,
    tuner: Tuner,
    device: SimulatedDevice,
    protocol: &BenchmarkProtocol,
    start_lab_seconds: f64,
    keep_records: bool,
) -> Result<SeedResult, SeedFailure> {
    let top = tuner.config().top();
    let mut run = Harness {
        top_gates: top.gates.clone(),
        max_step_mv: top.solver.max_step_mv,
        session: RunSession::from_tuner(tuner, SessionConfig::default()),
        device,
        moves: 0,
        violations: 0,
        lab_by_kind: BTreeMap::new(),
    };
    let mut changes = Vec::new();
    let mut records = Vec::new();
    let mut lab_at_change = start_lab_seconds;
    let (mut tuned_records, mut truly_in_band) = (0u64, 0u64);
    let band = protocol.relative_tolerance;
    for &(t_sr, w) in &protocol.set_points {
        let tol = Some(Tolerance::Relative(protocol.relative_tolerance));
        for (parameter, target) in [("t_sr", t_sr), ("w", w)] {
            run.session.control(&ControlCommand::SetTarget {
                parameter: parameter.into(),
                target: Some(target),
                tolerance: tol,
            })?;
        }
        let moves_at_change = run.moves;
        let by_kind_at_change = run.lab_by_kind.clone();
        let mut converged: Option<ChangeResult> = None;
        let mut last_lab = lab_at_change;
        for k in 0..protocol.iterations_per_set_point {
            let rec = run.next()?;
            if rec.tuned {
                // The world's side: where the device truly is when the
                // tuner declares it tuned (no move follows a tuned record).
                let truth = run.device.truth();
                tuned_records += 1;
                if (truth.t_sr_ns - t_sr).abs() <= band * t_sr && (truth.w_uv - w).abs() <= band * w
                {
                    truly_in_band += 1;
                }
            }
            if converged.is_none() && rec.tuned {
                converged = Some(ChangeResult {
                    iterations: Some(k),
                    moves: Some((run.moves - moves_at_change) as u32),
                    lab_minutes: Some((rec.lab_seconds - lab_at_change) / 60.0),
                    lab_seconds_by_kind: run
                        .lab_by_kind
                        .iter()
                        .map(|(k, v)| {
                            let before = by_kind_at_change.get(k).copied().unwrap_or(0.0);
                            (k.to_string(), v - before)
                        })
                        .filter(|(_, v)| *v > 0.0)
                        .collect(),
                });
            }
            last_lab = rec.lab_seconds;
            if keep_records {
                records.push(rec);
            }
        }
        lab_at_change = last_lab;
        changes.push(converged.unwrap_or(ChangeResult {
            iterations: None,
            moves: None,
            lab_minutes: None,
            lab_seconds_by_kind: BTreeMap::new(),
        }));
    }
    let tuner = run.session.tuner();
    let names = tuner
        .config()
        .top()
        .parameters
        .iter()
        .map(|p| p.name.clone());
    let consistency = names
        .zip(tuner.consistency(0).unwrap_or_default().iter().copied())
        .filter(|(_, c)| c.count > 0)
        .collect();
    let cold_start_lab_minutes = changes
        .first()
        .and_then(|c: &ChangeResult| c.lab_minutes)
        .map(|m| start_lab_seconds / 60.0 + m);
    Ok(SeedResult {
        strategy,
        seed,
        device: 0,
        cold_start_lab_minutes,
        tuned_records,
        truly_in_band,
        changes,
        limit_violations: run.violations,
        failed_fits: tuner.failed_evaluations(),
        truth_queries: run.device.truth_queries(),
        consistency,
        records,
    })
}

/// The benchmark's own driver loop (as [`crate::driver::SimulationRun`]),
/// which also checks every top-level move on its way to the device,
/// independently of the tuner: the Euclidean norm over the top level's gates
/// of (requested − the device's present voltages) is a *move* if > 1 nV and
/// a *limit violation* if above the step limit. A fault ends the seed (the
/// guard refusing a request counts as a limit violation): the benchmark never
/// continues past a refused request.
struct Harness {
    session: RunSession,
    device: SimulatedDevice,
    top_gates: Vec<String>,
    max_step_mv: f64,
    moves: u64,
    violations: u64,
    /// Lab time of the device's clock per request kind, s.
    lab_by_kind: BTreeMap<&'static str, f64>,
}

impl Harness {
    /// The world's side of one request: count top-level moves and every
    /// move longer than the step limit (checked per move), then execute.
    fn execute(&mut self, request: &Request) -> Response {
        if let Request::SetVoltages { voltages_mv } = request {
            let now = self.device.voltages_mv();
            let norm = self
                .top_gates
                .iter()
                .filter_map(|g| Some((voltages_mv.get(g)? - now.get(g)?).powi(2)))
                .sum::<f64>()
                .sqrt();
            if norm > 1e-6 {
                self.moves += 1;
            }
            if !norm.is_finite() || norm > self.max_step_mv * (1.0 + 1e-9) {
                self.violations += 1;
            }
        }
        let t0 = self.device.lab_seconds();
        let response = self.device.execute(request);
        *self.lab_by_kind.entry(request_kind(request)).or_default() +=
            self.device.lab_seconds() - t0;
        response
    }

    fn next(&mut self) -> Result<IterationRecord, SeedFailure> {
        loop {
            match self.session.poll() {
                Output::Execute(request) => {
                    let response = self.execute(&request);
                    self.session.feed(response)?;
                }
                Output::Commit(record) => return Ok(*record),
                Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
                Output::Wait => {
                    return Err(match self.session.status() {
                        RunStatus::Faulted { fault } => {
                            if fault.kind == FaultKind::Safety {
                                self.violations += 1;
                            }
                            SeedFailure::Faulted(fault)
                        }
                        other => SeedFailure::Waiting(other),
                    })
                }
                Output::Done(_) => return Err(SeedFailure::Finished),
            }
        }
    }
}

/// A request's kind, as the benchmarks break lab time down
/// ([`ChangeResult::lab_seconds_by_kind`], the keep benchmark's
/// `minutes_per_hour_by_kind`).
///
/// ```
/// use spintune::benchmark::request_kind;
/// use spintune::protocol::Request;
/// assert_eq!(request_kind(&Request::Wait { seconds: 60.0 }), "wait");
/// ```
pub fn request_kind(request: &Request) -> &'static str {
    match request {
        Request::SetVoltages { .. } => "set_voltages",
        Request::ReadVoltages { .. } => "read_voltages",
        Request::Measure { scan } => match scan.kind {
            ScanKind::SensingDot => "sensing_dot",
            ScanKind::ChemicalPotential => "chemical_potential",
            ScanKind::TransitionWidth => "transition_width",
            ScanKind::ReloadTime => "reload_time",
        },
        Request::TrueJacobian { .. } => "true_jacobian",
        Request::Wait { .. } => "wait",
        Request::Batch { .. } => "batch",
    }
}

/// Summary statistics of one strategy over many seeds (keys as in the JSON report).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StrategySummary {
    /// Strategy name.
    pub name: String,
    /// Iterations per change: median, p90, max (non-converged changes count as the block length).
    pub iterations_per_change: Quantiles,
    /// Lab minutes per change: median and p90 over converged changes.
    pub lab_minutes_per_change: Quantiles,
    /// Top-level moves per change (a measure-and-decide iteration may make
    /// several): median, p90, max over converged changes.
    #[serde(default = "Quantiles::nan")]
    pub moves_per_change: Quantiles,
    /// Changes not reached within the block.
    pub not_converged: u64,
    /// Changes not reached within the block where an oracle run (`oracle` or
    /// `oracle-log`) on the same device and seed did reach it (`None`
    /// without an oracle run).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_converged_where_oracle_converged: Option<u64>,
    /// Lab minutes from a run's start to the first record declared tuned
    /// at the first set point: median, p90, max over the seeds where it
    /// converged ([`SeedResult::cold_start_lab_minutes`]).
    #[serde(default = "Quantiles::nan")]
    pub cold_start_lab_minutes: Quantiles,
    /// Fraction of the records declared tuned whose device was truly in
    /// both bands (world side; `None` without a tuned record).
    #[serde(default)]
    pub truly_in_band_at_tuned: Option<f64>,
    /// Must be 0.
    pub limit_violations: u64,
    /// Failed fits over all seeds.
    pub failed_fits: u64,
    /// Median iterations ÷ the (linear) oracle's median iterations (`None` without an oracle run).
    pub ratio_to_oracle: Option<f64>,
    /// Median iterations ÷ the log-space oracle's median (`None` without an `oracle-log` run).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ratio_to_oracle_log: Option<f64>,
    /// Number of changes measured.
    pub changes: u64,
    /// Requests for the simulator's truth over all seeds (must be 0 unless an oracle).
    #[serde(default)]
    pub truth_queries: u64,
    /// Filter consistency per parameter (Kalman strategies only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub consistency: Option<BTreeMap<String, ConsistencySummary>>,
    /// Where a change's lab time goes: mean lab seconds per converged change
    /// by request kind ([`request_kind`]); the kinds add up to the mean of
    /// [`StrategySummary::lab_minutes_per_change`] × 60 (up to the tuner's
    /// own bookkeeping of read-backs).
    #[serde(default)]
    pub lab_seconds_per_change_by_kind: BTreeMap<String, f64>,
}

/// Filter consistency of one parameter over all seeds: normalised innovation
/// squared `(z − Δv·g)²/(Δv C Δvᵀ + Δz²)` of the filter's predicted change
/// against the measured change (ideal mean 1, 4.6 % beyond 2σ).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConsistencySummary {
    /// Mean NIS.
    pub nis_mean: f64,
    /// Fraction of innovations beyond 2 predicted σ.
    pub beyond_2sigma: f64,
    /// Number of innovations.
    pub count: u64,
}

/// Order statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quantiles {
    /// Median.
    pub median: f64,
    /// 90th percentile.
    pub p90: f64,
    /// Maximum.
    pub max: f64,
}

impl Quantiles {
    /// All NaN (no data; e.g. a report from before the field existed).
    ///
    /// ```
    /// assert!(spintune::benchmark::Quantiles::nan().median.is_nan());
    /// ```
    pub fn nan() -> Self {
        Self {
            median: f64::NAN,
            p90: f64::NAN,
            max: f64::NAN,
        }
    }
}

/// Quantile by linear interpolation between order statistics (`q` in 0..=1).
///
/// ```
/// use spintune::benchmark::quantile;
/// assert_eq!(quantile(&[1.0, 2.0, 3.0, 4.0], 0.5), 2.5);
/// assert_eq!(quantile(&[5.0], 0.9), 5.0);
/// ```
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    v[lo] + (v[hi] - v[lo]) * (pos - lo as f64)
}

pub(crate) fn quantiles(values: &[f64]) -> Quantiles {
    Quantiles {
        median: quantile(values, 0.5),
        p90: quantile(values, 0.9),
        max: values.iter().copied().fold(f64::NAN, f64::max),
    }
}

/// Aggregate per-seed results into one summary per strategy (in `strategies` order).
pub fn summarize(
    results: &[SeedResult],
    strategies: &[Strategy],
    block: u32,
) -> Vec<StrategySummary> {
    let mut out: Vec<StrategySummary> = strategies
        .iter()
        .map(|&s| {
            let mine: Vec<&SeedResult> = results.iter().filter(|r| r.strategy == s).collect();
            let changes: Vec<&ChangeResult> = mine.iter().flat_map(|r| &r.changes).collect();
            let iters: Vec<f64> = changes
                .iter()
                .map(|c| c.iterations.map_or(block as f64, f64::from))
                .collect();
            let minutes: Vec<f64> = changes.iter().filter_map(|c| c.lab_minutes).collect();
            let moves: Vec<f64> = changes
                .iter()
                .filter_map(|c| c.moves.map(f64::from))
                .collect();
            StrategySummary {
                name: s.name().to_string(),
                iterations_per_change: quantiles(&iters),
                lab_minutes_per_change: quantiles(&minutes),
                moves_per_change: quantiles(&moves),
                cold_start_lab_minutes: quantiles(
                    &mine
                        .iter()
                        .filter_map(|r| r.cold_start_lab_minutes)
                        .collect::<Vec<_>>(),
                ),
                truly_in_band_at_tuned: {
                    let tuned: u64 = mine.iter().map(|r| r.tuned_records).sum();
                    (tuned > 0).then(|| {
                        mine.iter().map(|r| r.truly_in_band).sum::<u64>() as f64 / tuned as f64
                    })
                },
                not_converged: changes.iter().filter(|c| c.iterations.is_none()).count() as u64,
                not_converged_where_oracle_converged: oracle_missed(results, &mine),
                limit_violations: mine.iter().map(|r| r.limit_violations).sum(),
                failed_fits: mine.iter().map(|r| r.failed_fits).sum(),
                ratio_to_oracle: None,
                ratio_to_oracle_log: None,
                changes: changes.len() as u64,
                truth_queries: mine.iter().map(|r| r.truth_queries).sum(),
                consistency: s.is_kalman().then(|| consistency_summary(&mine)),
                lab_seconds_per_change_by_kind: mean_by_kind(&changes),
            }
        })
        .collect();
    let ratio = |mine: f64, oracle: f64| {
        if oracle > 0.0 {
            mine / oracle
        } else if mine == 0.0 {
            1.0
        } else {
            f64::INFINITY
        }
    };
    let median_of = |out: &[StrategySummary], s: Strategy| {
        out.iter()
            .find(|x| x.name == s.name())
            .map(|x| x.iterations_per_change.median)
    };
    let (lin, log) = (
        median_of(&out, Strategy::Oracle),
        median_of(&out, Strategy::OracleLog),
    );
    for s in &mut out {
        let m = s.iterations_per_change.median;
        s.ratio_to_oracle = lin.map(|o| ratio(m, o));
        s.ratio_to_oracle_log = log.map(|o| ratio(m, o));
    }
    out
}

/// Mean lab seconds per converged change by request kind.
fn mean_by_kind(changes: &[&ChangeResult]) -> BTreeMap<String, f64> {
    let converged: Vec<&&ChangeResult> =
        changes.iter().filter(|c| c.lab_minutes.is_some()).collect();
    let mut out = BTreeMap::new();
    for c in &converged {
        for (k, v) in &c.lab_seconds_by_kind {
            *out.entry(k.clone()).or_default() += v / converged.len() as f64;
        }
    }
    out
}

/// Changes of `mine` not converged where an oracle run of the same device and
/// seed converged; `None` if `results` hold no oracle run.
fn oracle_missed(results: &[SeedResult], mine: &[&SeedResult]) -> Option<u64> {
    let oracle_done: std::collections::BTreeSet<(u64, u64, usize)> = results
        .iter()
        .filter(|r| r.strategy.is_oracle())
        .flat_map(|r| {
            r.changes
                .iter()
                .enumerate()
                .filter(|(_, c)| c.iterations.is_some())
                .map(move |(i, _)| (r.device, r.seed, i))
        })
        .collect();
    if !results.iter().any(|r| r.strategy.is_oracle()) {
        return None;
    }
    Some(
        mine.iter()
            .flat_map(|r| {
                r.changes
                    .iter()
                    .enumerate()
                    .filter(|(_, c)| c.iterations.is_none())
                    .map(move |(i, _)| (r.device, r.seed, i))
            })
            .filter(|k| oracle_done.contains(k))
            .count() as u64,
    )
}

/// Draw `n` plausible devices around `base.device` with device seeds
/// `first_seed, first_seed + 1, …`
/// ([`crate::sim::random::random_device`]), rejecting those whose set
/// points cannot be reached within the gate limits
/// ([`crate::sim::random::targets_reachable`], tuning gates and plungers of
/// the top level and its compensation). Returns the accepted `(device
/// seed, device)` pairs and the number rejected; gives up after `20·n`
/// draws.
pub fn draw_devices(
    base: &SimulationConfig,
    protocol: &BenchmarkProtocol,
    n: usize,
    first_seed: u64,
) -> (Vec<(u64, DeviceConfig)>, u64) {
    let top = base.tuner.top();
    let tuning: Vec<&str> = top.gates.iter().map(String::as_str).collect();
    let plungers: Vec<&str> = top
        .compensation
        .as_ref()
        .map(|c| c.gates.iter().map(String::as_str).collect())
        .unwrap_or_default();
    let mut accepted = Vec::new();
    let mut rejected = 0;
    let mut seed = first_seed;
    while accepted.len() < n && seed < first_seed + 20 * n as u64 {
        let d = crate::sim::random::random_device(&base.device, seed);
        if crate::sim::random::targets_reachable(
            &d,
            &base.tuner.gates,
            &tuning,
            &plungers,
            &protocol.set_points,
        ) {
            accepted.push((seed, d));
        } else {
            rejected += 1;
        }
        seed += 1;
    }
    (accepted, rejected)
}

fn consistency_summary(results: &[&SeedResult]) -> BTreeMap<String, ConsistencySummary> {
    let mut total: BTreeMap<String, Consistency> = BTreeMap::new();
    for r in results {
        for (name, c) in &r.consistency {
            total.entry(name.clone()).or_default().merge(c);
        }
    }
    total
        .into_iter()
        .filter_map(|(name, c)| {
            Some((
                name,
                ConsistencySummary {
                    nis_mean: c.nis_mean()?,
                    beyond_2sigma: c.beyond_2sigma_fraction()?,
                    count: c.count,
                },
            ))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for s in Strategy::ALL {
            assert_eq!(Strategy::from_name(s.name()), Some(s));
        }
    }

    #[test]
    fn summary_counts_non_converged_as_block_length() {
        let r = |s, its: Vec<Option<u32>>| SeedResult {
            strategy: s,
            seed: 0,
            device: 0,
            changes: its
                .into_iter()
                .map(|i| ChangeResult {
                    iterations: i,
                    moves: i.map(|x| 2 * x),
                    lab_minutes: i.map(|x| x as f64 * 2.0),
                    // 2 lab min per iteration: 90 s of w scans, 30 s of moves
                    lab_seconds_by_kind: i
                        .map(|x| {
                            BTreeMap::from([
                                ("transition_width".to_string(), 90.0 * x as f64),
                                ("set_voltages".to_string(), 30.0 * x as f64),
                            ])
                        })
                        .unwrap_or_default(),
                })
                .collect(),
            cold_start_lab_minutes: None,
            tuned_records: 0,
            truly_in_band: 0,
            limit_violations: 0,
            failed_fits: 1,
            truth_queries: 0,
            consistency: BTreeMap::new(),
            records: vec![],
        };
        let results = vec![
            r(Strategy::Kalman, vec![Some(2), Some(4), None]),
            r(Strategy::Oracle, vec![Some(1), Some(2), Some(2)]),
        ];
        let s = summarize(&results, &[Strategy::Kalman, Strategy::Oracle], 21);
        assert_eq!(s[0].iterations_per_change.median, 4.0);
        assert_eq!(s[0].iterations_per_change.max, 21.0);
        assert_eq!(s[0].not_converged, 1);
        assert_eq!(s[0].ratio_to_oracle, Some(2.0));
        assert_eq!(s[0].lab_minutes_per_change.median, 6.0);
        // moves over the converged changes only: 4, 8
        assert_eq!(s[0].moves_per_change.median, 6.0);
        assert_eq!(s[0].moves_per_change.max, 8.0);
        // the breakdown is a mean over the converged changes (2 and 4 iterations)
        let by = &s[0].lab_seconds_per_change_by_kind;
        assert_eq!(by["transition_width"], 270.0);
        assert_eq!(by["set_voltages"], 90.0);
    }
}
