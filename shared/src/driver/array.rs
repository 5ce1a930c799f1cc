//! Simulated arrays of double dots tuned jointly: the config a lab (or a
//! student) writes, and the run it builds — [`ArraySimulationRun`], the
//! joint loop ([`ArrayRun`]) in a [`RunSession`] (lifecycle, faults, and
//! the guard checking every request of every batch) on an [`ArrayDevice`].

use serde::{Deserialize, Serialize};

use super::{ArraySimulationRun, SimulationConfig, SimulationRun};
use crate::config_error::ConfigError;
use crate::parameter::Tolerance;
use crate::session::{RunSession, SessionConfig};
use crate::sim::array::{cell_devices, gate_name, ArrayConfig, ArrayDevice, MAX_CELLS};
use crate::sim::random::targets_reachable;
use crate::sim::{default_gates, DeviceConfig};
use crate::tuner::array_run::{ArrayRun, ArrayRunSettings};
use crate::tuner::{LevelKind, TunerConfig};

/// A simulated array run (every field optional in a config file).
///
/// ```
/// use spintune::driver::array::ArraySimulationConfig;
/// let cfg: ArraySimulationConfig = serde_json::from_str(r#"{"array": {"cells": 3, "device_seed": 5, "seed": 1}}"#).unwrap();
/// let mut run = cfg.build().unwrap();
/// let first = run.next_iteration().unwrap().expect("an iteration");
/// assert_eq!(first.parameters.len(), 6); // t_sr and w of 3 cells
/// assert_eq!(first.parameters[2].name, "c1.t_sr");
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ArraySimulationConfig {
    /// Human-readable name.
    pub name: String,
    /// The simulated array (the world: cells, population seed, crosstalk,
    /// readout groups, noise seed).
    pub array: ArrayConfig,
    /// Cell 0's device; cells ≥ 1 are drawn around it ([`cell_devices`]),
    /// each with the targets reachable within its gate limits.
    pub device: DeviceConfig,
    /// Targets `(t_sr ns, w µV)`: one pair for every cell, or one per cell.
    pub targets: Vec<(f64, f64)>,
    /// The joint loop's settings (the band among them).
    pub tuning: ArrayRunSettings,
    /// The lab's cross-cell virtual-gate calibration `λ̂` (nearest, next):
    /// the fraction of a neighbour's gate effect its compensation assumes
    /// (configuration a lab calibrates; default 0.3, 0.05).
    pub cross_calibration: [f64; 2],
}

impl Default for ArraySimulationConfig {
    fn default() -> Self {
        Self {
            name: "array".into(),
            array: ArrayConfig::chain(3, 0, 1),
            device: DeviceConfig::default(),
            targets: vec![super::PAPER_FIRST_TARGET],
            tuning: ArrayRunSettings::default(),
            cross_calibration: [0.3, 0.05],
        }
    }
}

impl ArraySimulationConfig {
    /// Every cell's targets, `Err` naming the field.
    pub fn cell_targets(&self) -> Result<Vec<(f64, f64)>, ConfigError> {
        let k = self.array.cells as usize;
        let targets = match self.targets.len() {
            1 => vec![self.targets[0]; k],
            n if n == k => self.targets.clone(),
            n => {
                return Err(ConfigError::new(
                    "targets",
                    format!("{n} pairs for {k} cells (one pair for all, or one per cell)"),
                ))
            }
        };
        for (i, &(t, w)) in targets.iter().enumerate() {
            if !(t.is_finite()
                && (1.0..=1000.0).contains(&t)
                && w.is_finite()
                && (10.0..=2000.0).contains(&w))
            {
                return Err(ConfigError::new(
                    format!("targets[{i}]"),
                    format!("({t} ns, {w} µV) (t_sr 1..=1000 ns, w 10..=2000 µV)"),
                ));
            }
        }
        Ok(targets)
    }

