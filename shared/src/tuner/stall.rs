//! A parameter that stopped approaching its target: [`StallWatch`].
//!
//! The joint array tuner learns each cell's rows from the cell's own moves.
//! Where a parameter's true gradient is about as small as one step's noise
//! (`w` on its thermal floor, or near a maximum in the gates), the learned
//! row ends up pointing wherever the noise took it, and the cell's moves
//! stop bringing the parameter nearer its target while the filter, having
//! seen little to contradict it, stays confident. Traced on random arrays
//! (docs/array-history.md, "Stalled parameters"): a `w` held at 154 µV for 30
//! iterations against a target of 180, a `t_sr` row that put the reload
//! time on the wrong gate. A watch per parameter notices when the
//! measurements have stayed out of band on one side for a window of
//! iterations without coming nearer by a band, and the loop starts the row
//! again ([`StalledRowSource`]): by default it keeps the learned gradient
//! but becomes as unsure as it started, so the next moves teach it again.

use serde::{Deserialize, Serialize};

/// Longest window a watch accepts (and so the most residuals it keeps):
/// invariant 8, bounded state.
pub const MAX_STALL_WINDOW: usize = 30;

/// Where a stalled parameter's row starts again
/// ([`super::array_run::ArrayRunSettings::stalled_row_from`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StalledRowSource {
    /// The mean of the rows the cells measured in band last learned
    /// ([`super::array::JointArrayTuner::borrow_row`]; every other cell
    /// when none is in band).
    Peers,
    /// The row's prior: the cell's initial measurement
    /// ([`super::array::JointArrayTuner::reset_row`]).
    Prior,
    /// The row as learned, its covariance widened by its prior's
    /// ([`super::array::JointArrayTuner::widen_row`]): the default.
    #[default]
    Widened,
}

/// The log residuals `ln(x/target)` of one parameter's measurements out of
/// band on one side since the parameter was last in band, crossed its
/// target, had its target changed or stalled; at most the window's length.
///
/// ```
/// use spintune::tuner::stall::StallWatch;
/// let band = 0.1; // ±10 %
/// let mut watch = StallWatch::default();
/// // w held near 154 µV against a target of 180 µV
/// let stalled: Vec<bool> = [152.0, 155.0, 153.0, 156.0]
///     .iter()
///     .map(|w| watch.note(w / 180.0_f64, band, 4))
///     .collect();
/// assert_eq!(stalled, [false, false, false, true]);
/// // a parameter that comes nearer by more than a band does not stall
/// let mut watch = StallWatch::default();
/// let approaching = [120.0, 135.0, 150.0, 160.0];
/// assert!(!approaching.iter().any(|w| watch.note(w / 180.0_f64, band, 4)));
/// ```
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StallWatch {
    residuals: Vec<f64>,
}

impl StallWatch {
    /// Note one measurement, `ratio = value/target` (positive; anything else
    /// is ignored, as a measurement that failed), against the band's
    /// `relative_tolerance` (`|value − target| ≤ relative_tolerance ·
    /// target` is in band). Returns `true` when the parameter stalled: the
    /// last `window` measurements (2..=[`MAX_STALL_WINDOW`], clamped) were
    /// all out of band on the same side and the latest is not nearer its
    /// target, in `|ln(value/target)|`, than the first by
    /// `ln(1 + relative_tolerance)` (one band). The watch then starts
    /// afresh, so a parameter that stays stalled is reported once per
    /// window.
    pub fn note(&mut self, ratio: f64, relative_tolerance: f64, window: usize) -> bool {
        if !(ratio.is_finite() && ratio > 0.0) {
            return false;
        }
        if (ratio - 1.0).abs() <= relative_tolerance {
            self.clear();
            return false;
        }
        let r = ratio.ln();
        if self
            .residuals
            .last()
            .is_some_and(|&l| l.signum() != r.signum())
        {
            // crossed its target: the moves did act on it
            self.clear();
        }
        let window = window.clamp(2, MAX_STALL_WINDOW);
        self.residuals.push(r);
        if self.residuals.len() > window {
            self.residuals.remove(0);
        }
        let stalled = self.residuals.len() == window
            && self.residuals[0].abs() - r.abs() < relative_tolerance.ln_1p();
        if stalled {
            self.clear();
        }
        stalled
    }

    /// Forget the measurements (the target changed, or the row was reset).
    pub fn clear(&mut self) {
        self.residuals.clear();
    }

    /// Measurements out of band on one side in a row, as kept (at most the
    /// window).
    pub fn len(&self) -> usize {
        self.residuals.len()
    }

    /// Whether no measurement is kept.
    pub fn is_empty(&self) -> bool {
        self.residuals.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_parameter_in_band_or_crossing_its_target_starts_the_watch_afresh() {
        let mut w = StallWatch::default();
        assert!(!w.note(0.8, 0.1, 3));
        assert!(!w.note(0.81, 0.1, 3));
        assert!(!w.note(0.95, 0.1, 3), "in band");
        assert!(w.is_empty());
        assert!(!w.note(0.8, 0.1, 3));
        assert!(!w.note(1.25, 0.1, 3), "crossed to the other side");
        assert_eq!(w.len(), 1);
        assert!(!w.note(1.24, 0.1, 3));
        assert!(w.note(1.26, 0.1, 3), "three high, none nearer by a band");
        assert!(w.is_empty(), "reported once, then afresh");
    }

    #[test]
    fn progress_is_judged_over_the_window_and_failed_measurements_are_ignored() {
        let mut w = StallWatch::default();
        // 0.5 → 0.8: ln 0.8 − ln 0.5 = 0.47 nearer, more than ln 1.1 = 0.095
        for r in [0.5, 0.6, 0.7, 0.8] {
            assert!(!w.note(r, 0.1, 4));
        }
        // the window slides: 0.6, 0.7, 0.8, 0.8 still came nearer
        assert!(!w.note(0.8, 0.1, 4));
        assert!(!w.note(f64::NAN, 0.1, 4));
        assert!(!w.note(-1.0, 0.1, 4));
        // 0.7, 0.8, 0.8, 0.75: ln(0.75/0.7) = 0.069 < 0.095
        assert!(w.note(0.75, 0.1, 4));
    }

    #[test]
    fn the_window_is_bounded() {
        let mut w = StallWatch::default();
        for i in 0..100 {
            // always coming nearer by a band, so never stalled
            let ratio = 0.001 * 1.2f64.powi(i).min(800.0);
            w.note(ratio, 0.1, 1000);
            assert!(w.len() <= MAX_STALL_WINDOW);
        }
        let mut w = StallWatch::default();
        assert!(!w.note(0.5, 0.1, 0));
        assert!(w.note(0.5, 0.1, 0), "a window below 2 is 2");
    }
}
