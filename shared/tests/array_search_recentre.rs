//! A cell's line search with `ArrayRunSettings::search_recentres_held_line`:
//! its probes also bring the line it holds back to its window's centre
//! (docs/array.md, "What was tried"). Without it, a held line that sits
//! near the ±4 mV window's edge when the search starts stays there for
//! every probe, and a probe whose line Jacobian is off pushes it out.
//!
//! World side: a charge rearrangement puts cell 1's line A 7 mV off (lost,
//! outside the window) and its line B 3 mV off (held: found, near the
//! window's edge). The test reads where both lines truly are at cell 1's
//! line scans; the loop only sees its scans.

mod support;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::tuner::array_run::{ArrayAction, ArrayRunSettings};
use support::array::{is_line_scan_of, sets_only_plungers_of, three_cells_tuned};

/// Where cell 1's lines truly were (mV from the window's centre) at the
/// line scan that started its search (the last scan before the first
/// probe) and at the scan right after that probe. The first probe is the
/// first set of cell 1's plungers alone while its line A is truly outside
/// the window: with a line lost there is no line correction, and the
/// lines' forecast is not acted on.
fn lines_around_the_first_probe(recentre: bool) -> ([f64; 2], [f64; 2]) {
    let settings = ArrayRunSettings {
        search_recentres_held_line: recentre,
        ..ArrayProtocol::default().run_settings()
    };
    let (mut run, mut device) = three_cells_tuned(settings);
    run.set_targets(1, PAPER_SET_POINTS[1]).unwrap();
    assert!(device.rearrange_charges(1, [7.0, 3.0]));
    let mut last_scan = None;
    let mut probed_from = None;
    for _ in 0..3000 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let lines = device.lines_now_mv(1).unwrap();
                if batch.iter().any(|r| is_line_scan_of(r, 1)) {
                    if let Some(before) = probed_from {
                        return (before, lines);
                    }
                    last_scan = Some(lines);
                }
                if probed_from.is_none()
                    && lines[0].abs() > 4.0
                    && batch.iter().any(|r| sets_only_plungers_of(r, 1))
                {
                    probed_from = last_scan;
                }
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(_) => {}
            ArrayAction::Idle => break,
        }
    }
    panic!("recentre {recentre}: no probe and scan after it");
}

#[test]
fn the_first_probe_brings_the_held_line_to_its_centre_only_when_asked() {
    // held where it was: B moves by no more than the line Jacobian's error
    // on the probe's shift of A, a small part of a mV
    let (before, after) = lines_around_the_first_probe(false);
    assert!(
        before[0].abs() > 4.0 && (2.5..3.5).contains(&before[1]),
        "{before:?}"
    );
    assert!(
        (after[1] - before[1]).abs() < 0.5,
        "{before:?} -> {after:?}"
    );
    // recentred: B from about 3 mV to its centre (the same scans up to the
    // probe: the option acts only inside a search)
    let (before_r, after_r) = lines_around_the_first_probe(true);
    assert_eq!(before_r, before);
    assert!(after_r[1].abs() < 0.5, "{before_r:?} -> {after_r:?}");
    // and the probe still shifts the lost line A by its step (4 mV; the
    // first probe's side from where A was last seen), as without the option
    for a in [after[0], after_r[0]] {
        assert!(
            ((a - before[0]).abs() - 4.0).abs() < 1.0,
            "{before:?} -> {a}"
        );
    }
}
