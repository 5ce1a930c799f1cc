//! State-machine tests against a small analytic device (independent of the
//! full simulator, which has its own end-to-end tests).

use std::collections::BTreeMap;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::*;
use crate::estimator::EstimatorKind;
use crate::parameter::{ParameterSpec, Transform};
use crate::protocol::ScanOutcome;
use crate::safety::GateSpec;
use crate::solver::SolverConfig;

/// p_a = 40·exp(−(v0 + 0.5 v1)/60) + 0.1 v2 (ns-like, positive)
/// p_b = 200 + 1.5 v1 − 0.8 v3 + 0.01 v0 v3 (µV-like)
/// mu  = 0.3 v0 + 0.2 v1 + 0.1 v2 + 0.1 v3 + PA  (mV-like, compensated by PA)
#[derive(Clone, Serialize, Deserialize)]
struct Toy {
    v: BTreeMap<String, f64>,
    rng: ChaCha8Rng,
    sigma: [f64; 2],
    log: Vec<String>,
    /// iteration index (counted in w measurements) at which w is reported absurdly
    bogus_at: Option<u32>,
    nan_at: Option<u32>,
    w_count: u32,
}

impl Toy {
    fn new(gates: &[GateSpec], seed: u64) -> Self {
        Self {
            v: gates
                .iter()
                .map(|g| (g.name.clone(), g.initial_mv))
                .collect(),
            rng: ChaCha8Rng::seed_from_u64(seed),
            sigma: [0.3, 2.0],
            log: Vec::new(),
            bogus_at: None,
            nan_at: None,
            w_count: 0,
        }
    }
    fn truth(&self) -> (f64, f64, f64) {
        let v = |g: &str| self.v[g];
        let a = 40.0 * (-(v("N") + 0.5 * v("SA")) / 60.0).exp() + 0.1 * v("SB");
        let b = 200.0 + 1.5 * v("SA") - 0.8 * v("T") + 0.01 * v("N") * v("T");
        let mu = 0.3 * v("N") + 0.2 * v("SA") + 0.1 * v("SB") + 0.1 * v("T") + v("PA");
        (a, b, mu)
    }
    fn execute(&mut self, req: &Request) -> Response {
        match req {
            Request::SetVoltages { voltages_mv } => {
                self.log.push(format!(
                    "set {}",
                    voltages_mv.keys().cloned().collect::<Vec<_>>().join(",")
                ));
                for (g, v) in voltages_mv {
                    self.v.insert(g.clone(), *v);
                }
                Response::VoltagesSet {
                    voltages_mv: voltages_mv.clone(),
                    lab_seconds: 0.1,
                }
            }
            Request::Measure { scan } => {
                self.log.push(format!("measure {:?}", scan.kind));
                let (a, b, mu) = self.truth();
                let values = match scan.kind {
                    ScanKind::ReloadTime => {
                        let n = Normal::new(0.0, self.sigma[0])
                            .unwrap()
                            .sample(&mut self.rng);
                        vec![ParameterValue {
                            name: "t_sr".into(),
                            value: a + n,
                            variance: self.sigma[0].powi(2),
                        }]
                    }
                    ScanKind::TransitionWidth => {
                        self.w_count += 1;
                        let n = Normal::new(0.0, self.sigma[1])
                            .unwrap()
                            .sample(&mut self.rng);
                        let bogus = self.bogus_at == Some(self.w_count);
                        let nan = self.nan_at == Some(self.w_count);
                        vec![ParameterValue {
                            name: "w".into(),
                            value: if bogus { b + 500.0 } else { b + n },
                            variance: if nan { f64::NAN } else { self.sigma[1].powi(2) },
                        }]
                    }
                    ScanKind::ChemicalPotential => vec![ParameterValue {
                        name: "mu_a_mv".into(),
                        value: mu,
                        variance: 1e-4,
                    }],
                    ScanKind::SensingDot => vec![ParameterValue {
                        name: "sd_flank_mv".into(),
                        value: -300.0 + 0.05 * self.v["N"],
                        variance: 0.01,
                    }],
                };
                Response::Scanned {
                    outcome: ScanOutcome::Evaluated { values },
                    lab_seconds: 10.0,
                }
            }
            Request::TrueJacobian { .. } | Request::ReadVoltages { .. } | Request::Batch { .. } => {
                Response::error(
                    "toy has no oracle, is not read back and runs no batch (the tuner never asks)",
                )
            }
            Request::Wait { seconds } => Response::Waited {
                lab_seconds: *seconds,
            },
        }
    }
}

