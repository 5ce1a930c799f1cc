//! The thermal floor of the inter-dot transition width `w`, and the scale
//! in which the joint array tuner can learn `w` ([`FloorLog`];
//! [`crate::tuner::array::JointConfig::thermal_floor`], off by default:
//! measured no better on random arrays, docs/array-history.md).
//!
//! The transition is broadened by the tunnel coupling `t_c` and by
//! temperature: as `t_c → 0`, `w` falls to the floor `f = 2kT/α` (electron
//! temperature over the lever arm), and for `t_c ≫ kT` it grows like `t_c`.
//! The gates act (nearly) linearly on `ln t_c`, but not on `ln w`: its
//! gradient is about `(w² − f²)/w²` times `ln t_c`'s, which doubles between
//! the paper's set points 180 and 270 µV at `f` = 144 µV, so a gradient
//! learned at one set point is wrong by 2× at the other. The excess over the
//! floor, `y = ½·ln(w² − f²)`, follows `ln t_c` within ±5 % from the floor
//! to 1.3 mV (test `the_excess_over_the_floor_follows_the_tunnel_coupling`,
//! on the simulator's lineshape).
//!
//! The floor is measured, not assumed: a lead transition is broadened by
//! temperature alone, so its fitted width is `2kT/α`
//! ([`crate::fit::lead_widths_mv`]); [`floor_from_lead_widths`] averages the
//! lead-transition scans a cell's initial measurement took. (In the
//! simulator, as in a device whose detuning axis is calibrated in the RF
//! gates' units, the two lever arms are the same.)

use serde::{Deserialize, Serialize};

/// The excess over the floor is taken as at least this fraction of the
/// value, `√max(p² − f², (r·p)²)`: a value at (or, by noise or a floor
/// measured high, below) the floor keeps a finite scale, and its slope
/// `dy/dln p` is at most `1/r² = 16`.
pub const MIN_EXCESS_FRACTION: f64 = 0.25;

/// Most lead widths kept per cell for its floor (invariant 8).
pub const MAX_LEAD_WIDTHS: usize = 32;

/// A parameter's learning scale: `y = ½·ln max(p² − f², (r·p)²)` with the
/// floor `f ≥ 0` in the parameter's unit and `r` =
/// [`MIN_EXCESS_FRACTION`]; `f = 0` is plain `y = ln p`, bit for bit.
///
/// ```
/// use spintune::tuner::thermal_floor::FloorLog;
/// let log = FloorLog::default();
/// assert_eq!(log.y(180.0), 180f64.ln());
/// // w = 180 µV over a floor of 144 µV: the excess is 108 µV
/// let s = FloorLog::new(144.0);
/// assert!((s.y(180.0) - 108f64.ln()).abs() < 1e-12);
/// assert!((s.value(s.y(180.0)) - 180.0).abs() < 1e-9);
/// // a relative change of w moves y by (180/108)² ≈ 2.8 times as much
/// assert!((s.log_gain(180.0) - (180.0f64 / 108.0).powi(2)).abs() < 1e-9);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct FloorLog {
    floor: f64,
}

impl FloorLog {
    /// The scale over `floor` (parameter unit); a floor that is not finite
    /// and positive gives plain `ln p`.
    pub fn new(floor: f64) -> Self {
        Self {
            floor: if floor.is_finite() && floor > 0.0 {
                floor
            } else {
                0.0
            },
        }
    }

    /// The floor, parameter unit (0: plain log).
    pub fn floor(&self) -> f64 {
        self.floor
    }

    /// `max(p² − f², (r·p)²)`, unit².
    fn excess_squared(&self, p: f64) -> f64 {
        (p * p - self.floor * self.floor).max((MIN_EXCESS_FRACTION * p).powi(2))
    }

    /// `y(p)` for `p > 0`.
    pub fn y(&self, p: f64) -> f64 {
        if self.floor == 0.0 {
            p.ln()
        } else {
            0.5 * self.excess_squared(p).ln()
        }
    }

    /// `dy/d(ln p)` at `p`: 1 for plain log, `p²/(p² − f²)` over a floor
    /// (at most `1/r²`). A log-space gradient times this is the gradient of
    /// `y`.
    pub fn log_gain(&self, p: f64) -> f64 {
        if self.floor == 0.0 {
            1.0
        } else {
            p * p / self.excess_squared(p)
        }
    }

