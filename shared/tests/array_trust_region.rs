//! The joint step inside a trust region per cell
//! (`JointConfig::trust_region`, `tuner::block_trust_region`), seen through
//! `JointArrayTuner::plan_move`: every cell within its step limit, a model
//! residual no larger than the paper's scaled step leaves, the bound on the
//! covariance weight named, and a tuner saved before the option planning
//! with the paper's rule.

mod support;

use std::collections::BTreeMap;

use nalgebra::DVector;
use spintune::sim::array::gate_name;
use spintune::tuner::array::{CellKnowledge, JointArrayTuner, JointConfig};
use support::array::wide_limits;

const GATES: [&str; 4] = ["N", "SA", "SB", "T"];

/// A cell whose `t_sr` and `w` rows point nearly the same way over its own
/// gates (log space, 1/mV): the Newton step that moves one without the
/// other is long.
fn cell(c: u32) -> CellKnowledge {
    CellKnowledge {
        gates: GATES.iter().map(|g| gate_name(c, g)).collect(),
        parameters: vec!["t_sr".into(), "w".into()],
        gradient: vec![
            vec![0.02, 0.02, -0.03, 0.0],
            vec![0.02, 0.021, -0.03, 0.002],
        ],
        covariance: vec![
            (0..4)
                .map(|r| (0..4).map(|s| if r == s { 1e-6 } else { 0.0 }).collect())
                .collect();
            2
        ],
        process_noise_per_mv: vec![0.003; 2],
        max_step_mv: 10.0,
        compensation: None,
        floors: Vec::new(),
    }
}

fn tuner(config: &JointConfig) -> JointArrayTuner {
    JointArrayTuner::new((0..3).map(cell).collect(), config, [0.3, 0.05]).unwrap()
}

/// The move as one vector over every gate (0 where a gate stays), mV.
fn as_vector(t: &JointArrayTuner, planned: &BTreeMap<String, f64>) -> DVector<f64> {
    DVector::from_iterator(
        t.gates().len(),
        t.gates()
            .iter()
            .map(|g| planned.get(g).copied().unwrap_or(0.0)),
    )
}

/// Cell 0 far off in `w` only (ln residual −0.5: the rows' near-parallel
/// difference needs a move far beyond 10 mV), cell 1 a little off, cell 2
/// held.
fn residual() -> Vec<Vec<Option<f64>>> {
    vec![
        vec![Some(0.0), Some(-0.5)],
        vec![Some(0.05), Some(0.0)],
        vec![Some(0.0), Some(0.0)],
    ]
}

/// What the linear model says is left of `residual` after `dv`:
/// `‖Δ + J·Δv‖` over the rows with a residual (every row here).
fn left(t: &JointArrayTuner, dv: &DVector<f64>) -> f64 {
    let delta = DVector::from_iterator(6, residual().into_iter().flatten().map(|r| r.unwrap()));
    (delta + t.jacobian() * dv).norm()
}

#[test]
fn every_cell_stays_within_its_limit_and_the_model_residual_falls_further() {
    let paper = tuner(&JointConfig {
        trust_region: false,
        excitation: 0.0,
        ..JointConfig::default()
    });
    let plain = tuner(&JointConfig {
        trust_region_covariance: 0.0,
        excitation: 0.0,
        ..JointConfig::default()
    });
    let gates = paper.gates().to_vec();
    let v: BTreeMap<String, f64> = gates.iter().map(|g| (g.clone(), 0.0)).collect();
    let limits = wide_limits(&gates);
    let scaled = as_vector(
        &paper,
        &paper.plan_move(&residual(), &paper.jacobian(), &v, &limits),
    );
    let damped = as_vector(
        &plain,
        &plain.plan_move(&residual(), &plain.jacobian(), &v, &limits),
    );
    for c in 0..3 {
        for dv in [&scaled, &damped] {
            assert!(dv.rows(4 * c, 4).norm() <= 10.0 + 1e-9, "cell {c}: {dv}");
        }
    }
    // cell 0 is limited by both rules
    assert!((scaled.rows(0, 4).norm() - 10.0).abs() < 1e-9);
    assert!((damped.rows(0, 4).norm() - 10.0).abs() < 1e-6);
    // the scaled Newton step spends cell 0's 10 mV mostly on the long
    // direction; the trust-region step leaves less of the residual
    let (by_scaling, by_trust_region) = (left(&paper, &scaled), left(&plain, &damped));
    assert!(
        by_trust_region < 0.9 * by_scaling,
        "left {by_trust_region} with the trust region, {by_scaling} scaled"
    );
}

