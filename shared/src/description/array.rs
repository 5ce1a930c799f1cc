//! An array of double dots as a lab describes it: the cells' gates described
//! once (every cell of a chain has the same gates, named `c{k}.NAME` on the
//! instrument), the limits and start voltages of the cells where they
//! differ, and the readout groups (cells that share a sensor).
//! [`ArrayDescription::cell_tuners`] derives every cell's tuner from it
//! through the one single-cell derivation ([`DeviceDescription::tuner`]) and
//! the one array-cell rule ([`array_cell_tuner`]), so the simulated array
//! and a lab's array are tuned alike.
//!
//! ```
//! use spintune::description::array::ArrayDescription;
//! let text = r#"{
//!   "cells": 2,
//!   "cell": {
//!     "gates": [
//!       {"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
//!       {"name": "B2", "min_mv": -500, "max_mv": 0, "initial_mv": -250},
//!       {"name": "SD", "min_mv": -900, "max_mv": -300, "initial_mv": -600, "max_step_mv": 30}
//!     ],
//!     "qubit": {"gates": ["B1", "B2"]},
//!     "sensing_dot": {"gate": "SD"}
//!   },
//!   "cell_gates": [{"cell": 1, "gates": [{"name": "B2", "min_mv": -450, "max_mv": 0, "initial_mv": -200}]}],
//!   "readout_groups": [[0, 1]]
//! }"#;
//! let d: ArrayDescription = serde_json::from_str(text).unwrap();
//! let gates = d.gates().unwrap();
//! assert_eq!(gates.len(), 6);
//! assert_eq!(gates[4].name, "c1.B2");
//! assert_eq!(gates[4].initial_mv, -200.0); // cell 1's own start voltage
//! let tuners = d.cell_tuners(&[(20.0, 270.0)], 0.1).unwrap();
//! assert_eq!(tuners[1].gates[0].name, "c1.B1");
//! ```

use serde::{Deserialize, Serialize};

use super::layout::{CellGrid, Layout};
use super::DeviceDescription;
use crate::config_error::ConfigError;
use crate::parameter::Tolerance;
use crate::safety::GateSpec;
use crate::sim::array::{check_readout_groups, gate_name, MAX_CELLS};
use crate::tuner::{LevelKind, TunerConfig};

/// An array of double-dot cells as a lab describes it (see the module docs).
/// Every field but `cells` and `cell` has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayDescription {
    /// Number of cells, 1..=[`MAX_CELLS`]; in a chain cell k's neighbours
    /// are cells k − 1 and k + 1.
    pub cells: u32,
    /// Where the cells sit: `"chain"` (default) or `"ladder"` (two rows of
    /// `cells / 2`, numbered row by row; an even number of cells, at least
    /// 4). Which cells are neighbours follows from it
    /// ([`crate::description::layout`]).
    #[serde(default, skip_serializing_if = "Layout::is_chain")]
    pub layout: Layout,
    /// Every cell's device, with its gates named without the cell prefix
    /// (`"N"`, not `"c0.N"`). Its qubit level tunes `t_sr` and `w` (the
    /// joint array tuner's parameters); its `qubit.relative_tolerance` is
    /// replaced by the array run's band.
    pub cell: DeviceDescription,
    /// Per-cell limits and start voltages where a cell differs from `cell`:
    /// each entry replaces the named gates' specs for one cell.
    #[serde(default)]
    pub cell_gates: Vec<CellGates>,
    /// Readout groups: lists of cells sharing a sensor readout (their scans
    /// run one after the other; a lab bridge runs a batch's scans of
    /// different groups at the same time). `None`: one sensor per cell.
    /// Every cell in exactly one group.
    #[serde(default)]
    pub readout_groups: Option<Vec<Vec<u32>>>,
}

/// One cell's own gate specs (limits, start voltage, step) replacing those
/// of [`ArrayDescription::cell`] for the named gates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellGates {
    /// The cell, `0..cells`.
    pub cell: u32,
    /// Gates named as in `cell.gates` (without the prefix).
    pub gates: Vec<GateSpec>,
}

impl ArrayDescription {
    /// The simulated array's description: `cells` cells of the paper's
    /// device ([`DeviceDescription::paper_device`], the gates of the
    /// simulated double dot), with the given readout groups.
    ///
    /// ```
    /// use spintune::description::array::ArrayDescription;
    /// use spintune::sim::array::cell_gates;
    /// let d = ArrayDescription::simulated(3, None);
    /// // the simulated array's gates and limits, cell by cell
    /// let simulated: Vec<_> = (0..3).flat_map(cell_gates).collect();
    /// assert_eq!(d.gates().unwrap(), simulated);
    /// ```
    pub fn simulated(cells: u32, readout_groups: Option<Vec<Vec<u32>>>) -> Self {
        Self {
            cells,
            layout: Layout::Chain,
            cell: DeviceDescription::paper_device(),
            cell_gates: Vec::new(),
            readout_groups,
        }
    }

