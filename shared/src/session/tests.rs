//! Unit tests of the run session against the simulated device. The
//! randomized model test with a lying instrument is
//! `shared/tests/session_model.rs`.

use std::collections::BTreeMap;

use super::*;
use crate::driver::SimulationConfig;
use crate::protocol::{ClearedBy, EventKind};
use crate::sim::SimulatedDevice;

fn setup(max_iterations: u64) -> (RunSession, SimulatedDevice) {
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(max_iterations);
    let dev = SimulatedDevice::new(cfg.device.clone(), &cfg.tuner.gates, 3).unwrap();
    (
        RunSession::new(cfg.tuner, SessionConfig::default()).unwrap(),
        dev,
    )
}

/// Poll until the session hands out a request (handling everything else);
/// commits are collected.
fn next_request(s: &mut RunSession, commits: &mut Vec<IterationRecord>) -> Option<Request> {
    for _ in 0..100 {
        match s.poll() {
            Output::Execute(r) => return Some(r),
            Output::Commit(r) => commits.push(*r),
            Output::Wait | Output::Done(_) => return None,
            Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
        }
    }
    panic!("session did not settle")
}

fn all_gates() -> usize {
    crate::sim::default_gates().len()
}

#[test]
fn every_gate_is_read_back_before_the_first_request() {
    let (mut s, mut dev) = setup(1);
    let mut commits = Vec::new();
    assert_eq!(s.poll(), Output::Publish(RunStatus::Running));
    let first = next_request(&mut s, &mut commits).unwrap();
    assert!(
        matches!(&first, Request::ReadVoltages { gates } if gates.len() == all_gates()),
        "{first:?}"
    );
    s.feed(dev.execute(&first)).unwrap();
    assert_eq!(s.guard().readback_mv().len(), all_gates());
}

#[test]
fn pause_mid_iteration_waits_then_resume_reads_every_gate_again() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    for _ in 0..5 {
        let r = next_request(&mut s, &mut commits).unwrap();
        s.feed(dev.execute(&r)).unwrap();
    }
    let r = next_request(&mut s, &mut commits).unwrap();
    assert_eq!(s.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
    // the request already at the device is answered and recorded...
    s.feed(dev.execute(&r)).unwrap();
    // ... but nothing more is issued while paused
    assert_eq!(s.poll(), Output::Publish(RunStatus::Paused));
    assert_eq!(s.poll(), Output::Wait);
    assert_eq!(s.poll(), Output::Wait);
    assert_eq!(s.control(&ControlCommand::Resume), Ok(RunStatus::Running));
    assert!(s.guard().readback_mv().is_empty());
    let again = next_request(&mut s, &mut commits).unwrap();
    assert!(
        matches!(&again, Request::ReadVoltages { gates } if gates.len() == all_gates()),
        "{again:?}"
    );
}

#[test]
fn stop_with_a_request_at_the_device_issues_nothing_more() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    let r = next_request(&mut s, &mut commits).unwrap();
    assert_eq!(s.control(&ControlCommand::Stop), Ok(RunStatus::Stopping));
    // polling again does not re-issue the request at the device
    assert_eq!(s.poll(), Output::Publish(RunStatus::Stopping));
    assert_eq!(s.poll(), Output::Wait);
    s.feed(dev.execute(&r)).unwrap();
    assert_eq!(s.poll(), Output::Publish(RunStatus::Stopped));
    // (that answer was the new run's first read-back: where the gates are is
    // persisted, nothing is requested)
    assert_eq!(s.poll(), Output::Save);
    assert_eq!(s.poll(), Output::Done(RunEnd::Stopped));
    assert!(matches!(
        s.control(&ControlCommand::Resume),
        Err(ControlError::Conflict { .. })
    ));
    assert_eq!(s.status(), RunStatus::Stopped);
}

#[test]
fn step_runs_exactly_one_iteration_then_pauses() {
    let (mut s, mut dev) = setup(10);
    let mut commits = Vec::new();
    s.control(&ControlCommand::Pause).unwrap();
    assert_eq!(next_request(&mut s, &mut commits), None);
    s.control(&ControlCommand::Step).unwrap();
    while let Some(r) = next_request(&mut s, &mut commits) {
        s.feed(dev.execute(&r)).unwrap();
    }
    assert_eq!(commits.len(), 1);
    assert_eq!(s.status(), RunStatus::Paused);
}

