//! `spintune.SimulationRun` and `spintune.SimulatedDevice`: the core's
//! `driver::SimulationRun` (run session + simulated double dot) and
//! `sim::SimulatedDevice`, iterated from Python.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::Request;
use spintune::sim::{SimulatedDevice, Truth};
use spintune::tuner::Tuner;

use crate::config::simulation_config;
use crate::convert::{from_py, to_py};
use crate::driven::{reduce, DrivenRun};

/// A tuning run of the paper's default setup on the simulated double dot
/// (the core's ``spintune::driver::SimulationRun``: the run session driving
/// the simulator). The same seed and config give bit-identical records to
/// ``spintune run`` and the dashboard's in-browser mode.
///
/// Args:
///     config: a (partial) run config as a dict with the keys of the run
///         config TOML/JSON — ``name``, ``seed``, ``device``, ``tuner`` — merged
///         into the paper default (tables key by key, arrays replace);
///         ``targets`` and ``tolerances`` (per top-level parameter, e.g.
///         ``{"t_sr": 20.0}`` in ns, ``{"w": {"relative": 0.1}}``) are
///         applied too. ``None``: the paper default (targets t_sr = 20 ns,
///         w = 270 µV, seed 1, no iteration limit — set
///         ``{"tuner": {"max_iterations": n}}`` or stop iterating yourself).
///
/// Iterating yields one dict per iteration, with the fields of the JSON
/// ``IterationRecord``: ``iteration``, ``voltages_mv`` (gate → mV),
/// ``gates``, ``parameters`` (``name``, ``unit``, ``value``, ``std``,
/// ``target``, ``tolerance``), ``gradients`` (``parameter``, ``unit``,
/// ``gradient``, ``covariance``), ``step_mv``, ``tuned``, ``lab_seconds`` (s),
/// ``scan_counts``, ``failed_evaluations``, ``scans``, ``events``.
///
/// Raises ``ValueError`` naming the field for an invalid config.
///
/// Thread-safe: ``status``, ``records``, ``control()`` (e.g. a stop) and the
/// other readers work from another thread while ``run()`` iterates (it
/// releases the GIL while computing; a reader waits at most for the
/// iteration in progress).
#[pyclass(name = "SimulationRun", module = "spintune", frozen)]
pub struct PySimulationRun {
    driven: DrivenRun<Tuner, SimulatedDevice>,
    config: SimulationConfig,
}

#[pymethods]
impl PySimulationRun {
    #[new]
    #[pyo3(signature = (config = None))]
    fn new(config: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let cfg = simulation_config(config)?;
        let run =
            SimulationRun::new(cfg.clone()).map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(Self {
            driven: DrivenRun::new(run),
            config: cfg,
        })
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    /// Run until the next iteration completes and return its record (dict).
    /// Raises ``StopIteration`` when the run is over (finished, stopped) or
    /// paused, ``RuntimeError`` if it faulted.
    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.driven.next_py(py)
    }

    /// Run to the end (or until paused or stopped, also from another thread)
    /// and return every record of the run so far (list of dicts). With
    /// ``max_iterations``, run at most that many more iterations.
    #[pyo3(signature = (max_iterations = None))]
    fn run<'py>(
        &self,
        py: Python<'py>,
        max_iterations: Option<u64>,
    ) -> PyResult<Bound<'py, PyList>> {
        self.driven.run(py, max_iterations)
    }

    /// Every record produced so far, oldest first (list of dicts).
    #[getter]
    fn records<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        self.driven.records(py)
    }

    /// The complete config of this run (dict: ``name``, ``seed``, ``device``,
    /// ``tuner``), defaults filled in.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, &self.config)
    }

    /// Present status, e.g. ``{"state": "running"}``.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.driven.status(py)
    }

    /// Apply a control command (JSON of ``protocol::ControlCommand``, e.g.
    /// ``{"action": "set_target", "parameter": "w", "target": 300.0}`` in the
    /// parameter's unit, ``{"action": "pause"}`` or ``{"action": "stop"}``,
    /// also from another thread while ``run()`` iterates); returns the new
    /// status.
    fn control<'py>(
        &self,
        py: Python<'py>,
        command: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        self.driven.control(py, command)
    }

    /// Noiseless ground truth of the simulated device at its present
    /// voltages (dict): ``w`` (µV), ``t_sr`` (ns), ``t_c_uev`` (µeV),
    /// ``gamma_per_ns`` (1/ns), ``mu_a_mv``, ``mu_b_mv``, ``sd_flank_mv`` (mV),
    /// ``sd_contrast`` (0..1).
    fn truth<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let truth = self.driven.with(py, |inner| inner.run.device().truth());
        truth_dict(py, &truth)
    }

    /// Present gate voltages of the simulated device, mV (dict gate → mV).
    #[getter]
    fn voltages_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let v = self
            .driven
            .with(py, |inner| inner.run.device().voltages_mv().clone());
        to_py(py, &v)
    }

    /// The records so far as an ``xarray.Dataset`` over dimension
    /// ``iteration`` (needs ``xarray``): per parameter ``p`` the variables
    /// ``p``, ``p_std``, ``p_target``, ``p_tolerance`` (unit of p), per
    /// gradient ``grad_p`` and ``grad_p_std`` over ``tuning_gate`` (unit of
    /// p per mV), ``voltage`` over ``gate`` (mV), ``step`` over
    /// ``tuning_gate`` (mV), ``lab_seconds`` (s), ``tuned``,
    /// ``failed_evaluations`` and ``scans_<kind>``; every variable has a
    /// ``units`` attribute.
    fn to_xarray<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let attrs = PyDict::new(py);
        attrs.set_item(
            "title",
            format!("spintune simulated run: {}", self.config.name),
        )?;
        attrs.set_item("name", &self.config.name)?;
        attrs.set_item("seed", self.config.seed)?;
        attrs.set_item(
            "spintune_config",
            serde_json::to_string(&self.config)
                .map_err(|e| PyRuntimeError::new_err(e.to_string()))?,
        )?;
        py.import("spintune._xarray")?
            .call_method1("records_to_dataset", (self.records(py)?, attrs))
    }

    /// Write ``to_xarray()`` to a netCDF file at ``path`` (needs ``xarray``
    /// and ``netcdf4``).
    fn to_netcdf(&self, py: Python<'_>, path: &Bound<'_, PyAny>) -> PyResult<()> {
        self.to_xarray(py)?.call_method1("to_netcdf", (path,))?;
        Ok(())
    }

    /// The whole run as a JSON string: config, session, simulated device
    /// (its RNG and lab clock included) and the records so far.
    /// ``SimulationRun.restore(text)`` continues bit for bit where this one
    /// is; pickling goes through it.
    fn checkpoint(&self, py: Python<'_>) -> PyResult<String> {
        self.driven.checkpoint(py, &self.config)
    }

    /// A run from ``checkpoint()``'s string.
    #[staticmethod]
    fn restore(py: Python<'_>, checkpoint: &str) -> PyResult<Self> {
        let (config, driven) = DrivenRun::restore(py, checkpoint)?;
        Ok(Self { driven, config })
    }

    /// Pickling: ``SimulationRun.restore(checkpoint())``.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        reduce(slf.as_any(), slf.get().checkpoint(slf.py())?)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let (n, status) = self.driven.summary(py);
        format!(
            "SimulationRun(name={:?}, seed={}, iterations={n}, status={status:?})",
            self.config.name, self.config.seed,
        )
    }
}

