//! Physics of the simulated device: Jacobian, nonlinearity, reachability,
//! virtual gates, sensing dot, lab clock, errors.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use spintune::protocol::{Request, Response, ScanKind, ScanOutcome, ScanRequest, Sweep};
use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};

const TUNING: [&str; 4] = ["N", "SA", "SB", "T"];

fn device() -> SimulatedDevice {
    SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 11).unwrap()
}

fn set(dev: &mut SimulatedDevice, v: &[(&str, f64)]) -> Response {
    dev.execute(&Request::SetVoltages {
        voltages_mv: v.iter().map(|(g, x)| (g.to_string(), *x)).collect(),
    })
}

/// Moves the tuning gates by `delta` from the start (no compensation).
fn at_offset(delta: [f64; 4]) -> SimulatedDevice {
    let mut dev = device();
    let start = dev.voltages_mv().clone();
    let v: Vec<(&str, f64)> = TUNING
        .iter()
        .zip(delta)
        .map(|(g, d)| (*g, start[*g] + d))
        .collect();
    assert!(matches!(set(&mut dev, &v), Response::VoltagesSet { .. }));
    dev
}

#[test]
fn start_point_is_as_documented() {
    let t = device().truth();
    assert!((t.t_sr_ns - 45.0).abs() < 1e-9);
    assert!((t.w_uv - 208.1).abs() < 1.0, "{t:?}");
    assert_eq!((t.mu_a_mv, t.mu_b_mv), (0.0, 0.0));
    assert!(t.sd_contrast > 0.999);
    assert!((t.sd_flank_mv - -600.0).abs() < 1e-9);
}

#[test]
fn jacobian_matches_finite_differences_of_truth() {
    let dev = at_offset([12.0, -7.0, 20.0, -15.0]);
    let params = ["w", "t_sr", "mu_a_mv", "mu_b_mv", "sd_flank_mv"];
    let gates = ["T", "N", "PA", "SB", "SA", "SD1"];
    let j = dev.true_jacobian(&gates, &params).unwrap();
    for (c, g) in gates.iter().enumerate() {
        let mut v = dev.voltages_mv().clone();
        let v0 = v[*g];
        let h = 0.5;
        let mut probe = |x: f64| {
            v.insert(g.to_string(), x);
            let mut d = dev.clone();
            let req: BTreeMap<String, f64> = v.clone();
            assert!(matches!(
                d.execute(&Request::SetVoltages { voltages_mv: req }),
                Response::VoltagesSet { .. }
            ));
            d.truth()
        };
        let (p, m) = (probe(v0 + h), probe(v0 - h));
        for (r, name) in params.iter().enumerate() {
            let fd = (p.get(name).unwrap() - m.get(name).unwrap()) / (2.0 * h);
            let tol = 1e-3 + 1e-2 * fd.abs();
            assert!(
                (j[(r, c)] - fd).abs() < tol,
                "d{name}/d{g}: {} vs {fd}",
                j[(r, c)]
            );
        }
    }
    // The request form returns the same numbers, rows and columns in order.
    let mut d = dev.clone();
    let Response::TrueJacobian { values, jacobian } = d.execute(&Request::TrueJacobian {
        gates: gates.iter().map(|s| s.to_string()).collect(),
        parameters: params.iter().map(|s| s.to_string()).collect(),
    }) else {
        panic!()
    };
    assert_eq!(values[1], dev.truth().t_sr_ns);
    for (r, row) in jacobian.iter().enumerate() {
        for (c, x) in row.iter().enumerate() {
            assert_eq!(*x, j[(r, c)]);
        }
    }
}

