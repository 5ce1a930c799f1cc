//! The simulation part of a run config, resolved from a user's partial
//! document: the one merge (ARCHITECTURE.md, dependency rules) used by the
//! backend's run config (TOML/JSON) and by Python's dicts alike.
//!
//! Every key is optional: what is not given comes from
//! [`SimulationConfig::recommended`]. A `description` table (a lab's device
//! in a few lines, [`DeviceDescription`]) replaces the default tuner's
//! gates and levels by those it derives; `tuner` keys still merge over them
//! (`tuner.gates` and `tuner.levels` are then refused: one source of levels). Tables are merged key by key into the
//! default; arrays replace the default array whole; a table whose tag
//! (`kind`, `type`, …) differs from the default's replaces it whole
//! ([`crate::config_merge::merge`]). `targets` and `tolerances` apply to the
//! top tuner level's parameters through the core's checks
//! ([`crate::parameter::ParameterSpec::check_target`]). Errors name the field.

use std::collections::BTreeMap;

use serde_json::{Map, Value};

use crate::config_error::ConfigError;
use crate::config_merge::merge;
use crate::description::DeviceDescription;
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
    let mut user = user;
    let description = user.remove("description");
    let user = Value::Object(user);
    crate::tuner::check_magnitudes(&user, "")?;
    let user_device = user.get("device").cloned();
    let mut default = SimulationConfig::recommended();
    if let Some(d) = description {
        default.tuner = default_tuner(Some(d), user.get("tuner"))?;
        default.name = "described device".into();
    }
    let mut merged = serde_json::to_value(default)
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

/// The tuner a user's `tuner` keys merge into: the recommended one
/// ([`SimulationConfig::recommended`]), or the one a device `description`
/// derives ([`DeviceDescription::tuner`]; errors named `description.…`).
/// Next to a description, `tuner.gates` and `tuner.levels` are refused (one
/// source of levels). Used by [`resolve_simulation`] and by Python's tuner
/// configs.
///
/// ```
/// use spintune::description::DeviceDescription;
/// use spintune::run_config::default_tuner;
/// let d = serde_json::to_value(DeviceDescription::paper_device()).unwrap();
/// let t = default_tuner(Some(d.clone()), None).unwrap();
/// assert_eq!(t.levels.len(), 3);
/// let user_tuner = serde_json::json!({"levels": []});
/// assert_eq!(default_tuner(Some(d), Some(&user_tuner)).unwrap_err().field, "tuner.levels");
/// ```
pub fn default_tuner(
    description: Option<Value>,
    user_tuner: Option<&Value>,
) -> Result<crate::tuner::TunerConfig, ConfigError> {
    let Some(d) = description else {
        return Ok(SimulationConfig::recommended().tuner);
    };
    crate::tuner::check_magnitudes(&d, "description")?;
    for key in ["gates", "levels"] {
        if user_tuner.and_then(|t| t.get(key)).is_some() {
            return Err(ConfigError::new(
                format!("tuner.{key}"),
                "`description` derives the gates and levels: give either `description` or `tuner.gates`/`tuner.levels`",
            ));
        }
    }
    let d: DeviceDescription = serde_path_to_error::deserialize(d).map_err(|e| {
        let path = e.path().to_string();
        let field = if path == "." { String::new() } else { path };
        ConfigError::new(field, e.inner().to_string()).within("description")
    })?;
    d.tuner().map_err(|e| e.within("description"))
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
    let Some(device) = user else {
        return Ok(());
    };
    let mut device = device.clone();
    visit_device_gates(&mut device, &mut |name, field| {
        if gates.iter().any(|g| g.name == name) {
            return Ok(true);
        }
        let names: Vec<&str> = gates.iter().map(|g| g.name.as_str()).collect();
        Err(ConfigError::new(
            field,
            format!("{name:?} is not a gate of `tuner.gates` (known: {names:?})"),
        ))
    })
}

