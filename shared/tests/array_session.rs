//! An array run in a run session (`ArraySimulationRun`): the same
//! lifecycle and the same guard as a single double dot, every request of
//! every batch checked against the instrument's read-backs; an instrument
//! that lies, errs or answers the wrong number of requests inside a batch
//! faults the run; a checkpoint mid-run resumes bit-identically; targets
//! are changed per cell by name (`c1.t_sr`).

use std::collections::BTreeMap;

mod support;

use spintune::description::array::ArrayDescription;
use spintune::description::layout::Layout;
use spintune::driver::array::ArraySimulationConfig;
use spintune::driver::{ArraySimulationRun, Halt, Simulated, SimulationRun};
use spintune::protocol::{ControlCommand, EventKind, FaultKind, Request, Response, RunStatus};
use spintune::session::{RunSession, SessionConfig};
use spintune::sim::array::{ArrayConfig, ArrayDevice};

fn config(cells: u32) -> ArraySimulationConfig {
    ArraySimulationConfig {
        array: ArrayConfig::chain(cells, 5, 3),
        ..ArraySimulationConfig::default()
    }
}

#[test]
fn three_cells_tune_into_band_and_a_cell_target_revives_the_run() {
    let mut run = config(3).build().unwrap();
    let mut last = None;
    let mut records = 0;
    while let Some(r) = run.next_iteration().unwrap() {
        records += 1;
        assert!(records <= 60, "not in band within 60 iterations");
        last = Some(r);
    }
    let last = last.expect("records");
    assert!(last.tuned, "{last:?}");
    assert_eq!(run.session().status(), RunStatus::Finished);
    for p in &last.parameters {
        let (v, t, tol) = (p.value.unwrap(), p.target.unwrap(), p.tolerance.unwrap());
        assert!((v - t).abs() <= tol, "{}: {v} vs {t} ± {tol}", p.name);
    }
    // the world agrees (truth read here, outside the run, by the test)
    // a new target for one cell: the run is revived (paused), then resumed
    let status = run
        .control(&ControlCommand::SetTarget {
            parameter: "c1.t_sr".into(),
            target: Some(30.0),
            tolerance: None,
        })
        .unwrap();
    assert_eq!(status, RunStatus::Paused);
    assert_eq!(run.tuner().targets()[1], (30.0, 270.0));
    run.control(&ControlCommand::Resume).unwrap();
    let mut tuned = false;
    for _ in 0..30 {
        match run.next_iteration().unwrap() {
            Some(r) => tuned = r.tuned,
            None => break,
        }
    }
    assert!(
        tuned,
        "cell 1 reached its new target with its neighbours in band"
    );
    // bad target changes name what is wrong and change nothing
    for (parameter, target, tolerance, needle) in [
        ("c7.t_sr", Some(30.0), None, "unknown parameter"),
        ("c1.x", Some(30.0), None, "unknown parameter"),
        ("c1.w", Some(f64::NAN), None, "finite positive"),
        ("c1.w", None, None, "always has a target"),
        (
            "c1.w",
            Some(200.0),
            Some(spintune::parameter::Tolerance::Relative(0.2)),
            "band of an array run",
        ),
    ] {
        let e = run
            .control(&ControlCommand::SetTarget {
                parameter: parameter.into(),
                target,
                tolerance,
            })
            .unwrap_err();
        assert!(e.to_string().contains(needle), "{parameter}: {e}");
    }
    assert_eq!(run.tuner().targets()[1], (30.0, 270.0));
}

/// An array whose answers a test corrupts.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct Faulty {
    inner: ArrayDevice,
    /// Corrupt the n-th batch that contains a set (0-based); `None`: never.
    at_set_batch: Option<usize>,
    set_batches: usize,
    how: Lie,
}

#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
enum Lie {
    /// A set's read-back 3 mV off.
    ReadBack,
    /// One answer of the batch is an instrument error.
    InnerError,
    /// One answer missing.
    Short,
    /// A lost connection inside the batch.
    Disconnected,
}