fn gate(name: &str, initial: f64, max_step: f64) -> GateSpec {
    GateSpec {
        name: name.into(),
        min_mv: -100.0,
        max_mv: 100.0,
        max_step_mv: max_step,
        initial_mv: initial,
    }
}

fn gates() -> Vec<GateSpec> {
    vec![
        gate("N", 0.0, 10.0),
        gate("SA", 0.0, 10.0),
        gate("SB", 0.0, 10.0),
        gate("T", 0.0, 10.0),
        gate("PA", 0.0, 20.0),
        GateSpec {
            min_mv: -400.0,
            ..gate("SP", -300.0, 20.0)
        },
    ]
}

fn qubit(estimator: EstimatorKind) -> NewtonConfig {
    NewtonConfig {
        gates: ["N", "SA", "SB", "T"].map(String::from).to_vec(),
        parameters: vec![
            ParameterSpec {
                name: "t_sr".into(),
                unit: "ns".into(),
                scan: ScanKind::ReloadTime,
                target: Some(20.0),
                tolerance: Tolerance::Relative(0.1),
                transform: Transform::Linear,
                process_noise_per_mv: 0.075,
            },
            ParameterSpec {
                name: "w".into(),
                unit: "µV".into(),
                scan: ScanKind::TransitionWidth,
                target: Some(230.0),
                tolerance: Tolerance::Relative(0.05),
                transform: Transform::Linear,
                process_noise_per_mv: 0.3,
            },
        ],
        estimator,
        initial_gradient: InitialGradient::FiniteDifference {
            step_mv: 3.0,
            repetitions: 2,
            recentre_between_offsets: true,
            central: false,
            mirrored: Vec::new(),
        },
        solver: SolverConfig::default(),
        outlier_sigma: Some(5.0),
        min_step_mv: 0.01,
        fd_step_mv: 3.0,
        max_iterations_per_call: 1,
        hold_initial_values: false,
        compensation: None,
        skip_confirmation_sigma: None,
        forecast: None,
        search: None,
    }
}

fn flat(estimator: EstimatorKind) -> TunerConfig {
    TunerConfig {
        gates: gates(),
        levels: vec![LevelConfig {
            name: "qubit".into(),
            kind: LevelKind::Newton(qubit(estimator)),
            after_move: vec![],
        }],
        stop_when_tuned: false,
        max_iterations: Some(25),
        schedule: Vec::new(),
        fit_references: Default::default(),
        keep: None,
    }
}

fn hierarchical() -> TunerConfig {
    let mut q = qubit(EstimatorKind::Kalman);
    q.compensation = Some(Compensation {
        gates: vec!["PA".into()],
        matrix: vec![vec![-0.3, -0.2, -0.1, -0.1]],
        relative_uncertainty: 0.2,
    });
    let chem = NewtonConfig {
        gates: vec!["PA".into()],
        parameters: vec![ParameterSpec {
            name: "mu_a_mv".into(),
            unit: "mV".into(),
            scan: ScanKind::ChemicalPotential,
            target: Some(0.0),
            tolerance: Tolerance::Absolute(0.05),
            transform: Transform::Linear,
            process_noise_per_mv: 0.001,
        }],
        estimator: EstimatorKind::Kalman,
        initial_gradient: InitialGradient::Given {
            gradient: vec![vec![0.9]],
            covariance: vec![vec![vec![0.01]]],
        },
        solver: SolverConfig {
            max_step_mv: 20.0,
            ..Default::default()
        },
        outlier_sigma: None,
        min_step_mv: 0.0,
        fd_step_mv: 1.0,
        max_iterations_per_call: 3,
        hold_initial_values: false,
        compensation: None,
        skip_confirmation_sigma: None,
        forecast: None,
        search: None,
    };
    TunerConfig {
        gates: gates(),
        levels: vec![
            LevelConfig {
                name: "qubit".into(),
                kind: LevelKind::Newton(q),
                after_move: vec!["sensing_dot".into(), "chemical_potential".into()],
            },
            LevelConfig {
                name: "chemical_potential".into(),
                kind: LevelKind::Newton(chem),
                after_move: vec!["sensing_dot".into()],
            },
            LevelConfig {
                name: "sensing_dot".into(),
                kind: LevelKind::SensingDot(SensingDotConfig {
                    gate: "SP".into(),
                    half_width_mv: 10.0,
                    points: 50,
                    fallback: None,
                    prediction: None,
                }),
                after_move: vec![],
            },
        ],
        stop_when_tuned: false,
        max_iterations: Some(25),
        schedule: Vec::new(),
        fit_references: Default::default(),
        keep: None,
    }
}

