//! SCPI driver for a multi-channel DC voltage source over raw TCP
//! (QDAC-II style; one command per line, `\n`-terminated).
//!
//! The subset used (`scpi.profile`, [`ScpiProfile`]):
//!
//! | command | profile | meaning |
//! |---|---|---|
//! | `sour{ch}:volt:mode fix` | qdac2 | on connect: fixed DC mode (a channel left in list/sweep mode does not follow `sour{ch}:volt`) |
//! | `sour{ch}:volt:slew {V/s}` | both | the instrument's own ramp rate, V/s (no answer) |
//! | `sour{ch}:volt?` | generic | read channel `ch` back; answers one line, volts |
//! | `sour{ch}:volt:last?` | qdac2 | the present output of `ch`, volts (`volt?` may echo the set point) |
//! | `sour{ch}:volt {V}` | both | set channel `ch` to `V` volts (no answer) |
//! | `read{ch}?` | qdac2 with `max_leakage_na` or `max_leakage_na_by_gate` | after every move, for every moved channel: the current it sources, A (comma-separated list; the largest magnitude counts) |
//!
//! The tuner works in mV, the instrument in V: every value is divided by
//! 1000 on the way out (formatted with 6 decimals, i.e. 1 µV resolution) and
//! multiplied by 1000 on the way back.
//!
//! Safety, on top of the run session's guard (which checks every request
//! against the limits and the instrument's last read-back as the session
//! accepted it), enforced against the *driver's own* read-back state before
//! any command is sent:
//!
//! 1. every gate must be mapped to a channel and have a [`GateSpec`];
//! 2. the target must lie within the gate's `[min_mv, max_mv]`;
//! 3. the change from the voltage last read back from the instrument must not
//!    exceed the gate's `max_step_mv`;
//! 4. the move is split into equal increments no larger than
//!    [`ScpiConfig::ramp_step_mv`] (all gates of the request advance together);
//!    every planned command is checked against the limits before the first is
//!    sent;
//! 5. after the last increment every channel is read back and compared with
//!    the target ([`ScpiConfig::readback_tolerance_mv`]); a mismatch is an
//!    error (the run pauses, nothing is retried silently).
//!
//! Numbers from the instrument are believed only if they are finite and not
//! SCPI's special values (`9.91E37` is NaN, `±9.9E37` is ±infinity/overflow,
//! [`scpi_number`]); anything else drops the connection and faults.
//!
//! Any I/O error or timeout drops the connection and forgets the instrument
//! state. The failed request is reported as an error (the run pauses with the
//! message); nothing is re-sent by the driver. When the run is resumed the
//! tuner re-issues the request, the driver reconnects, reads every channel
//! back and ramps from wherever the instrument really is — after checking the
//! step again.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::protocol::{Request, Response};
use spintune::safety::{GateSpec, SafetyLimits};
use spintune::ConfigError;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;

use super::bridge::BridgeDevice;
use super::DriverKind;
use super::{BoxFuture, Device, DeviceError, SimulatorDevice};

/// Magnitude from which a SCPI number is one of the standard's special
/// values: `9.91E37` (NaN) and `±9.9E37` (±infinity, overflow).
pub const SCPI_SPECIAL_MAGNITUDE: f64 = 9.9e37;

/// A number an instrument answered, if it is a real measurement: it parses,
/// is finite and is not one of SCPI's special values (NaN `9.91E37`,
/// overflow `±9.9E37`).
///
/// ```
/// use spintune_server::devices::scpi::scpi_number;
/// assert_eq!(scpi_number(" -0.75 "), Some(-0.75));
/// assert_eq!(scpi_number("9.91E37"), None);
/// assert_eq!(scpi_number("-9.9e37"), None);
/// assert_eq!(scpi_number("nan"), None);
/// assert_eq!(scpi_number("1 V"), None);
/// ```
pub fn scpi_number(answer: &str) -> Option<f64> {
    let v: f64 = answer.trim().parse().ok()?;
    (v.is_finite() && v.abs() < SCPI_SPECIAL_MAGNITUDE).then_some(v)
}

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

