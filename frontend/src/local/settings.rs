//! What the student chooses in the in-browser mode, and the simulation
//! config it makes (the paper's setup with these choices applied).

use spintune::driver::{SimulationConfig, SimulationRun, PAPER_DEFAULT_COMPENSATION};
use spintune::estimator::EstimatorKind;
use spintune::parameter::Tolerance;

/// What the student can choose.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalSettings {
    /// Gradient estimator of the qubit level.
    pub estimator: EstimatorKind,
    /// Process noise σ of the t_sr gradient, ns/mV per mV of step (Q = σ² I).
    pub q_tsr: f64,
    /// Process noise σ of the w gradient, µV/mV per mV of step.
    pub q_w: f64,
    /// Factor on the simulator's white measurement noise (1 = default device).
    pub noise_scale: f64,
    /// Step limit of the Newton solver, mV.
    pub max_step_mv: f64,
    /// Device RNG seed.
    pub seed: u64,
    /// Target t_sr, ns.
    pub target_tsr: f64,
    /// Target w, µV.
    pub target_w: f64,
    /// Relative tolerance of both targets (0.1 = ±10 %).
    pub tolerance: f64,
    /// Iteration limit of a run.
    pub max_iterations: u64,
    /// Pause between iterations, ms (0 still yields to the browser).
    pub delay_ms: u32,
    /// Cycle the paper's set points (21 iterations each) instead of fixed targets.
    pub paper_cycle: bool,
    /// Virtual-gate matrix of the qubit level (rows PA, PB; columns N, SA,
    /// SB, T; mV of plunger per mV of gate), as a lab would write it down.
    pub compensation: Vec<Vec<f64>>,
    /// Its relative 1σ uncertainty (0.2 = 20 %).
    pub compensation_uncertainty: f64,
}

impl Default for LocalSettings {
    fn default() -> Self {
        Self {
            estimator: EstimatorKind::Kalman,
            q_tsr: 0.075,
            q_w: 0.3,
            noise_scale: 1.0,
            max_step_mv: 10.0,
            seed: 1,
            target_tsr: 20.0,
            target_w: 270.0,
            tolerance: 0.1,
            max_iterations: 150,
            delay_ms: 150,
            paper_cycle: false,
            compensation: default_matrix(),
            compensation_uncertainty: 0.2,
        }
    }
}

impl LocalSettings {
    /// The simulation config: the paper's setup with these choices applied
    /// (an invalid virtual-gate matrix is refused, naming the cell).
    pub fn try_config(&self) -> Result<SimulationConfig, String> {
        self.to_config()
            .with_compensation(self.compensation.clone(), self.compensation_uncertainty)
            .map_err(|e| format!("virtual-gate matrix: {e}"))
    }

    /// The simulation config: the paper's setup with these choices applied
    /// (not validated: see [`LocalSettings::try_config`]).
    pub fn to_config(&self) -> SimulationConfig {
        let mut cfg = SimulationConfig::paper_default();
        cfg.name = "in-browser".into();
        cfg.seed = self.seed;
        cfg.tuner.max_iterations = Some(self.max_iterations);
        let noise = &mut cfg.device.noise;
        noise.white_sd *= self.noise_scale;
        noise.white_mu *= self.noise_scale;
        noise.white_w *= self.noise_scale;
        noise.white_tsr *= self.noise_scale;
        let top = cfg.tuner.top_mut();
        top.estimator = self.estimator;
        top.solver.max_step_mv = self.max_step_mv;
        for p in &mut top.parameters {
            match p.name.as_str() {
                "t_sr" => {
                    p.process_noise_per_mv = self.q_tsr;
                    p.target = Some(self.target_tsr);
                    p.tolerance = Tolerance::Relative(self.tolerance);
                }
                "w" => {
                    p.process_noise_per_mv = self.q_w;
                    p.target = Some(self.target_w);
                    p.tolerance = Tolerance::Relative(self.tolerance);
                }
                _ => {}
            }
        }
        if let Some(c) = &mut top.compensation {
            c.matrix = self.compensation.clone();
            c.relative_uncertainty = self.compensation_uncertainty;
        }
        if self.paper_cycle {
            // The paper's Fig. 3: the targets above are replaced at iterations 0, 21, 42, …
            cfg.tuner.schedule = spintune::benchmark::paper_schedule(21);
        }
        cfg
    }

    /// A fresh run with these settings.
    pub fn build(&self) -> Result<SimulationRun, String> {
        SimulationRun::new(self.try_config()?).map_err(|e| e.to_string())
    }
}

/// The paper setup's matrix ([`PAPER_DEFAULT_COMPENSATION`]) as rows.
pub fn default_matrix() -> Vec<Vec<f64>> {
    PAPER_DEFAULT_COMPENSATION
        .iter()
        .map(|r| r.to_vec())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn paper_cycle_switches_targets_at_iteration_21() {
        let settings = LocalSettings {
            paper_cycle: true,
            max_iterations: 22,
            ..LocalSettings::default()
        };
        assert_eq!(settings.to_config().tuner.schedule.len(), 5);
        let mut run = settings.build().unwrap();
        let mut records = Vec::new();
        while let Some(r) = run.next_iteration().unwrap() {
            records.push(r);
        }
        let t_sr_target = |k: usize| {
            records[k]
                .parameters
                .iter()
                .find(|p| p.name == "t_sr")
                .unwrap()
                .target
        };
        assert_eq!(t_sr_target(20), Some(20.0));
        assert_eq!(t_sr_target(21), Some(70.0));
    }
}
