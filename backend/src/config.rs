//! Run configuration: the file of `spintune run --config FILE.toml` and the JSON
//! body of `POST /api/runs`.
//!
//! A run config is a [`SimulationConfig`] (`name`, `seed`, `device`, `tuner`)
//! plus a few backend-only settings. Every key is optional: what is not given
//! comes from [`SimulationConfig::recommended`]. Tables are merged key by key
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
//! | `iteration_delay_ms` | integer, ms, at most `SessionConfig::MAX_ITERATION_DELAY_MS` (3,600,000: one hour) | wall-clock pause after each iteration (overrides the server's `--iteration-delay-ms`) |
//! | `moved_tolerance_mv` | number, mV, 0–100 (default 1) | largest distance of a gate's read-back from where the run left it; farther is a `moved` fault that waits for `accept_positions` |
//!
//! Gate names in the `device` table (keys of `reference_mv`, `*_per_mv`
//! maps, quadratic terms' `a`/`b`, `sensing_dot.gate`) must be gates of
//! `tuner.gates`. A JSON config is exactly one JSON value (nothing may
//! follow it but whitespace).
//!
//! Errors name the offending field, e.g. ``invalid config at `tuner.levels[0].kind`: …``.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use spintune::driver::array::ArraySimulationConfig;
use spintune::driver::SimulationConfig;
use spintune::parameter::Tolerance;
use spintune::run_config::resolve_simulation;
use spintune::session::SessionConfig;
use spintune::ConfigError;

pub use crate::devices::bridge::BridgeConfig;
pub use crate::devices::scpi::{MeasureSource, ScpiConfig, ScpiProfile};
pub use crate::devices::DriverKind;

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
    /// An array of double dots tuned jointly (the `array` table: on the
    /// simulator, or through the lab bridge with `array.description`): when
    /// set, the run is this array, not `simulation`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub array: Option<ArraySimulationConfig>,
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
    /// The default run (default device, the recommended tuner
    /// [`SimulationConfig::recommended`], seed and name): what an empty
    /// config file gives.
    pub fn recommended() -> Self {
        Self {
            simulation: SimulationConfig::recommended(),
            backend: BackendSettings::default(),
            array: None,
        }
    }

    /// Parse a TOML document.
    pub fn from_toml_str(text: &str) -> Result<Self, ConfigParseError> {
        let value: Value = toml::from_str(text)
            .map_err(|e| ConfigParseError(format!("invalid TOML: {}", e.to_string().trim())))?;
        Self::from_value(value)
    }

    /// Parse a JSON document (the body of `POST /api/runs`): exactly one
    /// JSON value, nothing after it but whitespace
    /// ([`spintune::strict_json::parse_value`]).
    pub fn from_json_str(text: &str) -> Result<Self, ConfigParseError> {
        let value = spintune::strict_json::parse_value(text).map_err(|e| {
            let e = e.to_string();
            let e = e.strip_prefix("malformed message").unwrap_or(&e);
            ConfigParseError(format!("invalid JSON{e}"))
        })?;
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
        validate_delay(&backend)?;
        if let Some(mv) = backend.moved_tolerance_mv {
            spintune::session::SessionConfig {
                moved_tolerance_mv: mv,
                ..Default::default()
            }
            .validate()?;
        }
        let array = user
            .remove("array")
            .map(|v| parse_array(v, &backend))
            .transpose()?;
        // The core's one merge and validation of the simulation part.
        let simulation = resolve_simulation(user, &backend.targets, &backend.tolerances)?;
        validate_drivers(&simulation, &backend)?;
        Ok(Self {
            simulation,
            backend,
            array,
        })
    }

    /// The config as one flat document, the layout of a config file
    /// (simulation keys and backend keys side by side, unset options left
    /// out, `device` entries of gates the run does not have left out:
    /// [`spintune::run_config::prune_device_gates`]): parsed back with [`RunConfig::from_value`] it gives this
    /// config again.
    pub fn to_document(&self) -> Value {
        fn drop_nulls(v: &mut Value) {
            match v {
                Value::Object(m) => {
                    m.retain(|_, x| !x.is_null());
                    m.values_mut().for_each(drop_nulls);
                }
                Value::Array(a) => a.iter_mut().for_each(drop_nulls),
                _ => {}
            }
        }
        let mut doc = serde_json::to_value(&self.simulation).unwrap_or_default();
        spintune::run_config::prune_device_gates(&mut doc);
        if let (Value::Object(d), Ok(Value::Object(b))) =
            (&mut doc, serde_json::to_value(&self.backend))
        {
            d.extend(b);
        }
        if let (Value::Object(d), Some(Ok(mut a))) =
            (&mut doc, self.array.as_ref().map(serde_json::to_value))
        {
            if self.backend.driver == DriverKind::Bridge {
                // A lab's array (its description) has no simulated world:
                // `array.array` and `array.device` would be printed unused.
                if let Value::Object(a) = &mut a {
                    a.remove("array");
                    a.remove("device");
                }
            }
            d.insert("array".into(), a);
        }
        drop_nulls(&mut doc);
        doc
    }

    /// [`RunConfig::to_document`] as TOML (what `spintune config resolve` prints).
    pub fn to_toml(&self) -> Result<String, ConfigParseError> {
        toml::to_string_pretty(&self.to_document())
            .map_err(|e| ConfigParseError(format!("cannot write the config as TOML: {e}")))
    }

    /// Every gate the run may touch, with its limits: the array's
    /// (prefixed `c{k}.`) or the single double dot's. Valid by construction
    /// (checked when the config was parsed).
    pub fn gates(&self) -> Vec<spintune::safety::GateSpec> {
        match &self.array {
            Some(a) => a.gates().unwrap_or_default(),
            None => self.simulation.tuner.gates.clone(),
        }
    }

    /// Run name.
    pub fn name(&self) -> &str {
        match &self.array {
            Some(a) => &a.name,
            None => &self.simulation.name,
        }
    }
}

