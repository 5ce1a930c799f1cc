//! Steps aimed at readings shrunk toward their targets
//! (`ArrayRunSettings::shrink_residuals`, `shrink_in_band_only`;
//! `spintune::tuner::shrink`).
//!
//! A 3-cell chain without crosstalk (and a lab calibration that says so)
//! is tuned from cold with the option off; copies of the run (through its
//! serialized form, as a checkpoint) get the option on or off and a band
//! of ±3 %, and every cell's targets are set again on copies of the same
//! world, so all copies take the same first measurement. Tuned cells
//! then have little to correct but their readings' noise: aimed at those
//! readings they wander by about a σ's worth of gate each iteration; with
//! a factor of 4 they move less than half as far per iteration (over 8
//! noise seeds). With `shrink_in_band_only`, readings out of band are
//! aimed at in full: moved to far targets, the first move is the same
//! gate for gate as without the option. The bounds name their field.

mod support;

use spintune::benchmark::array::{cell_tuner, world, ArrayProtocol};
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::IterationRecord;
use spintune::sim::array::{ArrayConfig, ArrayDevice, CrosstalkConfig};
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::{ArrayRun, ArrayRunSettings};
use support::array::{drive, until_tuned};

/// The records of `run` on `device` after every cell's targets were set
/// again to the cold start's, until tuned, idle or 16 iterations.
fn after_change(run: ArrayRun, device: ArrayDevice) -> Vec<IterationRecord> {
    after_change_to(run, device, PAPER_SET_POINTS[0])
}

/// [`after_change`] with every cell's targets set to `targets`.
fn after_change_to(
    mut run: ArrayRun,
    mut device: ArrayDevice,
    targets: (f64, f64),
) -> Vec<IterationRecord> {
    for c in 0..3 {
        run.set_targets(c, targets).unwrap();
    }
    drive(&mut run, &mut device, 16)
}

/// Length (mV) of cell `c`'s move of its tuning gates from record `i` to
/// record `i + 1`.
fn moved(records: &[IterationRecord], i: usize, c: u32) -> f64 {
    ["N", "T", "SA", "SB"]
        .iter()
        .map(|g| {
            let name = format!("c{c}.{g}");
            records[i + 1].voltages_mv[&name] - records[i].voltages_mv[&name]
        })
        .map(|d| d * d)
        .sum::<f64>()
        .sqrt()
}

fn with_shrink(run: &ArrayRun, factor: f64) -> ArrayRun {
    with_shrink_of(run, factor, false)
}

/// `run` with the option at `factor` (only for readings in band with
/// `in_band_only`) and a band of ±3 %, so that cells within a few σ of
/// their targets still iterate.
fn with_shrink_of(run: &ArrayRun, factor: f64, in_band_only: bool) -> ArrayRun {
    let mut v = serde_json::to_value(run).unwrap();
    v["settings"]["shrink_residuals"] = serde_json::json!(factor);
    v["settings"]["shrink_in_band_only"] = serde_json::json!(in_band_only);
    v["settings"]["relative_tolerance"] = serde_json::json!(0.03);
    serde_json::from_value(v).unwrap()
}

/// A tuned 3-cell chain without crosstalk (noise seed `seed`).
fn uncoupled_tuned(seed: u64) -> (ArrayRun, ArrayDevice) {
    let protocol = ArrayProtocol::default();
    let config = ArrayConfig {
        crosstalk: CrosstalkConfig {
            nearest: 0.0,
            next: 0.0,
            ..CrosstalkConfig::default()
        },
        ..ArrayConfig::chain(3, 5, seed)
    };
    let mut device = world(&DeviceConfig::default(), config, |_| true).unwrap();
    let cells = (0..3).map(|c| cell_tuner(c, &protocol)).collect();
    let settings = protocol.run_settings();
    assert_eq!(settings.shrink_residuals, 0.0, "off by default");
    let mut run = ArrayRun::new(cells, &device.gates(), settings, [0.0, 0.0], false).unwrap();
    until_tuned(&mut run, &mut device);
    (run, device)
}

#[test]
fn a_reading_within_its_noise_moves_its_cell_less() {
    // (moves summed in mV, moves counted) over every seed, off and on
    let (mut off_total, mut on_total) = ((0.0, 0), (0.0, 0));
    for seed in 11..=18 {
        let (run, device) = uncoupled_tuned(seed);
        let off = after_change(with_shrink(&run, 0.0), device.clone());
        let on = after_change(with_shrink(&run, 4.0), device);
        assert_eq!(
            off[0].parameters, on[0].parameters,
            "seed {seed}: the same measurement"
        );
        for (records, total) in [(&off, &mut off_total), (&on, &mut on_total)] {
            for i in 0..records.len().saturating_sub(1) {
                for c in 0..3 {
                    total.0 += moved(records, i, c);
                    total.1 += 1;
                }
            }
        }
    }
    let (a, b) = (
        off_total.0 / off_total.1 as f64,
        on_total.0 / on_total.1 as f64,
    );
    assert!(
        off_total.1 >= 24 && on_total.1 >= 24,
        "{off_total:?} {on_total:?}"
    );
    assert!(
        b < 0.5 * a,
        "a cell's move per iteration: {b} mV with the option, {a} mV without"
    );
}

/// With `shrink_in_band_only`, readings out of their band are aimed at in
/// full: after every cell's targets moved to (70 ns, 180 µV) (every
/// reading out of band), the first move is the same as without the
/// option, gate for gate, and differs with the option on every reading.
#[test]
fn in_band_only_leaves_readings_out_of_band_alone() {
    for seed in [11, 12, 13] {
        let (run, device) = uncoupled_tuned(seed);
        let first_move = |run: ArrayRun| {
            let r = after_change_to(run, device.clone(), (70.0, 180.0));
            assert!(r.len() >= 2, "seed {seed}");
            assert!(
                r[0].parameters.iter().all(|p| {
                    let (x, t) = (p.value.unwrap(), p.target.unwrap());
                    (x / t - 1.0).abs() > 0.1 && (t / x - 1.0).abs() > 0.1
                }),
                "{:?}",
                r[0].parameters
            );
            (0..3)
                .flat_map(|c| ["N", "T", "SA", "SB"].map(|g| format!("c{c}.{g}")))
                .map(|g| r[1].voltages_mv[&g])
                .collect::<Vec<f64>>()
        };
        let off = first_move(with_shrink(&run, 0.0));
        assert_eq!(
            off,
            first_move(with_shrink_of(&run, 4.0, true)),
            "seed {seed}"
        );
        assert_ne!(off, first_move(with_shrink(&run, 4.0)), "seed {seed}");
    }
}

#[test]
fn the_factor_is_bounded_and_named() {
    let s = |f: f64| ArrayRunSettings {
        shrink_residuals: f,
        ..ArrayProtocol::default().run_settings()
    };
    for f in [-0.5, 10.5, f64::NAN, f64::INFINITY] {
        assert_eq!(
            s(f).validate().unwrap_err().field,
            "shrink_residuals",
            "{f}"
        );
    }
    assert!(s(0.0).validate().is_ok() && s(10.0).validate().is_ok());
    // a settings file without it: off
    let old = support::array::oldest_settings();
    assert_eq!(old.shrink_residuals, 0.0);
    assert!(!old.shrink_in_band_only);
}
