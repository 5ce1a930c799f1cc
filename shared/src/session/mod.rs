//! The run session: one sans-IO state machine for a run's whole lifecycle
//! (ARCHITECTURE.md, invariant 6), wrapping the [`Tuner`] and the one safety
//! choke point ([`guard::Guard`], invariant 5).
//!
//! Every shell — the server's run task, the browser's in-page mode, the
//! benchmark, the headless CLI, the Python package, the tests — is a thin
//! driver of this loop:
//!
//! ```text
//! loop {
//!     match session.poll() {
//!         Output::Execute(request) => session.feed(device.execute(request))?,
//!         Output::Commit(record)   => { store(record, checkpoint(session)); broadcast(record) }
//!         Output::Save             => store(checkpoint(session)),
//!         Output::Publish(status)  => { store(status); broadcast(status) }
//!         Output::Sleep { ms }     => wait ms (handling control commands),
//!         Output::Wait             => wait for a control command (paused / faulted),
//!         Output::Done(end)        => break,
//!     }
//!     // at any time: session.control(command) for pause/resume/step/stop/targets
//! }
//! ```
//!
//! Guarantees (tested by the model-based property test `shared/tests/session_model.rs`):
//! * no request reaches the device unless [`guard::Guard::check`] passed it
//!   against the instrument's last read-back; every gate is read back on
//!   start, after a restore and on every resume;
//! * a read-back that carries gates not requested, lacks requested gates,
//!   holds non-finite values or values outside the gate's limits, or differs
//!   from the set value beyond the tolerance pauses the run with a [`Fault`]
//!   and is not believed; a gate that reads far from where the run left it
//!   (after a restore, resume or reconnect) faults with [`FaultKind::Moved`]
//!   until a person confirms the positions ([`ControlCommand::AcceptPositions`]);
//! * faults follow the policy of [`FaultKind::cleared_by`]: only a
//!   disconnected device's fault clears by itself
//!   ([`RunSession::device_recovered`]), every other waits for a person;
//! * after `stop` is acknowledged no request is issued;
//! * iteration numbers are contiguous and unique, also across a restore.
//!
//! ```
//! use spintune::driver::SimulationConfig;
//! use spintune::protocol::{ControlCommand, RunStatus};
//! use spintune::session::{Output, RunSession, SessionConfig};
//! use spintune::sim::SimulatedDevice;
//!
//! let mut cfg = SimulationConfig::paper_default();
//! cfg.tuner.max_iterations = Some(2);
//! let mut device = SimulatedDevice::new(cfg.device.clone(), &cfg.tuner.gates, 7).unwrap();
//! let mut session = RunSession::new(cfg.tuner, SessionConfig::default()).unwrap();
//! let mut records = 0;
//! loop {
//!     match session.poll() {
//!         Output::Execute(request) => session.feed(device.execute(&request)).unwrap(),
//!         Output::Commit(record) => {
//!             records += 1;
//!             // pause after the first iteration: nothing more is requested
//!             session.control(&ControlCommand::Pause).unwrap();
//!         }
//!         Output::Wait => break,
//!         Output::Done(_) => unreachable!(),
//!         _ => {}
//!     }
//! }
//! assert_eq!(records, 1);
//! assert_eq!(session.status(), RunStatus::Paused);
//! ```

pub mod guard;
mod plan;
pub mod ramp;

pub use plan::Plan;

use serde::{Deserialize, Serialize};

use crate::lifecycle::{Acceptance, Refusal};
use crate::parameter::Tolerance;
use crate::protocol::{
    ClearedBy, ControlCommand, ErrorCause, Fault, FaultKind, IterationRecord, Request, Response,
    RunStatus,
};
use crate::safety::SafetyLimits;
use crate::tuner::{Action, ConfigError, Tuner, TunerConfig, TunerError};
use guard::Guard;

/// Largest number of target changes held back until the next iteration
/// boundary (bounded by construction); more are refused.
pub const MAX_DEFERRED_TARGETS: usize = 64;

/// Settings of a session that are not the tuner's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionConfig {
    /// Largest accepted |read-back − set value| of a gate, mV.
    pub readback_tolerance_mv: f64,
    /// Wall-clock pause after each iteration while running, ms (0: none).
    pub iteration_delay_ms: u64,
    /// Largest accepted distance of a gate's read-back from where the run
    /// left it, mV, checked whenever the session reads the instrument (on a
    /// restore, resume or reconnect every gate). Farther is a
    /// [`FaultKind::Moved`] fault. A lie smaller than this can add at most
    /// this much to one physical step.
    pub moved_tolerance_mv: f64,
}

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            readback_tolerance_mv: 0.05,
            iteration_delay_ms: 0,
            moved_tolerance_mv: 1.0,
        }
    }
}

