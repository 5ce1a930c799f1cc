//! Raw scans of the simulated device.
//!
//! Every trace is the sensor signal `G(u) + drift + G'(u)·(charge signal +
//! RF crosstalk) + white noise`, linearised about the present sensing-dot
//! operating point u (which drifts and jumps during the scan). The step
//! height a scan sees is therefore `G'(u)·charge_shift_mv`: it shrinks and
//! the relative noise grows when the sensing dot leaves its flank.

use rand_distr::Distribution;

use super::device::SimulatedDevice;
use super::model;
use crate::detmath::{exp, StandardNormal};
use crate::protocol::{RawScan, ScanKind, ScanRequest, Sweep, Trace};

/// Largest number of points a sensing-dot sweep may request.
pub const MAX_SWEEP_POINTS: usize = 100_000;

const SIGNAL_LABEL: &str = "sensor signal (a.u.)";

/// Why the simulated device cannot take a scan (the scan fails with this
/// reason; nothing is measured, no lab time is charged).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScanError {
    /// The sweep names a gate the device does not have.
    #[error("unknown sweep gate {0:?}")]
    UnknownGate(String),
    /// The sweep's number of points is outside `2..=MAX_SWEEP_POINTS`.
    #[error("sweep points {0} outside 2..={MAX_SWEEP_POINTS}")]
    Points(usize),
    /// An end of the sweep is not finite or outside the gate's limits.
    #[error("sweep of {gate:?} to {mv} mV outside its limits [{min_mv}, {max_mv}] mV")]
    OutOfLimits {
        /// The swept gate.
        gate: String,
        /// The offending end, mV.
        mv: f64,
        /// Lower limit, mV.
        min_mv: f64,
        /// Upper limit, mV.
        max_mv: f64,
    },
}

impl SimulatedDevice {
    /// Runs one scan: returns the raw data and the lab time charged, s.
    pub(crate) fn scan(&mut self, request: &ScanRequest) -> Result<(RawScan, f64), ScanError> {
        let durations = self.config.durations.clone();
        let (scan, seconds) = match request.kind {
            ScanKind::SensingDot => {
                let sweep = match &request.sweep {
                    Some(s) => s.clone(),
                    None => self.default_sweep(),
                };
                (self.sd_sweep(&sweep)?, durations.sd_1d_s)
            }
            ScanKind::ChemicalPotential => (
                self.chemical_potential_scan(),
                durations.chemical_potential_s,
            ),
            ScanKind::TransitionWidth => (self.detuning_scan(), durations.transition_width_s),
            ScanKind::ReloadTime => (self.load_curve(), durations.reload_time_s),
        };
        self.clock.advance(seconds);
        Ok((scan, seconds))
    }

    /// The default sensing-dot sweep: the sensing gate ± the configured half range.
    pub fn default_sweep(&self) -> Sweep {
        let sd = &self.config.sensing_dot;
        let v = self.voltages_mv[&sd.gate];
        Sweep {
            gate: sd.gate.clone(),
            from_mv: v - sd.sweep_half_range_mv,
            to_mv: v + sd.sweep_half_range_mv,
            points: sd.sweep_points,
        }
    }

    /// Sensing-dot potential u now (model + drift + jumps), mV.
    fn sd_u(&self, base_u: f64) -> f64 {
        base_u + self.drift.sd_u_mv + self.drift.jump_u_mv
    }

    /// Line positions now, relative to the calibrated operating point, with drift, mV.
    pub(super) fn lines_now(&self, base: [f64; 2]) -> [f64; 2] {
        let jump = self.drift.jump_mu_mv;
        [
            base[0] + self.drift.mu_a_mv + jump[0],
            base[1] + self.drift.mu_b_mv + jump[1],
        ]
    }

    /// Records `n` points: `y_i = G(u) + drift + G'(u)·signal(x_i, lines) + white`,
    /// advancing the drifts by `dt_s` after each point.
    fn record(
        &mut self,
        x: &[f64],
        white: f64,
        dt_s: f64,
        signal: impl Fn(f64, [f64; 2]) -> f64,
    ) -> Vec<f64> {
        let d = model::deviations(&self.config, &self.voltages_mv);
        let base_u = model::sd_potential_mv(&self.config, &d);
        let raw = model::raw_lines_mv(&self.config, &d);
        let base_lines = [
            raw[0] - self.line_offsets_mv[0],
            raw[1] - self.line_offsets_mv[1],
        ];
        let mut y = Vec::with_capacity(x.len());
        for &xi in x {
            let (g, dg) = model::sd_signal(&self.config, self.sd_u(base_u));
            let n: f64 = StandardNormal.sample(&mut self.rng);
            y.push(g + self.drift.signal + dg * signal(xi, self.lines_now(base_lines)) + white * n);
            self.drift.advance(&self.config.noise, dt_s, &mut self.rng);
        }
        y
    }

