//! When a flat row may return to its prior again: [`FlatResetWatch`].
//!
//! A parameter measured out of band whose learned row is flat returns to
//! its prior, the cell's initial measurement
//! ([`super::array_run::ArrayRunSettings::reset_flat_row_fraction`]): where
//! `w` sits on its thermal floor the data say nothing, and the prior is the
//! one direction in which the parameter did respond. Every update after the
//! reset flattens the row again, so the reset repeats and the cell walks
//! along the prior's direction step after step. That is what brings a `w`
//! back off its floor, but the prior is a straight line measured at the cold
//! start, and the rows are not straight: `ln t_c` has quadratic terms in the
//! gates, and a hundred mV away its gradient can point the other way.
//! Traced on the default array and on 7003 (docs/array-history.md, "A flat row's
//! prior refuted"): `w` rose towards its target, turned over, and the
//! repeated resets walked the cell down onto its floor and on to the gate
//! limits, where `t_c` had vanished.
//!
//! The watch tells the two apart by what the resets did. From a row's first
//! reset it keeps the parameter's nearest reading to its target,
//! `|ln(value/target)|`, with that reading's relative σ. A parameter whose
//! latest reading is farther from its target than that nearest one, on the
//! same side, by more than `sigmas` σ of the two readings has turned away:
//! the prior is refuted, and the row is not reset again until the parameter
//! comes into band, crosses its target or gets a new one. A parameter that
//! stays where it was (on a floor) keeps its resets. (The nearest of many
//! noisy readings sits about 1.5 σ nearer than the truth after ten of them,
//! so the threshold counts from a reading that flatters: 3 σ of the pair
//! leaves room for that.)

use serde::{Deserialize, Serialize};

/// One parameter's flat-row resets since it was last in band, crossed its
/// target or had its target changed.
///
/// ```
/// use spintune::tuner::flat_reset::FlatResetWatch;
/// let band = 0.1; // ±10 %
/// // w against a target of 270 µV, readings ±2 %
/// let mut watch = FlatResetWatch::default();
/// assert!(watch.may_reset());
/// watch.reset_at(192.0 / 270.0, 0.02);
/// // the resets bring it nearer, to 213 µV ...
/// watch.note(213.0 / 270.0, 0.02, band, 3.0);
/// // ... then it turns: 205 µV is within the noise of the nearest reading
/// watch.note(205.0 / 270.0, 0.02, band, 3.0);
/// assert!(watch.may_reset());
/// // 186 µV is 0.136 in ln, 4.8 σ of the pair, from the nearest: refuted
/// watch.note(186.0 / 270.0, 0.02, band, 3.0);
/// assert!(!watch.may_reset());
/// // in band again: the next flat row may reset
/// watch.note(260.0 / 270.0, 0.02, band, 3.0);
/// assert!(watch.may_reset());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct FlatResetWatch {
    /// Since the first reset: the nearest reading's `ln(value/target)` and
    /// its relative σ.
    nearest: Option<(f64, f64)>,
    /// The parameter turned away from its target since the first reset.
    refuted: bool,
}

impl FlatResetWatch {
    /// Whether the row may return to its prior now.
    pub fn may_reset(&self) -> bool {
        !self.refuted
    }

    /// The row returned to its prior at a reading `ratio = value/target`
    /// with relative σ `rel_sigma` (σ/value). The first reset since the
    /// watch was cleared starts the watch; later ones change nothing.
    pub fn reset_at(&mut self, ratio: f64, rel_sigma: f64) {
        if self.nearest.is_none() && ratio.is_finite() && ratio > 0.0 {
            self.nearest = Some((ratio.ln(), finite_or_zero(rel_sigma)));
        }
    }

