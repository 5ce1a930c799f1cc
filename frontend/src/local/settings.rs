//! What the student chooses in the in-browser mode, and the simulation
//! config it makes (the recommended setup, or the paper's rule, with these
//! choices applied).

use spintune::description::RECOMMENDED_RELATIVE_Q_PER_MV;
use spintune::driver::{
    SimulationConfig, SimulationRun, PAPER_DEFAULT_COMPENSATION, PAPER_PROCESS_NOISE_PER_MV,
};
use spintune::estimator::EstimatorKind;
use spintune::parameter::{Tolerance, Transform};

use super::LocalError;
use crate::model::FieldError;

/// A number the student types in the sidebar, checked before it is applied
/// ([`Field::check`]): the message says in plain words what is allowed,
/// without the core's config paths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Field {
    /// Q σ of ∂t_sr/∂V, ns/mV per mV.
    QTsr,
    /// Q σ of ∂w/∂V, µV/mV per mV.
    QW,
    /// Factor on the measurement noise.
    Noise,
    /// Step limit, mV.
    MaxStep,
    /// Device seed.
    Seed,
    /// Target t_sr, ns.
    TargetTsr,
    /// Target w, µV.
    TargetW,
    /// Relative tolerance.
    Tolerance,
    /// Iteration limit.
    MaxIterations,
    /// Pause between iterations, ms.
    Delay,
}

impl Field {
    /// How the sidebar names it.
    pub fn label(self) -> &'static str {
        match self {
            Field::QTsr => "Q σ of ∂t_sr/∂V",
            Field::QW => "Q σ of ∂w/∂V",
            Field::Noise => "measurement noise",
            Field::MaxStep => "step limit",
            Field::Seed => "seed",
            Field::TargetTsr => "t_sr target",
            Field::TargetW => "w target",
            Field::Tolerance => "tolerance",
            Field::MaxIterations => "iteration limit",
            Field::Delay => "pause between iterations",
        }
    }

    /// Whether `v` is allowed here; the plain reason if not.
    pub fn check(self, v: f64) -> Result<(), FieldError> {
        let whole = v.fract() == 0.0;
        let ok = match self {
            Field::QTsr | Field::QW => (0.0..=1e3).contains(&v),
            Field::Noise => (0.0..=100.0).contains(&v),
            Field::MaxStep => v > 0.0 && v <= 1e3,
            Field::Seed => whole && (0.0..=9.0e15).contains(&v),
            Field::TargetTsr | Field::TargetW => v > 0.0 && v <= 1e6,
            Field::Tolerance => v > 0.0 && v < 1.0,
            Field::MaxIterations => whole && (1.0..=1e6).contains(&v),
            Field::Delay => whole && (0.0..=60_000.0).contains(&v),
        };
        if ok && v.is_finite() {
            return Ok(());
        }
        Err(FieldError::new(match self {
            Field::QTsr | Field::QW => "must be 0 or more (at most 1000); 0 means the filter stops learning once it is sure",
            Field::Noise => "must be between 0 and 100 (× the default noise)",
            Field::MaxStep => "must be more than 0 mV (at most 1000 mV): with 0 the tuner cannot move",
            Field::Seed => "must be a whole number, 0 or more",
            Field::TargetTsr | Field::TargetW => "must be more than 0 (at most 1,000,000)",
            Field::Tolerance => "must be between 0 and 1 (0.1 = ±10 % of the target)",
            Field::MaxIterations => "must be a whole number from 1 to 1,000,000",
            Field::Delay => "must be a whole number of ms from 0 to 60,000",
        }))
    }
}

/// Which step rule the qubit level follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Rule {
    /// The product's default ([`SimulationConfig::recommended`]): log space,
    /// trust-region step, two moves per measurement, a cheap cold start.
    #[default]
    Recommended,
    /// The paper's own rule ([`SimulationConfig::paper_default`]): linear
    /// space, pseudo-inverse step, one move, three finite-difference
    /// repetitions; for teaching and comparison.
    Paper,
}

impl Rule {
    /// Both, in menu order.
    pub const ALL: [Rule; 2] = [Rule::Recommended, Rule::Paper];

    /// Menu value.
    pub fn name(self) -> &'static str {
        match self {
            Rule::Recommended => "recommended",
            Rule::Paper => "paper",
        }
    }

    /// Menu label.
    pub fn label(self) -> &'static str {
        match self {
            Rule::Recommended => "recommended (log space, trust region, 2 moves)",
            Rule::Paper => "the paper's (linear, pseudo-inverse, 1 move)",
        }
    }

    /// Parse a menu value.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|r| r.name() == s)
    }
}

