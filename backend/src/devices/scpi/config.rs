//! The `[scpi]` table of a run config: the instrument's address and channel
//! map, ramp, read-back, timeout and leakage settings, their bounds, and
//! their validation against the run's gates (errors name the field).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use spintune::safety::GateSpec;
use spintune::ConfigError;

/// Where a SCPI run's measurements come from (the DC source only sets gates).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeasureSource {
    /// The embedded simulator, fed the voltages read back from the
    /// instrument (dry runs against a real or fake source).
    #[default]
    Simulator,
    /// The lab bridge (`/api/runs/{id}/bridge`): the lab's script measures,
    /// spintune sets the DC gates itself.
    Bridge,
}

/// The instrument dialect of a SCPI source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScpiProfile {
    /// `sour{ch}:volt` / `sour{ch}:volt?` only.
    #[default]
    Generic,
    /// QDevil QDAC-II: fixed mode on connect, `volt:last?` read-back, and the
    /// optional leakage check (`read{ch}?`).
    Qdac2,
}

/// `[scpi]` table of a run config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScpiConfig {
    /// `host:port` of the instrument's raw SCPI socket, e.g. `"192.168.8.40:5025"`.
    pub address: String,
    /// Gate name → channel number (1-based), e.g. `{ SB = 4 }`.
    pub channels: BTreeMap<String, u32>,
    /// Largest change of any channel in one `sour{ch}:volt` command, mV.
    #[serde(default = "default_ramp_step_mv")]
    pub ramp_step_mv: f64,
    /// Instrument ramp rate sent as `sour{ch}:volt:slew` at connect, V/s.
    /// When set, the driver also waits `increment / slew` after each increment.
    #[serde(default)]
    pub slew_v_per_s: Option<f64>,
    /// Largest accepted difference between target and read-back, mV.
    #[serde(default = "default_readback_tolerance_mv")]
    pub readback_tolerance_mv: f64,
    /// Time allowed for connecting, each write and each answer, ms.
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: u64,
    /// Wait after the last increment before reading back, ms.
    #[serde(default)]
    pub settle_ms: u64,
    /// Source of measurements.
    #[serde(default)]
    pub measure: MeasureSource,
    /// Instrument dialect (default `generic`).
    #[serde(default)]
    pub profile: ScpiProfile,
    /// QDAC-II only: after every move, the current each moved channel
    /// sources must not exceed this, nA; above it the run pauses as a device
    /// fault (a gate leaking into the 2DEG). `None`: no check.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_leakage_na: Option<f64>,
    /// QDAC-II only: per-gate leakage limits, nA, overriding
    /// `max_leakage_na` for the gates named (e.g. a plunger gate that is
    /// allowed less). A gate named here is checked even without
    /// `max_leakage_na`. Every key must be a mapped gate.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub max_leakage_na_by_gate: BTreeMap<String, f64>,
}

/// Most `sour{ch}:volt` commands one move may take (bounds the planned ramp).
pub const MAX_RAMP_STAGES: usize = 1_000;
/// Largest `ramp_step_mv`, mV.
pub const MAX_RAMP_STEP_MV: f64 = 1_000.0;
/// Largest `slew_v_per_s`, V/s.
pub const MAX_SLEW_V_PER_S: f64 = 1_000.0;
/// Largest `readback_tolerance_mv` (SCPI and bridge), mV.
pub const MAX_READBACK_TOLERANCE_MV: f64 =
    spintune::session::SessionConfig::MAX_READBACK_TOLERANCE_MV;
/// Largest `timeout_ms` and `settle_ms`, ms (10 minutes).
pub const MAX_TIMEOUT_MS: u64 = 600_000;
/// Largest `max_leakage_na`, nA (10 mA, the QDAC-II's high current range).
pub const MAX_LEAKAGE_NA: f64 = 1e7;

pub(super) fn default_ramp_step_mv() -> f64 {
    1.0
}
pub(super) fn default_readback_tolerance_mv() -> f64 {
    0.05
}
pub(super) fn default_timeout_ms() -> u64 {
    2000
}

impl ScpiConfig {
    /// The leakage limit of `gate`, nA, with the config key it comes from
    /// (`max_leakage_na_by_gate.SB` before `max_leakage_na`); `None`: the
    /// gate's current is not checked.
    pub fn leakage_limit_na(&self, gate: &str) -> Option<(String, f64)> {
        match self.max_leakage_na_by_gate.get(gate) {
            Some(&na) => Some((format!("max_leakage_na_by_gate.{gate}"), na)),
            None => self
                .max_leakage_na
                .map(|na| ("max_leakage_na".to_string(), na)),
        }
    }