    /// The cells on their grid; `Err` naming `layout` (a ladder of an odd
    /// number of cells, or of fewer than 4).
    pub fn grid(&self) -> Result<CellGrid, ConfigError> {
        CellGrid::new(self.layout, self.cells)
    }

    /// Check every field; the error names it (`cells`, `cell.qubit.gates[0]`,
    /// `cell_gates[1].gates[0].name`, `readout_groups[0][1]`, …).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.cell_descriptions().map(|_| ())
    }

    /// Every gate of the array (cell by cell, prefixed `c{k}.`) with its
    /// limits; `Err` as [`ArrayDescription::validate`].
    pub fn gates(&self) -> Result<Vec<GateSpec>, ConfigError> {
        Ok(self
            .cell_descriptions()?
            .into_iter()
            .enumerate()
            .flat_map(|(k, d)| {
                d.gates.into_iter().map(move |g| GateSpec {
                    name: gate_name(k as u32, &g.name),
                    ..g
                })
            })
            .collect())
    }

    /// Every cell's tuner: its description's ([`DeviceDescription::tuner`])
    /// made an array cell's ([`array_cell_tuner`]) with its targets
    /// `(t_sr ns, w µV)` (one pair for every cell, or one per cell) within
    /// the relative `band`.
    pub fn cell_tuners(
        &self,
        targets: &[(f64, f64)],
        band: f64,
    ) -> Result<Vec<TunerConfig>, ConfigError> {
        let cells = self.cell_descriptions()?;
        if targets.len() != 1 && targets.len() != cells.len() {
            return Err(ConfigError::new(
                "targets",
                format!(
                    "{} pairs for {} cells (one pair for all, or one per cell)",
                    targets.len(),
                    cells.len()
                ),
            ));
        }
        cells
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let t = d.tuner().map_err(|e| e.within(&self.cell_field(k)))?;
                let target = targets[if targets.len() == 1 { 0 } else { k }];
                Ok(array_cell_tuner(t, k as u32, target, band))
            })
            .collect()
    }

    /// The field that describes cell `k`'s gates: its `cell_gates` entry if
    /// it has one, else `cell`.
    fn cell_field(&self, k: usize) -> String {
        match self.cell_gates.iter().position(|c| c.cell as usize == k) {
            Some(i) => format!("cell_gates[{i}]"),
            None => "cell".into(),
        }
    }

    /// Each cell's own description (the `cell_gates` applied), validated.
    fn cell_descriptions(&self) -> Result<Vec<DeviceDescription>, ConfigError> {
        if !(1..=MAX_CELLS).contains(&self.cells) {
            return Err(ConfigError::new(
                "cells",
                format!("{} outside 1..={MAX_CELLS}", self.cells),
            ));
        }
        self.grid()?;
        let base = self.cell.tuner().map_err(|e| e.within("cell"))?;
        for (i, g) in self.cell.gates.iter().enumerate() {
            if g.name.is_empty() || g.name.contains(char::is_whitespace) {
                return Err(ConfigError::new(
                    format!("cell.gates[{i}].name"),
                    format!("{:?}: a gate name is non-empty, without spaces", g.name),
                ));
            }
        }
        let parameters = &base.top().parameters;
        for needed in ["t_sr", "w"] {
            if !parameters.iter().any(|p| p.name == needed) {
                return Err(ConfigError::new(
                    "cell.qubit.parameters",
                    format!("an array cell tunes t_sr and w (the joint tuner's parameters); {needed:?} is missing"),
                ));
            }
        }
        let mut cells = vec![self.cell.clone(); self.cells as usize];
        let mut seen = vec![false; self.cells as usize];
        for (i, entry) in self.cell_gates.iter().enumerate() {
            let field = format!("cell_gates[{i}]");
            let Some(d) = cells.get_mut(entry.cell as usize) else {
                return Err(ConfigError::new(
                    format!("{field}.cell"),
                    format!("cell {} outside 0..{}", entry.cell, self.cells),
                ));
            };
            if std::mem::replace(&mut seen[entry.cell as usize], true) {
                return Err(ConfigError::new(
                    format!("{field}.cell"),
                    format!("cell {} has two entries", entry.cell),
                ));
            }
            if entry.gates.is_empty() {
                return Err(ConfigError::new(
                    format!("{field}.gates"),
                    "empty: an entry names the gates whose specs differ in its cell",
                ));
            }
            for (j, g) in entry.gates.iter().enumerate() {
                let Some(slot) = d.gates.iter_mut().find(|s| s.name == g.name) else {
                    let known: Vec<&str> =
                        self.cell.gates.iter().map(|g| g.name.as_str()).collect();
                    return Err(ConfigError::new(
                        format!("{field}.gates[{j}].name"),
                        format!(
                            "{:?} is not a gate of `cell.gates` (known: {known:?})",
                            g.name
                        ),
                    ));
                };
                *slot = g.clone();
            }
            d.tuner().map_err(|e| e.within(&field))?;
        }
        if let Some(groups) = &self.readout_groups {
            check_readout_groups(self.cells, groups)?;
        }
        Ok(cells)
    }
}