/// Drive to completion; checks every request against the limits on the way.
fn drive(tuner: &mut Tuner, dev: &mut Toy, max_records: usize) -> Vec<IterationRecord> {
    let mut out = Vec::new();
    for _ in 0..100_000 {
        match tuner.poll() {
            Action::Request(req) => {
                if let Request::SetVoltages { voltages_mv } = &req {
                    tuner
                        .safety()
                        .check(&dev.v, voltages_mv)
                        .expect("tuner emitted an unsafe request");
                }
                let resp = dev.execute(&req);
                tuner.feed(resp).unwrap();
            }
            Action::Iteration(r) => {
                out.push(r);
                if out.len() >= max_records {
                    return out;
                }
            }
            Action::Finished => return out,
        }
    }
    panic!("tuner did not finish");
}

fn step_norm(a: &IterationRecord, b: &IterationRecord) -> f64 {
    a.gates
        .iter()
        .map(|g| (b.voltages_mv[g] - a.voltages_mv[g]).powi(2))
        .sum::<f64>()
        .sqrt()
}

#[test]
fn kalman_reaches_target_within_limits() {
    let cfg = flat(EstimatorKind::Kalman);
    let mut tuner = Tuner::new(cfg).unwrap();
    let mut dev = Toy::new(&gates(), 7);
    let recs = drive(&mut tuner, &mut dev, usize::MAX);
    assert_eq!(recs.len(), 25);
    let first_tuned = recs.iter().position(|r| r.tuned).expect("never tuned");
    assert!(first_tuned <= 10, "took {first_tuned} iterations");
    for pair in recs.windows(2) {
        assert!(step_norm(&pair[0], &pair[1]) <= 10.0 + 1e-9);
    }
    // records carry gradients with covariances and units
    let g = &recs[3].gradients[0];
    assert_eq!(g.unit, "ns/mV");
    assert_eq!(g.gradient.len(), 4);
    assert!(g.covariance.is_some());
    // the FD initialisation measured each parameter 1 + 4 times per repetition, twice
    assert!(recs[0].scan_counts[&ScanKind::ReloadTime] >= 10);
}

#[test]
fn every_estimator_kind_runs_and_respects_limits() {
    for kind in [
        EstimatorKind::KalmanAdaptiveQ,
        EstimatorKind::Broyden,
        EstimatorKind::FixedJacobian,
        EstimatorKind::FdNewton,
    ] {
        let mut tuner = Tuner::new(flat(kind)).unwrap();
        let mut dev = Toy::new(&gates(), 3);
        let recs = drive(&mut tuner, &mut dev, usize::MAX);
        assert!(recs.iter().any(|r| r.tuned), "{kind:?} never tuned");
        for pair in recs.windows(2) {
            assert!(step_norm(&pair[0], &pair[1]) <= 10.0 + 1e-9, "{kind:?}");
        }
    }
}

#[test]
fn fd_newton_counts_its_extra_measurements() {
    let mut a = Tuner::new(flat(EstimatorKind::FdNewton)).unwrap();
    let mut b = Tuner::new(flat(EstimatorKind::Kalman)).unwrap();
    let ra = drive(&mut a, &mut Toy::new(&gates(), 5), 6);
    let rb = drive(&mut b, &mut Toy::new(&gates(), 5), 6);
    let untuned = ra.iter().filter(|r| !r.tuned).count() as u64;
    // 4 extra measurements of each scan per untuned iteration
    assert!(
        ra[5].scan_counts[&ScanKind::ReloadTime]
            >= rb[5].scan_counts[&ScanKind::ReloadTime] + 4 * (untuned - 1)
    );
}

