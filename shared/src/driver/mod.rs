//! The synchronous driver that runs a [`RunSession`] against the simulated
//! double dot: used by the browser's teaching mode, the benchmarks and the
//! tests. (The backend drives the same session through async instruments.)

use serde::{Deserialize, Serialize};

pub mod array;

use crate::estimator::EstimatorKind;
use crate::fit::uncertainty::SIMULATED_DEVICE_REFERENCES;
use crate::parameter::{ParameterSpec, Tolerance, Transform};
use crate::protocol::{ControlCommand, Fault, IterationRecord, RunStatus, ScanKind};
use crate::session::{ControlError, Output, Plan, RunSession, SessionConfig, SessionError};
use crate::sim::array::ArrayDevice;
use crate::sim::{default_gates, DeviceConfig, SimulatedDevice};
use crate::solver::SolverConfig;
use crate::tuner::array_run::ArrayRun;
use crate::tuner::{
    Compensation, ConfigError, InitialGradient, LevelConfig, LevelKind, NewtonConfig,
    SensingDotConfig, SensingDotFallback, Tuner, TunerConfig,
};

/// Everything needed for a simulated run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimulationConfig {
    /// Human-readable name.
    pub name: String,
    /// Seed of the device's random number generator.
    pub seed: u64,
    /// The simulated device.
    pub device: DeviceConfig,
    /// The tuner hierarchy.
    pub tuner: TunerConfig,
}

impl Default for SimulationConfig {
    fn default() -> Self {
        Self::paper_default()
    }
}

/// The paper's process noise σ_Q of the gradient of `(t_sr, w)`:
/// 0.075 ns/mV and 0.3 µV/mV per mV of step (linear space).
pub const PAPER_PROCESS_NOISE_PER_MV: (f64, f64) = (0.075, 0.3);

/// Paper targets: t_sr = 20 ns, w = 270 µV (set point I).
pub const PAPER_FIRST_TARGET: (f64, f64) = (20.0, 270.0);

pub use crate::description::PAPER_DEFAULT_COMPENSATION;