impl Simulated for Faulty {
    fn execute(&mut self, request: &Request) -> Response {
        let mut answer = self.inner.execute(request);
        let Request::Batch { requests } = request else {
            return answer;
        };
        if !requests
            .iter()
            .any(|r| matches!(r, Request::SetVoltages { .. }))
        {
            return answer;
        }
        let n = self.set_batches;
        self.set_batches += 1;
        if Some(n) != self.at_set_batch {
            return answer;
        }
        if let Response::Batch { responses, .. } = &mut answer {
            let i = requests
                .iter()
                .position(|r| matches!(r, Request::SetVoltages { .. }))
                .unwrap();
            match self.how {
                Lie::ReadBack => {
                    if let Response::VoltagesSet { voltages_mv, .. } = &mut responses[i] {
                        voltages_mv.values_mut().for_each(|v| *v += 3.0);
                    }
                }
                Lie::InnerError => responses[i] = Response::error("DAC channel overheated"),
                Lie::Short => {
                    responses.pop();
                }
                Lie::Disconnected => {
                    responses[i] = Response::Error {
                        message: "socket closed".into(),
                        cause: spintune::protocol::ErrorCause::Disconnected,
                    }
                }
            }
        }
        answer
    }
}

fn faulty_run(how: Lie) -> SimulationRun<spintune::tuner::array_run::ArrayRun, Faulty> {
    let run: ArraySimulationRun = config(2).build().unwrap();
    let session: RunSession<_> = run.session().clone();
    let device = Faulty {
        inner: run.device().clone(),
        at_set_batch: Some(3),
        set_batches: 0,
        how,
    };
    SimulationRun::from_parts(session, device)
}

#[test]
fn a_lie_inside_a_batch_faults_the_run_and_needs_a_person() {
    for (how, kind, needle) in [
        (Lie::ReadBack, FaultKind::Readback, "batch request"),
        (Lie::InnerError, FaultKind::Device, "DAC channel overheated"),
        (Lie::Short, FaultKind::Response, "answered with"),
        (Lie::Disconnected, FaultKind::Disconnected, "socket closed"),
    ] {
        let mut run = faulty_run(how);
        let fault = loop {
            match run.next_iteration() {
                Ok(Some(_)) => {}
                Ok(None) => panic!("{how:?}: the run ended without the fault"),
                Err(Halt::Fault(f)) => break f,
                Err(e) => panic!("{how:?}: {e}"),
            }
        };
        assert_eq!(fault.kind, kind, "{how:?}: {fault:?}");
        assert!(fault.message.contains(needle), "{how:?}: {}", fault.message);
        // nothing more reaches the device until a person resumes (or, for a
        // lost connection, the device is back)
        let before = run.device().inner.lab_seconds();
        assert!(matches!(run.step(), Err(Halt::Fault(_))));
        assert_eq!(run.device().inner.lab_seconds(), before);
        if kind != FaultKind::Disconnected {
            run.control(&ControlCommand::Resume).unwrap();
            // resumed: every gate is read back first, then it tunes on
            let r = run.next_iteration().unwrap();
            assert!(r.is_some(), "{how:?}: the run goes on after resume");
        }
    }
}

#[test]
fn a_gate_moved_behind_a_restored_array_run_faults_before_anything_moves() {
    // a device that answers honestly but was moved 20 mV behind the run's
    // back after the first read: the next read-back is a `moved` fault, and
    // nothing was set
    let mut run = config(2).build().unwrap();
    for _ in 0..3 {
        run.step().unwrap();
    }
    let gate = "c1.SB".to_string();
    let at = run.device().voltages_mv()[&gate];
    let json = serde_json::to_string(&run).unwrap();
    // restore from a checkpoint (read-backs are not kept) after a person
    // moved the gate by hand
    let mut restored: ArraySimulationRun = serde_json::from_str(&json).unwrap();
    restored.device_mut().execute(&Request::SetVoltages {
        voltages_mv: BTreeMap::from([(gate.clone(), at + 5.0)]),
    });
    let restored_at = restored.device().voltages_mv()[&gate];
    assert_eq!(restored_at, at + 5.0);
    let fault = loop {
        match restored.step() {
            Ok(_) => {}
            Err(Halt::Fault(f)) => break f,
            Err(e) => panic!("{e}"),
        }
    };
    assert_eq!(fault.kind, FaultKind::Moved, "{fault:?}");
    assert!(fault.moved.iter().any(|m| m.gate == gate), "{fault:?}");
    assert_eq!(
        restored.device().voltages_mv()[&gate],
        at + 5.0,
        "nothing moved it"
    );
}

#[test]
fn a_checkpoint_mid_run_resumes_bit_identically() {
    let mut a = config(2).build().unwrap();
    let straight: Vec<_> = (0..3)
        .map(|_| a.next_iteration().unwrap().unwrap())
        .collect();
    let mut b = config(2).build().unwrap();
    b.next_iteration().unwrap().unwrap();
    let json = serde_json::to_string(&b).unwrap();
    let mut b: ArraySimulationRun = serde_json::from_str(&json).unwrap();
    let resumed: Vec<_> = (0..2)
        .map(|_| b.next_iteration().unwrap().unwrap())
        .collect();
    assert_eq!(
        serde_json::to_string(&resumed).unwrap(),
        serde_json::to_string(&straight[1..]).unwrap()
    );
    let _ = SessionConfig::default();
}

