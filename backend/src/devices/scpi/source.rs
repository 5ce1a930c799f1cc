//! [`ScpiSource`]: the TCP connection to the DC source and what the driver
//! knows of its state (the voltages last read back on this connection); the
//! driver's own checks (mapping, limits, step from the read-back, the ramp,
//! the read-back after it, leakage) before and after every move.

use std::collections::BTreeMap;
use std::time::Duration;

use spintune::safety::{GateSpec, SafetyLimits};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;

use super::commands::{
    current_command, fixed_mode_command, plan_ramp, readback_command, scpi_number, set_command,
    slew_command,
};
use super::config::{ScpiConfig, ScpiProfile};
use crate::devices::DeviceError;

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
