//! A lagging parameter scanned more than once per measurement
//! (`ArrayRunSettings::repeat_lagging_scans`, `lagging_after`;
//! `spintune::tuner::lagging`).
//!
//! On the 3-cell chain of `support::array`, tuned from cold, cell 1 gets
//! the paper's next set point. With the option (2 extra scans after 1
//! iteration out of band on one side) a measurement batch then holds three
//! `w` (or `t_sr`) scans of that cell, never more, and none extra of a
//! parameter in band; the record reports the three readings pooled by
//! their inverse variances, so the relative σ it reports for `w` after
//! such a measurement is about 1/√3 of what one scan reports in the same
//! phase (below 0.8 of their mean). Without the option no batch scans a
//! parameter twice. The bounds name their field.

mod support;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::array::{cell_tuner, world};
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::{IterationRecord, Request, ScanKind};
use spintune::sim::array::ArrayConfig;
use spintune::sim::array::ArrayDevice;
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::{ArrayAction, ArrayRun, ArrayRunSettings};
use support::array::{three_cells_tuned, until_tuned};

/// Per measurement batch after cell 1's change: how many scans of each
/// kind it held of cell 1, and each iteration's record; at most 40
/// iterations or until tuned.
fn after_change(settings: ArrayRunSettings) -> (Vec<[usize; 2]>, Vec<(usize, IterationRecord)>) {
    after_change_of(three_cells_tuned(settings))
}

/// [`after_change`] of a tuned run on its device.
fn after_change_of(
    (mut run, mut device): (ArrayRun, ArrayDevice),
) -> (Vec<[usize; 2]>, Vec<(usize, IterationRecord)>) {
    run.set_targets(1, PAPER_SET_POINTS[1]).unwrap();
    let (mut counts, mut records) = (Vec::new(), Vec::new());
    // `w` scans of cell 1 in the last batch that measured both its parameters
    let mut w_scans = 0;
    for _ in 0..4000 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let of = |kind: ScanKind| {
                    batch
                        .iter()
                        .filter(|r| matches!(r, Request::Measure { scan } if scan.cell == Some(1) && scan.kind == kind))
                        .count()
                };
                let count = [of(ScanKind::ReloadTime), of(ScanKind::TransitionWidth)];
                if count[0] > 0 && count[1] > 0 {
                    w_scans = count[1];
                }
                counts.push(count);
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(r) => {
                let tuned = r.tuned;
                records.push((w_scans, *r));
                if tuned || records.len() >= 40 {
                    break;
                }
            }
            ArrayAction::Idle => break,
        }
    }
    (counts, records)
}

fn settings(repeats: u32, after: u32) -> ArrayRunSettings {
    ArrayRunSettings {
        repeat_lagging_scans: repeats,
        lagging_after: after,
        ..ArrayProtocol::default().run_settings()
    }
}

#[test]
fn a_lagging_parameter_is_scanned_again_and_its_readings_pooled() {
    let (counts, records) = after_change(settings(2, 1));
    assert!(
        counts.iter().all(|c| c[0] <= 3 && c[1] <= 3),
        "at most 1 + 2 scans of a kind: {counts:?}"
    );
    let repeated = counts.iter().filter(|c| c[0] == 3 || c[1] == 3).count();
    assert!(
        repeated > 0,
        "the changed cell lagged and was scanned again: {counts:?}"
    );
    // the change moves t_sr from 20 to 70 ns and w from 270 to 180 µV:
    // both start out of band, so each lags from the first measurement
    let both = counts.iter().filter(|c| c[0] == 3 && c[1] == 3).count();
    assert!(both > 0, "{counts:?}");
    assert!(!records.is_empty());
    // pooled: the σ reported for a repeated parameter is below what one
    // scan of the same cell reports in the same phase (relative σ, since
    // w's σ grows with w)
    let (single, _) = after_change(settings(0, 4));
    assert!(
        single.iter().all(|c| c[0] <= 1 && c[1] <= 1),
        "off: never scanned twice: {single:?}"
    );
    // cell 1's w as reported after measurements with 3 scans and with 1
    let rel = |n: usize| -> Vec<f64> {
        records
            .iter()
            .filter(|(k, _)| *k == n)
            .filter_map(|(_, r)| {
                let p = r.parameters.iter().find(|p| p.name == "c1.w")?;
                Some(p.std? / p.value?)
            })
            .collect()
    };
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (pooled, one) = (rel(3), rel(1));
    assert!(!pooled.is_empty() && !one.is_empty());
    assert!(
        mean(&pooled) < 0.8 * mean(&one),
        "pooled {pooled:?} against one scan's {one:?}"
    );
}

/// The oracle plans with the true Jacobian: it never scans again.
#[test]
fn the_oracle_never_repeats() {
    let protocol = ArrayProtocol::default();
    let cells = (0..3).map(|c| cell_tuner(c, &protocol)).collect();
    let mut device = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(3, 5, 11),
        |_| true,
    )
    .unwrap();
    let mut run = ArrayRun::new(cells, &device.gates(), settings(2, 1), [0.3, 0.05], true).unwrap();
    until_tuned(&mut run, &mut device);
    let (counts, records) = after_change_of((run, device));
    assert!(!records.is_empty());
    assert!(counts.iter().all(|c| c[0] <= 1 && c[1] <= 1), "{counts:?}");
}

#[test]
fn the_repeats_are_bounded_and_named() {
    for (field, s) in [
        ("repeat_lagging_scans", settings(5, 4)),
        ("lagging_after", settings(1, 0)),
        ("lagging_after", settings(1, 31)),
    ] {
        let err = s.validate().unwrap_err();
        assert_eq!(err.field, field);
    }
    assert!(settings(4, 30).validate().is_ok());
}
