//! Run configs from Python dicts: the core's one merge and validation
//! ([`spintune::run_config::resolve_simulation`], the server's too): every
//! key is optional, tables are merged key by key into
//! [`SimulationConfig::recommended`] (or a `description`'s levels), arrays replace the default array
//! whole, and a table whose tag (`kind`, …) differs from the default's
//! replaces it whole.

use std::collections::BTreeMap;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::{Map, Value};
use spintune::config_merge::merge;
use spintune::driver::array::ArraySimulationConfig;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
use spintune::run_config::resolve_simulation;
use spintune::tuner::TunerConfig;

use spintune::ConfigError;

use crate::convert::{from_py, plain, to_value};

/// A config error as the core displays it (`invalid config at `field`:
/// message`), the one format of every config error of the package.
pub fn config_error(e: ConfigError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Deserialize a config value; an error names the field below `prefix`
/// (`tuner` → `invalid config at `tuner.levels[0].kind`: …`).
fn config_from_value<T: serde::de::DeserializeOwned>(value: Value, prefix: &str) -> PyResult<T> {
    serde_path_to_error::deserialize(value).map_err(|e| {
        let path = e.path().to_string();
        let field = if path == "." { String::new() } else { path };
        config_error(ConfigError::new(field, e.inner().to_string()).within(prefix))
    })
}

/// The first NaN or infinite float in a plain Python value (dicts, lists),
/// as a config error naming its field: JSON has no NaN, so without this
/// check it would arrive as `null` ("invalid type: null, expected f64").
fn check_finite(obj: &Bound<'_, PyAny>, path: &str) -> PyResult<()> {
    use pyo3::types::{PyDict, PyFloat, PyList};
    if let Ok(f) = obj.cast::<PyFloat>() {
        let v = f.value();
        if !v.is_finite() {
            return Err(config_error(ConfigError::new(
                path,
                format!("{v} is not a finite number"),
            )));
        }
    } else if let Ok(d) = obj.cast::<PyDict>() {
        for (k, v) in d.iter() {
            let key = k.str()?.to_string();
            let sub = if path.is_empty() {
                key
            } else {
                format!("{path}.{key}")
            };
            check_finite(&v, &sub)?;
        }
    } else if let Ok(l) = obj.cast::<PyList>() {
        for (i, v) in l.iter().enumerate() {
            check_finite(&v, &format!("{path}[{i}]"))?;
        }
    }
    Ok(())
}

/// A user's (partial) config dict as JSON; `prefix` is where it sits in the
/// run config (`""` for the whole, `tuner` for the tuner table).
fn user_object(config: Option<&Bound<'_, PyAny>>, prefix: &str) -> PyResult<Map<String, Value>> {
    match config {
        None => Ok(Map::new()),
        Some(obj) if obj.is_none() => Ok(Map::new()),
        Some(obj) => {
            let p = plain(obj)?;
            check_finite(&p, prefix)?;
            match from_py::<Value>(&p, "config")? {
                Value::Object(m) => Ok(m),
                other => Err(config_error(ConfigError::new(
                    prefix,
                    format!(
                        "expected a dict, got {}",
                        match other {
                            Value::Array(_) => "a list",
                            Value::String(_) => "a string",
                            Value::Number(_) => "a number",
                            Value::Bool(_) => "a bool",
                            _ => "None",
                        }
                    ),
                ))),
            }
        }
    }
}

/// A complete, validated [`SimulationConfig`] from a (partial) run config
/// dict: `name`, `seed`, `device`, `tuner`, and of the backend keys
/// `targets`, `tolerances` (applied to the top level), `driver` (must be
/// `"simulator"`) and `iteration_delay_ms` (no wall clock here: ignored).
pub fn simulation_config(config: Option<&Bound<'_, PyAny>>) -> PyResult<SimulationConfig> {
    let mut user = user_object(config, "")?;
    for key in ["scpi", "bridge"] {
        if user.contains_key(key) {
            return Err(config_error(ConfigError::new(
                key,
                format!("a simulated run has no instruments; `{key}` is a server setting (use spintune.RunSession or spintune.qcodes for instruments)"),
            )));
        }
    }
    if let Some(d) = user.remove("driver") {
        if d != Value::String("simulator".into()) {
            return Err(config_error(ConfigError::new(
                "driver",
                format!("a simulated run drives the simulator, got {d}"),
            )));
        }
    }
    user.remove("iteration_delay_ms");
    let targets: BTreeMap<String, f64> = match user.remove("targets") {
        Some(v) => config_from_value(v, "targets")?,
        None => BTreeMap::new(),
    };
    let tolerances: BTreeMap<String, Tolerance> = match user.remove("tolerances") {
        Some(v) => config_from_value(v, "tolerances")?,
        None => BTreeMap::new(),
    };
    // The core's one merge and validation (the server's too).
    let sim = resolve_simulation(user, &targets, &tolerances).map_err(config_error)?;
    Ok(sim)
}

/// A complete [`ArraySimulationConfig`] from a (partial) array config
/// dict (`name`, `array`, `device`, `targets`, `tuning`,
/// `cross_calibration`), merged into [`ArraySimulationConfig::default`] by
/// the same rule (tables key by key, lists replace); an unknown key or a
/// bad value is a `ValueError` naming the field. The core's
/// [`ArraySimulationConfig::build`] checks the rest.
pub fn array_simulation_config(
    config: Option<&Bound<'_, PyAny>>,
) -> PyResult<ArraySimulationConfig> {
    let user = user_object(config, "")?;
    let mut merged = to_value(&ArraySimulationConfig::default())?;
    merge(&mut merged, Value::Object(user));
    let cfg: ArraySimulationConfig = config_from_value(merged, "")?;
    // checked here so that the error names `device.…` (the array builds
    // every cell's device from it and would name the cell instead)
    cfg.device
        .validate()
        .map_err(|e| config_error(e.within("device")))?;
    Ok(cfg)
}

/// A complete, validated [`TunerConfig`] from a (partial) `tuner` dict,
/// merged into the recommended tuner, or into the tuner a device
/// description derives when the dict has a `description` key (the core's
/// one derivation, [`spintune::run_config::default_tuner`]; the other keys
/// merge over it, `gates`/`levels` are refused next to it).
pub fn tuner_config(config: Option<&Bound<'_, PyAny>>) -> PyResult<TunerConfig> {
    let mut user = user_object(config, "tuner")?;
    let description = user.remove("description");
    spintune::tuner::check_magnitudes(&Value::Object(user.clone()), "tuner")
        .map_err(config_error)?;
    let user_tuner = Value::Object(user.clone());
    let base = spintune::run_config::default_tuner(description, Some(&user_tuner))
        .map_err(config_error)?;
    let mut merged = to_value(&base)?;
    merge(&mut merged, Value::Object(user));
    let tuner: TunerConfig = config_from_value(merged, "tuner")?;
    tuner
        .validate()
        .map_err(|e| config_error(e.within("tuner")))?;
    Ok(tuner)
}
