//! [`ArrayDevice`]: a chain (or a 2×N ladder) of K double-dot cells with
//! crosstalk between neighbours and readout groups (issue 24).
//!
//! * **Cells.** Each cell is a whole [`SimulatedDevice`] (physics, scans,
//!   noise, drift, its own seeded RNG): cell 0 is the given base
//!   [`DeviceConfig`], cell k ≥ 1 is [`random_device`]`(base, cell_seed(device_seed, k))`
//!   (the documented population of `sim::random`; see [`cell_devices`]).
//!   Every cell has the gates of [`super::default_gates`], named with a cell
//!   prefix: gate `SB` of cell 3 is `c3.SB` ([`gate_name`], [`split_gate`]);
//!   a parameter of cell 3 is `c3.t_sr` ([`parameter_name`]).
//! * **Crosstalk** (effective-voltage model). The voltages a lab sets are
//!   the *commanded* ones (what a read-back returns). Cell j's own model sees
//!   each of its [`CrosstalkConfig::gates`] `g` at
//!   `v_j,g + Σ_{k≠j} λ(d(j,k))·(v_k,g − v⁰_k,g)` mV, where `v⁰` is the start
//!   voltage, `d` the cells' distance on the array's grid (`|j − k|` in a
//!   chain; [`crate::description::layout::CellGrid::distance`]) and
//!   `λ(1) = nearest`, `λ(2) = next`, `λ(d ≥ 3) = 0`. So moving a
//!   tuning gate or plunger of cell k shifts the neighbours' tunnel
//!   coupling, lead rate (hence w and t_sr), transition lines and sensing
//!   dot by that fraction of the own-cell effect (including the own model's
//!   curvature). Sensing-dot and RF gates do not couple by default (the
//!   list is configurable). Deterministic.
//! * **Readout groups.** Each cell belongs to exactly one group (default:
//!   one sensor per cell, so every cell is its own group).
//!   [`ArrayDevice::execute_batch`] runs a batch of requests "at the same
//!   time": requests of one group are serial (their lab times add), groups
//!   run in parallel, the array's lab clock advances by the longest group.
//!   Every cell then idles for the rest of the batch, so every cell's drift
//!   and clock follow the array's clock.
//! * **Truth** (invariant 7). Measurements are raw scans, as for one cell.
//!   The truth is available world-side ([`ArrayDevice::truth`], never
//!   handed to a strategy) and to the oracle through
//!   [`Request::TrueJacobian`] with prefixed gates and parameters, counted
//!   in [`ArrayDevice::truth_queries`] and refused once
//!   [`ArrayDevice::seal_truth`] was called.

use std::collections::BTreeMap;

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

use super::device::JACOBIAN_STEP_MV;
use super::random::random_device;
use super::{DeviceConfig, SimulatedDevice, Truth};
use crate::config_error::ConfigError;
use crate::description::layout::{CellGrid, Layout};
use crate::protocol::{Request, Response, ScanOutcome, ScanRequest};
use crate::safety::GateSpec;

/// Most cells an array may have (bounds every per-cell list and the
/// crosstalk sums; ARCHITECTURE.md invariant 8).
pub const MAX_CELLS: u32 = 16;
/// Largest crosstalk fraction `λ` (of the own-cell effect).
pub const MAX_CROSSTALK: f64 = 0.9;
/// Largest number of requests in one [`ArrayDevice::execute_batch`].
pub const MAX_BATCH: usize = crate::protocol::MAX_BATCH_REQUESTS;

/// Crosstalk between cells (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrosstalkConfig {
    /// `λ(1)`: fraction of a gate's own-cell effect seen by the nearest
    /// cells, 0 ≤ λ ≤ [`MAX_CROSSTALK`]. Default 0.3.
    pub nearest: f64,
    /// `λ(2)`: fraction seen by the next-nearest cells, 0 ≤ λ ≤ `nearest`.
    /// Default 0.05. Cells further apart do not couple.
    pub next: f64,
    /// The (unprefixed) gates that couple to neighbours. Default: the tuning
    /// gates and plungers `N, T, SA, SB, PA, PB` (through the own model they
    /// shift the neighbour's t_c, Γ, both transition lines and its sensing
    /// dot). Sensing-dot and RF gates are per-cell (not in the default).
    /// With every tuning gate and plunger coupling by the same λ, a cell's
    /// virtual-gate compensated move shifts its neighbours' lines little;
    /// with the tuning gates alone (measured on branch `array`), the
    /// single-cell tuners lose their neighbours' lines outside the ±4 mV scan.
    pub gates: Vec<String>,
}