/// Cell `cell`'s tuner in an array, from a single double dot's `tuner`:
/// every gate renamed `c{cell}.…`, the targets `(t_sr ns, w µV)` within a
/// relative `band`; the sensing dot sweeps at every call and the lines are
/// scanned (a cell's flank and line models would not see the neighbours'
/// gates); no iteration cap, no stop when tuned, no target schedule (the
/// joint loop decides).
pub fn array_cell_tuner(
    mut t: TunerConfig,
    cell: u32,
    (t_sr, w): (f64, f64),
    band: f64,
) -> TunerConfig {
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

#[cfg(test)]
mod tests {
    use super::*;

    fn described(extra: serde_json::Value) -> Result<Vec<GateSpec>, ConfigError> {
        let mut d = serde_json::to_value(ArrayDescription::simulated(3, None)).unwrap();
        crate::config_merge::merge(&mut d, extra);
        let d: ArrayDescription = serde_json::from_value(d).unwrap();
        d.gates()
    }

    #[test]
    fn errors_name_the_field() {
        let cases = [
            (serde_json::json!({"cells": 0}), "cells"),
            (serde_json::json!({"cells": 17}), "cells"),
            (
                serde_json::json!({"cell_gates": [{"cell": 3, "gates": []}]}),
                "cell_gates[0].cell",
            ),
            (
                serde_json::json!({"cell_gates": [{"cell": 1, "gates": []}]}),
                "cell_gates[0].gates",
            ),
            (
                serde_json::json!({"cell_gates": [{"cell": 9, "gates": []}]}),
                "cell_gates[0].cell",
            ),
            (
                serde_json::json!({"cell_gates": [
                    {"cell": 1, "gates": [{"name": "N", "min_mv": -900, "max_mv": -500, "initial_mv": -700}]},
                    {"cell": 1, "gates": []}]}),
                "cell_gates[1].cell",
            ),
            (
                serde_json::json!({"cell_gates": [{"cell": 1, "gates": [
                    {"name": "X", "min_mv": -1, "max_mv": 0, "initial_mv": -0.5}]}]}),
                "cell_gates[0].gates[0].name",
            ),
            (
                serde_json::json!({"readout_groups": [[0, 1], [1, 2]]}),
                "readout_groups[1][0]",
            ),
            (
                serde_json::json!({"readout_groups": [[0, 1]]}),
                "readout_groups",
            ),
            (
                serde_json::json!({"cell": {"qubit": {"parameters": ["w"]}}}),
                "cell.qubit.parameters",
            ),
            (
                serde_json::json!({"cell": {"qubit": {"gates": ["N", "NOPE"]}}}),
                "cell",
            ),
        ];
        for (extra, field) in cases {
            let e = described(extra.clone()).unwrap_err();
            assert!(
                e.field == field || e.field.starts_with(&format!("{field}.")),
                "{extra}: {e}"
            );
        }
    }

    /// A cell's override moves its start voltage and limits and nothing
    /// else; its start voltage outside its own limits is refused naming the
    /// entry.
    #[test]
    fn a_cell_s_own_gates_replace_the_shared_ones_for_that_cell_only() {
        let gates = described(serde_json::json!({"cell_gates": [{"cell": 2, "gates": [
            {"name": "SB", "min_mv": -900, "max_mv": -600, "initial_mv": -700}]}]}))
        .unwrap();
        let sb = |k: u32| gates.iter().find(|g| g.name == gate_name(k, "SB")).unwrap();
        assert_eq!(
            (sb(2).min_mv, sb(2).max_mv, sb(2).initial_mv),
            (-900.0, -600.0, -700.0)
        );
        let shared = DeviceDescription::paper_device();
        let shared_sb = shared.gates.iter().find(|g| g.name == "SB").unwrap();
        assert_eq!(sb(0).initial_mv, shared_sb.initial_mv);
        assert_eq!(sb(1).min_mv, shared_sb.min_mv);
        let e = described(serde_json::json!({"cell_gates": [{"cell": 2, "gates": [
            {"name": "SB", "min_mv": -900, "max_mv": -800, "initial_mv": -700}]}]}))
        .unwrap_err();
        assert!(e.field.starts_with("cell_gates[0]"), "{e}");
    }
}
