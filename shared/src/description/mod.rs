//! A lab's device in a few lines: gates with limits, which gates tune the
//! qubit, which plungers hold the transition lines, which gate re-tunes the
//! sensing dot. [`DeviceDescription::tuner`] derives the whole level
//! hierarchy from it with the recommended defaults (the strategy measured
//! best in `spintune bench`, docs/benchmarks.md), so a lab never restates a
//! level. This is the one derivation: the run config's `description` table
//! (CLI, server), Python and `SimulationConfig::recommended` (in `driver`)
//! all go through it.
//!
//! Which scan gives which parameter is fixed by the parameter's name (the
//! evaluation of a scan names its values, [`crate::fit`]): `t_sr` (ns) from
//! the load curve, `w` (µV) from the detuning scan, the line positions
//! `mu_a_mv`, `mu_b_mv` (mV) from the lead-transition scans.
//!
//! ```
//! use spintune::description::DeviceDescription;
//! let text = r#"{
//!   "gates": [
//!     {"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
//!     {"name": "B2", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
//!     {"name": "SD", "min_mv": -900, "max_mv": -300, "initial_mv": -600, "max_step_mv": 30}
//!   ],
//!   "qubit": {"gates": ["B1", "B2"]},
//!   "sensing_dot": {"gate": "SD"}
//! }"#;
//! let d: DeviceDescription = serde_json::from_str(text).unwrap();
//! let tuner = d.tuner().unwrap();
//! assert_eq!(tuner.levels.len(), 2); // qubit, sensing dot
//! assert_eq!(tuner.top().parameters[0].name, "t_sr");
//! ```

pub mod array;
pub mod layout;

use serde::{Deserialize, Serialize};

use crate::config_error::ConfigError;
use crate::estimator::EstimatorKind;
use crate::fit::uncertainty::References;
use crate::parameter::{ParameterSpec, ScanKind, Tolerance, Transform};
use crate::safety::GateSpec;
use crate::solver::{SolverConfig, StepRule};
use crate::tuner::{
    Compensation, FlankPrediction, InitialGradient, LevelConfig, LevelKind, NewtonConfig,
    ParameterForecast, ParameterSearch, SensingDotConfig, SensingDotFallback, TunerConfig,
};

/// Process noise of the recommended qubit level's log-space parameters:
/// the standard deviation a gradient element `∂ln p/∂v` gains per mV of
/// step (1/mV per mV). Twice the paper's Q relative to typical values of
/// the parameters (0.075/45 ns, 0.3/208 µV ≈ 0.0015): chosen on random
/// devices 101–110 for filter consistency (NIS means near 1 where 0.0015
/// gave 1.46 and 1.67) at the same lab time, and checked on fresh devices
/// (docs/benchmarks.md, "Choosing the default").
pub const RECOMMENDED_RELATIVE_Q_PER_MV: f64 = 0.003;

/// Offset per gate of the recommended cold start's finite differences, mV
/// (chosen on random devices over 4 and 8 mV: docs/benchmarks.md).
pub const RECOMMENDED_FD_STEP_MV: f64 = 6.0;

/// The virtual-gate matrix of the paper's device (rows PA, PB; columns N,
/// SA, SB, T; mV of plunger per mV of tuning gate): configuration a lab
/// writes down after measuring the transition-line slopes, here rounded to
/// two significant digits (so within about 5 % of the default simulated
/// device's first-order crosstalk, with a stated uncertainty of 20 %,
/// `Compensation::relative_uncertainty`). Nothing computes it from the
/// simulator at run time (ARCHITECTURE.md invariant 7); the benchmark
/// replaces it per seed by a perturbed matrix
/// (`benchmark::perturbed_compensation`).
pub const PAPER_DEFAULT_COMPENSATION: [[f64; 4]; 2] =
    [[-0.36, -0.50, 0.0042, -0.039], [-0.12, 0.013, -0.50, -0.46]];

/// The parameters a qubit level can tune, with their scan and unit.
pub const QUBIT_PARAMETERS: [(&str, ScanKind, &str); 2] = [
    ("t_sr", ScanKind::ReloadTime, "ns"),
    ("w", ScanKind::TransitionWidth, "µV"),
];

