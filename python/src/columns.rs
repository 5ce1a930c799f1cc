//! `spintune._core.RecordColumns`: iteration records → the columns of the
//! xarray Dataset (`spintune._xarray.records_to_dataset` builds the Dataset
//! from them). Records come as dicts or as their JSON text (a store's rows):
//! the text is parsed into a light view of the record whose raw scans and
//! events are skipped unparsed-into-values (serde ignores them), so a
//! 20,000-iteration store costs no more than its numbers.
//!
//! Layout and units as documented in `docs/python.md`: voltages mV, every
//! parameter in its own unit, lab time s. Missing values are NaN (counts 0).

use std::collections::{BTreeMap, HashMap};

use numpy::ndarray::Array2;
use numpy::{PyArray1, PyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyString};
use serde::Deserialize;

use crate::convert::from_py;

/// The part of an `IterationRecord` the Dataset holds (unknown keys, e.g.
/// `scans` and `events`, are skipped).
#[derive(Deserialize)]
struct LightRecord {
    iteration: i64,
    voltages_mv: BTreeMap<String, Option<f64>>,
    gates: Vec<String>,
    #[serde(default)]
    parameters: Vec<LightParameter>,
    #[serde(default)]
    gradients: Vec<LightGradient>,
    #[serde(default)]
    step_mv: Vec<Option<f64>>,
    tuned: bool,
    lab_seconds: Option<f64>,
    #[serde(default)]
    scan_counts: BTreeMap<String, i64>,
    #[serde(default)]
    failed_evaluations: i64,
}

#[derive(Deserialize)]
struct LightParameter {
    name: String,
    unit: String,
    value: Option<f64>,
    std: Option<f64>,
    target: Option<f64>,
    tolerance: Option<f64>,
}

#[derive(Deserialize)]
struct LightGradient {
    parameter: String,
    unit: String,
    gradient: Vec<Option<f64>>,
    #[serde(default)]
    covariance: Option<Vec<Vec<Option<f64>>>>,
}

fn nan(x: Option<f64>) -> f64 {
    x.unwrap_or(f64::NAN)
}

/// A growing column of `width` values per row, NaN-padded for rows it
/// missed.
fn put(col: &mut Vec<f64>, row: usize, width: usize, values: impl IntoIterator<Item = f64>) {
    col.resize(row * width, f64::NAN);
    let start = col.len();
    col.extend(values.into_iter().take(width));
    col.resize(start + width, f64::NAN);
}

/// Columns of the Dataset, built one record at a time.
#[derive(Default)]
struct Columns {
    rows: usize,
    iterations: Vec<i64>,
    tuning_gates: Option<Vec<String>>,
    gates: Vec<String>,
    voltage: HashMap<String, Vec<f64>>,
    params: Vec<(String, String)>,
    param_cols: HashMap<String, Vec<f64>>,
    grads: Vec<(String, String)>,
    grad_cols: HashMap<String, Vec<f64>>,
    step: Vec<f64>,
    lab_seconds: Vec<f64>,
    tuned: Vec<bool>,
    failed: Vec<i64>,
    kinds: Vec<String>,
    counts: HashMap<String, Vec<i64>>,
}

/// Why a record could not join the columns.
#[derive(Debug)]
enum ColumnsError {
    /// Its top-level gates differ from the first record's.
    GatesDiffer {
        iteration: i64,
        found: Vec<String>,
        first: Vec<String>,
    },
    /// A record of a JSON batch is malformed.
    Invalid {
        index: usize,
        path: String,
        message: String,
    },
}

impl std::fmt::Display for ColumnsError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ColumnsError::GatesDiffer {
                iteration,
                found,
                first,
            } => write!(
                f,
                "iteration {iteration}: top-level gates {found:?} differ from {first:?}; one dataset holds one tuner"
            ),
            ColumnsError::Invalid {
                index,
                path,
                message,
            } => write!(f, "record {index} of the batch: invalid at `{path}`: {message}"),
        }
    }
}