/// Cells that share a sensor have their scans skipped when the filter
/// predicts them in band with margin: such an iteration reports the
/// prediction as an event and no value for the skipped cell, and asks the
/// world for fewer scans; with one sensor per cell nothing is ever skipped
/// (it would save no lab time). The run still ends with every cell in band.
#[test]
fn cells_sharing_a_sensor_skip_scans_predicted_in_band_and_nothing_else_does() {
    let skipped_in = |groups: Option<Vec<Vec<u32>>>| {
        let mut c = config(3);
        c.array.readout_groups = groups;
        let mut run = c.build().unwrap();
        let mut skips = 0;
        let mut last = None;
        let mut changed = false;
        for _ in 0..120 {
            let Some(r) = run.next_iteration().unwrap() else {
                if changed {
                    break;
                }
                // tuned: one cell's new target, its neighbours held in band
                run.control(&ControlCommand::SetTarget {
                    parameter: "c1.t_sr".into(),
                    target: Some(30.0),
                    tolerance: None,
                })
                .unwrap();
                run.control(&ControlCommand::Resume).unwrap();
                changed = true;
                continue;
            };
            for e in &r.events {
                if let EventKind::ConfirmationSkipped { parameter, .. } = &e.kind {
                    skips += 1;
                    let p = r.parameters.iter().find(|p| &p.name == parameter).unwrap();
                    assert_eq!(p.value, None, "a skipped scan has no value: {p:?}");
                }
            }
            last = Some(r);
        }
        let last = last.unwrap();
        assert!(changed && last.tuned, "{last:?}");
        skips
    };
    assert_eq!(skipped_in(None), 0);
    assert!(skipped_in(Some(vec![vec![0, 1, 2]])) > 0);
}

/// A run that cannot tune gives up after `tuning.max_iterations` since the
/// start (finished, not tuned) instead of measuring forever; a target
/// change revives it for as many again.
#[test]
fn a_run_that_cannot_tune_gives_up_after_max_iterations_and_a_target_revives_it() {
    let mut c = config(2);
    c.tuning.relative_tolerance = 1e-4; // a band no measurement meets
    c.tuning.max_iterations = Some(4);
    let mut run = c.build().unwrap();
    let mut records = Vec::new();
    while let Some(r) = run.next_iteration().unwrap() {
        records.push(r);
        assert!(records.len() <= 4, "went on past max_iterations");
    }
    assert_eq!(records.len(), 4);
    assert!(!records.last().unwrap().tuned);
    assert_eq!(run.session().status(), RunStatus::Finished);
    let status = run
        .control(&ControlCommand::SetTarget {
            parameter: "c0.w".into(),
            target: Some(250.0),
            tolerance: None,
        })
        .unwrap();
    assert_eq!(status, RunStatus::Paused);
    run.control(&ControlCommand::Resume).unwrap();
    let mut again = 0;
    while run.next_iteration().unwrap().is_some() {
        again += 1;
        assert!(again <= 4, "went on past max_iterations after the change");
    }
    assert_eq!(again, 4);
    let mut bad = config(2);
    bad.tuning.max_iterations = Some(0);
    assert_eq!(bad.build().err().unwrap().field, "tuning.max_iterations");
}

