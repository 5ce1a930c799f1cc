//! The cells' initial rows pooled: each cell's measured row is combined
//! with what the other cells measured (empirical Bayes).
//!
//! One repetition of a 6 mV finite difference leaves each gate's `w`
//! gradient with a noise of about 0.010 /mV, the size of the true own-cell
//! gradients themselves (docs/array-history.md, "Stalled cells traced"), so a
//! cell's own row often points the wrong way. The cells of an array are
//! one design: their true rows scatter around a common mean. Per parameter
//! and gate, the other cells' rows give a prior for cell `k`'s true value
//! (leave-one-out, so nothing counts twice):
//!
//! * mean `μ` of their rows;
//! * variance `τ² = max(s² − σ̄², 0) + max(s², σ̄²)/n`: the spread `s²`
//!   between their rows less what their own noise `σ̄²` (mean measured
//!   variance) explains, plus the uncertainty of `μ` itself (`n` rows).
//!
//! Cell `k`'s row is then the precision-weighted mean of that prior and its
//! own measurement (`g`, `σ²`): `(g/σ² + μ/τ²) / (1/σ² + 1/τ²)`, variance
//! `1 / (1/σ² + 1/τ²)`. A row whose measurement failed (all zero) has no
//! measurement and takes the prior. Nothing here is a tuned constant: the
//! weights come from the rows' own measured variances and their spread.
//!
//! The cells measure in lockstep, so each measured its own row times its
//! lockstep factor ([`super::array::lockstep_factor`]: larger inside the
//! chain than at its ends). The rows can be pooled in units of a scale per
//! cell (each row divided by its cell's `scale`, its variance by the
//! square, and scaled back), so an end cell is not pulled towards the
//! inner cells' longer rows. The array does that only with
//! `ArrayRunSettings::pool_in_lockstep_units`: it measured worse than
//! pooling the rows as measured (docs/array-history.md).

use super::array::CellKnowledge;

