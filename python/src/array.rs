//! `spintune.ArraySimulation`: the core's `driver::ArraySimulationRun` (the
//! joint loop of an array of double dots in a run session, on a simulated
//! array), iterated from Python like `spintune.SimulationRun`.

use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use spintune::driver::array::ArraySimulationConfig;
use spintune::sim::array::ArrayDevice;
use spintune::tuner::array_run::ArrayRun;

use crate::config::{array_simulation_config, config_error};
use crate::convert::to_py;
use crate::driven::{reduce, DrivenRun};
use crate::simulation::truth_dict;

/// A simulated array of double-dot cells tuned jointly (the core's
/// ``spintune::driver::ArraySimulationRun``): every cell ``k`` has its own
/// gates ``c{k}.N``, ``c{k}.SA``, … (mV) and parameters ``c{k}.t_sr`` (ns)
/// and ``c{k}.w`` (µV); neighbouring cells couple through crosstalk. The run
/// finishes when every cell is measured inside its band.
///
/// Args:
///     config: a (partial) array config dict merged into the default
///         (tables key by key, lists replace): ``name``, ``array``
///         (``cells`` 1..=16, ``device_seed``, ``seed``, ``crosstalk``,
///         ``readout_groups``), ``device`` (cell 0; the other cells are
///         drawn around it), ``targets`` (list of ``(t_sr ns, w µV)``
///         pairs: one for every cell or one per cell), ``tuning`` (e.g.
///         ``relative_tolerance``, the band of every target, default 0.1),
///         ``cross_calibration``. ``None``: 3 cells, targets t_sr = 20 ns,
///         w = 270 µV.
///
/// Iterating yields one ``IterationRecord`` dict per iteration (as
/// ``SimulationRun``), its ``parameters`` named ``c{k}.t_sr`` and
/// ``c{k}.w``, ``tuned`` when every cell is in band, ``lab_seconds`` (s).
///
/// Raises ``ValueError`` naming the field for an unknown key or a bad value.
/// Thread-safe like ``SimulationRun``.
#[pyclass(name = "ArraySimulation", module = "spintune", frozen)]
pub struct PyArraySimulation {
    driven: DrivenRun<ArrayRun, ArrayDevice>,
    config: ArraySimulationConfig,
}

#[pymethods]
impl PyArraySimulation {
    #[new]
    #[pyo3(signature = (config = None))]
    fn new(config: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let config = array_simulation_config(config)?;
        let run = config.build().map_err(config_error)?;
        Ok(Self {
            driven: DrivenRun::new(run),
            config,
        })
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    /// Run until the next iteration completes and return its record (dict).
    /// Raises ``StopIteration`` when the run is over (every cell in band, or
    /// stopped) or paused, ``RuntimeError`` if it faulted.
    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.driven.next_py(py)
    }