pub(crate) fn truth_dict<'py>(py: Python<'py>, t: &Truth) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for name in Truth::PARAMETERS {
        d.set_item(name, t.get(name))?;
    }
    Ok(d)
}

/// The simulated double dot alone (the core's ``spintune::sim::SimulatedDevice``):
/// answers requests like an instrument, e.g. to back QCoDeS parameters in a
/// dry run or a test.
///
/// Args:
///     config: a (partial) run config dict as for ``SimulationRun``; its
///         ``device``, ``tuner.gates`` (limits and start voltages, mV) and
///         ``seed`` are used.
///     seed: overrides the config's seed.
///
/// ``execute(request)`` takes a request dict (JSON of ``protocol::Request``)
/// and returns the response dict (JSON of ``protocol::Response``); a set
/// outside the gate limits is answered with ``{"response": "error", …}``
/// and changes nothing.
#[pyclass(name = "SimulatedDevice", module = "spintune")]
pub struct PySimulatedDevice {
    device: SimulatedDevice,
}

#[pymethods]
impl PySimulatedDevice {
    #[new]
    #[pyo3(signature = (config = None, seed = None))]
    fn new(config: Option<&Bound<'_, PyAny>>, seed: Option<u64>) -> PyResult<Self> {
        let mut cfg = simulation_config(config)?;
        if let Some(seed) = seed {
            cfg.seed = seed;
        }
        let device = cfg
            .simulated_device()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(Self { device })
    }

    /// Execute one request (dict) and return the response (dict).
    /// Set/read requests are in mV; scans return raw traces.
    fn execute<'py>(
        &mut self,
        py: Python<'py>,
        request: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let request: Request = from_py(request, "request")?;
        let response = self.device.execute(&request);
        to_py(py, &response)
    }

    /// Present gate voltages, mV (dict gate → mV).
    #[getter]
    fn voltages_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.device.voltages_mv())
    }

    /// The gates with their limits (list of dicts, mV).
    #[getter]
    fn gates<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, self.device.gates())
    }

    /// Cumulative simulated lab time, s.
    #[getter]
    fn lab_seconds(&self) -> f64 {
        self.device.lab_seconds()
    }

    /// Noiseless ground truth at the present voltages (see ``SimulationRun.truth``).
    fn truth<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        truth_dict(py, &self.device.truth())
    }

    fn __repr__(&self) -> String {
        format!(
            "SimulatedDevice(gates={}, lab_seconds={:.1})",
            self.device.gates().len(),
            self.device.lab_seconds()
        )
    }
}

/// The default run config (dict: ``name``, ``seed``, ``device``,
/// ``tuner``; voltages in mV, t_sr in ns, w in µV): the recommended
/// strategy on the paper's device, what a config without ``tuner`` gets.
#[pyfunction]
pub fn default_config(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_py(py, &SimulationConfig::recommended())
}

/// The paper's own rule on its device (linear space, pseudo-inverse step,
/// one move per measurement, three finite-difference repetitions), for
/// teaching and comparison; pass it as the config of ``SimulationRun``.
#[pyfunction]
pub fn paper_config(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_py(py, &SimulationConfig::paper_default())
}

/// A (partial) run config dict merged into the default (the recommended
/// strategy, or the levels of a ``description`` key) and validated, as
/// ``SimulationRun`` sees it. Raises ``ValueError`` naming the field.
#[pyfunction]
#[pyo3(signature = (config = None))]
pub fn resolve_config<'py>(
    py: Python<'py>,
    config: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    to_py(py, &simulation_config(config)?)
}