#[test]
fn untargeted_parameter_is_not_driven() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().parameters[1].target = None;
    cfg.max_iterations = Some(15);
    let mut tuner = Tuner::new(cfg).unwrap();
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 9), usize::MAX);
    let last = recs.last().unwrap();
    assert!(last.tuned);
    assert_eq!(last.parameters[1].target, None);
    // once t_sr is in band, nothing moves although w is far from any value
    let i = recs.iter().position(|r| r.tuned).unwrap();
    assert!(recs[i].step_mv.iter().all(|&x| x == 0.0));
}

#[test]
fn hierarchy_runs_children_after_each_move_in_order() {
    let mut tuner = Tuner::new(hierarchical()).unwrap();
    let mut dev = Toy::new(&gates(), 11);
    let recs = drive(&mut tuner, &mut dev, 4);
    assert_eq!(recs.len(), 4);
    // after a qubit move (set with N,PA,SA,SB,T: compensation included) the
    // sensing dot is swept and parked, then the chemical potential measured.
    let log = &dev.log;
    let moves: Vec<usize> = log
        .iter()
        .enumerate()
        .filter(|(_, l)| l.as_str() == "set N,PA,SA,SB,T")
        .map(|(i, _)| i)
        .collect();
    assert!(!moves.is_empty());
    for &i in &moves {
        assert_eq!(log[i + 1], "measure SensingDot");
        assert_eq!(log[i + 2], "set SP");
        assert_eq!(log[i + 3], "measure ChemicalPotential");
    }
    // only the gates assigned to a level (and its compensation gates) ever move
    for l in log.iter().filter(|l| l.starts_with("set ")) {
        assert!(
            ["set N,PA,SA,SB,T", "set SP", "set PA"].contains(&l.as_str()),
            "unexpected set: {l}"
        );
    }
    // compensation + chemical level keep mu near 0 at every qubit measurement
    let (_, _, mu) = dev.truth();
    assert!(mu.abs() < 0.5, "mu = {mu}");
    assert!(recs.iter().all(|r| r.voltages_mv.contains_key("PA")));
}

#[test]
fn checkpoint_resume_is_bit_identical() {
    let cfg = hierarchical();
    let mut tuner = Tuner::new(cfg).unwrap();
    let mut dev = Toy::new(&gates(), 21);
    let _ = drive(&mut tuner, &mut dev, 5);
    let saved = (
        serde_json::to_string(&tuner).unwrap(),
        serde_json::to_string(&dev).unwrap(),
    );
    let straight = drive(&mut tuner, &mut dev, 8);
    let mut t2: Tuner = serde_json::from_str(&saved.0).unwrap();
    let mut d2: Toy = serde_json::from_str(&saved.1).unwrap();
    let resumed = drive(&mut t2, &mut d2, 8);
    assert_eq!(straight, resumed);
    assert_eq!(
        serde_json::to_string(&tuner).unwrap(),
        serde_json::to_string(&t2).unwrap()
    );
}

#[test]
fn targets_change_between_iterations() {
    let mut tuner = Tuner::new(flat(EstimatorKind::Kalman)).unwrap();
    let mut dev = Toy::new(&gates(), 13);
    let recs = drive(&mut tuner, &mut dev, 12);
    assert!(recs.last().unwrap().tuned);
    tuner.set_target("t_sr", Some(30.0), None).unwrap();
    assert!(tuner.set_target("t_sr", Some(f64::NAN), None).is_err());
    assert!(matches!(
        tuner.set_target("nope", Some(1.0), None),
        Err(TunerError::UnknownParameter(_))
    ));
    let after = drive(&mut tuner, &mut dev, 10);
    assert_eq!(after[0].parameters[0].target, Some(30.0));
    assert!(!after[0].tuned);
    assert!(
        after.iter().any(|r| r.tuned),
        "did not reach the new target"
    );
}

#[test]
fn outlier_is_gated_and_does_not_move_gradient() {
    let mut tuner = Tuner::new(flat(EstimatorKind::Kalman)).unwrap();
    let mut dev = Toy::new(&gates(), 17);
    // the FD init takes 2·(1+4) = 10 w measurements; the 3rd iteration's is bogus
    dev.bogus_at = Some(13);
    let recs = drive(&mut tuner, &mut dev, 4);
    let bad = &recs[2];
    assert!(
        bad.events.iter().any(|e| matches!(
            &e.kind,
            EventKind::OutlierGated { parameter, .. } if parameter == "w"
        )),
        "{:?}",
        bad.events
    );
    assert_eq!(recs[1].gradients[1].gradient, bad.gradients[1].gradient);
}