    /// The variance of `y` from the value's variance `var` (unit²) at `p`
    /// (first order).
    pub fn variance(&self, p: f64, var: f64) -> f64 {
        if self.floor == 0.0 {
            return var / (p * p);
        }
        let g = self.log_gain(p) / p;
        var * g * g
    }

    /// The value whose `y` is `y` (unit): `√(e^{2y} + f²)`, the inverse
    /// above the clamp.
    pub fn value(&self, y: f64) -> f64 {
        if self.floor == 0.0 {
            y.exp()
        } else {
            ((2.0 * y).exp() + self.floor * self.floor).sqrt()
        }
    }

    /// The value and its standard deviation (unit) for `y` with variance
    /// `var_y`: `(value(y), √var_y · p / (dy/dln p))`, first order — the
    /// inverse of [`FloorLog::variance`].
    pub fn value_and_std(&self, y: f64, var_y: f64) -> (f64, f64) {
        let p = self.value(y);
        (p, var_y.sqrt() * p / self.log_gain(p))
    }

    /// `y(value) − y(target)`: a step's residual (`ln(value/target)` for
    /// plain log, computed as such).
    pub fn residual(&self, value: f64, target: f64) -> f64 {
        if self.floor == 0.0 {
            (value / target).ln()
        } else {
            self.y(value) - self.y(target)
        }
    }

    /// Whether `y ± margin` lies in the band `target/(1 + tol) ..=
    /// target·(1 + tol)` (for plain log: `|y − ln target| + margin ≤ ln(1 +
    /// tol)`).
    pub fn within_band(&self, y: f64, margin: f64, target: f64, relative_tolerance: f64) -> bool {
        if self.floor == 0.0 {
            return (y - target.ln()).abs() + margin <= (1.0 + relative_tolerance).ln();
        }
        let (lo, hi) = self.band(target, relative_tolerance);
        y - margin >= lo && y + margin <= hi
    }

    /// The band `target/(1 + tol) ..= target·(1 + tol)` in `y`: `(lo, hi)`.
    /// For plain log it is `ln target ∓ ln(1 + tol)`.
    pub fn band(&self, target: f64, relative_tolerance: f64) -> (f64, f64) {
        let k = 1.0 + relative_tolerance;
        if self.floor == 0.0 {
            let (t, r) = (target.ln(), k.ln());
            (t - r, t + r)
        } else {
            (self.y(target / k), self.y(target * k))
        }
    }
}

