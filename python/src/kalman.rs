//! `spintune.KalmanGradient` and `spintune.newton_step`: thin wrappers of
//! `spintune::kalman::KalmanGradient` (with `ProcessNoise::Constant`) and
//! `spintune::solver::newton_step`. The numbers are the core's; this file
//! only converts and checks shapes.

use nalgebra::{DMatrix, DVector};
use numpy::ndarray::Array2;
use numpy::{PyArray1, PyArray2, PyArrayDyn, PyArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use spintune::kalman::{FilterError, KalmanGradient as CoreFilter, ProcessNoise};
use spintune::solver::{newton_step as core_newton_step, SolverConfig};

use crate::convert::to_py;

/// An array-like as float64: its shape and its entries in row-major order.
/// Anything numpy cannot read as numbers is a `ValueError` naming `name`.
fn float_array(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<(Vec<usize>, Vec<f64>)> {
    let py = obj.py();
    let kwargs = PyDict::new(py);
    kwargs.set_item("dtype", "float64")?;
    let arr = py
        .import("numpy")?
        .call_method("asarray", (obj,), Some(&kwargs))
        .map_err(|e| {
            PyValueError::new_err(format!(
                "`{name}` must be numbers (a list or a numpy array): {e}"
            ))
        })?;
    let arr = arr.cast::<PyArrayDyn<f64>>()?.readonly();
    let view = arr.as_array();
    let shape = view.shape().to_vec();
    let values: Vec<f64> = view.iter().copied().collect();
    if let Some(k) = values.iter().position(|x| !x.is_finite()) {
        // row-major index of the first bad entry
        let mut idx = vec![0; shape.len()];
        let mut rest = k;
        for d in (0..shape.len()).rev() {
            idx[d] = rest % shape[d];
            rest /= shape[d];
        }
        let at = if idx.is_empty() {
            String::new()
        } else {
            format!(
                "[{}]",
                idx.iter()
                    .map(|i| i.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        };
        return Err(PyValueError::new_err(format!(
            "`{name}{at}` is {}: every entry must be a finite number",
            values[k]
        )));
    }
    Ok((shape, values))
}

fn shape_str(shape: &[usize]) -> String {
    match shape {
        [] => "a scalar".into(),
        [n] => format!("shape ({n},)"),
        _ => format!(
            "shape ({})",
            shape
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// A 1-D array of length `n` (any length if `None`).
fn vector(obj: &Bound<'_, PyAny>, name: &str, n: Option<usize>) -> PyResult<DVector<f64>> {
    let (shape, values) = float_array(obj, name)?;
    match (shape.as_slice(), n) {
        ([m], Some(n)) if *m == n => Ok(DVector::from_vec(values)),
        ([_], None) => Ok(DVector::from_vec(values)),
        (_, Some(n)) => Err(PyValueError::new_err(format!(
            "`{name}` must be a 1-D array of length {n}, got {}",
            shape_str(&shape)
        ))),
        (_, None) => Err(PyValueError::new_err(format!(
            "`{name}` must be a 1-D array, got {}",
            shape_str(&shape)
        ))),
    }
}

/// A row-major 2-D array of shape `rows × cols` (`None`: any).
fn matrix(
    obj: &Bound<'_, PyAny>,
    name: &str,
    rows: Option<usize>,
    cols: Option<usize>,
    what: &str,
) -> PyResult<DMatrix<f64>> {
    let (shape, values) = float_array(obj, name)?;
    let ok = match shape.as_slice() {
        [r, c] => rows.is_none_or(|n| n == *r) && cols.is_none_or(|n| n == *c),
        _ => false,
    };
    if !ok {
        return Err(PyValueError::new_err(format!(
            "`{name}` must be {what}, got {}",
            shape_str(&shape)
        )));
    }
    Ok(DMatrix::from_row_slice(shape[0], shape[1], &values))
}

fn matrix_to_numpy<'py>(py: Python<'py>, m: &DMatrix<f64>) -> Bound<'py, PyArray2<f64>> {
    let a = Array2::from_shape_fn((m.nrows(), m.ncols()), |(i, j)| m[(i, j)]);
    PyArray2::from_owned_array(py, a)
}

/// The Python argument a core filter error is about.
fn filter_error(e: FilterError) -> PyErr {
    let arg = match &e {
        FilterError::Invalid { what, .. } | FilterError::Dimension { what, .. } => match *what {
            "voltage step" => " (argument `dv`)",
            "measured change" => " (argument `dz`)",
            "measurement variance" => " (argument `variance`)",
            "initial gradient" => " (argument `gradient`)",
            "initial covariance" => " (argument `covariance`)",
            "process noise Q" => " (argument `process_noise`)",
            _ => "",
        },
        FilterError::NotPsd { what } => match *what {
            "initial covariance" => " (argument `covariance`)",
            "process noise Q" => " (argument `process_noise`)",
            _ => "",
        },
    };
    PyValueError::new_err(format!("{e}{arg}"))
}

/// What ``KalmanGradient.checkpoint()`` holds.
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct FilterCheckpoint {
    filter: CoreFilter,
    outlier_sigma: Option<f64>,
    min_step_mv: f64,
}

/// The paper's Kalman filter for the gradient of one parameter over n gates
/// (Teske et al., APL 2019, eqs. 2–4; the core's `spintune::kalman::KalmanGradient`
/// with a constant process noise `Q`).
///
/// Args:
///     gradient: initial gradient g(0), length n, in parameter unit per mV
///         (e.g. ns/mV for t_sr, µV/mV for w).
///     covariance: initial covariance C(0), n×n, symmetric positive
///         semi-definite, in (parameter unit / mV)².
///     process_noise: the n×n matrix Q added after every update, in
///         (parameter unit / mV)², or a scalar σ² for Q = σ²·I.
///     outlier_sigma: gate innovations beyond this many predicted standard
///         deviations (the gradient is not moved, Q is still added);
///         ``None`` (default): never gate.
///     min_step_mv: voltage steps with |Δv| below this (mV) are skipped
///         (nothing learned, nothing changed); default 1e-6 mV.
///
/// Lists or numpy arrays are accepted. NaN/∞ entries, a covariance that is
/// not symmetric PSD and wrong shapes raise ``ValueError`` naming the
/// argument.
#[pyclass(name = "KalmanGradient", module = "spintune")]
#[derive(Clone)]
pub struct PyKalmanGradient {
    inner: CoreFilter,
    outlier_sigma: Option<f64>,
    min_step_mv: f64,
}

#[pymethods]
impl PyKalmanGradient {
    #[new]
    #[pyo3(signature = (gradient, covariance, process_noise, *, outlier_sigma = None, min_step_mv = 1e-6))]
    fn new(
        gradient: &Bound<'_, PyAny>,
        covariance: &Bound<'_, PyAny>,
        process_noise: &Bound<'_, PyAny>,
        outlier_sigma: Option<f64>,
        min_step_mv: f64,
    ) -> PyResult<Self> {
        let g = vector(gradient, "gradient", None)?;
        let n = g.len();
        if n == 0 {
            return Err(PyValueError::new_err(
                "`gradient` must have at least one entry (one per gate)",
            ));
        }
        let c = matrix(
            covariance,
            "covariance",
            Some(n),
            Some(n),
            &format!("a {n}×{n} matrix (gradient has {n} entries)"),
        )?;
        let (shape, values) = float_array(process_noise, "process_noise")?;
        let q = if shape.is_empty() {
            let s2 = values[0];
            if s2 < 0.0 {
                return Err(PyValueError::new_err(format!(
                    "`process_noise` as a scalar is the variance σ² (Q = σ²·I) and must be ≥ 0, got {s2}"
                )));
            }
            DMatrix::identity(n, n) * s2
        } else {
            matrix(
                process_noise,
                "process_noise",
                Some(n),
                Some(n),
                &format!("a {n}×{n} matrix or a scalar σ² (gradient has {n} entries)"),
            )?
        };
        let inner = CoreFilter::new(g, c, ProcessNoise::Constant { q })
            .map_err(filter_error)?
            .with_outlier_sigma(outlier_sigma)
            .map_err(|e| PyValueError::new_err(format!("{e} (argument `outlier_sigma`)")))?
            .with_min_step_mv(min_step_mv)
            .map_err(|e| PyValueError::new_err(format!("{e} (argument `min_step_mv`)")))?;
        Ok(Self {
            inner,
            outlier_sigma,
            min_step_mv,
        })
    }

    /// One filter step: the gates moved by ``dv`` (length n, mV), the
    /// parameter changed by ``dz`` (parameter unit), and ``variance`` is the
    /// measurement variance Δz² = δp(k)² + δp(k−1)² of that difference
    /// (parameter unit²).
    ///
    /// Returns what happened, as a dict: ``{"kind": "updated", "innovation":
    /// …, "innovation_sigma": …}`` (innovation z − H·g in parameter units and
    /// its predicted standard deviation), ``{"kind": "gated", …}`` (outlier,
    /// gradient unchanged, Q added) or ``{"kind": "skipped_small_step",
    /// "step_norm_mv": …}`` (nothing changed).
    ///
    /// Raises ``ValueError`` (state unchanged) for NaN/∞ inputs, a negative
    /// variance or a ``dv`` of the wrong length.
    fn update<'py>(
        &mut self,
        py: Python<'py>,
        dv: &Bound<'py, PyAny>,
        dz: f64,
        variance: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let n = self.inner.dimension();
        let dv = vector(dv, "dv", Some(n))?;
        let outcome = self.inner.update(&dv, dz, variance).map_err(filter_error)?;
        to_py(py, &outcome)
    }

    /// Present gradient estimate g, 1-D numpy array (length n), parameter unit per mV.
    #[getter]
    fn gradient<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.gradient().as_slice())
    }

    /// Present covariance C, 2-D numpy array (n×n), (parameter unit / mV)².
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix_to_numpy(py, self.inner.covariance())
    }

    /// The process noise Q added after every update, n×n, (parameter unit / mV)².
    #[getter]
    fn process_noise<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let q = self
            .inner
            .process_noise()
            .for_step(&DVector::zeros(self.inner.dimension()));
        matrix_to_numpy(py, &q)
    }

    /// Outlier gate in predicted standard deviations (``None``: never gate).
    #[getter]
    fn outlier_sigma(&self) -> Option<f64> {
        self.outlier_sigma
    }

    /// Steps with |Δv| below this are skipped, mV.
    #[getter]
    fn min_step_mv(&self) -> f64 {
        self.min_step_mv
    }

    /// Number of gates n.
    #[getter]
    fn n(&self) -> usize {
        self.inner.dimension()
    }

    /// The filter as a JSON string (gradient, covariance, process noise,
    /// outlier gate, small-step threshold; every float exact).
    /// ``KalmanGradient.restore(text)`` gives an identical filter; pickling
    /// goes through it.
    fn checkpoint(&self) -> PyResult<String> {
        serde_json::to_string(&FilterCheckpoint {
            filter: self.inner.clone(),
            outlier_sigma: self.outlier_sigma,
            min_step_mv: self.min_step_mv,
        })
        .map_err(|e| PyValueError::new_err(format!("cannot serialize the filter: {e}")))
    }

    /// A filter from ``checkpoint()``'s string.
    #[staticmethod]
    fn restore(checkpoint: &str) -> PyResult<Self> {
        let de = &mut serde_json::Deserializer::from_str(checkpoint);
        let c: FilterCheckpoint = serde_path_to_error::deserialize(de)
            .map_err(|e| PyValueError::new_err(format!("invalid checkpoint: {e}")))?;
        Ok(Self {
            inner: c.filter,
            outlier_sigma: c.outlier_sigma,
            min_step_mv: c.min_step_mv,
        })
    }

    /// Pickling: ``KalmanGradient.restore(checkpoint())``.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        let text = slf.borrow().checkpoint()?;
        Ok((slf.get_type().getattr("restore")?, (text,)))
    }

    /// An independent copy of the filter.
    fn copy(&self) -> Self {
        self.clone()
    }

    fn __copy__(&self) -> Self {
        self.clone()
    }

    fn __deepcopy__(&self, _memo: &Bound<'_, PyAny>) -> Self {
        self.clone()
    }

    fn __repr__(&self) -> String {
        format!(
            "KalmanGradient(n={}, gradient={:?})",
            self.inner.dimension(),
            self.inner.gradient().as_slice()
        )
    }
}