impl SessionConfig {
    /// Upper bound of [`SessionConfig::iteration_delay_ms`] (one hour).
    pub const MAX_ITERATION_DELAY_MS: u64 = 3_600_000;
    /// Upper bound of [`SessionConfig::readback_tolerance_mv`], mV (a wider
    /// tolerance would let the guard accept any read-back: invariant 5).
    pub const MAX_READBACK_TOLERANCE_MV: f64 = 100.0;
    /// Upper bound of [`SessionConfig::moved_tolerance_mv`], mV.
    pub const MAX_MOVED_TOLERANCE_MV: f64 = 100.0;

    /// Check the values; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(0.0..=Self::MAX_READBACK_TOLERANCE_MV).contains(&self.readback_tolerance_mv) {
            return Err(ConfigError::new(
                "readback_tolerance_mv",
                format!(
                    "must be a finite number ≥ 0 (mV), at most {} mV",
                    Self::MAX_READBACK_TOLERANCE_MV
                ),
            ));
        }
        if !(0.0..=Self::MAX_MOVED_TOLERANCE_MV).contains(&self.moved_tolerance_mv) {
            return Err(ConfigError::new(
                "moved_tolerance_mv",
                format!(
                    "must be a finite number ≥ 0 (mV), at most {} mV",
                    Self::MAX_MOVED_TOLERANCE_MV
                ),
            ));
        }
        if self.iteration_delay_ms > Self::MAX_ITERATION_DELAY_MS {
            return Err(ConfigError::new(
                "iteration_delay_ms",
                format!("must be at most {} ms", Self::MAX_ITERATION_DELAY_MS),
            ));
        }
        Ok(())
    }
}

/// What the driver must do next.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    /// Execute this request on the device and [`RunSession::feed`] the answer.
    /// It has passed the guard against the instrument's last read-back.
    Execute(Request),
    /// An iteration finished: persist the record together with a checkpoint
    /// of the session (serialize it now), then show it to viewers.
    Commit(Box<IterationRecord>),
    /// Persist a checkpoint of the session (a target change was applied).
    Save,
    /// The run's status changed: persist and show it.
    Publish(RunStatus),
    /// Pause this long (wall clock) before polling again; control commands
    /// may arrive meanwhile.
    Sleep {
        /// Duration, ms.
        ms: u64,
    },
    /// Nothing to do until a control command (paused or faulted) or, for a
    /// faulted run, until the device recovers ([`RunSession::device_recovered`]).
    Wait,
    /// The run is over.
    Done(RunEnd),
}

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunEnd {
    /// The tuner reached its goal or its iteration limit.
    Finished,
    /// A user stopped it.
    Stopped,
}

impl From<Refusal> for ControlError {
    fn from(r: Refusal) -> Self {
        ControlError::Conflict {
            status: r.status,
            message: r.reason,
        }
    }
}

/// A control command could not be applied. Nothing changed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ControlError {
    /// The command does not apply in the run's present state.
    #[error("the run is {status}: {message}")]
    Conflict {
        /// Short name of the present status.
        status: &'static str,
        /// Why the command does not apply.
        message: &'static str,
    },
    /// The command's content is invalid (e.g. unknown parameter).
    #[error(transparent)]
    Invalid(#[from] TunerError),
    /// Too many target changes are waiting for the iteration boundary.
    #[error(
        "{MAX_DEFERRED_TARGETS} target changes are already waiting for the end of the iteration"
    )]
    TooManyDeferred,
}

/// The driver broke the protocol of the session (a bug in the driver, not a
/// device fault). Nothing changed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SessionError {
    /// `feed` without an outstanding `Execute`.
    #[error("no request is outstanding")]
    NothingOutstanding,
}

/// The run's mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Mode {
    Running,
    Stepping,
    Paused,
    Stopping,
    Faulted(Fault),
    Finished,
    Stopped,
}

/// What was handed out with [`Output::Execute`] and not yet answered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum InFlight {
    /// The session's own read of these gates.
    Read(Vec<String>),
    /// The tuner's request.
    Tuner(Request),
}

