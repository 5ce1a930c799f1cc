//! Configuration of a tuner hierarchy: gates, levels, parameters, estimators.
//!
//! All voltages in mV, gradients in parameter unit per mV.

use serde::{Deserialize, Serialize};

pub use crate::config_error::ConfigError;
use crate::estimator::EstimatorKind;
use crate::fit::uncertainty::References;
use crate::parameter::ParameterSpec;
use crate::safety::GateSpec;
use crate::solver::SolverConfig;

use super::search::ParameterSearch;

/// How a Newton level obtains its initial gradient `g(0)` and covariance `C(0)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum InitialGradient {
    /// Measure by one-sided finite differences, `repetitions` times:
    /// `g(0)` the mean, `C(0)` diagonal with the sample variances of the
    /// individual estimates (with one repetition: the variance propagated from
    /// the measurement errors).
    FiniteDifference {
        /// Voltage offset per gate, mV.
        step_mv: f64,
        /// Number of repetitions (≥ 1).
        repetitions: u32,
        /// Run the levels of `after_move` (sensing dot, line re-centring)
        /// after every offset (`true`, the paper's procedure) or only before
        /// the first measurement and after the return to the base point
        /// (`false`: an offset of `step_mv` moves the lines and the sensor
        /// by a fraction of their scan windows, so the scans stay usable and
        /// the cold start costs a fraction of the lab time). Default `true`.
        #[serde(default = "default_true")]
        recentre_between_offsets: bool,
        /// Measure each gate at `−step_mv` too and take the central
        /// difference (`finite_difference` module docs): effects even in
        /// the offset cancel (the transition lines that an offset moves
        /// when the levels are not re-run between offsets) and the noise
        /// halves, for one more measurement per gate. Every gate at
        /// `+step_mv`, then every gate at `−step_mv`: consecutive points
        /// offset different gates (`√2·step_mv` apart; through the base
        /// where that exceeds the solver's `max_step_mv`, or with one
        /// gate). Default `false` (the paper's one-sided differences).
        #[serde(default)]
        central: bool,
        /// Per repetition (missing: `false`), whether its offsets take the
        /// opposite sign: every gate at `−step_mv` first, then (central)
        /// at `+step_mv`. On one double dot the same points in another
        /// order; in an array whose cells take their differences in
        /// lockstep, two cells mirrored against each other move opposite
        /// ways at every point, so their crosstalk enters that repetition's
        /// estimate with a minus sign (`tuner::array_run`,
        /// `staggered_differences`). At most `repetitions` entries.
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        mirrored: Vec<bool>,
    },
    /// Known gradient rows (one per parameter, unit/mV) and covariances.
    Given {
        /// `gradient[i][j] = ∂p_i/∂v_j`.
        gradient: Vec<Vec<f64>>,
        /// One n×n covariance per parameter.
        covariance: Vec<Vec<Vec<f64>>>,
    },
    /// A rough guess: `C(0) = diag((relative_std · g(0))²)`; the paper's recipe
    /// with `relative_std ≈ 1` lets the filter effectively re-learn.
    RoughGuess {
        /// `gradient[i][j] = ∂p_i/∂v_j`.
        gradient: Vec<Vec<f64>>,
        /// Relative standard deviation of each element.
        relative_std: f64,
    },
}

/// Linear virtual-gate compensation applied with every move of a level:
/// `Δv_gates = matrix · Δv_level`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Compensation {
    /// Compensating gates (rows), e.g. `["PA", "PB"]`.
    pub gates: Vec<String>,
    /// Rows: compensating gates; columns: the level's gates (dimensionless, mV/mV).
    /// Configuration a lab supplies (e.g. from the slopes of charge-stability
    /// diagrams); never derived from the simulator's truth (invariant 7).
    pub matrix: Vec<Vec<f64>>,
    /// Relative 1σ uncertainty of each matrix element as the lab knows it
    /// (dimensionless, 0 ≤ u ≤ 10; default 0.2). Documentation for the
    /// operator and the benchmark's perturbation scale: the tuner does not
    /// rely on the matrix being exact, the chemical-potential level re-centres
    /// the lines after every move.
    #[serde(default = "default_compensation_uncertainty")]
    pub relative_uncertainty: f64,
}

fn default_true() -> bool {
    true
}

fn default_compensation_uncertainty() -> f64 {
    0.2
}