/// A resolved config as a document (`serde_json` of a
/// [`SimulationConfig`]) without the `device` entries for gates the run does
/// not have (per-gate map keys and quadratic terms; the simulator computes
/// only with the run's gates, so they have no effect): the document reads
/// back through [`resolve_simulation`], which refuses a gate of the user's
/// `device` table that is not in `tuner.gates`.
///
/// ```
/// use spintune::run_config::{prune_device_gates, resolve_simulation};
/// let user = serde_json::json!({"tuner": {"gates": [
///     {"name": "N", "min_mv": -900, "max_mv": -500, "initial_mv": -700},
/// ]}});
/// // (the default levels name other gates: only the document is shown here)
/// let mut doc = serde_json::to_value(spintune::driver::SimulationConfig::paper_default()).unwrap();
/// doc["tuner"]["gates"] = user["tuner"]["gates"].clone();
/// prune_device_gates(&mut doc);
/// assert!(doc["device"]["reference_mv"].get("N").is_some());
/// assert!(doc["device"]["reference_mv"].get("SA").is_none());
/// ```
pub fn prune_device_gates(doc: &mut Value) {
    let gates: Vec<String> = doc
        .pointer("/tuner/gates")
        .and_then(Value::as_array)
        .map(|a| {
            a.iter()
                .filter_map(|g| Some(g.get("name")?.as_str()?.to_string()))
                .collect()
        })
        .unwrap_or_default();
    if let Some(device) = doc.get_mut("device") {
        let _ = visit_device_gates(device, &mut |name, _| Ok(gates.iter().any(|g| g == name)));
    }
}

/// Visit every gate a `device` table names (per-gate map keys, both ends
/// of quadratic terms; `sensing_dot.gate` is checked but never removed):
/// `keep(gate, field)` says whether the entry stays, or fails.
fn visit_device_gates(
    device: &mut Value,
    keep: &mut dyn FnMut(&str, String) -> Result<bool, ConfigError>,
) -> Result<(), ConfigError> {
    let Value::Object(device) = device else {
        return Ok(());
    };
    let maps = [
        ("reference_mv", None),
        ("tunnel_coupling_uev", Some("linear_per_mv")),
        ("lead_rate_per_ns", Some("linear_per_mv")),
        ("crosstalk", Some("line_a_per_mv")),
        ("crosstalk", Some("line_b_per_mv")),
        ("sensing_dot", Some("lever_per_mv")),
    ];
    for (outer, inner) in maps {
        let field = match inner {
            Some(i) => format!("device.{outer}.{i}"),
            None => format!("device.{outer}"),
        };
        let map = match inner {
            Some(i) => device.get_mut(outer).and_then(|o| o.get_mut(i)),
            None => device.get_mut(outer),
        };
        if let Some(Value::Object(m)) = map {
            let mut kept = Map::new();
            for (k, v) in std::mem::take(m) {
                if keep(&k, format!("{field}.{k}"))? {
                    kept.insert(k, v);
                }
            }
            *m = kept;
        }
    }
    let terms = [
        ("tunnel_coupling_uev", "quadratic_per_mv2"),
        ("lead_rate_per_ns", "quadratic_per_mv2"),
        ("crosstalk", "line_a_quadratic"),
        ("crosstalk", "line_b_quadratic"),
    ];
    for (outer, inner) in terms {
        if let Some(Value::Array(a)) = device.get_mut(outer).and_then(|o| o.get_mut(inner)) {
            let mut kept = Vec::new();
            for (i, t) in std::mem::take(a).into_iter().enumerate() {
                let mut ok = true;
                for end in ["a", "b"] {
                    if let Some(Value::String(g)) = t.get(end) {
                        ok &= keep(g, format!("device.{outer}.{inner}[{i}].{end}"))?;
                    }
                }
                if ok {
                    kept.push(t);
                }
            }
            *a = kept;
        }
    }
    if let Some(Value::String(g)) = device.get("sensing_dot").and_then(|s| s.get("gate")) {
        keep(g, "device.sensing_dot.gate".into())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resolve(v: serde_json::Value) -> Result<SimulationConfig, ConfigError> {
        resolve_simulation(
            v.as_object().unwrap().clone(),
            &BTreeMap::new(),
            &BTreeMap::new(),
        )
    }

    #[test]
    fn a_description_replaces_the_levels_and_tuner_keys_merge_over_it() {
        let d = serde_json::to_value(DeviceDescription::paper_device()).unwrap();
        let sim = resolve(serde_json::json!({
            "description": d,
            "tuner": {"max_iterations": 7},
        }))
        .unwrap();
        assert_eq!(sim.tuner.max_iterations, Some(7));
        assert_eq!(
            sim.tuner.levels,
            DeviceDescription::paper_device().tuner().unwrap().levels
        );
        let e = resolve(serde_json::json!({
            "description": serde_json::to_value(DeviceDescription::paper_device()).unwrap(),
            "tuner": {"gates": []},
        }))
        .unwrap_err();
        assert_eq!(e.field, "tuner.gates");
        let e = resolve(serde_json::json!({"description": {"gates": []}})).unwrap_err();
        assert_eq!(e.field, "description");
        assert!(e.message.contains("qubit"), "{e}");
    }
}