/// A target change waiting for the next iteration boundary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TargetChange {
    parameter: String,
    target: Option<f64>,
    tolerance: Option<Tolerance>,
}

/// The run session: tuner + mode + deferred targets + faults + the guard.
/// Serializable as a whole (a checkpoint); the instrument's read-backs and
/// any in-flight request are deliberately not, so a restored session reads
/// every gate before it moves anything.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSession<P = Tuner> {
    tuner: P,
    guard: Guard,
    config: SessionConfig,
    mode: Mode,
    /// Last status handed out by [`Output::Publish`].
    published: Option<RunStatus>,
    #[serde(skip)]
    in_flight: Option<InFlight>,
    deferred: Vec<TargetChange>,
    /// Between iterations (no tuner request outstanding in this iteration).
    at_boundary: bool,
    save_due: bool,
    sleep_due: bool,
}

impl RunSession {
    /// A running session for a new tuner. Both configs are validated.
    pub fn new(tuner: TunerConfig, config: SessionConfig) -> Result<Self, ConfigError> {
        config.validate().map_err(|e| e.within("session"))?;
        let tuner = Tuner::new(tuner)?;
        Ok(Self::from_tuner(tuner, config))
    }
}

impl<P: Plan> RunSession<P> {
    /// A running session around an existing plan (a tuner, e.g. one
    /// restored from an older checkpoint, or an array's run). `config` must
    /// be valid.
    pub fn from_tuner(tuner: P, config: SessionConfig) -> Self {
        let guard = Guard::new(
            SafetyLimits::new(tuner.gate_specs()),
            config.readback_tolerance_mv,
            config.moved_tolerance_mv,
        );
        Self {
            tuner,
            guard,
            config,
            mode: Mode::Running,
            published: None,
            in_flight: None,
            deferred: Vec::new(),
            at_boundary: true,
            save_due: false,
            sleep_due: false,
        }
    }

    /// The tuner (read-only: changes go through [`RunSession::control`]).
    pub fn tuner(&self) -> &P {
        &self.tuner
    }

    /// The guard with the instrument's last read-backs.
    pub fn guard(&self) -> &Guard {
        &self.guard
    }

    /// The session settings.
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// Change the pause between iterations, ms (bounded by
    /// [`SessionConfig::MAX_ITERATION_DELAY_MS`]).
    pub fn set_iteration_delay_ms(&mut self, ms: u64) {
        self.config.iteration_delay_ms = ms.min(SessionConfig::MAX_ITERATION_DELAY_MS);
    }

    /// The run's present status.
    pub fn status(&self) -> RunStatus {
        match &self.mode {
            Mode::Running => RunStatus::Running,
            Mode::Stepping => RunStatus::Stepping,
            Mode::Paused => RunStatus::Paused,
            Mode::Stopping => RunStatus::Stopping,
            Mode::Faulted(f) => RunStatus::Faulted { fault: f.clone() },
            Mode::Finished => RunStatus::Finished,
            Mode::Stopped => RunStatus::Stopped,
        }
    }

    /// Whether a request is at the device (handed out, not yet fed back).
    pub fn has_request_in_flight(&self) -> bool {
        self.in_flight.is_some()
    }

    /// Whether the session is between iterations.
    pub fn at_boundary(&self) -> bool {
        self.at_boundary
    }