#[test]
fn nan_variance_is_rejected_before_the_filter() {
    let mut tuner = Tuner::new(flat(EstimatorKind::Kalman)).unwrap();
    let mut dev = Toy::new(&gates(), 19);
    dev.nan_at = Some(12);
    let recs = drive(&mut tuner, &mut dev, 3);
    let r = &recs[1];
    assert_eq!(r.parameters[1].value, None);
    assert!(r.failed_evaluations >= 1);
    assert!(r.gradients[1].gradient.iter().all(|x| x.is_finite()));
    assert_eq!(recs[0].gradients[1].gradient, r.gradients[1].gradient);
}

#[test]
fn device_error_keeps_request_pending() {
    let mut tuner = Tuner::new(flat(EstimatorKind::Kalman)).unwrap();
    let Action::Request(first) = tuner.poll() else {
        panic!()
    };
    let before = tuner.clone();
    let err = tuner.feed(Response::error("bridge timed out"));
    assert!(matches!(err, Err(TunerError::Device(_))));
    assert_eq!(tuner, before);
    assert_eq!(tuner.poll(), Action::Request(first));
    // a response of the wrong kind is refused too
    assert!(tuner
        .feed(Response::VoltagesSet {
            voltages_mv: BTreeMap::new(),
            lab_seconds: 0.0
        })
        .is_err());
}

#[test]
fn stop_when_tuned_finishes() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.stop_when_tuned = true;
    cfg.max_iterations = None;
    let mut tuner = Tuner::new(cfg).unwrap();
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 23), 100);
    assert!(recs.last().unwrap().tuned);
    assert!(recs[..recs.len() - 1].iter().all(|r| !r.tuned));
    assert_eq!(tuner.poll(), Action::Finished);
}

#[test]
fn log_transform_tunes_and_reports_log_units() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().parameters[0].transform = Transform::Log;
    cfg.top_mut().parameters[0].process_noise_per_mv = 0.002;
    let mut tuner = Tuner::new(cfg).unwrap();
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 29), usize::MAX);
    assert!(recs.iter().any(|r| r.tuned));
    assert!(recs[0].gradients[0].unit.contains("log"));
}

#[test]
fn config_errors_name_the_field() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().gates[2] = "XX".into();
    let e = Tuner::new(cfg).unwrap_err();
    assert_eq!(e.field, "levels[0].gates[2]");
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.gates[0].initial_mv = 1000.0;
    assert_eq!(Tuner::new(cfg).unwrap_err().field, "gates[0].initial_mv");
    let mut cfg = hierarchical();
    cfg.levels[2].after_move = vec!["qubit".into()];
    assert!(Tuner::new(cfg)
        .unwrap_err()
        .field
        .starts_with("levels[2].after_move"));
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().parameters[0].process_noise_per_mv = -1.0;
    assert_eq!(
        Tuner::new(cfg).unwrap_err().field,
        "levels[0].parameters[0].process_noise_per_mv"
    );
}

