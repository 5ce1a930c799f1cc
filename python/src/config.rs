//! Run configs from Python dicts: the core's one merge and validation
//! ([`spintune::run_config::resolve_simulation`], the server's too): every
//! key is optional, tables are merged key by key into
//! [`SimulationConfig::paper_default`], arrays replace the default array
//! whole, and a table whose tag (`kind`, …) differs from the default's
//! replaces it whole.

use std::collections::BTreeMap;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::{Map, Value};
use spintune::config_merge::merge;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
use spintune::run_config::resolve_simulation;
use spintune::tuner::TunerConfig;

use crate::convert::{from_py, from_value, to_value};

fn user_object(config: Option<&Bound<'_, PyAny>>, what: &str) -> PyResult<Map<String, Value>> {
    match config {
        None => Ok(Map::new()),
        Some(obj) if obj.is_none() => Ok(Map::new()),
        Some(obj) => match from_py::<Value>(obj, what)? {
            Value::Object(m) => Ok(m),
            other => Err(PyValueError::new_err(format!(
                "invalid {what}: expected a dict, got {}",
                match other {
                    Value::Array(_) => "a list",
                    Value::String(_) => "a string",
                    Value::Number(_) => "a number",
                    Value::Bool(_) => "a bool",
                    _ => "None",
                }
            ))),
        },
    }
}

/// A complete, validated [`SimulationConfig`] from a (partial) run config
/// dict: `name`, `seed`, `device`, `tuner`, and of the backend keys
/// `targets`, `tolerances` (applied to the top level), `driver` (must be
/// `"simulator"`) and `iteration_delay_ms` (no wall clock here: ignored).
pub fn simulation_config(config: Option<&Bound<'_, PyAny>>) -> PyResult<SimulationConfig> {
    let mut user = user_object(config, "config")?;
    for key in ["scpi", "bridge"] {
        if user.contains_key(key) {
            return Err(PyValueError::new_err(format!(
                "invalid config at `{key}`: a simulated run has no instruments; `{key}` is a server setting (use spintune.RunSession or spintune.qcodes for instruments)"
            )));
        }
    }
    if let Some(d) = user.remove("driver") {
        if d != Value::String("simulator".into()) {
            return Err(PyValueError::new_err(format!(
                "invalid config at `driver`: a simulated run drives the simulator, got {d}"
            )));
        }
    }
    user.remove("iteration_delay_ms");
    let targets: BTreeMap<String, f64> = match user.remove("targets") {
        Some(v) => from_value(v, "config at `targets`")?,
        None => BTreeMap::new(),
    };
    let tolerances: BTreeMap<String, Tolerance> = match user.remove("tolerances") {
        Some(v) => from_value(v, "config at `tolerances`")?,
        None => BTreeMap::new(),
    };
    // The core's one merge and validation (the server's too).
    let sim = resolve_simulation(user, &targets, &tolerances)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(sim)
}

/// A complete, validated [`TunerConfig`] from a (partial) `tuner` dict,
/// merged into the paper default's tuner.
pub fn tuner_config(config: Option<&Bound<'_, PyAny>>) -> PyResult<TunerConfig> {
    let user = user_object(config, "tuner config")?;
    let mut merged = to_value(&SimulationConfig::paper_default().tuner)?;
    merge(&mut merged, Value::Object(user));
    let tuner: TunerConfig = from_value(merged, "tuner config")?;
    tuner
        .validate()
        .map_err(|e| PyValueError::new_err(e.within("tuner").to_string()))?;
    Ok(tuner)
}