    /// The next thing to do. Polling again without acting returns the same
    /// `Execute` (the request stays outstanding).
    pub fn poll(&mut self) -> Output {
        let status = self.status();
        if self.published.as_ref() != Some(&status) {
            self.published = Some(status.clone());
            return Output::Publish(status);
        }
        if self.save_due {
            self.save_due = false;
            return Output::Save;
        }
        if let Some(f) = &self.in_flight {
            // The answer to the request at the device is still expected; a
            // paused or stopping run re-issues nothing.
            return match (&self.mode, f) {
                (Mode::Running | Mode::Stepping, InFlight::Read(gates)) => {
                    Output::Execute(Request::ReadVoltages {
                        gates: gates.clone(),
                    })
                }
                (Mode::Running | Mode::Stepping, InFlight::Tuner(r)) => Output::Execute(r.clone()),
                _ => Output::Wait,
            };
        }
        match self.mode {
            Mode::Finished => return Output::Done(RunEnd::Finished),
            Mode::Stopped => return Output::Done(RunEnd::Stopped),
            Mode::Stopping => {
                self.mode = Mode::Stopped;
                return self.poll();
            }
            Mode::Paused | Mode::Faulted(_) => return Output::Wait,
            Mode::Running | Mode::Stepping => {}
        }
        if self.sleep_due {
            self.sleep_due = false;
            if self.mode == Mode::Running && self.config.iteration_delay_ms > 0 {
                return Output::Sleep {
                    ms: self.config.iteration_delay_ms,
                };
            }
        }
        let action = match self.tuner.next_action() {
            Ok(action) => action,
            Err(message) => {
                self.set_fault(Fault::new(FaultKind::Response, message));
                return self.poll();
            }
        };
        match action {
            Action::Request(request) => {
                self.at_boundary = false;
                let unknown = self.guard.unknown_gates(&request);
                if self.guard.readback_mv().is_empty() || !unknown.is_empty() {
                    // Ask the instrument where the gates are before moving any
                    // of them: every gate on start, restore and resume; after
                    // a sweep, the swept gate.
                    let gates: Vec<String> = if self.guard.readback_mv().is_empty() {
                        self.tuner
                            .gate_specs()
                            .iter()
                            .map(|g| g.name.clone())
                            .collect()
                    } else {
                        unknown.into_iter().collect()
                    };
                    self.in_flight = Some(InFlight::Read(gates.clone()));
                    return Output::Execute(Request::ReadVoltages { gates });
                }
                if let Err(e) = self.guard.check(&request) {
                    self.set_fault(Fault::new(
                        FaultKind::Safety,
                        format!("refused before it reached the device: {e}"),
                    ));
                    return self.poll();
                }
                self.in_flight = Some(InFlight::Tuner(request.clone()));
                Output::Execute(request)
            }
            Action::Iteration(record) => {
                self.at_boundary = true;
                // Target changes received during the iteration apply from the
                // next one; the committed checkpoint includes them.
                for change in std::mem::take(&mut self.deferred) {
                    // validated when received; a failure here cannot happen,
                    // but it must not be silent either
                    if let Err(e) =
                        self.tuner
                            .change_target(&change.parameter, change.target, change.tolerance)
                    {
                        debug_assert!(false, "deferred target became invalid: {e}");
                    }
                }
                if self.mode == Mode::Stepping {
                    self.mode = Mode::Paused;
                } else {
                    self.sleep_due = true;
                }
                Output::Commit(Box::new(record))
            }
            Action::Finished => {
                self.mode = Mode::Finished;
                self.poll()
            }
        }
    }

    /// Answer the outstanding `Execute`. A device error, a refused read-back
    /// or an answer that does not fit pauses the run with a [`Fault`] (the
    /// tuner keeps its request and re-issues it on resume, after a fresh
    /// read-back); only a driver bug is an `Err`.
    pub fn feed(&mut self, response: Response) -> Result<(), SessionError> {
        let in_flight = self
            .in_flight
            .take()
            .ok_or(SessionError::NothingOutstanding)?;
        if let InFlight::Tuner(request) = &in_flight {
            // Whatever the answer, the gates may be anywhere the request
            // could take them until an accepted answer says exactly where.
            self.guard.may_have_visited(request);
        }
        if let Response::Error { message, cause } = &response {
            if let InFlight::Tuner(request) = &in_flight {
                self.guard.after_request(request);
            }
            self.guard.forget_all();
            let kind = match cause {
                ErrorCause::Disconnected => FaultKind::Disconnected,
                ErrorCause::Instrument => FaultKind::Device,
            };
            self.set_fault(Fault::new(kind, message.clone()));
            return Ok(());
        }
        match in_flight {
            InFlight::Read(gates) => match response {
                Response::VoltagesRead {
                    voltages_mv,
                    lab_seconds,
                } => {
                    self.tuner.charge_time(lab_seconds);
                    let first_positions = self.guard.left_mv().is_empty();
                    match self.guard.accept_read(&gates, &voltages_mv) {
                        Ok(()) => {
                            // A new run now knows where its gates are: persist it,
                            // so a crash before the first iteration is committed
                            // still compares the instrument with it on restore.
                            self.save_due |= first_positions;
                            self.tuner
                                .adopt_voltages(&voltages_mv, self.config.readback_tolerance_mv);
                        }
                        Err(guard::ReadbackError::Moved { moved, .. }) => {
                            let message = format!(
                                "read_voltages: {}",
                                guard::ReadbackError::Moved {
                                    moved: moved.clone(),
                                    tolerance_mv: self.config.moved_tolerance_mv,
                                }
                            );
                            let mut fault = Fault::new(FaultKind::Moved, message);
                            fault.moved = moved;
                            self.set_fault(fault);
                        }
                        Err(e) => {
                            self.set_fault(Fault::new(
                                FaultKind::Readback,
                                format!("read_voltages: {e}"),
                            ));
                        }
                    }
                }
                other => self.wrong_answer("read_voltages", &other),
            },
            InFlight::Tuner(request) => {
                self.guard.after_request(&request);
                if let Err(fault) = self.take_answer(&request, &response) {
                    if !matches!(fault.kind, FaultKind::Readback | FaultKind::Moved) {
                        self.guard.forget_all();
                    }
                    self.set_fault(fault);
                    return Ok(());
                }
                if let Err(e) = self.tuner.take_response(response) {
                    self.set_fault(Fault::new(FaultKind::Response, e.to_string()));
                }
            }
        }
        if self.mode == Mode::Stopping {
            self.mode = Mode::Stopped;
        }
        Ok(())
    }

