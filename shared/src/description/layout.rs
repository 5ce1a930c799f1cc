//! Where an array's cells sit: a chain, or a ladder of two rows
//! ([`Layout`]), and the one rule every part of the array follows for which
//! cells are neighbours ([`CellGrid::distance`]): the simulated world's
//! crosstalk, the joint tuner's neighbourhoods and priors, the sensors
//! re-checked after a move, and the benchmark's "neighbours of a changed
//! cell".
//!
//! Cells are numbered row by row: in a ladder of 2×N cells, cells
//! `0..N` form the first row and `N..2N` the second, so cell `k` sits in
//! row `k / N`, column `k % N`, and cell `k` and cell `k + N` face each
//! other across the rung. The distance between two cells is the number of
//! steps along rows and rungs between them (`|Δrow| + |Δcolumn|`): 1 for
//! the nearest cells (the crosstalk `λ(1)`), 2 for the next ones (`λ(2)`;
//! in a ladder this includes the diagonal neighbours), 0 beyond. A chain is
//! the ladder's one-row case, so its distance is `|j − k|`.
//!
//! ```
//! use spintune::description::layout::{CellGrid, Layout};
//! let ladder = CellGrid::new(Layout::Ladder, 8).unwrap(); // 2 rows × 4 columns
//! assert_eq!(ladder.position(5), (1, 1));
//! assert_eq!(ladder.distance(1, 5), 1); // across the rung
//! assert_eq!(ladder.distance(0, 5), 2); // diagonal
//! assert_eq!(ladder.distance(0, 3), 3);
//! let chain = CellGrid::chain(8);
//! assert_eq!(chain.distance(1, 5), 4);
//! assert_eq!(CellGrid::new(Layout::Ladder, 5).unwrap_err().field, "layout");
//! ```

use serde::{Deserialize, Serialize};

use crate::config_error::ConfigError;

/// How the cells of an array are arranged (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// One row: cell k's nearest neighbours are k − 1 and k + 1.
    #[default]
    Chain,
    /// Two rows of `cells / 2` (an even number of cells, at least 4): cell
    /// k's nearest neighbours are its row's k − 1 and k + 1 and the cell
    /// across the rung.
    Ladder,
}

impl Layout {
    /// `true` for the default (a chain); lets configs leave the field out.
    pub fn is_chain(&self) -> bool {
        *self == Layout::Chain
    }
}

/// The cells of an array on their grid: `rows × columns` cells numbered row
/// by row (module docs). Invariant: `rows · columns = cells`, `rows` 1 or 2.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CellGrid {
    cells: usize,
    columns: usize,
}

impl CellGrid {
    /// The grid of `cells` cells in `layout`; `Err` naming `layout` for a
    /// ladder of an odd number of cells or of fewer than 4 (a ladder of 2
    /// is a chain of 2).
    pub fn new(layout: Layout, cells: u32) -> Result<Self, ConfigError> {
        let cells = cells as usize;
        match layout {
            Layout::Chain => Ok(Self::chain(cells)),
            Layout::Ladder if cells >= 4 && cells % 2 == 0 => Ok(Self {
                cells,
                columns: cells / 2,
            }),
            Layout::Ladder => Err(ConfigError::new(
                "layout",
                format!("a ladder needs an even number of cells, at least 4 (got {cells})"),
            )),
        }
    }

    /// The grid of `cells` cells in `layout` where that fits, else a chain:
    /// for state that was validated when it was built ([`CellGrid::new`]
    /// then), so the fallback is never taken in a run; it keeps a
    /// hand-edited checkpoint from panicking.
    pub fn or_chain(layout: Layout, cells: usize) -> Self {
        u32::try_from(cells)
            .ok()
            .and_then(|c| Self::new(layout, c).ok())
            .unwrap_or_else(|| Self::chain(cells))
    }

    /// A chain of `cells` cells.
    pub fn chain(cells: usize) -> Self {
        Self {
            cells,
            columns: cells.max(1),
        }
    }

    /// The layout this grid is (a one-row grid is a chain).
    pub fn layout(&self) -> Layout {
        if self.rows() > 1 {
            Layout::Ladder
        } else {
            Layout::Chain
        }
    }

