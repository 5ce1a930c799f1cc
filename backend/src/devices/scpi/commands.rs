//! What goes over the wire: the SCPI command strings (mV in, volts out),
//! which numbers from the instrument are believed ([`scpi_number`]), and the
//! plan of a ramp in equal increments ([`plan_ramp`]).

use std::collections::BTreeMap;

use super::config::ScpiProfile;

/// Magnitude from which a SCPI number is one of the standard's special
/// values: `9.91E37` (NaN) and `±9.9E37` (±infinity, overflow).
pub const SCPI_SPECIAL_MAGNITUDE: f64 = 9.9e37;

/// A number an instrument answered, if it is a real measurement: it parses,
/// is finite and is not one of SCPI's special values (NaN `9.91E37`,
/// overflow `±9.9E37`); e.g. `" -0.75 "` is −0.75, `9.91E37`, `-9.9e37`,
/// `nan` and `1 V` are not numbers (tests: `scpi::tests`).
pub fn scpi_number(answer: &str) -> Option<f64> {
    let v: f64 = answer.trim().parse().ok()?;
    (v.is_finite() && v.abs() < SCPI_SPECIAL_MAGNITUDE).then_some(v)
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