    /// Whether `response` answers `request` (a batch: one fitting answer
    /// per request, in order); every set's read-back goes to the guard. A
    /// batch's answer that is an error faults like the device's error.
    fn take_answer(&mut self, request: &Request, response: &Response) -> Result<(), Fault> {
        let wrong = || {
            Fault::new(
                FaultKind::Response,
                format!(
                    "answered `{}` to a `{}` request",
                    response_name(response),
                    request_name(request)
                ),
            )
        };
        match (request, response) {
            (
                Request::SetVoltages {
                    voltages_mv: requested,
                },
                Response::VoltagesSet { voltages_mv, .. },
            ) => self
                .guard
                .accept_set(requested, voltages_mv)
                .map_err(|e| Fault::new(FaultKind::Readback, format!("set_voltages: {e}"))),
            // a read inside a batch (an array cell's own session reading its
            // gates): held to the same plausibility as the session's reads
            (Request::ReadVoltages { gates }, Response::VoltagesRead { voltages_mv, .. }) => {
                self.guard.accept_read(gates, voltages_mv).map_err(|e| {
                    let moved = match &e {
                        guard::ReadbackError::Moved { moved, .. } => moved.clone(),
                        _ => Vec::new(),
                    };
                    let kind = if moved.is_empty() {
                        FaultKind::Readback
                    } else {
                        FaultKind::Moved
                    };
                    let mut fault = Fault::new(kind, format!("read_voltages: {e}"));
                    fault.moved = moved;
                    fault
                })
            }
            (Request::Measure { .. }, Response::Scanned { .. })
            | (Request::TrueJacobian { .. }, Response::TrueJacobian { .. })
            | (Request::Wait { .. }, Response::Waited { .. }) => Ok(()),
            (Request::Batch { requests }, Response::Batch { responses, .. }) => {
                if requests.len() != responses.len() {
                    return Err(Fault::new(
                        FaultKind::Response,
                        format!(
                            "a batch of {} requests was answered with {} responses",
                            requests.len(),
                            responses.len()
                        ),
                    ));
                }
                for (i, (q, a)) in requests.iter().zip(responses).enumerate() {
                    if let Response::Error { message, cause } = a {
                        let kind = match cause {
                            ErrorCause::Disconnected => FaultKind::Disconnected,
                            ErrorCause::Instrument => FaultKind::Device,
                        };
                        return Err(Fault::new(kind, format!("batch request {i}: {message}")));
                    }
                    self.take_answer(q, a).map_err(|mut f| {
                        f.message = format!("batch request {i}: {}", f.message);
                        f
                    })?;
                }
                Ok(())
            }
            _ => Err(wrong()),
        }
    }

    fn wrong_answer(&mut self, expected: &str, got: &Response) {
        self.guard.forget_all();
        self.set_fault(Fault::new(
            FaultKind::Response,
            format!(
                "answered `{}` to a `{expected}` request",
                response_name(got)
            ),
        ));
    }

    /// Pause with a fault (a stop in progress wins: the run just stops).
    fn set_fault(&mut self, fault: Fault) {
        self.mode = match self.mode {
            Mode::Stopping | Mode::Stopped => Mode::Stopped,
            _ => Mode::Faulted(fault),
        };
    }

