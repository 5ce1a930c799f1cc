//! `spintune export`: one row per iteration, as CSV or as a JSON array of
//! row objects (`pandas.read_csv(f)` / `pandas.read_json(f)`).
//!
//! Columns (units in the names; `µ` is written `u`):
//! * `seq` (position in the store), `iteration`, `lab_seconds` (s, cumulative),
//!   `tuned` (true/false), `failed_evaluations` (cumulative count);
//! * `V_<gate>_mV`: every gate voltage at the measurement, mV;
//! * per parameter `<p>`: `<p>_<unit>` (value), `<p>_std_<unit>` (δp),
//!   `<p>_target_<unit>`, `<p>_tolerance_<unit>` (half-width of the band);
//! * per parameter and top-level gate: `grad_<p>_<gate>_<unit>` (the estimate
//!   after this iteration's update, e.g. `grad_t_sr_SB_ns/mV` → written
//!   `grad_t_sr_SB_ns_per_mV`) and `grad_<p>_<gate>_std_<unit>` (√ of the
//!   covariance's diagonal, if the estimator has a covariance);
//! * `step_<gate>_mV`: the step decided in this iteration, mV.
//!
//! Missing values (a failed measurement, no target) are empty cells in CSV and
//! `null` in JSON.

use std::collections::BTreeMap;

use serde_json::Value;
use spintune::protocol::IterationRecord;

use crate::store::Store;

/// Output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Comma-separated values with a header row.
    Csv,
    /// A JSON array of row objects.
    Json,
}

/// Make a unit usable in a column name: `µV` → `uV`, `ns/mV` → `ns_per_mV`.
fn unit_suffix(unit: &str) -> String {
    let u = unit.replace(['µ', 'μ'], "u").replace('/', "_per_");
    u.chars()
        .filter(|c| c.is_ascii_alphanumeric() || *c == '_')
        .collect()
}

fn with_unit(base: String, unit: &str) -> String {
    let u = unit_suffix(unit);
    if u.is_empty() {
        base
    } else {
        format!("{base}_{u}")
    }
}

/// The table: column names and rows of values (`Value::Null` = missing).
pub struct Table {
    /// Column names.
    pub columns: Vec<String>,
    /// Rows, each as long as `columns`.
    pub rows: Vec<Vec<Value>>,
}

