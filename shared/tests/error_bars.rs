//! Error bars that hold over the operating range: at each of the paper's
//! four set points, 300 repeated simulated scans (each on a fresh seed) must
//! put the true value within the reported 1σ in 60–76 % of the cases (68 %
//! expected; with 300 scans the binomial standard error is 2.7 points).
//!
//! The test moves the device to each set point with the simulator's true
//! Jacobian (the test is the oracle here, not a strategy) and keeps the
//! transition lines centred and the sensing dot on its flank, as the
//! tuner's lower levels do.

use nalgebra::DVector;
use spintune::fit::evaluate_with;
use spintune::fit::uncertainty::SIMULATED_DEVICE_REFERENCES;
use spintune::protocol::{RawScan, Request, Response, ScanKind, ScanOutcome, ScanRequest};
use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice, SlowDrift};

/// The default device without the slow drift of t_c and Γ: this test is
/// about one scan's error bar at a fixed device state.
fn device_config() -> DeviceConfig {
    let mut c = DeviceConfig::default();
    c.noise.slow = SlowDrift::none();
    c
}

fn set(dev: &mut SimulatedDevice, gate: &str, mv: f64) {
    let r = dev.execute(&Request::SetVoltages {
        voltages_mv: [(gate.to_string(), mv)].into(),
    });
    assert!(matches!(r, Response::VoltagesSet { .. }), "{r:?}");
}

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

/// Gate voltages (mV) where the noiseless device has `t_sr_ns`, `w_uv`,
/// centred lines and the sensing dot on its flank.
fn set_point_voltages(t_sr_ns: f64, w_uv: f64) -> Vec<(String, f64)> {
    let mut dev = SimulatedDevice::new(device_config(), &default_gates(), 0).unwrap();
    let gates = ["N", "SA", "SB", "T", "PA", "PB"];
    let params = ["t_sr", "w", "mu_a_mv", "mu_b_mv"];
    for _ in 0..40 {
        let t = dev.truth();
        let r = DVector::from_vec(vec![
            t.t_sr_ns - t_sr_ns,
            t.w_uv - w_uv,
            t.mu_a_mv,
            t.mu_b_mv,
        ]);
        let j = dev.true_jacobian(&gates, &params).unwrap();
        let dv = j.pseudo_inverse(1e-12).unwrap() * r;
        for (i, g) in gates.iter().enumerate() {
            let v = dev.voltages_mv()[*g] - dv[i].clamp(-5.0, 5.0);
            set(&mut dev, g, v);
        }
        let flank = dev.truth().sd_flank_mv;
        set(&mut dev, "SD1", flank);
    }
    let t = dev.truth();
    assert!((t.t_sr_ns / t_sr_ns - 1.0).abs() < 1e-6 && (t.w_uv / w_uv - 1.0).abs() < 1e-6);
    assert!(t.mu_a_mv.abs() < 1e-6 && t.mu_b_mv.abs() < 1e-6 && t.sd_contrast > 0.99);
    dev.voltages_mv()
        .iter()
        .map(|(g, v)| (g.clone(), *v))
        .collect()
}

/// Fraction of `scans` fits of `kind` whose 1σ contains the truth.
fn coverage(voltages: &[(String, f64)], kind: ScanKind, name: &str, scans: u64) -> f64 {
    let (mut inside, mut fitted) = (0usize, 0usize);
    for seed in 0..scans {
        let mut dev = SimulatedDevice::new(device_config(), &default_gates(), 1000 + seed).unwrap();
        for (g, v) in voltages {
            set(&mut dev, g, *v);
        }
        let truth = dev.truth().get(name).unwrap();
        if let Ok(e) = evaluate_with(&measure(&mut dev, kind), &SIMULATED_DEVICE_REFERENCES) {
            let v = e.values.iter().find(|v| v.name == name).unwrap();
            fitted += 1;
            inside += usize::from((v.value - truth).abs() <= v.variance.sqrt());
        }
    }
    assert!(
        fitted as u64 * 100 >= scans * 97,
        "{name}: {fitted}/{scans} fits"
    );
    inside as f64 / fitted as f64
}

#[test]
fn one_sigma_coverage_is_60_to_76_percent_at_each_paper_set_point() {
    let mut report = Vec::new();
    for (t_sr, w) in [(20.0, 180.0), (20.0, 270.0), (70.0, 180.0), (70.0, 270.0)] {
        let v = set_point_voltages(t_sr, w);
        for (kind, name) in [
            (ScanKind::ReloadTime, "t_sr"),
            (ScanKind::TransitionWidth, "w"),
        ] {
            let c = coverage(&v, kind, name, 300);
            report.push(format!("({t_sr} ns, {w} µV) {name}: {c:.3}"));
            assert!((0.60..=0.76).contains(&c), "{report:#?}");
        }
    }
    eprintln!("{report:#?}");
}
