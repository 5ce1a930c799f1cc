//! A cell whose line is lost (docs/array-history.md, "A lost line: no forecast, a
//! new search"). A charge rearrangement puts cell 1's line B 16 mV off
//! (world side), past the line scan's ±4 mV window and the line search's
//! probes, right after a set-point change: the line stays lost. (At 14 mV,
//! the scenario's first offset, the run under today's defaults finds line
//! B again after one search; at 16, 18 and 20 mV, or 14 mV on line A or
//! the other way, it stays lost.)
//!
//! * While the line level counts it lost (two failed line scans in a row,
//!   the search's rule), the lines' forecast starts from a scan made before
//!   the loss, where the lines no longer are: nothing may act on it, so no
//!   pre-correction of the plungers before the next line scan. Seen on a
//!   random array (device 13203, seed 2): the stale forecast pre-corrected
//!   a lost line a few mV further away at every iteration.
//! * A search that gave up starts again after
//!   `ArrayRunSettings::rearm_line_search_after` more lost scans (default 3);
//!   0 keeps the single-cell rule, one search until a scan works.

mod support;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::EventKind;
use spintune::tuner::array_run::{ArrayAction, ArrayRunSettings};
use support::array::{is_line_scan_of, sets_only_plungers_of, three_cells_tuned};

/// What the 25 iterations after the rearrangement did, world side.
#[derive(Debug, Default)]
struct Watch {
    /// Iterations that began right after one whose search for cell 1's
    /// lines gave up, the last two line scans of cell 1 having truly lost a
    /// line (one beyond 5 mV there): lost by the line level's rule.
    after_a_loss: usize,
    /// Of those, the ones that set cell 1's plungers alone right before its
    /// first line scan: a pre-correction (a move is followed by the
    /// sensors' park, a pre-correction by the scan).
    precorrected_after_a_loss: usize,
    /// Searches of cell 1's lines that ended without finding them.
    searches_given_up: usize,
}

fn watch_after_rearrangement(settings: ArrayRunSettings) -> Watch {
    let (mut run, mut device) = three_cells_tuned(settings);
    for c in 0..3 {
        run.set_targets(c, PAPER_SET_POINTS[1]).unwrap();
    }
    assert!(device.rearrange_charges(1, [0.0, 16.0]));

    let mut w = Watch::default();
    // line scans of cell 1 in a row that lost a line (one 3–5 mV off is
    // unclear and leaves the count)
    let mut lost_in_a_row = 0;
    let mut at_start_lost = false;
    let (mut scanned, mut precorrected) = (false, false);
    let mut previous_sets_plungers = false;
    let mut iterations = 0;
    for _ in 0..3000 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                if batch.iter().any(|r| is_line_scan_of(r, 1)) {
                    // the batch right before the iteration's first line scan
                    // (a move is followed by the sensors' park first)
                    precorrected |= !scanned && previous_sets_plungers;
                    scanned = true;
                    let off = device.lines_now_mv(1).unwrap();
                    match off[0].abs().max(off[1].abs()) {
                        x if x > 5.0 => lost_in_a_row += 1,
                        x if x < 3.0 => lost_in_a_row = 0,
                        _ => {}
                    }
                }
                previous_sets_plungers = batch.iter().any(|r| sets_only_plungers_of(r, 1));
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(record) => {
                if at_start_lost {
                    w.after_a_loss += 1;
                    w.precorrected_after_a_loss += precorrected as usize;
                }
                let given_up = record
                    .events
                    .iter()
                    .filter(|e| {
                        e.level == "c1.lines"
                            && matches!(e.kind, EventKind::SearchEnded { found: false, .. })
                    })
                    .count();
                w.searches_given_up += given_up;
                let gave_up = given_up > 0 && lost_in_a_row >= 2;
                // (the line level's own evidence: a bogus fit may "find" a
                // line that is truly lost, and then may act on its forecast)
                at_start_lost = gave_up;
                (scanned, precorrected) = (false, false);
                iterations += 1;
                if iterations == 25 {
                    break;
                }
            }
            ArrayAction::Idle => break,
        }
    }
    w
}

#[test]
fn a_forecast_from_before_a_lost_line_is_not_acted_on() {
    let w = watch_after_rearrangement(ArrayProtocol::default().run_settings());
    // the scenario: the rearrangement lost the line for good
    assert!(w.after_a_loss >= 5, "{w:?}");
    // (with the rule taken out of `lines.rs`, 4 of the 8 did)
    assert_eq!(w.precorrected_after_a_loss, 0, "{w:?}");
}

#[test]
fn a_search_that_gave_up_starts_again() {
    let settings = ArrayProtocol::default().run_settings();
    assert_eq!(settings.rearm_line_search_after, 3);
    let rearmed = watch_after_rearrangement(settings.clone());
    let once = watch_after_rearrangement(ArrayRunSettings {
        rearm_line_search_after: 0,
        ..settings
    });
    assert_eq!(once.searches_given_up, 1, "{once:?}");
    // 25 iterations: a search, then one every few iterations
    assert!(rearmed.searches_given_up >= 3, "{rearmed:?}");
}
