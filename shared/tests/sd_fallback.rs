//! The 2-D sensing-dot fallback: when the 1-D sweep of the sensing gate
//! finds no flank, the tuner rasters the second gate and parks on the first
//! flank it finds (instead of carrying on blind).

use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::tuner::LevelKind;

/// Sparse Coulomb peaks (40 mV apart) and the sensing gate parked 25 mV off
/// the flank: the ±10 mV sweep sees no peak.
fn lost_sensor(fallback: bool) -> SimulationRun {
    let mut cfg = SimulationConfig::paper_default();
    cfg.seed = 2;
    cfg.device.sensing_dot.peak_spacing_mv = 40.0;
    cfg.device.noise.charge_jump_rate_per_s = 0.0;
    cfg.tuner.max_iterations = Some(0);
    if !fallback {
        for l in &mut cfg.tuner.levels {
            if let LevelKind::SensingDot(sd) = &mut l.kind {
                sd.fallback = None;
            }
        }
    }
    // the gate starts there (the device's reference stays on the flank)
    let sd1 = cfg
        .tuner
        .gates
        .iter_mut()
        .find(|g| g.name == "SD1")
        .unwrap();
    sd1.initial_mv += 25.0;
    let run = SimulationRun::new(cfg).unwrap();
    assert!(run.device().truth().sd_contrast < 0.01);
    run
}

#[test]
fn a_sweep_without_flank_falls_back_to_a_raster_of_the_second_gate_and_parks() {
    let mut with = lost_sensor(true);
    let mut without = lost_sensor(false);
    for run in [&mut with, &mut without] {
        while run.next_iteration().unwrap().is_some() {}
    }
    // without the fallback the sensor stays lost
    assert!(without.device().truth().sd_contrast < 0.2);
    // with it, the sensor is back on a steep flank and SP moved
    let t = with.device().truth();
    assert!(t.sd_contrast > 0.8, "{t:?}");
    assert_ne!(with.device().voltages_mv()["SP"], -500.0);
    // a lost sensor spoils every later scan: the raster (each sweep charged
    // by the device) pays for itself in failed evaluations and lab time
    assert!(with.tuner().failed_evaluations() < without.tuner().failed_evaluations());
    assert!(with.tuner().lab_seconds() < without.tuner().lab_seconds());
}