    /// Run at most ``max_iterations`` more iterations (fewer when every cell
    /// is in band, or the run is paused or stopped, also from another
    /// thread) and return every record so far (list of dicts).
    #[pyo3(signature = (max_iterations = 200))]
    fn run<'py>(&self, py: Python<'py>, max_iterations: u64) -> PyResult<Bound<'py, PyList>> {
        self.driven.run(py, Some(max_iterations))
    }

    /// Every record produced so far, oldest first (list of dicts).
    #[getter]
    fn records<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        self.driven.records(py)
    }

    /// The complete config of this array (dict), defaults filled in.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py(py, &self.config)
    }

    /// Number of cells.
    #[getter]
    fn cells(&self) -> u32 {
        self.config.described().cells
    }

    /// Present targets per cell (list of ``(t_sr ns, w µV)``).
    #[getter]
    fn targets(&self, py: Python<'_>) -> Vec<(f64, f64)> {
        self.driven
            .with(py, |inner| inner.run.tuner().targets().to_vec())
    }

    /// Present status, e.g. ``{"state": "running"}``.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.driven.status(py)
    }

    /// Apply a control command (JSON of ``protocol::ControlCommand``):
    /// ``{"action": "pause"}``, ``"resume"``, ``"stop"``, or a cell's new
    /// target, ``{"action": "set_target", "parameter": "c1.t_sr", "target":
    /// 30.0}`` (ns; ``"c1.w"`` in µV; the band stays the config's). A new
    /// target revives a finished run as paused: resume it. Returns the new
    /// status.
    fn control<'py>(
        &self,
        py: Python<'py>,
        command: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        self.driven.control(py, command)
    }

    /// The simulator's noiseless truth of every cell at the present
    /// voltages, crosstalk included (list of dicts, index = cell): ``w``
    /// (µV), ``t_sr`` (ns), ``t_c_uev`` (µeV), ``gamma_per_ns`` (1/ns),
    /// ``mu_a_mv``, ``mu_b_mv``, ``sd_flank_mv`` (mV), ``sd_contrast``
    /// (0..1). World side, for teaching and checking: the tuner never sees
    /// it (it measures).
    fn truth<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let truths = self.driven.with(py, |inner| {
            let device = inner.run.device();
            (0..device.cells())
                .filter_map(|c| device.truth(c))
                .collect::<Vec<_>>()
        });
        let list = PyList::empty(py);
        for t in &truths {
            list.append(truth_dict(py, t)?)?;
        }
        Ok(list)
    }

    /// Present gate voltages of every cell, mV (dict ``c{k}.gate`` → mV).
    #[getter]
    fn voltages_mv<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let v = self
            .driven
            .with(py, |inner| inner.run.device().voltages_mv());
        to_py(py, &v)
    }

    /// The records so far as an ``xarray.Dataset`` (needs ``xarray``) over
    /// ``iteration`` and ``cell`` (coordinate 0…cells−1): ``t_sr`` (ns) and
    /// ``w`` (uV) as measured, with ``*_std``, ``*_target`` and
    /// ``*_tolerance`` (same units), ``grad_t_sr``, ``grad_w`` (and
    /// ``*_std``) over ``cell`` and ``tuning_gate`` (1/mV, log space);
    /// ``voltage`` over ``gate`` (mV), ``step`` over ``tuning_gate`` (mV),
    /// ``lab_seconds`` (s), ``tuned`` (every cell in band) and
    /// ``failed_evaluations`` over ``iteration``. Every numeric variable has
    /// a ``units`` attribute (UDUNITS spelling: ``uV`` for µV).
    fn to_xarray<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let attrs = PyDict::new(py);
        attrs.set_item(
            "title",
            format!("spintune simulated array: {}", self.config.name),
        )?;
        attrs.set_item("name", &self.config.name)?;
        attrs.set_item("cells", self.config.array.cells)?;
        attrs.set_item("device_seed", self.config.array.device_seed)?;
        attrs.set_item("seed", self.config.array.seed)?;
        attrs.set_item(
            "spintune_config",
            serde_json::to_string(&self.config)
                .map_err(|e| PyRuntimeError::new_err(e.to_string()))?,
        )?;
        py.import("spintune._xarray")?.call_method1(
            "array_records_to_dataset",
            (self.records(py)?, self.config.array.cells, attrs),
        )
    }

    /// Write ``to_xarray()`` to a netCDF file at ``path`` (needs ``xarray``
    /// and ``netcdf4``).
    fn to_netcdf(&self, py: Python<'_>, path: &Bound<'_, PyAny>) -> PyResult<()> {
        self.to_xarray(py)?.call_method1("to_netcdf", (path,))?;
        Ok(())
    }

    /// The whole array run as a JSON string: config, session, simulated
    /// array (RNGs and lab clock included) and the records so far.
    /// ``ArraySimulation.restore(text)`` continues bit for bit where this
    /// one is; pickling goes through it.
    fn checkpoint(&self, py: Python<'_>) -> PyResult<String> {
        self.driven.checkpoint(py, &self.config)
    }

    /// An array run from ``checkpoint()``'s string.
    #[staticmethod]
    fn restore(py: Python<'_>, checkpoint: &str) -> PyResult<Self> {
        let (config, driven) = DrivenRun::restore(py, checkpoint)?;
        Ok(Self { driven, config })
    }

    /// Pickling: ``ArraySimulation.restore(checkpoint())``.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        reduce(slf.as_any(), slf.get().checkpoint(slf.py())?)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let (n, status) = self.driven.summary(py);
        format!(
            "ArraySimulation(name={:?}, cells={}, iterations={n}, status={status:?})",
            self.config.name, self.config.array.cells,
        )
    }
}
