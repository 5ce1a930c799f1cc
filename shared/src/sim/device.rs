//! [`SimulatedDevice`]: the double dot as a driver sees it.

use std::collections::BTreeMap;

use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::clock::LabClock;
use super::config::DeviceConfig;
use super::model;
use super::noise::DriftState;
use crate::config_error::ConfigError;
use crate::protocol::{Request, Response, ScanOutcome};
use crate::safety::GateSpec;

/// Noiseless ground truth at the present voltages (no white noise, drift
/// or charge jumps).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    /// Transition width w, µV (definition: [`Truth::W_DEFINITION`]). Parameter `"w"`.
    pub w_uv: f64,
    /// Singlet reload time t_sr = 1/Γ, ns. Parameter `"t_sr"`.
    pub t_sr_ns: f64,
    /// Inter-dot tunnel coupling t_c, µeV. Parameter `"t_c_uev"`.
    pub t_c_uev: f64,
    /// Lead tunnel rate Γ, 1/ns. Parameter `"gamma_per_ns"`.
    pub gamma_per_ns: f64,
    /// Transition line A, mV on RFA; 0 at the start voltages. Parameter `"mu_a_mv"`.
    pub mu_a_mv: f64,
    /// Transition line B, mV on RFB; 0 at the start voltages. Parameter `"mu_b_mv"`.
    pub mu_b_mv: f64,
    /// Steepest lower-voltage flank of the highest Coulomb peak within the
    /// default sweep window of the sensing gate
    /// ([`super::config::SensingDotConfig::gate`]), mV of that gate. Parameter `"sd_flank_mv"`.
    pub sd_flank_mv: f64,
    /// Readout contrast |G'(u)|/max|G'| at the present operating point, 0..1. Parameter `"sd_contrast"`.
    pub sd_contrast: f64,
}

impl Truth {
    /// How `w` is defined.
    pub const W_DEFINITION: &'static str = "width parameter (×1000, µV) of the tanh-step fit \
        (spintune::fit::tanh::fit_tanh_step) to the noiseless two-level excess-charge lineshape \
        on the centred detuning grid of the device's scan settings";

    /// Names accepted by [`Truth::get`] and [`SimulatedDevice::true_jacobian`].
    pub const PARAMETERS: [&'static str; 8] = [
        "w",
        "t_sr",
        "t_c_uev",
        "gamma_per_ns",
        "mu_a_mv",
        "mu_b_mv",
        "sd_flank_mv",
        "sd_contrast",
    ];

    /// The value of a parameter by name (see [`Truth::PARAMETERS`]).
    pub fn get(&self, name: &str) -> Option<f64> {
        Some(match name {
            "w" => self.w_uv,
            "t_sr" => self.t_sr_ns,
            "t_c_uev" => self.t_c_uev,
            "gamma_per_ns" => self.gamma_per_ns,
            "mu_a_mv" => self.mu_a_mv,
            "mu_b_mv" => self.mu_b_mv,
            "sd_flank_mv" => self.sd_flank_mv,
            "sd_contrast" => self.sd_contrast,
            _ => return None,
        })
    }
}

/// Step of the central finite differences in [`SimulatedDevice::true_jacobian`], mV.
pub const JACOBIAN_STEP_MV: f64 = 0.1;