#[test]
fn a_target_change_mid_iteration_applies_from_the_next_and_is_checkpointed() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    // run into the first iteration (finite differences first)
    let r = next_request(&mut s, &mut commits).unwrap();
    s.feed(dev.execute(&r)).unwrap();
    let r = next_request(&mut s, &mut commits).unwrap();
    assert!(!s.at_boundary());
    let cmd = ControlCommand::SetTarget {
        parameter: "t_sr".into(),
        target: Some(70.0),
        tolerance: None,
    };
    s.control(&cmd).unwrap();
    // invalid changes are refused at once and change nothing
    let bad = ControlCommand::SetTarget {
        parameter: "nope".into(),
        target: Some(1.0),
        tolerance: None,
    };
    assert!(matches!(s.control(&bad), Err(ControlError::Invalid(_))));
    s.feed(dev.execute(&r)).unwrap();
    let commit = loop {
        match s.poll() {
            Output::Execute(r) => s.feed(dev.execute(&r)).unwrap(),
            Output::Commit(rec) => break rec,
            _ => {}
        }
    };
    // the first record still has the old target; the checkpoint has the new one
    let t = |rec: &IterationRecord| {
        rec.parameters
            .iter()
            .find(|p| p.name == "t_sr")
            .unwrap()
            .target
    };
    assert_eq!(t(&commit), Some(20.0));
    let restored: RunSession = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
    let spec = |s: &RunSession| s.tuner().config().top().parameters[0].target;
    assert_eq!(spec(&restored), Some(70.0));
}

/// Runs until the first read is answered; returns the next request.
fn first_request_after_read(
    s: &mut RunSession,
    dev: &mut SimulatedDevice,
    commits: &mut Vec<IterationRecord>,
) -> Request {
    let read = next_request(s, commits).unwrap();
    s.feed(dev.execute(&read)).unwrap();
    next_request(s, commits).unwrap()
}

