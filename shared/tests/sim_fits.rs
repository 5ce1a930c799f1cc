//! Fits against the simulator: coverage of the uncertainty rule, charge
//! jumps, noiseless exactness, calibration constants.

use spintune::fit::uncertainty::SIMULATED_DEVICE_REFERENCES;
use spintune::fit::{evaluate_with, Evaluation, FitError};
use spintune::protocol::{RawScan, Request, Response, ScanKind, ScanOutcome, ScanRequest};
use spintune::sim::{calibrate_reference, default_gates, DeviceConfig, SimulatedDevice};

fn measure(dev: &mut SimulatedDevice, kind: ScanKind) -> RawScan {
    match dev.execute(&Request::Measure {
        scan: ScanRequest {
            kind,
            sweep: None,
            cell: None,
        },
    }) {
        Response::Scanned {
            outcome: ScanOutcome::Raw { scan },
            ..
        } => scan,
        other => panic!("{kind:?}: {other:?}"),
    }
}

/// These scans come from the default simulated device, so its calibration applies.
fn evaluate(scan: &RawScan) -> Result<Evaluation, FitError> {
    evaluate_with(scan, &SIMULATED_DEVICE_REFERENCES)
}

fn value(e: &Evaluation, name: &str) -> (f64, f64) {
    let v = e.values.iter().find(|v| v.name == name).unwrap();
    (v.value, v.variance.sqrt())
}

#[test]
fn one_sigma_coverage_of_w_and_t_sr() {
    let (mut inside_w, mut inside_t, mut n_w, mut n_t) = (0, 0, 0, 0);
    for seed in 0..300 {
        let mut dev =
            SimulatedDevice::new(DeviceConfig::default(), &default_gates(), seed).unwrap();
        let truth = dev.truth();
        if let Ok(e) = evaluate(&measure(&mut dev, ScanKind::TransitionWidth)) {
            let (w, dw) = value(&e, "w");
            n_w += 1;
            inside_w += usize::from((w - truth.w_uv).abs() <= dw);
        }
        if let Ok(e) = evaluate(&measure(&mut dev, ScanKind::ReloadTime)) {
            let (t, dt) = value(&e, "t_sr");
            n_t += 1;
            inside_t += usize::from((t - truth.t_sr_ns).abs() <= dt);
        }
    }
    assert!(
        n_w >= 295 && n_t >= 295,
        "too many failed fits: {n_w}, {n_t}"
    );
    let (fw, ft) = (inside_w as f64 / n_w as f64, inside_t as f64 / n_t as f64);
    assert!((0.55..=0.80).contains(&fw), "w coverage {fw}");
    assert!((0.55..=0.80).contains(&ft), "t_sr coverage {ft}");
}

#[test]
fn reference_constants_match_calibration() {
    let r = calibrate_reference(&DeviceConfig::default(), &default_gates(), 2024, 400).unwrap();
    let d = SIMULATED_DEVICE_REFERENCES;
    for (name, a, b) in [
        ("w.sigma0", d.w.sigma0, r.w.sigma0),
        ("w.delta_p0", d.w.delta_p0, r.w.delta_p0),
        ("t_sr.sigma0", d.t_sr.sigma0, r.t_sr.sigma0),
        ("t_sr.delta_p0", d.t_sr.delta_p0, r.t_sr.delta_p0),
        ("w.relative_floor", d.w.relative_floor, r.w.relative_floor),
        (
            "t_sr.relative_floor",
            d.t_sr.relative_floor,
            r.t_sr.relative_floor,
        ),
    ] {
        assert!(
            (a / b - 1.0).abs() < 0.01,
            "{name}: constant {a} vs calibrated {b}"
        );
    }
    // Another seed gives the same physics within sampling error.
    let r2 = calibrate_reference(&DeviceConfig::default(), &default_gates(), 7, 200).unwrap();
    assert!((r2.w.delta_p0 / r.w.delta_p0 - 1.0).abs() < 0.25);
    assert!((r2.t_sr.delta_p0 / r.t_sr.delta_p0 - 1.0).abs() < 0.25);
}

/// A charge jump in the middle of a scan yields an error or a variance far
/// above the reference (never a confident wrong value).
#[test]
fn charge_jumps_fail_or_inflate_the_variance() {
    let mut config = DeviceConfig::default();
    config.noise.charge_jump_rate_per_s = 0.05;
    config.noise.charge_jump_sd_mv = 1.0;
    // charge jumps only: t_c and Γ stay put while the truth is compared
    config.noise.slow = spintune::sim::SlowDrift::none();
    let mut checked = 0;
    for seed in 0..60 {
        let mut dev = SimulatedDevice::new(config.clone(), &default_gates(), seed).unwrap();
        for (kind, name, delta0) in [
            (
                ScanKind::TransitionWidth,
                "w",
                SIMULATED_DEVICE_REFERENCES.w.delta_p0,
            ),
            (
                ScanKind::ReloadTime,
                "t_sr",
                SIMULATED_DEVICE_REFERENCES.t_sr.delta_p0,
            ),
        ] {
            let before = dev.drift().clone();
            let truth = dev.truth();
            let scan = measure(&mut dev, kind);
            let jumped = (dev.drift().jump_u_mv - before.jump_u_mv).abs();
            if dev.drift().jumps == before.jumps + 1 && jumped > 0.3 {
                checked += 1;
                match evaluate(&scan) {
                    Err(_) => {}
                    Ok(e) => {
                        let (v, d) = value(&e, name);
                        let true_v = truth.get(name).unwrap();
                        assert!(
                            d > 3.0 * delta0 || (v - true_v).abs() < 2.0 * d,
                            "{name}: jump of {jumped:.2} mV gave {v} ± {d} (truth {true_v})"
                        );
                    }
                }
            }
        }
    }
    assert!(checked >= 5, "only {checked} scans with a jump");
}