/// A simulated double quantum dot with sensing dot, noise, drift, charge
/// jumps and a lab clock. All randomness comes from the seeded
/// `ChaCha8Rng` inside, so the same seed and requests give bit-identical
/// data on every target; the whole state (RNG included) serializes, and a
/// deserialized copy continues bit-identically.
///
/// ```
/// use spintune::protocol::{Request, Response};
/// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
/// let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 42).unwrap();
/// let t = dev.truth();
/// assert!((t.t_sr_ns - 45.0).abs() < 1e-9 && (t.w_uv - 210.0).abs() < 5.0);
/// let set = Request::SetVoltages { voltages_mv: [("SB".to_string(), -775.0)].into() };
/// assert!(matches!(dev.execute(&set), Response::VoltagesSet { .. }));
/// assert!(dev.truth().t_sr_ns < t.t_sr_ns);
/// assert!(dev.lab_seconds() > 0.0);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulatedDevice {
    pub(crate) config: DeviceConfig,
    pub(crate) gates: Vec<GateSpec>,
    pub(crate) voltages_mv: BTreeMap<String, f64>,
    /// Raw line positions at the start voltages (the calibrated operating point), mV.
    pub(crate) line_offsets_mv: [f64; 2],
    pub(crate) drift: DriftState,
    pub(crate) clock: LabClock,
    pub(crate) rng: ChaCha8Rng,
    /// Whether [`Request::TrueJacobian`] is answered (the oracle's
    /// capability; see [`SimulatedDevice::seal_truth`]). Default open.
    #[serde(default)]
    pub(crate) truth_sealed: bool,
    /// [`Request::TrueJacobian`] requests received, answered or refused.
    #[serde(default)]
    pub(crate) truth_queries: u64,
}

