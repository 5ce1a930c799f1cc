//! One cell of an array run seen as a run of one double dot, so that the
//! single-cell charts ([`crate::ui::Dashboard`]) draw it: each record
//! filtered to the cell's parameters, gates and gradient rows (over the
//! cell's own gates; the crosstalk onto the neighbours' gates is in the
//! overview's heat map), every name without its `c{k}.` prefix.

use spintune::protocol::{EventKind, IterationRecord};
use spintune::sim::array::split_gate;

use crate::array_view::{in_band, Band};
use crate::history::RunHistory;

/// `name` without the prefix of `cell` (`c3.SB` → `SB` for cell 3), or
/// `None` if it names another cell or none.
pub fn local_name(name: &str, cell: u32) -> Option<&str> {
    split_gate(name).and_then(|(c, local)| (c == cell).then_some(local))
}

/// The parameter an event is about, if it names one.
fn event_parameter(kind: &mut EventKind) -> Option<&mut String> {
    match kind {
        EventKind::NotRepresentable { parameter, .. }
        | EventKind::FiniteDifferenceFailed { parameter }
        | EventKind::TooUncertain { parameter, .. }
        | EventKind::OutlierGated { parameter, .. }
        | EventKind::NoMeasurement { parameter }
        | EventKind::UpdateRejected { parameter, .. }
        | EventKind::ConfirmationSkipped { parameter, .. }
        | EventKind::MeasurementSkipped { parameter, .. }
        | EventKind::KeepCheck { parameter, .. }
        | EventKind::BandEntryRechecked { parameter, .. } => Some(parameter),
        _ => None,
    }
}

/// Record `r` of an array run as cell `cell` alone: its parameters, its
/// tuning gates (voltages of every gate of the cell), its gradient rows
/// and steps over its own gates (covariance likewise), `tuned` when both
/// its parameters are in band, the events naming one of its parameters;
/// names without the cell prefix. Iteration, lab time, scan counts and
/// failed evaluations are the array's; scans are dropped.
pub fn cell_record(r: &IterationRecord, cell: u32) -> IterationRecord {
    let own: Vec<usize> = (0..r.gates.len())
        .filter(|&i| local_name(&r.gates[i], cell).is_some())
        .collect();
    let pick = |v: &[f64]| -> Vec<f64> { own.iter().filter_map(|&i| v.get(i).copied()).collect() };
    let parameters: Vec<_> = r
        .parameters
        .iter()
        .filter_map(|p| {
            let mut p2 = p.clone();
            p2.name = local_name(&p.name, cell)?.to_string();
            Some(p2)
        })
        .collect();
    let gradients = r
        .gradients
        .iter()
        .filter_map(|g| {
            let mut g2 = g.clone();
            g2.parameter = local_name(&g.parameter, cell)?.to_string();
            g2.gradient = pick(&g.gradient);
            g2.covariance = g.covariance.as_ref().map(|c| {
                own.iter()
                    .filter_map(|&i| c.get(i).map(|row| pick(row)))
                    .collect()
            });
            Some(g2)
        })
        .collect();
    let events = r
        .events
        .iter()
        .filter_map(|e| {
            let mut e2 = e.clone();
            let p = event_parameter(&mut e2.kind)?;
            *p = local_name(p, cell)?.to_string();
            Some(e2)
        })
        .collect();
    let keep = r.keep.clone().map(|mut k| {
        k.next_check = k
            .next_check
            .iter()
            .filter_map(|n| local_name(n, cell).map(str::to_string))
            .collect();
        k
    });
    IterationRecord {
        iteration: r.iteration,
        voltages_mv: r
            .voltages_mv
            .iter()
            .filter_map(|(g, v)| Some((local_name(g, cell)?.to_string(), *v)))
            .collect(),
        gates: own
            .iter()
            .filter_map(|&i| local_name(&r.gates[i], cell).map(str::to_string))
            .collect(),
        tuned: Band::of(
            parameters
                .iter()
                .map(|p| in_band(p.value, p.target, p.tolerance)),
        ) == Band::In,
        parameters,
        gradients,
        step_mv: pick(&r.step_mv),
        lab_seconds: r.lab_seconds,
        scan_counts: r.scan_counts.clone(),
        failed_evaluations: r.failed_evaluations,
        scans: Vec::new(),
        events,
        keep,
    }
}