#[test]
fn step_rule_fields_are_bounded_and_default_to_the_papers_rule() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().solver.covariance_weight = -0.5;
    assert_eq!(
        Tuner::new(cfg).unwrap_err().field,
        "levels[0].solver.covariance_weight"
    );
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.top_mut().solver.covariance_weight = 101.0;
    assert!(Tuner::new(cfg).is_err());
    for moves in [0, 6] {
        let mut cfg = flat(EstimatorKind::Kalman);
        cfg.top_mut().solver.max_moves_per_iteration = moves;
        assert_eq!(
            Tuner::new(cfg).unwrap_err().field,
            "levels[0].solver.max_moves_per_iteration"
        );
    }
    // a solver config written before item 6 gets the paper's behaviour
    let old: SolverConfig =
        serde_json::from_str(r#"{"max_step_mv": 7.0, "rank_tolerance": 1e-9}"#).unwrap();
    assert_eq!(old.rule, crate::solver::StepRule::PseudoInverse);
    assert_eq!(old.max_moves_per_iteration, 1);
    assert!(old.lower_levels_between_moves);
    assert_eq!(old.covariance_weight, 0.0);
    let new: SolverConfig = serde_json::from_str(
        r#"{"rule": "expected_cost", "covariance_weight": 1.0, "max_moves_per_iteration": 2, "lower_levels_between_moves": false}"#,
    )
    .unwrap();
    assert_eq!(new.rule, crate::solver::StepRule::ExpectedCost);
    assert_eq!(new.max_step_mv, 10.0);
    assert!(serde_json::from_str::<SolverConfig>(r#"{"moves": 2}"#).is_err());
}

#[test]
fn non_positive_or_non_finite_fit_references_are_rejected_naming_the_field() {
    type Set = fn(&mut TunerConfig, f64);
    let cases: [(&str, Set); 4] = [
        ("fit_references.w.sigma0", |c, x| {
            c.fit_references.w.sigma0 = x
        }),
        ("fit_references.w.delta_p0", |c, x| {
            c.fit_references.w.delta_p0 = x
        }),
        ("fit_references.t_sr.sigma0", |c, x| {
            c.fit_references.t_sr.sigma0 = x
        }),
        ("fit_references.t_sr.delta_p0", |c, x| {
            c.fit_references.t_sr.delta_p0 = x
        }),
    ];
    for (field, set) in cases {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let mut cfg = hierarchical();
            set(&mut cfg, bad);
            let e = Tuner::new(cfg).unwrap_err();
            assert_eq!(e.field, field, "{bad}");
            assert!(e.to_string().contains("> 0"), "{e}");
        }
        let mut cfg = hierarchical();
        set(&mut cfg, 1e-3);
        assert!(Tuner::new(cfg).is_ok(), "{field}");
    }
}

#[test]
fn fit_references_default_when_absent_from_a_config() {
    let cfg = hierarchical();
    let mut json: serde_json::Value = serde_json::to_value(&cfg).unwrap();
    assert!(json
        .as_object_mut()
        .unwrap()
        .remove("fit_references")
        .is_some());
    let back: TunerConfig = serde_json::from_value(json).unwrap();
    assert_eq!(
        back.fit_references,
        crate::fit::uncertainty::SIMULATED_DEVICE_REFERENCES
    );
}

#[test]
fn learned_gradients_seed_a_new_tuner() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.max_iterations = Some(0);
    let mut tuner = Tuner::new(cfg).unwrap();
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 31), 10);
    assert!(recs.is_empty());
    let learned = tuner.config_with_learned_gradients();
    assert!(matches!(
        learned.top().initial_gradient,
        InitialGradient::Given { .. }
    ));
    let t2 = Tuner::new(learned).unwrap();
    assert_eq!(
        t2.gradients(0).unwrap()[0].0,
        tuner.gradients(0).unwrap()[0].0
    );
}

#[test]
fn config_round_trips_and_refuses_unknown_fields() {
    let cfg = hierarchical();
    let json = serde_json::to_string(&cfg).unwrap();
    let back: TunerConfig = serde_json::from_str(&json).unwrap();
    assert_eq!(back, cfg);
    let bad = json.replacen("\"fd_step_mv\"", "\"fd_stepp_mv\"", 1);
    let err = serde_json::from_str::<TunerConfig>(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("fd_stepp_mv"), "{err}");
}

#[test]
fn rough_guess_start_relearns_the_gradient() {
    let mut cfg = flat(EstimatorKind::Kalman);
    // deliberately wrong by a factor ~2 and with C(0) ~ g(0)² (paper supplement)
    cfg.top_mut().initial_gradient = InitialGradient::RoughGuess {
        gradient: vec![vec![-1.0, -0.2, 0.2, 0.0], vec![0.0, 3.0, 0.0, -1.6]],
        relative_std: 1.0,
    };
    let mut tuner = Tuner::new(cfg).unwrap();
    let c0 = tuner.gradients(0).unwrap()[0].1.clone().unwrap();
    assert_eq!(c0[(0, 0)], 1.0);
    assert!((c0[(1, 1)] - 0.04).abs() < 1e-15);
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 37), usize::MAX);
    // no finite-difference scans were spent, and the target is reached
    assert_eq!(recs[0].scan_counts[&ScanKind::ReloadTime], 1);
    assert!(recs.iter().any(|r| r.tuned));
}