/// Pool every alike cell's row with the other cells' rows (module docs),
/// each cell's row in units of its `scales` entry (a missing, non-finite or
/// non-positive entry counts as 1). Cells of another gate or parameter
/// count, and rows that are not finite, neither lend nor change; a
/// parameter needs two measured rows besides the cell's own to estimate the
/// spread, else the cell's row is kept. Returns the `(cell, parameter)`
/// pairs that changed.
///
/// ```
/// use spintune::tuner::array::CellKnowledge;
/// use spintune::tuner::pooled_gradient::pool_gradients;
/// let cell = |g: f64, var: f64| CellKnowledge {
///     gates: vec!["N".into()],
///     parameters: vec!["w".into()],
///     gradient: vec![vec![g]],
///     covariance: vec![vec![vec![var]]],
///     process_noise_per_mv: vec![0.001],
///     floors: vec![0.0],
///     max_step_mv: 10.0,
///     compensation: None,
/// };
/// // three cells measured with noise σ² = 1e-4 (σ = 0.01 /mV)
/// let mut cells = vec![cell(0.010, 1e-4), cell(0.014, 1e-4), cell(-0.006, 1e-4)];
/// pool_gradients(&mut cells, &[1.0; 3]);
/// // cell 2's prior from cells 0 and 1: μ = 0.012, s² = 8e-6 < σ̄² = 1e-4,
/// // so τ² = σ̄²/2 = 5e-5: the noisy −0.006 is pulled to +0.006
/// let (g, var) = (cells[2].gradient[0][0], cells[2].covariance[0][0][0]);
/// assert!((g - 0.006).abs() < 1e-12);
/// assert!((var - 1.0 / (1.0 / 1e-4 + 1.0 / 5e-5)).abs() < 1e-15);
/// ```
pub fn pool_gradients(cells: &mut [CellKnowledge], scales: &[f64]) -> Vec<(usize, usize)> {
    let mut changed = Vec::new();
    let scale = |k: usize| {
        scales
            .get(k)
            .copied()
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(1.0)
    };
    let Some(first) = cells.first() else {
        return changed;
    };
    let (n_gates, n_params) = (first.gates.len(), first.gradient.len());
    let alike = |c: &CellKnowledge| c.has_shape(n_gates, n_params);
    for p in 0..n_params {
        // (row, own variance per gate) of every alike cell: `None` where
        // the row failed (all zero); non-finite rows are left out
        let rows: Vec<Option<(Vec<f64>, Vec<f64>)>> = cells
            .iter()
            .enumerate()
            .map(|(k, c)| {
                if !alike(c) || !c.gradient[p].iter().all(|x| x.is_finite()) {
                    return None;
                }
                if c.gradient[p].iter().all(|&x| x == 0.0) {
                    return None;
                }
                let s = scale(k);
                let var = (0..n_gates)
                    .map(|j| c.covariance[p][j][j] / (s * s))
                    .collect::<Vec<f64>>();
                let row = c.gradient[p].iter().map(|g| g / s).collect();
                var.iter()
                    .all(|v| v.is_finite() && *v > 0.0)
                    .then_some((row, var))
            })
            .collect();
        let mut pooled = Vec::new();
        for (k, c) in cells.iter().enumerate() {
            if !alike(c) || !c.gradient[p].iter().all(|x| x.is_finite()) {
                continue;
            }
            let others: Vec<&(Vec<f64>, Vec<f64>)> = rows
                .iter()
                .enumerate()
                .filter(|(i, _)| *i != k)
                .filter_map(|(_, r)| r.as_ref())
                .collect();
            if others.len() < 2 {
                continue;
            }
            let own = rows[k].as_ref();
            let n = others.len() as f64;
            let mut g = vec![0.0; n_gates];
            let mut var = vec![0.0; n_gates];
            for j in 0..n_gates {
                let mean = others.iter().map(|(r, _)| r[j]).sum::<f64>() / n;
                let spread = others
                    .iter()
                    .map(|(r, _)| (r[j] - mean).powi(2))
                    .sum::<f64>()
                    / (n - 1.0);
                let noise = others.iter().map(|(_, v)| v[j]).sum::<f64>() / n;
                // > 0: every lender's variance is
                let tau2 = (spread - noise).max(0.0) + spread.max(noise) / n;
                (g[j], var[j]) = match own {
                    Some((r, v)) => {
                        let precision = 1.0 / v[j] + 1.0 / tau2;
                        ((r[j] / v[j] + mean / tau2) / precision, 1.0 / precision)
                    }
                    None => (mean, tau2),
                };
            }
            pooled.push((k, g, var));
        }
        for (k, g, var) in pooled {
            let s = scale(k);
            let (g, var): (Vec<f64>, Vec<f64>) =
                g.iter().zip(&var).map(|(g, v)| (g * s, v * s * s)).unzip();
            let c = &mut cells[k];
            c.gradient[p] = g;
            c.covariance[p] = (0..n_gates)
                .map(|i| {
                    (0..n_gates)
                        .map(|j| if i == j { var[i] } else { 0.0 })
                        .collect()
                })
                .collect();
            changed.push((k, p));
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(g: Vec<f64>, var: f64) -> CellKnowledge {
        let gates = g.len();
        CellKnowledge {
            gates: (0..gates).map(|j| format!("G{j}")).collect(),
            parameters: vec!["w".into()],
            gradient: vec![g],
            covariance: vec![(0..gates)
                .map(|i| (0..gates).map(|j| if i == j { var } else { 0.0 }).collect())
                .collect()],
            process_noise_per_mv: vec![0.001],
            floors: vec![0.0],
            max_step_mv: 10.0,
            compensation: None,
        }
    }

    #[test]
    fn a_failed_row_takes_the_others_prior() {
        let mut cells = vec![
            cell(vec![0.01, 0.0], 1e-6),
            cell(vec![0.03, 0.0], 1e-6),
            cell(vec![0.02, 0.0], 1e-6),
            cell(vec![0.0, 0.0], 1.0), // failed
        ];
        pool_gradients(&mut cells, &[]);
        // others of cell 3: 0.01, 0.03, 0.02 → μ 0.02, s² 1e-4, σ̄² 1e-6
        assert!((cells[3].gradient[0][0] - 0.02).abs() < 1e-12);
        let tau2 = (1e-4 - 1e-6) + 1e-4 / 3.0;
        assert!((cells[3].covariance[0][0][0] - tau2).abs() < 1e-12);
        // gate 1 is zero in every measured row: no spread, so the mean's
        // own uncertainty σ̄²/n is all the variance
        assert_eq!(cells[3].gradient[0][1], 0.0);
        assert!((cells[3].covariance[0][1][1] - 1e-6 / 3.0).abs() < 1e-15);
    }

    #[test]
    fn precise_rows_far_apart_are_barely_moved() {
        // spread 1e-4 ≫ own noise 1e-10: each cell keeps its own row
        let mut cells = vec![
            cell(vec![0.01], 1e-10),
            cell(vec![0.03], 1e-10),
            cell(vec![0.02], 1e-10),
        ];
        pool_gradients(&mut cells, &[]);
        for (c, g) in cells.iter().zip([0.01, 0.03, 0.02]) {
            assert!((c.gradient[0][0] - g).abs() < 1e-7, "{c:?}");
        }
    }

    #[test]
    fn rows_are_pooled_in_units_of_their_scale() {
        // one true row 0.01, measured ×1.6 inside the chain, ×1.35 at its ends
        let scales = [1.35, 1.6, 1.6, 1.35];
        let mut cells: Vec<CellKnowledge> = scales
            .iter()
            .map(|s| cell(vec![0.01 * s], 1e-6 * s * s))
            .collect();
        cells[3].gradient[0][0] = 0.0; // failed
        pool_gradients(&mut cells, &scales);
        for (c, s) in cells.iter().zip(scales) {
            assert!((c.gradient[0][0] - 0.01 * s).abs() < 1e-12, "{c:?}");
        }
    }

    #[test]
    fn two_cells_are_too_few_to_pool() {
        let mut cells = vec![cell(vec![0.01], 1e-4), cell(vec![-0.03], 1e-4)];
        let before = cells.clone();
        assert!(pool_gradients(&mut cells, &[]).is_empty());
        assert_eq!(cells, before);
    }

    #[test]
    fn a_non_finite_row_neither_lends_nor_changes() {
        let mut cells = vec![
            cell(vec![0.01], 1e-4),
            cell(vec![f64::NAN], 1e-4),
            cell(vec![0.02], 1e-4),
            cell(vec![0.03], 1e-4),
        ];
        let changed = pool_gradients(&mut cells, &[]);
        assert!(cells[1].gradient[0][0].is_nan());
        assert!(!changed.contains(&(1, 0)));
        assert_eq!(changed.len(), 3);
    }
}