#[test]
fn gradients_vary_and_a_w_gradient_changes_sign_within_50_mv() {
    let corners: Vec<[f64; 4]> = (0..16)
        .map(|k| std::array::from_fn(|i| if k >> i & 1 == 1 { 50.0 } else { -50.0 }))
        .chain([[0.0; 4]])
        .collect();
    let js: Vec<DMatrix<f64>> = corners
        .iter()
        .map(|c| {
            at_offset(*c)
                .true_jacobian(&TUNING, &["w", "t_sr"])
                .unwrap()
        })
        .collect();
    let mut sign_change = false;
    let mut max_ratio: f64 = 0.0;
    for c in 0..4 {
        let col: Vec<f64> = js.iter().map(|j| j[(0, c)]).collect();
        sign_change |= col.iter().any(|x| *x > 0.0) && col.iter().any(|x| *x < 0.0);
        let t: Vec<f64> = js.iter().map(|j| j[(1, c)].abs()).collect();
        let ratio =
            t.iter().copied().fold(0.0, f64::max) / t.iter().copied().fold(f64::MAX, f64::min);
        max_ratio = max_ratio.max(ratio);
    }
    assert!(
        sign_change,
        "no dw/dV element changes sign over the ±50 mV box"
    );
    assert!(max_ratio > 3.0, "t_sr gradients change only by {max_ratio}");
}

/// Newton iteration with the true Jacobian (minimum-norm steps of ≤ 10 mV)
/// reaches every benchmark target from the start within ±100 mV.
#[test]
fn benchmark_targets_are_reachable() {
    for (t_sr, w) in [(20.0, 270.0), (70.0, 270.0), (70.0, 180.0), (20.0, 180.0)] {
        let mut dev = device();
        let start = dev.voltages_mv().clone();
        let mut reached = false;
        for _ in 0..80 {
            let truth = dev.truth();
            let r = DVector::from_vec(vec![truth.t_sr_ns - t_sr, truth.w_uv - w]);
            if r[0].abs() < 0.5 && r[1].abs() < 2.0 {
                reached = true;
                break;
            }
            let j = dev.true_jacobian(&TUNING, &["t_sr", "w"]).unwrap();
            let jt = j.transpose();
            let mut step = -(&jt * (&j * &jt).try_inverse().unwrap() * r);
            let big = step.amax();
            if big > 10.0 {
                step *= 10.0 / big;
            }
            let v: Vec<(&str, f64)> = TUNING
                .iter()
                .enumerate()
                .map(|(i, g)| (*g, dev.voltages_mv()[*g] + step[i]))
                .collect();
            assert!(matches!(set(&mut dev, &v), Response::VoltagesSet { .. }));
        }
        assert!(
            reached,
            "target ({t_sr}, {w}) not reached: {:?}",
            dev.truth()
        );
        for g in TUNING {
            assert!((dev.voltages_mv()[g] - start[g]).abs() < 100.0, "{g}");
        }
    }
    // Reachable ranges cover the paper's.
    let mut ranges = [(f64::MAX, f64::MIN); 2];
    for k in 0..81 {
        let d: [f64; 4] =
            std::array::from_fn(|i| [-50.0, 0.0, 50.0][(k / 3usize.pow(i as u32)) % 3]);
        let t = at_offset(d).truth();
        for (r, v) in ranges.iter_mut().zip([t.w_uv, t.t_sr_ns]) {
            *r = (r.0.min(v), r.1.max(v));
        }
    }
    assert!(
        ranges[0].0 < 150.0 && ranges[0].1 > 300.0,
        "w {:?}",
        ranges[0]
    );
    assert!(
        ranges[1].0 < 10.0 && ranges[1].1 > 100.0,
        "t_sr {:?}",
        ranges[1]
    );
}

#[test]
fn nominal_compensation_is_good_to_first_order_only() {
    let config = DeviceConfig::default();
    let m = config.nominal_compensation(&TUNING, &["PA", "PB"]);
    let compensated = |delta: [f64; 4]| {
        let mut dev = device();
        let start = dev.voltages_mv().clone();
        let mut v: Vec<(&str, f64)> = TUNING
            .iter()
            .zip(delta)
            .map(|(g, d)| (*g, start[*g] + d))
            .collect();
        for (p, row) in ["PA", "PB"].iter().zip(&m) {
            let dp: f64 = row.iter().zip(delta).map(|(a, b)| a * b).sum();
            v.push((p, start[*p] + dp));
        }
        set(&mut dev, &v);
        let t = dev.truth();
        t.mu_a_mv.abs().max(t.mu_b_mv.abs())
    };
    assert!(compensated([5.0, 3.0, 5.0, 2.0]) < 0.05);
    assert!(compensated([40.0, -30.0, 40.0, 30.0]) > 0.3);
    // Uncompensated, the same small step moves the lines by millivolts.
    let t = at_offset([5.0, 3.0, 5.0, 2.0]).truth();
    assert!(t.mu_a_mv.abs() > 1.0);
}

