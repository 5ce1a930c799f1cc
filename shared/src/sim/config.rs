//! [`DeviceConfig`]: every physical constant of the simulated double dot.
//!
//! All gate voltages are mV. The models are expanded about
//! [`DeviceConfig::reference_mv`] (by default the start point of
//! [`crate::sim::default_gates`]); `d_g = V_g − reference_g` below.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::gates::default_gates;
use crate::config_error::ConfigError;
use crate::detmath::STEEPEST_SECH2_OFFSET;

/// A second-order term `coefficient · d_a · d_b` of a model (for `a == b`
/// this is `coefficient · d_a²`). Unit: model unit per mV².
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QuadraticTerm {
    /// First gate.
    pub a: String,
    /// Second gate (may equal `a`).
    pub b: String,
    /// Coefficient, model unit per mV².
    pub coefficient_per_mv2: f64,
}

impl QuadraticTerm {
    /// `coefficient · d_a · d_b` with `d` the deviations from the reference, mV.
    pub(crate) fn eval(&self, d: &BTreeMap<String, f64>) -> f64 {
        let da = d.get(&self.a).copied().unwrap_or(0.0);
        let db = d.get(&self.b).copied().unwrap_or(0.0);
        self.coefficient_per_mv2 * da * db
    }
}

fn term(a: &str, b: &str, c: f64) -> QuadraticTerm {
    QuadraticTerm {
        a: a.into(),
        b: b.into(),
        coefficient_per_mv2: c,
    }
}

fn map(entries: &[(&str, f64)]) -> BTreeMap<String, f64> {
    entries.iter().map(|(k, v)| (k.to_string(), *v)).collect()
}

/// A positive quantity that depends exponentially on the gates:
/// `value = at_reference · exp(Σ_g linear_g·d_g + Σ quadratic terms)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpModel {
    /// Value at the reference voltages (unit of the quantity, > 0).
    pub at_reference: f64,
    /// `∂ ln(value) / ∂V_g` at the reference, 1/mV. Missing gates: 0.
    pub linear_per_mv: BTreeMap<String, f64>,
    /// Cross and square terms in the exponent, 1/mV².
    pub quadratic_per_mv2: Vec<QuadraticTerm>,
}

impl ExpModel {
    /// `ln(value)` at deviations `d` (mV) from the reference.
    pub(crate) fn ln_value(&self, d: &BTreeMap<String, f64>) -> f64 {
        let lin: f64 = self
            .linear_per_mv
            .iter()
            .map(|(g, c)| c * d.get(g).copied().unwrap_or(0.0))
            .sum();
        let quad: f64 = self.quadratic_per_mv2.iter().map(|t| t.eval(d)).sum();
        crate::detmath::ln(self.at_reference) + lin + quad
    }
}

/// Capacitive crosstalk of every gate onto the two lead-transition lines.
///
/// `μ_A = Σ_g line_a_per_mv_g·d_g + Σ line_a_quadratic`, in mV on RFA (same
/// for B on RFB). The linear part is the *nominal* (calibrated) matrix used
/// by [`DeviceConfig::nominal_compensation`]; the quadratic part is the
/// device's nonlinearity that the nominal virtual gates miss.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Crosstalk {
    /// `∂μ_A/∂V_g`, mV(RFA) per mV.
    pub line_a_per_mv: BTreeMap<String, f64>,
    /// `∂μ_B/∂V_g`, mV(RFB) per mV.
    pub line_b_per_mv: BTreeMap<String, f64>,
    /// Second-order terms of μ_A, mV per mV².
    pub line_a_quadratic: Vec<QuadraticTerm>,
    /// Second-order terms of μ_B, mV per mV².
    pub line_b_quadratic: Vec<QuadraticTerm>,
}

