//! A cell whose initial finite differences failed for a parameter borrows
//! its row from the cells that measured theirs.
//!
//! When one fit of a parameter's finite differences fails (its base or one
//! gate's offset), the single-cell level starts that row from zero with an
//! identity covariance (`EventKind::FiniteDifferenceFailed`: nothing known,
//! σ = 1/mV in log space). In an array that left a fifth of the cells'
//! `w` rows at zero when the joint tuner started (docs/array-history.md, "Stalled
//! cells traced"), and a zero row gives the step no direction for that
//! parameter. The cells of an array are alike (one design, one process):
//! the mean of the measured rows is a prior with the right signs, and the
//! spread between the cells says how far to trust it, as
//! `borrow_line_jacobians` does for the lines.

use super::array::CellKnowledge;

/// For each parameter, every cell whose row is all zero (the failed
/// measurement's row) takes the mean row of the cells whose row is not,
/// with a diagonal covariance per gate: the mean of their own variances
/// plus the variance between their rows (one measured cell: the square of
/// its value). Cells of another gate count or parameter count are left as
/// they are. Returns the `(cell, parameter)` pairs that borrowed.
///
/// ```
/// use spintune::tuner::array::CellKnowledge;
/// use spintune::tuner::borrowed_gradient::borrow_failed_gradients;
/// let cell = |g: Vec<f64>, var: f64| CellKnowledge {
///     gates: vec!["N".into(), "T".into()],
///     parameters: vec!["w".into()],
///     gradient: vec![g],
///     covariance: vec![vec![vec![var, 0.0], vec![0.0, var]]],
///     process_noise_per_mv: vec![0.001],
///     floors: vec![0.0],
///     max_step_mv: 10.0,
///     compensation: None,
/// };
/// let mut cells = vec![
///     cell(vec![0.010, -0.004], 1e-6),
///     cell(vec![0.0, 0.0], 1.0), // its finite differences failed
///     cell(vec![0.014, -0.002], 3e-6),
/// ];
/// assert_eq!(borrow_failed_gradients(&mut cells), vec![(1, 0)]);
/// assert!((cells[1].gradient[0][0] - 0.012).abs() < 1e-12);
/// assert!((cells[1].gradient[0][1] + 0.003).abs() < 1e-12);
/// // own variances 2e-6 on average, spread between the rows 8e-6 and 2e-6
/// assert!((cells[1].covariance[0][0][0] - 10e-6).abs() < 1e-12);
/// assert!((cells[1].covariance[0][1][1] - 4e-6).abs() < 1e-12);
/// assert_eq!(cells[1].covariance[0][0][1], 0.0);
/// assert_eq!(cells[0].gradient[0], vec![0.010, -0.004]); // measured: kept
/// ```
pub fn borrow_failed_gradients(cells: &mut [CellKnowledge]) -> Vec<(usize, usize)> {
    let mut borrowed = Vec::new();
    let Some(first) = cells.first() else {
        return borrowed;
    };
    let (n_gates, n_params) = (first.gates.len(), first.gradient.len());
    let alike = |c: &CellKnowledge| c.has_shape(n_gates, n_params);
    for p in 0..n_params {
        let (mut measured, mut failed) = (Vec::new(), Vec::new());
        for (k, c) in cells.iter().enumerate().filter(|(_, c)| alike(c)) {
            if c.gradient[p].iter().all(|&x| x == 0.0) {
                failed.push(k);
            } else if c.gradient[p].iter().all(|x| x.is_finite()) {
                measured.push(k);
            }
        }
        if measured.is_empty() || failed.is_empty() {
            continue;
        }
        let n = measured.len() as f64;
        let mean: Vec<f64> = (0..n_gates)
            .map(|j| {
                measured
                    .iter()
                    .map(|&k| cells[k].gradient[p][j])
                    .sum::<f64>()
                    / n
            })
            .collect();
        let variance: Vec<f64> = (0..n_gates)
            .map(|j| {
                let own = measured
                    .iter()
                    .map(|&k| {
                        cells[k]
                            .covariance
                            .get(p)
                            .and_then(|m| m.get(j))
                            .and_then(|r| r.get(j))
                            .copied()
                            .filter(|v| v.is_finite() && *v >= 0.0)
                            .unwrap_or(0.0)
                    })
                    .sum::<f64>()
                    / n;
                let spread = if measured.len() >= 2 {
                    measured
                        .iter()
                        .map(|&k| (cells[k].gradient[p][j] - mean[j]).powi(2))
                        .sum::<f64>()
                        / (n - 1.0)
                } else {
                    mean[j] * mean[j]
                };
                own + spread
            })
            .collect();
        for &k in &failed {
            let c = &mut cells[k];
            c.gradient[p] = mean.clone();
            let diagonal = (0..n_gates)
                .map(|i| {
                    (0..n_gates)
                        .map(|j| if i == j { variance[i] } else { 0.0 })
                        .collect()
                })
                .collect();
            match c.covariance.get_mut(p) {
                Some(m) => *m = diagonal,
                None => continue,
            }
            borrowed.push((k, p));
        }
    }
    borrowed
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(gates: usize, g: Vec<f64>) -> CellKnowledge {
        CellKnowledge {
            gates: (0..gates).map(|j| format!("G{j}")).collect(),
            parameters: vec!["t_sr".into(), "w".into()],
            gradient: vec![g.clone(), g],
            covariance: vec![vec![vec![1e-6; gates]; gates]; 2],
            process_noise_per_mv: vec![0.001; 2],
            floors: vec![0.0; 2],
            max_step_mv: 10.0,
            compensation: None,
        }
    }

    #[test]
    fn nothing_to_borrow_from_leaves_every_row_as_it_was() {
        let mut all_failed = vec![cell(2, vec![0.0, 0.0]), cell(2, vec![0.0, 0.0])];
        let before = all_failed.clone();
        assert!(borrow_failed_gradients(&mut all_failed).is_empty());
        assert_eq!(all_failed, before);
        let mut none_failed = vec![cell(2, vec![0.01, 0.0]), cell(2, vec![0.0, -0.02])];
        let before = none_failed.clone();
        assert!(borrow_failed_gradients(&mut none_failed).is_empty());
        assert_eq!(none_failed, before);
    }

    #[test]
    fn only_alike_cells_lend_and_borrow_and_a_non_finite_row_never_lends() {
        let mut cells = vec![
            cell(2, vec![0.02, 0.01]),
            cell(2, vec![f64::NAN, 0.5]), // not finite: neither lends nor borrows
            cell(3, vec![0.0, 0.0, 0.0]), // another design: left alone
            cell(2, vec![0.0, 0.0]),
        ];
        let borrowed = borrow_failed_gradients(&mut cells);
        assert_eq!(borrowed, vec![(3, 0), (3, 1)]);
        // one lender: its row, variance its own plus its value squared
        assert_eq!(cells[3].gradient[1], vec![0.02, 0.01]);
        assert!((cells[3].covariance[1][0][0] - (1e-6 + 4e-4)).abs() < 1e-15);
        assert!((cells[3].covariance[1][1][1] - (1e-6 + 1e-4)).abs() < 1e-15);
        assert_eq!(cells[2].gradient[0], vec![0.0; 3]);
        assert!(cells[1].gradient[0][0].is_nan());
    }
}