    /// Number of cells.
    pub fn cells(&self) -> usize {
        self.cells
    }

    /// Number of rows (1 for a chain, 2 for a ladder).
    pub fn rows(&self) -> usize {
        self.cells.div_ceil(self.columns)
    }

    /// Number of columns (cells per row).
    pub fn columns(&self) -> usize {
        self.columns
    }

    /// `(row, column)` of `cell`.
    pub fn position(&self, cell: usize) -> (usize, usize) {
        (cell / self.columns, cell % self.columns)
    }

    /// Steps along rows and rungs from `a` to `b` (module docs); `|a − b|`
    /// in a chain.
    pub fn distance(&self, a: usize, b: usize) -> usize {
        let ((ra, ca), (rb, cb)) = (self.position(a), self.position(b));
        ra.abs_diff(rb) + ca.abs_diff(cb)
    }

    /// The cells within `radius` of `cell` (itself included), in order.
    pub fn within(&self, cell: usize, radius: usize) -> impl Iterator<Item = usize> + '_ {
        (0..self.cells).filter(move |&k| self.distance(cell, k) <= radius)
    }

    /// The checkerboard colour of `cell` (`true` for odd `row + column`):
    /// no two nearest neighbours share it. In a chain, odd cells.
    pub fn odd(&self, cell: usize) -> bool {
        let (r, c) = self.position(cell);
        (r + c) % 2 == 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_ladder_of_eight_has_the_neighbours_a_drawing_shows() {
        // 0 1 2 3
        // 4 5 6 7
        let g = CellGrid::new(Layout::Ladder, 8).unwrap();
        let nearest = |c| g.within(c, 1).filter(|&k| k != c).collect::<Vec<_>>();
        assert_eq!(nearest(0), [1, 4]);
        assert_eq!(nearest(1), [0, 2, 5]);
        assert_eq!(nearest(6), [2, 5, 7]);
        let next: Vec<_> = g.within(1, 2).filter(|&k| g.distance(1, k) == 2).collect();
        assert_eq!(next, [3, 4, 6]);
        assert_eq!((g.rows(), g.columns()), (2, 4));
        assert_eq!(g.layout(), Layout::Ladder);
        assert_eq!(CellGrid::chain(8).layout(), Layout::Chain);
        assert_eq!(CellGrid::or_chain(Layout::Ladder, 8), g);
        assert_eq!(CellGrid::or_chain(Layout::Ladder, 5), CellGrid::chain(5));
        assert!(CellGrid::new(Layout::Ladder, 2).is_err());
        assert!(CellGrid::new(Layout::Ladder, 16).is_ok());
    }

    proptest! {
        /// A chain's distance is the index difference, and the
        /// checkerboard colour is the index's parity.
        #[test]
        fn a_chain_is_a_one_row_grid(cells in 1usize..=16, a in 0usize..16, b in 0usize..16) {
            let (a, b) = (a % cells, b % cells);
            let g = CellGrid::chain(cells);
            prop_assert_eq!(g.distance(a, b), a.abs_diff(b));
            prop_assert_eq!(g.odd(a), a % 2 == 1);
            prop_assert_eq!(g.rows(), 1);
        }

        /// The distance is a metric on the grid, nearest neighbours never
        /// share a colour, and a cell has at most 3 nearest neighbours in a
        /// ladder.
        #[test]
        fn a_ladder_distance_is_a_metric(half in 2usize..=8, a in 0usize..16, b in 0usize..16, c in 0usize..16) {
            let cells = 2 * half;
            let (a, b, c) = (a % cells, b % cells, c % cells);
            let g = CellGrid::new(Layout::Ladder, cells as u32).unwrap();
            prop_assert_eq!(g.distance(a, b), g.distance(b, a));
            prop_assert_eq!(g.distance(a, b) == 0, a == b);
            prop_assert!(g.distance(a, c) <= g.distance(a, b) + g.distance(b, c));
            if g.distance(a, b) == 1 {
                prop_assert_ne!(g.odd(a), g.odd(b));
            }
            prop_assert!(g.within(a, 1).count() <= 4);
        }
    }
}
