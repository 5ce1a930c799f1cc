//! Slow drifts (Ornstein–Uhlenbeck) and charge jumps.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;
use serde::{Deserialize, Serialize};

use super::config::NoiseConfig;
use crate::detmath::{exp, StandardNormal};

/// The device's slowly varying disorder state. All start at 0.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriftState {
    /// OU drift of transition line A, mV on RFA.
    pub mu_a_mv: f64,
    /// OU drift of transition line B, mV on RFB.
    pub mu_b_mv: f64,
    /// OU drift of the sensing-dot potential u, mV.
    pub sd_u_mv: f64,
    /// OU drift of the sensor signal offset, a.u.
    pub signal: f64,
    /// Accumulated (persistent) shift of u by charge jumps, mV.
    pub jump_u_mv: f64,
    /// Number of charge jumps so far.
    pub jumps: u64,
    /// Slow drift of `ln t_c` (OU part plus jumps): t_c is multiplied by
    /// `exp(ln_tunnel_coupling)`.
    #[serde(default)]
    pub ln_tunnel_coupling: f64,
    /// Slow drift of `ln Γ` (OU part plus jumps plus trend): Γ is
    /// multiplied by `exp(ln_lead_rate)`.
    #[serde(default)]
    pub ln_lead_rate: f64,
    /// Accumulated jumps of `ln t_c` (persistent, outside the OU part).
    #[serde(default)]
    pub jump_ln_tunnel_coupling: f64,
    /// Accumulated jumps and trend of `ln Γ` (persistent, outside the OU part).
    #[serde(default)]
    pub jump_ln_lead_rate: f64,
    /// Persistent shifts of transition lines A and B by charge
    /// rearrangements ([`super::SimulatedDevice::rearrange_charges`]), mV on
    /// RFA / RFB.
    #[serde(default)]
    pub jump_mu_mv: [f64; 2],
}

fn ou(x: f64, sigma: f64, decay: f64, rng: &mut ChaCha8Rng) -> f64 {
    let n: f64 = StandardNormal.sample(rng);
    x * decay + sigma * (1.0 - decay * decay).max(0.0).sqrt() * n
}

impl DriftState {
    /// Factor on the tunnel coupling t_c from the slow drift.
    pub fn tunnel_coupling_factor(&self) -> f64 {
        exp(self.ln_tunnel_coupling + self.jump_ln_tunnel_coupling)
    }

    /// Factor on the lead rate Γ (t_sr = 1/Γ) from the slow drift.
    pub fn lead_rate_factor(&self) -> f64 {
        exp(self.ln_lead_rate + self.jump_ln_lead_rate)
    }

    /// The slow drift of `ln t_c` and `ln Γ` over `dt_s` (nothing drawn
    /// when it is off, so devices without it keep their random streams).
    fn advance_slow(&mut self, slow: &super::config::SlowDrift, dt_s: f64, rng: &mut ChaCha8Rng) {
        if slow.is_none() {
            return;
        }
        let decay = exp(-dt_s / slow.time_s);
        self.ln_tunnel_coupling = ou(
            self.ln_tunnel_coupling,
            slow.tunnel_coupling_rel,
            decay,
            rng,
        );
        self.ln_lead_rate = ou(self.ln_lead_rate, slow.lead_rate_rel, decay, rng);
        self.jump_ln_lead_rate += slow.lead_rate_trend_per_hour * dt_s / 3600.0;
        let p_jump = 1.0 - exp(-slow.jump_rate_per_s * dt_s);
        if rng.gen::<f64>() < p_jump {
            let a: f64 = StandardNormal.sample(rng);
            let b: f64 = StandardNormal.sample(rng);
            self.jump_ln_tunnel_coupling += slow.jump_rel * a;
            self.jump_ln_lead_rate += slow.jump_rel * b;
        }
    }

    /// Evolves every drift by `dt_s` of lab time and draws charge jumps
    /// (Poisson rate [`NoiseConfig::charge_jump_rate_per_s`]). Returns
    /// whether a jump happened. Always consumes the same random numbers
    /// for the same state, so it is deterministic.
    pub(crate) fn advance(&mut self, noise: &NoiseConfig, dt_s: f64, rng: &mut ChaCha8Rng) -> bool {
        let decay = exp(-dt_s / noise.drift_time_s);
        self.mu_a_mv = ou(self.mu_a_mv, noise.drift_mu_mv, decay, rng);
        self.mu_b_mv = ou(self.mu_b_mv, noise.drift_mu_mv, decay, rng);
        self.sd_u_mv = ou(self.sd_u_mv, noise.drift_sd_mv, decay, rng);
        self.signal = ou(self.signal, noise.drift_signal, decay, rng);
        self.advance_slow(&noise.slow, dt_s, rng);
        let p_jump = 1.0 - exp(-noise.charge_jump_rate_per_s * dt_s);
        if rng.gen::<f64>() < p_jump {
            let n: f64 = StandardNormal.sample(rng);
            self.jump_u_mv += noise.charge_jump_sd_mv * n;
            self.jumps += 1;
            true
        } else {
            false
        }
    }
}