impl From<ColumnsError> for PyErr {
    fn from(e: ColumnsError) -> Self {
        PyValueError::new_err(e.to_string())
    }
}

impl Columns {
    fn add(&mut self, r: LightRecord) -> Result<(), ColumnsError> {
        let m = match &self.tuning_gates {
            None => {
                self.tuning_gates = Some(r.gates.clone());
                r.gates.len()
            }
            Some(t) if *t != r.gates => {
                return Err(ColumnsError::GatesDiffer {
                    iteration: r.iteration,
                    found: r.gates.clone(),
                    first: t.clone(),
                })
            }
            Some(t) => t.len(),
        };
        let row = self.rows;
        self.iterations.push(r.iteration);
        for (g, v) in &r.voltages_mv {
            if !self.voltage.contains_key(g) {
                self.gates.push(g.clone());
            }
            put(
                self.voltage.entry(g.clone()).or_default(),
                row,
                1,
                [nan(*v)],
            );
        }
        for p in &r.parameters {
            if !self.param_cols.contains_key(&p.name) {
                self.params.push((p.name.clone(), p.unit.clone()));
            }
            put(
                self.param_cols.entry(p.name.clone()).or_default(),
                row,
                4,
                [nan(p.value), nan(p.std), nan(p.target), nan(p.tolerance)],
            );
        }
        for g in &r.gradients {
            if !self.grad_cols.contains_key(&g.parameter) {
                self.grads.push((g.parameter.clone(), g.unit.clone()));
            }
            let mut values: Vec<f64> = g.gradient.iter().map(|x| nan(*x)).collect();
            values.resize(m, f64::NAN);
            for j in 0..m {
                let var = g
                    .covariance
                    .as_ref()
                    .and_then(|c| c.get(j))
                    .and_then(|row| row.get(j))
                    .copied()
                    .flatten();
                values.push(var.map_or(f64::NAN, |v| v.max(0.0).sqrt()));
            }
            put(
                self.grad_cols.entry(g.parameter.clone()).or_default(),
                row,
                2 * m,
                values,
            );
        }
        put(&mut self.step, row, m, r.step_mv.iter().map(|x| nan(*x)));
        self.lab_seconds.push(nan(r.lab_seconds));
        self.tuned.push(r.tuned);
        self.failed.push(r.failed_evaluations);
        for (k, c) in &r.scan_counts {
            if !self.counts.contains_key(k) {
                self.kinds.push(k.clone());
            }
            let col = self.counts.entry(k.clone()).or_default();
            col.resize(row, 0);
            col.push(*c);
        }
        self.rows += 1;
        Ok(())
    }
}

fn array2<'py>(
    py: Python<'py>,
    mut v: Vec<f64>,
    rows: usize,
    cols: usize,
) -> Bound<'py, PyArray2<f64>> {
    v.resize(rows * cols, f64::NAN);
    let a = Array2::from_shape_vec((rows, cols), v).expect("rows × cols values");
    PyArray2::from_owned_array(py, a)
}

/// Iteration records → the Dataset's columns (internal; see
/// ``spintune._xarray.records_to_dataset``). ``add(record_dict)``,
/// ``add_json([text, ...])`` (the records' JSON, raw scans skipped without
/// being turned into values), then ``finish()`` → dict of numpy arrays.
#[pyclass(name = "RecordColumns", module = "spintune._core")]
#[derive(Default)]
pub struct PyRecordColumns {
    inner: Columns,
}

#[pymethods]
impl PyRecordColumns {
    #[new]
    fn new() -> Self {
        Self::default()
    }

    /// Add one record (dict, the JSON ``IterationRecord``).
    fn add(&mut self, record: &Bound<'_, PyAny>) -> PyResult<()> {
        let r: LightRecord = from_py(record, "record")?;
        Ok(self.inner.add(r)?)
    }