#[test]
fn sensing_dot_loses_contrast_until_retuned() {
    let mut dev = at_offset([10.0, 10.0, 10.0, 10.0]);
    assert!(dev.truth().sd_contrast < 0.8, "{:?}", dev.truth());
    let Response::Scanned {
        outcome: ScanOutcome::Raw { scan },
        lab_seconds,
    } = dev.execute(&Request::Measure {
        scan: ScanRequest {
            kind: ScanKind::SensingDot,
            sweep: None,
            cell: None,
        },
    })
    else {
        panic!()
    };
    assert_eq!(lab_seconds, 17.0);
    let e = spintune::fit::evaluate_with(
        &scan,
        &spintune::fit::uncertainty::SIMULATED_DEVICE_REFERENCES,
    )
    .unwrap();
    let flank = e.values[0].value;
    assert!((flank - dev.truth().sd_flank_mv).abs() < 0.1);
    set(&mut dev, &[("SD1", flank)]);
    assert!(dev.truth().sd_contrast > 0.98);
}

#[test]
fn lab_clock_charges_each_operation() {
    let mut dev = device();
    let mut expected = 0.0;
    for (kind, s) in [
        (ScanKind::SensingDot, 17.0),
        (ScanKind::ChemicalPotential, 38.0),
        (ScanKind::TransitionWidth, 28.0),
        (ScanKind::ReloadTime, 5.0),
    ] {
        let r = dev.execute(&Request::Measure {
            scan: ScanRequest {
                kind,
                sweep: None,
                cell: None,
            },
        });
        assert!(matches!(r, Response::Scanned { lab_seconds, .. } if lab_seconds == s));
        expected += s;
        assert_eq!(dev.lab_seconds(), expected);
    }
    assert!(
        matches!(set(&mut dev, &[("N", -701.0)]), Response::VoltagesSet { lab_seconds, .. } if lab_seconds == 0.5)
    );
    assert_eq!(dev.lab_seconds(), expected + 0.5);
}

#[test]
fn bad_requests_are_refused() {
    let mut dev = device();
    let before = dev.voltages_mv().clone();
    assert!(matches!(
        set(&mut dev, &[("N", -705.0), ("X", 0.0)]),
        Response::Error { .. }
    ));
    assert!(matches!(
        set(&mut dev, &[("N", 50.0)]),
        Response::Error { .. }
    ));
    assert!(matches!(
        set(&mut dev, &[("N", f64::NAN)]),
        Response::Error { .. }
    ));
    assert_eq!(dev.voltages_mv(), &before);
    let sweep = |gate: &str, points| ScanRequest {
        kind: ScanKind::SensingDot,
        sweep: Some(Sweep {
            gate: gate.into(),
            from_mv: -610.0,
            to_mv: if points == 100 { -400.0 } else { -590.0 },
            points,
        }),
        cell: None,
    };
    for s in [sweep("Q", 100), sweep("SD1", 1), sweep("SD1", 100)] {
        let r = dev.execute(&Request::Measure { scan: s });
        assert!(
            matches!(r, Response::Scanned { outcome: ScanOutcome::Failed { .. }, lab_seconds } if lab_seconds == 0.0),
            "{r:?}"
        );
    }
    let r = dev.execute(&Request::TrueJacobian {
        gates: vec!["N".into()],
        parameters: vec!["nope".into()],
    });
    assert!(matches!(r, Response::Error { .. }));
    let r = dev.execute(&Request::TrueJacobian {
        gates: vec!["nope".into()],
        parameters: vec!["w".into()],
    });
    assert!(matches!(r, Response::Error { .. }));
    let mut config = DeviceConfig::default();
    config.scans.load_points = 3;
    assert_eq!(config.validate().unwrap_err().field, "scans.load_points");
    assert!(SimulatedDevice::new(config, &default_gates(), 0).is_err());
    let mut gates = default_gates();
    gates[0].name = "ZZ".into();
    let e = SimulatedDevice::new(DeviceConfig::default(), &gates, 0).unwrap_err();
    assert_eq!(e.field, "reference_mv");
    assert!(e.to_string().contains("ZZ"), "{e}");
}
