//! When a run raises an alert (issue 23): the one decision, used by every
//! shell (the server's run handle for viewers and its webhook, the
//! dashboard's run list). Pure: no clock, no IO; the shell stamps the
//! wall-clock time.
//!
//! A run raises an [`Alert`] when
//! * its status **becomes** `faulted` (a new fault: another kind or message
//!   than the one it was already paused by), `finished` or `failed`
//!   ([`status_alert`]: only on a change, so a status broadcast twice or a
//!   run listed again raises nothing);
//! * a committed record carries the tuner event
//!   [`EventKind::NotBackInBand`] (keep mode raises it once per re-tune;
//!   [`record_alerts`]).
//!
//! ```
//! use spintune::alert::status_alert;
//! use spintune::protocol::{AlertKind, RunStatus, RunSummary};
//! let run = RunSummary { id: 3, name: "night".into(), status: RunStatus::Finished,
//!     iterations: 12, lab_seconds: 90.0, tuned: true, driver: None };
//! let a = status_alert(&RunStatus::Running, &run).unwrap();
//! assert_eq!(a.kind, AlertKind::Finished);
//! assert_eq!(a.message, "finished after 12 iterations, in band");
//! assert_eq!(a.lab_seconds, 90.0);
//! assert!(status_alert(&RunStatus::Finished, &run).is_none());
//! ```

use crate::protocol::{Alert, AlertKind, EventKind, IterationRecord, RunStatus, RunSummary};

/// The alert `run`'s new status raises, coming from `previous` (`None`:
/// the status did not change in a way that needs a person).
pub fn status_alert(previous: &RunStatus, run: &RunSummary) -> Option<Alert> {
    let (kind, message) = match (&run.status, previous) {
        (RunStatus::Faulted { fault }, RunStatus::Faulted { fault: before })
            if before.kind == fault.kind && before.message == fault.message =>
        {
            return None
        }
        (RunStatus::Faulted { fault }, _) => (
            AlertKind::Faulted,
            format!(
                "{fault}; the run is paused until {}",
                match fault.cleared_by {
                    crate::protocol::ClearedBy::Reconnect =>
                        "the device reconnects (or a person resumes it)",
                    crate::protocol::ClearedBy::Resume => "a person resumes it",
                    crate::protocol::ClearedBy::AcceptPositions =>
                        "a person accepts the gates' positions (or moves them back and resumes)",
                }
            ),
        ),
        (RunStatus::Finished, RunStatus::Finished) => return None,
        (RunStatus::Finished, _) => (
            AlertKind::Finished,
            format!(
                "finished after {} iteration{}, {}",
                run.iterations,
                if run.iterations == 1 { "" } else { "s" },
                if run.tuned { "in band" } else { "not in band" }
            ),
        ),
        (RunStatus::Failed { .. }, RunStatus::Failed { .. }) => return None,
        (RunStatus::Failed { message }, _) => (AlertKind::Failed, format!("failed: {message}")),
        _ => return None,
    };
    Some(Alert {
        run: run.id,
        name: run.name.clone(),
        kind,
        message,
        lab_seconds: run.lab_seconds,
        iteration: run.iterations.checked_sub(1),
    })
}