/// A device as a lab describes it. Every field but `gates` and
/// `qubit.gates` has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceDescription {
    /// Every gate the tuner may touch: name, `min_mv`, `max_mv`,
    /// `initial_mv`, `max_step_mv` (default 10 mV).
    pub gates: Vec<GateSpec>,
    /// The top level: the gates that tune the qubit parameters.
    pub qubit: QubitDescription,
    /// Hold the transition lines with two plunger gates after each qubit
    /// move (a chemical-potential level); `None`: no line re-centring.
    #[serde(default)]
    pub lines: Option<LinesDescription>,
    /// Re-tune the sensing dot after each move; `None`: never.
    #[serde(default)]
    pub sensing_dot: Option<SensingDotDescription>,
    /// Fit references of the σ/σ₀ uncertainty rule (default: the simulated
    /// device's calibration; a lab calibrates its own, [`References`]).
    #[serde(default)]
    pub fit_references: References,
}

/// The qubit (top) level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QubitDescription {
    /// Gates moved by the level (Jacobian columns), e.g. `["N", "SA", "SB", "T"]`.
    pub gates: Vec<String>,
    /// Parameters tuned, by name (default `["t_sr", "w"]`; see [`QUBIT_PARAMETERS`]).
    #[serde(default = "default_qubit_parameters")]
    pub parameters: Vec<String>,
    /// Step limit of one move (Euclidean over the level's gates), mV (default 10).
    #[serde(default = "default_qubit_step_mv")]
    pub step_limit_mv: f64,
    /// Relative tolerance band of every parameter (default 0.1: ±10 %);
    /// the run config's `tolerances` override it per parameter.
    #[serde(default = "default_relative_tolerance")]
    pub relative_tolerance: f64,
}

/// The chemical-potential level: two plungers hold the transition lines.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinesDescription {
    /// The two plunger gates, e.g. `["PA", "PB"]` (rows of `compensation`).
    pub gates: Vec<String>,
    /// Virtual-gate matrix (rows: `gates`, columns: `qubit.gates`; mV of
    /// plunger per mV of qubit gate), read off the lab's charge-stability
    /// diagrams; applied with every qubit move. `None`: no compensation.
    #[serde(default)]
    pub compensation: Option<Vec<Vec<f64>>>,
    /// Relative 1σ uncertainty of the matrix elements (default 0.2).
    #[serde(default = "default_compensation_uncertainty")]
    pub compensation_uncertainty: f64,
    /// Lines count as centred within ± this, mV (default 0.1).
    #[serde(default = "default_line_tolerance_mv")]
    pub tolerance_mv: f64,
    /// Step limit of one plunger correction, mV (default 2).
    #[serde(default = "default_line_step_mv")]
    pub step_limit_mv: f64,
    /// Skip the confirming scan after a correction when the filter predicts
    /// both lines inside the tolerance with this many σ of margin (default
    /// 2; `null`: always confirm). Chosen on random devices
    /// (docs/benchmarks.md, "Skipping the confirming line scan").
    #[serde(default = "default_line_skip_sigma")]
    pub skip_confirmation_sigma: Option<f64>,
    /// Scan the lines at every call, as the paper does (default false:
    /// correct them from the learned forecast when it is confident, see
    /// `forecast`).
    #[serde(default)]
    pub always_scan: bool,
    /// How the lines are forecast (every field has a default; mV).
    #[serde(default)]
    pub forecast: ParameterForecast,
    /// Search for lines that left the line scan's window (a charge
    /// rearrangement, a neighbour's move) by probing the plungers (default
    /// true; false: the paper's rule, retreat and re-scan only).
    #[serde(default = "default_true")]
    pub search_lost_lines: bool,
    /// How lost lines are searched for (`step` in mV of line position: at
    /// most the half-width of the lab's line scan, the simulator's covers
    /// ±4 mV). Default: step 4 mV, 4 probes (±4, ±8 mV), after 2 failed
    /// scans in a row, the plungers at most 40 mV from where the search
    /// started.
    #[serde(default)]
    pub search: ParameterSearch,
}

fn default_true() -> bool {
    true
}

/// The sensing-dot level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensingDotDescription {
    /// The swept gate, e.g. `"SD1"`.
    pub gate: String,
    /// Sweep half-width around the present voltage, mV (default 6; at most
    /// the gate's `max_step_mv`).
    #[serde(default = "default_sd_half_width_mv")]
    pub half_width_mv: f64,
    /// Points per sweep (default 201).
    #[serde(default = "default_sd_points")]
    pub points: usize,
    /// A second gate rastered when the sweep finds no flank (the paper's 2-D scan).
    #[serde(default)]
    pub fallback: Option<SensingDotFallback>,
    /// Sweep at every call, as the paper does (default false: park on the
    /// flank the level predicts when it is confident, see `prediction`).
    #[serde(default)]
    pub always_sweep: bool,
    /// How the flank is predicted (every field has a default).
    #[serde(default)]
    pub prediction: FlankPrediction,
}

