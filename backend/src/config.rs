//! Run configuration: the file of `spintune run --config FILE.toml` and the JSON
//! body of `POST /api/runs`.
//!
//! A run config is a [`SimulationConfig`] (`name`, `seed`, `device`, `tuner`)
//! plus a few backend-only settings. Every key is optional: what is not given
//! comes from [`SimulationConfig::paper_default`]. Tables are merged key by key
//! into the default (so `[device]` may set one field only); arrays replace the
//! default array as a whole; a table whose tag (`kind`, `type`, …) differs from
//! the default's replaces it as a whole (it is another enum variant).
//!
//! Backend-only keys (top level):
//!
//! | key | type | meaning |
//! |---|---|---|
//! | `driver` | `"simulator"` \| `"scpi"` \| `"bridge"` | device driver (default `simulator`; see `docs/instruments.md`) |
//! | `scpi` | table, [`ScpiConfig`] | SCPI DC source: `address`, `channels`, ramp/read-back/timeout settings; required for `driver = "scpi"` |
//! | `bridge` | table, [`BridgeConfig`] | lab bridge: `request_timeout_s`, `readback_tolerance_mv` |
//! | `targets` | table parameter → number | targets of the top tuner level's parameters, in the parameter's unit (e.g. `t_sr` in ns, `w` in µV) |
//! | `tolerances` | table parameter → `{ absolute = x }` or `{ relative = f }` | tolerance bands of the top level's parameters |
//! | `iteration_delay_ms` | integer, ms | wall-clock pause after each iteration (overrides the server's `--iteration-delay-ms`) |
//! | `moved_tolerance_mv` | number, mV, 0–100 (default 1) | largest distance of a gate's read-back from where the run left it; farther is a `moved` fault that waits for `accept_positions` |
//!
//! Errors name the offending field, e.g. ``invalid config at `tuner.levels[0].kind`: …``.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use spintune::config_merge::merge;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
use spintune::ConfigError;

pub use crate::devices::bridge::BridgeConfig;
pub use crate::devices::scpi::{MeasureSource, ScpiConfig, ScpiProfile};

/// Which device a run drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DriverKind {
    /// The embedded simulated double dot (`spintune::sim`).
    #[default]
    Simulator,
    /// A SCPI DC voltage source over raw TCP sets the gates
    /// ([`crate::devices::scpi`]); measurements come from `scpi.measure`.
    Scpi,
    /// An external lab script connected over WebSocket sets gates and
    /// measures ([`crate::devices::bridge`]).
    Bridge,
}

/// Backend-only settings of a run (everything that is not a [`SimulationConfig`] field).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackendSettings {
    /// Device driver.
    #[serde(default)]
    pub driver: DriverKind,
    /// Targets of the top level's parameters (parameter units), applied over the tuner config.
    #[serde(default)]
    pub targets: BTreeMap<String, f64>,
    /// Tolerances of the top level's parameters, applied over the tuner config.
    #[serde(default)]
    pub tolerances: BTreeMap<String, Tolerance>,
    /// Wall-clock pause after each iteration, ms (`None`: the server's default).
    #[serde(default)]
    pub iteration_delay_ms: Option<u64>,
    /// Largest distance of a gate's read-back from where the run left it,
    /// mV (`None`: [`spintune::session::SessionConfig`]'s default, 1 mV).
    #[serde(default)]
    pub moved_tolerance_mv: Option<f64>,
    /// SCPI DC source settings (required for `driver = "scpi"`).
    #[serde(default)]
    pub scpi: Option<ScpiConfig>,
    /// Lab bridge settings (used by `driver = "bridge"` and `scpi.measure = "bridge"`).
    #[serde(default)]
    pub bridge: BridgeConfig,
}

impl BackendSettings {
    /// Whether the run's device includes the lab bridge.
    pub fn uses_bridge(&self) -> bool {
        match self.driver {
            DriverKind::Bridge => true,
            DriverKind::Scpi => self
                .scpi
                .as_ref()
                .is_some_and(|s| s.measure == MeasureSource::Bridge),
            DriverKind::Simulator => false,
        }
    }
}

const BACKEND_KEYS: [&str; 7] = [
    "driver",
    "targets",
    "tolerances",
    "iteration_delay_ms",
    "moved_tolerance_mv",
    "scpi",
    "bridge",
];

/// A complete, validated run configuration.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunConfig {
    /// The core's configuration (device model, tuner, seed, name), targets applied.
    pub simulation: SimulationConfig,
    /// Backend-only settings.
    pub backend: BackendSettings,
}

/// Why a config was rejected. The message names the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct ConfigParseError(pub String);