    /// Check the settings against the tuner's gates. The error's field is
    /// relative to the `[scpi]` table (`channels.SB`); a run config prefixes
    /// it with `scpi`.
    pub fn validate(&self, gates: &[GateSpec]) -> Result<(), ConfigError> {
        if self.address.trim().is_empty() || !self.address.contains(':') {
            return Err(ConfigError::new(
                "address",
                format!("expected \"host:port\", got {:?}", self.address),
            ));
        }
        if self.channels.is_empty() {
            return Err(ConfigError::new(
                "channels",
                "map at least one gate to a channel",
            ));
        }
        let mut seen = BTreeMap::new();
        for (gate, &ch) in &self.channels {
            let field = format!("channels.{gate}");
            if !gates.iter().any(|g| &g.name == gate) {
                let known: Vec<&str> = gates.iter().map(|g| g.name.as_str()).collect();
                return Err(ConfigError::new(
                    field,
                    format!("{gate:?} is not a gate of `tuner.gates` (known: {known:?})"),
                ));
            }
            if ch == 0 {
                return Err(ConfigError::new(field, "channel numbers start at 1"));
            }
            if let Some(other) = seen.insert(ch, gate) {
                return Err(ConfigError::new(
                    field,
                    format!("channel {ch} is already used by {other:?}"),
                ));
            }
        }
        if !(self.ramp_step_mv.is_finite()
            && self.ramp_step_mv > 0.0
            && self.ramp_step_mv <= MAX_RAMP_STEP_MV)
        {
            return Err(ConfigError::new(
                "ramp_step_mv",
                format!(
                    "must be a positive number of mV, at most {MAX_RAMP_STEP_MV}, got {}",
                    self.ramp_step_mv
                ),
            ));
        }
        // Bounded by construction: one move ramps in at most MAX_RAMP_STAGES commands.
        let largest_step_mv = gates
            .iter()
            .filter(|g| self.channels.contains_key(&g.name))
            .map(|g| g.max_step_mv)
            .fold(0.0, f64::max);
        if largest_step_mv / self.ramp_step_mv > MAX_RAMP_STAGES as f64 {
            return Err(ConfigError::new(
                "ramp_step_mv",
                format!(
                    "{} mV would ramp a {largest_step_mv} mV step in more than {MAX_RAMP_STAGES} commands; use at least {} mV",
                    self.ramp_step_mv,
                    largest_step_mv / MAX_RAMP_STAGES as f64
                ),
            ));
        }
        if let Some(s) = self.slew_v_per_s {
            if !(s.is_finite() && s > 0.0 && s <= MAX_SLEW_V_PER_S) {
                return Err(ConfigError::new(
                    "slew_v_per_s",
                    format!(
                        "must be a positive number of V/s, at most {MAX_SLEW_V_PER_S}, got {s}"
                    ),
                ));
            }
        }
        if !(self.readback_tolerance_mv.is_finite()
            && self.readback_tolerance_mv >= 0.0
            && self.readback_tolerance_mv <= MAX_READBACK_TOLERANCE_MV)
        {
            return Err(ConfigError::new(
                "readback_tolerance_mv",
                format!(
                    "must be a non-negative number of mV, at most {MAX_READBACK_TOLERANCE_MV}, got {}",
                    self.readback_tolerance_mv
                ),
            ));
        }
        if !(1..=MAX_TIMEOUT_MS).contains(&self.timeout_ms) {
            return Err(ConfigError::new(
                "timeout_ms",
                format!("must be 1 to {MAX_TIMEOUT_MS} ms, got {}", self.timeout_ms),
            ));
        }
        let limits = self
            .max_leakage_na
            .map(|na| ("max_leakage_na".to_string(), na))
            .into_iter()
            .chain(
                self.max_leakage_na_by_gate
                    .iter()
                    .map(|(g, &na)| (format!("max_leakage_na_by_gate.{g}"), na)),
            );
        for (field, na) in limits {
            if self.profile != ScpiProfile::Qdac2 {
                return Err(ConfigError::new(
                    field,
                    "the leakage check reads the current with the QDAC-II's `read{ch}?`: set profile = \"qdac2\"",
                ));
            }
            if !(na.is_finite() && na > 0.0 && na <= MAX_LEAKAGE_NA) {
                return Err(ConfigError::new(
                    field,
                    format!("must be a positive number of nA, at most {MAX_LEAKAGE_NA}, got {na}"),
                ));
            }
        }
        for gate in self.max_leakage_na_by_gate.keys() {
            if !self.channels.contains_key(gate) {
                let mapped: Vec<&str> = self.channels.keys().map(String::as_str).collect();
                return Err(ConfigError::new(
                    format!("max_leakage_na_by_gate.{gate}"),
                    format!("{gate:?} is not a gate of `channels` (mapped: {mapped:?})"),
                ));
            }
        }
        if self.settle_ms > MAX_TIMEOUT_MS {
            return Err(ConfigError::new(
                "settle_ms",
                format!(
                    "must be at most {MAX_TIMEOUT_MS} ms, got {}",
                    self.settle_ms
                ),
            ));
        }
        Ok(())
    }
}
