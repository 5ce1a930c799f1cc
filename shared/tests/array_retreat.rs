//! How a cell whose evaluation failed retreats (`ArrayRunSettings::retreat`).
//! By default (last rounds' rule) every gate of the cell goes half-way back
//! to its voltage at its last good evaluation, plungers and sensing gate
//! included. With `tuning_gates` it retreats as a single cell's tuner does:
//! its tuning gates half-way back, its compensation gates (plungers,
//! sensor) following through its virtual-gate matrix, not to their old
//! voltages, which the line level moved since (a cell stranded for a whole
//! phase by the two levels undoing each other, found on random arrays;
//! docs/array-history.md "A failed cell's retreat"). `tuning_gates_when_uncertain`
//! also retreats on a value whose error bar is wider than its band.
//! `every_gate_lines_kept` retreats every gate half-way, the plungers
//! toward their last good voltages shifted by the line corrections made
//! since (docs/array-history.md, "Lines brought back in one step").
//!
//! The failure is scripted: the world answers cell 1's second measurement
//! after a set-point change with instrument errors, or with a `w` of
//! σ = 2,000 µV (its band: ±10 % of 180–270 µV).

mod support;

use std::collections::BTreeMap;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::{
    IterationRecord, ParameterValue, Request, Response, ScanKind, ScanOutcome,
};
use spintune::tuner::array::CellKnowledge;
use spintune::tuner::array_run::{ArrayAction, Retreat};
use support::array::{is_measurement_of, three_cells_tuned};

/// Cell 1's gates in a record, mV.
fn cell_1(record: &IterationRecord) -> BTreeMap<String, f64> {
    record
        .voltages_mv
        .iter()
        .filter(|(g, _)| g.starts_with("c1."))
        .map(|(g, v)| (g.clone(), *v))
        .collect()
}

/// Cell 1's answers to a scripted failure: instrument errors.
fn instrument_error(_: &Request, _: Response) -> Response {
    Response::error("scripted: the instrument timed out")
}

/// Cell 1's answers to a scripted failure: `t_sr` as measured, `w` with an
/// error bar of 2,000 µV (its band is ±10 % of 180–270 µV).
fn too_uncertain_w(request: &Request, measured: Response) -> Response {
    match request {
        Request::Measure { scan } if scan.kind == ScanKind::TransitionWidth => Response::Scanned {
            outcome: ScanOutcome::Evaluated {
                values: vec![ParameterValue {
                    name: "w".into(),
                    value: 1900.0,
                    variance: 2000.0 * 2000.0,
                }],
            },
            lab_seconds: measured.lab_seconds(),
        },
        _ => measured,
    }
}

#[test]
fn by_default_a_failed_cell_moves_every_gate_half_way_back() {
    let m = after_a_scripted_failure(Retreat::default(), instrument_error);
    assert_eq!(Retreat::default(), Retreat::EveryGate);
    for (g, to) in &m.good {
        let expected = m.now[g] + 0.5 * (to - m.now[g]);
        let at = m.retreat.get(g).copied().unwrap_or(m.now[g]);
        assert!(
            (at - expected).abs() < 1e-6,
            "{g}: {at} mV, expected {expected} mV"
        );
    }
}

#[test]
fn with_lines_kept_the_plungers_retreat_toward_their_corrected_voltages() {
    let m = after_a_scripted_failure(Retreat::EveryGateLinesKept, instrument_error);
    // the line level corrected cell 1's plungers between the two
    // measurements; otherwise the rule is the default's and this proves nothing
    assert!(
        m.line_corrections.values().any(|d| d.abs() > 0.05),
        "no line correction between the measurements: {:?}",
        m.line_corrections
    );
    for (g, to) in &m.good {
        let target = to + m.line_corrections.get(g).copied().unwrap_or(0.0);
        let expected = m.now[g] + 0.5 * (target - m.now[g]);
        let at = m.retreat.get(g).copied().unwrap_or(m.now[g]);
        assert!(
            (at - expected).abs() < 1e-6,
            "{g}: {at} mV, expected {expected} mV"
        );
    }
}

#[test]
fn with_tuning_gates_a_failed_cell_retreats_them_and_its_plungers_follow() {
    tuning_gates_retreat(&after_a_scripted_failure(
        Retreat::TuningGates,
        instrument_error,
    ));
}

#[test]
fn a_cell_whose_w_is_too_uncertain_retreats_only_with_that_rule() {
    let m = after_a_scripted_failure(Retreat::TuningGatesWhenUncertain, too_uncertain_w);
    tuning_gates_retreat(&m);
    // with the other rules it steps on: its tuning gates do not go half-way back
    for rule in [Retreat::TuningGates, Retreat::EveryGate] {
        let m = after_a_scripted_failure(rule, too_uncertain_w);
        let halfway = m.cell.gates.iter().all(|g| {
            let expected = m.now[g] + 0.5 * (m.good[g] - m.now[g]);
            (m.retreat.get(g).copied().unwrap_or(m.now[g]) - expected).abs() < 1e-6
        });
        assert!(!halfway, "{rule:?}");
    }
}

