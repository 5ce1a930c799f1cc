//! Simulated arrays of double dots tuned jointly: the config a lab (or a
//! student) writes, and the run it builds — [`ArraySimulationRun`], the
//! joint loop ([`ArrayRun`]) in a [`RunSession`] (lifecycle, faults, and
//! the guard checking every request of every batch) on an [`ArrayDevice`].

use serde::{Deserialize, Serialize};

use super::{ArraySimulationRun, SimulationConfig, SimulationRun};
use crate::config_error::ConfigError;
use crate::description::array::{array_cell_tuner, ArrayDescription};
use crate::description::layout::CellGrid;
use crate::session::{RunSession, SessionConfig};
use crate::sim::array::{cell_devices, ArrayConfig, ArrayDevice, MAX_CELLS};
use crate::sim::random::cell_targets_reachable;
use crate::sim::{default_gates, DeviceConfig};
use crate::tuner::array_run::{ArrayRun, ArrayRunSettings};
use crate::tuner::TunerConfig;

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
    /// The array as the lab describes it (cells, their gates and limits,
    /// readout groups; [`ArrayDescription`]). `None`: the simulated array's
    /// own ([`ArrayDescription::simulated`], `array.cells` cells of the
    /// simulated double dot). Given, it is the one source of the cells and
    /// the readout groups: on the simulator the world takes them from it
    /// (`array.cells` and `array.readout_groups` are then not used), and
    /// every gate it names must be a gate of the simulated cell.
    pub description: Option<ArrayDescription>,
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
            description: None,
        }
    }
}

impl ArraySimulationConfig {
    /// Every cell's targets, `Err` naming the field.
    pub fn cell_targets(&self) -> Result<Vec<(f64, f64)>, ConfigError> {
        let k = self.described().cells as usize;
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

    /// The array as described: [`ArraySimulationConfig::description`], or
    /// the simulated array's own.
    pub fn described(&self) -> ArrayDescription {
        self.description
            .clone()
            .unwrap_or_else(|| ArrayDescription {
                layout: self.array.layout,
                ..ArrayDescription::simulated(self.array.cells, self.array.readout_groups.clone())
            })
    }

    /// The cells on their grid (a chain, or a ladder's two rows numbered
    /// row by row) as described; `Err` naming `description.layout` or
    /// `array.layout`.
    ///
    /// ```
    /// use spintune::driver::array::ArraySimulationConfig;
    /// let cfg: ArraySimulationConfig = serde_json::from_str(
    ///     r#"{"array": {"cells": 8, "layout": "ladder", "device_seed": 5, "seed": 1}}"#,
    /// ).unwrap();
    /// let grid = cfg.grid().unwrap();
    /// assert_eq!((grid.rows(), grid.columns()), (2, 4));
    /// let odd: ArraySimulationConfig = serde_json::from_str(
    ///     r#"{"array": {"cells": 5, "layout": "ladder", "device_seed": 5, "seed": 1}}"#,
    /// ).unwrap();
    /// assert_eq!(odd.grid().unwrap_err().field, "array.layout");
    /// ```
    pub fn grid(&self) -> Result<CellGrid, ConfigError> {
        self.described().grid().map_err(|e| self.described_error(e))
    }

    /// Every gate of the array with its limits (prefixed `c{k}.`), `Err`
    /// naming the description's field.
    pub fn gates(&self) -> Result<Vec<crate::safety::GateSpec>, ConfigError> {
        self.described()
            .gates()
            .map_err(|e| self.described_error(e))
    }

    /// An error of the described array, named where the user wrote it:
    /// under `description`, or (for the simulated array's own description)
    /// `array.cells`, `array.layout` and `array.readout_groups`.
    fn described_error(&self, e: ConfigError) -> ConfigError {
        match self.description {
            Some(_) => e.within("description"),
            None => e.within("array"),
        }
    }

    /// Validate and build the world and the run.
    pub fn build(&self) -> Result<ArraySimulationRun, ConfigError> {
        let (run, device) = self.build_parts()?;
        Ok(SimulationRun::from_parts(
            RunSession::from_tuner(run, SessionConfig::default()),
            device,
        ))
    }

    /// Validate and build the plan and the (truth-sealed) simulated world,
    /// for a shell that wraps them in its own session (the server).
    pub fn build_parts(&self) -> Result<(ArrayRun, ArrayDevice), ConfigError> {
        let run = self.build_plan()?;
        let device = self.build_world()?;
        Ok((run, device))
    }

    /// Validate and build the plan alone, for an array on a lab's
    /// instruments (the lab bridge): nothing simulated is built.
    pub fn build_plan(&self) -> Result<ArrayRun, ConfigError> {
        self.tuning.validate().map_err(|e| e.within("tuning"))?;
        let described = self.described();
        let gates = described.gates().map_err(|e| self.described_error(e))?;
        let targets = self.cell_targets()?;
        let cells = described
            .cell_tuners(&targets, self.tuning.relative_tolerance)
            .map_err(|e| match e.field.as_str() {
                "targets" => e,
                _ => self.described_error(e),
            })?;
        let mut run = ArrayRun::new(
            cells,
            &gates,
            self.tuning.clone(),
            self.cross_calibration,
            false,
        )
        .map_err(|e| match e {
            crate::tuner::array_run::ArrayRunError::Config(c) => c,
            other => ConfigError::new("", other.to_string()),
        })?;
        run.set_readout_groups(described.readout_groups.as_deref());
        run.set_grid(self.grid()?)
            .map_err(|e| ConfigError::new("", e.to_string()))?;
        Ok(run)
    }

    /// The simulated world (truth sealed): `array` with the described cells
    /// and readout groups, each cell drawn with the targets reachable within
    /// its gate limits. `Err` naming the field, also when the description
    /// names a gate the simulated cell does not have.
    pub fn build_world(&self) -> Result<ArrayDevice, ConfigError> {
        let mut world = self.array.clone();
        if let Some(d) = &self.description {
            world.cells = d.cells;
            world.layout = d.layout;
            world.readout_groups = d.readout_groups.clone();
            let simulated = default_gates();
            for (i, g) in d.cell.gates.iter().enumerate() {
                if !simulated.iter().any(|s| s.name == g.name) {
                    let names: Vec<&str> = simulated.iter().map(|s| s.name.as_str()).collect();
                    return Err(ConfigError::new(
                        format!("description.cell.gates[{i}].name"),
                        format!("{:?} is not a gate of the simulated cell (driver = \"simulator\"; its gates: {names:?}); a lab's array runs with driver = \"bridge\"", g.name),
                    ));
                }
            }
        }
        if !(1..=MAX_CELLS).contains(&world.cells) {
            return Err(ConfigError::new(
                "array.cells",
                format!("{} (1..={MAX_CELLS})", world.cells),
            ));
        }
        let targets = self.cell_targets()?;
        let reachable = |d: &DeviceConfig| cell_targets_reachable(d, &targets);
        let devices = cell_devices(&self.device, world.cells, world.device_seed, reachable);
        let mut device = ArrayDevice::new(world, devices).map_err(|e| e.within("array"))?;
        device.seal_truth();
        Ok(device)
    }
}

/// The recommended single-cell tuner for cell `cell` of the simulated
/// array ([`array_cell_tuner`] of [`SimulationConfig::recommended`]'s
/// tuner), the given targets `(t_sr ns, w µV)` within a relative `band`.
pub fn cell_tuner(cell: u32, targets: (f64, f64), band: f64) -> TunerConfig {
    array_cell_tuner(SimulationConfig::recommended().tuner, cell, targets, band)
}