impl From<ConfigError> for ConfigParseError {
    fn from(e: ConfigError) -> Self {
        Self(e.to_string())
    }
}

impl RunConfig {
    /// The paper's default run (default device, default tuner, seed and name).
    pub fn paper_default() -> Self {
        Self {
            simulation: SimulationConfig::paper_default(),
            backend: BackendSettings::default(),
        }
    }

    /// Parse a TOML document.
    pub fn from_toml_str(text: &str) -> Result<Self, ConfigParseError> {
        let value: Value = toml::from_str(text)
            .map_err(|e| ConfigParseError(format!("invalid TOML: {}", e.to_string().trim())))?;
        Self::from_value(value)
    }

    /// Parse a JSON document (the body of `POST /api/runs`).
    pub fn from_json_str(text: &str) -> Result<Self, ConfigParseError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let value: Value = serde_path_to_error::deserialize(de)
            .map_err(|e| ConfigParseError(format!("invalid JSON: {}", e.inner())))?;
        Self::from_value(value)
    }

    /// Build from a generic value (a table/object at the top).
    pub fn from_value(value: Value) -> Result<Self, ConfigParseError> {
        spintune::tuner::check_magnitudes(&value, "")?;
        let Value::Object(mut user) = value else {
            return Err(ConfigParseError(
                "invalid config: expected a table/object at the top level".into(),
            ));
        };
        let mut backend_map = Map::new();
        for key in BACKEND_KEYS {
            if let Some(v) = user.remove(key) {
                backend_map.insert(key.to_string(), v);
            }
        }
        let backend: BackendSettings = serde_path_to_error::deserialize(Value::Object(backend_map))
            .map_err(|e| {
                ConfigParseError(format!("invalid config at `{}`: {}", e.path(), e.inner()))
            })?;
        let mut merged = serde_json::to_value(SimulationConfig::paper_default())
            .map_err(|e| ConfigParseError(format!("internal: default config: {e}")))?;
        merge(&mut merged, Value::Object(user));
        let mut simulation: SimulationConfig =
            serde_path_to_error::deserialize(merged).map_err(|e| {
                let path = e.path().to_string();
                let inner = e.inner().to_string();
                if path == "." {
                    ConfigParseError(format!("invalid config: {inner}"))
                } else {
                    ConfigParseError(format!("invalid config at `{path}`: {inner}"))
                }
            })?;
        if let Some(mv) = backend.moved_tolerance_mv {
            spintune::session::SessionConfig {
                moved_tolerance_mv: mv,
                ..Default::default()
            }
            .validate()?;
        }
        apply_targets(&mut simulation, &backend)?;
        simulation.validate()?;
        validate_drivers(&simulation, &backend)?;
        Ok(Self {
            simulation,
            backend,
        })
    }

    /// Run name.
    pub fn name(&self) -> &str {
        &self.simulation.name
    }
}

/// Largest magnitude of any non-integer number in a run config, in the
/// field's unit (mV, ns, s, µeV, …): the core's bound
/// ([`spintune::tuner::check_magnitudes`]), checked on the whole
/// run config before it is parsed (ARCHITECTURE.md, invariant 8).
pub use spintune::tuner::MAX_MAGNITUDE as MAX_CONFIG_MAGNITUDE;

/// Largest integer in a run config, except `seed` (the core's bound).
pub use spintune::tuner::MAX_INTEGER as MAX_CONFIG_INTEGER;

fn apply_targets(sim: &mut SimulationConfig, b: &BackendSettings) -> Result<(), ConfigParseError> {
    if b.targets.is_empty() && b.tolerances.is_empty() {
        return Ok(());
    }
    let top = sim.tuner.top_mut();
    let known: Vec<String> = top.parameters.iter().map(|p| p.name.clone()).collect();
    for (name, &target) in &b.targets {
        if !target.is_finite() {
            return Err(ConfigParseError(format!(
                "invalid config at `targets.{name}`: must be a finite number"
            )));
        }
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown_parameter("targets", name, &known))?;
        p.target = Some(target);
    }
    for (name, &tol) in &b.tolerances {
        tol.validate()
            .map_err(|e| e.within(&format!("tolerances.{name}")))?;
        let p = top
            .parameters
            .iter_mut()
            .find(|p| &p.name == name)
            .ok_or_else(|| unknown_parameter("tolerances", name, &known))?;
        p.tolerance = tol;
    }
    Ok(())
}