/// The thermal floor of `w` (µV) from lead-transition widths `(width,
/// standard error)` in mV ([`crate::fit::lead_widths_mv`]): their
/// inverse-variance weighted mean × 1000. `None` without a usable width.
///
/// ```
/// use spintune::tuner::thermal_floor::floor_from_lead_widths;
/// let f = floor_from_lead_widths(&[(0.14, 0.01), (0.15, 0.01)]).unwrap();
/// assert!((f - 145.0).abs() < 1e-9);
/// assert_eq!(floor_from_lead_widths(&[]), None);
/// ```
pub fn floor_from_lead_widths(widths_mv: &[(f64, f64)]) -> Option<f64> {
    let (mut sum, mut weight) = (0.0, 0.0);
    for &(w, s) in widths_mv {
        if w.is_finite() && w > 0.0 && s.is_finite() && s > 0.0 {
            sum += w / (s * s);
            weight += 1.0 / (s * s);
        }
    }
    (weight > 0.0).then(|| 1000.0 * sum / weight)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::model::{kt_uev, transition_width_uv};
    use crate::sim::DeviceConfig;

    /// The premise of the scale, on the simulator's lineshape: `½·ln(w² −
    /// f²)` with `f = 2kT/α` moves with `ln t_c` at a slope within 0.88–1.06
    /// from 1.1·f (above the clamp) to 1.3 mV, while `ln w`'s slope runs
    /// from 0.25 to 0.9 over the same range.
    #[test]
    fn the_excess_over_the_floor_follows_the_tunnel_coupling() {
        let c = DeviceConfig::default();
        let floor = 2.0 * kt_uev(&c) / c.lever_arm_uev_per_uv;
        let s = FloorLog::new(floor);
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        let (mut lo_ln, mut hi_ln) = (f64::INFINITY, 0.0f64);
        let mut prev: Option<(f64, f64)> = None;
        for i in 0..30 {
            let tc = 0.5 * 1.2f64.powi(i);
            let w = transition_width_uv(&c, tc);
            if let Some((ptc, pw)) = prev.filter(|&(_, pw)| pw >= 1.1 * floor) {
                let dl = tc.ln() - ptc.ln();
                let slope = (s.y(w) - s.y(pw)) / dl;
                lo = lo.min(slope);
                hi = hi.max(slope);
                let slope_ln = (w.ln() - pw.ln()) / dl;
                lo_ln = lo_ln.min(slope_ln);
                hi_ln = hi_ln.max(slope_ln);
            }
            prev = Some((tc, w));
        }
        assert!(lo > 0.88 && hi < 1.06, "slope of y: {lo}..{hi}");
        assert!(
            lo_ln < 0.3 && hi_ln > 0.85,
            "slope of ln w: {lo_ln}..{hi_ln}"
        );
    }

    #[test]
    fn plain_log_is_bit_for_bit_ln() {
        let s = FloorLog::new(0.0);
        for p in [0.3, 20.0, 270.0] {
            assert_eq!(s.y(p), p.ln());
            assert_eq!(s.value(p.ln()), p.ln().exp());
            assert_eq!(s.log_gain(p), 1.0);
            assert_eq!(s.variance(p, 4.0), 4.0 / (p * p));
            assert_eq!(s.residual(p, 180.0), (p / 180.0).ln());
        }
        assert_eq!(FloorLog::new(f64::NAN), FloorLog::default());
        assert_eq!(FloorLog::new(-1.0).floor(), 0.0);
    }

    #[test]
    fn at_and_below_the_floor_the_scale_stays_finite() {
        let s = FloorLog::new(144.0);
        // at the floor the excess is r·p, and the gain 1/r²
        let y = s.y(144.0);
        assert!((y - (MIN_EXCESS_FRACTION * 144.0).ln()).abs() < 1e-12);
        assert!((s.log_gain(100.0) - 16.0).abs() < 1e-12);
        assert!(s.y(100.0).is_finite() && s.variance(100.0, 1.0).is_finite());
        // the band around 180 µV: its bounds map back to 180/1.03 and 180·1.03
        let (lo, hi) = s.band(180.0, 0.03);
        assert!((s.value(lo) - 180.0 / 1.03).abs() < 1e-9);
        assert!((s.value(hi) - 180.0 * 1.03).abs() < 1e-9);
        assert!(s.within_band(s.y(180.0), 0.0, 180.0, 0.03));
        assert!(!s.within_band(s.y(180.0 * 1.04), 0.0, 180.0, 0.03));
        assert!(!s.within_band(s.y(180.0), hi - s.y(180.0) + 1e-9, 180.0, 0.03));
        assert!((s.residual(270.0, 180.0) - (s.y(270.0) - s.y(180.0))).abs() < 1e-15);
        // the value's std back from y's variance: the inverse of `variance`
        let (p, std) = s.value_and_std(s.y(200.0), s.variance(200.0, 4.0));
        assert!((p - 200.0).abs() < 1e-9 && (std - 2.0).abs() < 1e-9);
        // the variance by the chain rule: dy/dp = p/(p² − f²)
        let d = 180.0 / (180.0f64 * 180.0 - 144.0 * 144.0);
        assert!((s.variance(180.0, 9.0) - 9.0 * d * d).abs() < 1e-15);
    }

    #[test]
    fn the_floor_is_the_weighted_mean_of_usable_widths() {
        // weights 1/0.01² and 1/0.02² = 4:1
        let f = floor_from_lead_widths(&[(0.10, 0.01), (0.20, 0.02), (f64::NAN, 0.01), (0.3, 0.0)]);
        assert!((f.unwrap() - 1000.0 * (4.0 * 0.10 + 0.20) / 5.0).abs() < 1e-9);
    }
}