impl SimulationConfig {
    /// The paper's setup on the default simulated device: the qubit level tunes
    /// `t_sr` (ns) and `w` (µV) with N, SA, SB, T (Kalman filter, the paper's Q,
    /// 10 mV step limit, initial gradient by finite differences), with a linear
    /// virtual-gate correction on PA/PB ([`PAPER_DEFAULT_COMPENSATION`]); after each move the sensing dot is
    /// re-tuned and the transition lines are held at 0 mV by a Kalman-tuned
    /// PA/PB level. Targets: the paper's first set point. Fit uncertainties
    /// use the references calibrated on this very device
    /// ([`crate::fit::uncertainty::SIMULATED_DEVICE_REFERENCES`]); a changed
    /// `device` needs its own (see [`crate::sim::calibrate_reference`]).
    pub fn paper_default() -> Self {
        let device = DeviceConfig::default();
        let gates = default_gates();
        let tuning = ["N", "SA", "SB", "T"];
        let plungers = ["PA", "PB"];
        let compensation = Compensation {
            gates: plungers.iter().map(|s| s.to_string()).collect(),
            matrix: PAPER_DEFAULT_COMPENSATION
                .iter()
                .map(|row| row.to_vec())
                .collect(),
            relative_uncertainty: 0.2,
        };
        let qubit = NewtonConfig {
            gates: tuning.iter().map(|s| s.to_string()).collect(),
            parameters: vec![
                ParameterSpec {
                    name: "t_sr".into(),
                    unit: "ns".into(),
                    scan: ScanKind::ReloadTime,
                    target: Some(PAPER_FIRST_TARGET.0),
                    tolerance: Tolerance::Relative(0.1),
                    transform: Transform::Linear,
                    process_noise_per_mv: PAPER_PROCESS_NOISE_PER_MV.0,
                },
                ParameterSpec {
                    name: "w".into(),
                    unit: "µV".into(),
                    scan: ScanKind::TransitionWidth,
                    target: Some(PAPER_FIRST_TARGET.1),
                    tolerance: Tolerance::Relative(0.1),
                    transform: Transform::Linear,
                    process_noise_per_mv: PAPER_PROCESS_NOISE_PER_MV.1,
                },
            ],
            estimator: EstimatorKind::Kalman,
            initial_gradient: InitialGradient::FiniteDifference {
                step_mv: 4.0,
                repetitions: 3,
                recentre_between_offsets: true,
                central: false,
                mirrored: Vec::new(),
            },
            solver: SolverConfig::default(),
            outlier_sigma: Some(5.0),
            min_step_mv: 0.01,
            fd_step_mv: 4.0,
            max_iterations_per_call: 1,
            hold_initial_values: false,
            compensation: Some(compensation),
            skip_confirmation_sigma: None,
            forecast: None,
            search: None,
        };
        let chemical = NewtonConfig {
            gates: plungers.iter().map(|s| s.to_string()).collect(),
            parameters: ["mu_a_mv", "mu_b_mv"]
                .iter()
                .map(|name| ParameterSpec {
                    name: name.to_string(),
                    unit: "mV".into(),
                    scan: ScanKind::ChemicalPotential,
                    target: Some(0.0),
                    tolerance: Tolerance::Absolute(0.1),
                    transform: Transform::Linear,
                    process_noise_per_mv: 0.005,
                })
                .collect(),
            estimator: EstimatorKind::Kalman,
            initial_gradient: InitialGradient::FiniteDifference {
                step_mv: 2.0,
                repetitions: 1,
                recentre_between_offsets: true,
                central: false,
                mirrored: Vec::new(),
            },
            solver: SolverConfig {
                // the transition lines are scanned over ±4 mV: small corrections only
                max_step_mv: 2.0,
                ..SolverConfig::default()
            },
            outlier_sigma: None,
            min_step_mv: 0.01,
            fd_step_mv: 2.0,
            max_iterations_per_call: 3,
            hold_initial_values: false,
            compensation: None,
            skip_confirmation_sigma: None,
            forecast: None,
            search: None,
        };
        let sensing = SensingDotConfig {
            gate: device.sensing_dot.gate.clone(),
            half_width_mv: device.sensing_dot.sweep_half_range_mv,
            points: device.sensing_dot.sweep_points,
            // the paper's 2-D scan as a raster: SP in 6 mV steps, 6 sweeps ≈ 100 s
            fallback: Some(SensingDotFallback {
                gate: "SP".into(),
                offsets_mv: vec![-15.0, -9.0, -3.0, 3.0, 9.0, 15.0],
            }),
            prediction: None,
        };
        let tuner = TunerConfig {
            gates,
            levels: vec![
                LevelConfig {
                    name: "qubit".into(),
                    kind: LevelKind::Newton(qubit),
                    after_move: vec!["sensing_dot".into(), "chemical_potential".into()],
                },
                LevelConfig {
                    name: "chemical_potential".into(),
                    kind: LevelKind::Newton(chemical),
                    after_move: vec!["sensing_dot".into()],
                },
                LevelConfig {
                    name: "sensing_dot".into(),
                    kind: LevelKind::SensingDot(sensing),
                    after_move: Vec::new(),
                },
            ],
            stop_when_tuned: false,
            max_iterations: None,
            schedule: Vec::new(),
            // calibrated on exactly this device (`DeviceConfig::default()`)
            fit_references: SIMULATED_DEVICE_REFERENCES,
            keep: None,
        };
        Self {
            name: "paper default".into(),
            seed: 1,
            device,
            tuner,
        }
    }

