//! What the array overview shows of a run of an array of double-dot cells
//! (issue 24): whether a run is one (its parameters are named per cell,
//! `c{k}.t_sr`, `c{k}.w`), one tile per cell (in band or not, values
//! against targets, lab time) and the heat map of the learned |Jacobian|
//! with the prior's block structure (a cell's own gates and its nearest
//! neighbours'). Plain data from an [`IterationRecord`]; drawn by
//! [`crate::array_panel`].

use spintune::protocol::{EventKind, IterationRecord, ParameterReport, TunerEvent};
use spintune::sim::array::split_gate;

/// The cells of a run whose every parameter is named `c{k}.<name>`, in the
/// order they first appear (`None` for a run of one double dot: a name
/// without a cell prefix, or no parameters).
pub fn cells<'a>(parameter_names: impl IntoIterator<Item = &'a str>) -> Option<Vec<u32>> {
    let mut out: Vec<u32> = Vec::new();
    for name in parameter_names {
        let (cell, _) = split_gate(name)?;
        if !out.contains(&cell) {
            out.push(cell);
        }
    }
    (!out.is_empty()).then_some(out)
}

/// Whether `value` lies within `target ± tolerance` (`None` when any of
/// them is missing).
pub fn in_band(value: Option<f64>, target: Option<f64>, tolerance: Option<f64>) -> Option<bool> {
    let (v, t) = (value?, target?);
    let tol = tolerance.unwrap_or(0.0);
    (v.is_finite() && t.is_finite()).then(|| (v - t).abs() <= tol)
}

/// Where a cell stands against its targets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Band {
    /// Every parameter of the cell within its target ± tolerance.
    In,
    /// Some parameter measured outside its band.
    Out,
    /// Some parameter without a measurement (or target), none outside.
    Unknown,
}

impl Band {
    /// Text on the tile.
    pub fn label(self) -> &'static str {
        match self {
            Band::In => "in band",
            Band::Out => "out of band",
            Band::Unknown => "not measured",
        }
    }

    /// CSS class and `data-band` of the tile.
    pub fn name(self) -> &'static str {
        match self {
            Band::In => "in",
            Band::Out => "out",
            Band::Unknown => "unknown",
        }
    }

    /// Of several parameters' `in_band` answers: out if any is out, in if
    /// all are in, unknown otherwise (and for none).
    pub fn of(each: impl IntoIterator<Item = Option<bool>>) -> Self {
        let mut all_in = true;
        let mut any = false;
        for b in each {
            any = true;
            match b {
                Some(false) => return Band::Out,
                Some(true) => {}
                None => all_in = false,
            }
        }
        if any && all_in {
            Band::In
        } else {
            Band::Unknown
        }
    }
}

/// One parameter of a cell, its name without the cell prefix.
#[derive(Debug, Clone, PartialEq)]
pub struct CellParameter {
    /// E.g. `t_sr`.
    pub name: String,
    /// E.g. `ns`.
    pub unit: String,
    /// Measured value.
    pub value: Option<f64>,
    /// Its σ.
    pub std: Option<f64>,
    /// Target.
    pub target: Option<f64>,
    /// Half-width of the band.
    pub tolerance: Option<f64>,
    /// Within target ± tolerance ([`in_band`]).
    pub in_band: Option<bool>,
    /// `value` is the filter's prediction: the cell's scan was skipped
    /// (it shares a sensor and was predicted in band with margin).
    pub predicted: bool,
    /// `value` is a second scan's: the cell had just entered its band near
    /// the edge, and the run scanned it again before stopping (the
    /// record's `band_entry_rechecked` event).
    pub rechecked: bool,
}

impl CellParameter {
    /// The parameter as reported, or (not measured) as the record's
    /// `confirmation_skipped` event for it predicts it, or (scanned again)
    /// as its `band_entry_rechecked` event read it last.
    fn of(local: &str, p: &ParameterReport, events: &[TunerEvent]) -> Self {
        let again = events.iter().find_map(|e| match &e.kind {
            EventKind::BandEntryRechecked {
                parameter,
                value,
                std,
                ..
            } if parameter == &p.name => Some((*value, *std)),
            _ => None,
        });
        let skipped = p.value.is_none().then(|| {
            events.iter().find_map(|e| match &e.kind {
                EventKind::ConfirmationSkipped {
                    parameter,
                    predicted,
                    std,
                    ..
                } if parameter == &p.name => Some((*predicted, *std)),
                _ => None,
            })
        });
        let (value, std, predicted) = match (again, skipped.flatten()) {
            (Some((v, s)), _) => (v, s, false),
            (None, Some((v, s))) => (Some(v), Some(s), true),
            (None, None) => (p.value, p.std, false),
        };
        Self {
            name: local.to_string(),
            unit: p.unit.clone(),
            value,
            std,
            target: p.target,
            tolerance: p.tolerance,
            in_band: in_band(value, p.target, p.tolerance),
            predicted,
            rechecked: again.is_some(),
        }
    }

