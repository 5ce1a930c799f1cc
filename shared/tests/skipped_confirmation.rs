//! A lower level that skips its confirming scan (the line level of the
//! recommended config, `skip_confirmation_sigma = 2`) is right to: at every
//! skip, the simulator's truth (world side, with the drift the scans see)
//! has both transition lines inside the level's tolerance. And skipping is
//! not vacuous: it happens, and it saves line scans against the same run
//! that always confirms.

use spintune::driver::SimulationConfig;
use spintune::protocol::{Request, ScanKind};
use spintune::session::{Output, RunSession, SessionConfig};
use spintune::tuner::{LevelKind, Tuner};

struct Outcome {
    skips: u32,
    skips_in_band: u32,
    line_scans: u64,
    iterations: u64,
}

/// Drive the recommended config on `seed` for `iterations` top-level
/// iterations; a skip is a line-level correction (a set of PA/PB only)
/// whose sensing-dot re-tune (sweeps and parking sets of SD1/SP) is
/// followed by anything but a line scan.
fn drive(seed: u64, skip: Option<f64>, iterations: u64) -> Outcome {
    let mut cfg = SimulationConfig::recommended();
    cfg.seed = seed;
    cfg.tuner.max_iterations = Some(iterations);
    let idx = cfg.tuner.level_index("chemical_potential").unwrap();
    let tolerance_mv = match &mut cfg.tuner.levels[idx].kind {
        LevelKind::Newton(n) => {
            n.skip_confirmation_sigma = skip;
            // every call scans first (no forecast, `tests/line_forecast.rs`):
            // a correction without a line scan after it is a skipped confirmation
            n.forecast = None;
            n.parameters[0].tolerance.half_width(0.0)
        }
        LevelKind::SensingDot(_) => unreachable!(),
    };
    // the sensing dot sweeps at every call here (no predicted flank), so a
    // line correction's sensing-dot re-tune is always a sweep this test sees
    let sd = cfg.tuner.level_index("sensing_dot").unwrap();
    if let LevelKind::SensingDot(sd) = &mut cfg.tuner.levels[sd].kind {
        sd.prediction = None;
    }
    let mut device = cfg.simulated_device().unwrap();
    device.seal_truth();
    let mut session =
        RunSession::from_tuner(Tuner::new(cfg.tuner).unwrap(), SessionConfig::default());
    let (mut skips, mut in_band, mut iterations_done) = (0, 0, 0);
    // after a PA/PB-only set: 1 = waiting for the sensing-dot sweep, 2 = swept
    let mut after_correction = 0;
    loop {
        match session.poll() {
            Output::Execute(request) => {
                match &request {
                    // the sensing dot parks its gates (SD1, SP) between sweeps
                    Request::SetVoltages { voltages_mv }
                        if voltages_mv.keys().all(|g| g == "SD1" || g == "SP") => {}
                    Request::SetVoltages { voltages_mv } => {
                        let plungers_only = voltages_mv.keys().all(|g| g == "PA" || g == "PB");
                        if after_correction == 2 {
                            skips += 1;
                            let truth = device.truth();
                            let drift = device.drift();
                            let a = truth.mu_a_mv + drift.mu_a_mv;
                            let b = truth.mu_b_mv + drift.mu_b_mv;
                            if a.abs() <= tolerance_mv && b.abs() <= tolerance_mv {
                                in_band += 1;
                            }
                        }
                        after_correction = usize::from(plungers_only);
                    }
                    Request::Measure { scan } => {
                        after_correction = match (after_correction, scan.kind) {
                            (1, ScanKind::SensingDot) => 2,
                            (2, ScanKind::SensingDot) => 2,
                            (2, ScanKind::ChemicalPotential) => 0,
                            (2, _) => {
                                let truth = device.truth();
                                let drift = device.drift();
                                skips += 1;
                                let a = truth.mu_a_mv + drift.mu_a_mv;
                                let b = truth.mu_b_mv + drift.mu_b_mv;
                                if a.abs() <= tolerance_mv && b.abs() <= tolerance_mv {
                                    in_band += 1;
                                }
                                0
                            }
                            _ => 0,
                        };
                    }
                    _ => {}
                }
                let response = device.execute(&request);
                session.feed(response).unwrap();
            }
            Output::Commit(_) => iterations_done += 1,
            Output::Done(_) => break,
            Output::Wait => panic!("the run waits: {:?}", session.status()),
            Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
        }
    }
    Outcome {
        skips,
        skips_in_band: in_band,
        line_scans: session
            .tuner()
            .scan_counts()
            .get(&ScanKind::ChemicalPotential)
            .copied()
            .unwrap_or(0),
        iterations: iterations_done,
    }
}

#[test]
fn skipped_line_scans_were_in_band_and_save_scans() {
    let (mut skips, mut in_band, mut scans_skip, mut scans_confirm) = (0, 0, 0, 0);
    for seed in 1..=6 {
        let s = drive(seed, Some(2.0), 21);
        let c = drive(seed, None, 21);
        assert_eq!((s.iterations, c.iterations), (21, 21));
        skips += s.skips;
        in_band += s.skips_in_band;
        scans_skip += s.line_scans;
        scans_confirm += c.line_scans;
    }
    let summary = format!("{skips} skips, {in_band} truly in band; line scans {scans_skip} (skipping) vs {scans_confirm} (confirming)");
    assert!(skips >= 6, "{summary}");
    assert!(f64::from(in_band) >= 0.9 * f64::from(skips), "{summary}");
    eprintln!("{summary}");
    assert!(scans_skip < scans_confirm, "{summary}");
}