#[test]
fn the_covariance_weight_is_bounded_and_named() {
    for k in [-0.1, 10.5, f64::NAN] {
        let config = JointConfig {
            trust_region_covariance: k,
            ..JointConfig::default()
        };
        let err = JointArrayTuner::new(vec![cell(0)], &config, [0.0; 2]).unwrap_err();
        assert_eq!(err.field, "joint.trust_region_covariance", "{k}");
    }
    // on by default, and a settings file may turn it off by name
    let config = JointConfig::default();
    assert!(config.trust_region && config.trust_region_covariance == 0.5);
    let off: JointConfig = serde_json::from_value(serde_json::json!({
        "radius": 1, "neighbour_prior_fraction": 0.1, "outlier_sigma": 5.0,
        "min_step_mv": 0.01, "trust_region": false
    }))
    .unwrap();
    assert!(!off.trust_region);
}

#[test]
fn a_tuner_saved_before_the_trust_region_plans_with_the_paper_s_rule() {
    let paper = tuner(&JointConfig {
        trust_region: false,
        ..JointConfig::default()
    });
    let now = tuner(&JointConfig::default());
    let mut saved = serde_json::to_value(&now).unwrap();
    let fields = saved.as_object_mut().unwrap();
    assert!(fields.remove("trust_region").is_some());
    assert!(fields.remove("trust_region_covariance").is_some());
    let old: JointArrayTuner = serde_json::from_value(saved).unwrap();
    let gates = paper.gates().to_vec();
    let v: BTreeMap<String, f64> = gates.iter().map(|g| (g.clone(), 0.0)).collect();
    let limits = wide_limits(&gates);
    let plan = |t: &JointArrayTuner| t.plan_move(&residual(), &t.jacobian(), &v, &limits);
    assert_eq!(plan(&old), plan(&paper));
    assert_ne!(plan(&now), plan(&paper));
}

/// `JointConfig::widened_row_explores`: a widened row's covariance stays
/// out of the step's uncertainty term for that many of its measurements,
/// then counts again. With every row widened and left out, the step is the
/// plain trust region's (`κ = 0`); once the count is used up it is the
/// step of a tuner that never left them out.
#[test]
fn a_widened_row_is_left_out_of_the_step_s_uncertainty_for_its_explores() {
    let uncertain = |c: u32| {
        let mut k = cell(c);
        for cov in &mut k.covariance {
            for (r, row) in cov.iter_mut().enumerate() {
                row[r] = 1e-4;
            }
        }
        k
    };
    let make = |config: JointConfig| {
        let mut t = JointArrayTuner::new(
            (0..3).map(uncertain).collect(),
            &JointConfig {
                excitation: 0.0,
                ..config
            },
            [0.3, 0.05],
        )
        .unwrap();
        for c in 0..3 {
            for p in 0..2 {
                assert!(t.widen_row(c, p));
            }
        }
        t
    };
    let mut explore = make(JointConfig {
        widened_row_explores: 2,
        ..JointConfig::default()
    });
    let mut counted = make(JointConfig::default());
    let mut plain = make(JointConfig {
        trust_region_covariance: 0.0,
        ..JointConfig::default()
    });
    let gates = explore.gates().to_vec();
    let v: BTreeMap<String, f64> = gates.iter().map(|g| (g.clone(), 0.0)).collect();
    let limits = wide_limits(&gates);
    let plan =
        |t: &JointArrayTuner| as_vector(t, &t.plan_move(&residual(), &t.jacobian(), &v, &limits));
    let close = |a: &DVector<f64>, b: &DVector<f64>| (a - b).norm() <= 1e-9 * b.norm().max(1.0);
    // the widened covariance shortens the counted step measurably
    assert!(
        (plan(&counted) - plan(&plain)).norm() > 1e-3,
        "{}",
        plan(&counted)
    );
    for seen in 0..=2 {
        let (e, c, p) = (plan(&explore), plan(&counted), plan(&plain));
        if seen < 2 {
            assert!(
                close(&e, &p),
                "after {seen} measurements: {e} against κ = 0's {p}"
            );
        } else {
            assert!(close(&e, &c), "after {seen} measurements: {e} against {c}");
            assert!(!close(&e, &p));
        }
        // one measurement of every cell (the same in each tuner)
        for t in [&mut explore, &mut counted, &mut plain] {
            for cell in 0..3 {
                t.observe(cell, &[Some((20.0, 0.25)), Some((250.0, 100.0))], &v);
            }
        }
    }
    // bounded and named
    let err = JointArrayTuner::new(
        vec![cell(0)],
        &JointConfig {
            widened_row_explores: 31,
            ..JointConfig::default()
        },
        [0.0; 2],
    )
    .unwrap_err();
    assert_eq!(err.field, "joint.widened_row_explores");
}
