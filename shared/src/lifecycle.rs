//! The one lifecycle table: which control command a run status accepts
//! (ARCHITECTURE.md, invariant 6). The run session applies it to its mode,
//! the server's manager to a run without a live task, and the dashboard to
//! its buttons; none of them states the rule again.
//!
//! | command | accepted in | a no-op in | refused in |
//! |---|---|---|---|
//! | `pause` | running, stepping, faulted, interrupted, failed | paused | stopping, stopped, finished |
//! | `resume` | paused, faulted, interrupted, failed, stepping | running | stopping, stopped, finished |
//! | `step` | paused, faulted, interrupted, failed, running | stepping | stopping, stopped, finished |
//! | `stop` | everything else | stopping, stopped, finished | — |
//! | `accept_positions` | faulted with kind `moved` | — | everything else |
//! | `set_target` | everything else | — | stopping, stopped |

use crate::protocol::{ControlCommand, FaultKind, RunStatus};

/// A command a status accepts: whether it changes anything.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acceptance {
    /// The command changes the run.
    Applies,
    /// The run is already where the command would take it (e.g. `pause` of a
    /// paused run); accepted, nothing changes.
    AlreadyThere,
}

/// Why a status refuses a command. Nothing changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the run is {status}: {reason}")]
pub struct Refusal {
    /// Short name of the status ([`RunStatus::name`]).
    pub status: &'static str,
    /// Why the command does not apply.
    pub reason: &'static str,
}

impl RunStatus {
    /// Whether this status accepts `command` (the lifecycle table above).
    ///
    /// ```
    /// use spintune::lifecycle::Acceptance;
    /// use spintune::protocol::{ControlCommand, RunStatus};
    /// assert_eq!(RunStatus::Running.accepts(&ControlCommand::Pause), Ok(Acceptance::Applies));
    /// assert_eq!(RunStatus::Paused.accepts(&ControlCommand::Pause), Ok(Acceptance::AlreadyThere));
    /// let refused = RunStatus::Stopped.accepts(&ControlCommand::Resume).unwrap_err();
    /// assert_eq!(refused.to_string(), "the run is stopped: a stopped run cannot be resumed");
    /// ```
    pub fn accepts(&self, command: &ControlCommand) -> Result<Acceptance, Refusal> {
        use Acceptance::{AlreadyThere, Applies};
        let refuse = |reason| {
            Err(Refusal {
                status: self.name(),
                reason,
            })
        };
        let stopped = matches!(self, RunStatus::Stopping | RunStatus::Stopped);
        match command {
            ControlCommand::Pause => match self {
                _ if stopped => refuse("a stopped run cannot be paused"),
                RunStatus::Finished => refuse("the run has finished"),
                RunStatus::Paused => Ok(AlreadyThere),
                _ => Ok(Applies),
            },
            ControlCommand::Resume | ControlCommand::Step => match self {
                _ if stopped => refuse("a stopped run cannot be resumed"),
                RunStatus::Finished => refuse("the run has finished"),
                RunStatus::Running if *command == ControlCommand::Resume => Ok(AlreadyThere),
                RunStatus::Stepping if *command == ControlCommand::Step => Ok(AlreadyThere),
                _ => Ok(Applies),
            },
            ControlCommand::Stop => match self {
                RunStatus::Stopping | RunStatus::Stopped | RunStatus::Finished => Ok(AlreadyThere),
                _ => Ok(Applies),
            },
            ControlCommand::AcceptPositions => match self {
                RunStatus::Faulted { fault } if fault.kind == FaultKind::Moved => Ok(Applies),
                _ => refuse("only a run faulted because gates moved has positions to accept"),
            },
            ControlCommand::SetTarget { .. } => match self {
                _ if stopped => refuse("a stopped run takes no new targets"),
                _ => Ok(Applies),
            },
        }
    }

    /// Whether `command` would change a run in this status (a control
    /// button is enabled exactly then).
    pub fn is_changed_by(&self, command: &ControlCommand) -> bool {
        self.accepts(command) == Ok(Acceptance::Applies)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Fault;

    fn statuses() -> Vec<RunStatus> {
        vec![
            RunStatus::Running,
            RunStatus::Stepping,
            RunStatus::Paused,
            RunStatus::Stopping,
            RunStatus::Faulted {
                fault: Fault::new(FaultKind::Device, "x"),
            },
            RunStatus::Faulted {
                fault: Fault::new(FaultKind::Moved, "x"),
            },
            RunStatus::Finished,
            RunStatus::Stopped,
            RunStatus::Interrupted,
            RunStatus::Failed {
                message: "x".into(),
            },
        ]
    }

    #[test]
    fn stop_is_always_accepted_and_a_stopped_run_takes_nothing_else() {
        for s in statuses() {
            assert!(s.accepts(&ControlCommand::Stop).is_ok(), "{s:?}");
            let stopped = matches!(s, RunStatus::Stopped | RunStatus::Stopping);
            for c in [
                ControlCommand::Pause,
                ControlCommand::Resume,
                ControlCommand::Step,
                ControlCommand::SetTarget {
                    parameter: "w".into(),
                    target: None,
                    tolerance: None,
                },
            ] {
                assert_eq!(
                    s.accepts(&c).is_err(),
                    stopped
                        || (s == RunStatus::Finished
                            && !matches!(c, ControlCommand::SetTarget { .. })),
                    "{s:?} {c:?}"
                );
            }
        }
    }

    #[test]
    fn only_a_moved_fault_accepts_positions_and_resumable_statuses_resume() {
        for s in statuses() {
            let moved =
                matches!(&s, RunStatus::Faulted { fault } if fault.kind == FaultKind::Moved);
            assert_eq!(
                s.is_changed_by(&ControlCommand::AcceptPositions),
                moved,
                "{s:?}"
            );
            assert_eq!(
                s.is_changed_by(&ControlCommand::Resume),
                s.is_resumable() || s == RunStatus::Stepping,
                "{s:?}"
            );
        }
    }
}
