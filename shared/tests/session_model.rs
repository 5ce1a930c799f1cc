//! Model-based property test of the run session (`spintune::session`).
//!
//! A scripted instrument holds the *physical* gate voltages. Random scripts
//! interleave control commands (pause, resume ×k, step, stop, target
//! changes), device faults, lying / partial / extra read-backs, gates moved
//! by hand while the run is paused, and crashes with a restore from the last
//! committed checkpoint. Whatever the script, these must hold:
//!
//! 1. no request visits a voltage outside the gate limits;
//! 2. no move, and no sweep's first point, is farther than `max_step_mv`
//!    from the gate's **physical** voltage (so a lie never turns into a big
//!    step), and sweep points are at most `max_step_mv` apart;
//! 3. after `stop` is acknowledged, no request reaches the instrument;
//! 4. committed iteration numbers are contiguous and unique (0, 1, 2, …),
//!    across crashes;
//! 5. the fault policy: only a `disconnected` fault clears when the device
//!    reconnects; a reconnect never clears any other fault (nothing is
//!    requested until a person acts), and `accept_positions` is accepted only
//!    for a `moved` fault and leaves the run paused.
//!
//! The instrument also lies: transient read-backs far from the physical
//! voltage, read-backs outside the limits and 1e308; invariant 2 (measured
//! against the physical voltage) holds through them. What no guard can tell
//! from the truth is not scripted: a lie on a gate the run has not left at
//! one known voltage (a new run's first read, a gate after a sweep, which
//! may have left it anywhere in the sweep's range) or one that lands within
//! the moved tolerance of where the run left it.
//!
//! The number of generated steps is counted and asserted (≥ 10⁵ per run of
//! the test binary), so the test cannot pass by generating nothing.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};

use proptest::prelude::*;
use serde::Serialize;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
use spintune::protocol::{
    ClearedBy, ControlCommand, FaultKind, ParameterValue, Request, Response, RunStatus, ScanKind,
    ScanOutcome,
};
use spintune::safety::GateSpec;
use spintune::session::{Output, Plan, RunSession, SessionConfig};
use spintune::tuner::array_run::{ArrayRun, ArrayRunSettings};
use spintune::tuner::{FlankPrediction, InitialGradient, LevelKind, SensingDotConfig, TunerConfig};

/// Steps executed by all cases of this binary.
static STEPS: AtomicU64 = AtomicU64::new(0);
/// Iterations committed, faults published and requests executed, over all cases.
static COMMITS: AtomicU64 = AtomicU64::new(0);
static FAULTS: AtomicU64 = AtomicU64::new(0);
static EXECUTED: AtomicU64 = AtomicU64::new(0);
/// `moved` faults published and positions accepted, over all cases.
static MOVED: AtomicU64 = AtomicU64::new(0);
static ACCEPTED: AtomicU64 = AtomicU64::new(0);
/// Keep mode: check records committed and waits executed.
static KEEP_CHECKS: AtomicU64 = AtomicU64::new(0);
static WAITS: AtomicU64 = AtomicU64::new(0);
/// Array runs: batches executed, iterations committed, faults published.
static BATCHES: AtomicU64 = AtomicU64::new(0);
static ARRAY_COMMITS: AtomicU64 = AtomicU64::new(0);
static ARRAY_FAULTS: AtomicU64 = AtomicU64::new(0);

const CASES: u32 = 500;
const MAX_SCRIPT: usize = 300;
const MIN_TOTAL_STEPS: u64 = 100_000;

fn gate(name: &str, min_mv: f64, max_mv: f64, max_step_mv: f64, initial_mv: f64) -> GateSpec {
    GateSpec {
        name: name.into(),
        min_mv,
        max_mv,
        max_step_mv,
        initial_mv,
    }
}