/// A quasi-Newton level: parameters driven by gates through an estimated Jacobian.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewtonConfig {
    /// Gates this level moves (Jacobian columns), e.g. `["N", "SA", "SB", "T"]`.
    pub gates: Vec<String>,
    /// Parameters (Jacobian rows).
    pub parameters: Vec<ParameterSpec>,
    /// Gradient estimator.
    pub estimator: EstimatorKind,
    /// Where `g(0)`, `C(0)` come from.
    pub initial_gradient: InitialGradient,
    /// Step limit and rank tolerance.
    #[serde(default)]
    pub solver: SolverConfig,
    /// Kalman innovations beyond this many σ are gated as outliers (`None`: never).
    #[serde(default)]
    pub outlier_sigma: Option<f64>,
    /// Steps smaller than this (mV) teach the estimator nothing.
    #[serde(default = "default_min_step_mv")]
    pub min_step_mv: f64,
    /// Finite-difference offset for `fd-newton` re-measurements, mV.
    #[serde(default = "default_fd_step_mv")]
    pub fd_step_mv: f64,
    /// For levels run as children: iterations per call before returning to the
    /// parent even if not tuned. Ignored for the top level.
    #[serde(default = "default_max_inner")]
    pub max_iterations_per_call: u32,
    /// Set each target from the first successful measurement (e.g. keep the
    /// transition lines where they were at the start).
    #[serde(default)]
    pub hold_initial_values: bool,
    /// Linear virtual-gate correction applied with each move.
    #[serde(default)]
    pub compensation: Option<Compensation>,
    /// For levels run as children: after a correction, end the call
    /// without the confirming measurement when the filter predicts every
    /// targeted parameter inside its band with this many standard
    /// deviations of margin (prediction `y + g·Δv`, variance
    /// `Δv C Δvᵀ + δy²`, in estimator space). The next call measures
    /// anyway. `None` (default): always confirm. Ignored for the top level.
    #[serde(default)]
    pub skip_confirmation_sigma: Option<f64>,
    /// For levels run as children: correct from a learned forecast instead
    /// of scanning when the forecast is confident (`None`, the paper's rule:
    /// scan at every call). Refused on the top level.
    #[serde(default)]
    pub forecast: Option<ParameterForecast>,
    /// For levels run as children: search for parameters the scans lost
    /// (a line that left the scan's window) by probing the level's gates
    /// (`tuner::search`). `None` (default, the paper's rule): retreat and
    /// re-scan only. Refused on the top level.
    #[serde(default)]
    pub search: Option<ParameterSearch>,
}

/// Correct a child level from a forecast of its parameters instead of
/// scanning them (e.g. the transition lines after the qubit level's move).
///
/// Every parameter is predicted from the level's last scan, its own
/// Jacobian for its own gates' moves, and a learned row (Kalman, zero-mean
/// prior) for every other gate's move since — what the parents' virtual-gate
/// compensation did not cancel. When the level is next called and every
/// targeted parameter's predicted standard deviation is at most `skip_std`,
/// it takes one Newton step on the forecast (or none, if the forecast is
/// inside the band) without a scan (event `measurement_skipped`). It scans
/// anyway after `max_skips` such calls in a row, when any scan failed to
/// evaluate since its last scan, when its last scan is more than
/// `max_age_s` of lab time old, and whenever it has no scan to start from.
/// Units are the parameters' estimator units (mV for the chemical
/// potentials). Every move goes through the guard like any other.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParameterForecast {
    /// Largest predicted standard deviation at which the scan is skipped,
    /// estimator units (0 < value ≤ 1000).
    #[serde(default = "default_forecast_skip_std")]
    pub skip_std: f64,
    /// Prior standard deviation of each other gate's lever on a parameter,
    /// estimator units per mV (0 < value ≤ 10).
    #[serde(default = "default_prior_lever")]
    pub prior_lever_per_mv: f64,
    /// Scatter between scans that no gate explains (fit noise, drift,
    /// charge jumps), estimator units (0 ≤ value ≤ 1000).
    #[serde(default = "default_forecast_noise")]
    pub noise: f64,
    /// Forecast calls in a row after which the level scans anyway
    /// (0..=[`MAX_FLANK_SKIPS`]).
    #[serde(default = "default_max_skips")]
    pub max_skips: u32,
    /// Lab time after the level's last scan beyond which it scans anyway,
    /// s (0 < value ≤ 86400): the model knows the gates' moves, not the
    /// drift and charge jumps that accumulate while nothing moves (e.g.
    /// between keep mode's checks).
    #[serde(default = "default_forecast_max_age_s")]
    pub max_age_s: f64,
}

/// Chosen on random devices 101–130 (`docs/benchmarks.md`, "Choosing the
/// line forecast"): lab time per change falls up to 0.5 mV, and from 0.7 mV
/// on changes are left unconverged; 0.3 mV keeps a margin from that edge.
fn default_forecast_skip_std() -> f64 {
    0.3
}
fn default_forecast_noise() -> f64 {
    0.05
}
/// A tuning change takes a few lab minutes; keep mode's checks are tens of
/// minutes to hours apart. Set once, not tuned.
fn default_forecast_max_age_s() -> f64 {
    900.0
}

impl Default for ParameterForecast {
    fn default() -> Self {
        Self {
            skip_std: default_forecast_skip_std(),
            prior_lever_per_mv: default_prior_lever(),
            noise: default_forecast_noise(),
            max_skips: default_max_skips(),
            max_age_s: default_forecast_max_age_s(),
        }
    }
}