    /// Every gate of the array with its limits (prefixed `c{k}.`).
    pub fn gates(&self) -> Vec<crate::safety::GateSpec> {
        (0..self.array.cells)
            .flat_map(crate::sim::array::cell_gates)
            .collect()
    }

    /// Validate and build the world and the run.
    pub fn build(&self) -> Result<ArraySimulationRun, ConfigError> {
        let (run, device) = self.build_parts()?;
        Ok(SimulationRun::from_parts(
            RunSession::from_tuner(run, SessionConfig::default()),
            device,
        ))
    }

    /// Validate and build the plan and the (truth-sealed) world, for a
    /// shell that wraps them in its own session (the server).
    pub fn build_parts(&self) -> Result<(ArrayRun, ArrayDevice), ConfigError> {
        if !(1..=MAX_CELLS).contains(&self.array.cells) {
            return Err(ConfigError::new(
                "array.cells",
                format!("{} (1..={MAX_CELLS})", self.array.cells),
            ));
        }
        self.tuning.validate().map_err(|e| e.within("tuning"))?;
        let targets = self.cell_targets()?;
        let reachable = |d: &DeviceConfig| {
            targets_reachable(
                d,
                &default_gates(),
                &["N", "SA", "SB", "T"],
                &["PA", "PB"],
                &targets,
            )
        };
        let devices = cell_devices(
            &self.device,
            self.array.cells,
            self.array.device_seed,
            reachable,
        );
        let mut device =
            ArrayDevice::new(self.array.clone(), devices).map_err(|e| e.within("array"))?;
        device.seal_truth();
        let cells = targets
            .iter()
            .enumerate()
            .map(|(c, &t)| cell_tuner(c as u32, t, self.tuning.relative_tolerance))
            .collect();
        let run = ArrayRun::new(
            cells,
            &device.gates(),
            self.tuning.clone(),
            self.cross_calibration,
            false,
        )
        .map_err(|e| ConfigError::new("array", e.to_string()))?;
        Ok((run, device))
    }
}

/// The recommended single-cell tuner for cell `cell` of an array: every
/// gate renamed `c{cell}.…`, the given targets `(t_sr ns, w µV)` within a
/// relative `band`; the sensing dot sweeps at every call and the lines are
/// scanned (a cell's flank and line models would not see the neighbours'
/// gates).
pub fn cell_tuner(cell: u32, (t_sr, w): (f64, f64), band: f64) -> TunerConfig {
    let mut t = SimulationConfig::recommended().tuner;
    let rn = |g: &mut String| *g = gate_name(cell, g);
    t.gates.iter_mut().for_each(|g| rn(&mut g.name));
    for level in &mut t.levels {
        match &mut level.kind {
            LevelKind::Newton(n) => {
                n.gates.iter_mut().for_each(rn);
                if let Some(c) = &mut n.compensation {
                    c.gates.iter_mut().for_each(rn);
                }
                // As the flank below: a cell's line forecast cannot see the
                // neighbours' gates, whose moves shift its lines too.
                n.forecast = None;
            }
            LevelKind::SensingDot(sd) => {
                rn(&mut sd.gate);
                if let Some(f) = &mut sd.fallback {
                    rn(&mut f.gate);
                }
                // A cell's flank model sees only its own gates, and in an
                // array the neighbours' moves shift its flank too: the
                // cells sweep at every call (measured: with the single-cell
                // prediction, 9-cell `joint` left 6 changes unconverged
                // where the oracle converged, against 1).
                sd.prediction = None;
            }
        }
    }
    t.max_iterations = None;
    t.stop_when_tuned = false;
    t.schedule.clear();
    for p in &mut t.top_mut().parameters {
        p.tolerance = Tolerance::Relative(band);
        p.target = match p.name.as_str() {
            "t_sr" => Some(t_sr),
            "w" => Some(w),
            _ => p.target,
        };
    }
    t
}