/// The sensing dot: a comb of thermally broadened Coulomb peaks
/// `G(u) = background + Σ_k h_k·sech²((u − u_k)/γ)` in the dot's potential
/// `u = Σ_g lever_g·d_g` (in "SD1-equivalent mV"), `u_k = peak_offset + k·spacing`,
/// `h_k = peak_heights[k mod len]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensingDotConfig {
    /// Gate swept by default and reported by [`crate::sim::Truth::sd_flank_mv`].
    pub gate: String,
    /// Default sweep half-width around the gate's present voltage, mV.
    pub sweep_half_range_mv: f64,
    /// Default number of sweep points.
    pub sweep_points: usize,
    /// `∂u/∂V_g` (dimensionless). Must be non-zero for [`Self::gate`].
    pub lever_per_mv: BTreeMap<String, f64>,
    /// Peak spacing in u, mV.
    pub peak_spacing_mv: f64,
    /// Peak width γ in u, mV.
    pub peak_width_mv: f64,
    /// Position of peak 0 in u, mV. The default puts u = 0 (the reference
    /// voltages) on the steepest rising flank of peak 0.
    pub peak_offset_mv: f64,
    /// Peak heights, a.u., repeated cyclically; peak 0 uses the first entry.
    pub peak_heights: Vec<f64>,
    /// Constant sensor signal, a.u.
    pub background: f64,
    /// Shift of u when one electron moves between the dots or to a lead, mV.
    /// The step seen in a scan is `G'(u)·charge_shift_mv`.
    pub charge_shift_mv: f64,
    /// Crosstalk of the fast RF sweep onto u, mV(u) per mV(RF): the linear
    /// background of the w and chemical-potential scans.
    pub rf_lever: f64,
}

/// White noise, drift and charge jumps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseConfig {
    /// White noise on sensing-dot sweeps, a.u. (standard deviation per point).
    pub white_sd: f64,
    /// White noise on chemical-potential scans, a.u.
    pub white_mu: f64,
    /// White noise on transition-width (detuning) scans, a.u.
    pub white_w: f64,
    /// White noise on load curves, a.u.
    pub white_tsr: f64,
    /// Correlation time of all Ornstein–Uhlenbeck drifts, s.
    pub drift_time_s: f64,
    /// Stationary std of the drift of each transition line, mV.
    pub drift_mu_mv: f64,
    /// Stationary std of the drift of the sensing-dot potential u, mV.
    pub drift_sd_mv: f64,
    /// Stationary std of the drift of the sensor signal offset, a.u.
    pub drift_signal: f64,
    /// Rate of charge jumps (background charges rearranging), 1/s of lab time.
    pub charge_jump_rate_per_s: f64,
    /// Std of the persistent shift of u caused by one charge jump, mV.
    pub charge_jump_sd_mv: f64,
    /// Slow drift of the tunnel coupling and the lead rate (so of w and
    /// t_sr) over lab hours.
    #[serde(default)]
    pub slow: SlowDrift,
}

/// Slow drift of the inter-dot tunnel coupling t_c and the lead rate Γ,
/// the quantities behind w and t_sr: an Ornstein–Uhlenbeck process on
/// `ln t_c` and on `ln Γ` (hour-scale correlation time), rare jumps of
/// both (two-level fluctuators, charge rearrangements near the barriers),
/// and a day-scale trend of `ln Γ`. With the defaults an untouched tuned
/// point typically leaves a ±10 % band of t_sr or w within one to a few
/// lab hours (`shared/tests/slow_drift.rs`; docs/simulator-drift.md).
/// All zero: no slow drift (and no random numbers drawn for it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlowDrift {
    /// Correlation time of the drift of `ln t_c` and `ln Γ`, s (default 4 h).
    pub time_s: f64,
    /// Stationary std of `ln t_c` (relative drift of t_c; default 0.06).
    pub tunnel_coupling_rel: f64,
    /// Stationary std of `ln Γ` (relative drift of Γ, so of t_sr; default 0.1).
    pub lead_rate_rel: f64,
    /// Rate of jumps of `ln t_c` and `ln Γ`, 1/s of lab time (default one
    /// per 8 h).
    pub jump_rate_per_s: f64,
    /// Std of one jump of `ln t_c` and of `ln Γ` (default 0.05).
    pub jump_rel: f64,
    /// Linear trend of `ln Γ`, per hour of lab time (default 0.01: t_sr
    /// shortens by about 1 % per hour, ~20 % over a day).
    pub lead_rate_trend_per_hour: f64,
}