    /// The product's default (what `spintune run`, the server, the
    /// browser and Python use when a config has no `tuner` section): the
    /// paper's device ([`crate::description::DeviceDescription::paper_device`])
    /// with the strategy measured best in `spintune bench`
    /// (docs/benchmarks.md): `t_sr` and `w` tuned in log space with a
    /// relative process noise of
    /// [`crate::description::RECOMMENDED_RELATIVE_Q_PER_MV`], the covariance-aware trust-region
    /// step, up to two limited moves per measurement with the lower levels
    /// after the last, and a cold start of one finite-difference repetition
    /// (6 mV offsets) that re-centres the lines and the sensor only before
    /// and after the offsets.
    ///
    /// ```
    /// use spintune::driver::SimulationConfig;
    /// use spintune::parameter::Transform;
    /// let cfg = SimulationConfig::recommended();
    /// assert!(cfg.tuner.top().parameters.iter().all(|p| p.transform == Transform::Log));
    /// assert_eq!(cfg.tuner.top().solver.max_moves_per_iteration, 2);
    /// assert!(cfg.validate().is_ok());
    /// ```
    pub fn recommended() -> Self {
        let mut tuner = crate::description::DeviceDescription::paper_device()
            .tuner()
            .expect("the paper device's description is valid (tested)");
        for p in &mut tuner.top_mut().parameters {
            p.target = match p.name.as_str() {
                "t_sr" => Some(PAPER_FIRST_TARGET.0),
                "w" => Some(PAPER_FIRST_TARGET.1),
                _ => None,
            };
        }
        Self {
            name: "recommended".into(),
            tuner,
            ..Self::paper_default()
        }
    }

    /// Check the whole config; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.device.validate().map_err(|e| e.within("device"))?;
        self.tuner.validate().map_err(|e| e.within("tuner"))
    }

    /// The top (qubit) level's virtual-gate compensation, if it has one.
    pub fn compensation(&self) -> Option<&Compensation> {
        match &self.tuner.levels.first()?.kind {
            LevelKind::Newton(n) => n.compensation.as_ref(),
            LevelKind::SensingDot(_) => None,
        }
    }

    /// This config with the top level's virtual-gate matrix (rows: its
    /// compensation gates, e.g. PA and PB; columns: the level's gates, e.g.
    /// N, SA, SB, T; mV of plunger per mV of gate) and its relative
    /// uncertainty replaced, checked by the core's config rules
    /// ([`SimulationConfig::validate`]). A refused cell is named by row and
    /// column, e.g. for an editor:
    ///
    /// ```
    /// use spintune::driver::{SimulationConfig, PAPER_DEFAULT_COMPENSATION};
    /// let mut m: Vec<Vec<f64>> = PAPER_DEFAULT_COMPENSATION.iter().map(|r| r.to_vec()).collect();
    /// m[1][2] = -0.45;
    /// let cfg = SimulationConfig::paper_default().with_compensation(m.clone(), 0.1).unwrap();
    /// assert_eq!(cfg.compensation().unwrap().matrix[1][2], -0.45);
    /// m[1][2] = f64::NAN;
    /// let e = SimulationConfig::paper_default().with_compensation(m.clone(), 0.1).unwrap_err();
    /// assert_eq!(e.cell, Some((1, 2)));
    /// assert!(e.to_string().starts_with("PB per SB (mV/mV): "), "{e}");
    /// m[1][2] = 3e6;
    /// let e = SimulationConfig::paper_default().with_compensation(m, 0.1).unwrap_err();
    /// assert_eq!(e.cell, Some((1, 2)));
    /// assert!(e.to_string().contains("out of range"), "{e}");
    /// ```
    pub fn with_compensation(
        mut self,
        matrix: Vec<Vec<f64>>,
        relative_uncertainty: f64,
    ) -> Result<Self, CompensationError> {
        let top = self.tuner.top_mut();
        let names = (
            top.compensation
                .as_ref()
                .map(|c| c.gates.clone())
                .unwrap_or_default(),
            top.gates.clone(),
        );
        let c = top.compensation.get_or_insert_with(|| Compensation {
            gates: Vec::new(),
            matrix: Vec::new(),
            relative_uncertainty,
        });
        c.matrix = matrix;
        c.relative_uncertainty = relative_uncertainty;
        let Err(error) = self.validate() else {
            return Ok(self);
        };
        // `…compensation.matrix[r][c]` (a number out of range) or
        // `…compensation.matrix[r]` (the row's first non-finite number).
        let c = self.compensation();
        let cell = error
            .field
            .split_once("compensation.matrix[")
            .and_then(|(_, rest)| {
                let mut idx = rest
                    .split(['[', ']'])
                    .filter(|t| !t.is_empty())
                    .map(|t| t.parse::<usize>().ok());
                let r = idx.next()??;
                let col = match idx.next() {
                    Some(col) => col?,
                    None => c?.matrix.get(r)?.iter().position(|x| !x.is_finite())?,
                };
                Some((r, col))
            });
        let label = cell
            .and_then(|(r, col)| Some(format!("{} per {}", names.0.get(r)?, names.1.get(col)?)));
        Err(CompensationError { cell, label, error })
    }

    /// The simulated device of this config (`device` with `tuner.gates`,
    /// seeded with `seed`) at the gates' initial voltages; the error names
    /// the field within this config (`device.…` or `tuner.gates[i]…`).
    ///
    /// ```
    /// let mut cfg = spintune::driver::SimulationConfig::paper_default();
    /// cfg.device.reference_mv.remove("SB");
    /// let e = cfg.simulated_device().unwrap_err();
    /// assert_eq!(e.field, "device.reference_mv");
    /// ```
    pub fn simulated_device(&self) -> Result<SimulatedDevice, ConfigError> {
        SimulatedDevice::new(self.device.clone(), &self.tuner.gates, self.seed).map_err(|e| {
            if e.field.starts_with("gates[") {
                e.within("tuner")
            } else {
                e.within("device")
            }
        })
    }
}

