//! Plunger steps that re-centre several cells' transition lines **at once**,
//! with the crosstalk of each cell's step onto its neighbours' lines taken
//! out (cross-cell virtual gates for the line level).
//!
//! A cell's line correction moves its own line gates (plungers) by the
//! single-cell step `q_c = −J_c⁻¹·μ_c` (`J_c` its line Jacobian, mV/mV;
//! `μ_c` its lines' offsets, mV). When every cell corrects in the same
//! batch, cell `k`'s plunger step `p_k` also acts on cell `c` as if `c`'s
//! own plunger of the same name had moved by `λ̂(|c − k|)·p_k` (the lab's
//! cross-cell calibration `λ̂`, nearest and next; the crosstalk model of
//! [`super::array`]'s prior). So the steps that put every corrected cell's
//! lines where its single-cell step would are the solution of
//!
//! `p_c + Σ_{k ≠ c} λ̂(|c − k|)·p_k = q_c`  for every corrected cell `c`,
//!
//! one linear system per line gate (`m × m`, `m ≤` the array's 16 cells).
//! Cells that do not correct in the batch take no step and are not
//! constrained. With `λ̂ = 0` the steps are the single-cell ones. (A cell
//! listed twice would make the system singular: each cell once.)

use nalgebra::{DMatrix, DVector};

use super::array::calibrated_fraction;
use crate::description::layout::CellGrid;

/// The joint steps: `cells[i] = (cell index, q)`, `q` the cell's
/// single-cell plunger step (mV per line gate, the same gate names in the
/// same order in every cell); returns `p` in the same order (mV), before
/// any step limit. `None` if the system is singular (only possible for
/// `λ̂` far beyond physical crosstalk: the matrix is diagonally dominant
/// while `2·(λ̂₁ + λ̂₂) < 1`).
///
/// ```
/// use spintune::tuner::line_steps::joint_line_steps;
/// // two neighbours that each need +1 mV: each moves 1/(1 + 0.3) mV, and
/// // each then sees its own move plus 0.3 × its neighbour's, 1 mV in all
/// let chain = spintune::description::layout::CellGrid::chain(2);
/// let p = joint_line_steps(&chain, &[(0, vec![1.0]), (1, vec![1.0])], [0.3, 0.05]).unwrap();
/// assert!((p[0][0] - 1.0 / 1.3).abs() < 1e-12);
/// assert!((p[0][0] + 0.3 * p[1][0] - 1.0).abs() < 1e-12);
/// ```
pub fn joint_line_steps(
    grid: &CellGrid,
    cells: &[(usize, Vec<f64>)],
    cross_calibration: [f64; 2],
) -> Option<Vec<Vec<f64>>> {
    let m = cells.len();
    let gates = cells.first().map_or(0, |(_, q)| q.len());
    if cells.iter().any(|(_, q)| q.len() != gates) {
        return None;
    }
    let coupling = DMatrix::from_fn(m, m, |i, j| {
        calibrated_fraction(cross_calibration, grid.distance(cells[i].0, cells[j].0))
    });
    let lu = coupling.lu();
    let mut steps = vec![vec![0.0; gates]; m];
    for g in 0..gates {
        let q = DVector::from_iterator(m, cells.iter().map(|(_, q)| q[g]));
        let p = lu.solve(&q)?;
        if p.iter().any(|x| !x.is_finite()) {
            return None;
        }
        for (step, x) in steps.iter_mut().zip(p.iter()) {
            step[g] = *x;
        }
    }
    Some(steps)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What cell `c` feels of everyone's steps under the crosstalk model,
    /// summed directly (an independent evaluation of the system).
    fn felt(cells: &[(usize, Vec<f64>)], p: &[Vec<f64>], lambda: [f64; 2], i: usize) -> Vec<f64> {
        let c = cells[i].0;
        let mut sum = p[i].clone();
        for (j, (k, _)) in cells.iter().enumerate() {
            let l = match c.abs_diff(*k) {
                1 => lambda[0],
                2 => lambda[1],
                _ => 0.0,
            };
            if j != i {
                for (s, x) in sum.iter_mut().zip(&p[j]) {
                    *s += l * x;
                }
            }
        }
        sum
    }

    #[test]
    fn every_corrected_cell_feels_its_single_cell_step() {
        let lambda = [0.3, 0.05];
        // cells 0..=3 and 6 correct, 4 and 5 do not (cell 6 is three cells
        // from the nearest corrected one: it moves alone)
        let cells = vec![
            (0, vec![1.0, -0.5]),
            (1, vec![-2.0, 0.3]),
            (2, vec![0.4, 1.5]),
            (3, vec![0.0, -1.0]),
            (6, vec![2.5, 0.1]),
        ];
        let p = joint_line_steps(&CellGrid::chain(7), &cells, lambda).unwrap();
        for (i, (_, q)) in cells.iter().enumerate() {
            for (f, q) in felt(&cells, &p, lambda, i).iter().zip(q) {
                assert!((f - q).abs() < 1e-12, "cell {i}: felt {f}, wanted {q}");
            }
        }
        // the isolated cell 6 moves by its own step
        assert_eq!(p[4], vec![2.5, 0.1]);
    }

    #[test]
    fn without_crosstalk_the_steps_are_the_single_cell_ones() {
        let cells = vec![(0, vec![1.0, 2.0]), (1, vec![-3.0, 0.5])];
        let p = joint_line_steps(&CellGrid::chain(2), &cells, [0.0, 0.0]).unwrap();
        assert_eq!(p, vec![vec![1.0, 2.0], vec![-3.0, 0.5]]);
    }

    #[test]
    fn independent_steps_would_overshoot_a_chain() {
        // three cells all needing +1 mV: single-cell steps make the middle
        // one feel 1 + 2·0.3 = 1.6 mV; the joint steps make everyone feel 1
        let lambda = [0.3, 0.05];
        let cells: Vec<_> = (0..3).map(|c| (c, vec![1.0])).collect();
        let single: Vec<Vec<f64>> = cells.iter().map(|(_, q)| q.clone()).collect();
        assert!((felt(&cells, &single, lambda, 1)[0] - 1.6).abs() < 1e-12);
        let p = joint_line_steps(&CellGrid::chain(7), &cells, lambda).unwrap();
        for i in 0..3 {
            assert!((felt(&cells, &p, lambda, i)[0] - 1.0).abs() < 1e-12);
        }
        assert!(
            p[1][0] < p[0][0],
            "the middle cell has two neighbours helping"
        );
    }

    #[test]
    fn mismatched_gate_counts_are_refused() {
        assert!(joint_line_steps(
            &CellGrid::chain(2),
            &[(0, vec![1.0]), (1, vec![1.0, 2.0])],
            [0.3, 0.05]
        )
        .is_none());
        assert_eq!(
            joint_line_steps(&CellGrid::chain(0), &[], [0.3, 0.05]),
            Some(vec![])
        );
    }
}
