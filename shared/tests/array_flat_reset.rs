//! A flat row's prior refuted (`ArrayRunSettings::flat_reset_refuted_sigma`,
//! `tuner::flat_reset`), on the world where it was traced: the default
//! 9-cell array of `spintune bench-array`, noise seed 10, cell 6 through
//! the paper's set points. At the last change (`w` 180 → 270 µV) its `w`
//! rose towards the target, turned over, and the flat-row resets walked it
//! back onto its thermal floor (docs/array-history.md, "A flat row's prior
//! refuted").
//!
//! The test reads the trace of cell 6: a move planned with the `w` row
//! equal, bit for bit, to the row of the run's first iteration (its prior)
//! follows a reset. From the readings it derives, independently of the
//! loop's watch, the first iteration at which `w` had turned away from its
//! target by more than the threshold since the phase's first reset; the
//! rule on, no reset may follow it, and the rule off, resets go on after
//! it.
//!
//! The world runs with the loop it was traced in: line corrections of at
//! most 2 mV (`line_max_step_mv = 2`, the default before "Lines brought
//! back in one step") each cell's alone (`joint_line_steps = false`, the
//! default before "Line steps that are not cut"), every line scanned (no
//! `line_forecast`, the default before "Lines forecast instead of scanned,
//! now the default"); with today's line level the run takes another path,
//! on which cell 6's `w` never turns away from its target by the threshold.

use spintune::benchmark::array::{run_strategy, world, ArrayProtocol, ArrayStrategy};
use spintune::benchmark::array_timeline::TimelinePoint;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::driver::SimulationConfig;
use spintune::sim::array::ArrayConfig;
use spintune::sim::random::cell_targets_reachable;

const CELL: u32 = 6;
const W: usize = 1;
/// The last change of the set points: (20, 180) → (20, 270).
const PHASE: u32 = 4;

/// Cell 6's trace points of the last change, run with the rule at `sigma`.
fn traced(sigma: f64) -> (Vec<TimelinePoint>, Vec<f64>) {
    let base = SimulationConfig::paper_default();
    let mut set_points = PAPER_SET_POINTS.to_vec();
    let mut protocol = ArrayProtocol {
        set_points: set_points.clone(),
        single_cell_changes: 0,
        trace_cell: Some(CELL),
        ..ArrayProtocol::default()
    };
    protocol.tuning.flat_reset_refuted_sigma = sigma;
    protocol.tuning.line_max_step_mv = Some(2.0);
    protocol.tuning.joint_line_steps = false;
    protocol.tuning.finite_difference_step_mv = None;
    // the scenario was traced with the references' own t_sr floor, and
    // with every line scanned (no forecast)
    protocol.tuning.t_sr_floor = 0.0;
    protocol.tuning.line_forecast = None;
    set_points.push(protocol.single_cell_target);
    let reachable = |d: &spintune::sim::DeviceConfig| cell_targets_reachable(d, &set_points);
    let config = ArrayConfig {
        seed: 10,
        device_seed: 0,
        ..ArrayConfig::chain(9, 0, 0)
    };
    let array = world(&base.device, config, reachable).unwrap();
    let r = run_strategy(ArrayStrategy::Joint, array, &protocol).unwrap();
    let prior = r.timeline[0].trace.as_ref().unwrap().learned_rows[W].clone();
    let phase = r
        .timeline
        .into_iter()
        .filter(|p| p.phase == PHASE)
        .collect();
    (phase, prior)
}

/// Per point: whether its move followed a reset of the `w` row, and
/// whether `w` had by then turned away from its target by more than
/// `sigmas` σ of the pair since the phase's first reset (the readings the
/// loop acts on: σ within the band).
fn resets_and_turned(points: &[TimelinePoint], prior: &[f64], sigmas: f64) -> Vec<(bool, bool)> {
    let target = PAPER_SET_POINTS[PHASE as usize].1;
    // since the first reset: the nearest reading's ln(x/target) and relative σ
    let mut nearest: Option<(f64, f64)> = None;
    let mut turned = false;
    points
        .iter()
        .map(|p| {
            let t = p.trace.as_ref().unwrap();
            let reset = t.learned_rows[W] == prior;
            if let Some((x, s)) = t.measured[W].filter(|(x, s)| *s <= 0.1 * x) {
                let (r, rel) = ((x / target).ln(), s / x);
                let in_band = (x / target - 1.0).abs() <= 0.1;
                match nearest {
                    // in band or across the target: the watch starts afresh
                    Some((r0, _)) if in_band || r.signum() != r0.signum() => {
                        (nearest, turned) = (None, false);
                    }
                    Some((r0, _)) if r.abs() < r0.abs() => nearest = Some((r, rel)),
                    Some((r0, s0)) => turned |= r.abs() - r0.abs() > sigmas * s0.hypot(rel),
                    None if reset => nearest = Some((r, rel)),
                    None => {}
                }
            }
            (reset, turned)
        })
        .collect()
}

#[test]
fn a_flat_rows_prior_is_not_put_back_once_the_parameter_turned_away() {
    let (on, prior) = traced(3.0);
    let marks = resets_and_turned(&on, &prior, 3.0);
    let turned_at = marks.iter().position(|&(_, t)| t).expect("w turned away");
    assert!(
        marks[..turned_at].iter().any(|&(r, _)| r),
        "the row was reset before: {marks:?}"
    );
    assert!(
        marks[turned_at..].iter().all(|&(r, _)| !r),
        "no reset once w turned away (point {turned_at}): {marks:?}"
    );

    let (off, prior_off) = traced(0.0);
    assert_eq!(prior_off, prior);
    let marks = resets_and_turned(&off, &prior, 3.0);
    let turned_at = marks.iter().position(|&(_, t)| t).expect("w turned away");
    let after = marks[turned_at..].iter().filter(|&&(r, _)| r).count();
    assert!(after >= 3, "the rule off, the resets go on: {marks:?}");
}
