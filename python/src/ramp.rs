//! `spintune.Ramp`: the core's sans-IO ramp to a working point
//! (`spintune::session::ramp::Ramp`), through the run session's guard. This
//! file converts dicts.

use std::collections::BTreeMap;

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use serde::Deserialize;
use spintune::protocol::{Request, Response};
use spintune::safety::GateSpec;
use spintune::session::ramp::{Ramp, RampError, RampOutput};

use crate::convert::{from_py, to_py};

/// A gate's limits for a ramp (`initial_mv` optional: not used).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RampGate {
    name: String,
    min_mv: f64,
    max_mv: f64,
    max_step_mv: f64,
    #[serde(default)]
    #[allow(dead_code)]
    initial_mv: Option<f64>,
}

fn ramp_error(e: RampError) -> PyErr {
    match e {
        RampError::NothingOutstanding => PyRuntimeError::new_err(e.to_string()),
        other => PyValueError::new_err(other.to_string()),
    }
}

/// A ramp of gates from where the instrument says they are to a working
/// point, in steps within the limits (the core's
/// ``spintune::session::ramp::Ramp``): a sans-IO loop like ``RunSession``,
/// through the same safety guard. It reads every gate first, then sets all
/// gates together along straight lines; each set is checked against the
/// gates' limits and ``max_step_mv`` from the last **read-back**, each answer
/// must carry exactly the set gates within ``readback_tolerance_mv``::
///
///     ramp = spintune.Ramp(gates, {"SD1": -600.0})
///     while (out := ramp.poll())["output"] == "execute":
///         ramp.feed(my_instrument(out["request"]))
///
/// Args:
///     gates: the gates' limits, a list of dicts ``{"name", "min_mv",
///         "max_mv", "max_step_mv"}`` (mV; ``initial_mv`` allowed, unused):
///         the range each gate may be ramped *through* (e.g. the
///         instrument's safe range, wider than the tuning window).
///     target_mv: gate → working point, mV (inside its limits). Only these
///         gates are read and moved.
///     readback_tolerance_mv: largest accepted |read-back − set value|, mV.
///
/// ``poll()`` returns ``{"output": "execute", "request": {...}}`` (a
/// ``read_voltages`` first, then ``set_voltages``; answer them like a
/// ``RunSession``'s) or ``{"output": "done"}``. A refusal — a target or a
/// read-back outside the limits (``"SD1 reads 0 mV, outside [-1000, -100] mV
/// …"``), an answer the guard refuses, a device error — raises
/// ``ValueError`` from ``feed``/``poll`` and ends the ramp (nothing more is
/// requested).
#[pyclass(name = "Ramp", module = "spintune")]
pub struct PyRamp {
    inner: Ramp,
}

#[pymethods]
impl PyRamp {
    #[new]
    #[pyo3(signature = (gates, target_mv, readback_tolerance_mv = 0.05))]
    fn new(
        gates: &Bound<'_, PyAny>,
        target_mv: &Bound<'_, PyAny>,
        readback_tolerance_mv: f64,
    ) -> PyResult<Self> {
        let gates: Vec<RampGate> = from_py(gates, "gates")?;
        let specs: Vec<GateSpec> = gates
            .into_iter()
            .map(|g| GateSpec {
                name: g.name,
                min_mv: g.min_mv,
                max_mv: g.max_mv,
                max_step_mv: g.max_step_mv,
                initial_mv: g.min_mv,
            })
            .collect();
        for g in &specs {
            if !(g.min_mv.is_finite()
                && g.max_mv.is_finite()
                && g.min_mv <= g.max_mv
                && g.max_step_mv.is_finite()
                && g.max_step_mv > 0.0)
            {
                return Err(PyValueError::new_err(format!(
                    "gate {}: limits [{}, {}] mV with max_step_mv {}: need finite min_mv ≤ max_mv and max_step_mv > 0",
                    g.name, g.min_mv, g.max_mv, g.max_step_mv
                )));
            }
        }
        let target: BTreeMap<String, f64> = from_py(target_mv, "target_mv")?;
        let inner = Ramp::new(&specs, &target, readback_tolerance_mv).map_err(ramp_error)?;
        Ok(Self { inner })
    }

    /// The next request (``{"output": "execute", "request": {...}}``) or
    /// ``{"output": "done"}``. Raises ``ValueError`` once the ramp failed.
    fn poll<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        #[derive(serde::Serialize)]
        #[serde(tag = "output", rename_all = "snake_case")]
        enum View<'a> {
            Execute { request: &'a Request },
            Done,
        }
        match self.inner.poll().map_err(ramp_error)? {
            RampOutput::Execute(request) => to_py(py, &View::Execute { request: &request }),
            RampOutput::Done => to_py(py, &View::Done),
        }
    }

    /// Answer the outstanding request (a response dict as for
    /// ``RunSession.feed``). Raises ``ValueError`` if the answer is refused
    /// (the ramp ends) and ``RuntimeError`` if no request is outstanding.
    fn feed(&mut self, response: &Bound<'_, PyAny>) -> PyResult<()> {
        let response: Response = from_py(response, "response")?;
        self.inner.feed(response).map_err(ramp_error)
    }

    /// Sets sent so far.
    #[getter]
    fn steps_done(&self) -> usize {
        self.inner.steps_done()
    }

    /// Sets in all (sent + still needed from the present read-backs);
    /// ``None`` before the first read.
    #[getter]
    fn steps_planned(&self) -> Option<usize> {
        self.inner.steps_planned()
    }

    /// The last accepted read-backs, gate → mV.
    #[getter]
    fn readback_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.inner.readback_mv())
    }

    /// The target, gate → mV.
    #[getter]
    fn target_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.inner.target_mv())
    }

    fn __repr__(&self) -> String {
        format!(
            "Ramp(gates={}, steps_done={})",
            self.inner.target_mv().len(),
            self.inner.steps_done()
        )
    }
}
