//! Axis arithmetic shared by the charts and the iteration window: 1-2-5
//! steps and ranges widened to them.

/// `[lo, hi]` widened outward to multiples of a 1-2-5 step of about a fifth
/// of the span, so that small changes of the data do not change the axis
/// (and its frame). Degenerate or non-finite ranges are returned as they are.
pub fn nice_range(lo: f64, hi: f64) -> (f64, f64) {
    let span = hi - lo;
    if !(span.is_finite() && span > 0.0) {
        return (lo, hi);
    }
    let step = nice_step(span / 5.0);
    let (mut a, mut b) = ((lo / step).floor() * step, (hi / step).ceil() * step);
    // Rounding of the division must not cut the data.
    if a > lo {
        a -= step;
    }
    if b < hi {
        b += step;
    }
    if a.is_finite() && b.is_finite() && b > a {
        (a, b)
    } else {
        (lo, hi)
    }
}

/// The smallest of 1, 2, 5 × 10^k that is ≥ `x` (`x` > 0, finite).
pub fn nice_step(x: f64) -> f64 {
    let p = 10f64.powf(x.log10().floor());
    let m = x / p;
    let f = if m <= 1.0 {
        1.0
    } else if m <= 2.0 {
        2.0
    } else if m <= 5.0 {
        5.0
    } else {
        10.0
    };
    f * p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn nice_range_widens_to_steps_and_absorbs_small_changes() {
        assert_eq!(nice_step(0.3), 0.5);
        assert_eq!(nice_step(2.0), 2.0);
        assert_eq!(nice_step(7.0), 10.0);
        assert_eq!(nice_step(1200.0), 2000.0);
        assert_eq!(nice_range(3.2, 27.9), (0.0, 30.0));
        assert_eq!(nice_range(-1.3, 0.4), (-1.5, 0.5));
        // A slightly different data range keeps the axis.
        assert_eq!(nice_range(3.5, 28.7), nice_range(3.2, 27.9));
        // Contains the input.
        for (lo, hi) in [(0.001, 0.0013), (-5e-9, 7e-9), (99.0, 101.0), (1e6, 3e6)] {
            let (a, b) = nice_range(lo, hi);
            assert!(
                a <= lo && b >= hi && b - a <= 3.0 * (hi - lo),
                "{lo} {hi} -> {a} {b}"
            );
        }
        assert_eq!(nice_range(1.0, 1.0), (1.0, 1.0));
        assert!(nice_range(f64::NAN, 1.0).0.is_nan());
    }
}