/// Why an edited virtual-gate matrix was refused
/// ([`SimulationConfig::with_compensation`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CompensationError {
    /// The refused cell (row, column), when one cell is at fault.
    pub cell: Option<(usize, usize)>,
    /// The cell as "PB per SB".
    pub label: Option<String>,
    /// The core's config error.
    pub error: ConfigError,
}

impl std::fmt::Display for CompensationError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.label {
            Some(l) => write!(f, "{l} (mV/mV): {}", self.error.message),
            None => write!(f, "{}", self.error),
        }
    }
}

impl std::error::Error for CompensationError {}

/// What one [`SimulationRun::step`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// One device request was executed and its answer fed to the session.
    Executed,
    /// A top-level iteration completed.
    Iteration(Box<IterationRecord>),
    /// The run is over (finished or stopped).
    Over,
}

/// Why a simulated run halted without a record (distinct from the
/// backend's `run::RunError`, the error of a control action on a stored run).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Halt {
    /// The session paused the run with a fault (device error, refused
    /// read-back, a request the guard refused). Resumable with
    /// [`SimulationRun::control`].
    #[error("run faulted: {0}")]
    Fault(Fault),
    /// The run is paused: nothing happens until it is resumed or stepped.
    #[error("the run is paused")]
    Paused,
    /// The driver broke the session's protocol (a bug).
    #[error(transparent)]
    Session(#[from] SessionError),
}

/// A run session wired to a simulated device: the driver of the browser's
/// teaching mode, the benchmark and the tests. Serializable as a whole (RNG
/// and lab clock included); a deserialized run reads every gate back before
/// it moves one, like any restored session.
///
/// ```
/// use spintune::driver::{SimulationConfig, SimulationRun};
/// let mut cfg = SimulationConfig::paper_default();
/// cfg.tuner.max_iterations = Some(1);
/// let mut run = SimulationRun::new(cfg).unwrap();
/// let rec = run.next_iteration().unwrap().expect("one iteration");
/// assert!(rec.lab_seconds > 0.0);
/// assert!(run.next_iteration().unwrap().is_none());
/// ```
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SimulationRun<P = Tuner, D = SimulatedDevice> {
    session: RunSession<P>,
    device: D,
}

/// A simulated device a [`SimulationRun`] can drive: one double dot
/// ([`SimulatedDevice`]) or an array of them ([`ArrayDevice`]).
pub trait Simulated {
    /// Execute one request (a [`crate::protocol::Request::Batch`] too).
    fn execute(&mut self, request: &crate::protocol::Request) -> crate::protocol::Response;
}

