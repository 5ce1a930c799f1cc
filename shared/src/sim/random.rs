//! Plausible devices: a documented, seeded distribution of
//! [`DeviceConfig`]s around a base device (the benchmark's
//! `--random-devices`).
//!
//! Every factor is drawn independently from a ChaCha8 stream seeded by the
//! device seed (deterministic on every target):
//!
//! | what | factor |
//! |---|---|
//! | lever arm `lever_arm_uev_per_uv`, every linear gate gradient of `t_c` and `Γ`, every linear crosstalk element onto the transition lines (RF gates excluded), every sensing-dot lever except the swept gate's | uniform ×[0.7, 1.3] |
//! | every quadratic (curvature) term of `t_c`, `Γ` and the crosstalk | uniform ×[0, 3] |
//! | white noise of each scan kind | log-uniform ×[0.5, 2] |
//! | drift amplitudes (lines, sensing dot, signal) | log-uniform ×[0.5, 2] |
//! | charge-jump rate | log-uniform ×[0.5, 2] |
//! | slow drift of t_c and Γ: amplitudes, jump rate, trend of Γ | log-uniform ×[0.5, 2] |
//!
//! The values at the reference (t_sr = 45 ns, t_c) and the gates are those
//! of the base. A drawn device whose benchmark targets cannot be reached
//! within the gate limits is rejected by [`targets_reachable`].

use std::collections::BTreeMap;

use nalgebra::DVector;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{DeviceConfig, SimulatedDevice};
use crate::protocol::{Request, Response};
use crate::safety::GateSpec;

/// Relative half-width of the uniform factor on lever arms and linear gradients.
pub const LINEAR_SPREAD: f64 = 0.3;
/// Upper end of the uniform factor on curvature (quadratic) terms; lower end 0.
pub const CURVATURE_MAX_FACTOR: f64 = 3.0;
/// Noise, drift and charge-jump rate factors are log-uniform in `[1/N, N]`.
pub const NOISE_FACTOR: f64 = 2.0;

/// A device drawn around `base` with `seed` (see the module docs for the distribution).
///
/// ```
/// use spintune::sim::{random::random_device, DeviceConfig};
/// let base = DeviceConfig::default();
/// let d = random_device(&base, 4);
/// assert_eq!(d, random_device(&base, 4));
/// assert_ne!(d, base);
/// let r = d.lever_arm_uev_per_uv / base.lever_arm_uev_per_uv;
/// assert!((0.7..=1.3).contains(&r));
/// ```
pub fn random_device(base: &DeviceConfig, seed: u64) -> DeviceConfig {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6465_7669_6365_7321); // "devices!"
    let mut d = base.clone();
    let mut lin = |rng: &mut ChaCha8Rng| 1.0 + LINEAR_SPREAD * rng.gen_range(-1.0..=1.0);
    let curv = |rng: &mut ChaCha8Rng| rng.gen_range(0.0..=CURVATURE_MAX_FACTOR);
    let noise = |rng: &mut ChaCha8Rng| NOISE_FACTOR.powf(rng.gen_range(-1.0..=1.0));
    d.lever_arm_uev_per_uv *= lin(&mut rng);
    for m in [&mut d.tunnel_coupling_uev, &mut d.lead_rate_per_ns] {
        m.linear_per_mv
            .values_mut()
            .for_each(|c| *c *= lin(&mut rng));
        m.quadratic_per_mv2
            .iter_mut()
            .for_each(|t| t.coefficient_per_mv2 *= curv(&mut rng));
    }
    let not_rf = |g: &str| !g.starts_with("RF");
    for row in [
        &mut d.crosstalk.line_a_per_mv,
        &mut d.crosstalk.line_b_per_mv,
    ] {
        scale_map(row, &mut rng, &mut lin, not_rf);
    }
    for q in [
        &mut d.crosstalk.line_a_quadratic,
        &mut d.crosstalk.line_b_quadratic,
    ] {
        q.iter_mut()
            .for_each(|t| t.coefficient_per_mv2 *= curv(&mut rng));
    }
    let swept = d.sensing_dot.gate.clone();
    scale_map(&mut d.sensing_dot.lever_per_mv, &mut rng, &mut lin, |g| {
        g != swept
    });
    let n = &mut d.noise;
    for x in [
        &mut n.white_sd,
        &mut n.white_mu,
        &mut n.white_w,
        &mut n.white_tsr,
        &mut n.drift_mu_mv,
        &mut n.drift_sd_mv,
        &mut n.drift_signal,
        &mut n.charge_jump_rate_per_s,
    ] {
        *x *= noise(&mut rng);
    }
    // drawn last, so every device's other parameters are those drawn before
    let slow = &mut n.slow;
    for x in [
        &mut slow.tunnel_coupling_rel,
        &mut slow.lead_rate_rel,
        &mut slow.jump_rate_per_s,
        &mut slow.lead_rate_trend_per_hour,
    ] {
        *x *= noise(&mut rng);
    }
    d
}

