//! The simulated array (`spintune::sim::array`): crosstalk by distance,
//! readout groups and the lab clock, the sealed oracle, config validation.
//! Expected values follow from the documented model (effective voltage
//! `v_j + Σ λ(|j−k|)·Δv_k`, λ = 1, 0.3, 0.05, 0) and the default scan
//! durations (load curve 5 s, transition width 28 s), not from outputs.

use std::collections::BTreeMap;

use spintune::description::layout::Layout;
use spintune::protocol::{Request, Response, ScanKind, ScanRequest};
use spintune::sim::array::{gate_name, parameter_name, ArrayConfig, ArrayDevice};
use spintune::sim::DeviceConfig;

/// `cells` identical default devices (so every cell's own model is the
/// same) without the slow drift of t_c and Γ (so the truth changes only
/// with the voltages).
fn identical(cells: u32) -> ArrayDevice {
    let mut d = DeviceConfig::default();
    let slow = &mut d.noise.slow;
    slow.tunnel_coupling_rel = 0.0;
    slow.lead_rate_rel = 0.0;
    slow.jump_rate_per_s = 0.0;
    slow.lead_rate_trend_per_hour = 0.0;
    ArrayDevice::new(ArrayConfig::chain(cells, 0, 7), vec![d; cells as usize]).unwrap()
}

fn set(dev: &mut ArrayDevice, gate: &str, mv: f64) {
    let r = dev.execute(&Request::SetVoltages {
        voltages_mv: BTreeMap::from([(gate.to_string(), mv)]),
    });
    assert!(matches!(r, Response::VoltagesSet { .. }), "{r:?}");
}

#[test]
fn crosstalk_decays_with_distance_and_vanishes_beyond_the_next_cell() {
    let mut dev = identical(7);
    let start: Vec<f64> = (0..7)
        .map(|c| dev.effective_voltages_mv(c).unwrap()["SB"])
        .collect();
    let before: Vec<_> = (0..7).map(|c| dev.truth(c).unwrap()).collect();
    let sb = dev.voltages_mv()[&gate_name(3, "SB")];
    set(&mut dev, &gate_name(3, "SB"), sb + 5.0);
    let shift = |c: u32| dev.effective_voltages_mv(c).unwrap()["SB"] - start[c as usize];
    assert!((shift(3) - 5.0).abs() < 1e-12);
    for c in [2, 4] {
        assert!(
            (shift(c) - 0.3 * 5.0).abs() < 1e-12,
            "cell {c}: {}",
            shift(c)
        );
    }
    for c in [1, 5] {
        assert!(
            (shift(c) - 0.05 * 5.0).abs() < 1e-12,
            "cell {c}: {}",
            shift(c)
        );
    }
    for c in [0, 6] {
        assert_eq!(shift(c), 0.0);
        assert_eq!(dev.truth(c).unwrap(), before[c as usize]);
    }
    // the read-back is the commanded voltage: neighbours were not "moved"
    assert_eq!(
        dev.voltages_mv()[&gate_name(2, "SB")],
        dev.voltages_mv()[&gate_name(0, "SB")]
    );
    // opening SB speeds up the reload: the own cell most, the neighbours less
    let dt = |c: u32| before[c as usize].t_sr_ns - dev.truth(c).unwrap().t_sr_ns;
    assert!(dt(3) > dt(2) && dt(2) > dt(1) && dt(1) > 0.0);
    assert!((dt(2) - dt(4)).abs() < 1e-9);
}