impl Default for SlowDrift {
    fn default() -> Self {
        Self {
            time_s: 4.0 * 3600.0,
            tunnel_coupling_rel: 0.06,
            lead_rate_rel: 0.1,
            jump_rate_per_s: 1.0 / (8.0 * 3600.0),
            jump_rel: 0.05,
            lead_rate_trend_per_hour: 0.01,
        }
    }
}

impl SlowDrift {
    /// No slow drift at all.
    ///
    /// ```
    /// assert!(spintune::sim::SlowDrift::none().is_none());
    /// assert!(!spintune::sim::SlowDrift::default().is_none());
    /// ```
    pub fn none() -> Self {
        Self {
            time_s: 4.0 * 3600.0,
            tunnel_coupling_rel: 0.0,
            lead_rate_rel: 0.0,
            jump_rate_per_s: 0.0,
            jump_rel: 0.0,
            lead_rate_trend_per_hour: 0.0,
        }
    }

    /// Whether every amplitude is zero (nothing drifts).
    pub fn is_none(&self) -> bool {
        self.tunnel_coupling_rel == 0.0
            && self.lead_rate_rel == 0.0
            && (self.jump_rate_per_s == 0.0 || self.jump_rel == 0.0)
            && self.lead_rate_trend_per_hour == 0.0
    }
}

/// Scan grids and scan-quality constants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanSettings {
    /// Detuning scan (w) half-range, mV.
    pub detuning_half_range_mv: f64,
    /// Detuning scan points.
    pub detuning_points: usize,
    /// Load curve wait-time start, ns.
    pub load_from_ns: f64,
    /// Load curve wait-time end, ns.
    pub load_to_ns: f64,
    /// Load curve points.
    pub load_points: usize,
    /// Reload visibility (fraction of a full charge step seen in the load curve).
    pub load_visibility: f64,
    /// Chemical-potential scan half-range on RFA/RFB, mV.
    pub mu_half_range_mv: f64,
    /// Chemical-potential scan points (per line).
    pub mu_points: usize,
    /// Scale of the line offsets at which the w / t_sr scans lose their
    /// signal: step height × `exp(−(offset/scale)²)`, mV.
    pub mu_tolerance_mv: f64,
    /// Apparent reload time `t_sr·(1 + c·μ_B²)` when line B is off by μ_B: c, 1/mV².
    pub reload_detuning_per_mv2: f64,
}

/// Lab time charged per operation, s.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabDurations {
    /// Setting voltages (any number of gates), s.
    pub set_voltages_s: f64,
    /// 1-D sensing-dot sweep, s (paper: 17 s).
    pub sd_1d_s: f64,
    /// 2-D sensing-dot sweep, s (paper: 100 s). Not requested by protocol v1;
    /// kept so lab-time budgets can account for it.
    pub sd_2d_s: f64,
    /// Chemical-potential scan (both lines), s (paper: 38 s).
    pub chemical_potential_s: f64,
    /// Transition-width scan, s (paper: 28 s).
    pub transition_width_s: f64,
    /// Load curve, s (paper: 5 s).
    pub reload_time_s: f64,
}

/// Every physical constant of the simulated device. Voltages mV, energies µeV.
///
/// `Default` is the documented default device: at the start point of
/// [`crate::sim::default_gates`] it has t_sr ≈ 45 ns and w ≈ 210 µV, with the
/// sensing dot on the steepest flank of its highest peak and both transition
/// lines at 0 mV.
///
/// ```
/// let config = spintune::sim::DeviceConfig::default();
/// assert!(config.validate().is_ok());
/// let json = serde_json::to_string(&config).unwrap();
/// let back: spintune::sim::DeviceConfig = serde_json::from_str(&json).unwrap();
/// assert_eq!(back, config);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DeviceConfig {
    /// Expansion point of all models, mV per gate. Must cover every gate of the device.
    pub reference_mv: BTreeMap<String, f64>,
    /// Lever arm α of the detuning axis, µeV per µV (= eV/V).
    pub lever_arm_uev_per_uv: f64,
    /// Electron temperature, mK.
    pub electron_temperature_mk: f64,
    /// Inter-dot tunnel coupling t_c, µeV.
    pub tunnel_coupling_uev: ExpModel,
    /// Lead tunnel rate Γ (t_sr = 1/Γ), 1/ns.
    pub lead_rate_per_ns: ExpModel,
    /// Crosstalk onto the transition lines.
    pub crosstalk: Crosstalk,
    /// The sensing dot.
    pub sensing_dot: SensingDotConfig,
    /// Noise.
    pub noise: NoiseConfig,
    /// Scan settings.
    pub scans: ScanSettings,
    /// Lab time per operation.
    pub durations: LabDurations,
}

