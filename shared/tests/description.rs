//! The device description derives the paper's hierarchy (against the
//! hand-written `SimulationConfig::paper_default`, an independent statement
//! of the same levels).

use spintune::description::{
    DeviceDescription, RECOMMENDED_FD_STEP_MV, RECOMMENDED_RELATIVE_Q_PER_MV,
};
use spintune::driver::SimulationConfig;
use spintune::parameter::Transform;
use spintune::solver::StepRule;
use spintune::tuner::{
    FlankPrediction, InitialGradient, LevelKind, ParameterForecast, ParameterSearch,
};

/// The paper's device described in a few lines derives exactly the
/// paper's hierarchy with the recommended qubit strategy: every level
/// field that `paper_default` states by hand comes out the same but the
/// strategy's (and the line level's skipped confirmation, the sensing dot's
/// predicted flank).
#[test]
fn paper_device_derives_the_paper_hierarchy_with_the_recommended_strategy() {
    let derived = DeviceDescription::paper_device().tuner().unwrap();
    let mut paper = SimulationConfig::paper_default().tuner;
    let top = paper.top_mut();
    for p in &mut top.parameters {
        p.transform = Transform::Log;
        p.process_noise_per_mv = RECOMMENDED_RELATIVE_Q_PER_MV;
    }
    top.solver.rule = StepRule::ExpectedCost;
    top.solver.max_moves_per_iteration = 2;
    top.solver.lower_levels_between_moves = false;
    top.initial_gradient = InitialGradient::FiniteDifference {
        step_mv: RECOMMENDED_FD_STEP_MV,
        repetitions: 1,
        recentre_between_offsets: false,
        central: false,
        mirrored: Vec::new(),
    };
    top.fd_step_mv = RECOMMENDED_FD_STEP_MV;
    // the paper states its targets; a description leaves them to the run config
    for p in &mut top.parameters {
        p.target = None;
    }
    if let LevelKind::Newton(lines) = &mut paper.levels[1].kind {
        lines.skip_confirmation_sigma = Some(2.0);
        lines.forecast = Some(ParameterForecast::default());
        // lost lines are searched for: probes of the ±4 mV window's half-width
        lines.search = Some(ParameterSearch {
            step: 4.0,
            max_probes: 4,
            after_failures: 2,
            max_excursion_mv: 40.0,
        });
    }
    if let LevelKind::SensingDot(sd) = &mut paper.levels[2].kind {
        sd.prediction = Some(FlankPrediction::default());
    }
    assert_eq!(derived, paper);
}

