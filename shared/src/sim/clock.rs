//! The simulated lab clock.

use serde::{Deserialize, Serialize};

/// Cumulative simulated lab time, s. Advanced only by the device's
/// operations (never by the host's clock).
///
/// ```
/// let mut c = spintune::sim::LabClock::default();
/// c.advance(17.0);
/// c.advance(28.0);
/// assert_eq!(c.seconds(), 45.0);
/// ```
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabClock {
    seconds: f64,
}

impl LabClock {
    /// Lab time elapsed so far, s.
    pub fn seconds(&self) -> f64 {
        self.seconds
    }

    /// Charges `dt_s ≥ 0` seconds (negative or non-finite values are ignored).
    pub fn advance(&mut self, dt_s: f64) {
        if dt_s.is_finite() && dt_s > 0.0 {
            self.seconds += dt_s;
        }
    }
}