fn scale_map(
    m: &mut BTreeMap<String, f64>,
    rng: &mut ChaCha8Rng,
    factor: &mut impl FnMut(&mut ChaCha8Rng) -> f64,
    include: impl Fn(&str) -> bool,
) {
    for (g, c) in m.iter_mut() {
        // draw for every entry so the stream does not depend on `include`
        let f = factor(rng);
        if include(g) {
            *c *= f;
        }
    }
}

/// Whether every `(t_sr ns, w µV)` set point can be reached on a simulated
/// array cell `config`: [`targets_reachable`] over the default gates
/// ([`super::default_gates`]), tuning gates N, SA, SB, T and plungers PA,
/// PB. The filter a simulated array's cells are drawn with
/// ([`super::array::cell_devices`]) by the array driver and
/// `spintune bench-array`.
///
/// ```
/// use spintune::sim::{random::cell_targets_reachable, DeviceConfig};
/// assert!(cell_targets_reachable(&DeviceConfig::default(), &[(20.0, 270.0)]));
/// ```
pub fn cell_targets_reachable(config: &DeviceConfig, set_points: &[(f64, f64)]) -> bool {
    targets_reachable(
        config,
        &super::default_gates(),
        &["N", "SA", "SB", "T"],
        &["PA", "PB"],
        set_points,
    )
}

/// Whether every `(t_sr ns, w µV)` set point can be reached within the gate
/// limits: Newton with the noiseless Jacobian over `tuning` (lines held by
/// `plungers`), 60 iterations from the start, voltages clamped to the
/// limits; reached when both parameters are within 1 % and the lines
/// within 0.05 mV. (World-side: this reads the simulator's truth to decide
/// which devices are plausible benchmark subjects; no strategy sees it.)
pub fn targets_reachable(
    config: &DeviceConfig,
    gates: &[GateSpec],
    tuning: &[&str],
    plungers: &[&str],
    set_points: &[(f64, f64)],
) -> bool {
    let Ok(start) = SimulatedDevice::new(config.clone(), gates, 0) else {
        return false;
    };
    let all: Vec<&str> = tuning.iter().chain(plungers).copied().collect();
    let params = ["t_sr", "w", "mu_a_mv", "mu_b_mv"];
    set_points.iter().all(|&(t_sr, w)| {
        let mut dev = start.clone();
        for _ in 0..60 {
            let t = dev.truth();
            let r = DVector::from_vec(vec![t.t_sr_ns - t_sr, t.w_uv - w, t.mu_a_mv, t.mu_b_mv]);
            if (r[0] / t_sr).abs() < 0.01
                && (r[1] / w).abs() < 0.01
                && r[2].abs() < 0.05
                && r[3].abs() < 0.05
            {
                return true;
            }
            let Ok(j) = dev.true_jacobian(&all, &params) else {
                return false;
            };
            // a non-finite Jacobian (a device driven where its model breaks
            // down; nalgebra's unbounded SVD looped for ever on it) or one
            // that does not decompose: not a plausible subject
            let Some(svd) = crate::decomposition::svd_unordered(j, true, true) else {
                return false;
            };
            let Ok(pinv) = svd.pseudo_inverse(1e-12) else {
                return false;
            };
            let dv = pinv * r;
            let mut set = BTreeMap::new();
            for (i, g) in all.iter().enumerate() {
                let spec = gates.iter().find(|s| s.name == *g);
                let v = dev.voltages_mv()[*g] - dv[i].clamp(-10.0, 10.0);
                let v = spec.map_or(v, |s| v.clamp(s.min_mv, s.max_mv));
                set.insert(g.to_string(), v);
            }
            if !matches!(
                dev.execute(&Request::SetVoltages { voltages_mv: set }),
                Response::VoltagesSet { .. }
            ) {
                return false;
            }
        }
        false
    })
}