/// A lab's sensing dot: a few lines derive a level that predicts its flank;
/// `always_sweep` gives the paper's rule; a bad prediction field is named.
#[test]
fn described_lines_are_forecast_unless_told_to_always_scan() {
    let text = |lines: &str| {
        format!(
            r#"{{
              "gates": [
                {{"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}},
                {{"name": "B2", "min_mv": -500, "max_mv": 0, "initial_mv": -250}},
                {{"name": "P1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}},
                {{"name": "P2", "min_mv": -500, "max_mv": 0, "initial_mv": -250}}
              ],
              "qubit": {{"gates": ["B1", "B2"]}},
              "lines": {lines}
            }}"#
        )
    };
    let line_level = |lines: &str| {
        let d: DeviceDescription = serde_json::from_str(&text(lines)).unwrap();
        d.tuner().map(|t| match &t.levels[1].kind {
            LevelKind::Newton(n) => n.forecast.clone(),
            LevelKind::SensingDot(_) => panic!("level 1 is the lines"),
        })
    };
    let plain = r#"{"gates": ["P1", "P2"]"#;
    assert_eq!(
        line_level(&format!("{plain}}}")).unwrap(),
        Some(ParameterForecast::default())
    );
    assert_eq!(
        line_level(&format!(r#"{plain}, "always_scan": true}}"#)).unwrap(),
        None
    );
    let tight = line_level(&format!(r#"{plain}, "forecast": {{"skip_std": 0.05}}}}"#)).unwrap();
    assert_eq!(tight.unwrap().skip_std, 0.05);
    let err = line_level(&format!(r#"{plain}, "forecast": {{"skip_std": 0}}}}"#)).unwrap_err();
    assert_eq!(err.field, "lines.forecast.skip_std");
    let err = line_level(&format!(r#"{plain}, "forecast": {{"max_skips": 1000}}}}"#)).unwrap_err();
    assert_eq!(err.field, "lines.forecast.max_skips");
    // lost lines: searched for by default, with the fields a lab sets named
    let search = |lines: &str| {
        let d: DeviceDescription = serde_json::from_str(&text(lines)).unwrap();
        d.tuner().map(|t| match &t.levels[1].kind {
            LevelKind::Newton(n) => n.search.clone(),
            LevelKind::SensingDot(_) => panic!("level 1 is the lines"),
        })
    };
    assert_eq!(
        search(&format!("{plain}}}")).unwrap(),
        Some(ParameterSearch::default())
    );
    assert_eq!(
        search(&format!(r#"{plain}, "search_lost_lines": false}}"#)).unwrap(),
        None
    );
    let wide = search(&format!(
        r#"{plain}, "search": {{"step": 3, "max_probes": 8}}}}"#
    ))
    .unwrap()
    .unwrap();
    assert_eq!(
        (wide.step, wide.max_probes, wide.after_failures),
        (3.0, 8, 2)
    );
    for (field, bad) in [
        ("step", "0"),
        ("max_probes", "17"),
        ("after_failures", "0"),
        ("max_excursion_mv", "1e9"),
    ] {
        let err = search(&format!(r#"{plain}, "search": {{"{field}": {bad}}}}}"#)).unwrap_err();
        assert_eq!(err.field, format!("lines.search.{field}"));
    }
    // the top level moves the qubit gates: it never searches
    let mut t = DeviceDescription::paper_device().tuner().unwrap();
    t.top_mut().search = Some(ParameterSearch::default());
    assert_eq!(t.validate().unwrap_err().field, "levels[0].search");
    // the top level always measures
    let mut t = DeviceDescription::paper_device().tuner().unwrap();
    t.top_mut().forecast = Some(ParameterForecast::default());
    assert_eq!(t.validate().unwrap_err().field, "levels[0].forecast");
}

#[test]
fn a_described_sensing_dot_predicts_its_flank_unless_told_to_always_sweep() {
    let text = |sd: &str| {
        format!(
            r#"{{
              "gates": [
                {{"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}},
                {{"name": "B2", "min_mv": -500, "max_mv": 0, "initial_mv": -250}},
                {{"name": "SD", "min_mv": -900, "max_mv": -300, "initial_mv": -600, "max_step_mv": 30}}
              ],
              "qubit": {{"gates": ["B1", "B2"]}},
              "sensing_dot": {sd}
            }}"#
        )
    };
    let sd_level = |sd: &str| {
        let d: DeviceDescription = serde_json::from_str(&text(sd)).unwrap();
        d.tuner().map(|t| match &t.levels[1].kind {
            LevelKind::SensingDot(s) => s.prediction.clone(),
            LevelKind::Newton(_) => panic!("level 1 is the sensing dot"),
        })
    };
    assert_eq!(
        sd_level(r#"{"gate": "SD"}"#).unwrap(),
        Some(FlankPrediction::default())
    );
    assert_eq!(
        sd_level(r#"{"gate": "SD", "always_sweep": true}"#).unwrap(),
        None
    );
    let tight = sd_level(r#"{"gate": "SD", "prediction": {"skip_std_mv": 0.1}}"#).unwrap();
    assert_eq!(tight.unwrap().skip_std_mv, 0.1);
    let err = sd_level(r#"{"gate": "SD", "prediction": {"skip_std_mv": -1}}"#).unwrap_err();
    assert_eq!(err.field, "sensing_dot.prediction.skip_std_mv");
    let err = sd_level(r#"{"gate": "SD", "prediction": {"max_skips": 1000}}"#).unwrap_err();
    assert_eq!(err.field, "sensing_dot.prediction.max_skips");
}
