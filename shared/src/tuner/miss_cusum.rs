//! Persistent misses of a learned row, detected ([`MissCusum`]): Page's
//! two-sided CUSUM over the row's normalised innovations.
//!
//! A Kalman row whose process noise was chosen for a gently changing
//! gradient lags a gradient that turns fast (docs/array-history.md, "why a stuck
//! row lags"): its predictions then miss, step after step, on the same
//! side. A single miss of a few σ is a noisy value and should teach only
//! as much as the filter's gain says; misses that persist in one direction
//! are a change the row has not kept up with. The CUSUM tells the two
//! apart: each normalised innovation `z = innovation / σ_innovation` is
//! clamped to ±[`MAX_SCORE`] (at `h` ≥ 2.5σ one wild value alone cannot
//! fire: it counts at most `3 − k`), less the
//! slack [`SLACK`] it is summed on each side, `S⁺ ← max(0, S⁺ + z − k)`,
//! `S⁻ ← max(0, S⁻ − z − k)`; when either passes the threshold `h` the
//! detector fires and restarts. With unit-variance innovations and the
//! textbook `k = 0.5`, `h = 4`, the detector fires by chance about once in
//! 170 innovations (Montgomery's table for the two-sided tabular CUSUM); a
//! row that misses by 2σ every time fires on its third.

use serde::{Deserialize, Serialize};

/// The CUSUM's slack `k`, σ: innovations within ±k of zero pull both sums
/// down (the textbook choice for detecting a shift of 1σ).
pub const SLACK: f64 = 0.5;

/// A normalised innovation counts at most this many σ.
pub const MAX_SCORE: f64 = 3.0;

/// The two one-sided sums (σ, ≥ 0); plain data, part of a row's state.
///
/// ```
/// use spintune::tuner::miss_cusum::MissCusum;
/// let mut c = MissCusum::default();
/// // noise around zero never accumulates …
/// for z in [0.4, -0.3, 0.5, -0.5, 0.2] {
///     assert!(!c.observe(z, 4.0));
/// }
/// // … misses of 2σ on one side fire on the third (3 × 1.5σ > 4σ)
/// assert!(!c.observe(2.0, 4.0));
/// assert!(!c.observe(2.0, 4.0));
/// assert!(c.observe(2.0, 4.0));
/// assert_eq!(c, MissCusum::default());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct MissCusum {
    high: f64,
    low: f64,
}

impl MissCusum {
    /// Add one normalised innovation `z` (σ) against the threshold `h`
    /// (σ, positive): whether the misses now persist (both sums then
    /// restart). A non-finite `z` is ignored.
    pub fn observe(&mut self, z: f64, threshold: f64) -> bool {
        if !z.is_finite() {
            return false;
        }
        let z = z.clamp(-MAX_SCORE, MAX_SCORE);
        self.high = (self.high + z - SLACK).max(0.0);
        self.low = (self.low - z - SLACK).max(0.0);
        let fired = self.high > threshold || self.low > threshold;
        if fired {
            *self = Self::default();
        }
        fired
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alternating_misses_never_fire_and_one_sided_ones_do() {
        let mut c = MissCusum::default();
        for i in 0..1000 {
            let z = if i % 2 == 0 { 3.0 } else { -3.0 };
            assert!(!c.observe(z, 4.0), "alternating ±3σ fired at {i}");
        }
        let mut c = MissCusum::default();
        let fired_at = (1..=10).find(|_| c.observe(-1.5, 4.0));
        // −1.5σ counts 1.0σ after the slack: the sum passes 4 on the fifth
        assert_eq!(fired_at, Some(5));
    }

    #[test]
    fn one_wild_value_is_clamped_and_does_not_fire_alone() {
        let mut c = MissCusum::default();
        assert!(!c.observe(1e9, 4.0));
        assert!(!c.observe(f64::NAN, 4.0));
        // the clamped 3σ (2.5 after the slack) plus one more 2σ miss fires
        assert!(c.observe(2.0, 3.9));
    }

    #[test]
    fn false_alarms_on_unit_noise_are_rare() {
        // Deterministic normal deviates (Box–Muller over a fixed LCG): the
        // textbook average run length of the two-sided CUSUM for k = 0.5,
        // h = 4 is ≈ 168, so 20,000 innovations fire about 120 times.
        let mut state: u64 = 0x2545_f491_4f6c_dd1d;
        let mut uniform = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut c = MissCusum::default();
        let mut fired = 0;
        for _ in 0..10_000 {
            let (u1, u2) = (uniform(), uniform());
            let r = (-2.0 * u1.ln()).sqrt();
            let angle = std::f64::consts::TAU * u2;
            for z in [r * angle.cos(), r * angle.sin()] {
                fired += usize::from(c.observe(z, 4.0));
            }
        }
        assert!((80..=180).contains(&fired), "{fired} alarms in 20,000");
    }
}