/// A 2×3 ladder (cells 0 1 2 over 3 4 5): the cell across the rung is a
/// nearest neighbour, the diagonal ones next-nearest; cell 3 is three
/// cells away from cell 2 in a chain but one step from cell 0 here.
#[test]
fn in_a_ladder_the_cell_across_the_rung_is_a_nearest_neighbour() {
    let mut d = DeviceConfig::default();
    d.noise.slow.tunnel_coupling_rel = 0.0;
    d.noise.slow.lead_rate_rel = 0.0;
    d.noise.slow.jump_rate_per_s = 0.0;
    let mut cfg = ArrayConfig::chain(6, 0, 7);
    cfg.layout = Layout::Ladder;
    let mut dev = ArrayDevice::new(cfg, vec![d; 6]).unwrap();
    let start: Vec<f64> = (0..6)
        .map(|c| dev.effective_voltages_mv(c).unwrap()["SB"])
        .collect();
    let sb = dev.voltages_mv()[&gate_name(0, "SB")];
    set(&mut dev, &gate_name(0, "SB"), sb + 4.0);
    let shift = |c: u32| dev.effective_voltages_mv(c).unwrap()["SB"] - start[c as usize];
    // distances from cell 0: 1 → 1, 3 → 1 (the rung), 2 → 2, 4 → 2 (diagonal), 5 → 3
    for (c, lambda) in [(0, 1.0), (1, 0.3), (3, 0.3), (2, 0.05), (4, 0.05), (5, 0.0)] {
        assert!(
            (shift(c) - lambda * 4.0).abs() < 1e-12,
            "cell {c}: {}",
            shift(c)
        );
    }
    // a ladder needs an even number of cells, at least 4: the error names the field
    let mut odd = ArrayConfig::chain(5, 0, 0);
    odd.layout = Layout::Ladder;
    assert_eq!(odd.validate().unwrap_err().field, "layout");
    // the layout is read from a config file, a chain when left out
    let read: ArrayConfig =
        serde_json::from_str(r#"{"cells": 4, "layout": "ladder", "device_seed": 0, "seed": 1}"#)
            .unwrap();
    assert_eq!(read.layout, Layout::Ladder);
    let chain: ArrayConfig =
        serde_json::from_str(r#"{"cells": 4, "device_seed": 0, "seed": 1}"#).unwrap();
    assert_eq!(chain.layout, Layout::Chain);
}

#[test]
fn the_true_jacobian_has_the_locality_structure() {
    let mut dev = identical(5);
    let gates = [gate_name(2, "SB"), gate_name(2, "SD1")];
    let g: Vec<&str> = gates.iter().map(String::as_str).collect();
    let params: Vec<String> = (0..5).map(|c| parameter_name(c, "t_sr")).collect();
    let p: Vec<&str> = params.iter().map(String::as_str).collect();
    let j = dev.true_jacobian(&g, &p).unwrap();
    let own = j[(2, 0)];
    assert!(own < -0.5);
    // identical cells at the same point: λ times the own derivative (to O(h²))
    for (c, lambda) in [(1, 0.3), (3, 0.3), (0, 0.05), (4, 0.05)] {
        assert!(
            (j[(c, 0)] - lambda * own).abs() < 0.01 * lambda * own.abs(),
            "cell {c}: {} vs {}",
            j[(c, 0)],
            lambda * own
        );
    }
    // a sensing-dot gate does not couple to the neighbours
    for c in [0, 1, 3, 4] {
        assert_eq!(j[(c, 1)], 0.0);
    }
    // the same through the oracle's request, counted
    let r = dev.execute(&Request::TrueJacobian {
        gates: gates.to_vec(),
        parameters: params.clone(),
    });
    assert!(matches!(r, Response::TrueJacobian { .. }));
    assert_eq!(dev.truth_queries(), 1);
}

fn scan(cell: u32, kind: ScanKind) -> Request {
    Request::Measure {
        scan: ScanRequest {
            kind,
            sweep: None,
            cell: Some(cell),
        },
    }
}

#[test]
fn a_batch_costs_its_longest_readout_group() {
    let batch = [
        scan(0, ScanKind::ReloadTime),
        scan(1, ScanKind::TransitionWidth),
        scan(2, ScanKind::TransitionWidth),
    ];
    // one sensor per cell: three groups in parallel → the longest, 28 s
    let mut dev = identical(3);
    let r = dev.execute_batch(&batch);
    assert!(r.iter().all(|r| matches!(r, Response::Scanned { .. })));
    assert_eq!(dev.lab_seconds(), 28.0);
    // one shared readout: serial → 5 + 28 + 28 s
    let mut cfg = ArrayConfig::chain(3, 0, 7);
    cfg.readout_groups = Some(vec![vec![0, 1, 2]]);
    let mut shared = ArrayDevice::new(cfg.clone(), vec![DeviceConfig::default(); 3]).unwrap();
    shared.execute_batch(&batch);
    assert_eq!(shared.lab_seconds(), 61.0);
    // groups {0, 1} and {2}: max(5 + 28, 28) s
    cfg.readout_groups = Some(vec![vec![0, 1], vec![2]]);
    let mut two = ArrayDevice::new(cfg, vec![DeviceConfig::default(); 3]).unwrap();
    two.execute_batch(&batch);
    assert_eq!(two.lab_seconds(), 33.0);
}

#[test]
fn a_scan_must_name_a_cell() {
    let mut dev = identical(2);
    let r = dev.execute(&Request::Measure {
        scan: ScanRequest {
            kind: ScanKind::ReloadTime,
            sweep: None,
            cell: None,
        },
    });
    assert!(matches!(
        r,
        Response::Scanned {
            outcome: spintune::protocol::ScanOutcome::Failed { .. },
            ..
        }
    ));
    assert_eq!(dev.lab_seconds(), 0.0);
}

#[test]
fn a_sealed_array_refuses_the_truth_and_counts_every_request() {
    let mut dev = identical(2);
    dev.seal_truth();
    let ask = Request::TrueJacobian {
        gates: vec![gate_name(0, "T")],
        parameters: vec![parameter_name(1, "w")],
    };
    for n in 1..=3 {
        assert!(matches!(dev.execute(&ask), Response::Error { .. }));
        assert_eq!(dev.truth_queries(), n);
    }
    assert!(dev.is_truth_sealed());
}

#[test]
fn config_errors_name_the_field() {
    let mut cfg = ArrayConfig::chain(3, 0, 0);
    cfg.readout_groups = Some(vec![vec![0, 1]]);
    assert_eq!(cfg.validate().unwrap_err().field, "readout_groups");
    cfg.readout_groups = Some(vec![vec![0, 1], vec![1, 2]]);
    assert_eq!(cfg.validate().unwrap_err().field, "readout_groups[1][0]");
    cfg.readout_groups = None;
    cfg.crosstalk.nearest = 1.5;
    assert_eq!(cfg.validate().unwrap_err().field, "crosstalk.nearest");
    cfg.crosstalk.nearest = 0.3;
    cfg.crosstalk.next = 0.4;
    assert_eq!(cfg.validate().unwrap_err().field, "crosstalk.next");
    let too_many = ArrayConfig::chain(17, 0, 0);
    assert_eq!(too_many.validate().unwrap_err().field, "cells");
}

#[test]
fn a_single_cell_scan_request_serializes_without_a_cell() {
    let none = ScanRequest {
        kind: ScanKind::ReloadTime,
        sweep: None,
        cell: None,
    };
    let json = serde_json::to_string(&none).unwrap();
    assert!(!json.contains("cell"), "{json}");
    let some = ScanRequest {
        cell: Some(4),
        ..none
    };
    let json = serde_json::to_string(&some).unwrap();
    assert!(json.contains("\"cell\":4"), "{json}");
    let back: ScanRequest = serde_json::from_str(&json).unwrap();
    assert_eq!(back, some);
}