/// The paper's hierarchy shape on a toy device: qubit level (N, SA, SB, T →
/// t_sr, w), then a sensing-dot sweep of SD1. Built from the paper default so
/// it follows any new config field.
fn tuner_config() -> TunerConfig {
    let mut t = SimulationConfig::paper_default().tuner;
    t.gates = vec![
        gate("N", -60.0, 60.0, 10.0, 0.0),
        gate("SA", -60.0, 60.0, 10.0, 0.0),
        gate("SB", -60.0, 60.0, 10.0, 0.0),
        gate("T", -60.0, 60.0, 10.0, 0.0),
        gate("SD1", -100.0, 100.0, 5.0, 0.0),
        gate("X", -1.0, 1.0, 0.5, 0.0),
    ];
    let mut qubit = t.levels[0].clone();
    if let LevelKind::Newton(n) = &mut qubit.kind {
        n.compensation = None;
        // a rough guess: iterations start at once (finite differences would
        // spend most of a short script)
        n.initial_gradient = InitialGradient::Given {
            gradient: vec![vec![-0.4, -0.2, 0.05, 0.0], vec![0.3, 1.0, 0.0, -1.0]],
            covariance: vec![
                vec![
                    vec![0.04, 0.0, 0.0, 0.0],
                    vec![0.0, 0.04, 0.0, 0.0],
                    vec![0.0, 0.0, 0.04, 0.0],
                    vec![0.0, 0.0, 0.0, 0.04],
                ];
                2
            ],
        };
        n.parameters[1].target = Some(230.0);
    }
    qubit.after_move = vec!["sensing_dot".into()];
    let mut sd = t.levels[2].clone();
    sd.kind = LevelKind::SensingDot(SensingDotConfig {
        gate: "SD1".into(),
        half_width_mv: 5.0,
        points: 11,
        fallback: None,
        // the product default: parks on a predicted flank when confident
        prediction: Some(FlankPrediction::default()),
    });
    t.levels = vec![qubit, sd];
    t.max_iterations = Some(200);
    t.schedule.clear();
    t
}

/// How the instrument answers one request.
#[derive(Debug, Clone, Copy)]
enum Answer {
    Honest,
    /// Error, nothing applied.
    Error,
    /// Applies the first gate, then reports an error.
    PartialError,
    /// Honest answer plus a read-back of a gate that was not requested (a lie: it did not move).
    ExtraGate(f64),
    /// Applies everything, omits one gate from the answer.
    MissingGate,
    /// Applies `set + δ` and reports it honestly.
    Mismatch(f64),
    /// Applies, reports NaN for one gate.
    NonFinite,
    /// Answers with the wrong kind of response.
    WrongKind,
    /// The device is unreachable (a dropped lab bridge): nothing applied.
    Disconnected,
    /// A read reports one gate this far from its physical voltage (a
    /// transient lie; a set is answered honestly).
    LyingRead(f64),
    /// A read reports one gate outside its limits (or 1e308).
    ImpossibleRead(bool),
}

#[derive(Debug, Clone)]
enum Action {
    Exec(Answer),
    Pause,
    Resume(usize),
    Step,
    Stop,
    SetTarget(f64),
    BadTarget,
    /// Someone turns a knob while the run is not moving gates (paused, faulted, crashed).
    KnobTurn(usize, f64),
    Crash,
    /// The device reconnects by itself (`RunSession::device_recovered`).
    Reconnect,
    /// A person confirms the positions of a `moved` fault.
    AcceptPositions,
}

fn answer() -> impl Strategy<Value = Answer> {
    prop_oneof![
        150 => Just(Answer::Honest),
        2 => Just(Answer::Error),
        1 => Just(Answer::PartialError),
        2 => (-80.0..80.0f64).prop_map(Answer::ExtraGate),
        1 => Just(Answer::MissingGate),
        2 => (0.2..30.0f64).prop_map(Answer::Mismatch),
        1 => Just(Answer::NonFinite),
        1 => Just(Answer::WrongKind),
        2 => Just(Answer::Disconnected),
        2 => prop_oneof![(-60.0..-2.0f64), (2.0..60.0f64)].prop_map(Answer::LyingRead),
        1 => any::<bool>().prop_map(Answer::ImpossibleRead),
    ]
}