/// Boltzmann constant, µeV/mK.
pub const K_B_UEV_PER_MK: f64 = 8.617_333_262e-2;

impl Default for DeviceConfig {
    fn default() -> Self {
        let reference_mv = default_gates()
            .into_iter()
            .map(|g| (g.name, g.initial_mv))
            .collect();
        let sd_width_mv = 1.0;
        DeviceConfig {
            reference_mv,
            lever_arm_uev_per_uv: 0.12,
            electron_temperature_mk: 100.0,
            tunnel_coupling_uev: ExpModel {
                at_reference: 10.5,
                linear_per_mv: map(&[
                    ("N", 0.009),
                    ("SA", 0.015),
                    ("SB", 0.012),
                    ("T", -0.006),
                    ("PA", 0.002),
                    ("PB", 0.002),
                ]),
                quadratic_per_mv2: vec![
                    term("N", "N", -1.2e-4),
                    term("SB", "SB", 1.0e-4),
                    term("SB", "T", 1.0e-4),
                    term("N", "SA", -1.0e-4),
                    term("T", "T", 0.6e-4),
                ],
            },
            lead_rate_per_ns: ExpModel {
                at_reference: 1.0 / 45.0,
                linear_per_mv: map(&[
                    ("N", 0.003),
                    ("SA", -0.002),
                    ("SB", 0.022),
                    ("T", 0.018),
                    ("PB", 0.004),
                ]),
                quadratic_per_mv2: vec![term("SB", "T", 5e-5), term("N", "SB", 2e-5)],
            },
            crosstalk: Crosstalk {
                line_a_per_mv: map(&[
                    ("N", 0.35),
                    ("T", 0.15),
                    ("SA", 0.45),
                    ("SB", 0.12),
                    ("PA", 0.9),
                    ("PB", 0.25),
                    ("SD1", 0.02),
                    ("SP", 0.01),
                    ("SD2", 0.01),
                    ("RFA", -1.0),
                    ("RFB", -0.2),
                ]),
                line_b_per_mv: map(&[
                    ("N", 0.18),
                    ("T", 0.4),
                    ("SA", 0.1),
                    ("SB", 0.42),
                    ("PA", 0.22),
                    ("PB", 0.85),
                    ("SD1", 0.01),
                    ("SP", 0.01),
                    ("SD2", 0.03),
                    ("RFA", -0.2),
                    ("RFB", -1.0),
                ]),
                line_a_quadratic: vec![
                    term("N", "N", 4e-4),
                    term("SA", "PA", 3e-4),
                    term("T", "SB", -2e-4),
                ],
                line_b_quadratic: vec![
                    term("SB", "SB", 4e-4),
                    term("T", "PB", 3e-4),
                    term("N", "SA", -2e-4),
                ],
            },
            sensing_dot: SensingDotConfig {
                gate: "SD1".into(),
                sweep_half_range_mv: 10.0,
                sweep_points: 201,
                lever_per_mv: map(&[
                    ("SD1", 1.0),
                    ("SP", 0.6),
                    ("SD2", 0.9),
                    ("N", 0.04),
                    ("T", 0.05),
                    ("SA", 0.06),
                    ("SB", 0.08),
                    ("PA", 0.07),
                    ("PB", 0.1),
                    ("RFA", 0.02),
                    ("RFB", 0.03),
                ]),
                peak_spacing_mv: 8.0,
                peak_width_mv: sd_width_mv,
                peak_offset_mv: STEEPEST_SECH2_OFFSET * sd_width_mv,
                peak_heights: vec![4.0, 3.3, 2.9, 3.6, 3.1],
                background: 0.5,
                charge_shift_mv: 0.33,
                rf_lever: 0.05,
            },
            noise: NoiseConfig {
                white_sd: 0.05,
                white_mu: 0.05,
                white_w: 0.01,
                white_tsr: 0.006,
                drift_time_s: 600.0,
                drift_mu_mv: 0.03,
                drift_sd_mv: 0.01,
                drift_signal: 0.005,
                charge_jump_rate_per_s: 3e-4,
                charge_jump_sd_mv: 1.0,
                slow: SlowDrift::default(),
            },
            scans: ScanSettings {
                detuning_half_range_mv: 2.0,
                detuning_points: 100,
                load_from_ns: 0.0,
                load_to_ns: 500.0,
                load_points: 101,
                load_visibility: 0.8,
                mu_half_range_mv: 4.0,
                mu_points: 201,
                mu_tolerance_mv: 1.5,
                reload_detuning_per_mv2: 0.1,
            },
            durations: LabDurations {
                set_voltages_s: 0.5,
                sd_1d_s: 17.0,
                sd_2d_s: 100.0,
                chemical_potential_s: 38.0,
                transition_width_s: 28.0,
                reload_time_s: 5.0,
            },
        }
    }
}

