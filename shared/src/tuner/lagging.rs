//! A parameter that lags: measured out of band on the same side of its
//! target iteration after iteration without coming nearer
//! ([`super::array_run::ArrayRunSettings::repeat_lagging_scans`]).
//!
//! A cell left out of band while the rest of the array is in band is most
//! often one whose learned row points off a gradient that is small and
//! turning (docs/array-history.md, "A row that learns its bend"): each
//! move changes its value by less than one reading's σ, so the filter
//! learns the row slowly. Scanning that parameter more than once per
//! iteration and pooling the readings gives each move a smaller error bar,
//! at the lab time of the extra scans.

use serde::{Deserialize, Serialize};

/// Most extra scans of a lagging parameter per iteration.
pub const MAX_REPEATS: u32 = 4;

/// Most measurements a [`LagCount`] keeps (the longest
/// [`super::array_run::ArrayRunSettings::lagging_after`]).
pub const MAX_LAGGING_AFTER: u32 = 30;

/// One parameter's measurements in a row out of band on the same side of
/// its target (their `|ln(value/target)|`, at most [`MAX_LAGGING_AFTER`]).
/// The parameter lags when `after` of them in a row came no nearer the
/// target than by one band: a parameter that approaches, however far it
/// started, does not lag.
///
/// ```
/// use spintune::tuner::lagging::LagCount;
/// let (band, after) = (0.1, 3);
/// let mut lag = LagCount::default();
/// // w against a target of 270 µV: held near 200 µV
/// let lags: Vec<bool> = [200.0, 210.0, 205.0, 207.0]
///     .iter()
///     .map(|w| lag.note(w / 270.0_f64, band, after))
///     .collect();
/// assert_eq!(lags, [false, false, true, true]);
/// // in band, then approaching from below by more than a band in 3: no lag
/// let mut lag = LagCount::default();
/// let lags: Vec<bool> = [280.0, 150.0, 170.0, 195.0, 215.0]
///     .iter()
///     .map(|w| lag.note(w / 270.0_f64, band, after))
///     .collect();
/// assert_eq!(lags, [false; 5]);
/// ```
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct LagCount {
    /// −1 below the band, +1 above, 0 in band or not yet measured.
    side: i8,
    /// `|ln(value/target)|` of the measurements on that side, oldest first.
    residuals: Vec<f64>,
}

impl LagCount {
    /// Note a measurement, `ratio = value/target` (a non-finite or
    /// non-positive ratio, a failed fit, changes nothing), against the
    /// band's `relative_tolerance`; returns whether the parameter now lags
    /// over `after` measurements (1..=[`MAX_LAGGING_AFTER`], clamped).
    pub fn note(&mut self, ratio: f64, relative_tolerance: f64, after: u32) -> bool {
        if ratio.is_finite() && ratio > 0.0 {
            let side = if (ratio - 1.0).abs() <= relative_tolerance {
                0
            } else if ratio > 1.0 {
                1
            } else {
                -1
            };
            if side != self.side || side == 0 {
                self.residuals.clear();
            }
            self.side = side;
            if side != 0 {
                self.residuals.push(ratio.ln().abs());
                if self.residuals.len() > MAX_LAGGING_AFTER as usize {
                    self.residuals.remove(0);
                }
            }
        }
        self.lags(relative_tolerance, after)
    }

    /// Whether the last `after` measurements were all out of band on one
    /// side and the latest is not nearer the target than the first of them
    /// by `ln(1 + relative_tolerance)` (one band).
    pub fn lags(&self, relative_tolerance: f64, after: u32) -> bool {
        let after = after.clamp(1, MAX_LAGGING_AFTER) as usize;
        let n = self.residuals.len();
        n >= after && self.residuals[n - after] - self.residuals[n - 1] < relative_tolerance.ln_1p()
    }

    /// Start afresh (the target changed).
    pub fn clear(&mut self) {
        *self = Self::default();
    }
}