fn action() -> impl Strategy<Value = Action> {
    prop_oneof![
        160 => answer().prop_map(Action::Exec),
        2 => Just(Action::Pause),
        6 => (1..4usize).prop_map(Action::Resume),
        2 => Just(Action::Step),
        1 => Just(Action::Stop),
        2 => (150.0..300.0f64).prop_map(Action::SetTarget),
        1 => Just(Action::BadTarget),
        2 => ((0..5usize), (-40.0..40.0f64)).prop_map(|(g, d)| Action::KnobTurn(g, d)),
        1 => Just(Action::Crash),
        2 => Just(Action::Reconnect),
        6 => Just(Action::AcceptPositions),
    ]
}

/// The scripted instrument: physical voltages and a toy physics.
struct Instrument {
    limits: BTreeMap<String, GateSpec>,
    phys: BTreeMap<String, f64>,
    noise: u64,
}

impl Instrument {
    fn new(gates: &[GateSpec]) -> Self {
        Self {
            limits: gates.iter().map(|g| (g.name.clone(), g.clone())).collect(),
            phys: gates
                .iter()
                .map(|g| (g.name.clone(), g.initial_mv))
                .collect(),
            noise: 1,
        }
    }

    fn jitter(&mut self) -> f64 {
        // a tiny deterministic LCG: the property is about safety, not tuning
        self.noise = self
            .noise
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.noise >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    }

    /// Invariants 1 and 2: every voltage the request can visit, against the physical state.
    fn check_request(&self, req: &Request) -> Result<(), String> {
        let within = |g: &str, v: f64| -> Result<(), String> {
            let s = &self.limits[g];
            if !(v >= s.min_mv && v <= s.max_mv) {
                return Err(format!("{g}: {v} mV outside [{}, {}]", s.min_mv, s.max_mv));
            }
            Ok(())
        };
        let step_ok = |g: &str, v: f64| -> Result<(), String> {
            let s = &self.limits[g];
            let d = (v - self.phys[g]).abs();
            if d > s.max_step_mv * (1.0 + 1e-9) + 1e-9 {
                return Err(format!(
                    "{g}: physical step {d} mV from {} mV (max {})",
                    self.phys[g], s.max_step_mv
                ));
            }
            Ok(())
        };
        match req {
            Request::SetVoltages { voltages_mv } => {
                for (g, &v) in voltages_mv {
                    within(g, v)?;
                    step_ok(g, v)?;
                }
            }
            Request::Measure { scan } => {
                if let Some(s) = &scan.sweep {
                    within(&s.gate, s.from_mv)?;
                    within(&s.gate, s.to_mv)?;
                    step_ok(&s.gate, s.from_mv)?;
                    let spacing = (s.to_mv - s.from_mv).abs() / (s.points as f64 - 1.0);
                    if spacing > self.limits[&s.gate].max_step_mv + 1e-9 {
                        return Err(format!("sweep spacing {spacing} mV"));
                    }
                }
            }
            Request::ReadVoltages { .. } | Request::TrueJacobian { .. } | Request::Wait { .. } => {}
            Request::Batch { requests } => {
                for r in requests {
                    self.check_request(r)?;
                }
            }
        }
        Ok(())
    }