/// What the move after the failure did, and the voltages around it.
struct AfterFailure {
    /// Cell 1's gates at its last good evaluation, mV.
    good: BTreeMap<String, f64>,
    /// At the failed one, mV.
    now: BTreeMap<String, f64>,
    /// The set of cell 1's gates that followed, mV.
    retreat: BTreeMap<String, f64>,
    /// Cell 1's knowledge (gates, compensation).
    cell: CellKnowledge,
    /// What the sets right after cell 1's line scans moved its gates by
    /// between the two measurements (world side), mV.
    line_corrections: BTreeMap<String, f64>,
}

/// Tuning gates half-way back, compensation gates at their matrix times
/// that retreat, and the old rule (every gate half-way) told apart.
fn tuning_gates_retreat(m: &AfterFailure) {
    let (good, now, retreat, cell) = (&m.good, &m.now, &m.retreat, &m.cell);
    // tuning gates: half-way back (the step is well within 10 mV here)
    let mut delta = Vec::new();
    for g in &cell.gates {
        let expected = now[g] + 0.5 * (good[g] - now[g]);
        let to = retreat.get(g).copied().unwrap_or(now[g]);
        assert!(
            (to - expected).abs() < 1e-6,
            "{g}: {to} mV, expected {expected} mV"
        );
        delta.push(to - now[g]);
    }
    assert!(
        delta.iter().map(|d| d * d).sum::<f64>().sqrt() > 0.5,
        "the tuning gates moved between the two measurements: {delta:?}"
    );
    // compensation gates: the virtual-gate matrix times that retreat
    let (comp_gates, matrix) = cell.compensation.as_ref().expect("compensation");
    let mut plunger_apart = 0.0_f64;
    for (g, row) in comp_gates.iter().zip(matrix) {
        let expected = now[g] + row.iter().zip(&delta).map(|(m, d)| m * d).sum::<f64>();
        let to = retreat.get(g).copied().unwrap_or(now[g]);
        assert!(
            (to - expected).abs() < 1e-6,
            "{g}: {to} mV, expected {expected} mV"
        );
        let halfway = now[g] + 0.5 * (good[g] - now[g]);
        plunger_apart = plunger_apart.max((expected - halfway).abs());
    }
    // the old rule (every gate half-way back) would have put some
    // compensation gate elsewhere: the line level had moved it since
    assert!(
        plunger_apart > 0.05,
        "the scenario does not tell the rules apart ({plunger_apart} mV)"
    );
}

/// Cell 1's second measurement in a new phase answered by `script`, with
/// `rule`; the move after it.
fn after_a_scripted_failure(
    rule: Retreat,
    script: fn(&Request, Response) -> Response,
) -> AfterFailure {
    // the world of the other array tests, with `rule`
    let mut settings = ArrayProtocol::default().run_settings();
    settings.retreat = rule;
    let (mut run, mut device) = three_cells_tuned(settings);
    run.set_targets(1, PAPER_SET_POINTS[1]).unwrap();

    // measurement batches of cell 1 in the new phase; the second fails
    let mut measured = 0;
    let mut records: Vec<IterationRecord> = Vec::new();
    let mut retreat: Option<BTreeMap<String, f64>> = None;
    let mut line_corrections: BTreeMap<String, f64> = BTreeMap::new();
    let mut after_line_scan = false;
    for _ in 0..500 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = device.lab_seconds();
                let volts_before = device.voltages_mv();
                let mut answers = device.execute_batch(&batch);
                if measured == 1 && after_line_scan {
                    for (g, v) in device.voltages_mv() {
                        let d = v - volts_before[&g];
                        if g.starts_with("c1.") && d != 0.0 {
                            *line_corrections.entry(g).or_default() += d;
                        }
                    }
                }
                after_line_scan = batch.iter().any(|r| {
                    matches!(r, Request::Measure { scan }
                        if scan.cell == Some(1) && scan.kind == ScanKind::ChemicalPotential)
                });
                if batch.iter().any(|r| is_measurement_of(r, 1)) {
                    measured += 1;
                    if measured == 2 {
                        for (a, r) in answers.iter_mut().zip(&batch) {
                            if is_measurement_of(r, 1) {
                                *a = script(r, a.clone());
                            }
                        }
                    }
                }
                // the first move after the failed evaluation (its record
                // comes at the end of its iteration)
                if measured == 2 && retreat.is_none() {
                    retreat = batch.iter().find_map(|r| match r {
                        Request::SetVoltages { voltages_mv }
                            if voltages_mv.keys().any(|g| g.starts_with("c1.")) =>
                        {
                            Some(voltages_mv.clone())
                        }
                        _ => None,
                    });
                }
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(record) => {
                records.push(*record);
                if retreat.is_some() {
                    break;
                }
            }
            ArrayAction::Idle => break,
        }
    }
    assert_eq!(records.len(), 2, "two iterations in the new phase");
    let good_record = &records[0];
    assert!(
        good_record
            .parameters
            .iter()
            .filter(|p| p.name.starts_with("c1."))
            .all(|p| p.value.is_some()),
        "cell 1's first measurement in the new phase worked"
    );
    let failed_record = &records[1];
    assert!(failed_record
        .parameters
        .iter()
        .any(|p| p.name == "c1.w" && p.value.is_none_or(|w| w == 1900.0)));
    AfterFailure {
        good: cell_1(good_record),
        now: cell_1(failed_record),
        retreat: retreat.expect("a move of cell 1 after its failed evaluation"),
        cell: run.tuner().expect("the joint tuner").cells()[1].clone(),
        line_corrections,
    }
}