impl ParameterForecast {
    /// Whether a forecast `sample` (estimator value and variance) is
    /// narrow enough to act on: its standard deviation at most `skip_std`
    /// (`None`, no forecast: not confident).
    ///
    /// ```
    /// use spintune::tuner::ParameterForecast;
    /// let f = ParameterForecast::default(); // skip_std 0.3
    /// assert!(f.confident(Some((1.2, 0.3 * 0.3))));
    /// assert!(!f.confident(Some((1.2, 0.31 * 0.31))));
    /// assert!(!f.confident(None));
    /// ```
    pub fn confident(&self, sample: Option<(f64, f64)>) -> bool {
        sample.is_some_and(|(_, var)| var.sqrt() <= self.skip_std)
    }

    /// Check the bounds; the error names the field (relative to the level).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !within(self.skip_std, true, 1000.0) {
            return Err(ConfigError::new(
                "forecast.skip_std",
                "must be > 0 and ≤ 1000",
            ));
        }
        if !within(self.prior_lever_per_mv, true, 10.0) {
            return Err(ConfigError::new(
                "forecast.prior_lever_per_mv",
                "must be > 0 and ≤ 10 per mV",
            ));
        }
        if !within(self.noise, false, 1000.0) {
            return Err(ConfigError::new("forecast.noise", "must be ≥ 0 and ≤ 1000"));
        }
        if self.max_skips > MAX_FLANK_SKIPS {
            return Err(ConfigError::new(
                "forecast.max_skips",
                format!("must be at most {MAX_FLANK_SKIPS}"),
            ));
        }
        if !within(self.max_age_s, true, 86400.0) {
            return Err(ConfigError::new(
                "forecast.max_age_s",
                "must be > 0 and ≤ 86400 s",
            ));
        }
        Ok(())
    }
}

fn default_min_step_mv() -> f64 {
    0.01
}
fn default_fd_step_mv() -> f64 {
    2.0
}
fn default_max_inner() -> u32 {
    3
}

/// Largest magnitude of any non-integer number of a config (tuner, run), in
/// its unit (mV, ns, µV, …); gate voltages are bounded tighter
/// ([`MAX_GATE_MV`]). Every field has its own range on top of this one.
pub const MAX_MAGNITUDE: f64 = 1e6;

/// Largest integer of a config, except fields named `seed` (any 64-bit seed
/// is fine). Integer fields with their own tighter bounds (sweep points,
/// timeouts) check those too.
pub const MAX_INTEGER: u64 = 1 << 40;

/// Check every number of a config given as a JSON value: non-integers
/// finite and within ±[`MAX_MAGNITUDE`], integers within ±[`MAX_INTEGER`]
/// (fields named `seed` exempt). The error names the field, prefixed by
/// `path`. This is the first check of [`TunerConfig::validate`] and of the
/// server's run-config parser: it keeps any value a config can carry far
/// from overflow and from allocation sizes (bounded by construction).
///
/// ```
/// use spintune::tuner::check_magnitudes;
/// let v = serde_json::json!({"a": {"b": [1.0, 1e300]}, "seed": u64::MAX});
/// let e = check_magnitudes(&v, "").unwrap_err();
/// assert_eq!(e.field, "a.b[1]");
/// assert!(check_magnitudes(&serde_json::json!({"seed": u64::MAX}), "").is_ok());
/// assert!(check_magnitudes(&serde_json::json!({"n": 1u64 << 41}), "").is_err());
/// ```
pub fn check_magnitudes(v: &serde_json::Value, path: &str) -> Result<(), ConfigError> {
    use serde_json::Value;
    match v {
        Value::Number(n) => {
            let is_seed = path == "seed" || path.ends_with(".seed");
            let ok = if let Some(u) = n.as_u64() {
                u <= MAX_INTEGER || is_seed
            } else if let Some(i) = n.as_i64() {
                i.unsigned_abs() <= MAX_INTEGER
            } else {
                n.as_f64()
                    .is_some_and(|x| x.is_finite() && x.abs() <= MAX_MAGNITUDE)
            };
            if ok {
                Ok(())
            } else if n.is_f64() {
                Err(ConfigError::new(
                    path,
                    format!("{n} is out of range (a finite number within ±{MAX_MAGNITUDE:e} in its unit)"),
                ))
            } else {
                Err(ConfigError::new(
                    path,
                    format!("{n} is out of range (integers of a config are at most {MAX_INTEGER})"),
                ))
            }
        }
        Value::Object(m) => m.iter().try_for_each(|(k, x)| {
            let p = if path.is_empty() {
                k.clone()
            } else {
                format!("{path}.{k}")
            };
            check_magnitudes(x, &p)
        }),
        Value::Array(a) => a
            .iter()
            .enumerate()
            .try_for_each(|(i, x)| check_magnitudes(x, &format!("{path}[{i}]"))),
        _ => Ok(()),
    }
}

/// Largest magnitude of a gate's limits, initial voltage and step, mV
/// (±100 V: beyond any DC source; bounded by construction).
pub const MAX_GATE_MV: f64 = 100_000.0;

/// Upper bound on the repetitions of [`InitialGradient::FiniteDifference`]
/// (bounded by construction: each repetition keeps its points).
pub const MAX_FD_REPETITIONS: u32 = 20;