    /// "19.8 ns (target 20 ± 2 ns)" — value and target with units.
    pub fn text(&self) -> String {
        let n = |x: f64| crate::charts::num_label(&x);
        let u = &self.unit;
        let value = match (self.value, self.predicted) {
            (None, _) => "no valid measurement".to_string(),
            (Some(v), _) if self.rechecked => format!("{} {u}, scanned again", n(v)),
            (Some(v), false) => format!("{} {u}", n(v)),
            (Some(v), true) => format!("predicted {} {u}, scan skipped", n(v)),
        };
        let target = match (self.target, self.tolerance) {
            (Some(t), Some(tol)) => format!("target {} ± {} {u}", n(t), n(tol)),
            (Some(t), None) => format!("target {} {u}", n(t)),
            _ => "no target".to_string(),
        };
        format!("{value} ({target})")
    }
}

/// One cell's tile.
#[derive(Debug, Clone, PartialEq)]
pub struct Tile {
    /// Cell number k (of `c{k}.…`).
    pub cell: u32,
    /// Its parameters in the record's order (t_sr, w).
    pub parameters: Vec<CellParameter>,
    /// In band when every parameter is ([`Band::of`]).
    pub band: Band,
    /// Lab time of the record, minutes (the array's clock: one for all cells).
    pub lab_minutes: f64,
}

/// A tile per cell of `record`, in cell order of first appearance (none
/// for a record of one double dot).
pub fn tiles(record: &IterationRecord) -> Vec<Tile> {
    let Some(cells) = cells(record.parameters.iter().map(|p| p.name.as_str())) else {
        return Vec::new();
    };
    cells
        .into_iter()
        .map(|cell| {
            let parameters: Vec<CellParameter> = record
                .parameters
                .iter()
                .filter_map(|p| match split_gate(&p.name) {
                    Some((c, local)) if c == cell => {
                        Some(CellParameter::of(local, p, &record.events))
                    }
                    _ => None,
                })
                .collect();
            Tile {
                cell,
                band: Band::of(parameters.iter().map(|p| p.in_band)),
                parameters,
                lab_minutes: record.lab_seconds / 60.0,
            }
        })
        .collect()
}

/// What the prior expects of a Jacobian element: rows of cell c are
/// non-zero only over the gates of cell c (own block) and of the cells in
/// its neighbourhood (neighbour blocks: c ± 1 in a chain, and the cell
/// across the rung in a ladder). The joint tuner's rows are exactly zero
/// outside their neighbourhood, so a record shows it: [`heat_map`] takes a
/// neighbour block to be one with a non-zero element.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prior {
    /// The row's own cell's gates.
    Own,
    /// A nearest neighbour's gates.
    Neighbour,
    /// Further away: the prior says zero.
    Outside,
}

impl Prior {
    /// Of a row of cell `row` and a gate of cell `col` in a chain (the
    /// previews' records, [`fake_array_records`]).
    pub fn in_chain(row: u32, col: u32) -> Self {
        match row.abs_diff(col) {
            0 => Prior::Own,
            1 => Prior::Neighbour,
            _ => Prior::Outside,
        }
    }

    /// `data-prior` of a heat-map element.
    pub fn name(self) -> &'static str {
        match self {
            Prior::Own => "own",
            Prior::Neighbour => "neighbour",
            Prior::Outside => "outside",
        }
    }
}

/// A rectangle of heat-map elements sharing one [`Prior`] (`Own` or
/// `Neighbour`): rows `row0..row0 + rows`, columns `col0..col0 + cols`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Block {
    /// First row.
    pub row0: usize,
    /// Rows.
    pub rows: usize,
    /// First column.
    pub col0: usize,
    /// Columns.
    pub cols: usize,
    /// Own cell or nearest neighbour.
    pub prior: Prior,
}