/// Largest magnitude of any number of the device model, in its unit
/// (bounded by construction: far from overflow in the model's exponentials
/// and products).
pub const MAX_MAGNITUDE: f64 = 1e6;

fn positive(name: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 && v <= MAX_MAGNITUDE {
        Ok(())
    } else {
        Err(ConfigError::new(
            name,
            format!("must be a finite number > 0, at most {MAX_MAGNITUDE:e}, got {v}"),
        ))
    }
}

fn non_negative(name: &str, v: f64) -> Result<(), ConfigError> {
    if (0.0..=MAX_MAGNITUDE).contains(&v) {
        Ok(())
    } else {
        Err(ConfigError::new(
            name,
            format!("must be a finite number ≥ 0, at most {MAX_MAGNITUDE:e}, got {v}"),
        ))
    }
}

fn finite(name: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v.abs() <= MAX_MAGNITUDE {
        Ok(())
    } else {
        Err(ConfigError::new(
            name,
            format!("must be a finite number within ±{MAX_MAGNITUDE:e}, got {v}"),
        ))
    }
}

fn finite_map(name: &str, m: &BTreeMap<String, f64>) -> Result<(), ConfigError> {
    for (g, v) in m {
        finite(&format!("{name}.{g}"), *v)?;
    }
    Ok(())
}

fn finite_terms(name: &str, terms: &[QuadraticTerm]) -> Result<(), ConfigError> {
    for (i, t) in terms.iter().enumerate() {
        finite(
            &format!("{name}[{i}].coefficient_per_mv2"),
            t.coefficient_per_mv2,
        )?;
    }
    Ok(())
}

fn points(name: &str, n: usize) -> Result<(), ConfigError> {
    if (10..=100_000).contains(&n) {
        Ok(())
    } else {
        Err(ConfigError::new(
            name,
            format!("must be in 10..=100000, got {n}"),
        ))
    }
}