impl Default for CrosstalkConfig {
    fn default() -> Self {
        Self {
            nearest: 0.3,
            next: 0.05,
            gates: ["N", "T", "SA", "SB", "PA", "PB"]
                .iter()
                .map(|s| s.to_string())
                .collect(),
        }
    }
}

impl CrosstalkConfig {
    /// `λ(distance)`: 1 for the own cell, `nearest`, `next`, then 0.
    ///
    /// ```
    /// let x = spintune::sim::array::CrosstalkConfig::default();
    /// assert_eq!((x.lambda(0), x.lambda(1), x.lambda(2), x.lambda(3)), (1.0, 0.3, 0.05, 0.0));
    /// ```
    pub fn lambda(&self, distance: u32) -> f64 {
        match distance {
            0 => 1.0,
            1 => self.nearest,
            2 => self.next,
            _ => 0.0,
        }
    }

    /// `Err` naming the field: fractions finite and within bounds, gates known.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.nearest.is_finite() && (0.0..=MAX_CROSSTALK).contains(&self.nearest)) {
            return Err(ConfigError::new(
                "crosstalk.nearest",
                format!("{} outside [0, {MAX_CROSSTALK}]", self.nearest),
            ));
        }
        if !(self.next.is_finite() && (0.0..=self.nearest).contains(&self.next)) {
            return Err(ConfigError::new(
                "crosstalk.next",
                format!("{} outside [0, nearest = {}]", self.next, self.nearest),
            ));
        }
        let known = super::default_gates();
        for (i, g) in self.gates.iter().enumerate() {
            if !known.iter().any(|k| &k.name == g) {
                return Err(ConfigError::new(
                    format!("crosstalk.gates[{i}]"),
                    format!("{g:?} is not a gate of a cell"),
                ));
            }
        }
        Ok(())
    }
}

/// An array's configuration (the world's side; a lab knows the gate names,
/// the readout groups and the limits, not the crosstalk).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayConfig {
    /// Number of cells, 1..=[`MAX_CELLS`].
    pub cells: u32,
    /// Where the cells sit (default a chain; a ladder needs an even number
    /// of cells, at least 4): which cells are neighbours for the crosstalk
    /// ([`crate::description::layout`]).
    #[serde(default, skip_serializing_if = "Layout::is_chain")]
    pub layout: Layout,
    /// Seed of the cell population (cells ≥ 1; see [`cell_devices`]).
    pub device_seed: u64,
    /// Crosstalk between cells.
    #[serde(default)]
    pub crosstalk: CrosstalkConfig,
    /// Readout groups: lists of cells that share a sensor readout (scans
    /// within a group are serial). `None`: one group per cell. Every cell
    /// must be in exactly one group.
    #[serde(default)]
    pub readout_groups: Option<Vec<Vec<u32>>>,
    /// Seed of the cells' noise (cell k's RNG is seeded `seed + k`).
    pub seed: u64,
}

impl ArrayConfig {
    /// A chain of `cells` with the default crosstalk and one sensor per cell.
    pub fn chain(cells: u32, device_seed: u64, seed: u64) -> Self {
        Self {
            cells,
            layout: Layout::Chain,
            device_seed,
            crosstalk: CrosstalkConfig::default(),
            readout_groups: None,
            seed,
        }
    }

    /// `Err` naming the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(1..=MAX_CELLS).contains(&self.cells) {
            return Err(ConfigError::new(
                "cells",
                format!("{} outside 1..={MAX_CELLS}", self.cells),
            ));
        }
        self.grid()?;
        self.crosstalk.validate()?;
        if let Some(groups) = &self.readout_groups {
            check_readout_groups(self.cells, groups)?;
        }
        Ok(())
    }

    /// The cells on their grid; `Err` naming `layout` as [`CellGrid::new`].
    pub fn grid(&self) -> Result<CellGrid, ConfigError> {
        CellGrid::new(self.layout, self.cells)
    }

    /// The readout group of every cell (index = cell).
    pub fn group_of_cells(&self) -> Vec<usize> {
        match &self.readout_groups {
            None => (0..self.cells as usize).collect(),
            Some(groups) => {
                let mut g = vec![0; self.cells as usize];
                for (i, group) in groups.iter().enumerate() {
                    for &c in group {
                        if let Some(slot) = g.get_mut(c as usize) {
                            *slot = i;
                        }
                    }
                }
                g
            }
        }
    }
}