/// The quasi-Newton step Δv = −J⁺·Δ with the minimum-norm pseudo-inverse
/// (SVD, singular values below ``rank_tolerance``·σ_max treated as zero),
/// scaled down to ``max_step_mv`` if longer: the core's
/// ``spintune::solver::newton_step``.
///
/// Args:
///     jacobian: J, m×n (parameters × gates), parameter unit per mV.
///     residual: Δ = p − p*, length m, parameter units (measured minus target).
///     max_step_mv: largest Euclidean norm of the step, mV (paper: 10 mV).
///     rank_tolerance: relative singular-value cut-off (default 1e-9).
///
/// Returns:
///     The step Δv, 1-D numpy array of length n, mV.
///
/// Raises ``ValueError`` for wrong shapes, NaN/∞ entries or a step limit
/// that is not a positive number.
#[pyfunction]
#[pyo3(signature = (jacobian, residual, max_step_mv = 10.0, *, rank_tolerance = 1e-9))]
pub fn newton_step<'py>(
    py: Python<'py>,
    jacobian: &Bound<'py, PyAny>,
    residual: &Bound<'py, PyAny>,
    max_step_mv: f64,
    rank_tolerance: f64,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let j = matrix(
        jacobian,
        "jacobian",
        None,
        None,
        "a 2-D array (parameters × gates)",
    )?;
    let d = vector(residual, "residual", Some(j.nrows()))?;
    if !(max_step_mv.is_finite() && max_step_mv > 0.0) {
        return Err(PyValueError::new_err(format!(
            "`max_step_mv` must be a finite number > 0 (mV), got {max_step_mv}"
        )));
    }
    if !(rank_tolerance.is_finite() && rank_tolerance >= 0.0) {
        return Err(PyValueError::new_err(format!(
            "`rank_tolerance` must be a finite number ≥ 0, got {rank_tolerance}"
        )));
    }
    let step = core_newton_step(
        &j,
        &d,
        &SolverConfig {
            max_step_mv,
            rank_tolerance,
            ..SolverConfig::default()
        },
    );
    Ok(PyArray1::from_slice(py, step.dv_mv.as_slice()))
}