    fn execute(&mut self, req: &Request, how: Answer) -> Response {
        if matches!(how, Answer::Disconnected) {
            return Response::disconnected("scripted: the bridge dropped");
        }
        match req {
            Request::SetVoltages { voltages_mv } => {
                if matches!(how, Answer::Error) {
                    return Response::error("scripted error");
                }
                if matches!(how, Answer::PartialError) {
                    if let Some((g, v)) = voltages_mv.iter().next() {
                        self.phys.insert(g.clone(), *v);
                    }
                    return Response::error("scripted error after one gate");
                }
                let mut answer = BTreeMap::new();
                for (i, (g, &v)) in voltages_mv.iter().enumerate() {
                    let applied = match how {
                        Answer::Mismatch(d) if i == 0 => {
                            let s = &self.limits[g];
                            (v + d).clamp(s.min_mv, s.max_mv)
                        }
                        _ => v,
                    };
                    self.phys.insert(g.clone(), applied);
                    answer.insert(g.clone(), applied);
                }
                match how {
                    Answer::ExtraGate(lie) => {
                        let extra = self
                            .phys
                            .keys()
                            .find(|g| !voltages_mv.contains_key(*g))
                            .cloned();
                        if let Some(g) = extra {
                            answer.insert(g, lie);
                        }
                    }
                    Answer::MissingGate => {
                        let first = answer.keys().next().cloned();
                        if let Some(g) = first {
                            answer.remove(&g);
                        }
                    }
                    Answer::NonFinite => {
                        if let Some(v) = answer.values_mut().next() {
                            *v = f64::NAN;
                        }
                    }
                    Answer::WrongKind => {
                        return Response::Scanned {
                            outcome: ScanOutcome::Failed {
                                reason: "wrong kind".into(),
                            },
                            lab_seconds: 0.0,
                        }
                    }
                    _ => {}
                }
                Response::VoltagesSet {
                    voltages_mv: answer,
                    lab_seconds: 0.1,
                }
            }
            Request::ReadVoltages { gates } => {
                let mut answer: BTreeMap<String, f64> =
                    gates.iter().map(|g| (g.clone(), self.phys[g])).collect();
                match how {
                    Answer::Error | Answer::PartialError => {
                        return Response::error("scripted read error")
                    }
                    Answer::ExtraGate(lie) => {
                        if let Some(g) = self.phys.keys().find(|g| !gates.contains(g)).cloned() {
                            answer.insert(g, lie);
                        }
                    }
                    Answer::MissingGate => {
                        let first = answer.keys().next().cloned();
                        if let Some(g) = first {
                            answer.remove(&g);
                        }
                    }
                    Answer::NonFinite => {
                        if let Some(v) = answer.values_mut().next() {
                            *v = f64::INFINITY;
                        }
                    }
                    Answer::WrongKind => {
                        return Response::VoltagesSet {
                            voltages_mv: answer,
                            lab_seconds: 0.0,
                        }
                    }
                    Answer::LyingRead(d) => {
                        if let Some(v) = answer.values_mut().next() {
                            *v += d;
                        }
                    }
                    Answer::ImpossibleRead(huge) => {
                        let first = answer.keys().next().cloned();
                        if let Some(g) = first {
                            let lie = if huge {
                                1e308
                            } else {
                                self.limits[&g].max_mv + 5.0
                            };
                            answer.insert(g, lie);
                        }
                    }
                    Answer::Honest | Answer::Mismatch(_) | Answer::Disconnected => {}
                }
                Response::VoltagesRead {
                    voltages_mv: answer,
                    lab_seconds: 0.0,
                }
            }
            Request::Measure { scan } => {
                match how {
                    Answer::Error | Answer::PartialError => {
                        return Response::error("scripted measurement error")
                    }
                    Answer::WrongKind => {
                        return Response::VoltagesSet {
                            voltages_mv: BTreeMap::new(),
                            lab_seconds: 0.0,
                        }
                    }
                    _ => {}
                }
                let phys = self.phys.clone();
                // an array's scan names its cell: that cell's gates
                let prefix = scan.cell.map(|c| format!("c{c}.")).unwrap_or_default();
                let v = |g: &str| phys[&format!("{prefix}{g}")];
                let t_sr = 30.0 * (-(v("N") + 0.5 * v("SA")) / 80.0).exp() + 0.05 * v("SB");
                let w = 250.0 + 1.2 * v("SA") - 0.9 * v("T") + 0.3 * v("N");
                let values = match scan.kind {
                    ScanKind::ReloadTime => vec![ParameterValue {
                        name: "t_sr".into(),
                        value: t_sr + 0.2 * self.jitter(),
                        variance: 0.04,
                    }],
                    ScanKind::TransitionWidth => vec![ParameterValue {
                        name: "w".into(),
                        value: w + 2.0 * self.jitter(),
                        variance: 4.0,
                    }],
                    ScanKind::SensingDot => {
                        let s = scan.sweep.as_ref().expect("sensing-dot scans sweep");
                        // worst case for the next move: the sweep leaves the gate at its end
                        self.phys.insert(s.gate.clone(), s.to_mv);
                        // the flank near the sweep's start: parking there from
                        // the sweep's end is a long way
                        vec![ParameterValue {
                            name: "sd_flank_mv".into(),
                            value: s.from_mv.min(s.to_mv) + 0.5 + 0.01 * v("N").abs(),
                            variance: 0.01,
                        }]
                    }
                    ScanKind::ChemicalPotential => Vec::new(),
                };
                Response::Scanned {
                    outcome: ScanOutcome::Evaluated { values },
                    lab_seconds: 1.0,
                }
            }
            Request::TrueJacobian { .. } => Response::error("no oracle here"),
            Request::Wait { seconds } => Response::Waited {
                lab_seconds: *seconds,
            },
            // the scripted answer goes to one request of the batch (its
            // first of the same kind as the scripted fault needs), the
            // others are answered honestly
            Request::Batch { requests } => {
                if matches!(how, Answer::WrongKind) {
                    return Response::Waited { lab_seconds: 0.0 };
                }
                let target = self.jitter().abs() * requests.len() as f64 * 2.0;
                let pick = (target as usize).min(requests.len().saturating_sub(1));
                let responses = requests
                    .iter()
                    .enumerate()
                    .map(|(i, r)| self.execute(r, if i == pick { how } else { Answer::Honest }))
                    .collect();
                Response::Batch {
                    responses,
                    lab_seconds: 1.0,
                }
            }
        }
    }
}

