//! The noiseless physics of the double dot, as pure functions of the gate
//! voltages (mV). `d` always denotes deviations from
//! [`DeviceConfig::reference_mv`].

use std::collections::BTreeMap;

use super::config::{DeviceConfig, K_B_UEV_PER_MK};
use crate::detmath::{exp, sech2, tanh, MAX_SECH2_SLOPE, STEEPEST_SECH2_OFFSET};
use crate::fit::tanh::fit_tanh_step;

/// Deviations `V_g − reference_g` (mV) of every gate that has a reference.
pub(crate) fn deviations(
    config: &DeviceConfig,
    voltages_mv: &BTreeMap<String, f64>,
) -> BTreeMap<String, f64> {
    voltages_mv
        .iter()
        .filter_map(|(g, v)| config.reference_mv.get(g).map(|r| (g.clone(), v - r)))
        .collect()
}

/// `k_B·T`, µeV.
pub(crate) fn kt_uev(config: &DeviceConfig) -> f64 {
    K_B_UEV_PER_MK * config.electron_temperature_mk
}

/// Inter-dot tunnel coupling t_c, µeV.
pub(crate) fn tunnel_coupling_uev(config: &DeviceConfig, d: &BTreeMap<String, f64>) -> f64 {
    exp(config.tunnel_coupling_uev.ln_value(d))
}

/// Lead tunnel rate Γ, 1/ns.
pub(crate) fn lead_rate_per_ns(config: &DeviceConfig, d: &BTreeMap<String, f64>) -> f64 {
    exp(config.lead_rate_per_ns.ln_value(d))
}

/// Uncalibrated positions of the two transition lines, mV on RFA / RFB.
pub(crate) fn raw_lines_mv(config: &DeviceConfig, d: &BTreeMap<String, f64>) -> [f64; 2] {
    let x = &config.crosstalk;
    let line = |lin: &BTreeMap<String, f64>, quad: &[super::config::QuadraticTerm]| {
        lin.iter()
            .map(|(g, c)| c * d.get(g).copied().unwrap_or(0.0))
            .sum::<f64>()
            + quad.iter().map(|t| t.eval(d)).sum::<f64>()
    };
    [
        line(&x.line_a_per_mv, &x.line_a_quadratic),
        line(&x.line_b_per_mv, &x.line_b_quadratic),
    ]
}

/// Sensing-dot potential u, mV (SD1-equivalent), without drift.
pub(crate) fn sd_potential_mv(config: &DeviceConfig, d: &BTreeMap<String, f64>) -> f64 {
    config
        .sensing_dot
        .lever_per_mv
        .iter()
        .map(|(g, l)| l * d.get(g).copied().unwrap_or(0.0))
        .sum()
}

/// Sensor signal `G(u)` and its slope `G'(u)` (a.u., a.u./mV).
pub(crate) fn sd_signal(config: &DeviceConfig, u: f64) -> (f64, f64) {
    let sd = &config.sensing_dot;
    let k_near = ((u - sd.peak_offset_mv) / sd.peak_spacing_mv).round() as i64;
    let (mut g, mut dg) = (sd.background, 0.0);
    for k in k_near - 4..=k_near + 4 {
        let h = peak_height(config, k);
        let z = (u - sd.peak_offset_mv - k as f64 * sd.peak_spacing_mv) / sd.peak_width_mv;
        let s = sech2(z);
        g += h * s;
        dg += -2.0 * h * s * tanh(z) / sd.peak_width_mv;
    }
    (g, dg)
}

/// Height of peak `k`, a.u.
pub(crate) fn peak_height(config: &DeviceConfig, k: i64) -> f64 {
    let h = &config.sensing_dot.peak_heights;
    h[k.rem_euclid(h.len() as i64) as usize]
}

