//! The full hierarchy (sensing dot → chemical potentials → w, t_sr) on the
//! default simulated device reaches the paper's first target from the
//! documented start point, within limits, and checkpoints bit-identically.

use spintune::driver::{SimulationConfig, SimulationRun, PAPER_FIRST_TARGET};
use spintune::protocol::IterationRecord;

fn run(seed: u64, iterations: u64) -> (SimulationRun, Vec<IterationRecord>) {
    let mut cfg = SimulationConfig::paper_default();
    cfg.seed = seed;
    cfg.tuner.max_iterations = Some(iterations);
    let mut run = SimulationRun::new(cfg).unwrap();
    let mut recs = Vec::new();
    // SimulationRun refuses (with an error) any request outside the safety limits.
    while let Some(r) = run
        .next_iteration()
        .expect("no safety refusal, no device error")
    {
        recs.push(r);
    }
    (run, recs)
}

#[test]
fn reaches_first_target_within_limits() {
    let (t_sr, w) = PAPER_FIRST_TARGET;
    for seed in [1, 2, 3] {
        let (run, recs) = run(seed, 14);
        let first = recs.iter().position(|r| r.tuned);
        let k = first.unwrap_or_else(|| panic!("seed {seed}: never tuned; last {:?}", recs.last()));
        assert!(k <= 12, "seed {seed}: tuned only at iteration {k}");
        let r = &recs[k];
        let val = |n: &str| {
            r.parameters
                .iter()
                .find(|p| p.name == n)
                .unwrap()
                .value
                .unwrap()
        };
        assert!((val("t_sr") - t_sr).abs() <= 0.1 * t_sr);
        assert!((val("w") - w).abs() <= 0.1 * w);
        // the truth agrees (the measurement did not merely get lucky by much)
        let truth = run.device().truth();
        assert!(
            (truth.t_sr_ns - t_sr).abs() <= 0.2 * t_sr,
            "seed {seed}: {truth:?}"
        );
        assert!((truth.w_uv - w).abs() <= 0.2 * w, "seed {seed}: {truth:?}");
        for pair in recs.windows(2) {
            let norm: f64 = pair[0]
                .gates
                .iter()
                .map(|g| (pair[1].voltages_mv[g] - pair[0].voltages_mv[g]).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(norm <= 10.0 + 1e-9, "seed {seed}: step of {norm} mV");
        }
        let limits = run.tuner().safety();
        for r in &recs {
            for (g, v) in &r.voltages_mv {
                let spec = limits.gate(g).unwrap();
                assert!(*v >= spec.min_mv && *v <= spec.max_mv);
            }
        }
        // lab time is charged: minutes, not seconds
        assert!(recs[k].lab_seconds > 60.0);
    }
}

#[test]
fn checkpoint_resume_is_bit_identical_with_the_simulator() {
    let mut cfg = SimulationConfig::paper_default();
    cfg.seed = 5;
    let mut a = SimulationRun::new(cfg).unwrap();
    for _ in 0..3 {
        a.next_iteration().unwrap();
    }
    let saved = serde_json::to_string(&a).unwrap();
    let mut b: SimulationRun = serde_json::from_str(&saved).unwrap();
    for _ in 0..4 {
        assert_eq!(a.next_iteration().unwrap(), b.next_iteration().unwrap());
    }
    assert_eq!(
        serde_json::to_string(&a).unwrap(),
        serde_json::to_string(&b).unwrap()
    );
}

#[test]
fn config_round_trips_through_json_and_names_bad_fields() {
    let cfg = SimulationConfig::paper_default();
    let json = serde_json::to_string(&cfg).unwrap();
    let back: SimulationConfig = serde_json::from_str(&json).unwrap();
    assert_eq!(back, cfg);
    let mut bad = cfg.clone();
    bad.tuner.top_mut().solver.max_step_mv = -1.0;
    let e = bad.validate().unwrap_err();
    assert_eq!(e.field, "tuner.levels[0].solver.max_step_mv");
}