/// `Err` naming the field (`readout_groups[i][j]`, `readout_groups`) unless
/// every cell of `0..cells` is in exactly one of `groups`.
///
/// ```
/// use spintune::sim::array::check_readout_groups;
/// assert!(check_readout_groups(3, &[vec![0, 2], vec![1]]).is_ok());
/// assert_eq!(check_readout_groups(3, &[vec![0, 2]]).unwrap_err().field, "readout_groups");
/// ```
pub fn check_readout_groups(cells: u32, groups: &[Vec<u32>]) -> Result<(), ConfigError> {
    let mut seen = vec![false; cells as usize];
    for (i, group) in groups.iter().enumerate() {
        for (j, &c) in group.iter().enumerate() {
            let field = format!("readout_groups[{i}][{j}]");
            if c >= cells {
                return Err(ConfigError::new(
                    field,
                    format!("cell {c} outside 0..{cells}"),
                ));
            }
            if std::mem::replace(&mut seen[c as usize], true) {
                return Err(ConfigError::new(field, format!("cell {c} listed twice")));
            }
        }
    }
    if let Some(c) = seen.iter().position(|s| !s) {
        return Err(ConfigError::new(
            "readout_groups",
            format!("cell {c} is in no group"),
        ));
    }
    Ok(())
}

/// The seed of cell `cell`'s device in the population `device_seed`
/// (a fixed mixing of both; cell 0 is the base itself).
pub fn cell_seed(device_seed: u64, cell: u32) -> u64 {
    device_seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(u64::from(cell).wrapping_mul(0xD1B5_4A32_D192_ED03))
}

/// The cells' devices: cell 0 = `base`; cell k = [`random_device`]`(base,
/// s)` with `s = cell_seed(device_seed, k) + attempt`, the first attempt
/// (< 64) `accept` takes (e.g. [`super::random::targets_reachable`]; else
/// the last draw).
pub fn cell_devices(
    base: &DeviceConfig,
    cells: u32,
    device_seed: u64,
    accept: impl Fn(&DeviceConfig) -> bool,
) -> Vec<DeviceConfig> {
    (0..cells)
        .map(|k| {
            if k == 0 {
                return base.clone();
            }
            let mut d = base.clone();
            for attempt in 0..64u64 {
                d = random_device(base, cell_seed(device_seed, k).wrapping_add(attempt));
                if accept(&d) {
                    break;
                }
            }
            d
        })
        .collect()
}

/// The array name of gate `gate` of cell `cell`, e.g. `c3.SB`.
pub fn gate_name(cell: u32, gate: &str) -> String {
    format!("c{cell}.{gate}")
}

/// The array name of parameter `parameter` of cell `cell`, e.g. `c3.t_sr`.
pub fn parameter_name(cell: u32, parameter: &str) -> String {
    format!("c{cell}.{parameter}")
}

/// `c3.SB` → `(3, "SB")`; `None` for a name without a cell prefix.
///
/// ```
/// use spintune::sim::array::{gate_name, split_gate};
/// assert_eq!(split_gate(&gate_name(12, "SB")), Some((12, "SB")));
/// assert_eq!(split_gate("SB"), None);
/// ```
pub fn split_gate(name: &str) -> Option<(u32, &str)> {
    let rest = name.strip_prefix('c')?;
    let (cell, local) = rest.split_once('.')?;
    Some((cell.parse().ok()?, local))
}

/// The default gates of one cell, prefixed with the cell.
pub fn cell_gates(cell: u32) -> Vec<GateSpec> {
    super::default_gates()
        .into_iter()
        .map(|g| GateSpec {
            name: gate_name(cell, &g.name),
            ..g
        })
        .collect()
}

