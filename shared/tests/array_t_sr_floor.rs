//! The least relative floor of a `t_sr` reading's σ in the joint loop
//! (`ArrayRunSettings::t_sr_floor`), checked from outside: a 3-cell chain
//! tuned from cold and through an all-cell change, every `t_sr` reading's
//! reported σ in the records against `floor × value` when the floor
//! applies everywhere (`t_sr_floor_filter_only = false`); and by default
//! (`t_sr_floor_filter_only`), the readings with their own σ and the
//! filter taught with the floor.

mod support;

use spintune::benchmark::array::ArrayProtocol;
use spintune::fit::uncertainty::SIMULATED_DEVICE_REFERENCES;
use spintune::protocol::IterationRecord;
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::{ArrayAction, ArrayRunSettings};
use support::array::{chain_world, joint_in_lab, records_through, TargetChange};

fn records(seed: u64, floor: f64) -> Vec<IterationRecord> {
    let mut protocol = ArrayProtocol::default();
    protocol.tuning.t_sr_floor = floor;
    // the floor on every reading, not only on what the filter learns
    protocol.tuning.t_sr_floor_filter_only = false;
    let phases: [TargetChange; 2] = [(None, (20.0, 270.0)), (None, (30.0, 240.0))];
    records_through(
        chain_world(&DeviceConfig::default(), 3, seed),
        &protocol,
        seed,
        &phases,
    )
}

/// `(value ns, σ ns)` of every `t_sr` reading in `records`.
fn t_sr_readings(records: &[IterationRecord]) -> Vec<(f64, f64)> {
    records
        .iter()
        .flat_map(|r| &r.parameters)
        .filter(|p| p.name.ends_with("t_sr"))
        .filter_map(|p| Some((p.value?, p.std?)))
        .collect()
}

#[test]
fn every_t_sr_reading_carries_at_least_the_floor() {
    let floor = 0.055;
    assert_eq!(ArrayRunSettings::default().t_sr_floor, floor);
    for seed in [3, 4] {
        let readings = t_sr_readings(&records(seed, floor));
        assert!(
            readings.len() >= 6,
            "seed {seed}: {} readings",
            readings.len()
        );
        for (x, s) in &readings {
            assert!(
                *s >= floor * x * (1.0 - 1e-9),
                "seed {seed}: t_sr {x:.2} ± {s:.3} ns, below {floor} of its value"
            );
        }
        // Off (0), the references' own floor (0.9 %) and the fit's error:
        // some reading reports less, so the floor above changed something.
        let off = t_sr_readings(&records(seed, 0.0));
        assert!(
            off.iter().any(|(x, s)| *s < floor * x),
            "seed {seed}: every reading already above {floor} without the floor"
        );
    }
}

/// With the floor for the filter only (the default), a `t_sr` reading keeps the load
/// curve's σ in the record (some below the floor), while the filter's row
/// holds it with the floor added in quadrature: its prediction at the
/// voltages it was measured at (no change since, so no row uncertainty)
/// has `σ² = s² + (r² − r_ref²)·x²`, `s` the reported σ, `x` the value, `r`
/// the run's floor and `r_ref` the references' own.
#[test]
fn the_floor_can_teach_the_filter_alone() {
    let protocol = ArrayProtocol::default();
    assert!(protocol.tuning.t_sr_floor_filter_only);
    let r = protocol.tuning.t_sr_floor;
    let r_ref = SIMULATED_DEVICE_REFERENCES.t_sr.relative_floor;
    let band = protocol.tuning.relative_tolerance;
    let seed = 3;
    let (mut run, mut lab) = joint_in_lab(
        chain_world(&DeviceConfig::default(), 3, seed),
        &protocol,
        seed,
    );
    let (mut below, mut checked, mut iterations) = (0, 0, 0);
    while iterations < 30 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = lab.device.lab_seconds();
                let answers = lab.batch(&batch);
                run.feed(answers, lab.device.lab_seconds() - before)
                    .unwrap();
            }
            ArrayAction::Iteration(record) => {
                iterations += 1;
                let Some(tuner) = run.tuner() else { continue };
                for c in 0..3 {
                    let name = format!("c{c}.t_sr");
                    let p = record.parameters.iter().find(|p| p.name == name);
                    // a value with an error bar wider than the band is not taught
                    let Some((x, s)) = p
                        .and_then(|p| p.value.zip(p.std))
                        .filter(|&(x, s)| x > 0.0 && s <= band * x)
                    else {
                        continue;
                    };
                    below += usize::from(s < r * x);
                    let (y, var) = tuner.predict(c, 0, &record.voltages_mv).unwrap();
                    let (_, taught) = tuner.scale(c, 0).unwrap().value_and_std(y, var);
                    let expected = (s * s + (r * r - r_ref * r_ref) * x * x).sqrt();
                    assert!(
                        (taught - expected).abs() <= 1e-6 * expected,
                        "iteration {}, {name} = {x:.2} ± {s:.3} ns: taught ± {taught:.4}, \
                         expected ± {expected:.4}",
                        record.iteration
                    );
                    checked += 1;
                }
            }
            ArrayAction::Idle => break,
        }
    }
    assert!(checked >= 6, "{checked} readings checked");
    assert!(
        below > 0,
        "no reading below the floor: the records were floored"
    );
}

#[test]
fn the_floor_is_bounded_and_named() {
    for bad in [-0.01, 0.2, f64::NAN] {
        let settings = ArrayRunSettings {
            t_sr_floor: bad,
            ..ArrayRunSettings::default()
        };
        let e = settings.validate().unwrap_err().to_string();
        assert!(e.contains("t_sr_floor"), "{bad}: {e}");
    }
    // an old settings file without the field gets the default
    assert_eq!(support::array::oldest_settings().t_sr_floor, 0.055);
    assert!(support::array::oldest_settings().t_sr_floor_filter_only);
}