fn published_fault(s: &mut RunSession) -> Fault {
    match s.poll() {
        Output::Publish(RunStatus::Faulted { fault }) => fault,
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_disconnection_faults_keeps_the_request_and_reconnecting_resumes_after_a_read_back() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    let r = first_request_after_read(&mut s, &mut dev, &mut commits);
    s.feed(Response::disconnected("the lab bridge disconnected"))
        .unwrap();
    let fault = published_fault(&mut s);
    assert_eq!(fault.kind, FaultKind::Disconnected);
    assert_eq!(fault.cleared_by, ClearedBy::Reconnect);
    assert!(s.awaits_reconnect());
    assert_eq!(s.poll(), Output::Wait);
    assert!(s.device_recovered());
    let read = next_request(&mut s, &mut commits).unwrap();
    assert!(matches!(read, Request::ReadVoltages { .. }));
    s.feed(dev.execute(&read)).unwrap();
    assert_eq!(next_request(&mut s, &mut commits), Some(r));
    // a user's pause is not lifted by a device recovering
    s.control(&ControlCommand::Pause).unwrap();
    assert!(!s.device_recovered());
}

#[test]
fn faults_that_need_a_person_never_clear_on_reconnect() {
    // leakage (an instrument error), a refused read-back, a moved gate
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    let r = first_request_after_read(&mut s, &mut dev, &mut commits);
    s.feed(Response::error("leakage on SB: 500 nA exceeds 100 nA"))
        .unwrap();
    let fault = published_fault(&mut s);
    assert_eq!(
        (fault.kind, fault.cleared_by),
        (FaultKind::Device, ClearedBy::Resume)
    );
    for _ in 0..3 {
        assert!(!s.device_recovered());
        assert!(!s.awaits_reconnect());
        assert_eq!(
            s.poll(),
            Output::Wait,
            "nothing is requested until a person resumes"
        );
    }
    assert_eq!(s.control(&ControlCommand::Resume), Ok(RunStatus::Running));
    let read = next_request(&mut s, &mut commits).unwrap();
    // the read-back says 1e308: refused, nothing moves, and a reconnect does not help
    let Request::ReadVoltages { gates } = &read else {
        panic!("{read:?}")
    };
    let mut lie: BTreeMap<String, f64> = dev.voltages_mv().clone();
    lie.retain(|g, _| gates.contains(g));
    lie.insert("N".into(), 1e308);
    s.feed(Response::VoltagesRead {
        voltages_mv: lie,
        lab_seconds: 0.0,
    })
    .unwrap();
    let fault = published_fault(&mut s);
    assert_eq!(fault.kind, FaultKind::Readback, "{fault}");
    assert!(fault.message.contains("outside its limits"), "{fault}");
    assert!(!s.device_recovered());
    assert_eq!(s.poll(), Output::Wait);
    assert!(s.guard().readback_mv().is_empty());
    // an honest read after a person resumes: the kept request goes out
    s.control(&ControlCommand::Resume).unwrap();
    let read = next_request(&mut s, &mut commits).unwrap();
    s.feed(dev.execute(&read)).unwrap();
    assert_eq!(next_request(&mut s, &mut commits), Some(r));
}

#[test]
fn non_finite_and_out_of_limit_read_backs_fault_with_nothing_moved() {
    for (value, needle) in [
        (f64::NAN, "not a finite number"),
        (f64::INFINITY, "not a finite number"),
        (9.91e40, "outside its limits"),
        (1e308, "outside its limits"),
    ] {
        let (mut s, dev) = setup(3);
        let mut commits = Vec::new();
        let read = next_request(&mut s, &mut commits).unwrap();
        let Request::ReadVoltages { gates } = &read else {
            panic!("{read:?}")
        };
        let mut answer: BTreeMap<String, f64> = dev.voltages_mv().clone();
        answer.retain(|g, _| gates.contains(g));
        answer.insert("SB".into(), value);
        s.feed(Response::VoltagesRead {
            voltages_mv: answer,
            lab_seconds: 0.0,
        })
        .unwrap();
        let fault = published_fault(&mut s);
        assert_eq!(fault.kind, FaultKind::Readback, "{value}");
        assert!(fault.message.contains(needle), "{value}: {fault}");
        assert_eq!(next_request(&mut s, &mut commits), None, "nothing moves");
    }
    // 5 mV outside the limits (the issue's 195 mV physical step)
    let (mut s, dev) = setup(3);
    let mut commits = Vec::new();
    let read = next_request(&mut s, &mut commits).unwrap();
    let Request::ReadVoltages { gates } = &read else {
        panic!("{read:?}")
    };
    let spec = s.guard().limits().gate("N").unwrap().clone();
    let mut answer: BTreeMap<String, f64> = dev.voltages_mv().clone();
    answer.retain(|g, _| gates.contains(g));
    answer.insert("N".into(), spec.min_mv - 5.0);
    s.feed(Response::VoltagesRead {
        voltages_mv: answer,
        lab_seconds: 0.0,
    })
    .unwrap();
    assert_eq!(published_fault(&mut s).kind, FaultKind::Readback);
    assert_eq!(next_request(&mut s, &mut commits), None);
}

#[test]
fn a_gate_moved_far_while_faulted_waits_for_accept_positions_then_steps_from_there() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    // run until a move of the top level is handed out
    let mv = loop {
        let r = next_request(&mut s, &mut commits).unwrap();
        if matches!(&r, Request::SetVoltages { voltages_mv } if voltages_mv.contains_key("N")) {
            break r;
        }
        s.feed(dev.execute(&r)).unwrap();
    };
    // the device errors; meanwhile someone moves N by 25 mV
    s.feed(Response::error("timeout")).unwrap();
    let n = dev.voltages_mv()["N"];
    dev.execute(&Request::SetVoltages {
        voltages_mv: BTreeMap::from([("N".to_string(), n + 25.0)]),
    });
    // accept_positions is refused for any fault but a moved one
    assert!(matches!(
        s.control(&ControlCommand::AcceptPositions),
        Err(ControlError::Conflict { .. })
    ));
    for _ in 0..2 {
        // resume reads every gate: N is 25 mV from where the run left it
        s.control(&ControlCommand::Resume).unwrap();
        let read = next_request(&mut s, &mut commits).unwrap();
        s.feed(dev.execute(&read)).unwrap();
        let fault = published_fault(&mut s);
        assert_eq!(fault.kind, FaultKind::Moved, "{fault}");
        assert_eq!(fault.cleared_by, ClearedBy::AcceptPositions);
        assert_eq!(fault.moved.len(), 1, "{fault:?}");
        assert_eq!(fault.moved[0].gate, "N");
        assert_eq!(fault.moved[0].read_mv, n + 25.0);
        assert!(fault.moved[0].left_to_mv < n + 15.0);
        assert!(!s.device_recovered());
        assert_eq!(next_request(&mut s, &mut commits), None, "nothing moves");
    }
    // a restored checkpoint remembers where the run left the gates
    let mut s: RunSession = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
    assert_eq!(
        s.control(&ControlCommand::AcceptPositions),
        Ok(RunStatus::Paused)
    );
    assert_eq!(
        next_request(&mut s, &mut commits),
        None,
        "accepting does not resume"
    );
    s.control(&ControlCommand::Resume).unwrap();
    let read = next_request(&mut s, &mut commits).unwrap();
    s.feed(dev.execute(&read)).unwrap();
    let replanned = next_request(&mut s, &mut commits).unwrap();
    assert_ne!(replanned, mv, "the move was not re-planned");
    let Request::SetVoltages { voltages_mv } = &replanned else {
        panic!("{replanned:?}")
    };
    let max_step = s.guard().limits().gate("N").unwrap().max_step_mv;
    assert!((voltages_mv["N"] - (n + 25.0)).abs() <= max_step + 1e-9);
    s.feed(dev.execute(&replanned)).unwrap();
    while commits.is_empty() {
        let r = next_request(&mut s, &mut commits).unwrap();
        s.feed(dev.execute(&r)).unwrap();
    }
    assert!(commits[0].events.iter().any(|e| matches!(
        &e.kind,
        EventKind::InstrumentMoved { gate, .. } if gate == "N"
    )));
}