/// Drive `session` until it hands out a request, handling everything else
/// like a server would (commit with checkpoint, save, publish). Returns the
/// request, or `None` if the session waits or is done.
fn next_request<P: Plan + Serialize>(
    session: &mut RunSession<P>,
    committed: &mut Vec<u64>,
    checkpoint: &mut String,
    faults: &mut u64,
) -> Result<Option<Request>, String> {
    for _ in 0..10_000 {
        match session.poll() {
            Output::Execute(r) => return Ok(Some(r)),
            Output::Commit(rec) => {
                // invariant 4
                if rec.iteration != committed.len() as u64 {
                    return Err(format!(
                        "iteration {} committed after {:?}",
                        rec.iteration,
                        committed.last()
                    ));
                }
                committed.push(rec.iteration);
                COMMITS.fetch_add(1, Ordering::Relaxed);
                if rec
                    .keep
                    .as_ref()
                    .is_some_and(|k| k.phase == spintune::protocol::KeepPhase::Check)
                {
                    KEEP_CHECKS.fetch_add(1, Ordering::Relaxed);
                }
                *checkpoint = serde_json::to_string(session).unwrap();
            }
            Output::Save => *checkpoint = serde_json::to_string(session).unwrap(),
            Output::Publish(RunStatus::Faulted { fault }) => {
                FAULTS.fetch_add(1, Ordering::Relaxed);
                *faults += 1;
                if fault.kind == FaultKind::Moved {
                    MOVED.fetch_add(1, Ordering::Relaxed);
                }
                if fault.cleared_by != fault.kind.cleared_by()
                    || fault.moved.is_empty() != (fault.kind != FaultKind::Moved)
                {
                    return Err(format!("fault off the policy: {fault:?}"));
                }
            }
            Output::Publish(_) | Output::Sleep { .. } => {}
            Output::Wait | Output::Done(_) => return Ok(None),
        }
    }
    Err("the session never settled".into())
}

fn session_config() -> SessionConfig {
    SessionConfig {
        readback_tolerance_mv: 0.05,
        iteration_delay_ms: 0,
        moved_tolerance_mv: 1.0,
    }
}

/// The names a script's actions use on one toy: a single double dot, or
/// an array of them (whose gates and parameters carry a cell prefix).
struct Toy {
    gates: Vec<GateSpec>,
    /// Prefix of the gates a knob turn or a crash touches (`""`, `"c0."`).
    knob_prefix: &'static str,
    /// The parameter a target change names, and its tolerance.
    target_parameter: &'static str,
    target_tolerance: Option<Tolerance>,
}

fn run_script(script: &[Action]) -> Result<(), TestCaseError> {
    run_script_with(tuner_config(), script)
}

fn run_script_with(cfg: TunerConfig, script: &[Action]) -> Result<(), TestCaseError> {
    let toy = Toy {
        gates: cfg.gates.clone(),
        knob_prefix: "",
        target_parameter: "w",
        target_tolerance: Some(Tolerance::Relative(0.05)),
    };
    let session = RunSession::new(cfg, session_config()).unwrap();
    run_script_on(session, &toy, script).map(|_| ())
}