fn default_qubit_parameters() -> Vec<String> {
    QUBIT_PARAMETERS.iter().map(|p| p.0.to_string()).collect()
}
fn default_qubit_step_mv() -> f64 {
    10.0
}
fn default_relative_tolerance() -> f64 {
    0.1
}
fn default_compensation_uncertainty() -> f64 {
    0.2
}
fn default_line_tolerance_mv() -> f64 {
    0.1
}
fn default_line_step_mv() -> f64 {
    2.0
}
fn default_line_skip_sigma() -> Option<f64> {
    Some(2.0)
}
fn default_sd_half_width_mv() -> f64 {
    6.0
}
fn default_sd_points() -> usize {
    201
}

impl DeviceDescription {
    /// The tuner of this description: a qubit level with the recommended
    /// strategy (log space, relative Q [`RECOMMENDED_RELATIVE_Q_PER_MV`],
    /// trust-region step, two moves per measurement with the lower levels
    /// after the last, a cold start of one finite-difference repetition of
    /// [`RECOMMENDED_FD_STEP_MV`] without re-centring between offsets; the
    /// line level skips its confirming scan when confident);
    /// after each qubit move the sensing dot (if described), then the line
    /// level (if described; itself followed by the sensing dot). The result
    /// is validated; errors name the description's field (`qubit.gates[1]`,
    /// `lines.compensation`, …).
    pub fn tuner(&self) -> Result<TunerConfig, ConfigError> {
        let q = &self.qubit;
        let positive = |field: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ConfigError::new(
                    field,
                    format!("must be a finite number > 0, got {v}"),
                ))
            }
        };
        positive("qubit.step_limit_mv", q.step_limit_mv)?;
        positive("qubit.relative_tolerance", q.relative_tolerance)?;
        if let Some(l) = &self.lines {
            positive("lines.step_limit_mv", l.step_limit_mv)?;
            positive("lines.tolerance_mv", l.tolerance_mv)?;
        }
        let mut parameters = Vec::new();
        for (i, name) in q.parameters.iter().enumerate() {
            let Some((_, scan, unit)) = QUBIT_PARAMETERS.iter().find(|p| p.0 == name) else {
                let known: Vec<&str> = QUBIT_PARAMETERS.iter().map(|p| p.0).collect();
                return Err(ConfigError::new(
                    format!("qubit.parameters[{i}]"),
                    format!("unknown parameter {name:?} (known: {known:?})"),
                ));
            };
            parameters.push(ParameterSpec {
                name: name.clone(),
                unit: unit.to_string(),
                scan: *scan,
                target: None,
                tolerance: Tolerance::Relative(q.relative_tolerance),
                transform: Transform::Log,
                process_noise_per_mv: RECOMMENDED_RELATIVE_Q_PER_MV,
            });
        }
        let fd_step_mv = RECOMMENDED_FD_STEP_MV.min(q.step_limit_mv);
        let mut after_qubit = Vec::new();
        let mut levels = Vec::new();
        let compensation = match &self.lines {
            Some(l) => l.compensation.as_ref().map(|m| Compensation {
                gates: l.gates.clone(),
                matrix: m.clone(),
                relative_uncertainty: l.compensation_uncertainty,
            }),
            None => None,
        };
        if self.sensing_dot.is_some() {
            after_qubit.push("sensing_dot".to_string());
        }
        if self.lines.is_some() {
            after_qubit.push("chemical_potential".to_string());
        }
        levels.push(LevelConfig {
            name: "qubit".into(),
            kind: LevelKind::Newton(NewtonConfig {
                gates: q.gates.clone(),
                parameters,
                estimator: EstimatorKind::Kalman,
                initial_gradient: InitialGradient::FiniteDifference {
                    step_mv: fd_step_mv,
                    repetitions: 1,
                    recentre_between_offsets: false,
                    central: false,
                    mirrored: Vec::new(),
                },
                solver: SolverConfig {
                    max_step_mv: q.step_limit_mv,
                    rule: StepRule::ExpectedCost,
                    max_moves_per_iteration: 2,
                    lower_levels_between_moves: false,
                    ..SolverConfig::default()
                },
                outlier_sigma: Some(5.0),
                min_step_mv: 0.01,
                fd_step_mv,
                max_iterations_per_call: 1,
                hold_initial_values: false,
                compensation,
                skip_confirmation_sigma: None,
                forecast: None,
                search: None,
            }),
            after_move: after_qubit,
        });
        if let Some(l) = &self.lines {
            let plunger_step = l.step_limit_mv;
            levels.push(LevelConfig {
                name: "chemical_potential".into(),
                kind: LevelKind::Newton(NewtonConfig {
                    gates: l.gates.clone(),
                    parameters: ["mu_a_mv", "mu_b_mv"]
                        .iter()
                        .map(|name| ParameterSpec {
                            name: name.to_string(),
                            unit: "mV".into(),
                            scan: ScanKind::ChemicalPotential,
                            target: Some(0.0),
                            tolerance: Tolerance::Absolute(l.tolerance_mv),
                            transform: Transform::Linear,
                            process_noise_per_mv: 0.005,
                        })
                        .collect(),
                    estimator: EstimatorKind::Kalman,
                    initial_gradient: InitialGradient::FiniteDifference {
                        step_mv: plunger_step,
                        repetitions: 1,
                        recentre_between_offsets: true,
                        central: false,
                        mirrored: Vec::new(),
                    },
                    solver: SolverConfig {
                        max_step_mv: plunger_step,
                        ..SolverConfig::default()
                    },
                    outlier_sigma: None,
                    min_step_mv: 0.01,
                    fd_step_mv: plunger_step,
                    max_iterations_per_call: 3,
                    hold_initial_values: false,
                    compensation: None,
                    skip_confirmation_sigma: l.skip_confirmation_sigma,
                    forecast: (!l.always_scan).then(|| l.forecast.clone()),
                    search: l.search_lost_lines.then(|| l.search.clone()),
                }),
                after_move: if self.sensing_dot.is_some() {
                    vec!["sensing_dot".into()]
                } else {
                    Vec::new()
                },
            });
        }
        if let Some(sd) = &self.sensing_dot {
            levels.push(LevelConfig {
                name: "sensing_dot".into(),
                kind: LevelKind::SensingDot(SensingDotConfig {
                    gate: sd.gate.clone(),
                    half_width_mv: sd.half_width_mv,
                    points: sd.points,
                    fallback: sd.fallback.clone(),
                    prediction: (!sd.always_sweep).then(|| sd.prediction.clone()),
                }),
                after_move: Vec::new(),
            });
        }
        let tuner = TunerConfig {
            gates: self.gates.clone(),
            levels,
            stop_when_tuned: false,
            max_iterations: None,
            schedule: Vec::new(),
            fit_references: self.fit_references,
            keep: None,
        };
        tuner.validate().map_err(|e| self.name_field(e))?;
        Ok(tuner)
    }

    /// A derived tuner's error in the description's own terms.
    fn name_field(&self, e: ConfigError) -> ConfigError {
        let map = [
            ("levels[0].gates", "qubit.gates"),
            ("levels[0].solver.max_step_mv", "qubit.step_limit_mv"),
            ("levels[0].compensation.gates", "lines.gates"),
            ("levels[0].compensation.matrix", "lines.compensation"),
            (
                "levels[0].compensation.relative_uncertainty",
                "lines.compensation_uncertainty",
            ),
            ("levels[0].parameters", "qubit"),
        ];
        let line_level = if self.lines.is_some() { 1 } else { usize::MAX };
        let sd_level = 1 + usize::from(self.lines.is_some());
        let mut field = e.field.clone();
        for (from, to) in map {
            if let Some(rest) = field.strip_prefix(from) {
                field = format!("{to}{rest}");
                break;
            }
        }
        for (prefix, to) in [
            (format!("levels[{line_level}].gates"), "lines.gates"),
            (
                format!("levels[{line_level}].solver.max_step_mv"),
                "lines.step_limit_mv",
            ),
            (
                format!("levels[{line_level}].parameters[0].tolerance"),
                "lines.tolerance_mv",
            ),
            (format!("levels[{line_level}].forecast"), "lines.forecast"),
            (format!("levels[{line_level}].search"), "lines.search"),
            (format!("levels[{sd_level}]"), "sensing_dot"),
        ] {
            if let Some(rest) = field.strip_prefix(prefix.as_str()) {
                field = format!("{to}{rest}");
                break;
            }
        }
        ConfigError::new(field, e.message)
    }

    /// The paper's device as a lab would describe it: the default simulated
    /// double dot's gates ([`crate::sim::default_gates`]), N/SA/SB/T tuning
    /// the qubit, PA/PB holding the lines with
    /// [`PAPER_DEFAULT_COMPENSATION`], SD1 re-tuning the
    /// sensing dot with SP rastered when no flank is found.
    pub fn paper_device() -> Self {
        let sd = crate::sim::DeviceConfig::default().sensing_dot;
        Self {
            gates: crate::sim::default_gates(),
            qubit: QubitDescription {
                gates: ["N", "SA", "SB", "T"].map(String::from).to_vec(),
                parameters: default_qubit_parameters(),
                step_limit_mv: default_qubit_step_mv(),
                relative_tolerance: default_relative_tolerance(),
            },
            lines: Some(LinesDescription {
                gates: ["PA", "PB"].map(String::from).to_vec(),
                compensation: Some(
                    PAPER_DEFAULT_COMPENSATION
                        .iter()
                        .map(|r| r.to_vec())
                        .collect(),
                ),
                compensation_uncertainty: default_compensation_uncertainty(),
                tolerance_mv: default_line_tolerance_mv(),
                step_limit_mv: default_line_step_mv(),
                skip_confirmation_sigma: default_line_skip_sigma(),
                always_scan: false,
                forecast: ParameterForecast::default(),
                search_lost_lines: true,
                search: ParameterSearch::default(),
            }),
            sensing_dot: Some(SensingDotDescription {
                gate: sd.gate,
                half_width_mv: sd.sweep_half_range_mv,
                points: sd.sweep_points,
                fallback: Some(SensingDotFallback {
                    gate: "SP".into(),
                    offsets_mv: vec![-15.0, -9.0, -3.0, 3.0, 9.0, 15.0],
                }),
                always_sweep: false,
                prediction: FlankPrediction::default(),
            }),
            fit_references: crate::fit::uncertainty::SIMULATED_DEVICE_REFERENCES,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn minimal() -> DeviceDescription {
        serde_json::from_value(serde_json::json!({
            "gates": [
                {"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
                {"name": "B2", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
                {"name": "P1", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
                {"name": "P2", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
            ],
            "qubit": {"gates": ["B1", "B2"], "parameters": ["w"]},
            "lines": {"gates": ["P1", "P2"], "compensation": [[0.1, 0.2], [0.3, 0.4]]},
        }))
        .unwrap()
    }

    #[test]
    fn a_minimal_description_derives_every_level_field() {
        let t = minimal().tuner().unwrap();
        assert_eq!(t.levels.len(), 2);
        assert_eq!(t.levels[0].after_move, ["chemical_potential"]);
        assert!(t.levels[1].after_move.is_empty());
        let top = t.top();
        assert_eq!(top.parameters.len(), 1);
        assert_eq!(top.parameters[0].unit, "µV");
        assert_eq!(top.compensation.as_ref().unwrap().gates, ["P1", "P2"]);
    }

    #[test]
    fn errors_name_the_description_field() {
        let mut d = minimal();
        d.qubit.gates[1] = "B9".into();
        assert_eq!(d.tuner().unwrap_err().field, "qubit.gates[1]");
        let mut d = minimal();
        d.qubit.parameters = vec!["t_rs".into()];
        let e = d.tuner().unwrap_err();
        assert_eq!(e.field, "qubit.parameters[0]");
        assert!(e.message.contains("t_sr"), "{e}");
        let mut d = minimal();
        d.lines.as_mut().unwrap().compensation = Some(vec![vec![0.1]]);
        assert!(
            d.tuner()
                .unwrap_err()
                .field
                .starts_with("lines.compensation"),
            "{:?}",
            d.tuner().unwrap_err()
        );
        let mut d = minimal();
        d.qubit.step_limit_mv = 0.0;
        assert_eq!(d.tuner().unwrap_err().field, "qubit.step_limit_mv");
        let mut d = minimal();
        d.lines.as_mut().unwrap().gates[0] = "B1".into();
        assert!(d.tuner().unwrap_err().field.starts_with("lines.gates"));
        let mut d = minimal();
        d.sensing_dot = Some(SensingDotDescription {
            gate: "X".into(),
            half_width_mv: 6.0,
            points: 201,
            fallback: None,
            always_sweep: false,
            prediction: FlankPrediction::default(),
        });
        assert_eq!(d.tuner().unwrap_err().field, "sensing_dot.gate");
    }
}