#[test]
fn schedule_changes_targets_at_the_given_iterations() {
    let mut cfg = flat(EstimatorKind::Kalman);
    cfg.max_iterations = Some(20);
    cfg.schedule = vec![ScheduledTargets {
        at_iteration: 10,
        targets: [("t_sr".to_string(), 30.0)].into(),
    }];
    let mut tuner = Tuner::new(cfg.clone()).unwrap();
    let recs = drive(&mut tuner, &mut Toy::new(&gates(), 41), usize::MAX);
    assert!(recs[..10]
        .iter()
        .all(|r| r.parameters[0].target == Some(20.0)));
    assert!(recs[10..]
        .iter()
        .all(|r| r.parameters[0].target == Some(30.0)));
    assert!(
        recs[10..].iter().any(|r| r.tuned),
        "did not reach the scheduled target"
    );
    cfg.schedule[0].targets.insert("nope".into(), 1.0);
    assert_eq!(
        Tuner::new(cfg).unwrap_err().field,
        "schedule[0].targets.nope"
    );
}

/// Several limited moves per iteration: every move is its own guarded set
/// request within the step limit, followed by the lower levels, each charged
/// its lab time; w and t_sr are measured once per iteration, before the moves.
#[test]
fn multi_move_iteration_charges_every_move_and_no_move_bypasses_safety() {
    multi_move_iteration(true);
}

/// As above, the lower levels only after the last move of an iteration: the
/// intermediate moves are bare set requests, still guarded and charged.
#[test]
fn bare_multi_move_iteration_runs_lower_levels_once_per_iteration() {
    multi_move_iteration(false);
}

fn multi_move_iteration(lower_levels_between_moves: bool) {
    use crate::solver::StepRule;
    let mut cfg = hierarchical();
    let max_step_mv = 3.0;
    let LevelKind::Newton(q) = &mut cfg.levels[0].kind else {
        unreachable!()
    };
    q.solver = SolverConfig {
        max_step_mv,
        rule: StepRule::ExpectedCost,
        max_moves_per_iteration: 3,
        lower_levels_between_moves,
        ..SolverConfig::default()
    };
    // a tight gate limit the moves run into
    cfg.gates[0].max_mv = 6.0;
    cfg.max_iterations = Some(12);
    let top_gates = ["N", "SA", "SB", "T"];
    let mut tuner = Tuner::new(cfg).unwrap();
    let mut dev = Toy::new(&gates(), 3);
    let mut charged_s = 0.0;
    let mut records = 0;
    // per iteration: top moves, and (kind, index) of every request
    let mut moves_this_iteration = 0;
    let mut most_moves = 0;
    let mut since_top_move: Vec<ScanKind> = Vec::new();
    let mut parameter_scan_after_move = false;
    let mut moved_this_iteration = false;
    let mut total_top_moves = 0;
    for _ in 0..100_000 {
        match tuner.poll() {
            Action::Request(req) => {
                match &req {
                    Request::SetVoltages { voltages_mv } => {
                        tuner
                            .safety()
                            .check(&dev.v, voltages_mv)
                            .expect("tuner emitted an unsafe request");
                        let norm = top_gates
                            .iter()
                            .filter_map(|g| Some((voltages_mv.get(*g)? - dev.v[*g]).powi(2)))
                            .sum::<f64>()
                            .sqrt();
                        // (the initial finite differences, iteration 0, step between offsets)
                        assert!(
                            records == 0 || norm <= max_step_mv * (1.0 + 1e-9),
                            "move of {norm} mV"
                        );
                        assert!(voltages_mv.get("N").is_none_or(|&v| v <= 6.0));
                        if norm > 1e-9 && records > 0 {
                            // the lower levels ran since the previous top move
                            if moved_this_iteration {
                                // the lower levels ran since the previous move, or not at all
                                assert_eq!(
                                    since_top_move.contains(&ScanKind::SensingDot),
                                    lower_levels_between_moves
                                );
                                assert_eq!(
                                    since_top_move.contains(&ScanKind::ChemicalPotential),
                                    lower_levels_between_moves
                                );
                            }
                            since_top_move.clear();
                            moves_this_iteration += 1;
                            total_top_moves += 1;
                            moved_this_iteration = true;
                        }
                    }
                    Request::Measure { scan } => {
                        since_top_move.push(scan.kind);
                        if moved_this_iteration
                            && matches!(scan.kind, ScanKind::ReloadTime | ScanKind::TransitionWidth)
                        {
                            parameter_scan_after_move = true;
                        }
                    }
                    _ => {}
                }
                let resp = dev.execute(&req);
                if let Response::VoltagesSet { lab_seconds, .. }
                | Response::Scanned { lab_seconds, .. } = &resp
                {
                    charged_s += lab_seconds;
                }
                tuner.feed(resp).unwrap();
            }
            Action::Iteration(_) => {
                if moved_this_iteration {
                    // the lower levels always follow the last move
                    assert!(since_top_move.contains(&ScanKind::SensingDot));
                    assert!(since_top_move.contains(&ScanKind::ChemicalPotential));
                }
                records += 1;
                most_moves = most_moves.max(moves_this_iteration);
                moves_this_iteration = 0;
                moved_this_iteration = false;
            }
            Action::Finished => break,
        }
    }
    assert_eq!(records, 12);
    assert!(
        most_moves >= 2,
        "never more than {most_moves} move per iteration"
    );
    assert!(most_moves <= 3);
    assert!(total_top_moves > records - 1);
    // w and t_sr are measured only at the start of an iteration, before its moves
    assert!(!parameter_scan_after_move);
    // every request's lab time, moves included, is on the tuner's clock
    assert!((tuner.lab_seconds() - charged_s).abs() < 1e-9);
}