/// The learned |Jacobian| of an array record: rows the parameters
/// (`c{k}.t_sr`, `c{k}.w`), columns the tuning gates (`c{k}.N`, …).
#[derive(Debug, Clone, PartialEq)]
pub struct HeatMap {
    /// Iteration of the record.
    pub iteration: u64,
    /// Row names (parameters).
    pub rows: Vec<String>,
    /// Column names (gates).
    pub cols: Vec<String>,
    /// Unit of the gradients (`1/mV`: log space).
    pub unit: String,
    /// `values[r][c]` = |∂p_r/∂V_c| (NaN where the record has no row or element).
    pub values: Vec<Vec<f64>>,
    /// Cell of each row.
    pub row_cells: Vec<u32>,
    /// Cell of each column.
    pub col_cells: Vec<u32>,
    /// `(row cell, column cell)` of every block of two different cells
    /// with a non-zero element: the rows' neighbourhoods.
    pub neighbour_blocks: Vec<(u32, u32)>,
}

impl HeatMap {
    /// What the prior expects of element `(r, c)`.
    pub fn prior(&self, r: usize, c: usize) -> Prior {
        self.prior_of_cells(self.row_cells[r], self.col_cells[c])
    }

    /// What the prior expects of a row of cell `row` over a gate of cell `col`.
    fn prior_of_cells(&self, row: u32, col: u32) -> Prior {
        if row == col {
            Prior::Own
        } else if self.neighbour_blocks.contains(&(row, col)) {
            Prior::Neighbour
        } else {
            Prior::Outside
        }
    }

    /// The block mask: [`Prior`] of every element, row by row.
    pub fn mask(&self) -> Vec<Vec<Prior>> {
        (0..self.rows.len())
            .map(|r| (0..self.cols.len()).map(|c| self.prior(r, c)).collect())
            .collect()
    }

    /// The prior's non-zero blocks (own cell and nearest neighbours), one
    /// per pair of a run of rows of one cell and a run of columns of one
    /// cell: what the heat map outlines.
    pub fn blocks(&self) -> Vec<Block> {
        let rows = cell_runs(&self.row_cells);
        let cols = cell_runs(&self.col_cells);
        let mut out = Vec::new();
        for &(rc, row0, nr) in &rows {
            for &(cc, col0, nc) in &cols {
                let prior = self.prior_of_cells(rc, cc);
                if prior != Prior::Outside {
                    out.push(Block {
                        row0,
                        rows: nr,
                        col0,
                        cols: nc,
                        prior,
                    });
                }
            }
        }
        out
    }

    /// Largest finite |element| where the prior expects `prior` (NaN if none).
    pub fn max_where(&self, prior: Prior) -> f64 {
        self.values
            .iter()
            .enumerate()
            .flat_map(|(r, row)| row.iter().enumerate().map(move |(c, v)| (r, c, *v)))
            .filter(|&(r, c, v)| v.is_finite() && self.prior(r, c) == prior)
            .map(|(_, _, v)| v)
            .fold(f64::NAN, f64::max)
    }

    /// Largest finite |element| (NaN if none).
    pub fn max(&self) -> f64 {
        self.values
            .iter()
            .flatten()
            .copied()
            .filter(|v| v.is_finite())
            .fold(f64::NAN, f64::max)
    }
}

/// Runs of equal cells in a row or column order: `(cell, first index,
/// length)` (a heat map's groups of rows or columns).
pub fn cell_runs(cells: &[u32]) -> Vec<(u32, usize, usize)> {
    let mut out: Vec<(u32, usize, usize)> = Vec::new();
    for (i, &c) in cells.iter().enumerate() {
        match out.last_mut() {
            Some(last) if last.0 == c => last.2 += 1,
            _ => out.push((c, i, 1)),
        }
    }
    out
}