/// Two toy cells as an array (`c0.…`, `c1.…`), tuned jointly.
fn run_array_script(script: &[Action]) -> Result<(), TestCaseError> {
    let cells: Vec<TunerConfig> = (0..2).map(array_cell).collect();
    let gates: Vec<GateSpec> = cells.iter().flat_map(|c| c.gates.clone()).collect();
    let plan = ArrayRun::new(
        cells,
        &gates,
        ArrayRunSettings::default(),
        [0.3, 0.05],
        false,
    )
    .unwrap();
    let toy = Toy {
        gates,
        knob_prefix: "c0.",
        target_parameter: "c1.w",
        target_tolerance: None,
    };
    let (commits, faults) =
        run_script_on(RunSession::from_tuner(plan, session_config()), &toy, script)?;
    ARRAY_COMMITS.fetch_add(commits, Ordering::Relaxed);
    ARRAY_FAULTS.fetch_add(faults, Ordering::Relaxed);
    Ok(())
}

/// The toy tuner with every gate renamed `c{cell}.…`.
fn array_cell(cell: u32) -> TunerConfig {
    let mut t = tuner_config();
    let rn = |g: &mut String| *g = format!("c{cell}.{g}");
    t.gates.iter_mut().for_each(|g| rn(&mut g.name));
    for level in &mut t.levels {
        match &mut level.kind {
            LevelKind::Newton(n) => n.gates.iter_mut().for_each(rn),
            LevelKind::SensingDot(sd) => rn(&mut sd.gate),
        }
    }
    t
}