    /// Note a reading `ratio = value/target` with relative σ `rel_sigma`
    /// against the band's `relative_tolerance`: in band, or across the
    /// target from the first reset, clears the watch; farther from the
    /// target than the nearest reading since the first reset by more than
    /// `sigmas` × the two readings' combined σ refutes the prior (`sigmas =
    /// 0`: never); a nearer one becomes the nearest. A reading that is not
    /// finite and positive (a failed fit) is ignored.
    pub fn note(&mut self, ratio: f64, rel_sigma: f64, relative_tolerance: f64, sigmas: f64) {
        if !(ratio.is_finite() && ratio > 0.0) {
            return;
        }
        if (ratio - 1.0).abs() <= relative_tolerance {
            *self = Self::default();
            return;
        }
        let Some((r0, s0)) = self.nearest else { return };
        let (r, s) = (ratio.ln(), finite_or_zero(rel_sigma));
        if r.signum() != r0.signum() {
            *self = Self::default();
        } else if r.abs() < r0.abs() {
            self.nearest = Some((r, s));
        } else if sigmas > 0.0 && r.abs() - r0.abs() > sigmas * s0.hypot(s) {
            self.refuted = true;
        }
    }
}

fn finite_or_zero(x: f64) -> f64 {
    if x.is_finite() && x > 0.0 {
        x
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_watch_without_a_reset_never_refutes() {
        let mut w = FlatResetWatch::default();
        for x in [0.5, 0.4, 0.3] {
            w.note(x, 0.01, 0.1, 3.0);
        }
        assert!(w.may_reset());
    }

    #[test]
    fn the_distance_counts_from_the_nearest_reading_since_the_first_reset() {
        let mut w = FlatResetWatch::default();
        w.reset_at(0.8, 0.02);
        // a later reset farther away does not move the anchor
        w.reset_at(0.7, 0.02);
        // ln(0.75/0.8) = −0.065 > 3·0.028 = 0.085? no: kept
        w.note(0.75, 0.02, 0.1, 3.0);
        assert!(w.may_reset());
        // ln(0.72/0.8) = −0.105 > 0.085: refuted
        w.note(0.72, 0.02, 0.1, 3.0);
        assert!(!w.may_reset());
        // a nearer reading moves the anchor, but refuted stays refuted
        w.note(0.85, 0.02, 0.1, 3.0);
        assert!(!w.may_reset());
    }

    #[test]
    fn a_nearer_reading_becomes_the_anchor() {
        let mut w = FlatResetWatch::default();
        w.reset_at(0.7, 0.02);
        w.note(0.85, 0.02, 0.1, 3.0);
        // ln(0.75/0.85) = −0.125: refuted from 0.85, though nearer than 0.7
        w.note(0.75, 0.02, 0.1, 3.0);
        assert!(!w.may_reset());
    }

    #[test]
    fn in_band_or_across_the_target_clears_the_watch() {
        let mut w = FlatResetWatch::default();
        w.reset_at(0.8, 0.02);
        w.note(0.5, 0.02, 0.1, 3.0);
        assert!(!w.may_reset());
        w.note(0.95, 0.02, 0.1, 3.0);
        assert!(w.may_reset());
        w.note(0.5, 0.02, 0.1, 3.0);
        assert!(w.may_reset(), "no reset since the watch cleared");
        // above the target: crossing below clears it
        let mut w = FlatResetWatch::default();
        w.reset_at(1.3, 0.02);
        w.note(0.7, 0.02, 0.1, 3.0);
        w.note(0.5, 0.02, 0.1, 3.0);
        assert!(w.may_reset());
    }

    #[test]
    fn above_the_target_moving_up_refutes_and_zero_sigmas_never() {
        let mut w = FlatResetWatch::default();
        w.reset_at(1.3, 0.02);
        w.note(1.45, 0.02, 0.1, 3.0);
        assert!(!w.may_reset());
        let mut w = FlatResetWatch::default();
        w.reset_at(1.3, 0.02);
        w.note(3.0, 0.02, 0.1, 0.0);
        assert!(w.may_reset());
    }

    #[test]
    fn failed_readings_are_ignored() {
        let mut w = FlatResetWatch::default();
        w.reset_at(f64::NAN, 0.02);
        w.reset_at(0.8, f64::NAN);
        for x in [f64::NAN, 0.0, -1.0, f64::INFINITY] {
            w.note(x, 0.02, 0.1, 3.0);
        }
        assert!(w.may_reset());
        // an unknown σ counts as 0: with both unknown, any step away refutes
        w.note(0.79, f64::NAN, 0.1, 3.0);
        assert!(!w.may_reset());
    }
}
