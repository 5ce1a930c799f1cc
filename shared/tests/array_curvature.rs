//! Rows that learn how their gradient bends
//! (`JointConfig::curvature_prior_per_mv2`, `spintune::tuner::curvature`).
//!
//! One cell whose `w` follows `ln w = ln 200 + g·d + h_NN·d_N² + h_NT·d_N·d_T`
//! exactly (d: mV from where it first measured), measured precisely along a
//! walk of 2 mV steps that turns through every own gate. The true gradient
//! at the walk's end is `g + (2·h_NN·d_N + h_NT·d_T, 0, 0, h_NT·d_N)`,
//! derived by hand from that formula. A row with curvature ends near it and
//! predicts `w` far from the walk; a row without curvature, which can only
//! follow the bend through its process noise, ends further off. The bound
//! names its field.

use std::collections::BTreeMap;

use spintune::sim::array::gate_name;
use spintune::tuner::array::{CellKnowledge, JointArrayTuner, JointConfig};

const GATES: [&str; 4] = ["N", "SA", "SB", "T"];
const G: [f64; 4] = [0.01, 0.02, -0.03, 0.005];
const H_NN: f64 = -3e-4;
const H_NT: f64 = 2e-4;

fn knowledge() -> CellKnowledge {
    CellKnowledge {
        gates: GATES.iter().map(|g| gate_name(0, g)).collect(),
        parameters: vec!["t_sr".into(), "w".into()],
        // the initial measurement: the gradient at the start, roughly
        gradient: vec![G.iter().map(|g| g * 1.1).collect(); 2],
        covariance: vec![
            (0..4)
                .map(|r| (0..4).map(|s| if r == s { 1e-5 } else { 0.0 }).collect())
                .collect();
            2
        ],
        process_noise_per_mv: vec![3e-4; 2],
        max_step_mv: 10.0,
        compensation: None,
        floors: Vec::new(),
    }
}

/// `ln w` and its true gradient at deviations `d` (N, SA, SB, T), mV.
fn truth(d: &[f64; 4]) -> (f64, [f64; 4]) {
    let y = 200f64.ln()
        + G.iter().zip(d).map(|(g, x)| g * x).sum::<f64>()
        + H_NN * d[0] * d[0]
        + H_NT * d[0] * d[3];
    let grad = [
        G[0] + 2.0 * H_NN * d[0] + H_NT * d[3],
        G[1],
        G[2],
        G[3] + H_NT * d[0],
    ];
    (y, grad)
}

fn voltages(d: &[f64; 4]) -> BTreeMap<String, f64> {
    GATES
        .iter()
        .zip(d)
        .map(|(g, x)| (gate_name(0, g), -700.0 + x))
        .collect()
}

/// Walk, learning `w` (σ 0.2 %), and return (the row's gradient error at
/// the end, 1/mV; the prediction's error 20 mV further along N and T, in
/// `ln w`).
fn learn(config: &JointConfig) -> (f64, f64) {
    let mut t = JointArrayTuner::new(vec![knowledge()], config, [0.0; 2]).unwrap();
    let mut d = [0.0; 4];
    let measure = |t: &mut JointArrayTuner, d: &[f64; 4]| {
        let w = truth(d).0.exp();
        t.observe(0, &[None, Some((w, (0.002 * w).powi(2)))], &voltages(d));
    };
    measure(&mut t, &d);
    // 2 mV steps turning through the gates, drifting along +N and −T
    let steps: [[f64; 4]; 6] = [
        [2.0, 0.0, 0.0, 0.0],
        [0.0, 2.0, 0.0, 0.0],
        [2.0, 0.0, 0.0, -2.0],
        [0.0, 0.0, 2.0, 0.0],
        [0.0, -2.0, 0.0, -2.0],
        [2.0, 0.0, -2.0, 0.0],
    ];
    for i in 0..60 {
        for (x, s) in d.iter_mut().zip(steps[i % steps.len()]) {
            *x += s;
        }
        measure(&mut t, &d);
    }
    let row: BTreeMap<String, f64> = t.row_gradient(0, 1).into_iter().collect();
    let (_, grad) = truth(&d);
    let error = GATES
        .iter()
        .zip(grad)
        .map(|(g, x)| (row[&gate_name(0, g)] - x).powi(2))
        .sum::<f64>()
        .sqrt();
    let far = [d[0] + 20.0, d[1], d[2], d[3] - 20.0];
    let (y, _) = t.predict(0, 1, &voltages(&far)).unwrap();
    (error, (y - truth(&far).0).abs())
}

#[test]
fn a_row_with_curvature_follows_a_bending_gradient() {
    let (flat, flat_far) = learn(&JointConfig::default());
    let (bent, bent_far) = learn(&JointConfig {
        curvature_prior_per_mv2: 1e-3,
        ..JointConfig::default()
    });
    // the walk ends ~40 mV along N from where it started: the true N
    // gradient has moved by ~0.03/mV from the start's
    assert!(bent < 0.003, "with curvature {bent}/mV off the truth");
    assert!(
        bent < 0.25 * flat,
        "with curvature {bent}/mV off, without {flat}/mV"
    );
    assert!(bent_far < 0.02, "prediction 20 mV on off by {bent_far}");
    assert!(bent_far < 0.25 * flat_far, "{bent_far} against {flat_far}");
}

#[test]
fn the_curvature_prior_is_bounded_and_named() {
    for c in [-1e-4, 0.1, f64::NAN] {
        let config = JointConfig {
            curvature_prior_per_mv2: c,
            ..JointConfig::default()
        };
        let err = JointArrayTuner::new(vec![knowledge()], &config, [0.0; 2]).unwrap_err();
        assert_eq!(err.field, "joint.curvature_prior_per_mv2");
    }
}