#[test]
fn bad_configs_name_the_field() {
    let e = serde_json::from_str::<ArraySimulationConfig>(r#"{"array": {"cells": 3, "seed": 1}}"#)
        .unwrap_err();
    assert!(e.to_string().contains("device_seed"), "{e}");
    let mut c = config(3);
    c.targets = vec![(20.0, 270.0); 2];
    assert_eq!(c.build().err().unwrap().field, "targets");
    c.targets = vec![(20.0, 270.0), (20.0, 5.0), (20.0, 270.0)];
    assert_eq!(c.build().err().unwrap().field, "targets[1]");
    let mut c = config(17);
    c.targets = vec![(20.0, 270.0)];
    assert_eq!(c.build().err().unwrap().field, "array.cells");
    let mut c = config(2);
    c.tuning.line_rounds = 9;
    assert_eq!(c.build().err().unwrap().field, "tuning.line_rounds");
    // the lines' check before a stop must sit above the tolerance that
    // line corrections aim at (a line beyond it is taken as lost)
    let mut c = config(2);
    c.tuning.line_tolerance_mv = 0.5;
    c.tuning.verify_lines_above_mv = Some(0.3);
    let e = c.build().err().unwrap();
    assert_eq!(e.field, "tuning.verify_lines_above_mv", "{e}");
    assert!(e.to_string().contains("line_tolerance_mv"), "{e}");
    c.tuning.verify_lines_above_mv = Some(0.5);
    assert!(c.build().is_ok());
    // a ladder needs an even number of cells, at least 4: named where it
    // was written, in the simulated array or in the lab's description
    let mut c = config(3);
    c.array.layout = Layout::Ladder;
    let e = c.build().err().unwrap();
    assert_eq!(e.field, "array.layout", "{e}");
    let mut d = ArrayDescription::simulated(3, None);
    d.layout = Layout::Ladder;
    let mut c = config(3);
    c.description = Some(d);
    assert_eq!(c.build().err().unwrap().field, "description.layout");
    let mut c = config(4);
    c.array.layout = Layout::Ladder;
    let mut run = c.build().unwrap();
    assert!(run.next_iteration().unwrap().is_some());
}

/// Bounded by construction (invariant 8): at the most cells an array may
/// have (16), one record — every cell's parameters, every gate's voltage,
/// the learned rows over every tuning gate — stays below 64 KiB of JSON
/// (documented in docs/array.md). Array records carry no raw scans.
#[test]
fn a_record_of_sixteen_cells_stays_below_64_kib() {
    let mut cfg = config(spintune::sim::array::MAX_CELLS);
    cfg.array.device_seed = 0;
    let mut run = cfg.build().unwrap();
    let r = run.next_iteration().unwrap().expect("a record");
    assert_eq!(r.parameters.len(), 32);
    assert_eq!(r.gradients.len(), 32);
    assert!(r.gradients.iter().all(|g| g.gradient.len() == 64));
    assert!(r.scans.is_empty());
    let bytes = serde_json::to_string(&r).unwrap().len();
    eprintln!("a 16-cell record: {bytes} bytes of JSON");
    assert!(bytes < 64 * 1024, "{bytes} bytes");
}

/// A batch handed out but not answered is planned again when a read-back
/// moved the gates (`Plan::adopt_voltages`). A park whose sweeps were out
/// (some cells sweeping, others parked on their predicted flank) is planned
/// again from the new voltages, every one of its cells, instead of ending
/// the run: the regression that stalled the array bridge's fault test.
#[test]
fn a_park_dropped_by_a_moved_read_back_is_planned_again() {
    use spintune::benchmark::array::{cell_tuner, ArrayProtocol};
    use spintune::protocol::ScanKind;
    use spintune::session::Plan;
    use spintune::tuner::array_run::ArrayAction;

    let protocol = ArrayProtocol::default();
    let cells = (0..3).map(|c| cell_tuner(c, &protocol)).collect();
    let (mut run, mut device) = support::array::three_cells(cells);
    let is_sweep = |r: &Request| matches!(r, Request::Measure { scan } if scan.kind == ScanKind::SensingDot && scan.cell.is_some());
    // run until the joint loop hands out a park's sweeps
    let mut parks = 0;
    let batch = loop {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                if run.tuner().is_some() && batch.iter().all(is_sweep) {
                    parks += 1;
                    if parks == 3 {
                        break batch;
                    }
                }
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(_) => {}
            ArrayAction::Idle => panic!("tuned before its third park"),
        }
    };
    // someone moves c1.SD1 by 0.5 mV; the read-back shows it
    let mut v = device.voltages_mv();
    let g = "c1.SD1".to_string();
    let moved = v[&g] + 0.5;
    device.execute(&Request::SetVoltages {
        voltages_mv: [(g.clone(), moved)].into(),
    });
    v.insert(g.clone(), moved);
    run.adopt_voltages(&v, 0.0);
    let ArrayAction::Execute(again) = run.poll().unwrap() else {
        panic!("no batch after the read-back")
    };
    assert!(!again.is_empty() && again.iter().all(is_sweep), "{again:?}");
    assert!(again.len() >= batch.len(), "{again:?} vs {batch:?}");
    // c1's sweep, if it sweeps, is centred on the moved gate
    for r in &again {
        if let Request::Measure { scan } = r {
            let s = scan.sweep.as_ref().unwrap();
            if s.gate == g {
                assert!(((s.from_mv + s.to_mv) / 2.0 - moved).abs() < 1e-9, "{s:?}");
            }
        }
    }
    // and the run goes on: three more iterations without an error
    let mut iterations = 0;
    while iterations < 3 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(_) => iterations += 1,
            ArrayAction::Idle => break,
        }
    }
}
