//! Determinism of the simulator and fits: same seed ⇒ bit-identical data,
//! serde round trip mid-run continues bit-identically, and a golden hash
//! that must be the same natively and in wasm (run these tests with
//! `--target wasm32-unknown-unknown` to check the cross-target claim).

#[cfg(not(target_arch = "wasm32"))]
use std::prelude::v1::test as native_test;
#[cfg(target_arch = "wasm32")]
use wasm_bindgen_test::wasm_bindgen_test as wasm_test;

use spintune::fit::{evaluate_with, uncertainty::SIMULATED_DEVICE_REFERENCES};
use spintune::protocol::{Request, Response, ScanKind, ScanOutcome, ScanRequest};
use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};

/// A short tuning-like script: every scan kind, a few voltage moves.
fn script() -> Vec<Request> {
    let mut out = Vec::new();
    for step in 0..3 {
        let dv = 2.0 * step as f64;
        out.push(Request::SetVoltages {
            voltages_mv: [
                ("N".to_string(), -700.0 + dv),
                ("SB".to_string(), -780.0 - dv),
                ("PA".to_string(), -300.0 - 0.5 * dv),
            ]
            .into(),
        });
        for kind in ScanKind::ALL {
            out.push(Request::Measure {
                scan: ScanRequest {
                    kind,
                    sweep: None,
                    cell: None,
                },
            });
        }
    }
    out
}

/// FNV-1a over the bit patterns of all returned numbers and fitted values.
fn run(dev: &mut SimulatedDevice, requests: &[Request], hash: &mut u64) {
    let mut eat = |x: f64| {
        for b in x.to_bits().to_le_bytes() {
            *hash ^= u64::from(b);
            *hash = hash.wrapping_mul(0x100_0000_01b3);
        }
    };
    for r in requests {
        match dev.execute(r) {
            Response::Scanned {
                outcome: ScanOutcome::Raw { scan },
                lab_seconds,
            } => {
                eat(lab_seconds);
                for t in &scan.traces {
                    t.x.iter().chain(&t.y).for_each(|&v| eat(v));
                }
                if let Ok(e) = evaluate_with(&scan, &SIMULATED_DEVICE_REFERENCES) {
                    for v in &e.values {
                        eat(v.value);
                        eat(v.variance);
                    }
                }
            }
            Response::VoltagesSet { voltages_mv, .. } => voltages_mv.values().for_each(|&v| eat(v)),
            other => panic!("{other:?}"),
        }
    }
    eat(dev.lab_seconds());
    eat(dev.truth().w_uv);
}

fn device(seed: u64) -> SimulatedDevice {
    SimulatedDevice::new(DeviceConfig::default(), &default_gates(), seed).unwrap()
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// Hash of `script()` on seed 7, recorded natively (x86_64; re-recorded when
/// the default device gained the slow drift of t_c and Γ). The same value in
/// wasm proves the data are bit-identical across targets.
const GOLDEN_SEED7: u64 = 0x54f8_da75_7ccc_45a2;

#[cfg_attr(not(target_arch = "wasm32"), native_test)]
#[cfg_attr(target_arch = "wasm32", wasm_test)]
fn same_seed_gives_bit_identical_data_and_golden_hash() {
    let (mut a, mut b, mut c) = (FNV_OFFSET, FNV_OFFSET, FNV_OFFSET);
    run(&mut device(7), &script(), &mut a);
    run(&mut device(7), &script(), &mut b);
    run(&mut device(8), &script(), &mut c);
    assert_eq!(a, b);
    assert_ne!(a, c);
    assert_eq!(a, GOLDEN_SEED7, "golden hash changed: {a:#x}");
}

#[cfg_attr(not(target_arch = "wasm32"), native_test)]
#[cfg_attr(target_arch = "wasm32", wasm_test)]
fn serde_round_trip_mid_run_continues_bit_identically() {
    let requests = script();
    let (first, second) = requests.split_at(7);
    let mut dev = device(3);
    let mut h = FNV_OFFSET;
    run(&mut dev, first, &mut h);
    let json = serde_json::to_string(&dev).unwrap();
    let mut restored: SimulatedDevice = serde_json::from_str(&json).unwrap();
    assert_eq!(restored, dev);
    let (mut a, mut b) = (h, h);
    run(&mut dev, second, &mut a);
    run(&mut restored, second, &mut b);
    assert_eq!(a, b);
    assert_eq!(restored, dev);
}