    /// Add records given as JSON texts (a list of ``str``), in order.
    fn add_json(&mut self, py: Python<'_>, texts: &Bound<'_, PyList>) -> PyResult<()> {
        // owned copies (the abi3 API of Python 3.9 lends no &str), parsed
        // with the GIL released
        let strs: Vec<String> = texts
            .iter()
            .map(|t| {
                let s = t.cast_into::<PyString>().map_err(PyErr::from)?;
                Ok(s.to_cow()?.into_owned())
            })
            .collect::<PyResult<_>>()?;
        let inner = &mut self.inner;
        py.detach(|| {
            for (i, s) in strs.iter().enumerate() {
                let de = &mut serde_json::Deserializer::from_str(s);
                let r: LightRecord =
                    serde_path_to_error::deserialize(de).map_err(|e| ColumnsError::Invalid {
                        index: i,
                        path: e.path().to_string(),
                        message: e.inner().to_string(),
                    })?;
                inner.add(r)?;
            }
            Ok::<(), ColumnsError>(())
        })?;
        Ok(())
    }

    /// Number of records added.
    fn __len__(&self) -> usize {
        self.inner.rows
    }

    /// The columns: ``iteration`` (int64), ``tuning_gates``, ``gates``,
    /// ``voltage`` (rows × gates, mV), ``parameters`` (list of ``(name,
    /// unit, rows × 4: value, std, target, tolerance)``), ``gradients``
    /// (list of ``(parameter, unit, rows × m gradient, rows × m std)``),
    /// ``step`` (rows × m, mV), ``lab_seconds`` (s), ``tuned`` (bool),
    /// ``failed_evaluations`` (int64), ``scan_counts`` (list of ``(kind,
    /// int64)``).
    fn finish<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let c = &self.inner;
        let n = c.rows;
        let tuning = c.tuning_gates.clone().unwrap_or_default();
        let m = tuning.len();
        let d = PyDict::new(py);
        d.set_item("iteration", PyArray1::from_vec(py, c.iterations.clone()))?;
        d.set_item("tuning_gates", tuning)?;
        d.set_item("gates", c.gates.clone())?;
        let mut v = vec![f64::NAN; n * c.gates.len()];
        for (j, g) in c.gates.iter().enumerate() {
            for (i, x) in c.voltage[g].iter().enumerate() {
                v[i * c.gates.len() + j] = *x;
            }
        }
        d.set_item("voltage", array2(py, v, n, c.gates.len()))?;
        let params = PyList::empty(py);
        for (name, unit) in &c.params {
            params.append((name, unit, array2(py, c.param_cols[name].clone(), n, 4)))?;
        }
        d.set_item("parameters", params)?;
        let grads = PyList::empty(py);
        for (name, unit) in &c.grads {
            let mut both = c.grad_cols[name].clone();
            both.resize(n * 2 * m, f64::NAN);
            let (mut g, mut s) = (Vec::with_capacity(n * m), Vec::with_capacity(n * m));
            for row in both.chunks(2 * m.max(1)) {
                g.extend_from_slice(&row[..m.min(row.len())]);
                s.extend_from_slice(&row[m.min(row.len())..]);
            }
            grads.append((name, unit, array2(py, g, n, m), array2(py, s, n, m)))?;
        }
        d.set_item("gradients", grads)?;
        d.set_item("step", array2(py, c.step.clone(), n, m))?;
        d.set_item("lab_seconds", PyArray1::from_vec(py, c.lab_seconds.clone()))?;
        d.set_item("tuned", PyArray1::from_vec(py, c.tuned.clone()))?;
        d.set_item(
            "failed_evaluations",
            PyArray1::from_vec(py, c.failed.clone()),
        )?;
        let counts = PyList::empty(py);
        for k in &c.kinds {
            let mut col = c.counts[k].clone();
            col.resize(n, 0);
            counts.append((k, PyArray1::from_vec(py, col)))?;
        }
        d.set_item("scan_counts", counts)?;
        Ok(d)
    }
}
