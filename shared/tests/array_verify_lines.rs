//! Lines checked before a run stops (`ArrayRunSettings::verify_lines_above_mv`),
//! read off the requests: 5-cell chains through the paper's set points.
//! A line-scan batch that follows a measurement batch with no set and no
//! record in between is a check (in the plain loop a measurement is
//! followed by a move, a confirming scan or the record). With the setting
//! such checks happen, only of cells whose previous line scan was at lines
//! near or beyond the threshold (world side, at the time of that scan),
//! and every cell a check finds off is moved and its `t_sr` scanned again
//! before the iteration's record; without it, none happen.

mod support;

use spintune::benchmark::array::{world, ArrayProtocol};
use spintune::protocol::{Request, ScanKind};
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
    /// Cells checked whose previous line scan had both lines within the
    /// threshold less 0.2 mV (the scan's noise): should never be checked.
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
                    if at_last_scan[c as usize] < limit - 0.2 {
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
        replay.batch(&batch);
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