impl DeviceConfig {
    /// `Err` naming the first bad field (non-finite, out-of-range, empty);
    /// the field path is relative to the device config (a
    /// [`crate::driver::SimulationConfig`] prefixes it with `device`).
    ///
    /// ```
    /// let mut c = spintune::sim::DeviceConfig::default();
    /// c.electron_temperature_mk = -1.0;
    /// let e = c.validate().unwrap_err();
    /// assert_eq!(e.field, "electron_temperature_mk");
    /// assert!(e.to_string().contains("got -1"));
    /// ```
    pub fn validate(&self) -> Result<(), ConfigError> {
        finite_map("reference_mv", &self.reference_mv)?;
        positive("lever_arm_uev_per_uv", self.lever_arm_uev_per_uv)?;
        positive("electron_temperature_mk", self.electron_temperature_mk)?;
        for (name, m) in [
            ("tunnel_coupling_uev", &self.tunnel_coupling_uev),
            ("lead_rate_per_ns", &self.lead_rate_per_ns),
        ] {
            positive(&format!("{name}.at_reference"), m.at_reference)?;
            finite_map(&format!("{name}.linear_per_mv"), &m.linear_per_mv)?;
            finite_terms(&format!("{name}.quadratic_per_mv2"), &m.quadratic_per_mv2)?;
        }
        let x = &self.crosstalk;
        finite_map("crosstalk.line_a_per_mv", &x.line_a_per_mv)?;
        finite_map("crosstalk.line_b_per_mv", &x.line_b_per_mv)?;
        finite_terms("crosstalk.line_a_quadratic", &x.line_a_quadratic)?;
        finite_terms("crosstalk.line_b_quadratic", &x.line_b_quadratic)?;
        let sd = &self.sensing_dot;
        positive("sensing_dot.sweep_half_range_mv", sd.sweep_half_range_mv)?;
        points("sensing_dot.sweep_points", sd.sweep_points)?;
        finite_map("sensing_dot.lever_per_mv", &sd.lever_per_mv)?;
        match sd.lever_per_mv.get(&sd.gate) {
            Some(l) if *l != 0.0 => {}
            _ => {
                return Err(ConfigError::new(
                    "sensing_dot.lever_per_mv",
                    format!(
                        "must have a non-zero entry for sensing_dot.gate {:?}",
                        sd.gate
                    ),
                ))
            }
        }
        positive("sensing_dot.peak_spacing_mv", sd.peak_spacing_mv)?;
        positive("sensing_dot.peak_width_mv", sd.peak_width_mv)?;
        finite("sensing_dot.peak_offset_mv", sd.peak_offset_mv)?;
        if sd.peak_heights.is_empty() {
            return Err(ConfigError::new(
                "sensing_dot.peak_heights",
                "must not be empty",
            ));
        }
        for (i, h) in sd.peak_heights.iter().enumerate() {
            positive(&format!("sensing_dot.peak_heights[{i}]"), *h)?;
        }
        finite("sensing_dot.background", sd.background)?;
        positive("sensing_dot.charge_shift_mv", sd.charge_shift_mv)?;
        finite("sensing_dot.rf_lever", sd.rf_lever)?;
        let n = &self.noise;
        for (name, v) in [
            ("noise.white_sd", n.white_sd),
            ("noise.white_mu", n.white_mu),
            ("noise.white_w", n.white_w),
            ("noise.white_tsr", n.white_tsr),
            ("noise.drift_mu_mv", n.drift_mu_mv),
            ("noise.drift_sd_mv", n.drift_sd_mv),
            ("noise.drift_signal", n.drift_signal),
            ("noise.charge_jump_rate_per_s", n.charge_jump_rate_per_s),
            ("noise.charge_jump_sd_mv", n.charge_jump_sd_mv),
        ] {
            non_negative(name, v)?;
        }
        positive("noise.drift_time_s", n.drift_time_s)?;
        let sl = &n.slow;
        positive("noise.slow.time_s", sl.time_s)?;
        for (name, v) in [
            ("noise.slow.tunnel_coupling_rel", sl.tunnel_coupling_rel),
            ("noise.slow.lead_rate_rel", sl.lead_rate_rel),
            ("noise.slow.jump_rate_per_s", sl.jump_rate_per_s),
            ("noise.slow.jump_rel", sl.jump_rel),
        ] {
            non_negative(name, v)?;
            if v > 10.0 {
                return Err(ConfigError::new(
                    name,
                    format!("must be at most 10, got {v}"),
                ));
            }
        }
        finite(
            "noise.slow.lead_rate_trend_per_hour",
            sl.lead_rate_trend_per_hour,
        )?;
        if sl.lead_rate_trend_per_hour.abs() > 1.0 {
            return Err(ConfigError::new(
                "noise.slow.lead_rate_trend_per_hour",
                "must be within ±1 per hour",
            ));
        }
        let s = &self.scans;
        positive("scans.detuning_half_range_mv", s.detuning_half_range_mv)?;
        points("scans.detuning_points", s.detuning_points)?;
        non_negative("scans.load_from_ns", s.load_from_ns)?;
        if !(s.load_to_ns.is_finite()
            && s.load_to_ns > s.load_from_ns
            && s.load_to_ns <= MAX_MAGNITUDE)
        {
            return Err(ConfigError::new(
                "scans.load_to_ns",
                format!(
                    "must be finite, > scans.load_from_ns ({} ns) and at most 1e6 ns, got {}",
                    s.load_from_ns, s.load_to_ns
                ),
            ));
        }
        points("scans.load_points", s.load_points)?;
        if !(s.load_visibility > 0.0 && s.load_visibility <= 1.0) {
            return Err(ConfigError::new(
                "scans.load_visibility",
                format!("must be in (0, 1], got {}", s.load_visibility),
            ));
        }
        positive("scans.mu_half_range_mv", s.mu_half_range_mv)?;
        points("scans.mu_points", s.mu_points)?;
        positive("scans.mu_tolerance_mv", s.mu_tolerance_mv)?;
        non_negative("scans.reload_detuning_per_mv2", s.reload_detuning_per_mv2)?;
        let d = &self.durations;
        for (name, v) in [
            ("durations.set_voltages_s", d.set_voltages_s),
            ("durations.sd_1d_s", d.sd_1d_s),
            ("durations.sd_2d_s", d.sd_2d_s),
            ("durations.chemical_potential_s", d.chemical_potential_s),
            ("durations.transition_width_s", d.transition_width_s),
            ("durations.reload_time_s", d.reload_time_s),
        ] {
            non_negative(name, v)?;
        }
        Ok(())
    }