/// The heat map of `record`'s learned gradients: a row per parameter (in
/// the record's order, matched to its gradient by name), a column per
/// gate of `record.gates`; `None` unless every parameter and gate is
/// named per cell and there is a gradient.
pub fn heat_map(record: &IterationRecord) -> Option<HeatMap> {
    if record.gradients.is_empty() {
        return None;
    }
    let row_cells = record
        .parameters
        .iter()
        .map(|p| split_gate(&p.name).map(|c| c.0))
        .collect::<Option<Vec<u32>>>()?;
    let col_cells = record
        .gates
        .iter()
        .map(|g| split_gate(g).map(|c| c.0))
        .collect::<Option<Vec<u32>>>()?;
    if row_cells.is_empty() || col_cells.is_empty() {
        return None;
    }
    let values = record
        .parameters
        .iter()
        .map(|p| {
            let g = record.gradients.iter().find(|g| g.parameter == p.name);
            (0..record.gates.len())
                .map(|c| {
                    g.and_then(|g| g.gradient.get(c))
                        .map_or(f64::NAN, |v| v.abs())
                })
                .collect()
        })
        .collect::<Vec<Vec<f64>>>();
    let mut neighbour_blocks = Vec::new();
    for (row, &rc) in values.iter().zip(&row_cells) {
        for (v, &cc) in row.iter().zip(&col_cells) {
            if rc != cc && *v != 0.0 && !v.is_nan() && !neighbour_blocks.contains(&(rc, cc)) {
                neighbour_blocks.push((rc, cc));
            }
        }
    }
    Some(HeatMap {
        iteration: record.iteration,
        rows: record.parameters.iter().map(|p| p.name.clone()).collect(),
        cols: record.gates.clone(),
        unit: record
            .gradients
            .first()
            .map(|g| g.unit.clone())
            .unwrap_or_default(),
        values,
        row_cells,
        col_cells,
        neighbour_blocks,
    })
}

