//! How far one line round moves a cell's plungers
//! (`ArrayRunSettings::line_max_step_mv`). A charge rearrangement puts
//! cell 1's transition lines (2.5, −1.5) mV off (world side) right after
//! a set-point change; its next line scan finds them, and the correction
//! is limited to the setting: the default 10 mV makes the whole step the
//! coupled line level asks for (its Jacobian divided by the lockstep
//! factor: about 6 mV), the earlier 4 mV and the recommended cell tuner's
//! 2 mV stop short, and the lines are farther off at the next measurement
//! (docs/array-history.md, "Line steps that are not cut", "Lines brought back in
//! one step").

mod support;

use std::collections::BTreeMap;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::{Request, ScanKind};
use spintune::tuner::array_run::{ArrayAction, ArrayRunSettings};
use support::array::{is_measurement_of, three_cells_tuned};

fn is_line_scan_of(request: &Request, cell: u32) -> bool {
    matches!(request, Request::Measure { scan }
        if scan.cell == Some(cell) && scan.kind == ScanKind::ChemicalPotential)
}

/// What cell 1's first line round after the rearrangement did.
struct LineRound {
    /// Its plungers' move in the set right after its line scan, mV (norm).
    correction_mv: f64,
    /// Its lines, world side, at its next `t_sr`/`w` measurement, mV.
    lines_at_next_measurement: [f64; 2],
}

/// A 3-cell chain tuned from cold, then a set-point change with cell 1's
/// lines shifted by (2.5, −1.5) mV; `settings` as given.
fn first_line_round(settings: ArrayRunSettings) -> LineRound {
    let (mut run, mut device) = three_cells_tuned(settings);
    for c in 0..3 {
        run.set_targets(c, PAPER_SET_POINTS[1]).unwrap();
    }
    assert!(device.rearrange_charges(1, [2.5, -1.5]));

    let plungers = |v: &BTreeMap<String, f64>| -> Vec<f64> {
        ["c1.PA", "c1.PB"].iter().map(|g| v[*g]).collect()
    };
    let mut after_line_scan = false;
    let mut correction_mv = None;
    for _ in 0..500 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                if let Some(correction_mv) = correction_mv {
                    if batch.iter().any(|r| is_measurement_of(r, 1)) {
                        return LineRound {
                            correction_mv,
                            lines_at_next_measurement: device.lines_now_mv(1).unwrap(),
                        };
                    }
                }
                let before_v = device.voltages_mv();
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                if after_line_scan && correction_mv.is_none() {
                    let (a, b) = (plungers(&before_v), plungers(&device.voltages_mv()));
                    correction_mv = Some((b[0] - a[0]).hypot(b[1] - a[1]));
                }
                after_line_scan = batch.iter().any(|r| is_line_scan_of(r, 1));
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(_) => {}
            ArrayAction::Idle => break,
        }
    }
    panic!("cell 1 was not measured again after its line round");
}

#[test]
fn one_line_round_makes_the_whole_correction_within_10_mv() {
    let settings = ArrayProtocol::default().run_settings();
    assert_eq!(settings.line_max_step_mv, Some(10.0));
    assert!(settings.joint_line_steps);
    let wide = first_line_round(settings.clone());
    let cut = |mv: f64| {
        first_line_round(ArrayRunSettings {
            line_max_step_mv: Some(mv),
            ..settings.clone()
        })
    };
    let (four, two) = (cut(4.0), cut(2.0));
    // the scan found the lines off: the correction wants more than 4 mV
    assert!(
        wide.correction_mv > 5.0 && wide.correction_mv <= 10.0 + 1e-9,
        "{} mV",
        wide.correction_mv
    );
    for (limit, r) in [(4.0, &four), (2.0, &two)] {
        assert!(r.correction_mv <= limit + 1e-9, "{} mV", r.correction_mv);
    }
    // the lines nearer their centre at the next measurement, the more so
    // the longer the step (less what the Jacobian gets wrong)
    let off = |l: [f64; 2]| l[0].hypot(l[1]);
    let (w, f, t) = (
        off(wide.lines_at_next_measurement),
        off(four.lines_at_next_measurement),
        off(two.lines_at_next_measurement),
    );
    eprintln!(
        "corrections {:.2} / {:.2} / {:.2} mV, lines off at the next measurement {w:.2} / {f:.2} \
         / {t:.2} mV (limits 10 / 4 / 2 mV)",
        wide.correction_mv, four.correction_mv, two.correction_mv
    );
    assert!(w + 0.3 < f && f + 0.3 < t, "{w} {f} {t}");
}