fn default_ramp_step_mv() -> f64 {
    1.0
}
fn default_readback_tolerance_mv() -> f64 {
    0.05
}
fn default_timeout_ms() -> u64 {
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

/// `sour{ch}:volt {V}` with the voltage given in mV.
pub fn set_command(channel: u32, mv: f64) -> String {
    format!("sour{channel}:volt {:.6}", mv / 1000.0)
}

/// `sour{ch}:volt?`.
pub fn query_command(channel: u32) -> String {
    format!("sour{channel}:volt?")
}

/// The read-back query of `profile`: `sour{ch}:volt?` (generic) or
/// `sour{ch}:volt:last?` (QDAC-II: the present output, not the set point).
pub fn readback_command(profile: ScpiProfile, channel: u32) -> String {
    match profile {
        ScpiProfile::Generic => query_command(channel),
        ScpiProfile::Qdac2 => format!("sour{channel}:volt:last?"),
    }
}

/// `sour{ch}:volt:mode fix` (QDAC-II).
pub fn fixed_mode_command(channel: u32) -> String {
    format!("sour{channel}:volt:mode fix")
}

/// `read{ch}?` (QDAC-II): the current the channel sources, A.
pub fn current_command(channel: u32) -> String {
    format!("read{channel}?")
}

/// `sour{ch}:volt:slew {V/s}`.
pub fn slew_command(channel: u32, v_per_s: f64) -> String {
    format!("sour{channel}:volt:slew {v_per_s}")
}

/// Plan the ramp from `present` to `target` (gate → mV): equal increments no
/// larger than `ramp_step_mv`, all gates advancing together. Returns the list
/// of stages, each a list of (gate, voltage mV). Gates whose target equals the
/// present voltage get no command.
pub fn plan_ramp(
    present: &BTreeMap<String, f64>,
    target: &BTreeMap<String, f64>,
    ramp_step_mv: f64,
) -> Vec<Vec<(String, f64)>> {
    let moves: Vec<(&String, f64, f64)> = target
        .iter()
        .filter_map(|(g, &t)| {
            let p = present.get(g).copied().unwrap_or(t);
            (t != p).then_some((g, p, t))
        })
        .collect();
    let n = moves
        .iter()
        .map(|(_, p, t)| ((t - p).abs() / ramp_step_mv * (1.0 - 1e-12)).ceil() as usize)
        .max()
        .unwrap_or(0)
        .max(usize::from(!moves.is_empty()));
    (1..=n)
        .map(|k| {
            moves
                .iter()
                .map(|(g, p, t)| {
                    let v = if k == n {
                        *t
                    } else {
                        p + (t - p) * k as f64 / n as f64
                    };
                    ((*g).clone(), v)
                })
                .collect()
        })
        .collect()
}

struct Conn {
    reader: BufReader<OwnedReadHalf>,
    writer: OwnedWriteHalf,
}

/// A connection to the DC source plus what the driver knows of its state.
pub struct ScpiSource {
    cfg: ScpiConfig,
    limits: SafetyLimits,
    conn: Option<Conn>,
    /// Voltages last read back from the instrument on this connection, mV.
    known: BTreeMap<String, f64>,
}

impl ScpiSource {
    /// A source for `cfg` with the tuner's gate limits. Does not connect yet.
    pub fn new(cfg: ScpiConfig, gates: &[GateSpec]) -> Self {
        Self {
            cfg,
            limits: SafetyLimits::new(gates),
            conn: None,
            known: BTreeMap::new(),
        }
    }

    /// The settings.
    pub fn config(&self) -> &ScpiConfig {
        &self.cfg
    }

    /// Whether a connection is open.
    pub fn is_connected(&self) -> bool {
        self.conn.is_some()
    }

    fn timeout(&self) -> Duration {
        Duration::from_millis(self.cfg.timeout_ms)
    }

    fn channel(&self, gate: &str) -> Result<u32, DeviceError> {
        self.cfg
            .channels
            .get(gate)
            .copied()
            .ok_or_else(|| DeviceError::Unmapped {
                gate: gate.to_string(),
            })
    }

    fn drop_conn(&mut self) {
        self.conn = None;
        self.known.clear();
    }

    async fn write_line(&mut self, line: &str) -> Result<(), DeviceError> {
        let t = self.timeout();
        let Some(conn) = self.conn.as_mut() else {
            return Err(DeviceError::NotConnected);
        };
        let data = format!("{line}\n");
        let r = tokio::time::timeout(t, async {
            conn.writer.write_all(data.as_bytes()).await?;
            conn.writer.flush().await
        })
        .await;
        match r {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => {
                self.drop_conn();
                Err(DeviceError::Io {
                    what: format!("sending `{line}`"),
                    error: e.to_string(),
                })
            }
            Err(_) => {
                self.drop_conn();
                Err(DeviceError::Timeout {
                    what: format!("sending `{line}`"),
                    ms: self.cfg.timeout_ms,
                })
            }
        }
    }

    async fn query_mv(&mut self, channel: u32) -> Result<f64, DeviceError> {
        let q = readback_command(self.cfg.profile, channel);
        let answer = self.query_line(&q).await?;
        match scpi_number(&answer) {
            Some(v) => Ok(v * 1000.0),
            None => {
                self.drop_conn();
                Err(DeviceError::Protocol(format!(
                    "answer {answer:?} to `{q}` is not a voltage"
                )))
            }
        }
    }

    /// The largest magnitude of the current(s) `read{ch}?` answers, nA.
    async fn query_current_na(&mut self, channel: u32) -> Result<f64, DeviceError> {
        let q = current_command(channel);
        let answer = self.query_line(&q).await?;
        let values: Option<Vec<f64>> = answer.split(',').map(scpi_number).collect();
        match values {
            Some(v) if !v.is_empty() => Ok(v.iter().fold(0.0f64, |m, x| m.max(x.abs())) * 1e9),
            _ => {
                self.drop_conn();
                Err(DeviceError::Protocol(format!(
                    "answer {answer:?} to `{q}` is not a current"
                )))
            }
        }
    }

    /// Send query `q` and return its one-line answer, trimmed.
    async fn query_line(&mut self, q: &str) -> Result<String, DeviceError> {
        let q = q.to_string();
        self.write_line(&q).await?;
        let t = self.timeout();
        let conn = self.conn.as_mut().ok_or(DeviceError::NotConnected)?;
        let mut line = String::new();
        let r = tokio::time::timeout(t, conn.reader.read_line(&mut line)).await;
        let answer = match r {
            Ok(Ok(0)) => {
                self.drop_conn();
                return Err(DeviceError::Io {
                    what: format!("reading the answer to `{q}`"),
                    error: "the instrument closed the connection".into(),
                });
            }
            Ok(Ok(_)) => line.trim().to_string(),
            Ok(Err(e)) => {
                self.drop_conn();
                return Err(DeviceError::Io {
                    what: format!("reading the answer to `{q}`"),
                    error: e.to_string(),
                });
            }
            Err(_) => {
                // A late answer would desynchronise the line protocol: drop it.
                self.drop_conn();
                return Err(DeviceError::NoAnswer {
                    query: q,
                    ms: self.cfg.timeout_ms,
                });
            }
        };
        Ok(answer)
    }

    /// Connect (if needed): open the socket, send the slew rate to every
    /// mapped channel and read every channel back.
    pub async fn ensure_connected(&mut self) -> Result<(), DeviceError> {
        if self.conn.is_some() {
            return Ok(());
        }
        let t = self.timeout();
        let stream = match tokio::time::timeout(t, TcpStream::connect(&self.cfg.address)).await {
            Ok(Ok(s)) => s,
            Ok(Err(e)) => {
                return Err(DeviceError::Connect {
                    address: self.cfg.address.clone(),
                    error: e.to_string(),
                })
            }
            Err(_) => {
                return Err(DeviceError::Timeout {
                    what: format!("connecting to {}", self.cfg.address),
                    ms: self.cfg.timeout_ms,
                })
            }
        };
        let _ = stream.set_nodelay(true);
        let (r, w) = stream.into_split();
        self.conn = Some(Conn {
            reader: BufReader::new(r),
            writer: w,
        });
        self.known.clear();
        let channels: Vec<(String, u32)> = self
            .cfg
            .channels
            .iter()
            .map(|(g, &c)| (g.clone(), c))
            .collect();
        for (gate, ch) in channels {
            if self.cfg.profile == ScpiProfile::Qdac2 {
                // Before anything else: a channel in list/sweep mode ignores
                // `sour{ch}:volt`. The read-back below is taken after it.
                self.write_line(&fixed_mode_command(ch)).await?;
            }
            if let Some(slew) = self.cfg.slew_v_per_s {
                self.write_line(&slew_command(ch, slew)).await?;
            }
            let mv = self.query_mv(ch).await?;
            self.known.insert(gate, mv);
        }
        Ok(())
    }

    /// Ask the instrument for the present output of `gates` (one query per
    /// channel, now — not a cached value), mV.
    pub async fn read(&mut self, gates: &[String]) -> Result<BTreeMap<String, f64>, DeviceError> {
        for gate in gates {
            self.channel(gate)?;
        }
        let fresh = self.conn.is_none();
        self.ensure_connected().await?;
        let mut out = BTreeMap::new();
        for gate in gates {
            let mv = match (fresh, self.known.get(gate)) {
                // just read on connecting
                (true, Some(&v)) => v,
                _ => {
                    let ch = self.channel(gate)?;
                    let v = self.query_mv(ch).await?;
                    self.known.insert(gate.clone(), v);
                    v
                }
            };
            out.insert(gate.clone(), mv);
        }
        Ok(out)
    }

    /// Voltages last read back from the instrument, mV (empty when not connected).
    pub fn known_mv(&self) -> &BTreeMap<String, f64> {
        &self.known
    }

    /// Safely move the gates in `target` (gate → mV) and return the read-back
    /// voltages (mV). See the module documentation for the checks.
    pub async fn set(
        &mut self,
        target: &BTreeMap<String, f64>,
    ) -> Result<BTreeMap<String, f64>, DeviceError> {
        // Refuse what can be refused before touching the network.
        for gate in target.keys() {
            self.channel(gate)?;
        }
        self.limits
            .check(&BTreeMap::new(), target)
            .map_err(|e| DeviceError::Refused(e.to_string()))?;
        self.ensure_connected().await?;
        let present = self.known.clone();
        // Step from where the instrument really is.
        self.limits.check(&present, target).map_err(|e| {
            DeviceError::Refused(format!("{e} (measured from the instrument's read-back)"))
        })?;
        let stages = plan_ramp(&present, target, self.cfg.ramp_step_mv);
        // Check every planned command before sending the first.
        let mut last = present.clone();
        for stage in &stages {
            for (gate, v) in stage {
                let single = BTreeMap::from([(gate.clone(), *v)]);
                self.limits
                    .check(&BTreeMap::new(), &single)
                    .map_err(|e| DeviceError::Refused(format!("planned ramp: {e}")))?;
                let prev = last.get(gate).copied().unwrap_or(*v);
                if (v - prev).abs() > self.cfg.ramp_step_mv * (1.0 + 1e-9) + 1e-12 {
                    return Err(DeviceError::Refused(format!(
                        "planned ramp of {gate}: increment {} mV exceeds ramp_step_mv {} mV",
                        (v - prev).abs(),
                        self.cfg.ramp_step_mv
                    )));
                }
                last.insert(gate.clone(), *v);
            }
        }
        let n = stages.len();
        let mut prev = present.clone();
        for (k, stage) in stages.iter().enumerate() {
            let mut largest = 0.0f64;
            for (gate, v) in stage {
                let ch = self.channel(gate)?;
                let cmd = set_command(ch, *v);
                if let Err(e) = self.write_line(&cmd).await {
                    return Err(DeviceError::RampInterrupted {
                        error: Box::new(e),
                        increment: k + 1,
                        increments: n,
                        gate: gate.clone(),
                        channel: ch,
                    });
                }
                largest = largest.max((v - prev.get(gate).copied().unwrap_or(*v)).abs());
                prev.insert(gate.clone(), *v);
            }
            if let Some(slew) = self.cfg.slew_v_per_s {
                let wait = largest / 1000.0 / slew;
                if wait > 0.0 {
                    tokio::time::sleep(Duration::from_secs_f64(wait.min(60.0))).await;
                }
            }
        }
        if self.cfg.settle_ms > 0 {
            tokio::time::sleep(Duration::from_millis(self.cfg.settle_ms)).await;
        }
        // Read every channel back first (so the driver knows the real state
        // even when one of them disagrees), then compare.
        let mut readback = BTreeMap::new();
        for gate in target.keys() {
            let ch = self.channel(gate)?;
            let mv = match self.query_mv(ch).await {
                Ok(mv) => mv,
                Err(e) => {
                    return Err(DeviceError::ReadbackFailed {
                        gate: gate.clone(),
                        channel: ch,
                        error: Box::new(e),
                    })
                }
            };
            self.known.insert(gate.clone(), mv);
            readback.insert(gate.clone(), mv);
        }
        for (gate, &t) in target {
            let mv = readback[gate];
            if (mv - t).abs() > self.cfg.readback_tolerance_mv {
                let ch = self.channel(gate)?;
                // An instrument that disagrees cannot be trusted as the start
                // of the next ramp: forget everything, re-read on the next request.
                self.drop_conn();
                return Err(DeviceError::ReadbackMismatch {
                    gate: gate.clone(),
                    channel: ch,
                    set_mv: t,
                    read_mv: mv,
                    tolerance_mv: self.cfg.readback_tolerance_mv,
                });
            }
        }
        for gate in target.keys() {
            let Some((limit, max_na)) = self.cfg.leakage_limit_na(gate) else {
                continue;
            };
            let ch = self.channel(gate)?;
            let current_na = self.query_current_na(ch).await?;
            if current_na > max_na {
                return Err(DeviceError::Leakage {
                    gate: gate.clone(),
                    channel: ch,
                    current_na,
                    limit,
                    max_na,
                });
            }
        }
        Ok(readback)
    }
}

/// The measurement half of a SCPI run.
enum Measurer {
    Simulator(Box<SimulatorDevice>),
    Bridge(BridgeDevice),
}

/// A SCPI DC source for the gates plus a measurement device ([`MeasureSource`]).
pub struct ScpiDevice {
    source: ScpiSource,
    measurer: Measurer,
}

impl ScpiDevice {
    /// Gates through `source`, measurements from the simulator (whose state is
    /// the device checkpoint).
    pub fn with_simulator(source: ScpiSource, simulator: SimulatorDevice) -> Self {
        Self {
            source,
            measurer: Measurer::Simulator(Box::new(simulator)),
        }
    }

    /// Gates through `source`, measurements from the lab bridge.
    pub fn with_bridge(source: ScpiSource, bridge: BridgeDevice) -> Self {
        Self {
            source,
            measurer: Measurer::Bridge(bridge),
        }
    }

    /// A fault of the DC source as the device's answer, naming the source.
    fn source_fault(&self, e: DeviceError) -> Response {
        Response::error(format!("SCPI source {}: {e}", self.source.cfg.address))
    }

    async fn execute_inner(&mut self, request: Request) -> Response {
        match request {
            Request::SetVoltages { voltages_mv } => {
                let start = Instant::now();
                match self.source.set(&voltages_mv).await {
                    Ok(readback) => {
                        if let Measurer::Simulator(sim) = &mut self.measurer {
                            // The simulated device follows the real voltages.
                            if let Response::Error { message, .. } = sim
                                .execute(Request::SetVoltages {
                                    voltages_mv: readback.clone(),
                                })
                                .await
                            {
                                return Response::error(format!(
                                    "simulator refused the read-back voltages: {message}"
                                ));
                            }
                        }
                        Response::VoltagesSet {
                            voltages_mv: readback,
                            lab_seconds: start.elapsed().as_secs_f64(),
                        }
                    }
                    Err(e) => self.source_fault(e),
                }
            }
            Request::ReadVoltages { gates } => {
                // Mapped gates are read from the source; any other gate (not
                // settable through SCPI) from the measuring side.
                let start = Instant::now();
                let (mapped, other): (Vec<String>, Vec<String>) = gates
                    .into_iter()
                    .partition(|g| self.source.cfg.channels.contains_key(g));
                let mut voltages_mv = match self.source.read(&mapped).await {
                    Ok(v) => v,
                    Err(e) => return self.source_fault(e),
                };
                if !other.is_empty() {
                    let request = Request::ReadVoltages { gates: other };
                    let answer = match &mut self.measurer {
                        Measurer::Simulator(sim) => sim.execute(request).await,
                        Measurer::Bridge(bridge) => bridge.execute(request).await,
                    };
                    match answer {
                        Response::VoltagesRead { voltages_mv: v, .. } => voltages_mv.extend(v),
                        other => return other,
                    }
                }
                Response::VoltagesRead {
                    voltages_mv,
                    lab_seconds: start.elapsed().as_secs_f64(),
                }
            }
            other => match &mut self.measurer {
                Measurer::Simulator(sim) => sim.execute(other).await,
                Measurer::Bridge(bridge) => bridge.execute(other).await,
            },
        }
    }
}

impl Device for ScpiDevice {
    fn execute(&mut self, request: Request) -> BoxFuture<'_, Response> {
        Box::pin(self.execute_inner(request))
    }

    fn checkpoint(&self) -> Result<Value, serde_json::Error> {
        match &self.measurer {
            Measurer::Simulator(sim) => sim.checkpoint(),
            Measurer::Bridge(_) => Ok(Value::Null),
        }
    }

    fn driver(&self) -> DriverKind {
        DriverKind::Scpi
    }

    fn recovered(&self) -> BoxFuture<'static, ()> {
        match &self.measurer {
            Measurer::Bridge(b) => b.recovered(),
            Measurer::Simulator(_) => Box::pin(std::future::pending()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A config with the defaults of a run config, `generic` profile, no
    /// leakage check.
    fn config(address: &str, channels: &[(&str, u32)]) -> ScpiConfig {
        ScpiConfig {
            address: address.into(),
            channels: channels.iter().map(|(g, c)| (g.to_string(), *c)).collect(),
            ramp_step_mv: default_ramp_step_mv(),
            slew_v_per_s: None,
            readback_tolerance_mv: default_readback_tolerance_mv(),
            timeout_ms: default_timeout_ms(),
            settle_ms: 0,
            measure: MeasureSource::Simulator,
            profile: Default::default(),
            max_leakage_na: None,
            max_leakage_na_by_gate: BTreeMap::new(),
        }
    }

    #[test]
    fn ramp_increments_never_exceed_the_step_and_end_on_target() {
        let present = BTreeMap::from([("A".to_string(), -780.0), ("B".to_string(), 10.0)]);
        let target = BTreeMap::from([("A".to_string(), -777.5), ("B".to_string(), 10.0)]);
        let stages = plan_ramp(&present, &target, 1.0);
        assert_eq!(stages.len(), 3);
        assert!(stages.iter().all(|s| s.len() == 1 && s[0].0 == "A"));
        assert_eq!(stages[2][0].1, -777.5);
        let mut prev = -780.0;
        for s in &stages {
            assert!((s[0].1 - prev).abs() <= 1.0 + 1e-12);
            prev = s[0].1;
        }
        // exactly one step's worth: one command
        let t = BTreeMap::from([("A".to_string(), -779.0)]);
        assert_eq!(plan_ramp(&present, &t, 1.0).len(), 1);
        // nothing to do
        assert!(plan_ramp(&present, &present, 1.0).is_empty());
    }

    #[test]
    fn config_errors_name_the_field_within_the_scpi_table() {
        let gates = spintune::sim::default_gates();
        let cfg = |channels: &[(&str, u32)]| config("127.0.0.1:5025", channels);
        assert_eq!(cfg(&[("N", 1), ("SB", 4)]).validate(&gates), Ok(()));
        let e = cfg(&[("NOPE", 1)]).validate(&gates).unwrap_err();
        assert_eq!(e.field, "channels.NOPE");
        assert!(e.message.contains("\"NOPE\" is not a gate"), "{e}");
        let e = cfg(&[("N", 2), ("SB", 2)]).validate(&gates).unwrap_err();
        assert_eq!(e.field, "channels.SB");
        assert_eq!(e.message, "channel 2 is already used by \"N\"");
        assert_eq!(e.within("scpi").field, "scpi.channels.SB");
        let mut c = cfg(&[("N", 1)]);
        c.ramp_step_mv = f64::NAN;
        let e = c.validate(&gates).unwrap_err();
        assert_eq!(
            e.to_string(),
            "invalid config at `ramp_step_mv`: must be a positive number of mV, at most 1000, got NaN"
        );
        c.ramp_step_mv = 1e-7;
        let e = c.validate(&gates).unwrap_err();
        assert_eq!(e.field, "ramp_step_mv");
        assert!(e.to_string().contains("more than 1000 commands"), "{e}");
        c.ramp_step_mv = 1.0;
        c.timeout_ms = 0;
        assert_eq!(c.validate(&gates).unwrap_err().field, "timeout_ms");
        c.timeout_ms = 1;
        c.address = "localhost".into();
        assert_eq!(c.validate(&gates).unwrap_err().field, "address");
    }

    #[test]
    fn per_gate_leakage_limits_override_the_default_and_are_validated() {
        let gates = spintune::sim::default_gates();
        let mut c = ScpiConfig {
            profile: ScpiProfile::Qdac2,
            max_leakage_na_by_gate: BTreeMap::from([("SB".to_string(), 20.0)]),
            ..config("127.0.0.1:5025", &[("N", 1), ("SB", 4)])
        };
        assert_eq!(c.validate(&gates), Ok(()));
        // Only the named gate is checked without a default...
        assert_eq!(
            c.leakage_limit_na("SB"),
            Some(("max_leakage_na_by_gate.SB".to_string(), 20.0))
        );
        assert_eq!(c.leakage_limit_na("N"), None);
        // ...and with one, the others get the default.
        c.max_leakage_na = Some(100.0);
        assert_eq!(
            c.leakage_limit_na("N"),
            Some(("max_leakage_na".to_string(), 100.0))
        );
        assert_eq!(c.leakage_limit_na("SB").map(|l| l.1), Some(20.0));
        // A gate that is not mapped, a bad value, or the generic profile: errors naming the key.
        c.max_leakage_na_by_gate.insert("PA".into(), 5.0);
        let e = c.validate(&gates).unwrap_err();
        assert_eq!(e.field, "max_leakage_na_by_gate.PA");
        assert!(e.message.contains("not a gate of `channels`"), "{e}");
        c.max_leakage_na_by_gate.remove("PA");
        c.max_leakage_na_by_gate.insert("SB".into(), -1.0);
        assert_eq!(
            c.validate(&gates).unwrap_err().field,
            "max_leakage_na_by_gate.SB"
        );
        c.max_leakage_na_by_gate.insert("SB".into(), 20.0);
        c.max_leakage_na = None;
        c.profile = ScpiProfile::Generic;
        let e = c.validate(&gates).unwrap_err();
        assert_eq!(e.field, "max_leakage_na_by_gate.SB");
        assert!(e.message.contains("qdac2"), "{e}");
    }

    #[tokio::test]
    async fn refusals_and_connection_failures_are_typed() {
        let gates = spintune::sim::default_gates();
        // A port nobody listens on (bound, then released).
        let addr = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let cfg = ScpiConfig {
            timeout_ms: 500,
            ..config(&addr.to_string(), &[("SB", 4)])
        };
        let mut src = ScpiSource::new(cfg, &gates);
        assert_eq!(
            src.set(&BTreeMap::from([("N".to_string(), -700.0)])).await,
            Err(DeviceError::Unmapped { gate: "N".into() })
        );
        assert!(matches!(
            src.set(&BTreeMap::from([("SB".to_string(), 1e6)])).await,
            Err(DeviceError::Refused(_))
        ));
        let e = src.read(&["SB".to_string()]).await.unwrap_err();
        assert!(
            matches!(&e, DeviceError::Connect { address, .. } if *address == addr.to_string()),
            "{e:?}"
        );
        assert!(
            e.to_string().starts_with("cannot connect to 127.0.0.1:"),
            "{e}"
        );
        assert!(!src.is_connected());
    }

    #[test]
    fn commands_are_in_volts() {
        assert_eq!(set_command(4, -777.5), "sour4:volt -0.777500");
        assert_eq!(query_command(12), "sour12:volt?");
        assert_eq!(slew_command(1, 0.5), "sour1:volt:slew 0.5");
    }
}