fn run_script_on<P: Plan + Serialize + serde::de::DeserializeOwned>(
    mut session: RunSession<P>,
    toy: &Toy,
    script: &[Action],
) -> Result<(u64, u64), TestCaseError> {
    let mut dev = Instrument::new(&toy.gates);
    let mut faults = 0;
    let mut committed = Vec::new();
    let mut checkpoint = serde_json::to_string(&session).unwrap();
    let mut stopped = false;
    for step in script {
        STEPS.fetch_add(1, Ordering::Relaxed);
        match step {
            Action::Exec(how) => {
                let req = next_request(&mut session, &mut committed, &mut checkpoint, &mut faults)
                    .map_err(TestCaseError::fail)?;
                let Some(req) = req else { continue };
                // invariant 3
                prop_assert!(!stopped, "request after stop: {req:?}");
                // invariants 1 and 2
                dev.check_request(&req).map_err(TestCaseError::fail)?;
                EXECUTED.fetch_add(1, Ordering::Relaxed);
                if matches!(req, Request::Wait { .. }) {
                    WAITS.fetch_add(1, Ordering::Relaxed);
                }
                if matches!(req, Request::Batch { .. }) {
                    BATCHES.fetch_add(1, Ordering::Relaxed);
                }
                let how = match (how, &req) {
                    (Answer::LyingRead(d), Request::ReadVoltages { gates }) => {
                        // The lie is told about the first gate of the answer.
                        let g = gates.iter().min().cloned().unwrap_or_default();
                        let detectable = session.guard().left_mv().get(&g).is_some_and(|s| {
                            s.lo_mv == s.hi_mv && (dev.phys[&g] + d - s.lo_mv).abs() > 1.0
                        });
                        if detectable {
                            Answer::LyingRead(*d)
                        } else {
                            Answer::Honest
                        }
                    }
                    (other, _) => *other,
                };
                let resp = dev.execute(&req, how);
                session
                    .feed(resp)
                    .map_err(|e| TestCaseError::fail(e.to_string()))?;
            }
            Action::Pause => {
                let _ = session.control(&ControlCommand::Pause);
            }
            Action::Resume(k) => {
                for _ in 0..*k {
                    let r = session.control(&ControlCommand::Resume);
                    prop_assert_eq!(r.is_ok(), !stopped && !session.status().is_terminal());
                }
            }
            Action::Step => {
                let _ = session.control(&ControlCommand::Step);
            }
            Action::Stop => {
                let s = session.control(&ControlCommand::Stop).unwrap();
                if s == RunStatus::Stopped || s == RunStatus::Stopping {
                    stopped = true;
                }
            }
            Action::SetTarget(w) => {
                let r = session.control(&ControlCommand::SetTarget {
                    parameter: toy.target_parameter.into(),
                    target: Some(*w),
                    tolerance: toy.target_tolerance,
                });
                prop_assert_eq!(r.is_ok(), !stopped);
            }
            Action::BadTarget => {
                let r = session.control(&ControlCommand::SetTarget {
                    parameter: toy.target_parameter.into(),
                    target: Some(f64::NAN),
                    tolerance: None,
                });
                prop_assert!(r.is_err());
            }
            Action::KnobTurn(g, d) => {
                let moving = matches!(session.status(), RunStatus::Running | RunStatus::Stepping);
                if !moving {
                    let name = format!("{}{}", toy.knob_prefix, ["N", "SA", "SB", "T", "SD1"][*g]);
                    let s = &dev.limits[&name];
                    let v = (dev.phys[&name] + d).clamp(s.min_mv, s.max_mv);
                    dev.phys.insert(name, v);
                }
            }
            Action::Reconnect => {
                let before = session.status();
                let resumed = session.device_recovered();
                let policy_allows = matches!(&before, RunStatus::Faulted { fault } if fault.kind.cleared_by() == ClearedBy::Reconnect);
                prop_assert_eq!(resumed, policy_allows, "reconnect while {:?}", before);
                if !resumed {
                    prop_assert_eq!(session.status(), before);
                }
            }
            Action::AcceptPositions => {
                let before = session.status();
                let r = session.control(&ControlCommand::AcceptPositions);
                let moved = matches!(&before, RunStatus::Faulted { fault } if fault.kind == FaultKind::Moved);
                prop_assert_eq!(r.is_ok(), moved, "accept_positions while {:?}", before);
                if moved {
                    ACCEPTED.fetch_add(1, Ordering::Relaxed);
                    prop_assert_eq!(session.status(), RunStatus::Paused);
                } else {
                    prop_assert_eq!(session.status(), before);
                }
            }
            Action::Crash => {
                // Everything since the last commit is lost; the instrument
                // stays where it is, and someone may have touched it.
                session = serde_json::from_str(&checkpoint).unwrap();
                let name = format!("{}T", toy.knob_prefix);
                let s = &dev.limits[&name];
                let v = (dev.phys[&name] + 17.0).clamp(s.min_mv, s.max_mv);
                dev.phys.insert(name, v);
                // a restored run that was stopped stays stopped
                stopped = session.status() == RunStatus::Stopped;
            }
        }
    }
    Ok((committed.len() as u64, faults))
}

/// Runs [`CASES`] random scripts (proptest shrinks a failing one to a
/// minimal counterexample) and checks that they added up to at least
/// [`MIN_TOTAL_STEPS`] steps.
#[test]
fn session_holds_safety_and_lifecycle_invariants_over_1e5_random_steps() {
    // A fixed seed: the thresholds below count what the scripts provoke,
    // and a fresh random seed per run made them flaky (a run at 18,681
    // requests against a threshold of 18,867). Every script still comes
    // from proptest's generator and shrinks on failure.
    use proptest::test_runner::{RngAlgorithm, TestRng, TestRunner};
    let mut runner = TestRunner::new_with_rng(
        ProptestConfig {
            cases: CASES,
            ..ProptestConfig::default()
        },
        TestRng::deterministic_rng(RngAlgorithm::ChaCha),
    );
    let before = STEPS.load(Ordering::Relaxed);
    let result = runner.run(
        &prop::collection::vec(action(), MAX_SCRIPT / 2..=MAX_SCRIPT),
        |script| run_script(&script),
    );
    if let Err(e) = result {
        panic!("{e}");
    }
    let generated = STEPS.load(Ordering::Relaxed) - before;
    let (commits, faults, executed) = (
        COMMITS.load(Ordering::Relaxed),
        FAULTS.load(Ordering::Relaxed),
        EXECUTED.load(Ordering::Relaxed),
    );
    let (moved, accepted) = (
        MOVED.load(Ordering::Relaxed),
        ACCEPTED.load(Ordering::Relaxed),
    );
    eprintln!("{generated} steps: {executed} requests executed, {commits} iterations committed, {faults} faults ({moved} moved, {accepted} positions accepted)");
    assert!(
        generated >= MIN_TOTAL_STEPS,
        "only {generated} steps generated"
    );
    // The scripts must really drive tuning and really provoke faults.
    // (an eighth: faults that wait for a person — moved gates need
    // accept_positions and a resume — keep many scripts waiting)
    assert!(executed >= generated / 8, "{executed} requests executed");
    assert!(
        commits >= u64::from(CASES) * 5,
        "{commits} iterations committed"
    );
    assert!(faults >= u64::from(CASES), "{faults} faults");
    assert!(moved >= u64::from(CASES) / 2, "{moved} moved faults");
    assert!(
        accepted >= u64::from(CASES) / 5,
        "{accepted} positions accepted"
    );
}