/// Largest magnitude of any non-integer number in a run config, in the
/// field's unit (mV, ns, s, µeV, …): the core's bound
/// ([`spintune::tuner::check_magnitudes`]), checked on the whole
/// run config before it is parsed (ARCHITECTURE.md, invariant 8).
pub use spintune::tuner::MAX_MAGNITUDE as MAX_CONFIG_MAGNITUDE;

/// Largest integer in a run config, except `seed` (the core's bound).
pub use spintune::tuner::MAX_INTEGER as MAX_CONFIG_INTEGER;

/// `iteration_delay_ms` within its documented bound
/// ([`SessionConfig::MAX_ITERATION_DELAY_MS`]): refused, never clamped.
fn validate_delay(b: &BackendSettings) -> Result<(), ConfigParseError> {
    let Some(ms) = b.iteration_delay_ms else {
        return Ok(());
    };
    let session = SessionConfig {
        iteration_delay_ms: ms,
        ..SessionConfig::default()
    };
    session.validate().map_err(|e| {
        ConfigParseError(format!(
            "invalid config at `iteration_delay_ms`: {ms} ms: {}",
            e.message
        ))
    })
}

/// The `array` table: an [`ArraySimulationConfig`] merged key by key into
/// its default (errors name the field under `array.`), on the simulator
/// or (with its `description`) through the lab bridge, with its own targets.
fn parse_array(
    value: Value,
    b: &BackendSettings,
) -> Result<ArraySimulationConfig, ConfigParseError> {
    // merged key by key into the default, like every table of a run config
    let mut merged = serde_json::to_value(ArraySimulationConfig::default())
        .map_err(|e| ConfigParseError(format!("internal: {e}")))?;
    spintune::config_merge::merge(&mut merged, value);
    let array: ArraySimulationConfig = serde_path_to_error::deserialize(merged).map_err(|e| {
        ConfigParseError(format!(
            "invalid config at `array.{}`: {}",
            e.path(),
            e.inner()
        ))
    })?;
    match b.driver {
        DriverKind::Simulator => {}
        DriverKind::Bridge if array.description.is_some() => {}
        DriverKind::Bridge => {
            return Err(ConfigParseError(
                "invalid config at `array.description`: an array on the lab bridge needs its description (cells, their gates with limits, readout groups; docs/array.md)".into(),
            ))
        }
        DriverKind::Scpi => {
            return Err(ConfigParseError(
                "invalid config at `driver`: an array runs on the simulator or through the lab bridge (driver = \"simulator\" or \"bridge\"), not on a SCPI source".into(),
            ))
        }
    }
    if !b.targets.is_empty() || !b.tolerances.is_empty() {
        return Err(ConfigParseError(
            "invalid config at `targets`: an array run's targets are `array.targets` (one [t_sr ns, w µV] pair for every cell, or one per cell)".into(),
        ));
    }
    // every bound, and on the simulator that the world can be drawn
    array.build_plan().map_err(|e| e.within("array"))?;
    if b.driver == DriverKind::Simulator {
        array.build_world().map_err(|e| e.within("array"))?;
    }
    Ok(array)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_toml_is_the_recommended_default() {
        let c = RunConfig::from_toml_str("").unwrap();
        assert_eq!(
            serde_json::to_value(&c.simulation).unwrap(),
            serde_json::to_value(SimulationConfig::recommended()).unwrap()
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
    fn targets_over_a_missing_or_sensing_top_level_are_refused_not_a_panic() {
        // Issue 20 item 7: `top_mut()` on empty levels indexed out of bounds.
        for (text, field) in [
            (
                r#"{"targets":{"t_sr":20},"tuner":{"levels":[]}}"#,
                "`tuner.levels`",
            ),
            (
                r#"{"tolerances":{"w":{"absolute":1}},"tuner":{"levels":[]}}"#,
                "`tuner.levels`",
            ),
            (
                r#"{"targets":{"t_sr":20},"tuner":{"levels":[{"name":"sd","kind":"sensing_dot","gate":"SP","half_width_mv":10,"points":20}]}}"#,
                "`tuner.levels[0].kind`",
            ),
        ] {
            let e = RunConfig::from_json_str(text).unwrap_err();
            assert!(e.0.contains(field), "{text}: {e}");
        }
        let e = RunConfig::from_json_str(r#"{"tuner":{"levels":[]}}"#).unwrap_err();
        assert!(e.0.contains("`tuner.levels`"), "{e}");
    }

    #[test]
    fn the_iteration_delay_is_bounded_not_clamped() {
        let max = SessionConfig::MAX_ITERATION_DELAY_MS;
        let c = RunConfig::from_json_str(&format!(r#"{{"iteration_delay_ms":{max}}}"#)).unwrap();
        assert_eq!(c.backend.iteration_delay_ms, Some(max));
        for ms in [max + 1, 1 << 40] {
            let e =
                RunConfig::from_json_str(&format!(r#"{{"iteration_delay_ms":{ms}}}"#)).unwrap_err();
            assert!(e.0.contains("`iteration_delay_ms`"), "{e}");
            assert!(e.0.contains(&max.to_string()), "{e}");
        }
    }

    #[test]
    fn unknown_gates_in_the_device_table_are_refused_naming_the_field() {
        for (text, field) in [
            (
                r#"{"device":{"reference_mv":{"NOPE":1}}}"#,
                "device.reference_mv.NOPE",
            ),
            (
                r#"{"device":{"tunnel_coupling_uev":{"linear_per_mv":{"X":0.1}}}}"#,
                "device.tunnel_coupling_uev.linear_per_mv.X",
            ),
            (
                r#"{"device":{"lead_rate_per_ns":{"quadratic_per_mv2":[{"a":"N","b":"Q","coefficient_per_mv2":1e-4}]}}}"#,
                "device.lead_rate_per_ns.quadratic_per_mv2[0].b",
            ),
            (
                r#"{"device":{"crosstalk":{"line_b_per_mv":{"n":0.1}}}}"#,
                "device.crosstalk.line_b_per_mv.n",
            ),
            (
                r#"{"device":{"crosstalk":{"line_a_quadratic":[{"a":"Z","b":"N","coefficient_per_mv2":0}]}}}"#,
                "device.crosstalk.line_a_quadratic[0].a",
            ),
            (
                r#"{"device":{"sensing_dot":{"lever_per_mv":{"SPP":0.5}}}}"#,
                "device.sensing_dot.lever_per_mv.SPP",
            ),
            (
                r#"{"device":{"sensing_dot":{"gate":"SD9"}}}"#,
                "device.sensing_dot.gate",
            ),
        ] {
            let e = RunConfig::from_json_str(text).unwrap_err();
            assert!(e.0.contains(&format!("`{field}`")), "{text}: {e}");
        }
        // Known gates are fine, and a custom gate set may leave default gates out.
        RunConfig::from_json_str(r#"{"device":{"crosstalk":{"line_b_per_mv":{"N":0.1}}}}"#)
            .unwrap();
    }

    #[test]
    fn a_json_config_is_one_value() {
        for text in [r#"{}{}"#, r#"{"seed":3} x"#, r#"{"seed":3}]"#] {
            let e = RunConfig::from_json_str(text).unwrap_err();
            assert!(e.0.contains("trailing characters"), "{text}: {e}");
        }
        assert_eq!(
            RunConfig::from_json_str(" {\"seed\":3}\n")
                .unwrap()
                .simulation
                .seed,
            3
        );
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
