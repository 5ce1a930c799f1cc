//! The simulation part of a run config, resolved from a user's partial
//! document: the one merge (ARCHITECTURE.md, dependency rules) used by the
//! backend's run config (TOML/JSON) and by Python's dicts alike.
//!
//! Every key is optional: what is not given comes from
//! [`SimulationConfig::paper_default`]. Tables are merged key by key into the
//! default; arrays replace the default array whole; a table whose tag
//! (`kind`, `type`, …) differs from the default's replaces it whole
//! ([`crate::config_merge::merge`]). `targets` and `tolerances` apply to the
//! top tuner level's parameters through the core's checks
//! ([`crate::parameter::ParameterSpec::check_target`]). Errors name the field.

use std::collections::BTreeMap;

use serde_json::{Map, Value};

use crate::config_error::ConfigError;
use crate::config_merge::merge;
use crate::driver::SimulationConfig;
use crate::parameter::Tolerance;
use crate::safety::GateSpec;

/// Resolve a user's partial simulation config (`name`, `seed`, `device`,
/// `tuner`) with top-level `targets` and `tolerances` into a complete,
/// validated [`SimulationConfig`].
///
/// ```
/// use std::collections::BTreeMap;
/// use spintune::run_config::resolve_simulation;
/// let user = serde_json::json!({ "seed": 4, "tuner": { "max_iterations": 3 } });
/// let targets = BTreeMap::from([("t_sr".to_string(), 70.0)]);
/// let sim = resolve_simulation(user.as_object().unwrap().clone(), &targets, &BTreeMap::new()).unwrap();
/// assert_eq!(sim.seed, 4);
/// assert_eq!(sim.tuner.top().parameters[0].target, Some(70.0));
/// let bad = BTreeMap::from([("t_sr".to_string(), -50.0)]);
/// let e = resolve_simulation(Default::default(), &bad, &BTreeMap::new()).unwrap_err();
/// assert_eq!(e.field, "targets.t_sr");
/// ```
pub fn resolve_simulation(
    user: Map<String, Value>,
    targets: &BTreeMap<String, f64>,
    tolerances: &BTreeMap<String, Tolerance>,
) -> Result<SimulationConfig, ConfigError> {
    let user = Value::Object(user);
    crate::tuner::check_magnitudes(&user, "")?;
    let user_device = user.get("device").cloned();
    let mut merged = serde_json::to_value(SimulationConfig::paper_default())
        .map_err(|e| ConfigError::new("", format!("internal: default config: {e}")))?;
    merge(&mut merged, user);
    let mut simulation: SimulationConfig =
        serde_path_to_error::deserialize(merged).map_err(|e| {
            let path = e.path().to_string();
            let field = if path == "." { String::new() } else { path };
            ConfigError::new(field, e.inner().to_string())
        })?;
    // The tuner as given first (an error names what is wrong with it, not a
    // device gate or a target that no longer fits), then the device's gate
    // names, then everything with the targets applied.
    simulation.tuner.validate().map_err(|e| e.within("tuner"))?;
    check_device_gates(user_device.as_ref(), &simulation.tuner.gates)?;
    apply_targets(&mut simulation, targets, tolerances)?;
    simulation.validate()?;
    Ok(simulation)
}

/// Targets and tolerances of the top level's parameters (`targets.NAME`,
/// `tolerances.NAME` in errors).
fn apply_targets(
    sim: &mut SimulationConfig,
    targets: &BTreeMap<String, f64>,
    tolerances: &BTreeMap<String, Tolerance>,
) -> Result<(), ConfigError> {
    if targets.is_empty() && tolerances.is_empty() {
        return Ok(());
    }
    let top = sim.tuner.top_level_mut().map_err(|e| e.within("tuner"))?;
    let known: Vec<String> = top.parameters.iter().map(|p| p.name.clone()).collect();
    let unknown = |section: &str, name: &str| {
        ConfigError::new(
            format!("{section}.{name}"),
            format!("the top tuner level has no parameter {name:?} (it has {known:?})"),
        )
    };
    for (name, &target) in targets {
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown("targets", name))?;
        p.check_target(target)
            .map_err(|e| ConfigError::new(format!("targets.{name}"), e.message))?;
        p.target = Some(target);
    }
    for (name, &tol) in tolerances {
        tol.validate()
            .map_err(|e| e.within(&format!("tolerances.{name}")))?;
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown("tolerances", name))?;
        p.tolerance = tol;
    }
    Ok(())
}

/// Every gate named by the user's `device` table (keys of its per-gate
/// maps, the gates of its quadratic terms, `sensing_dot.gate`) is a gate of
/// `tuner.gates`: a misspelt gate would otherwise be silently ignored (it
/// never moves). Only the user's keys are checked: the default device's
/// maps may name gates a custom `tuner.gates` leaves out. Call after the
/// config deserialized (the shapes are right).
fn check_device_gates(user: Option<&Value>, gates: &[GateSpec]) -> Result<(), ConfigError> {
    let Some(Value::Object(device)) = user else {
        return Ok(());
    };
    let known = |name: &str, field: String| -> Result<(), ConfigError> {
        if gates.iter().any(|g| g.name == name) {
            return Ok(());
        }
        let names: Vec<&str> = gates.iter().map(|g| g.name.as_str()).collect();
        Err(ConfigError::new(
            field,
            format!("{name:?} is not a gate of `tuner.gates` (known: {names:?})"),
        ))
    };
    let keys = |v: Option<&Value>, field: &str| -> Result<(), ConfigError> {
        if let Some(Value::Object(m)) = v {
            for k in m.keys() {
                known(k, format!("device.{field}.{k}"))?;
            }
        }
        Ok(())
    };
    let terms = |v: Option<&Value>, field: &str| -> Result<(), ConfigError> {
        if let Some(Value::Array(a)) = v {
            for (i, t) in a.iter().enumerate() {
                for end in ["a", "b"] {
                    if let Some(Value::String(g)) = t.get(end) {
                        known(g, format!("device.{field}[{i}].{end}"))?;
                    }
                }
            }
        }
        Ok(())
    };
    keys(device.get("reference_mv"), "reference_mv")?;
    for model in ["tunnel_coupling_uev", "lead_rate_per_ns"] {
        let m = device.get(model);
        keys(
            m.and_then(|m| m.get("linear_per_mv")),
            &format!("{model}.linear_per_mv"),
        )?;
        terms(
            m.and_then(|m| m.get("quadratic_per_mv2")),
            &format!("{model}.quadratic_per_mv2"),
        )?;
    }
    let x = device.get("crosstalk");
    for line in ["line_a", "line_b"] {
        let map = format!("{line}_per_mv");
        keys(x.and_then(|x| x.get(&map)), &format!("crosstalk.{map}"))?;
        let quad = format!("{line}_quadratic");
        terms(x.and_then(|x| x.get(&quad)), &format!("crosstalk.{quad}"))?;
    }
    let sd = device.get("sensing_dot");
    keys(
        sd.and_then(|s| s.get("lever_per_mv")),
        "sensing_dot.lever_per_mv",
    )?;
    if let Some(Value::String(g)) = sd.and_then(|s| s.get("gate")) {
        known(g, "device.sensing_dot.gate".into())?;
    }
    Ok(())
}
