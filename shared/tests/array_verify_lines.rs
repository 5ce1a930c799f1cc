//! Lines checked before a run stops (`ArrayRunSettings::verify_lines_above_mv`),
//! read off the requests: 5-cell chains through the paper's set points.
//! A line-scan batch that follows a measurement batch with no set and no
//! record in between is a check (in the plain loop a measurement is
//! followed by a move, a confirming scan or the record). With the setting
//! such checks happen, only of cells whose previous line scan found a line
//! beyond the threshold or lost one (fitted here again from the scan's raw
//! data: a misfit several σ off, world side within the threshold, is a
//! reason to check too, as the loop cannot know), and every cell a check
//! finds truly off (world side) is moved and its `t_sr` scanned again
//! before the iteration's record; without it, none happen.

mod support;

use spintune::benchmark::array::{world, ArrayProtocol};
use spintune::fit::evaluate_with;
use spintune::fit::uncertainty::References;
use spintune::protocol::{Request, Response, ScanKind, ScanOutcome};
use spintune::sim::array::ArrayConfig;
use spintune::sim::DeviceConfig;
use support::array::{joint_in_lab, through_set_points};

const CELLS: u32 = 5;

/// What one run's checks did.
#[derive(Default)]
struct Checks {
    /// Checks (batches).
    batches: usize,
    /// Cells checked.
    cells: usize,
    /// Cells checked whose previous line scan found both lines within the
    /// threshold: should never be checked.
    needless: usize,
    /// Checked cells found beyond the threshold plus 0.2 mV.
    found_off: usize,
    /// Of those, the ones with no plunger set and no `t_sr` scan after
    /// the check and before the record.
    left_unconfirmed: usize,
}

fn line_scan_cell(q: &Request) -> Option<u32> {
    match q {
        Request::Measure { scan } if scan.kind == ScanKind::ChemicalPotential => scan.cell,
        _ => None,
    }
}

/// A line scan's answer fitted to `name`, mV, if the fit is valid (the
/// loop's rule for a line found).
fn fitted(answer: &Response, references: &References, name: &str) -> Option<f64> {
    let Response::Scanned {
        outcome: ScanOutcome::Raw { scan },
        ..
    } = answer
    else {
        return None;
    };
    let e = evaluate_with(scan, references).ok()?;
    e.values
        .iter()
        .find(|v| v.name == name && v.validate().is_ok())
        .map(|v| v.value)
}

fn is_parameter_scan(q: &Request) -> bool {
    matches!(q, Request::Measure { scan }
        if matches!(scan.kind, ScanKind::ReloadTime | ScanKind::TransitionWidth))
}

fn run(verify: Option<f64>, seed: u64) -> Checks {
    let mut protocol = ArrayProtocol::default();
    protocol.tuning.verify_lines_above_mv = verify;
    let limit = verify.unwrap_or(f64::INFINITY);
    let array = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(CELLS, 11, seed),
        |_| true,
    )
    .unwrap();
    let (mut run, mut lab) = joint_in_lab(array, &protocol, seed);
    let off = |l: [f64; 2]| l[0].abs().max(l[1].abs());
    let mut checks = Checks::default();
    // the lines (world side) at each cell's last line scan, mV
    let mut at_last_scan = vec![0.0; CELLS as usize];
    // the farthest line (fitted, mV) a cell's last line scan found, `None`
    // when it lost one
    let mut found_at_last_scan: Vec<Option<f64>> = vec![None; CELLS as usize];
    let references: Vec<_> = (0..CELLS)
        .map(|c| spintune::benchmark::array::cell_tuner(c, &protocol).fit_references)
        .collect();
    let mut after_measurement = false;
    // cells a check found off: (cell, set since, t_sr scanned since)
    let mut open: Vec<(u32, bool, bool)> = Vec::new();
    // each batch, and an empty one for each record
    let batches = std::cell::RefCell::new(Vec::new());
    through_set_points(
        &mut run,
        &mut lab,
        &protocol.set_points.clone(),
        |b| batches.borrow_mut().push(b.to_vec()),
        |_, _| batches.borrow_mut().push(Vec::new()),
    );
    assert_eq!(lab.violations, 0);
    // replay: the lines at each scan (world side) come from a second,
    // identical world given the same batches (a world is deterministic for
    // its seed)
    let array = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(CELLS, 11, seed),
        |_| true,
    )
    .unwrap();
    let mut replay = spintune::benchmark::array::Lab::new(array);
    for batch in batches.into_inner() {
        if batch.is_empty() {
            // a record
            checks.left_unconfirmed += open.iter().filter(|o| !(o.1 && o.2)).count();
            open.clear();
            after_measurement = false;
            continue;
        }
        let lines: Vec<Option<u32>> = batch.iter().map(line_scan_cell).collect();
        if lines.iter().all(Option::is_some) {
            for c in lines.into_iter().flatten() {
                let now = off(replay.device.lines_now_mv(c).unwrap());
                if after_measurement {
                    checks.cells += 1;
                    if found_at_last_scan[c as usize].is_some_and(|m| m <= limit) {
                        checks.needless += 1;
                    }
                    if now > limit + 0.2 {
                        checks.found_off += 1;
                        open.push((c, false, false));
                    }
                }
                at_last_scan[c as usize] = now;
            }
            if after_measurement {
                checks.batches += 1;
            }
            after_measurement = false;
        } else if batch.iter().any(is_parameter_scan) {
            after_measurement = true;
            for q in &batch {
                if let Request::Measure { scan } = q {
                    if scan.kind == ScanKind::ReloadTime {
                        for o in open.iter_mut().filter(|o| Some(o.0) == scan.cell) {
                            o.2 = o.1;
                        }
                    }
                }
            }
        } else {
            after_measurement = false;
            for q in &batch {
                if let Request::SetVoltages { voltages_mv } = q {
                    for o in &mut open {
                        let prefix = format!("c{}.P", o.0);
                        if voltages_mv.keys().any(|g| g.starts_with(&prefix)) {
                            o.1 = true;
                        }
                    }
                }
            }
        }
        let answers = replay.batch(&batch);
        for (q, a) in batch.iter().zip(&answers) {
            if let Some(c) = line_scan_cell(q) {
                found_at_last_scan[c as usize] = match [
                    fitted(a, &references[c as usize], "mu_a_mv"),
                    fitted(a, &references[c as usize], "mu_b_mv"),
                ] {
                    [Some(a), Some(b)] => Some(a.abs().max(b.abs())),
                    _ => None,
                };
            }
        }
    }
    assert_eq!(replay.device.voltages_mv(), lab.device.voltages_mv());
    assert_eq!(replay.device.lab_seconds(), lab.device.lab_seconds());
    checks
}

#[test]
fn lines_off_at_the_last_scan_are_checked_and_confirmed_before_the_run_stops() {
    let (mut with, mut without) = (Checks::default(), Checks::default());
    for seed in [3, 4, 5] {
        let w = run(Some(0.5), seed);
        let o = run(None, seed);
        for (total, one) in [(&mut with, w), (&mut without, o)] {
            total.batches += one.batches;
            total.cells += one.cells;
            total.needless += one.needless;
            total.found_off += one.found_off;
            total.left_unconfirmed += one.left_unconfirmed;
        }
    }
    assert_eq!(without.batches, 0, "no checks without the setting");
    assert!(
        with.batches > 0 && with.cells > 0,
        "the setting checks lines"
    );
    assert_eq!(with.needless, 0, "of {} cells checked", with.cells);
    assert_eq!(
        with.left_unconfirmed, 0,
        "of {} cells found off",
        with.found_off
    );
}