/// Largest sensor slope anywhere, a.u./mV (steepest flank of the highest peak).
pub(crate) fn sd_max_slope(config: &DeviceConfig) -> f64 {
    let sd = &config.sensing_dot;
    let h_max = sd.peak_heights.iter().copied().fold(0.0, f64::max);
    h_max * MAX_SECH2_SLOPE / sd.peak_width_mv
}

/// Steepest lower-voltage flank of the highest peak whose centre lies in the
/// default sweep window around the sensing gate's present voltage, in mV of
/// that gate (nearest peak if none lies inside).
pub(crate) fn sd_flank_mv(config: &DeviceConfig, gate_mv: f64, u: f64) -> f64 {
    let sd = &config.sensing_dot;
    let lever = sd.lever_per_mv[&sd.gate];
    let r = sd.sweep_half_range_mv;
    // Gate voltage at which peak k is centred.
    let centre = |k: i64| gate_mv + (sd.peak_offset_mv + k as f64 * sd.peak_spacing_mv - u) / lever;
    let k_near = ((u - sd.peak_offset_mv) / sd.peak_spacing_mv).round() as i64;
    let span = (r * lever.abs() / sd.peak_spacing_mv).ceil() as i64 + 1;
    let best = (k_near - span..=k_near + span)
        .filter(|&k| (centre(k) - gate_mv).abs() <= r)
        .max_by(|&a, &b| {
            peak_height(config, a)
                .total_cmp(&peak_height(config, b))
                .then(
                    (centre(b) - gate_mv)
                        .abs()
                        .total_cmp(&(centre(a) - gate_mv).abs()),
                )
        })
        .unwrap_or(k_near);
    centre(best) - STEEPEST_SECH2_OFFSET * sd.peak_width_mv / lever.abs()
}

/// Excess charge of the two-level system at detuning `x_mv` from the
/// inter-dot transition: `½(1 − ε/Ω·tanh(Ω/2kT))`, `ε = α·x`, `Ω = √(ε²+4t_c²)`.
pub(crate) fn excess_charge(config: &DeviceConfig, t_c_uev: f64, x_mv: f64) -> f64 {
    let eps = config.lever_arm_uev_per_uv * 1000.0 * x_mv;
    let omega = (eps * eps + 4.0 * t_c_uev * t_c_uev).sqrt();
    0.5 * (1.0 - eps / omega * tanh(omega / (2.0 * kt_uev(config))))
}

/// Occupation of a lead transition at `x_mv` from the line (Fermi function):
/// `½(1 + tanh(α·x/2kT))`.
pub(crate) fn lead_occupation(config: &DeviceConfig, x_mv: f64) -> f64 {
    let eps = config.lever_arm_uev_per_uv * 1000.0 * x_mv;
    0.5 * (1.0 + tanh(eps / (2.0 * kt_uev(config))))
}

/// The detuning grid of the w scan, mV.
pub(crate) fn detuning_grid(config: &DeviceConfig) -> Vec<f64> {
    grid(
        -config.scans.detuning_half_range_mv,
        config.scans.detuning_half_range_mv,
        config.scans.detuning_points,
    )
}

/// `n` equally spaced points from `a` to `b` inclusive.
pub(crate) fn grid(a: f64, b: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| a + (b - a) * i as f64 / (n - 1) as f64)
        .collect()
}

/// The transition width w, µV: by definition the width parameter of the
/// tanh-step fit ([`crate::fit::tanh::fit_tanh_step`]) to the noiseless
/// excess-charge lineshape on the centred detuning grid, × 1000. A noiseless,
/// centred scan therefore yields exactly this value. NaN if that fit fails
/// (not seen for any t_c in 0.01–1000 µeV at the default settings).
pub(crate) fn transition_width_uv(config: &DeviceConfig, t_c_uev: f64) -> f64 {
    let x = detuning_grid(config);
    let y: Vec<f64> = x
        .iter()
        .map(|&x| excess_charge(config, t_c_uev, x))
        .collect();
    fit_tanh_step(&x, &y)
        .map(|f| 1000.0 * f.width)
        .unwrap_or(f64::NAN)
}