#[test]
fn a_gate_left_anywhere_in_a_sweep_may_read_anywhere_in_it() {
    let (mut s, mut dev) = setup(3);
    let mut commits = Vec::new();
    let sweep = loop {
        let r = next_request(&mut s, &mut commits).unwrap();
        if let Request::Measure { scan } = &r {
            if let Some(sw) = &scan.sweep {
                break (r.clone(), sw.clone());
            }
        }
        s.feed(dev.execute(&r)).unwrap();
    };
    let (request, sw) = sweep;
    s.feed(dev.execute(&request)).unwrap();
    // the instrument left the swept gate at the sweep's end: plausible
    let read = next_request(&mut s, &mut commits).unwrap();
    assert_eq!(
        read,
        Request::ReadVoltages {
            gates: vec![sw.gate.clone()]
        }
    );
    s.feed(Response::VoltagesRead {
        voltages_mv: BTreeMap::from([(sw.gate.clone(), sw.to_mv)]),
        lab_seconds: 0.0,
    })
    .unwrap();
    assert!(
        !matches!(s.status(), RunStatus::Faulted { .. }),
        "{:?}",
        s.status()
    );
}

#[test]
fn pacing_is_a_sleep_output_after_each_iteration_while_running() {
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(2);
    let mut dev = SimulatedDevice::new(cfg.device.clone(), &cfg.tuner.gates, 3).unwrap();
    let mut s = RunSession::new(
        cfg.tuner,
        SessionConfig {
            iteration_delay_ms: 250,
            ..SessionConfig::default()
        },
    )
    .unwrap();
    let mut sleeps = 0;
    let mut commits = 0;
    loop {
        match s.poll() {
            Output::Execute(r) => s.feed(dev.execute(&r)).unwrap(),
            Output::Commit(_) => commits += 1,
            Output::Sleep { ms } => {
                assert_eq!(ms, 250);
                sleeps += 1;
            }
            Output::Done(end) => {
                assert_eq!(end, RunEnd::Finished);
                break;
            }
            _ => {}
        }
    }
    assert_eq!((commits, sleeps), (2, 2));
    // pausing and resuming at the boundary does not skip the pause
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(5);
    let mut dev = SimulatedDevice::new(cfg.device.clone(), &cfg.tuner.gates, 3).unwrap();
    let mut s = RunSession::new(
        cfg.tuner,
        SessionConfig {
            iteration_delay_ms: 1000,
            ..SessionConfig::default()
        },
    )
    .unwrap();
    let (mut commits, mut sleeps, mut interrupted) = (0, 0, false);
    loop {
        match s.poll() {
            Output::Execute(r) => s.feed(dev.execute(&r)).unwrap(),
            Output::Commit(_) => {
                commits += 1;
                interrupted = false;
            }
            Output::Sleep { .. } => {
                sleeps += 1;
                if !interrupted {
                    // a user pauses and resumes during the pause: it starts over
                    s.control(&ControlCommand::Pause).unwrap();
                    s.control(&ControlCommand::Resume).unwrap();
                    interrupted = true;
                }
            }
            Output::Done(_) => break,
            _ => {}
        }
    }
    assert_eq!((commits, sleeps), (5, 10));
    assert!(SessionConfig {
        iteration_delay_ms: SessionConfig::MAX_ITERATION_DELAY_MS + 1,
        ..SessionConfig::default()
    }
    .validate()
    .is_err());
}

#[test]
fn feeding_without_a_request_is_a_driver_error_that_changes_nothing() {
    let (mut s, _) = setup(1);
    let before = serde_json::to_string(&s).unwrap();
    assert_eq!(
        s.feed(Response::error("x")),
        Err(SessionError::NothingOutstanding)
    );
    assert_eq!(serde_json::to_string(&s).unwrap(), before);
}

#[test]
fn a_sweep_wider_than_one_step_is_refused_by_the_config() {
    let mut cfg = SimulationConfig::paper_default();
    if let crate::tuner::LevelKind::SensingDot(sd) = &mut cfg.tuner.levels[2].kind {
        sd.half_width_mv = 45.0;
    }
    let e = RunSession::new(cfg.tuner, SessionConfig::default()).unwrap_err();
    assert_eq!(e.field, "levels[2].half_width_mv", "{e}");
    assert!(e.to_string().contains("max_step_mv"), "{e}");
}