/// Deterministic records of an array of `cells` cells for tests and
/// previews: the array's parameter, gate and gradient names, units and
/// block-banded gradients (own block ≈ 0.05 /mV, neighbours ≈ 0.005 /mV,
/// zero beyond); cell 1 stays out of band in `w` until iteration 4.
pub fn fake_array_records(n: u64, cells: u32) -> Vec<IterationRecord> {
    use spintune::protocol::GradientReport;
    use spintune::sim::array::{gate_name, parameter_name};
    let local = ["N", "SA", "SB", "T"];
    let gates: Vec<String> = (0..cells)
        .flat_map(|c| local.map(|g| gate_name(c, g)))
        .collect();
    (0..n)
        .map(|k| {
            let kf = k as f64;
            let mut parameters = Vec::new();
            let mut gradients = Vec::new();
            for c in 0..cells {
                let off = if c == 1 && k < 4 { 60.0 } else { 0.0 };
                for (name, unit, target, tol, value) in [
                    ("t_sr", "ns", 20.0, 2.0, 20.0 + 0.3 * (kf + c as f64).sin()),
                    ("w", "µV", 270.0, 27.0, 270.0 + off + 3.0 * (kf * 0.7).cos()),
                ] {
                    let p = parameter_name(c, name);
                    parameters.push(ParameterReport {
                        name: p.clone(),
                        unit: unit.into(),
                        value: Some(value),
                        std: Some(tol / 4.0),
                        target: Some(target),
                        tolerance: Some(tol),
                    });
                    let sign = if name == "w" { -1.0 } else { 1.0 };
                    gradients.push(GradientReport {
                        parameter: p,
                        unit: "1/mV".into(),
                        gradient: gates
                            .iter()
                            .enumerate()
                            .map(|(i, _)| {
                                let gc = (i / 4) as u32;
                                let scale = match Prior::in_chain(c, gc) {
                                    Prior::Own => 0.05,
                                    Prior::Neighbour => 0.005,
                                    Prior::Outside => 0.0,
                                };
                                sign * scale * (1.0 + 0.1 * (i % 4) as f64 + 0.01 * kf)
                            })
                            .collect(),
                        covariance: None,
                    });
                }
            }
            let voltages_mv = gates
                .iter()
                .enumerate()
                .map(|(i, g)| (g.clone(), -500.0 + 10.0 * (i % 4) as f64 + 0.5 * kf))
                .collect();
            let tuned = parameters
                .iter()
                .all(|p| in_band(p.value, p.target, p.tolerance) == Some(true));
            IterationRecord {
                iteration: k,
                voltages_mv,
                gates: gates.clone(),
                parameters,
                gradients,
                step_mv: vec![0.5; gates.len()],
                tuned,
                lab_seconds: 45.0 * (kf + 1.0),
                scan_counts: Default::default(),
                failed_evaluations: 0,
                scans: Vec::new(),
                events: Vec::new(),
                keep: None,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::fake_records;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_run_of_cells_is_told_from_its_parameter_names() {
        let names = ["c0.t_sr", "c0.w", "c1.t_sr", "c1.w", "c2.t_sr", "c2.w"];
        assert_eq!(cells(names), Some(vec![0, 1, 2]));
        assert_eq!(cells(["t_sr", "w"]), None);
        assert_eq!(cells(["c0.t_sr", "w"]), None, "all or nothing");
        assert_eq!(cells(std::iter::empty()), None);
        let single = &fake_records(1)[0];
        assert!(tiles(single).is_empty());
        assert!(heat_map(single).is_none());
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn in_band_is_within_target_plus_minus_tolerance_for_every_parameter() {
        assert_eq!(in_band(Some(21.9), Some(20.0), Some(2.0)), Some(true));
        assert_eq!(in_band(Some(22.0), Some(20.0), Some(2.0)), Some(true));
        assert_eq!(in_band(Some(17.9), Some(20.0), Some(2.0)), Some(false));
        assert_eq!(in_band(None, Some(20.0), Some(2.0)), None);
        assert_eq!(in_band(Some(20.0), None, Some(2.0)), None);
        assert_eq!(in_band(Some(f64::NAN), Some(20.0), Some(2.0)), None);
        assert_eq!(Band::of([Some(true), Some(true)]), Band::In);
        assert_eq!(Band::of([Some(true), Some(false)]), Band::Out);
        assert_eq!(Band::of([None, Some(false)]), Band::Out);
        assert_eq!(Band::of([Some(true), None]), Band::Unknown);
        assert_eq!(Band::of([]), Band::Unknown);
        assert_eq!(Band::In.label(), "in band");
        assert_eq!(Band::Out.label(), "out of band");
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_tile_per_cell_with_values_targets_units_and_lab_minutes() {
        let recs = fake_array_records(6, 3);
        let t = tiles(&recs[2]);
        assert_eq!(t.iter().map(|t| t.cell).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(
            t.iter().map(|t| t.band).collect::<Vec<_>>(),
            [Band::In, Band::Out, Band::In]
        );
        let c1 = &t[1];
        assert_eq!(c1.parameters.len(), 2);
        assert_eq!(
            (
                c1.parameters[0].name.as_str(),
                c1.parameters[0].unit.as_str()
            ),
            ("t_sr", "ns")
        );
        assert_eq!(
            (
                c1.parameters[1].name.as_str(),
                c1.parameters[1].unit.as_str()
            ),
            ("w", "µV")
        );
        assert_eq!(c1.parameters[1].in_band, Some(false));
        assert!((c1.lab_minutes - 45.0 * 3.0 / 60.0).abs() < 1e-12);
        let text = c1.parameters[1].text();
        assert!(text.ends_with("µV (target 270 ± 27.0 µV)"), "{text}");
        assert!(tiles(&recs[5]).iter().all(|t| t.band == Band::In));
        let mut unmeasured = recs[5].clone();
        unmeasured.parameters[2].value = None;
        assert_eq!(tiles(&unmeasured)[1].band, Band::Unknown);
        assert!(tiles(&unmeasured)[1].parameters[0]
            .text()
            .starts_with("no valid measurement"));
        // a skipped scan: the tile shows the prediction, in band by it
        unmeasured.events.push(TunerEvent {
            level: "array".into(),
            kind: EventKind::ConfirmationSkipped {
                parameter: unmeasured.parameters[2].name.clone(),
                predicted: 20.5,
                std: 0.4,
                unit: "ns".into(),
            },
        });
        let tile = &tiles(&unmeasured)[1];
        assert_eq!(tile.band, Band::In, "{tile:?}");
        assert!(tile.parameters[0].predicted);
        assert!(
            tile.parameters[0]
                .text()
                .starts_with("predicted 20.5 ns, scan skipped"),
            "{}",
            tile.parameters[0].text()
        );
        // a second scan of a cell that had just entered its band read it
        // out: the tile shows that latest reading, out of band
        let mut rechecked = recs[5].clone();
        rechecked.events.push(TunerEvent {
            level: "array".into(),
            kind: EventKind::BandEntryRechecked {
                parameter: rechecked.parameters[3].name.clone(),
                value: Some(300.0),
                std: Some(12.0),
                in_band: false,
                unit: "µV".into(),
            },
        });
        let tile = &tiles(&rechecked)[1];
        assert_eq!(tile.band, Band::Out, "{tile:?}");
        assert!(tile.parameters[1].rechecked && !tile.parameters[0].rechecked);
        assert!(
            tile.parameters[1]
                .text()
                .starts_with("300 µV, scanned again"),
            "{}",
            tile.parameters[1].text()
        );
    }

    /// A 2×2 ladder (cells 0 1 over 2 3): cell 0's rows span cells 1 and
    /// 2 (across the rung), not 3. The record says so (exactly zero outside
    /// a row's neighbourhood), and the mask follows the record, not the
    /// chain's c ± 1.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_ladder_s_rung_neighbour_is_a_neighbour_block() {
        let mut r = fake_array_records(1, 4).remove(0);
        for g in r
            .gradients
            .iter_mut()
            .filter(|g| g.parameter.starts_with("c0."))
        {
            g.gradient[8..12].fill(0.004); // cell 2's gates
            g.gradient[12..16].fill(0.0); // cell 3's gates
        }
        let h = heat_map(&r).unwrap();
        assert_eq!(h.prior(0, 4), Prior::Neighbour);
        assert_eq!(h.prior(0, 8), Prior::Neighbour);
        assert_eq!(h.prior(1, 12), Prior::Outside);
        assert!(h
            .blocks()
            .iter()
            .any(|b| b.row0 == 0 && b.col0 == 8 && b.prior == Prior::Neighbour));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn the_heat_map_is_2k_by_4k_of_absolute_gradients_with_the_prior_s_blocks() {
        let r = &fake_array_records(3, 3)[2];
        let h = heat_map(r).unwrap();
        assert_eq!((h.rows.len(), h.cols.len()), (6, 12));
        assert_eq!(h.unit, "1/mV");
        assert_eq!(h.iteration, 2);
        assert_eq!(h.rows[3], "c1.w");
        assert_eq!(h.cols[5], "c1.SA");
        // |gradient|: the w rows are negative in the record.
        assert_eq!(h.values[3][5], r.gradients[3].gradient[5].abs());
        assert!(h.values.iter().flatten().all(|v| *v >= 0.0));
        // the mask: own, neighbour, outside
        let m = h.mask();
        assert_eq!(m[0][0], Prior::Own);
        assert_eq!(m[0][4], Prior::Neighbour);
        assert_eq!(m[0][8], Prior::Outside);
        assert_eq!(m[2][0], Prior::Neighbour);
        assert_eq!(m[2][8], Prior::Neighbour);
        assert_eq!(m[5][0], Prior::Outside);
        // blocks: 3 own + 4 neighbour (0↔1, 1↔0, 1↔2, 2↔1)
        let b = h.blocks();
        let own: Vec<_> = b.iter().filter(|b| b.prior == Prior::Own).collect();
        assert_eq!(own.len(), 3);
        assert_eq!(
            *own[1],
            Block {
                row0: 2,
                rows: 2,
                col0: 4,
                cols: 4,
                prior: Prior::Own
            }
        );
        assert_eq!(b.iter().filter(|b| b.prior == Prior::Neighbour).count(), 4);
        assert!(b.contains(&Block {
            row0: 0,
            rows: 2,
            col0: 4,
            cols: 4,
            prior: Prior::Neighbour
        }));
        // every element inside a block has the block's prior, outside none
        for (r, row) in m.iter().enumerate() {
            for (c, p) in row.iter().enumerate() {
                let inside: Vec<_> = b
                    .iter()
                    .filter(|b| (b.row0..b.row0 + b.rows).contains(&r))
                    .filter(|b| (b.col0..b.col0 + b.cols).contains(&c))
                    .collect();
                match p {
                    Prior::Outside => assert!(inside.is_empty()),
                    _ => assert_eq!(inside.iter().map(|b| b.prior).collect::<Vec<_>>(), [*p]),
                }
            }
        }
        assert_eq!(h.max_where(Prior::Outside), 0.0);
        assert!((h.max_where(Prior::Neighbour) - 0.005 * 1.32).abs() < 1e-12);
        assert!((h.max() - 0.05 * 1.32).abs() < 1e-12);
        // a missing row is NaN, and not a maximum
        let mut partial = r.clone();
        partial.gradients.remove(0);
        let p = heat_map(&partial).unwrap();
        assert!(p.values[0].iter().all(|v| v.is_nan()));
        assert_eq!(p.max(), h.max());
        let mut none = r.clone();
        none.gradients.clear();
        assert!(heat_map(&none).is_none());
    }
}
