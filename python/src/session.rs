//! `spintune.RunSession`: the core's sans-IO run session
//! (`spintune::session::RunSession`) for a driver written in Python. Every
//! safety check (limits, steps, read-back guard) is the core's; this file
//! converts dicts.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use serde::Serialize;
use spintune::protocol::{ControlCommand, IterationRecord, Request, Response, RunStatus};
use spintune::session::{ControlError, Output, RunEnd, RunSession, SessionConfig};

use crate::convert::{from_py, to_py};

/// [`Output`] in its dict form: `{"output": "execute", "request": {...}}`, ….
#[derive(Serialize)]
#[serde(tag = "output", rename_all = "snake_case")]
enum OutputView<'a> {
    Execute { request: &'a Request },
    Commit { record: &'a IterationRecord },
    Save,
    Publish { status: &'a RunStatus },
    Sleep { ms: u64 },
    Wait,
    Done { end: RunEnd },
}

pub(crate) fn control_error(e: ControlError) -> PyErr {
    match e {
        ControlError::Invalid(e) => PyValueError::new_err(e.to_string()),
        other => PyRuntimeError::new_err(other.to_string()),
    }
}

/// The run session: the whole lifecycle of a tuning run as a sans-IO state
/// machine (the core's ``spintune::session::RunSession``). A driver — a
/// notebook, ``spintune.qcodes`` — loops::
///
///     while True:
///         out = session.poll()
///         if out["output"] == "execute":
///             session.feed(my_instrument(out["request"]))
///         elif out["output"] == "commit":
///             store(out["record"])
///         elif out["output"] in ("wait", "done"):
///             break
///
/// ``poll()`` returns the next output as a dict:
///
/// * ``{"output": "execute", "request": {...}}`` — run this request on the
///   device and ``feed()`` the answer. Requests (JSON of
///   ``protocol::Request``): ``{"request": "read_voltages", "gates": [...]}``,
///   ``{"request": "set_voltages", "voltages_mv": {gate: mV}}``,
///   ``{"request": "measure", "scan": {"kind": ..., "sweep": ...}}``.
///   Every request has passed the safety guard against the instrument's last
///   read-back (gate limits, per-gate step, sweep points).
/// * ``{"output": "commit", "record": {...}}`` — an iteration finished (the
///   JSON ``IterationRecord``); store it with ``checkpoint()``.
/// * ``{"output": "save"}`` — store ``checkpoint()`` (a target changed).
/// * ``{"output": "publish", "status": {"state": ...}}`` — the status changed.
/// * ``{"output": "sleep", "ms": n}`` — pause n ms before polling again.
/// * ``{"output": "wait"}`` — paused or faulted: nothing happens until
///   ``control()`` (or ``device_recovered()``).
/// * ``{"output": "done", "end": "finished" | "stopped"}`` — the run is over.
///
/// Args:
///     tuner_config: the tuner (the run config's ``tuner`` table) as a dict,
///         merged into the paper's default tuner: gates with limits
///         (``min_mv``, ``max_mv``, ``max_step_mv``, ``initial_mv``, all mV),
///         levels, parameters and targets. ``None``: the paper default.
///     readback_tolerance_mv: largest accepted |read-back − set value| of a
///         gate, mV (default 0.05 mV); a larger difference faults the run.
///     iteration_delay_ms: wall-clock pause after each iteration, ms
///         (announced by ``{"output": "sleep"}``; default 0).
///     moved_tolerance_mv: largest accepted distance of a gate's read-back
///         from where the run left it, mV (default 1 mV); farther is a
///         ``moved`` fault that waits for ``control({"action":
///         "accept_positions"})``.
#[pyclass(name = "RunSession", module = "spintune")]
pub struct PyRunSession {
    inner: RunSession,
}

#[pymethods]
impl PyRunSession {
    #[new]
    #[pyo3(signature = (tuner_config = None, readback_tolerance_mv = 0.05, iteration_delay_ms = 0, moved_tolerance_mv = 1.0))]
    fn new(
        tuner_config: Option<&Bound<'_, PyAny>>,
        readback_tolerance_mv: f64,
        iteration_delay_ms: u64,
        moved_tolerance_mv: f64,
    ) -> PyResult<Self> {
        let tuner = crate::config::tuner_config(tuner_config)?;
        let inner = RunSession::new(
            tuner,
            SessionConfig {
                readback_tolerance_mv,
                iteration_delay_ms,
                moved_tolerance_mv,
            },
        )
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(Self { inner })
    }

    /// The next thing to do, as a dict with key ``"output"`` (see the class
    /// docstring). Polling again without acting returns the same
    /// ``execute`` (the request stays outstanding).
    fn poll<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let out = self.inner.poll();
        let view = match &out {
            Output::Execute(request) => OutputView::Execute { request },
            Output::Commit(record) => OutputView::Commit { record },
            Output::Save => OutputView::Save,
            Output::Publish(status) => OutputView::Publish { status },
            Output::Sleep { ms } => OutputView::Sleep { ms: *ms },
            Output::Wait => OutputView::Wait,
            Output::Done(end) => OutputView::Done { end: *end },
        };
        to_py(py, &view)
    }

    /// Answer the outstanding ``execute`` with the device's response (JSON of
    /// ``protocol::Response``):
    ///
    /// * ``{"response": "voltages_read", "voltages_mv": {gate: mV}, "lab_seconds": s}``
    /// * ``{"response": "voltages_set", "voltages_mv": {gate: read-back mV}, "lab_seconds": s}``
    /// * ``{"response": "scanned", "lab_seconds": s, "outcome": {"kind": "raw", "scan": {...}}}``
    ///   (or ``{"kind": "evaluated", "values": [{"name", "value", "variance"}]}``,
    ///   or ``{"kind": "failed", "reason": "..."}``)
    /// * ``{"response": "error", "message": "..."}`` — the device failed.
    ///
    /// numpy arrays and scalars are accepted wherever the JSON has numbers.
    /// A device error, a read-back that does not match the request or an
    /// answer of the wrong kind pauses the run with a fault (not an
    /// exception). Raises ``ValueError`` if the dict does not have the shape
    /// of a response (nothing changed) and ``RuntimeError`` if no request is
    /// outstanding.
    fn feed(&mut self, response: &Bound<'_, PyAny>) -> PyResult<()> {
        let response: Response = from_py(response, "response")?;
        self.inner
            .feed(response)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
    }

    /// Apply a control command (JSON of ``protocol::ControlCommand``):
    /// ``{"action": "pause"}``, ``"resume"``, ``"step"``, ``"stop"``, or
    /// ``{"action": "set_target", "parameter": "t_sr", "target": 25.0,
    /// "tolerance": {"relative": 0.1}}`` (target in the parameter's unit,
    /// ``None`` removes it). Returns the new status dict.
    ///
    /// Raises ``ValueError`` for a malformed command or an invalid target
    /// and ``RuntimeError`` if the command does not apply in the present
    /// state (e.g. resuming a stopped run); nothing changes then.
    fn control<'py>(
        &mut self,
        py: Python<'py>,
        command: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let command: ControlCommand = from_py(command, "control command")?;
        let status = self.inner.control(&command).map_err(control_error)?;
        to_py(py, &status)
    }

    /// The device recovered by itself: a faulted run resumes (after reading
    /// every gate back). Returns whether it did; a paused run stays paused.
    fn device_recovered(&mut self) -> bool {
        self.inner.device_recovered()
    }

    /// Present status, e.g. ``{"state": "running"}`` or ``{"state":
    /// "faulted", "fault": {"kind": "readback", "message": "..."}}``.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, &self.inner.status())
    }

    /// Whether a request is at the device (handed out by ``poll``, not yet fed).
    #[getter]
    fn has_request_in_flight(&self) -> bool {
        self.inner.has_request_in_flight()
    }

    /// Whether the session is between iterations.
    #[getter]
    fn at_boundary(&self) -> bool {
        self.inner.at_boundary()
    }

    /// The instrument's last accepted read-back per gate, mV (gates whose
    /// position is unknown are absent).
    #[getter]
    fn readback_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.inner.guard().readback_mv())
    }

    /// Where the run left each gate, gate → ``[lo, hi]`` mV (a range: the
    /// last accepted read-back, widened to what a request since may have
    /// visited; kept in the checkpoint). Empty before the run first read its
    /// gates: a gate found elsewhere than this range is a ``moved`` fault.
    #[getter]
    fn left_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let spans: std::collections::BTreeMap<&String, [f64; 2]> = self
            .inner
            .guard()
            .left_mv()
            .iter()
            .map(|(g, s)| (g, [s.lo_mv, s.hi_mv]))
            .collect();
        to_py(py, &spans)
    }

    /// The complete tuner config in use (gates with limits in mV, levels, …).
    #[getter]
    fn tuner_config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.inner.tuner().config())
    }

    /// Largest accepted |read-back − set value|, mV.
    #[getter]
    fn readback_tolerance_mv(&self) -> f64 {
        self.inner.config().readback_tolerance_mv
    }

    /// The session as a JSON string (tuner, mode, targets). A session
    /// restored from it reads every gate back before it moves one.
    fn checkpoint(&self) -> PyResult<String> {
        serde_json::to_string(&self.inner)
            .map_err(|e| PyRuntimeError::new_err(format!("cannot serialize the session: {e}")))
    }

    /// A session from ``checkpoint()``'s string.
    #[staticmethod]
    fn restore(checkpoint: &str) -> PyResult<Self> {
        let de = &mut serde_json::Deserializer::from_str(checkpoint);
        let inner: RunSession = serde_path_to_error::deserialize(de)
            .map_err(|e| PyValueError::new_err(format!("invalid checkpoint: {e}")))?;
        Ok(Self { inner })
    }

    /// Pickling: ``RunSession.restore(checkpoint())`` (so, like any
    /// restored session, an unpickled one reads every gate first).
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        let text = slf.borrow().checkpoint()?;
        Ok((slf.get_type().getattr("restore")?, (text,)))
    }

    fn __repr__(&self) -> String {
        format!("RunSession(status={:?})", self.inner.status().name())
    }
}

/// A (partial) tuner config dict (the run config's ``tuner`` table) merged
/// into the recommended tuner and validated, as ``RunSession`` sees it. With
/// a ``description`` key (a lab's device in a few lines: ``gates``,
/// ``qubit``, optional ``lines`` and ``sensing_dot``, as in the CLI's
/// ``[description]``) every level is derived from it and the other keys
/// merge over. Raises ``ValueError`` naming the field.
#[pyfunction]
#[pyo3(signature = (tuner_config = None))]
pub fn resolve_tuner_config<'py>(
    py: Python<'py>,
    tuner_config: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    to_py(py, &crate::config::tuner_config(tuner_config)?)
}