    fn sd_sweep(&mut self, sweep: &Sweep) -> Result<RawScan, ScanError> {
        let gate = self
            .gates
            .iter()
            .find(|g| g.name == sweep.gate)
            .ok_or_else(|| ScanError::UnknownGate(sweep.gate.clone()))?
            .clone();
        if !(2..=MAX_SWEEP_POINTS).contains(&sweep.points) {
            return Err(ScanError::Points(sweep.points));
        }
        for v in [sweep.from_mv, sweep.to_mv] {
            if !(v.is_finite() && gate.min_mv <= v && v <= gate.max_mv) {
                return Err(ScanError::OutOfLimits {
                    gate: gate.name.clone(),
                    mv: v,
                    min_mv: gate.min_mv,
                    max_mv: gate.max_mv,
                });
            }
        }
        let x = model::grid(sweep.from_mv, sweep.to_mv, sweep.points);
        let lever = self
            .config
            .sensing_dot
            .lever_per_mv
            .get(&gate.name)
            .copied()
            .unwrap_or(0.0);
        let v0 = self.voltages_mv[&gate.name];
        let d = model::deviations(&self.config, &self.voltages_mv);
        let base_u = model::sd_potential_mv(&self.config, &d);
        let white = self.config.noise.white_sd;
        let dt = self.config.durations.sd_1d_s / x.len() as f64;
        let mut y = Vec::with_capacity(x.len());
        for &xi in &x {
            let (g, _) = model::sd_signal(&self.config, self.sd_u(base_u) + lever * (xi - v0));
            let n: f64 = StandardNormal.sample(&mut self.rng);
            y.push(g + self.drift.signal + white * n);
            self.drift.advance(&self.config.noise, dt, &mut self.rng);
        }
        Ok(RawScan {
            kind: ScanKind::SensingDot,
            x_label: format!("{} (mV)", gate.name),
            y_label: SIGNAL_LABEL.into(),
            traces: vec![Trace {
                label: format!("{} sweep", gate.name),
                x,
                y,
            }],
        })
    }

    fn chemical_potential_scan(&mut self) -> RawScan {
        let s = self.config.scans.clone();
        let sd = self.config.sensing_dot.clone();
        let x = model::grid(-s.mu_half_range_mv, s.mu_half_range_mv, s.mu_points);
        let dt = self.config.durations.chemical_potential_s / (2 * x.len()) as f64;
        let white = self.config.noise.white_mu;
        let cfg = self.config.clone();
        let mut traces = Vec::new();
        for (line, label) in [(0usize, "RFA sweep"), (1, "RFB sweep")] {
            let y = self.record(&x, white, dt, |xi, lines| {
                sd.charge_shift_mv * model::lead_occupation(&cfg, xi - lines[line])
                    + sd.rf_lever * xi
            });
            traces.push(Trace {
                label: label.into(),
                x: x.clone(),
                y,
            });
        }
        RawScan {
            kind: ScanKind::ChemicalPotential,
            x_label: "RF gate offset from the operating point (mV)".into(),
            y_label: SIGNAL_LABEL.into(),
            traces,
        }
    }

    fn detuning_scan(&mut self) -> RawScan {
        let cfg = self.config.clone();
        let x = model::detuning_grid(&cfg);
        let d = model::deviations(&cfg, &self.voltages_mv);
        let t_c = model::tunnel_coupling_uev(&cfg, &d) * self.drift.tunnel_coupling_factor();
        let dt = cfg.durations.transition_width_s / x.len() as f64;
        let (q, rf, tol) = (
            cfg.sensing_dot.charge_shift_mv,
            cfg.sensing_dot.rf_lever,
            cfg.scans.mu_tolerance_mv,
        );
        let y = self.record(&x, cfg.noise.white_w, dt, |xi, [a, b]| {
            let centre = 0.5 * (a - b);
            let common = 0.5 * (a + b) / tol;
            q * exp(-common * common) * model::excess_charge(&cfg, t_c, xi - centre) + rf * xi
        });
        RawScan {
            kind: ScanKind::TransitionWidth,
            x_label: "detuning (mV)".into(),
            y_label: SIGNAL_LABEL.into(),
            traces: vec![Trace {
                label: "detuning scan".into(),
                x,
                y,
            }],
        }
    }

    fn load_curve(&mut self) -> RawScan {
        let cfg = self.config.clone();
        let s = &cfg.scans;
        let x = model::grid(s.load_from_ns, s.load_to_ns, s.load_points);
        let d = model::deviations(&cfg, &self.voltages_mv);
        let t_sr = 1.0 / (model::lead_rate_per_ns(&cfg, &d) * self.drift.lead_rate_factor());
        let dt = cfg.durations.reload_time_s / x.len() as f64;
        let q = cfg.sensing_dot.charge_shift_mv;
        let y = self.record(&x, cfg.noise.white_tsr, dt, |t, [_, b]| {
            let tau = t_sr * (1.0 + s.reload_detuning_per_mv2 * b * b);
            let off = b / s.mu_tolerance_mv;
            q * s.load_visibility * exp(-off * off) * (1.0 - exp(-t / tau))
        });
        RawScan {
            kind: ScanKind::ReloadTime,
            x_label: "wait time (ns)".into(),
            y_label: SIGNAL_LABEL.into(),
            traces: vec![Trace {
                label: "load curve".into(),
                x,
                y,
            }],
        }
    }
}