/// What the student can choose.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalSettings {
    /// Step rule of the qubit level.
    pub rule: Rule,
    /// Gradient estimator of the qubit level.
    pub estimator: EstimatorKind,
    /// Process noise σ of the t_sr gradient, ns/mV per mV of step (Q = σ² I;
    /// the paper's 0.075). Under [`Rule::Recommended`] (log space) the
    /// gradient is relative: σ scales the recommended relative Q by
    /// σ / 0.075 (so the default means the default in both rules).
    pub q_tsr: f64,
    /// Process noise σ of the w gradient, µV/mV per mV of step (the paper's
    /// 0.3; scaled likewise under [`Rule::Recommended`]).
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
            rule: Rule::default(),
            estimator: EstimatorKind::Kalman,
            q_tsr: PAPER_PROCESS_NOISE_PER_MV.0,
            q_w: PAPER_PROCESS_NOISE_PER_MV.1,
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
    /// Every field's value with [`Field::check`]: the first refused one.
    pub fn check(&self) -> Result<(), LocalError> {
        let fields = [
            (Field::QTsr, self.q_tsr),
            (Field::QW, self.q_w),
            (Field::Noise, self.noise_scale),
            (Field::MaxStep, self.max_step_mv),
            (Field::Seed, self.seed as f64),
            (Field::TargetTsr, self.target_tsr),
            (Field::TargetW, self.target_w),
            (Field::Tolerance, self.tolerance),
            (Field::MaxIterations, self.max_iterations as f64),
            (Field::Delay, self.delay_ms as f64),
        ];
        for (field, v) in fields {
            field.check(v).map_err(|e| LocalError::Field {
                field,
                message: e.message,
            })?;
        }
        Ok(())
    }

    /// The simulation config: the paper's setup with these choices applied
    /// (each field checked first, [`LocalSettings::check`]; an invalid
    /// virtual-gate matrix is refused naming the cell).
    pub fn try_config(&self) -> Result<SimulationConfig, LocalError> {
        self.check()?;
        self.to_config()
            .with_compensation(self.compensation.clone(), self.compensation_uncertainty)
            .map_err(|e| {
                // Anything else the core refuses is not the matrix's fault.
                if e.error.field.contains("compensation") {
                    LocalError::Compensation(e)
                } else {
                    LocalError::Config(e.error)
                }
            })
    }

    /// The simulation config: the chosen rule's setup with these choices
    /// applied (not validated: see [`LocalSettings::try_config`]).
    pub fn to_config(&self) -> SimulationConfig {
        let mut cfg = match self.rule {
            Rule::Recommended => SimulationConfig::recommended(),
            Rule::Paper => SimulationConfig::paper_default(),
        };
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
            // Q as the paper states it, or relative in log space (scaled from
            // the recommended Q by the same factor as from the paper's).
            let q = |sigma: f64, paper: f64| match p.transform {
                Transform::Linear => sigma,
                Transform::Log => RECOMMENDED_RELATIVE_Q_PER_MV * sigma / paper,
            };
            let (q_tsr, q_w) = (
                q(self.q_tsr, PAPER_PROCESS_NOISE_PER_MV.0),
                q(self.q_w, PAPER_PROCESS_NOISE_PER_MV.1),
            );
            match p.name.as_str() {
                "t_sr" => {
                    p.process_noise_per_mv = q_tsr;
                    p.target = Some(self.target_tsr);
                    p.tolerance = Tolerance::Relative(self.tolerance);
                }
                "w" => {
                    p.process_noise_per_mv = q_w;
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
    pub fn build(&self) -> Result<SimulationRun, LocalError> {
        SimulationRun::new(self.try_config()?).map_err(LocalError::Config)
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

    /// A refused field value is a typed [`FieldError`] whose text is the
    /// plain reason shown next to the field; the settings' check names the
    /// field with the same reason.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_refused_field_is_a_typed_error_with_the_plain_reason() {
        assert_eq!(Field::Tolerance.check(0.1), Ok(()));
        let e: FieldError = Field::Tolerance.check(1.5).unwrap_err();
        assert_eq!(
            e,
            FieldError::new("must be between 0 and 1 (0.1 = ±10 % of the target)")
        );
        assert_eq!(e.to_string(), e.message);
        assert_eq!(
            Field::Seed.check(1.5).unwrap_err().to_string(),
            "must be a whole number, 0 or more"
        );
        assert!(Field::MaxStep.check(f64::NAN).is_err());
        let s = LocalSettings {
            tolerance: 1.5,
            ..LocalSettings::default()
        };
        assert_eq!(
            s.check().unwrap_err().to_string(),
            "tolerance: must be between 0 and 1 (0.1 = ±10 % of the target)"
        );
    }

    /// The in-browser mode runs the product's default unless the student
    /// picks the paper's rule; the Q fields mean the same in both (the
    /// paper's σ, or the recommended relative σ scaled by the same factor).
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn the_recommended_rule_is_the_default_and_the_paper_rule_is_a_choice() {
        let s = LocalSettings::default();
        let top = s.to_config().tuner.top().clone();
        let recommended = SimulationConfig::recommended().tuner.top().clone();
        assert_eq!(top.solver, recommended.solver);
        assert_eq!(top.initial_gradient, recommended.initial_gradient);
        for p in &top.parameters {
            assert_eq!(p.transform, Transform::Log);
            assert_eq!(p.process_noise_per_mv, RECOMMENDED_RELATIVE_Q_PER_MV);
        }
        let ten_times = LocalSettings {
            q_tsr: 0.75,
            ..LocalSettings::default()
        };
        let t_sr = ten_times.to_config().tuner.top().parameters[0].clone();
        assert_eq!(t_sr.name, "t_sr");
        assert!((t_sr.process_noise_per_mv - 10.0 * RECOMMENDED_RELATIVE_Q_PER_MV).abs() < 1e-15);
        let paper = LocalSettings {
            rule: Rule::Paper,
            ..LocalSettings::default()
        };
        let top = paper.to_config().tuner.top().clone();
        assert_eq!(
            top.solver,
            SimulationConfig::paper_default().tuner.top().solver
        );
        assert_eq!(top.parameters[0].transform, Transform::Linear);
        assert_eq!(top.parameters[0].process_noise_per_mv, 0.075);
        assert!(paper.build().is_ok() && s.build().is_ok());
    }

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
