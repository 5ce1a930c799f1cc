//! Run configs from Python dicts, with the merge rules of the run config
//! TOML/JSON (`backend/src/config.rs`): every key is optional, tables are
//! merged key by key into [`SimulationConfig::paper_default`], arrays replace
//! the default array whole, and a table whose tag (`kind`, …) differs from the
//! default's replaces it whole.

use std::collections::BTreeMap;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::{Map, Value};
use spintune::config_merge::merge;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
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
    let mut merged = to_value(&SimulationConfig::paper_default())?;
    merge(&mut merged, Value::Object(user));
    let mut sim: SimulationConfig = from_value(merged, "config")?;
    apply_targets(&mut sim, &targets, &tolerances)?;
    sim.validate()
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

fn apply_targets(
    sim: &mut SimulationConfig,
    targets: &BTreeMap<String, f64>,
    tolerances: &BTreeMap<String, Tolerance>,
) -> PyResult<()> {
    if targets.is_empty() && tolerances.is_empty() {
        return Ok(());
    }
    let top = sim.tuner.top_mut();
    let known: Vec<String> = top.parameters.iter().map(|p| p.name.clone()).collect();
    let unknown = |section: &str, name: &str| {
        PyValueError::new_err(format!(
            "invalid config at `{section}.{name}`: the top tuner level has no parameter {name:?} (it has {known:?})"
        ))
    };
    for (name, &target) in targets {
        if !target.is_finite() {
            return Err(PyValueError::new_err(format!(
                "invalid config at `targets.{name}`: must be a finite number"
            )));
        }
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown("targets", name))?;
        p.target = Some(target);
    }
    for (name, &tol) in tolerances {
        tol.validate().map_err(|e| {
            PyValueError::new_err(e.within(&format!("tolerances.{name}")).to_string())
        })?;
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown("tolerances", name))?;
        p.tolerance = tol;
    }
    Ok(())
}