/// The same invariants with keep mode on: once tuned, the run waits
/// (`Request::Wait`), checks and re-tunes; crashes, faults, lies and target
/// changes land in every phase of it. The scripts must reach keep mode.
#[test]
fn keep_mode_session_holds_the_same_invariants() {
    use proptest::test_runner::{RngAlgorithm, TestRng, TestRunner};
    let mut cfg = tuner_config();
    cfg.max_iterations = None;
    cfg.keep = Some(spintune::tuner::KeepConfig {
        min_check_interval_s: 10.0,
        max_check_interval_s: 60.0,
        batch_window_s: 0.0,
        ..spintune::tuner::KeepConfig::default()
    });
    let mut runner = TestRunner::new_with_rng(
        ProptestConfig {
            cases: CASES / 5,
            ..ProptestConfig::default()
        },
        TestRng::deterministic_rng(RngAlgorithm::ChaCha),
    );
    let result = runner.run(
        &prop::collection::vec(action(), MAX_SCRIPT / 2..=MAX_SCRIPT),
        |script| run_script_with(cfg.clone(), &script),
    );
    if let Err(e) = result {
        panic!("{e}");
    }
    let (checks, waits) = (
        KEEP_CHECKS.load(Ordering::Relaxed),
        WAITS.load(Ordering::Relaxed),
    );
    eprintln!("keep mode: {checks} checks committed, {waits} waits executed");
    assert!(checks >= u64::from(CASES / 5), "{checks} checks");
    assert!(waits >= u64::from(CASES / 5), "{waits} waits");
}

/// The same invariants on an array of two toy double dots tuned jointly:
/// every request goes out in a batch, the scripted fault lands on one
/// request of a batch (the others are answered honestly), and the
/// instrument's checks look into every batch. The scripts must drive the
/// joint tuner through iterations and provoke faults.
#[test]
fn array_session_holds_the_same_invariants() {
    use proptest::test_runner::{RngAlgorithm, TestRng, TestRunner};
    let before = (
        ARRAY_COMMITS.load(Ordering::Relaxed),
        ARRAY_FAULTS.load(Ordering::Relaxed),
        BATCHES.load(Ordering::Relaxed),
    );
    let mut runner = TestRunner::new_with_rng(
        ProptestConfig {
            cases: CASES / 5,
            ..ProptestConfig::default()
        },
        TestRng::deterministic_rng(RngAlgorithm::ChaCha),
    );
    let result = runner.run(
        &prop::collection::vec(action(), MAX_SCRIPT / 2..=MAX_SCRIPT),
        |script| run_array_script(&script),
    );
    if let Err(e) = result {
        panic!("{e}");
    }
    let (commits, faults, batches) = (
        ARRAY_COMMITS.load(Ordering::Relaxed) - before.0,
        ARRAY_FAULTS.load(Ordering::Relaxed) - before.1,
        BATCHES.load(Ordering::Relaxed) - before.2,
    );
    eprintln!("array: {batches} batches executed, {commits} iterations committed, {faults} faults");
    assert!(batches >= u64::from(CASES / 5) * 10, "{batches} batches");
    assert!(
        commits >= u64::from(CASES / 5),
        "{commits} iterations committed"
    );
    assert!(faults >= u64::from(CASES / 5), "{faults} faults");
}
