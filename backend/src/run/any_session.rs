//! [`AnySession`]: a run's session, of a single double dot or of an array
//! of them. Both are the core's one `RunSession` (lifecycle, faults, the
//! guard) around a different plan; this only dispatches, so the run task,
//! the manager and the checkpoint handle both alike.

use spintune::protocol::{ControlCommand, Fault, Response, RunStatus};
use spintune::session::{ControlError, Output, RunSession, SessionError};
use spintune::tuner::array_run::ArrayRun;

/// A run's session (see the module docs).
#[derive(Debug, Clone)]
pub enum AnySession {
    /// One double dot (the single-cell tuner).
    Cell(Box<RunSession>),
    /// An array of double dots (the joint array run).
    Array(Box<RunSession<ArrayRun>>),
}

macro_rules! each {
    ($self:expr, $s:ident => $e:expr) => {
        match $self {
            AnySession::Cell($s) => $e,
            AnySession::Array($s) => $e,
        }
    };
}

impl AnySession {
    /// [`RunSession::poll`].
    pub fn poll(&mut self) -> Output {
        each!(self, s => s.poll())
    }

    /// [`RunSession::feed`].
    pub fn feed(&mut self, response: Response) -> Result<(), SessionError> {
        each!(self, s => s.feed(response))
    }

    /// [`RunSession::control`].
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, ControlError> {
        each!(self, s => s.control(command))
    }

    /// [`RunSession::status`].
    pub fn status(&self) -> RunStatus {
        each!(self, s => s.status())
    }

    /// [`RunSession::awaits_reconnect`].
    pub fn awaits_reconnect(&self) -> bool {
        each!(self, s => s.awaits_reconnect())
    }

    /// [`RunSession::device_recovered`].
    pub fn device_recovered(&mut self) -> bool {
        each!(self, s => s.device_recovered())
    }

    /// [`RunSession::restore_fault`].
    pub fn restore_fault(&mut self, fault: Fault) {
        each!(self, s => s.restore_fault(fault))
    }

    /// Whether the plan has nothing left to do (a run that finished because
    /// it was tuned, until a target changes).
    pub fn plan_done(&self) -> bool {
        use spintune::session::Plan;
        each!(self, s => s.tuner().done())
    }

    /// [`RunSession::set_iteration_delay_ms`].
    pub fn set_iteration_delay_ms(&mut self, ms: u64) {
        each!(self, s => s.set_iteration_delay_ms(ms))
    }
}
