//! A parameter that lags: measured out of band on the same side of its
//! target iteration after iteration
//! ([`super::array_run::ArrayRunSettings::repeat_lagging_scans`]).
//!
//! A cell left out of band while the rest of the array is in band is most
//! often one whose learned row points off a gradient that is small and
//! turning (docs/array-history.md, "A row that learns its bend"): each
//! move changes its value by less than one reading's σ, so the filter
//! learns the row slowly. Scanning that parameter more than once per
//! iteration and pooling the readings gives each move a smaller error bar,
//! at the lab time of the extra scans. Off by default (measured there).

use serde::{Deserialize, Serialize};

/// Most extra scans of a lagging parameter per iteration.
pub const MAX_REPEATS: u32 = 4;

/// Largest [`super::array_run::ArrayRunSettings::lagging_after`].
pub const MAX_LAGGING_AFTER: u32 = 30;

/// Consecutive measurements of one parameter out of band on the same side.
/// The parameter lags once they reach `after`
/// ([`super::array_run::ArrayRunSettings::lagging_after`]), approaching or
/// not: a rule that also asked it to come no nearer than a band lagged
/// later and measured worse (docs/array-history.md, "A row that learns
/// its bend; a lagging parameter scanned again"). Off by default: on fresh
/// arrays the extra scans cost more lab time than the phases they spared.
///
/// ```
/// use spintune::tuner::lagging::LagCount;
/// let mut lag = LagCount::default();
/// // w against a target of 270 µV, band ±10 %
/// let counts: Vec<u32> = [200.0, 210.0, 205.0, 280.0, 200.0, 310.0]
///     .iter()
///     .map(|w| lag.note(w / 270.0_f64, 0.1))
///     .collect();
/// // in band at 280 µV, then low again, then high (the other side)
/// assert_eq!(counts, [1, 2, 3, 0, 1, 1]);
/// assert!(lag.lags(1) && !lag.lags(2));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LagCount {
    /// −1 below the band, +1 above, 0 in band or not yet measured.
    side: i8,
    /// Measurements in a row on that side.
    count: u32,
}

impl LagCount {
    /// Note a measurement, `ratio = value/target` (a non-finite or
    /// non-positive ratio, a failed fit, leaves the count as it is),
    /// against the band's `relative_tolerance`; returns the count.
    pub fn note(&mut self, ratio: f64, relative_tolerance: f64) -> u32 {
        if !(ratio.is_finite() && ratio > 0.0) {
            return self.count;
        }
        let side = if (ratio - 1.0).abs() <= relative_tolerance {
            0
        } else if ratio > 1.0 {
            1
        } else {
            -1
        };
        self.count = match side {
            0 => 0,
            s if s == self.side => self.count.saturating_add(1),
            _ => 1,
        };
        self.side = side;
        self.count
    }

    /// Whether `after` or more measurements in a row were out of band on
    /// one side.
    pub fn lags(&self, after: u32) -> bool {
        after > 0 && self.count >= after
    }

    /// Start afresh (the target changed).
    pub fn clear(&mut self) {
        *self = Self::default();
    }
}
