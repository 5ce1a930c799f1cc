//! `spintune replay FILE.json`: offline Kalman replay of a recorded sequence,
//! to choose the process noise `Q` from real data.
//!
//! Input (JSON, unknown keys rejected):
//! ```json
//! {"gates": ["N", "T"],
//!  "initial_gradient": [g1, g2],                 // unit/mV
//!  "initial_covariance": [[c11, c12], [c21, c22]], // (unit/mV)²
//!  "process_noise": [[q11, q12], [q21, q22]],      // (unit/mV)², added after every update
//!  "outlier_sigma": 5.0,                          // or null: no gating
//!  "steps": [{"voltages": [v1, v2], "value": p, "variance": dp2}, …]}  // mV, unit, unit²
//! ```
//! Output: one JSON line per update, `{"step": k, "gradient": […], "covariance": [[…]]}`,
//! where update `k` (1, 2, …) uses `steps[k-1] → steps[k]`: `Δv = v_k − v_{k−1}`,
//! `z = p_k − p_{k−1}`, `Δz² = δp_k² + δp_{k−1}²`, computed by exactly the core's
//! [`KalmanGradient::update`] with [`ProcessNoise::Constant`].

use std::io::Write;

use nalgebra::{DMatrix, DVector};
use serde::Deserialize;
use spintune::kalman::{FilterError, KalmanGradient, ProcessNoise};

/// One recorded measurement.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayStep {
    /// Gate voltages, mV, in the order of `gates`.
    pub voltages: Vec<f64>,
    /// Measured parameter value (parameter units).
    pub value: f64,
    /// Its variance δp² (parameter units²).
    pub variance: f64,
}

/// The replay input file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayInput {
    /// Gate names (n).
    pub gates: Vec<String>,
    /// g(0), n entries, unit/mV.
    pub initial_gradient: Vec<f64>,
    /// C(0), n×n, (unit/mV)².
    pub initial_covariance: Vec<Vec<f64>>,
    /// Q, n×n, (unit/mV)².
    pub process_noise: Vec<Vec<f64>>,
    /// Outlier gate in predicted standard deviations; `null`: no gating.
    pub outlier_sigma: Option<f64>,
    /// The recorded sequence.
    pub steps: Vec<ReplayStep>,
}

/// One output line.
#[derive(Debug, Clone, PartialEq, serde::Serialize, Deserialize)]
pub struct ReplayLine {
    /// Update number (1-based).
    pub step: usize,
    /// Gradient after the update, unit/mV.
    pub gradient: Vec<f64>,
    /// Covariance after the update (row-major), (unit/mV)².
    pub covariance: Vec<Vec<f64>>,
}

/// Why a replay failed; every message names the field, the update or the file.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The input is not valid JSON of the documented shape (`at`: the path
    /// of the offending field, `None` for the document itself).
    #[error("invalid replay input{}: {error}", at_field(.at))]
    Input {
        at: Option<String>,
        error: serde_json::Error,
    },
    /// `gates` is empty.
    #[error("`gates` must name at least one gate")]
    NoGates,
    /// A list has the wrong length (`unit`: rows or entries).
    #[error("`{field}` has {got} {unit}, expected {expected}{}", if *.per_gate { " (one per gate)" } else { "" })]
    Length {
        field: String,
        unit: &'static str,
        got: usize,
        expected: usize,
        per_gate: bool,
    },
    /// NaN or ±∞ where a number is needed.
    #[error("`{field}` is not a finite number")]
    NotFinite { field: String },
    /// A negative or non-finite variance.
    #[error("`steps[{step}].variance` must be finite and non-negative, got {value}")]
    Variance { step: usize, value: f64 },
    /// The core refused the initial gradient and covariance.
    #[error("invalid initial state: {0}")]
    InitialState(FilterError),
    /// The core refused the outlier gate.
    #[error("invalid `outlier_sigma`: {0}")]
    OutlierSigma(FilterError),
    /// The core refused update `step` (`steps[step-1] → steps[step]`).
    #[error("update {step} (steps[{}] → steps[{step}]): {error}", .step - 1)]
    Update { step: usize, error: FilterError },
    /// The input file could not be read.
    #[error("cannot read {}: {error}", path.display())]
    Read {
        path: std::path::PathBuf,
        error: std::io::Error,
    },
    /// An output line could not be written.
    #[error("cannot write output: {0}")]
    Write(std::io::Error),
    /// An output line could not be serialized.
    #[error("{0}")]
    Serialize(serde_json::Error),
}

fn at_field(at: &Option<String>) -> String {
    at.as_ref()
        .map(|p| format!(" at `{p}`"))
        .unwrap_or_default()
}