/// Upper bound on [`SensingDotConfig::points`] (bounded by construction).
pub const MAX_SWEEP_POINTS: usize = 10_000;

/// A sensing-dot level: sweep one gate and park it on the steepest flank of the
/// highest Coulomb peak.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensingDotConfig {
    /// Swept gate, e.g. `"SP"`.
    pub gate: String,
    /// Sweep half-width around the present voltage, mV.
    pub half_width_mv: f64,
    /// Points per sweep.
    pub points: usize,
    /// What to do when the sweep finds no flank (`None`: park nowhere and
    /// carry on, as before).
    #[serde(default)]
    pub fallback: Option<SensingDotFallback>,
    /// Skip the sweep when the flank's position can be predicted (`None`:
    /// sweep every time, the paper's rule).
    #[serde(default)]
    pub prediction: Option<FlankPrediction>,
}

/// Predict the sensing dot's flank instead of sweeping for it.
///
/// The flank (mV of the swept gate) moves with every other gate: the level
/// learns those levers online (a Kalman row, zero-mean prior) from the
/// sweeps it does take. When it is next called it predicts the flank from
/// the gates' moves since its last sweep; if the prediction's standard
/// deviation is at most `skip_std_mv` it parks the gate there without a
/// sweep (event `sweep_skipped`). It sweeps anyway after `max_skips`
/// skips in a row, when any scan failed to evaluate since its last sweep,
/// and whenever it has no sweep to start from. Every parked voltage goes
/// through the guard like a sweep's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlankPrediction {
    /// Largest predicted standard deviation of the flank at which the sweep
    /// is skipped, mV (0 < value ≤ 10).
    #[serde(default = "default_skip_std_mv")]
    pub skip_std_mv: f64,
    /// Prior standard deviation of each gate's lever on the flank, mV per
    /// mV (0 < value ≤ 10).
    #[serde(default = "default_prior_lever")]
    pub prior_lever_per_mv: f64,
    /// Scatter of the flank between sweeps that no gate explains (fit
    /// noise, drift, charge jumps), mV (0 ≤ value ≤ 10).
    #[serde(default = "default_flank_noise_mv")]
    pub noise_mv: f64,
    /// Skips in a row after which the level sweeps anyway (0..=100).
    #[serde(default = "default_max_skips")]
    pub max_skips: u32,
}

/// Whether `x` is finite, above 0 (`lo_open`) or at least 0, and at most `hi`:
/// the bounds of the prediction settings.
fn within(x: f64, lo_open: bool, hi: f64) -> bool {
    x.is_finite() && (if lo_open { x > 0.0 } else { x >= 0.0 }) && x <= hi
}

/// Upper bound on [`FlankPrediction::max_skips`].
pub const MAX_FLANK_SKIPS: u32 = 100;

/// Chosen on random devices 101–130 (`docs/benchmarks.md`): lab time per
/// change falls from 0.1 to 0.3 mV and is flat beyond.
fn default_skip_std_mv() -> f64 {
    0.3
}
fn default_prior_lever() -> f64 {
    0.1
}
fn default_flank_noise_mv() -> f64 {
    0.05
}
fn default_max_skips() -> u32 {
    3
}

impl Default for FlankPrediction {
    fn default() -> Self {
        Self {
            skip_std_mv: default_skip_std_mv(),
            prior_lever_per_mv: default_prior_lever(),
            noise_mv: default_flank_noise_mv(),
            max_skips: default_max_skips(),
        }
    }
}

impl FlankPrediction {
    /// Check the bounds; the error names the field (relative to the level).
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !within(self.skip_std_mv, true, 10.0) {
            return Err(("prediction.skip_std_mv", "must be > 0 and ≤ 10 mV".into()));
        }
        if !within(self.prior_lever_per_mv, true, 10.0) {
            return Err((
                "prediction.prior_lever_per_mv",
                "must be > 0 and ≤ 10 mV/mV".into(),
            ));
        }
        if !within(self.noise_mv, false, 10.0) {
            return Err(("prediction.noise_mv", "must be ≥ 0 and ≤ 10 mV".into()));
        }
        if self.max_skips > MAX_FLANK_SKIPS {
            return Err((
                "prediction.max_skips",
                format!("must be at most {MAX_FLANK_SKIPS}"),
            ));
        }
        Ok(())
    }
}

/// Upper bound on [`SensingDotFallback::offsets_mv`] (bounded by construction).
pub const MAX_FALLBACK_SWEEPS: usize = 16;

/// The paper's 2-D sensing-dot scan, as a raster of 1-D sweeps: when the
/// sweep of [`SensingDotConfig::gate`] finds no flank, step a second gate
/// through `offsets_mv` (relative to its present voltage) and sweep again at
/// each, stopping at the first sweep with a flank (park both gates there);
/// if none has one, the second gate goes back. Each sweep is a scan the
/// device charges its lab time (the default simulator: 6 sweeps × 17 s ≈
/// the paper's 100 s 2-D scan). Every set goes through the guard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensingDotFallback {
    /// Second gate stepped between sweeps, e.g. `"SP"`.
    pub gate: String,
    /// Offsets from its present voltage, mV, in order
    /// (1..=[`MAX_FALLBACK_SWEEPS`] entries, each finite and |offset| ≤ 1000 mV).
    pub offsets_mv: Vec<f64>,
}