impl SimulatedDevice {
    /// A device at the gates' `initial_mv`, lab clock 0, drifts 0.
    /// `Err` if the config is invalid, gate names repeat, a gate's limits are
    /// inconsistent, a gate has no entry in [`DeviceConfig::reference_mv`], or
    /// the sensing gate is missing. Field paths are relative to the device
    /// config, except `gates[i]…`, which name the `gates` argument
    /// ([`crate::driver::SimulationConfig::simulated_device`] places both).
    pub fn new(config: DeviceConfig, gates: &[GateSpec], seed: u64) -> Result<Self, ConfigError> {
        config.validate()?;
        let mut voltages_mv = BTreeMap::new();
        for (i, g) in gates.iter().enumerate() {
            if !(g.min_mv.is_finite() && g.max_mv.is_finite() && g.initial_mv.is_finite()) {
                return Err(ConfigError::new(
                    format!("gates[{i}]"),
                    format!(
                        "gate {:?}: limits and initial voltage must be finite",
                        g.name
                    ),
                ));
            }
            if !(g.min_mv <= g.initial_mv && g.initial_mv <= g.max_mv) {
                return Err(ConfigError::new(
                    format!("gates[{i}].initial_mv"),
                    format!(
                        "gate {:?}: initial {} mV outside [{}, {}] mV",
                        g.name, g.initial_mv, g.min_mv, g.max_mv
                    ),
                ));
            }
            if !config.reference_mv.contains_key(&g.name) {
                return Err(ConfigError::new(
                    "reference_mv",
                    format!("has no entry for gate {:?}", g.name),
                ));
            }
            if voltages_mv.insert(g.name.clone(), g.initial_mv).is_some() {
                return Err(ConfigError::new(
                    format!("gates[{i}].name"),
                    format!("gate {:?} listed twice", g.name),
                ));
            }
        }
        if !voltages_mv.contains_key(&config.sensing_dot.gate) {
            return Err(ConfigError::new(
                "sensing_dot.gate",
                format!("{:?} is not among the gates", config.sensing_dot.gate),
            ));
        }
        let d = model::deviations(&config, &voltages_mv);
        let line_offsets_mv = model::raw_lines_mv(&config, &d);
        Ok(SimulatedDevice {
            config,
            gates: gates.to_vec(),
            voltages_mv,
            line_offsets_mv,
            drift: DriftState::default(),
            clock: LabClock::default(),
            rng: ChaCha8Rng::seed_from_u64(seed),
            truth_sealed: false,
            truth_queries: 0,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &DeviceConfig {
        &self.config
    }

    /// The gates.
    pub fn gates(&self) -> &[GateSpec] {
        &self.gates
    }

    /// Present gate voltages, mV.
    pub fn voltages_mv(&self) -> &BTreeMap<String, f64> {
        &self.voltages_mv
    }

    /// Cumulative simulated lab time, s.
    pub fn lab_seconds(&self) -> f64 {
        self.clock.seconds()
    }

    /// Take the oracle's capability away (ARCHITECTURE.md invariant 7): from
    /// now on [`Request::TrueJacobian`] is answered with an error (and still
    /// counted in [`SimulatedDevice::truth_queries`]). Irreversible for this
    /// value; the benchmark hands every non-oracle strategy a sealed device.
    ///
    /// ```
    /// use spintune::protocol::{Request, Response};
    /// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
    /// let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 1).unwrap();
    /// dev.seal_truth();
    /// let r = dev.execute(&Request::TrueJacobian { gates: vec!["T".into()], parameters: vec!["w".into()] });
    /// assert!(matches!(r, Response::Error { .. }));
    /// assert_eq!(dev.truth_queries(), 1);
    /// ```
    pub fn seal_truth(&mut self) {
        self.truth_sealed = true;
    }

    /// Whether [`SimulatedDevice::seal_truth`] was called.
    pub fn is_truth_sealed(&self) -> bool {
        self.truth_sealed
    }

    /// How many [`Request::TrueJacobian`] requests this device received
    /// (answered or refused): 0 for every run that never asked the oracle.
    pub fn truth_queries(&self) -> u64 {
        self.truth_queries
    }

    /// Lab time passes with nothing done (the device left alone, e.g.
    /// between checks of a tuned point): the drifts and charge jumps evolve
    /// over `seconds` (in steps of at most a minute; the OU updates are
    /// exact for any step) and the lab clock advances. Non-finite or
    /// negative durations do nothing.
    ///
    /// ```
    /// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
    /// let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 3).unwrap();
    /// let before = dev.truth().t_sr_ns;
    /// dev.idle(6.0 * 3600.0);
    /// assert_eq!(dev.lab_seconds(), 6.0 * 3600.0);
    /// assert_ne!(dev.truth().t_sr_ns, before); // Γ drifted
    /// ```
    pub fn idle(&mut self, seconds: f64) {
        if !(seconds.is_finite() && seconds > 0.0) {
            return;
        }
        let mut left = seconds;
        while left > 0.0 {
            let dt = left.min(60.0);
            self.drift.advance(&self.config.noise, dt, &mut self.rng);
            left -= dt;
        }
        self.clock.advance(seconds);
    }

    /// A charge rearrangement near the dots, as a lab sees one now and
    /// then: both transition lines jump by these amounts (mV on RFA / RFB)
    /// and stay there; their slow drift goes on around the new place.
    /// Nothing else changes and no gate moves: a tuner finds out by
    /// scanning. Non-finite shifts are ignored.
    ///
    /// ```
    /// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
    /// let mut dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 3).unwrap();
    /// dev.rearrange_charges([7.0, -1.0]);
    /// assert_eq!(dev.drift().jump_mu_mv, [7.0, -1.0]);
    /// ```
    pub fn rearrange_charges(&mut self, shift_mv: [f64; 2]) {
        for (j, s) in self.drift.jump_mu_mv.iter_mut().zip(shift_mv) {
            if s.is_finite() {
                *j += s;
            }
        }
    }

    /// Present drift and charge-jump state (what [`SimulatedDevice::truth`] leaves out).
    pub fn drift(&self) -> &DriftState {
        &self.drift
    }

    /// Executes one request. Never panics on bad input: unknown gates,
    /// non-finite or out-of-limit voltages and unknown parameters give
    /// [`Response::Error`] (nothing applied); a scan that cannot be made gives
    /// [`ScanOutcome::Failed`] with 0 lab seconds.
    pub fn execute(&mut self, request: &Request) -> Response {
        match request {
            Request::SetVoltages { voltages_mv } => match self.set_voltages(voltages_mv) {
                Ok(readback) => Response::VoltagesSet {
                    voltages_mv: readback,
                    lab_seconds: self.config.durations.set_voltages_s,
                },
                Err(message) => Response::error(message),
            },
            Request::ReadVoltages { gates } => {
                // A read takes no simulated lab time and draws no random
                // numbers, so reading back never changes a run's outcome.
                let mut voltages_mv = BTreeMap::new();
                for g in gates {
                    match self.voltages_mv.get(g) {
                        Some(&v) => voltages_mv.insert(g.clone(), v),
                        None => return Response::error(format!("unknown gate {g:?}")),
                    };
                }
                Response::VoltagesRead {
                    voltages_mv,
                    lab_seconds: 0.0,
                }
            }
            // One double dot has one readout: its requests run one after another.
            Request::Batch { requests } => {
                if requests.len() > crate::protocol::MAX_BATCH_REQUESTS
                    || requests.iter().any(|r| matches!(r, Request::Batch { .. }))
                {
                    return Response::error(format!(
                        "a batch of at most {} requests, none of them a batch",
                        crate::protocol::MAX_BATCH_REQUESTS
                    ));
                }
                let before = self.clock.seconds();
                let responses = requests.iter().map(|r| self.execute(r)).collect();
                Response::Batch {
                    responses,
                    lab_seconds: self.clock.seconds() - before,
                }
            }
            Request::Measure { scan } => match self.scan(scan) {
                Ok((scan, lab_seconds)) => Response::Scanned {
                    outcome: ScanOutcome::Raw { scan },
                    lab_seconds,
                },
                Err(e) => Response::Scanned {
                    outcome: ScanOutcome::Failed {
                        reason: e.to_string(),
                    },
                    lab_seconds: 0.0,
                },
            },
            Request::Wait { seconds } => {
                if !(seconds.is_finite()
                    && *seconds > 0.0
                    && *seconds <= crate::protocol::MAX_WAIT_SECONDS)
                {
                    return Response::error(format!(
                        "a wait of {seconds} s (allowed: more than 0, at most {} s)",
                        crate::protocol::MAX_WAIT_SECONDS
                    ));
                }
                self.idle(*seconds);
                Response::Waited {
                    lab_seconds: *seconds,
                }
            }
            Request::TrueJacobian { .. } if self.truth_sealed => {
                self.truth_queries += 1;
                Response::error(
                    "the true Jacobian is sealed on this device: only the oracle \
                        may read the simulator's truth (ARCHITECTURE.md invariant 7)",
                )
            }
            Request::TrueJacobian { gates, parameters } => {
                self.truth_queries += 1;
                let g: Vec<&str> = gates.iter().map(String::as_str).collect();
                let p: Vec<&str> = parameters.iter().map(String::as_str).collect();
                let truth = self.truth();
                let values: Option<Vec<f64>> = p.iter().map(|n| truth.get(n)).collect();
                match (values, self.true_jacobian(&g, &p)) {
                    (Some(values), Ok(j)) => Response::TrueJacobian {
                        values,
                        jacobian: (0..j.nrows())
                            .map(|r| j.row(r).iter().copied().collect())
                            .collect(),
                    },
                    (_, Err(message)) => Response::error(message),
                    (None, Ok(_)) => Response::error("unknown parameter"),
                }
            }
        }
    }

    fn set_voltages(
        &mut self,
        request: &BTreeMap<String, f64>,
    ) -> Result<BTreeMap<String, f64>, String> {
        for (name, &v) in request {
            let g = self
                .gates
                .iter()
                .find(|g| &g.name == name)
                .ok_or_else(|| format!("unknown gate {name:?}"))?;
            if !v.is_finite() {
                return Err(format!("gate {name:?}: voltage {v} mV is not finite"));
            }
            if !(g.min_mv..=g.max_mv).contains(&v) {
                return Err(format!(
                    "gate {name:?}: {v} mV outside the device limits [{}, {}] mV",
                    g.min_mv, g.max_mv
                ));
            }
        }
        for (name, &v) in request {
            self.voltages_mv.insert(name.clone(), v);
        }
        let dt = self.config.durations.set_voltages_s;
        self.drift.advance(&self.config.noise, dt, &mut self.rng);
        self.clock.advance(dt);
        Ok(request
            .keys()
            .map(|k| (k.clone(), self.voltages_mv[k]))
            .collect())
    }

    /// Noiseless ground truth at the present voltages: the model with the
    /// slow drift of t_c and Γ ([`crate::sim::SlowDrift`], the device's
    /// physical state now), without the fast drifts and noise of the scans.
    pub fn truth(&self) -> Truth {
        self.truth_at(&self.voltages_mv)
    }

    /// World side: where the two transition lines sit now, mV on RFA / RFB
    /// from the operating point, with the fast line drift and charge jumps
    /// that a scan sees (unlike [`SimulatedDevice::truth`]). A cell whose
    /// lines sit off 0 reads `t_sr` long and `w` faint (`sim::scans`).
    ///
    /// ```
    /// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
    /// let dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 3).unwrap();
    /// let [a, b] = dev.lines_now_mv();
    /// assert!(a.abs() < 1.0 && b.abs() < 1.0); // calibrated at the start
    /// ```
    pub fn lines_now_mv(&self) -> [f64; 2] {
        let t = self.truth();
        self.lines_now([t.mu_a_mv, t.mu_b_mv])
    }

    pub(crate) fn truth_at(&self, voltages_mv: &BTreeMap<String, f64>) -> Truth {
        let c = &self.config;
        let d = model::deviations(c, voltages_mv);
        let t_c_uev = model::tunnel_coupling_uev(c, &d) * self.drift.tunnel_coupling_factor();
        let gamma_per_ns = model::lead_rate_per_ns(c, &d) * self.drift.lead_rate_factor();
        let lines = model::raw_lines_mv(c, &d);
        let u = model::sd_potential_mv(c, &d);
        let (_, slope) = model::sd_signal(c, u);
        Truth {
            w_uv: model::transition_width_uv(c, t_c_uev),
            t_sr_ns: 1.0 / gamma_per_ns,
            t_c_uev,
            gamma_per_ns,
            mu_a_mv: lines[0] - self.line_offsets_mv[0],
            mu_b_mv: lines[1] - self.line_offsets_mv[1],
            sd_flank_mv: model::sd_flank_mv(c, voltages_mv[&c.sensing_dot.gate], u),
            sd_contrast: slope.abs() / model::sd_max_slope(c),
        }
    }

    /// Noiseless Jacobian `∂parameter/∂gate` (rows: `parameters` in order,
    /// columns: `gates` in order; unit of the parameter per mV) at the present
    /// voltages, by central differences with step [`JACOBIAN_STEP_MV`].
    /// `Err` naming an unknown gate or parameter (see [`Truth::PARAMETERS`]).
    ///
    /// ```
    /// use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};
    /// let dev = SimulatedDevice::new(DeviceConfig::default(), &default_gates(), 0).unwrap();
    /// let j = dev.true_jacobian(&["SB", "T"], &["t_sr", "w"]).unwrap();
    /// assert!(j[(0, 0)] < -0.5); // opening SB speeds up the reload
    /// assert!(dev.true_jacobian(&["X"], &["w"]).is_err());
    /// ```
    pub fn true_jacobian(
        &self,
        gates: &[&str],
        parameters: &[&str],
    ) -> Result<DMatrix<f64>, String> {
        for p in parameters {
            if !Truth::PARAMETERS.contains(p) {
                return Err(format!(
                    "unknown parameter {p:?} (known: {:?})",
                    Truth::PARAMETERS
                ));
            }
        }
        let mut j = DMatrix::zeros(parameters.len(), gates.len());
        for (col, gate) in gates.iter().enumerate() {
            let v0 = *self
                .voltages_mv
                .get(*gate)
                .ok_or_else(|| format!("unknown gate {gate:?}"))?;
            let mut v = self.voltages_mv.clone();
            v.insert(gate.to_string(), v0 + JACOBIAN_STEP_MV);
            let plus = self.truth_at(&v);
            v.insert(gate.to_string(), v0 - JACOBIAN_STEP_MV);
            let minus = self.truth_at(&v);
            for (row, p) in parameters.iter().enumerate() {
                let (a, b) = (
                    plus.get(p).unwrap_or(f64::NAN),
                    minus.get(p).unwrap_or(f64::NAN),
                );
                j[(row, col)] = (a - b) / (2.0 * JACOBIAN_STEP_MV);
            }
        }
        Ok(j)
    }
}