fn validate_drivers(sim: &SimulationConfig, b: &BackendSettings) -> Result<(), ConfigParseError> {
    match (&b.driver, &b.scpi) {
        (DriverKind::Scpi, None) => {
            return Err(ConfigParseError(
                "invalid config at `scpi`: driver = \"scpi\" needs a [scpi] table with `address` and `channels`".into(),
            ))
        }
        (_, Some(scpi)) => scpi
            .validate(&sim.tuner.gates)
            .map_err(|e| e.within("scpi"))?,
        _ => {}
    }
    Ok(b.bridge.validate().map_err(|e| e.within("bridge"))?)
}

fn unknown_parameter(section: &str, name: &str, known: &[String]) -> ConfigParseError {
    ConfigParseError(format!(
        "invalid config at `{section}.{name}`: the top tuner level has no parameter {name:?} (it has {known:?})"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_toml_is_paper_default() {
        let c = RunConfig::from_toml_str("").unwrap();
        assert_eq!(
            serde_json::to_value(&c.simulation).unwrap(),
            serde_json::to_value(SimulationConfig::paper_default()).unwrap()
        );
    }

    #[test]
    fn partial_override_and_targets() {
        let c = RunConfig::from_toml_str(
            "name = \"x\"\nseed = 7\n[targets]\nt_sr = 70.0\n[tolerances]\nw = { absolute = 5.0 }\n",
        )
        .unwrap();
        assert_eq!(c.simulation.name, "x");
        assert_eq!(c.simulation.seed, 7);
        let top = c.simulation.tuner.top();
        let t = top.parameters.iter().find(|p| p.name == "t_sr").unwrap();
        assert_eq!(t.target, Some(70.0));
        let w = top.parameters.iter().find(|p| p.name == "w").unwrap();
        assert_eq!(w.tolerance, Tolerance::Absolute(5.0));
    }

    #[test]
    fn errors_name_the_field() {
        let e = RunConfig::from_toml_str("seed = \"abc\"").unwrap_err();
        assert!(e.0.contains("seed"), "{e}");
        let e = RunConfig::from_toml_str("bogus = 1").unwrap_err();
        assert!(e.0.contains("bogus"), "{e}");
        let e = RunConfig::from_toml_str("[targets]\nnope = 1.0").unwrap_err();
        assert!(e.0.contains("targets.nope"), "{e}");
        let e = RunConfig::from_toml_str("driver = \"gpib\"").unwrap_err();
        assert!(e.0.contains("driver"), "{e}");
        let e = RunConfig::from_toml_str("driver = \"scpi\"").unwrap_err();
        assert!(e.0.contains("`scpi`"), "{e}");
        let e = RunConfig::from_toml_str(
            "driver = \"scpi\"\n[scpi]\naddress = \"127.0.0.1:5025\"\nchannels = { NOPE = 1 }",
        )
        .unwrap_err();
        assert!(e.0.contains("scpi.channels") && e.0.contains("NOPE"), "{e}");
        let e = RunConfig::from_toml_str(
            "driver = \"scpi\"\n[scpi]\naddress = \"127.0.0.1:5025\"\nchannels = { N = 1, T = 1 }",
        )
        .unwrap_err();
        assert!(e.0.contains("scpi.channels"), "{e}");
        let e = RunConfig::from_toml_str("driver = \"bridge\"\n[bridge]\nrequest_timeout_s = -1")
            .unwrap_err();
        assert!(e.0.contains("bridge.request_timeout_s"), "{e}");
        let c = RunConfig::from_toml_str(
            "driver = \"scpi\"\n[scpi]\naddress = \"127.0.0.1:5025\"\nchannels = { N = 1, T = 2 }\nmeasure = \"bridge\"",
        )
        .unwrap();
        assert!(c.backend.uses_bridge());
        let e = RunConfig::from_json_str("{\"tuner\": {\"gates\": []}}").unwrap_err();
        assert!(e.0.contains("gates"), "{e}");
    }

    #[test]
    fn nested_validation_errors_carry_the_full_path() {
        let e = RunConfig::from_toml_str("[tolerances]\nw = { relative = -1.0 }").unwrap_err();
        assert!(e.0.contains("`tolerances.w.relative`"), "{e}");
        assert!(e.0.contains("got -1"), "{e}");
        let e = RunConfig::from_toml_str("[device]\nelectron_temperature_mk = 0.0").unwrap_err();
        assert!(e.0.contains("`device.electron_temperature_mk`"), "{e}");
        let e = RunConfig::from_toml_str(
            "driver = \"scpi\"\n[scpi]\naddress = \"127.0.0.1:5025\"\nchannels = { N = 0 }",
        )
        .unwrap_err();
        assert_eq!(
            e.0,
            "invalid config at `scpi.channels.N`: channel numbers start at 1"
        );
    }
}