/// What a level does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LevelKind {
    /// Quasi-Newton level.
    Newton(NewtonConfig),
    /// Sensing-dot re-tuning.
    SensingDot(SensingDotConfig),
}

/// One level of the hierarchy. (Unknown fields are still refused: the
/// flattened `kind` config denies them.)
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelConfig {
    /// Unique name, e.g. `"qubit"`, `"chemical_potential"`, `"sensing_dot"`.
    pub name: String,
    /// Behaviour.
    #[serde(flatten)]
    pub kind: LevelKind,
    /// Levels run (in order, to completion) after every move of this level.
    /// Must name levels listed *after* this one (no cycles).
    #[serde(default)]
    pub after_move: Vec<String>,
}

/// A whole tuner: gates with limits and the level hierarchy (`levels[0]` is the top).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TunerConfig {
    /// Every gate the tuner may touch, with limits and start voltages.
    pub gates: Vec<GateSpec>,
    /// Levels; the first is the top level that defines an iteration.
    pub levels: Vec<LevelConfig>,
    /// Stop as soon as every targeted top-level parameter is in its band.
    #[serde(default)]
    pub stop_when_tuned: bool,
    /// Stop after this many top-level iterations (`None`: never).
    #[serde(default)]
    pub max_iterations: Option<u64>,
    /// Target changes planned ahead (e.g. the paper's set-point cycle), applied
    /// at the start of the given top-level iterations.
    #[serde(default)]
    pub schedule: Vec<ScheduledTargets>,
    /// Reference constants `σ₀`, `δp₀` of the σ/σ₀ uncertainty rule
    /// (`δp ≈ δp₀·σ/σ₀`, [`crate::fit::uncertainty`]) with which the tuner
    /// evaluates raw `w` and `t_sr` scans. A lab calibrates its own (repeated
    /// scans at a fixed operating point); the default is the calibration of
    /// the default simulated device
    /// ([`crate::fit::uncertainty::SIMULATED_DEVICE_REFERENCES`]).
    #[serde(default)]
    pub fit_references: References,
    /// Keep mode: once tuned, keep the top level in tune while the device
    /// drifts ([`super::KeepConfig`]; `None`: stop or go on as configured).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keep: Option<super::KeepConfig>,
}

/// New targets for some parameters from a given top-level iteration on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduledTargets {
    /// Iteration k at whose start the targets change.
    pub at_iteration: u64,
    /// Parameter name → new target (parameter units).
    pub targets: std::collections::BTreeMap<String, f64>,
}

impl TunerConfig {
    /// The top level's Newton config.
    ///
    /// # Panics
    /// If the top level is not a Newton level (rejected by [`TunerConfig::validate`]).
    pub fn top(&self) -> &NewtonConfig {
        match &self.levels[0].kind {
            LevelKind::Newton(n) => n,
            LevelKind::SensingDot(_) => panic!("top level must be a Newton level"),
        }
    }

    /// Mutable access to the top level's Newton config (estimator, Q, step limit, targets).
    ///
    /// # Panics
    /// If the top level is not a Newton level.
    pub fn top_mut(&mut self) -> &mut NewtonConfig {
        match &mut self.levels[0].kind {
            LevelKind::Newton(n) => n,
            LevelKind::SensingDot(_) => panic!("top level must be a Newton level"),
        }
    }

    /// The top level's Newton config for a config that may not be valid
    /// yet (e.g. to apply targets before [`TunerConfig::validate`]): an
    /// error naming `levels` (none) or `levels[0].kind` (not `newton`)
    /// instead of the panic of [`TunerConfig::top_mut`].
    ///
    /// ```
    /// let mut t = spintune::driver::SimulationConfig::paper_default().tuner;
    /// assert!(t.top_level_mut().is_ok());
    /// t.levels.clear();
    /// assert_eq!(t.top_level_mut().unwrap_err().field, "levels");
    /// ```
    pub fn top_level_mut(&mut self) -> Result<&mut NewtonConfig, ConfigError> {
        match self.levels.first_mut().map(|l| &mut l.kind) {
            None => Err(ConfigError::new("levels", "at least one level is required")),
            Some(LevelKind::Newton(n)) => Ok(n),
            Some(LevelKind::SensingDot(_)) => Err(ConfigError::new(
                "levels[0].kind",
                "the top level must be `newton`",
            )),
        }
    }

    /// Index of the level called `name`.
    pub fn level_index(&self, name: &str) -> Option<usize> {
        self.levels.iter().position(|l| l.name == name)
    }