    /// The nominal virtual-gate matrix `M` (rows: `plungers`, columns:
    /// `tuning`, dimensionless mV/mV): moving the tuning gates by `Δv_t` and
    /// the plungers by `Δv_p = M·Δv_t` keeps both transition lines fixed to
    /// first order in the *nominal* linear crosstalk
    /// ([`Crosstalk::line_a_per_mv`], [`Crosstalk::line_b_per_mv`]).
    ///
    /// `M = −K_p⁺·K_t` with `K` the 2×n crosstalk rows and `K_p⁺` the
    /// minimum-norm pseudo-inverse `K_pᵀ(K_p K_pᵀ)⁻¹`. The device's quadratic
    /// crosstalk terms make this correction imperfect away from the
    /// reference. Unknown gate names have zero crosstalk; if the plungers
    /// cannot move both lines independently the matrix is all zeros.
    ///
    /// ```
    /// let c = spintune::sim::DeviceConfig::default();
    /// let m = c.nominal_compensation(&["N", "SA", "SB", "T"], &["PA", "PB"]);
    /// assert_eq!((m.len(), m[0].len()), (2, 4));
    /// // Compensating a +1 mV step on N leaves μ_A unchanged to first order:
    /// let k = &c.crosstalk.line_a_per_mv;
    /// let dmu = k["N"] + k["PA"] * m[0][0] + k["PB"] * m[1][0];
    /// assert!(dmu.abs() < 1e-12);
    /// ```
    pub fn nominal_compensation(&self, tuning: &[&str], plungers: &[&str]) -> Vec<Vec<f64>> {
        let k = |row: &BTreeMap<String, f64>, g: &str| row.get(g).copied().unwrap_or(0.0);
        let (ra, rb) = (&self.crosstalk.line_a_per_mv, &self.crosstalk.line_b_per_mv);
        let kp: Vec<[f64; 2]> = plungers.iter().map(|p| [k(ra, p), k(rb, p)]).collect();
        // G = K_p K_pᵀ (2×2) and its inverse.
        let mut g = [[0.0; 2]; 2];
        for col in &kp {
            for i in 0..2 {
                for j in 0..2 {
                    g[i][j] += col[i] * col[j];
                }
            }
        }
        let det = g[0][0] * g[1][1] - g[0][1] * g[1][0];
        let scale = (g[0][0] * g[1][1]).abs().max(f64::MIN_POSITIVE);
        let mut m = vec![vec![0.0; tuning.len()]; plungers.len()];
        if det.is_nan() || det.abs() <= 1e-12 * scale {
            return m;
        }
        let inv = [
            [g[1][1] / det, -g[0][1] / det],
            [-g[1][0] / det, g[0][0] / det],
        ];
        for (j, t) in tuning.iter().enumerate() {
            let kt = [k(ra, t), k(rb, t)];
            // y = G⁻¹ K_t[:, j]
            let y = [
                inv[0][0] * kt[0] + inv[0][1] * kt[1],
                inv[1][0] * kt[0] + inv[1][1] * kt[1],
            ];
            for (p, col) in kp.iter().enumerate() {
                m[p][j] = -(col[0] * y[0] + col[1] * y[1]);
            }
        }
        m
    }
}