/// Bring `cell`'s history `into` up to date with the array run's `full`
/// history: every row of `full` it lacks is added as [`cell_record`] of
/// [`RunHistory::record`]; the total follows. A history holding rows that
/// `full` does not (another run, or `full` was cleared) starts over.
/// Returns the rows added.
pub fn sync(full: &RunHistory, cell: u32, into: &mut RunHistory) -> usize {
    if into.rows().iter().any(|r| full.row(r.iteration).is_none()) {
        into.clear();
    }
    let missing: Vec<IterationRecord> = full
        .rows()
        .iter()
        .filter(|r| into.row(r.iteration).is_none())
        .filter_map(|r| full.record(r.iteration))
        .map(|r| cell_record(&r, cell))
        .collect();
    let added = if missing.is_empty() {
        0
    } else {
        into.insert(missing).added
    };
    into.set_total(full.total());
    added
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::array_view::fake_array_records;
    use spintune::protocol::TunerEvent;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_cell_s_record_is_a_single_double_dot_s_record() {
        let mut r = fake_array_records(3, 3).remove(2);
        r.events.push(TunerEvent {
            level: "array".into(),
            kind: EventKind::TooUncertain {
                parameter: "c1.w".into(),
                value: 300.0,
                std: 90.0,
                unit: "µV".into(),
            },
        });
        r.events.push(TunerEvent {
            level: "array".into(),
            kind: EventKind::NoMeasurement {
                parameter: "c2.t_sr".into(),
            },
        });
        let c = cell_record(&r, 1);
        assert_eq!(c.iteration, 2);
        assert_eq!(
            c.parameters
                .iter()
                .map(|p| p.name.as_str())
                .collect::<Vec<_>>(),
            ["t_sr", "w"]
        );
        assert_eq!(c.parameters[1].value, r.parameters[3].value);
        assert_eq!(c.gates, ["N", "SA", "SB", "T"]);
        assert_eq!(c.voltages_mv.len(), 4);
        assert_eq!(c.voltages_mv["SB"], r.voltages_mv["c1.SB"]);
        assert_eq!(c.gradients.len(), 2);
        assert_eq!(c.gradients[1].parameter, "w");
        assert_eq!(c.gradients[1].unit, "1/mV");
        assert_eq!(c.gradients[1].gradient, r.gradients[3].gradient[4..8]);
        assert_eq!(c.step_mv.len(), 4);
        assert!(!c.tuned, "cell 1 is out of band at iteration 2");
        assert!(cell_record(&r, 0).tuned);
        assert_eq!(c.lab_seconds, r.lab_seconds);
        assert_eq!(c.events.len(), 1);
        assert!(
            matches!(&c.events[0].kind, EventKind::TooUncertain { parameter, .. } if parameter == "w")
        );
        // a cell the record does not have: nothing of it
        let none = cell_record(&r, 7);
        assert!(none.parameters.is_empty() && none.gates.is_empty());
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_covariance_is_cut_to_the_cell_s_gates() {
        let mut r = fake_array_records(1, 2).remove(0);
        let n = r.gates.len();
        r.gradients[2].covariance = Some(
            (0..n)
                .map(|i| (0..n).map(|j| (10 * i + j) as f64).collect())
                .collect(),
        );
        let c = cell_record(&r, 1);
        let cov = c.gradients[0].covariance.as_ref().unwrap();
        assert_eq!(cov.len(), 4);
        assert_eq!(cov[0], [44.0, 45.0, 46.0, 47.0]);
        assert_eq!(cov[3], [74.0, 75.0, 76.0, 77.0]);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_cell_s_history_follows_the_run_s_incrementally() {
        let recs = fake_array_records(10, 3);
        let mut full = RunHistory::new();
        full.insert(recs[4..7].to_vec());
        full.set_total(10);
        let mut cell = RunHistory::new();
        assert_eq!(sync(&full, 2, &mut cell), 3);
        assert_eq!(cell.layout().gates, ["N", "SA", "SB", "T"]);
        assert_eq!(
            cell.layout().parameters,
            [
                ("t_sr".to_string(), "ns".to_string()),
                ("w".to_string(), "µV".to_string())
            ]
        );
        assert_eq!(cell.total(), 10);
        assert_eq!(sync(&full, 2, &mut cell), 0, "nothing new");
        // older pages and live records arrive
        full.insert(recs[0..4].to_vec());
        full.insert([recs[7].clone()]);
        assert_eq!(sync(&full, 2, &mut cell), 5);
        assert_eq!(cell.len(), 8);
        let newest = cell.latest().unwrap();
        assert_eq!(newest.iteration, 7);
        assert_eq!(*newest, cell_record(&recs[7].summary(), 2));
        // an older row rebuilt from the numbers equals the filtered record
        let old = cell.record(1).unwrap();
        let want = cell_record(&recs[1], 2);
        assert_eq!(old.parameters, want.parameters);
        assert_eq!(old.gradients, want.gradients);
        assert_eq!(old.step_mv, want.step_mv);
        assert_eq!(old.tuned, want.tuned);
        // another run: start over
        let mut other = RunHistory::new();
        other.insert(fake_array_records(2, 3));
        assert_eq!(sync(&other, 2, &mut cell), 2);
        assert_eq!(cell.len(), 2);
    }
}