    /// Check the config; the error names the offending field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        // Every number first: within ±MAX_MAGNITUDE in its unit, integers
        // within MAX_INTEGER (bounded by construction; the checks below add
        // each field's range).
        if let Ok(v) = serde_json::to_value(self) {
            check_magnitudes(&v, "")?;
        }
        if self.gates.is_empty() {
            return Err(ConfigError::new("gates", "at least one gate is required"));
        }
        for (i, g) in self.gates.iter().enumerate() {
            let f = |x: &str| format!("gates[{i}].{x}");
            if g.name.is_empty() {
                return Err(ConfigError::new(f("name"), "must not be empty"));
            }
            if self.gates[..i].iter().any(|o| o.name == g.name) {
                return Err(ConfigError::new(
                    f("name"),
                    format!("duplicate gate {:?}", g.name),
                ));
            }
            for (name, v) in [
                ("min_mv", g.min_mv),
                ("max_mv", g.max_mv),
                ("initial_mv", g.initial_mv),
                ("max_step_mv", g.max_step_mv),
            ] {
                if !(v.is_finite() && v.abs() <= MAX_GATE_MV) {
                    return Err(ConfigError::new(
                        f(name),
                        format!("must be a finite number within ±{MAX_GATE_MV} mV, got {v}"),
                    ));
                }
            }
            if g.min_mv > g.max_mv {
                return Err(ConfigError::new(f("min_mv"), "must not exceed max_mv"));
            }
            if !(g.min_mv..=g.max_mv).contains(&g.initial_mv) {
                return Err(ConfigError::new(
                    f("initial_mv"),
                    format!(
                        "{} mV is outside [{}, {}] mV",
                        g.initial_mv, g.min_mv, g.max_mv
                    ),
                ));
            }
            if g.max_step_mv <= 0.0 {
                return Err(ConfigError::new(f("max_step_mv"), "must be > 0"));
            }
        }
        // The levels exist and the top one is a Newton level before
        // anything below looks at them.
        if self.levels.is_empty() {
            return Err(ConfigError::new("levels", "at least one level is required"));
        }
        if !matches!(self.levels[0].kind, LevelKind::Newton(_)) {
            return Err(ConfigError::new(
                "levels[0].kind",
                "the top level must be `newton`",
            ));
        }
        if matches!(&self.levels[0].kind, LevelKind::Newton(n) if n.search.is_some()) {
            return Err(ConfigError::new(
                "levels[0].search",
                "the top level moves the qubit gates: a search is for levels run as children",
            ));
        }
        if matches!(&self.levels[0].kind, LevelKind::Newton(n) if n.forecast.is_some()) {
            return Err(ConfigError::new(
                "levels[0].forecast",
                "the top level always measures: a forecast is for levels run as children",
            ));
        }
        for (parameter, r) in [
            ("w", &self.fit_references.w),
            ("t_sr", &self.fit_references.t_sr),
        ] {
            for (name, v) in [("sigma0", r.sigma0), ("delta_p0", r.delta_p0)] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(ConfigError::new(
                        format!("fit_references.{parameter}.{name}"),
                        "must be a finite number > 0",
                    ));
                }
            }
        }
        for (parameter, r) in [
            ("w", &self.fit_references.w),
            ("t_sr", &self.fit_references.t_sr),
        ] {
            let floor = r.relative_floor;
            if !(floor.is_finite() && (0.0..1.0).contains(&floor)) {
                return Err(ConfigError::new(
                    format!("fit_references.{parameter}.relative_floor"),
                    "must be a finite number in [0, 1)",
                ));
            }
        }
        if let Some(k) = &self.keep {
            k.validate().map_err(|e| e.within("keep"))?;
        }
        let has_gate = |name: &str| self.gates.iter().any(|g| g.name == name);
        for (li, level) in self.levels.iter().enumerate() {
            let lf = |x: &str| format!("levels[{li}].{x}");
            if self.levels[..li].iter().any(|o| o.name == level.name) {
                return Err(ConfigError::new(
                    lf("name"),
                    format!("duplicate level {:?}", level.name),
                ));
            }
            for (ci, child) in level.after_move.iter().enumerate() {
                match self.level_index(child) {
                    Some(idx) if idx > li => {}
                    Some(_) => {
                        return Err(ConfigError::new(
                            lf(&format!("after_move[{ci}]")),
                            format!(
                                "{child:?} must be listed after {:?} (no cycles)",
                                level.name
                            ),
                        ))
                    }
                    None => {
                        return Err(ConfigError::new(
                            lf(&format!("after_move[{ci}]")),
                            format!("unknown level {child:?}"),
                        ))
                    }
                }
            }
            match &level.kind {
                LevelKind::SensingDot(sd) => {
                    if !has_gate(&sd.gate) {
                        return Err(ConfigError::new(
                            lf("gate"),
                            format!("unknown gate {:?}", sd.gate),
                        ));
                    }
                    if !(sd.half_width_mv.is_finite() && sd.half_width_mv > 0.0) {
                        return Err(ConfigError::new(lf("half_width_mv"), "must be > 0"));
                    }
                    if !(5..=MAX_SWEEP_POINTS).contains(&sd.points) {
                        return Err(ConfigError::new(
                            lf("points"),
                            format!("must be between 5 and {MAX_SWEEP_POINTS}"),
                        ));
                    }
                    // The sweep starts half a width from the gate's present
                    // voltage: that first point must be within one step.
                    if let Some(g) = self.gates.iter().find(|g| g.name == sd.gate) {
                        if sd.half_width_mv > g.max_step_mv {
                            return Err(ConfigError::new(
                                lf("half_width_mv"),
                                format!(
                                    "{} mV exceeds gate {}'s max_step_mv ({} mV): the sweep's first point would be farther than one step from the present voltage",
                                    sd.half_width_mv, g.name, g.max_step_mv
                                ),
                            ));
                        }
                    }
                    if let Some(p) = &sd.prediction {
                        p.validate().map_err(|(f, m)| ConfigError::new(lf(f), m))?;
                    }
                    if let Some(fb) = &sd.fallback {
                        if !has_gate(&fb.gate) || fb.gate == sd.gate {
                            return Err(ConfigError::new(
                                lf("fallback.gate"),
                                format!(
                                    "{:?} must be a known gate other than the swept one",
                                    fb.gate
                                ),
                            ));
                        }
                        if !(1..=MAX_FALLBACK_SWEEPS).contains(&fb.offsets_mv.len())
                            || fb
                                .offsets_mv
                                .iter()
                                .any(|o| !(o.is_finite() && o.abs() <= 1000.0))
                        {
                            return Err(ConfigError::new(
                                lf("fallback.offsets_mv"),
                                format!(
                                    "needs 1 to {MAX_FALLBACK_SWEEPS} finite offsets of at most 1000 mV"
                                ),
                            ));
                        }
                    }
                }
                LevelKind::Newton(n) => {
                    validate_newton(n, &has_gate).map_err(|e| e.within(&format!("levels[{li}]")))?
                }
            }
        }
        // Scheduled targets last: a level's own error (e.g. no parameters)
        // is named before a target that no longer fits it.
        for (i, entry) in self.schedule.iter().enumerate() {
            for (name, &t) in &entry.targets {
                let field = format!("schedule[{i}].targets.{name}");
                let spec = self.levels.iter().find_map(|l| match &l.kind {
                    LevelKind::Newton(n) => n.parameters.iter().find(|p| &p.name == name),
                    LevelKind::SensingDot(_) => None,
                });
                let Some(spec) = spec else {
                    return Err(ConfigError::new(
                        field,
                        format!("unknown parameter {name:?}"),
                    ));
                };
                spec.check_target(t)
                    .map_err(|e| ConfigError::new(field, e.message))?;
            }
        }
        Ok(())
    }
}