#[test]
fn central_finite_differences_cancel_the_curvature_and_stay_within_a_step() {
    // ∂p_a/∂N at the start (every gate at 0): −40/60 ns/mV exactly; a
    // one-sided 3 mV difference reads (40·e^(−0.05) − 40)/3 = −0.6503, the
    // central one (40·e^(−0.05) − 40·e^(0.05))/6 = −0.66694
    let exact = -40.0 / 60.0;
    let first_gradient = |central: bool| {
        let mut cfg = flat(EstimatorKind::FixedJacobian);
        if let LevelKind::Newton(n) = &mut cfg.levels[0].kind {
            n.initial_gradient = InitialGradient::FiniteDifference {
                step_mv: 3.0,
                repetitions: 1,
                recentre_between_offsets: false,
                central,
                mirrored: Vec::new(),
            };
        }
        let mut tuner = Tuner::new(cfg).unwrap();
        let mut dev = Toy::new(&gates(), 11);
        dev.sigma = [1e-6, 1e-6];
        // `drive` checks every set against the gates' limits and steps
        let recs = drive(&mut tuner, &mut dev, 1);
        let sets = dev.log.iter().filter(|l| l.starts_with("set")).count();
        (
            recs[0].gradients[0].gradient[0],
            recs[0].scan_counts[&ScanKind::ReloadTime],
            sets,
        )
    };
    let (one_sided, one_sided_scans, one_sided_sets) = first_gradient(false);
    let (central, central_scans, central_sets) = first_gradient(true);
    assert!((one_sided - exact).abs() > 0.01, "{one_sided}");
    assert!((central - exact).abs() < 1e-3, "{central}");
    // a base and 4 offsets, against a base and 8 offsets
    assert_eq!(central_scans, one_sided_scans + 4);
    // 3·√2 mV between consecutive offsets is within the 10 mV step: no
    // return to the base between them (4 more sets, one per offset)
    assert_eq!(central_sets, one_sided_sets + 4);
}

/// Bounded by construction: the initial repetitions (each keeps its
/// points) are at most `MAX_FD_REPETITIONS`, and `mirrored` has at most one
/// entry per repetition; the error names the field.
#[test]
fn finite_difference_repetitions_and_mirrors_are_bounded() {
    let with = |reps: u32, mirrored: Vec<bool>| {
        let mut cfg = flat(EstimatorKind::Kalman);
        if let LevelKind::Newton(n) = &mut cfg.levels[0].kind {
            n.initial_gradient = InitialGradient::FiniteDifference {
                step_mv: 3.0,
                repetitions: reps,
                recentre_between_offsets: false,
                central: true,
                mirrored,
            };
        }
        Tuner::new(cfg).err().map(|e| e.to_string())
    };
    assert_eq!(with(2, vec![false, true]), None);
    let too_many = with(super::config::MAX_FD_REPETITIONS + 1, Vec::new()).unwrap();
    assert!(too_many.contains("repetitions"), "{too_many}");
    let mirrors = with(1, vec![false, true]).unwrap();
    assert!(mirrors.contains("mirrored"), "{mirrors}");
}