/// The alerts a committed record of run `run` (named `name`) raises: one
/// per [`EventKind::NotBackInBand`] event it carries.
///
/// ```
/// use spintune::alert::record_alerts;
/// use spintune::protocol::{EventKind, IterationRecord, TunerEvent};
/// let mut r: IterationRecord = serde_json::from_str(r#"{"iteration":41,"voltages_mv":{},"gates":[],
///     "parameters":[],"gradients":[],"step_mv":[],"tuned":false,"lab_seconds":4000.0,
///     "scan_counts":{},"failed_evaluations":0,"scans":[],"events":[]}"#).unwrap();
/// assert!(record_alerts(3, "night", &r).is_empty());
/// r.events.push(TunerEvent { level: "qubit".into(), kind: EventKind::NotBackInBand {
///     out_of_band_lab_seconds: 1500.0, limit_lab_seconds: 1200.0 } });
/// let a = record_alerts(3, "night", &r);
/// assert_eq!(a[0].message, "qubit: not back in band after 25.0 lab min (limit 20.0 lab min)");
/// assert_eq!((a[0].iteration, a[0].lab_seconds), (Some(41), 4000.0));
/// ```
pub fn record_alerts(run: u64, name: &str, record: &IterationRecord) -> Vec<Alert> {
    record
        .events
        .iter()
        .filter_map(|e| match e.kind {
            EventKind::NotBackInBand {
                out_of_band_lab_seconds,
                limit_lab_seconds,
            } => Some(Alert {
                run,
                name: name.to_string(),
                kind: AlertKind::NotBackInBand,
                message: format!(
                    "{}: not back in band after {:.1} lab min (limit {:.1} lab min)",
                    e.level,
                    out_of_band_lab_seconds / 60.0,
                    limit_lab_seconds / 60.0
                ),
                lab_seconds: record.lab_seconds,
                iteration: Some(record.iteration),
            }),
            _ => None,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Fault, FaultKind};

    fn run(status: RunStatus) -> RunSummary {
        RunSummary {
            id: 7,
            name: "r".into(),
            status,
            iterations: 0,
            lab_seconds: 0.0,
            tuned: false,
            driver: None,
        }
    }

    fn every_status() -> Vec<RunStatus> {
        vec![
            RunStatus::Running,
            RunStatus::Stepping,
            RunStatus::Paused,
            RunStatus::Stopping,
            RunStatus::Faulted {
                fault: Fault::new(FaultKind::Device, "leakage on SB"),
            },
            RunStatus::Finished,
            RunStatus::Stopped,
            RunStatus::Interrupted,
            RunStatus::Failed {
                message: "disk full".into(),
            },
        ]
    }

    #[test]
    fn only_a_change_into_faulted_finished_or_failed_alerts() {
        for previous in every_status() {
            for next in every_status() {
                let alert = status_alert(&previous, &run(next.clone()));
                let expected = match &next {
                    RunStatus::Faulted { .. } | RunStatus::Finished | RunStatus::Failed { .. } => {
                        previous.name() != next.name()
                    }
                    _ => false,
                };
                assert_eq!(alert.is_some(), expected, "{previous:?} → {next:?}");
                if let Some(a) = alert {
                    assert_eq!(a.kind.name(), next.name());
                    assert_eq!(a.run, 7);
                    assert_eq!(a.iteration, None);
                }
            }
        }
    }

    #[test]
    fn another_fault_alerts_again_and_the_message_says_what_clears_it() {
        let device = RunStatus::Faulted {
            fault: Fault::new(FaultKind::Device, "leakage on SB"),
        };
        let moved = run(RunStatus::Faulted {
            fault: Fault::new(FaultKind::Moved, "gate SB reads -410 mV"),
        });
        let a = status_alert(&device, &moved).unwrap();
        assert_eq!(a.kind, AlertKind::Faulted);
        assert!(
            a.message.starts_with("moved fault: gate SB reads -410 mV"),
            "{}",
            a.message
        );
        assert!(
            a.message.contains("accepts the gates' positions"),
            "{}",
            a.message
        );
        let disconnected = run(RunStatus::Faulted {
            fault: Fault::new(FaultKind::Disconnected, "bridge gone"),
        });
        assert!(status_alert(&device, &disconnected)
            .unwrap()
            .message
            .contains("the device reconnects"));
    }

    #[test]
    fn records_without_the_event_raise_nothing() {
        let r: IterationRecord = serde_json::from_str(
            r#"{"iteration":2,"voltages_mv":{},"gates":[],"parameters":[],"gradients":[],
            "step_mv":[],"tuned":false,"lab_seconds":1.0,"scan_counts":{},
            "failed_evaluations":0,"scans":[],"events":[{"level":"qubit","event":"back_in_band","after_lab_seconds":60.0}]}"#,
        )
        .unwrap();
        assert!(record_alerts(1, "x", &r).is_empty());
    }
}