fn matrix(rows: &[Vec<f64>], n: usize, what: &str) -> Result<DMatrix<f64>, ReplayError> {
    if rows.len() != n {
        return Err(ReplayError::Length {
            field: what.to_string(),
            unit: "rows",
            got: rows.len(),
            expected: n,
            per_gate: true,
        });
    }
    for (i, r) in rows.iter().enumerate() {
        if r.len() != n {
            return Err(ReplayError::Length {
                field: format!("{what}[{i}]"),
                unit: "entries",
                got: r.len(),
                expected: n,
                per_gate: false,
            });
        }
        if let Some(j) = r.iter().position(|x| !x.is_finite()) {
            return Err(ReplayError::NotFinite {
                field: format!("{what}[{i}][{j}]"),
            });
        }
    }
    Ok(DMatrix::from_fn(n, n, |i, j| rows[i][j]))
}

/// Parse the input text. Errors name the offending field.
pub fn parse(text: &str) -> Result<ReplayInput, ReplayError> {
    let de = &mut serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        ReplayError::Input {
            at: (path != ".").then_some(path),
            error: e.into_inner(),
        }
    })
}

/// Run the replay; every update's result in order.
pub fn replay(input: &ReplayInput) -> Result<Vec<ReplayLine>, ReplayError> {
    let n = input.gates.len();
    if n == 0 {
        return Err(ReplayError::NoGates);
    }
    if input.initial_gradient.len() != n {
        return Err(ReplayError::Length {
            field: "initial_gradient".into(),
            unit: "entries",
            got: input.initial_gradient.len(),
            expected: n,
            per_gate: true,
        });
    }
    let c0 = matrix(&input.initial_covariance, n, "initial_covariance")?;
    let q = matrix(&input.process_noise, n, "process_noise")?;
    let filter = KalmanGradient::new(
        DVector::from_vec(input.initial_gradient.clone()),
        c0,
        ProcessNoise::Constant { q },
    )
    .map_err(ReplayError::InitialState)?;
    let mut filter = filter
        .with_outlier_sigma(input.outlier_sigma)
        .map_err(ReplayError::OutlierSigma)?;
    for (k, s) in input.steps.iter().enumerate() {
        if s.voltages.len() != n {
            return Err(ReplayError::Length {
                field: format!("steps[{k}].voltages"),
                unit: "entries",
                got: s.voltages.len(),
                expected: n,
                per_gate: true,
            });
        }
        if let Some(j) = s.voltages.iter().position(|x| !x.is_finite()) {
            return Err(ReplayError::NotFinite {
                field: format!("steps[{k}].voltages[{j}]"),
            });
        }
        if !s.value.is_finite() {
            return Err(ReplayError::NotFinite {
                field: format!("steps[{k}].value"),
            });
        }
        if !(s.variance.is_finite() && s.variance >= 0.0) {
            return Err(ReplayError::Variance {
                step: k,
                value: s.variance,
            });
        }
    }
    let mut out = Vec::with_capacity(input.steps.len().saturating_sub(1));
    for k in 1..input.steps.len() {
        let (a, b) = (&input.steps[k - 1], &input.steps[k]);
        let dv = DVector::from_fn(n, |i, _| b.voltages[i] - a.voltages[i]);
        filter
            .update(&dv, b.value - a.value, a.variance + b.variance)
            .map_err(|error| ReplayError::Update { step: k, error })?;
        let c = filter.covariance();
        out.push(ReplayLine {
            step: k,
            gradient: filter.gradient().iter().copied().collect(),
            covariance: (0..n)
                .map(|i| (0..n).map(|j| c[(i, j)]).collect())
                .collect(),
        });
    }
    Ok(out)
}

/// Read `path`, replay, write JSON lines to `out`.
pub fn run_file(path: &std::path::Path, out: &mut dyn Write) -> Result<(), ReplayError> {
    let text = std::fs::read_to_string(path).map_err(|error| ReplayError::Read {
        path: path.to_path_buf(),
        error,
    })?;
    let input = parse(&text)?;
    for line in replay(&input)? {
        let s = serde_json::to_string(&line).map_err(ReplayError::Serialize)?;
        writeln!(out, "{s}").map_err(ReplayError::Write)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_free_replay_is_broyden() {
        let input = parse(
            r#"{"gates":["a","b"],"initial_gradient":[0,0],"initial_covariance":[[1,0],[0,1]],
                "process_noise":[[0,0],[0,0]],"outlier_sigma":null,
                "steps":[{"voltages":[0,0],"value":0,"variance":0},
                         {"voltages":[1,0],"value":2,"variance":0},
                         {"voltages":[1,1],"value":5,"variance":0}]}"#,
        )
        .unwrap();
        let lines = replay(&input).unwrap();
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[0].step, 1);
        assert!((lines[1].gradient[0] - 2.0).abs() < 1e-12);
        assert!((lines[1].gradient[1] - 3.0).abs() < 1e-12);
    }

    #[test]
    fn errors_name_the_problem() {
        let e = parse(r#"{"gates":["a"],"bogus":1}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus"), "{e}");
        let e = replay(
            &parse(
                r#"{"gates":["a","b"],"initial_gradient":[0],"initial_covariance":[[1]],
                    "process_noise":[[0]],"outlier_sigma":null,"steps":[]}"#,
            )
            .unwrap(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("initial_gradient"), "{e}");
    }
}