    /// The device is reachable again by itself (e.g. the lab bridge
    /// reconnected). Only a fault the policy lets clear on reconnect
    /// ([`FaultKind::Disconnected`], see [`FaultKind::cleared_by`]) resumes
    /// the run (after reading every gate back, with every plausibility
    /// check); every other fault, and a run paused by a user, stays as it is.
    /// Returns whether the run resumed.
    pub fn device_recovered(&mut self) -> bool {
        match &self.mode {
            Mode::Faulted(f) if f.kind.cleared_by() == ClearedBy::Reconnect => {
                self.resume(Mode::Running);
                true
            }
            _ => false,
        }
    }

    /// A fault recorded after the session's last checkpoint (a server stores
    /// statuses apart from checkpoints): the restored session is faulted
    /// with it, so that what clears it ([`FaultKind::cleared_by`]) still
    /// applies. A finished or stopped session stays as it is.
    pub fn restore_fault(&mut self, fault: Fault) {
        if !matches!(self.mode, Mode::Finished | Mode::Stopped | Mode::Stopping) {
            self.mode = Mode::Faulted(fault);
        }
    }

    /// Whether the run waits for the device to reconnect (a fault that
    /// [`RunSession::device_recovered`] would clear).
    pub fn awaits_reconnect(&self) -> bool {
        matches!(&self.mode, Mode::Faulted(f) if f.kind.cleared_by() == ClearedBy::Reconnect)
    }

    fn resume(&mut self, mode: Mode) {
        // Wherever the instrument is now, it is read before anything moves.
        self.guard.forget_all();
        self.mode = mode;
        // The pause between iterations is not skipped by pausing and resuming.
        if self.at_boundary && self.in_flight.is_none() {
            self.sleep_due = true;
        }
    }

    /// Apply a control command. Pause, stop and target changes take effect
    /// at once (a target change received mid-iteration applies from the next
    /// iteration); the returned status is the new one. Whether the present
    /// status accepts the command is the lifecycle table
    /// ([`RunStatus::accepts`]), stated once for every shell.
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, ControlError> {
        if self.status().accepts(command)? == Acceptance::AlreadyThere {
            return Ok(self.status());
        }
        match command {
            ControlCommand::Pause => self.mode = Mode::Paused,
            ControlCommand::Resume | ControlCommand::Step => {
                let target = if *command == ControlCommand::Step {
                    Mode::Stepping
                } else {
                    Mode::Running
                };
                match self.mode {
                    Mode::Running | Mode::Stepping => self.mode = target,
                    _ => self.resume(target),
                }
            }
            ControlCommand::Stop => {
                self.mode = if self.in_flight.is_some() {
                    Mode::Stopping
                } else {
                    Mode::Stopped
                }
            }
            ControlCommand::AcceptPositions => {
                if let Mode::Faulted(f) = &self.mode {
                    let moved = f.moved.clone();
                    self.guard.accept_positions(&moved);
                    self.mode = Mode::Paused;
                }
            }
            ControlCommand::SetTarget {
                parameter,
                target,
                tolerance,
            } => {
                self.tuner.check_target(parameter, *target, *tolerance)?;
                let change = TargetChange {
                    parameter: parameter.clone(),
                    target: *target,
                    tolerance: *tolerance,
                };
                if self.at_boundary {
                    self.tuner
                        .change_target(&change.parameter, change.target, change.tolerance)?;
                    if self.mode == Mode::Finished && !self.tuner.done() {
                        // a new target revives a run that stopped when tuned
                        self.mode = Mode::Paused;
                    }
                    self.save_due = true;
                } else {
                    if self.deferred.len() >= MAX_DEFERRED_TARGETS {
                        return Err(ControlError::TooManyDeferred);
                    }
                    self.deferred.push(change);
                }
            }
        }
        Ok(self.status())
    }
}

fn request_name(r: &Request) -> &'static str {
    match r {
        Request::SetVoltages { .. } => "set_voltages",
        Request::ReadVoltages { .. } => "read_voltages",
        Request::Measure { .. } => "measure",
        Request::TrueJacobian { .. } => "true_jacobian",
        Request::Wait { .. } => "wait",
        Request::Batch { .. } => "batch",
    }
}

fn response_name(r: &Response) -> &'static str {
    match r {
        Response::VoltagesSet { .. } => "voltages_set",
        Response::VoltagesRead { .. } => "voltages_read",
        Response::Scanned { .. } => "scanned",
        Response::TrueJacobian { .. } => "true_jacobian",
        Response::Waited { .. } => "waited",
        Response::Batch { .. } => "batch",
        Response::Error { .. } => "error",
    }
}

#[cfg(test)]
mod tests;