fn validate_newton(n: &NewtonConfig, has_gate: &dyn Fn(&str) -> bool) -> Result<(), ConfigError> {
    if n.gates.is_empty() {
        return Err(ConfigError::new("gates", "at least one gate is required"));
    }
    for (i, g) in n.gates.iter().enumerate() {
        if !has_gate(g) {
            return Err(ConfigError::new(
                format!("gates[{i}]"),
                format!("unknown gate {g:?}"),
            ));
        }
        if n.gates[..i].contains(g) {
            return Err(ConfigError::new(
                format!("gates[{i}]"),
                format!("duplicate gate {g:?}"),
            ));
        }
    }
    if let Some(f) = &n.forecast {
        f.validate()?;
    }
    if let Some(s) = &n.search {
        s.validate()?;
    }
    if n.parameters.is_empty() {
        return Err(ConfigError::new(
            "parameters",
            "at least one parameter is required",
        ));
    }
    for (i, p) in n.parameters.iter().enumerate() {
        let f = |x: &str| format!("parameters[{i}].{x}");
        if n.parameters[..i].iter().any(|o| o.name == p.name) {
            return Err(ConfigError::new(
                f("name"),
                format!("duplicate parameter {:?}", p.name),
            ));
        }
        if let Some(t) = p.target {
            p.check_target(t)
                .map_err(|e| e.within(&format!("parameters[{i}]")))?;
        }
        p.tolerance
            .validate()
            .map_err(|e| e.within(&f("tolerance")))?;
        if !(p.process_noise_per_mv.is_finite() && p.process_noise_per_mv >= 0.0) {
            return Err(ConfigError::new(
                f("process_noise_per_mv"),
                "must be finite and non-negative",
            ));
        }
    }
    let (m, k) = (n.parameters.len(), n.gates.len());
    match &n.initial_gradient {
        InitialGradient::FiniteDifference {
            step_mv,
            repetitions,
            mirrored,
            ..
        } => {
            if !(step_mv.is_finite() && *step_mv > 0.0) {
                return Err(ConfigError::new("initial_gradient.step_mv", "must be > 0"));
            }
            if !(1..=MAX_FD_REPETITIONS).contains(repetitions) {
                return Err(ConfigError::new(
                    "initial_gradient.repetitions",
                    format!("must be 1..={MAX_FD_REPETITIONS}, got {repetitions}"),
                ));
            }
            if mirrored.len() > *repetitions as usize {
                return Err(ConfigError::new(
                    "initial_gradient.mirrored",
                    format!(
                        "{} entries for {repetitions} repetitions: at most one per repetition",
                        mirrored.len()
                    ),
                ));
            }
        }
        InitialGradient::Given {
            gradient,
            covariance,
        } => {
            check_rows(gradient, m, k, "initial_gradient.gradient")?;
            if covariance.len() != m {
                return Err(ConfigError::new(
                    "initial_gradient.covariance",
                    format!("needs {m} matrices"),
                ));
            }
            for (i, c) in covariance.iter().enumerate() {
                check_rows(c, k, k, &format!("initial_gradient.covariance[{i}]"))?;
                let mat = nalgebra::DMatrix::from_fn(k, k, |r, s| c[r][s]);
                crate::kalman::validate_covariance(&mat, "covariance").map_err(|e| {
                    ConfigError::new(format!("initial_gradient.covariance[{i}]"), e.to_string())
                })?;
            }
        }
        InitialGradient::RoughGuess {
            gradient,
            relative_std,
        } => {
            check_rows(gradient, m, k, "initial_gradient.gradient")?;
            if !(relative_std.is_finite() && *relative_std >= 0.0) {
                return Err(ConfigError::new(
                    "initial_gradient.relative_std",
                    "must be ≥ 0",
                ));
            }
        }
    }
    if !(n.solver.max_step_mv.is_finite() && n.solver.max_step_mv > 0.0) {
        return Err(ConfigError::new("solver.max_step_mv", "must be > 0"));
    }
    if !(n.solver.rank_tolerance.is_finite() && n.solver.rank_tolerance >= 0.0) {
        return Err(ConfigError::new("solver.rank_tolerance", "must be ≥ 0"));
    }
    let kappa = n.solver.covariance_weight;
    if !(kappa.is_finite() && (0.0..=crate::solver::MAX_COVARIANCE_WEIGHT).contains(&kappa)) {
        return Err(ConfigError::new(
            "solver.covariance_weight",
            format!(
                "must be a finite number in [0, {}]",
                crate::solver::MAX_COVARIANCE_WEIGHT
            ),
        ));
    }
    if !(1..=crate::solver::MAX_MOVES_PER_ITERATION).contains(&n.solver.max_moves_per_iteration) {
        return Err(ConfigError::new(
            "solver.max_moves_per_iteration",
            format!(
                "must be between 1 and {}",
                crate::solver::MAX_MOVES_PER_ITERATION
            ),
        ));
    }
    if let Some(s) = n.outlier_sigma {
        if !(s.is_finite() && s > 0.0) {
            return Err(ConfigError::new(
                "outlier_sigma",
                "must be > 0 (or null for no gating)",
            ));
        }
    }
    if let Some(k) = n.skip_confirmation_sigma {
        if !(k.is_finite() && (0.0..=10.0).contains(&k)) {
            return Err(ConfigError::new(
                "skip_confirmation_sigma",
                "must be a number in [0, 10] (or null: always confirm)",
            ));
        }
    }
    if !(n.min_step_mv.is_finite() && n.min_step_mv >= 0.0) {
        return Err(ConfigError::new("min_step_mv", "must be ≥ 0"));
    }
    if !(n.fd_step_mv.is_finite() && n.fd_step_mv > 0.0) {
        return Err(ConfigError::new("fd_step_mv", "must be > 0"));
    }
    if let Some(c) = &n.compensation {
        for (i, g) in c.gates.iter().enumerate() {
            if !has_gate(g) {
                return Err(ConfigError::new(
                    format!("compensation.gates[{i}]"),
                    format!("unknown gate {g:?}"),
                ));
            }
            if n.gates.contains(g) {
                return Err(ConfigError::new(
                    format!("compensation.gates[{i}]"),
                    format!("{g:?} is also a tuning gate of this level"),
                ));
            }
        }
        check_rows(&c.matrix, c.gates.len(), k, "compensation.matrix")?;
        let u = c.relative_uncertainty;
        if !(u.is_finite() && (0.0..=10.0).contains(&u)) {
            return Err(ConfigError::new(
                "compensation.relative_uncertainty",
                "must be a finite number in [0, 10]",
            ));
        }
    }
    Ok(())
}

fn check_rows(rows: &[Vec<f64>], m: usize, n: usize, field: &str) -> Result<(), ConfigError> {
    if rows.len() != m {
        return Err(ConfigError::new(
            field,
            format!("needs {m} rows, got {}", rows.len()),
        ));
    }
    for (i, r) in rows.iter().enumerate() {
        if r.len() != n {
            return Err(ConfigError::new(
                format!("{field}[{i}]"),
                format!("needs {n} entries, got {}", r.len()),
            ));
        }
        if let Some(x) = r.iter().find(|x| !x.is_finite()) {
            return Err(ConfigError::new(
                format!("{field}[{i}]"),
                format!("{x} is not a finite number"),
            ));
        }
    }
    Ok(())
}
