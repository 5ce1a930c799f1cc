//! The Python package `spintune` (native part `spintune._core`), built by
//! maturin: `pip install ./python`. It wraps the core crate `spintune` and
//! holds no tuner logic of its own; see `docs/python.md`.
//!
//! Units as in the core: gate voltages in mV, t_sr in ns, w in µV, gradients
//! in parameter unit per mV, lab time in s.

use pyo3::prelude::*;

mod array;
mod columns;
mod config;
mod convert;
mod driven;
mod kalman;
mod ramp;
mod session;
mod simulation;

/// Native part of ``spintune`` (import ``spintune``, not this module).
#[pymodule]
#[pyo3(name = "_core")]
fn core_module(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<kalman::PyKalmanGradient>()?;
    m.add_function(wrap_pyfunction!(kalman::newton_step, m)?)?;
    m.add_class::<session::PyRunSession>()?;
    m.add_class::<ramp::PyRamp>()?;
    m.add_class::<columns::PyRecordColumns>()?;
    m.add_function(wrap_pyfunction!(session::resolve_tuner_config, m)?)?;
    m.add_class::<simulation::PySimulationRun>()?;
    m.add_class::<simulation::PySimulatedDevice>()?;
    m.add_class::<array::PyArraySimulation>()?;
    m.add_function(wrap_pyfunction!(simulation::default_config, m)?)?;
    m.add_function(wrap_pyfunction!(simulation::paper_config, m)?)?;
    m.add_function(wrap_pyfunction!(simulation::resolve_config, m)?)?;
    m.add("PROTOCOL_VERSION", spintune::protocol::PROTOCOL_VERSION)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