impl Simulated for SimulatedDevice {
    fn execute(&mut self, request: &crate::protocol::Request) -> crate::protocol::Response {
        SimulatedDevice::execute(self, request)
    }
}

impl Simulated for ArrayDevice {
    fn execute(&mut self, request: &crate::protocol::Request) -> crate::protocol::Response {
        ArrayDevice::execute(self, request)
    }
}

/// An array of double dots tuned jointly: [`ArrayRun`] in a run session
/// (its guard checks every request of every batch) on a simulated array.
pub type ArraySimulationRun = SimulationRun<ArrayRun, ArrayDevice>;

impl SimulationRun {
    /// Validate the config and build session and device at the gates' initial voltages.
    pub fn new(cfg: SimulationConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let device = cfg.simulated_device()?;
        let session =
            RunSession::new(cfg.tuner, SessionConfig::default()).map_err(|e| e.within("tuner"))?;
        Ok(Self { session, device })
    }
}

impl<P: Plan, D: Simulated> SimulationRun<P, D> {
    /// Assemble from parts (e.g. a device state cloned from another run).
    pub fn from_parts(session: RunSession<P>, device: D) -> Self {
        Self { session, device }
    }

    /// One step of the run: at most one device request executed and fed
    /// back, or the iteration that just completed, or the end. A driver
    /// that must yield between requests (the browser's time slices) calls
    /// this; [`SimulationRun::next_iteration`] loops over it. A fault or a
    /// pause is an `Err` (resumable with [`SimulationRun::control`]).
    ///
    /// ```
    /// use spintune::driver::{SimulationConfig, SimulationRun, Step};
    /// let mut cfg = SimulationConfig::recommended();
    /// cfg.tuner.max_iterations = Some(1);
    /// let mut run = SimulationRun::new(cfg).unwrap();
    /// let mut requests = 0;
    /// let record = loop {
    ///     match run.step().unwrap() {
    ///         Step::Executed => requests += 1,
    ///         Step::Iteration(r) => break r,
    ///         Step::Over => unreachable!(),
    ///     }
    /// };
    /// assert_eq!(record.iteration, 0);
    /// assert!(requests > 10);
    /// assert!(matches!(run.step().unwrap(), Step::Over));
    /// ```
    pub fn step(&mut self) -> Result<Step, Halt> {
        loop {
            match self.session.poll() {
                Output::Execute(request) => {
                    let response = self.device.execute(&request);
                    self.session.feed(response)?;
                    return Ok(Step::Executed);
                }
                Output::Commit(record) => return Ok(Step::Iteration(record)),
                // nothing to persist, no wall clock to wait on
                Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
                Output::Wait => {
                    return Err(match self.session.status() {
                        RunStatus::Faulted { fault } => Halt::Fault(fault),
                        _ => Halt::Paused,
                    })
                }
                Output::Done(_) => return Ok(Step::Over),
            }
        }
    }

    /// Run until the next top-level iteration completes; `None` when the run
    /// is over (finished or stopped). A fault or a pause is an `Err` (the
    /// run can be resumed with [`SimulationRun::control`]).
    pub fn next_iteration(&mut self) -> Result<Option<IterationRecord>, Halt> {
        loop {
            match self.step()? {
                Step::Executed => {}
                Step::Iteration(record) => return Ok(Some(*record)),
                Step::Over => return Ok(None),
            }
        }
    }

    /// Apply a control command (pause, resume, step, stop, target change).
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, ControlError> {
        self.session.control(command)
    }

    /// The run session.
    pub fn session(&self) -> &RunSession<P> {
        &self.session
    }

    /// The tuner.
    pub fn tuner(&self) -> &P {
        self.session.tuner()
    }

    /// The simulated device.
    pub fn device(&self) -> &D {
        &self.device
    }

    /// The simulated device, mutably (e.g. to move a gate behind the run's back in a test).
    pub fn device_mut(&mut self) -> &mut D {
        &mut self.device
    }
}