/// An array of simulated double dots (see the module docs). Plain data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayDevice {
    config: ArrayConfig,
    cells: Vec<SimulatedDevice>,
    /// Commanded voltages per cell (unprefixed gate → mV).
    commanded: Vec<BTreeMap<String, f64>>,
    /// Start voltages per cell (unprefixed gate → mV).
    start: Vec<BTreeMap<String, f64>>,
    group_of: Vec<usize>,
    lab_seconds: f64,
    truth_sealed: bool,
    truth_queries: u64,
}

impl ArrayDevice {
    /// An array with one device config per cell (`devices.len() == config.cells`),
    /// every cell at its start voltages. `Err` naming the field.
    pub fn new(config: ArrayConfig, devices: Vec<DeviceConfig>) -> Result<Self, ConfigError> {
        config.validate()?;
        if devices.len() != config.cells as usize {
            return Err(ConfigError::new(
                "cells",
                format!("{} cells but {} devices", config.cells, devices.len()),
            ));
        }
        let gates = super::default_gates();
        let mut cells = Vec::new();
        for (k, d) in devices.into_iter().enumerate() {
            let dev = SimulatedDevice::new(d, &gates, config.seed.wrapping_add(k as u64))
                .map_err(|e| e.within(&format!("cell[{k}]")))?;
            cells.push(dev);
        }
        let start: Vec<BTreeMap<String, f64>> =
            cells.iter().map(|c| c.voltages_mv().clone()).collect();
        Ok(Self {
            group_of: config.group_of_cells(),
            commanded: start.clone(),
            start,
            cells,
            config,
            lab_seconds: 0.0,
            truth_sealed: false,
            truth_queries: 0,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ArrayConfig {
        &self.config
    }

    /// Number of cells.
    pub fn cells(&self) -> u32 {
        self.config.cells
    }

    /// Every gate of the array (prefixed names, with limits and step limits).
    pub fn gates(&self) -> Vec<GateSpec> {
        (0..self.cells()).flat_map(cell_gates).collect()
    }

    /// The readout group of `cell`.
    pub fn group_of(&self, cell: u32) -> Option<usize> {
        self.group_of.get(cell as usize).copied()
    }

    /// Commanded voltages of every gate (prefixed names), mV: what a read-back returns.
    pub fn voltages_mv(&self) -> BTreeMap<String, f64> {
        let mut all = BTreeMap::new();
        for (k, v) in self.commanded.iter().enumerate() {
            for (g, &mv) in v {
                all.insert(gate_name(k as u32, g), mv);
            }
        }
        all
    }

    /// The voltages cell `cell`'s own model sees (crosstalk included; unprefixed), mV.
    pub fn effective_voltages_mv(&self, cell: u32) -> Option<&BTreeMap<String, f64>> {
        self.cells
            .get(cell as usize)
            .map(SimulatedDevice::voltages_mv)
    }

    /// The array's lab clock, s.
    pub fn lab_seconds(&self) -> f64 {
        self.lab_seconds
    }

    /// World side only (never handed to a strategy; invariant 7): the
    /// noiseless truth of `cell` at the present voltages.
    pub fn truth(&self, cell: u32) -> Option<Truth> {
        self.cells.get(cell as usize).map(SimulatedDevice::truth)
    }

    /// World side: cell `cell`'s transition lines now, drift included
    /// ([`SimulatedDevice::lines_now_mv`]), mV; `None` if there is no such cell.
    pub fn lines_now_mv(&self, cell: u32) -> Option<[f64; 2]> {
        self.cells
            .get(cell as usize)
            .map(SimulatedDevice::lines_now_mv)
    }

    /// World side: a charge rearrangement near cell `cell`'s dots
    /// ([`SimulatedDevice::rearrange_charges`]): its two transition lines
    /// jump by `shift_mv` (mV on its RFA / RFB) and stay there. No gate
    /// moves; a tuner finds out by scanning. `false` if there is no such cell.
    ///
    /// ```
    /// use spintune::sim::array::{ArrayConfig, ArrayDevice};
    /// use spintune::sim::DeviceConfig;
    /// let mut a = ArrayDevice::new(ArrayConfig::chain(2, 0, 1), vec![DeviceConfig::default(); 2]).unwrap();
    /// assert!(a.rearrange_charges(1, [7.0, 0.0]));
    /// assert!(!a.rearrange_charges(2, [7.0, 0.0]));
    /// ```
    pub fn rearrange_charges(&mut self, cell: u32, shift_mv: [f64; 2]) -> bool {
        self.cells
            .get_mut(cell as usize)
            .map(|c| c.rearrange_charges(shift_mv))
            .is_some()
    }

    /// Refuse [`Request::TrueJacobian`] from now on (still counted). Irreversible.
    pub fn seal_truth(&mut self) {
        self.truth_sealed = true;
    }

    /// Whether [`ArrayDevice::seal_truth`] was called.
    pub fn is_truth_sealed(&self) -> bool {
        self.truth_sealed
    }

    /// [`Request::TrueJacobian`] requests received (answered or refused).
    pub fn truth_queries(&self) -> u64 {
        self.truth_queries
    }

    /// The cell a request belongs to (its readout group decides its slot in
    /// a batch): a scan's `cell` (or its sweep gate's prefix), a set's or
    /// read's first gate. `None` for a wait or a truth request.
    pub fn cell_of(request: &Request) -> Option<u32> {
        match request {
            Request::Measure { scan } => scan.cell.or_else(|| {
                scan.sweep
                    .as_ref()
                    .and_then(|s| split_gate(&s.gate))
                    .map(|(c, _)| c)
            }),
            Request::SetVoltages { voltages_mv } => voltages_mv
                .keys()
                .next()
                .and_then(|g| split_gate(g))
                .map(|(c, _)| c),
            Request::ReadVoltages { gates } => {
                gates.first().and_then(|g| split_gate(g)).map(|(c, _)| c)
            }
            Request::Wait { .. } | Request::TrueJacobian { .. } | Request::Batch { .. } => None,
        }
    }

    /// One request: a [`Request::Batch`] runs as [`ArrayDevice::execute_batch`]
    /// and is answered by [`Response::Batch`] with the array clock's advance;
    /// any other request alone (a batch of one).
    pub fn execute(&mut self, request: &Request) -> Response {
        if let Request::Batch { requests } = request {
            let before = self.lab_seconds;
            let responses = self.execute_batch(requests);
            return Response::Batch {
                responses,
                lab_seconds: self.lab_seconds - before,
            };
        }
        self.execute_batch(std::slice::from_ref(request))
            .pop()
            .unwrap_or_else(|| Response::error("empty batch"))
    }

    /// Runs `requests` as one batch (at most [`MAX_BATCH`]; more are refused
    /// one by one with an error and no effect): in order, each charged its
    /// own lab time; the array clock advances by the largest sum of lab time
    /// over one readout group (requests without a cell, such as a wait,
    /// form a group of their own). Every cell then idles for the batch's
    /// time it was not busy. Responses in request order.
    pub fn execute_batch(&mut self, requests: &[Request]) -> Vec<Response> {
        let groups = self.group_of.iter().max().map_or(0, |m| m + 1);
        let mut group_seconds = vec![0.0; groups + 1];
        let mut busy = vec![0.0; self.cells.len()];
        let mut out = Vec::with_capacity(requests.len());
        for (i, request) in requests.iter().enumerate() {
            if i >= MAX_BATCH {
                out.push(Response::error(format!(
                    "more than {MAX_BATCH} requests in one batch"
                )));
                continue;
            }
            let response = self.execute_one(request);
            let seconds = response.lab_seconds();
            let cell = Self::cell_of(request).filter(|&c| c < self.cells());
            let slot = cell.map_or(groups, |c| self.group_of[c as usize]);
            group_seconds[slot] += seconds;
            match (cell, request) {
                (Some(c), _) => busy[c as usize] += seconds,
                // a wait lets every cell idle; the truth costs nothing
                (None, Request::Wait { .. }) => busy.iter_mut().for_each(|b| *b += seconds),
                (None, _) => {}
            }
            out.push(response);
        }
        let batch = group_seconds.iter().copied().fold(0.0, f64::max);
        for (dev, b) in self.cells.iter_mut().zip(busy) {
            dev.idle(batch - b);
        }
        self.lab_seconds += batch;
        out
    }

    fn execute_one(&mut self, request: &Request) -> Response {
        match request {
            Request::Batch { .. } => Response::error("a batch inside a batch"),
            Request::SetVoltages { voltages_mv } => self.set(voltages_mv),
            Request::ReadVoltages { gates } => {
                let mut read = BTreeMap::new();
                for g in gates {
                    match self.commanded_of(g) {
                        Some(v) => read.insert(g.clone(), v),
                        None => return Response::error(format!("unknown gate {g:?}")),
                    };
                }
                Response::VoltagesRead {
                    voltages_mv: read,
                    lab_seconds: 0.0,
                }
            }
            Request::Measure { scan } => self.measure(scan),
            Request::Wait { seconds } => {
                if !(seconds.is_finite()
                    && *seconds > 0.0
                    && *seconds <= crate::protocol::MAX_WAIT_SECONDS)
                {
                    return Response::error(format!(
                        "a wait of {seconds} s (allowed: more than 0, at most {} s)",
                        crate::protocol::MAX_WAIT_SECONDS
                    ));
                }
                // the clocks advance in `execute_batch` (every cell idles)
                Response::Waited {
                    lab_seconds: *seconds,
                }
            }
            Request::TrueJacobian { gates, parameters } => {
                self.truth_queries += 1;
                if self.truth_sealed {
                    return Response::error(
                        "the true Jacobian is sealed on this array: only the oracle \
                         may read the simulator's truth (ARCHITECTURE.md invariant 7)",
                    );
                }
                let g: Vec<&str> = gates.iter().map(String::as_str).collect();
                let p: Vec<&str> = parameters.iter().map(String::as_str).collect();
                match (self.true_values(&p), self.true_jacobian(&g, &p)) {
                    (Ok(values), Ok(j)) => Response::TrueJacobian {
                        values,
                        jacobian: (0..j.nrows())
                            .map(|r| j.row(r).iter().copied().collect())
                            .collect(),
                    },
                    (Err(m), _) | (_, Err(m)) => Response::error(m),
                }
            }
        }
    }

    fn commanded_of(&self, gate: &str) -> Option<f64> {
        let (c, local) = split_gate(gate)?;
        self.commanded.get(c as usize)?.get(local).copied()
    }

    fn set(&mut self, request: &BTreeMap<String, f64>) -> Response {
        let gates = super::default_gates();
        let mut parsed = Vec::new();
        for (name, &v) in request {
            let Some((c, local)) = split_gate(name).filter(|(c, _)| *c < self.cells()) else {
                return Response::error(format!("unknown gate {name:?}"));
            };
            let Some(spec) = gates.iter().find(|g| g.name == local) else {
                return Response::error(format!("unknown gate {name:?}"));
            };
            if !(v.is_finite() && (spec.min_mv..=spec.max_mv).contains(&v)) {
                return Response::error(format!(
                    "gate {name:?}: {v} mV outside the device limits [{}, {}] mV",
                    spec.min_mv, spec.max_mv
                ));
            }
            parsed.push((c, local.to_string(), v));
        }
        let mut touched = Vec::new();
        for (c, local, v) in parsed {
            self.commanded[c as usize].insert(local, v);
            touched.push(c);
        }
        touched.sort_unstable();
        touched.dedup();
        self.apply_crosstalk();
        let dt = touched.first().map_or(0.0, |&c| {
            self.cells[c as usize].config.durations.set_voltages_s
        });
        Response::VoltagesSet {
            voltages_mv: request
                .keys()
                .filter_map(|k| Some((k.clone(), self.commanded_of(k)?)))
                .collect(),
            lab_seconds: dt,
        }
    }

    /// Effective voltages of every cell from the commanded ones (module docs).
    fn apply_crosstalk(&mut self) {
        let effective = self.effective_from(&self.commanded);
        for (dev, v) in self.cells.iter_mut().zip(effective) {
            dev.voltages_mv = v;
        }
    }

    fn effective_from(&self, commanded: &[BTreeMap<String, f64>]) -> Vec<BTreeMap<String, f64>> {
        let x = &self.config.crosstalk;
        let grid = CellGrid::or_chain(self.config.layout, commanded.len());
        (0..commanded.len())
            .map(|j| {
                let mut v = commanded[j].clone();
                for g in &x.gates {
                    let mut shift = 0.0;
                    for (k, other) in commanded.iter().enumerate() {
                        let lambda = x.lambda(grid.distance(j, k) as u32);
                        if k == j || lambda == 0.0 {
                            continue;
                        }
                        if let (Some(now), Some(s)) = (other.get(g), self.start[k].get(g)) {
                            shift += lambda * (now - s);
                        }
                    }
                    if let Some(e) = v.get_mut(g) {
                        *e += shift;
                    }
                }
                v
            })
            .collect()
    }

    fn measure(&mut self, scan: &ScanRequest) -> Response {
        let failed = |reason: String| Response::Scanned {
            outcome: ScanOutcome::Failed { reason },
            lab_seconds: 0.0,
        };
        let Some(c) = Self::cell_of(&Request::Measure { scan: scan.clone() }) else {
            return failed("an array scan must name its cell".into());
        };
        if c >= self.cells() {
            return failed(format!("cell {c} outside 0..{}", self.cells()));
        }
        let mut local = scan.clone();
        local.cell = None;
        if let Some(sweep) = &mut local.sweep {
            match split_gate(&sweep.gate) {
                Some((sc, g)) if sc == c => {
                    // the cell's model sweeps its effective voltage
                    let offset = self.cells[c as usize]
                        .voltages_mv
                        .get(g)
                        .copied()
                        .unwrap_or(0.0)
                        - self.commanded[c as usize].get(g).copied().unwrap_or(0.0);
                    sweep.gate = g.to_string();
                    sweep.from_mv += offset;
                    sweep.to_mv += offset;
                }
                _ => {
                    return failed(format!(
                        "sweep gate {:?} is not a gate of cell {c}",
                        sweep.gate
                    ))
                }
            }
        }
        match self.cells[c as usize].scan(&local) {
            Ok((scan, lab_seconds)) => Response::Scanned {
                outcome: ScanOutcome::Raw { scan },
                lab_seconds,
            },
            Err(e) => failed(e.to_string()),
        }
    }

    fn true_values(&self, parameters: &[&str]) -> Result<Vec<f64>, String> {
        parameters
            .iter()
            .map(|p| {
                let (c, local) = split_gate(p)
                    .filter(|(c, _)| *c < self.cells())
                    .ok_or_else(|| format!("unknown parameter {p:?}"))?;
                self.cells[c as usize]
                    .truth()
                    .get(local)
                    .ok_or_else(|| format!("unknown parameter {p:?}"))
            })
            .collect()
    }

    /// Noiseless Jacobian of prefixed `parameters` (e.g. `c2.w`) with
    /// respect to the commanded voltages of prefixed `gates`, crosstalk
    /// included (central differences, step [`JACOBIAN_STEP_MV`]; unit/mV).
    /// World side and the oracle's only.
    pub fn true_jacobian(
        &self,
        gates: &[&str],
        parameters: &[&str],
    ) -> Result<DMatrix<f64>, String> {
        self.true_values(parameters)?;
        let mut j = DMatrix::zeros(parameters.len(), gates.len());
        for (col, gate) in gates.iter().enumerate() {
            let (c, local) = split_gate(gate)
                .filter(|(c, l)| *c < self.cells() && self.commanded[*c as usize].contains_key(*l))
                .ok_or_else(|| format!("unknown gate {gate:?}"))?;
            let eval = |delta: f64| -> Vec<Truth> {
                let mut cmd = self.commanded.clone();
                if let Some(v) = cmd[c as usize].get_mut(local) {
                    *v += delta;
                }
                let eff = self.effective_from(&cmd);
                self.cells
                    .iter()
                    .zip(&eff)
                    .map(|(dev, v)| dev.truth_at(v))
                    .collect()
            };
            let (plus, minus) = (eval(JACOBIAN_STEP_MV), eval(-JACOBIAN_STEP_MV));
            for (row, p) in parameters.iter().enumerate() {
                let (pc, pl) = split_gate(p).expect("checked by true_values");
                let a = plus[pc as usize].get(pl).unwrap_or(f64::NAN);
                let b = minus[pc as usize].get(pl).unwrap_or(f64::NAN);
                j[(row, col)] = (a - b) / (2.0 * JACOBIAN_STEP_MV);
            }
        }
        Ok(j)
    }
}