/// Build the table from records in store order.
pub fn table(records: &[IterationRecord]) -> Table {
    let mut columns: Vec<String> = [
        "seq",
        "iteration",
        "lab_seconds",
        "tuned",
        "failed_evaluations",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let mut index: BTreeMap<String, usize> = BTreeMap::new();
    let mut col = |columns: &mut Vec<String>, name: String| -> usize {
        if let Some(&i) = index.get(&name) {
            return i;
        }
        columns.push(name.clone());
        index.insert(name, columns.len() - 1);
        columns.len() - 1
    };
    // First pass: columns in order of first appearance.
    let mut cells: Vec<Vec<(usize, Value)>> = Vec::with_capacity(records.len());
    for (seq, r) in records.iter().enumerate() {
        let mut row = vec![
            (0, Value::from(seq as u64)),
            (1, Value::from(r.iteration)),
            (2, Value::from(r.lab_seconds)),
            (3, Value::from(r.tuned)),
            (4, Value::from(r.failed_evaluations)),
        ];
        for (gate, v) in &r.voltages_mv {
            row.push((col(&mut columns, format!("V_{gate}_mV")), Value::from(*v)));
        }
        for p in &r.parameters {
            let opt = |x: Option<f64>| x.map(Value::from).unwrap_or(Value::Null);
            row.push((
                col(&mut columns, with_unit(p.name.clone(), &p.unit)),
                opt(p.value),
            ));
            row.push((
                col(&mut columns, with_unit(format!("{}_std", p.name), &p.unit)),
                opt(p.std),
            ));
            row.push((
                col(
                    &mut columns,
                    with_unit(format!("{}_target", p.name), &p.unit),
                ),
                opt(p.target),
            ));
            row.push((
                col(
                    &mut columns,
                    with_unit(format!("{}_tolerance", p.name), &p.unit),
                ),
                opt(p.tolerance),
            ));
        }
        for g in &r.gradients {
            for (j, gate) in r.gates.iter().enumerate() {
                if let Some(x) = g.gradient.get(j) {
                    row.push((
                        col(
                            &mut columns,
                            with_unit(format!("grad_{}_{gate}", g.parameter), &g.unit),
                        ),
                        Value::from(*x),
                    ));
                }
                if let Some(c) = g.covariance.as_ref().and_then(|c| c.get(j)?.get(j)) {
                    row.push((
                        col(
                            &mut columns,
                            with_unit(format!("grad_{}_{gate}_std", g.parameter), &g.unit),
                        ),
                        Value::from(c.max(0.0).sqrt()),
                    ));
                }
            }
        }
        for (j, gate) in r.gates.iter().enumerate() {
            if let Some(x) = r.step_mv.get(j) {
                row.push((
                    col(&mut columns, format!("step_{gate}_mV")),
                    Value::from(*x),
                ));
            }
        }
        cells.push(row);
    }
    let rows = cells
        .into_iter()
        .map(|cells| {
            let mut row = vec![Value::Null; columns.len()];
            for (i, v) in cells {
                row[i] = v;
            }
            row
        })
        .collect();
    Table { columns, rows }
}

fn csv_cell(v: &Value) -> String {
    match v {
        Value::Null => String::new(),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Why a run could not be exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The store could not be read (e.g. no such run).
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    /// A stored iteration is not a readable record.
    #[error("stored iteration {index} of run {run} is unreadable: {error}")]
    Record {
        /// The run.
        run: u64,
        /// The iteration's index.
        index: usize,
        /// Why.
        error: serde_json::Error,
    },
    /// Writing the CSV failed.
    #[error("cannot write CSV: {0}")]
    Csv(String),
}

/// Render a table.
pub fn render(t: &Table, format: Format) -> Result<String, ExportError> {
    let csv_error = |e: &dyn std::fmt::Display| ExportError::Csv(e.to_string());
    match format {
        Format::Csv => {
            let mut w = csv::Writer::from_writer(Vec::new());
            w.write_record(&t.columns).map_err(|e| csv_error(&e))?;
            for row in &t.rows {
                w.write_record(row.iter().map(csv_cell))
                    .map_err(|e| csv_error(&e))?;
            }
            let bytes = w.into_inner().map_err(|e| csv_error(&e))?;
            String::from_utf8(bytes).map_err(|e| csv_error(&e))
        }
        Format::Json => {
            let mut s = String::from("[");
            for (i, row) in t.rows.iter().enumerate() {
                if i > 0 {
                    s.push(',');
                }
                s.push_str("\n{");
                for (j, (c, v)) in t.columns.iter().zip(row).enumerate() {
                    if j > 0 {
                        s.push(',');
                    }
                    s.push_str(&Value::from(c.as_str()).to_string());
                    s.push(':');
                    s.push_str(&v.to_string());
                }
                s.push('}');
            }
            s.push_str("\n]\n");
            Ok(s)
        }
    }
}

/// Export run `id` from the store.
pub fn export(store: &Store, id: u64, format: Format) -> Result<String, ExportError> {
    store.get_run(id)?;
    let json = store.iterations_json(id, 0, None)?;
    let records = json
        .iter()
        .enumerate()
        .map(|(index, j)| {
            serde_json::from_str::<IterationRecord>(j).map_err(|error| ExportError::Record {
                run: id,
                index,
                error,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    render(&table(&records), format)
}

#[cfg(test)]
mod tests {
    use super::*;
    use spintune::protocol::{GradientReport, ParameterReport};

    fn rec(k: u64, value: Option<f64>) -> IterationRecord {
        IterationRecord {
            iteration: k,
            voltages_mv: [("N".to_string(), -1.5), ("T".to_string(), 2.0)].into(),
            gates: vec!["N".into(), "T".into()],
            parameters: vec![ParameterReport {
                name: "w".into(),
                unit: "µV".into(),
                value,
                std: Some(3.0),
                target: Some(270.0),
                tolerance: Some(27.0),
            }],
            gradients: vec![GradientReport {
                parameter: "w".into(),
                unit: "µV/mV".into(),
                gradient: vec![1.0, -2.0],
                covariance: Some(vec![vec![4.0, 0.0], vec![0.0, 9.0]]),
            }],
            step_mv: vec![0.5, 0.0],
            tuned: false,
            lab_seconds: 10.0 * k as f64,
            scan_counts: Default::default(),
            failed_evaluations: 0,
            scans: vec![],
            events: vec![],
            keep: None,
        }
    }

    #[test]
    fn csv_has_one_row_per_iteration_and_named_columns() {
        let t = table(&[rec(0, Some(250.0)), rec(1, None)]);
        let csv = render(&t, Format::Csv).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 3);
        for c in [
            "V_N_mV",
            "w_uV",
            "w_std_uV",
            "w_target_uV",
            "grad_w_T_uV_per_mV",
            "grad_w_T_std_uV_per_mV",
            "step_N_mV",
        ] {
            assert!(
                lines[0].split(',').any(|h| h == c),
                "missing {c} in {}",
                lines[0]
            );
        }
        let json: Vec<serde_json::Map<String, Value>> =
            serde_json::from_str(&render(&t, Format::Json).unwrap()).unwrap();
        assert_eq!(json[1]["w_uV"], Value::Null);
        assert_eq!(json[0]["grad_w_T_std_uV_per_mV"], Value::from(3.0));
    }
}