#[test]
fn noiseless_scans_give_the_exact_model_quantities() {
    for (t_c, gamma) in [(10.5, 1.0 / 45.0), (5.0, 1.0 / 15.0), (16.0, 1.0 / 90.0)] {
        let mut config = DeviceConfig::default();
        let n = &mut config.noise;
        (n.white_sd, n.white_mu, n.white_w, n.white_tsr) = (0.0, 0.0, 0.0, 0.0);
        (n.drift_mu_mv, n.drift_sd_mv, n.drift_signal) = (0.0, 0.0, 0.0);
        n.charge_jump_rate_per_s = 0.0;
        n.slow = spintune::sim::SlowDrift::none();
        config.tunnel_coupling_uev.at_reference = t_c;
        config.lead_rate_per_ns.at_reference = gamma;
        let mut dev = SimulatedDevice::new(config, &default_gates(), 1).unwrap();
        let truth = dev.truth();
        let w = evaluate(&measure(&mut dev, ScanKind::TransitionWidth)).unwrap();
        assert!(
            (value(&w, "w").0 - truth.w_uv).abs() < 1e-6,
            "{w:?} vs {truth:?}"
        );
        let t = evaluate(&measure(&mut dev, ScanKind::ReloadTime)).unwrap();
        assert!((value(&t, "t_sr").0 - truth.t_sr_ns).abs() < 1e-6);
        let mu = evaluate(&measure(&mut dev, ScanKind::ChemicalPotential)).unwrap();
        assert!(value(&mu, "mu_a_mv").0.abs() < 1e-6 && value(&mu, "mu_b_mv").0.abs() < 1e-6);
        let sd = evaluate(&measure(&mut dev, ScanKind::SensingDot)).unwrap();
        assert!((value(&sd, "sd_flank_mv").0 - truth.sd_flank_mv).abs() < 1e-4);
        assert!(
            (value(&sd, "sd_contrast").0 - truth.sd_contrast).abs() < 1e-3,
            "{sd:?} {truth:?}"
        );
    }
}

#[test]
fn poor_contrast_gives_large_variance_or_error() {
    let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 5).unwrap();
    // Detune the sensing dot: 0.6 mV off the flank towards the peak top.
    dev.execute(&Request::SetVoltages {
        voltages_mv: [("SD1".to_string(), -599.4)].into(),
    });
    let c = dev.truth().sd_contrast;
    assert!(c < 0.5, "contrast {c}");
    for _ in 0..10 {
        match evaluate(&measure(&mut dev, ScanKind::TransitionWidth)) {
            Err(FitError::BadData(_) | FitError::NotConverged(_)) => {}
            Err(e) => panic!("unexpected {e}"),
            Ok(e) => assert!(value(&e, "w").1 > 2.0 * SIMULATED_DEVICE_REFERENCES.w.delta_p0),
        }
    }
}

#[test]
fn off_centre_lines_degrade_the_width_scan() {
    let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 9).unwrap();
    // 5 mV on PA moves line A by ~4.5 mV: the step leaves the ±2 mV window.
    dev.execute(&Request::SetVoltages {
        voltages_mv: [("PA".to_string(), -295.0)].into(),
    });
    assert!(dev.truth().mu_a_mv > 4.0);
    // Each scan either fails or reports a variance far above the reference.
    for _ in 0..5 {
        if let Ok(e) = evaluate(&measure(&mut dev, ScanKind::TransitionWidth)) {
            let (w, dw) = value(&e, "w");
            assert!(
                dw > 10.0 * SIMULATED_DEVICE_REFERENCES.w.delta_p0,
                "{w} ± {dw}"
            );
        }
    }
}

#[test]
fn a_line_outside_the_window_leaves_the_other_line_s_value() {
    let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 9).unwrap();
    // line A 7 mV up, beyond the ±4 mV line scan; line B where it was
    dev.rearrange_charges([7.0, 0.0]);
    let e = evaluate(&measure(&mut dev, ScanKind::ChemicalPotential)).unwrap();
    assert_eq!(e.values.len(), 1);
    let (mu_b, _) = value(&e, "mu_b_mv");
    assert!(mu_b.abs() < 0.5, "mu_b {mu_b}");
    assert_eq!(e.missing.len(), 1);
    assert_eq!(e.missing[0].0, "mu_a_mv");
    assert_eq!(e.fit.len(), 1);
    // both lines out: the scan fails
    dev.rearrange_charges([0.0, -7.0]);
    assert!(evaluate(&measure(&mut dev, ScanKind::ChemicalPotential)).is_err());
}
