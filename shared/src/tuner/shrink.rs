//! A step aimed at a reading shrunk toward its target
//! ([`super::array_run::ArrayRunSettings::shrink_residuals`]).
//!
//! A reading `y = x + e` (row scale, `e ~ N(0, σ²)`) of a parameter whose
//! true residual `x` the step takes out carries its noise `e` into the
//! parameter's next value: aimed at a noisy reading, a cell already at its
//! target moves off it by one σ each iteration, and an array of cells
//! reads all in band at once less often. The empirical-Bayes answer
//! (Wiener gain with the reading as its own signal estimate) is to aim at
//! `y · y²/(y² + s·σ²)`: almost the whole residual when it is many σ
//! (a cell far from its target moves as before), little of it when it is
//! within the noise.

/// Largest [`super::array_run::ArrayRunSettings::shrink_residuals`].
pub const MAX_SHRINK: f64 = 10.0;

/// The residual `y` (row scale) with variance `var_y` (row scale²) shrunk
/// by `y²/(y² + factor·var_y)`; unchanged for `factor ≤ 0`, a variance that
/// is not finite and positive, or `y = 0`.
///
/// ```
/// use spintune::tuner::shrink::shrunk_residual;
/// // one σ: half the residual; three σ: 90 % of it; off: all of it
/// assert!((shrunk_residual(0.05, 0.05 * 0.05, 1.0) - 0.025).abs() < 1e-12);
/// assert!((shrunk_residual(-0.15, 0.05 * 0.05, 1.0) + 0.135).abs() < 1e-12);
/// assert_eq!(shrunk_residual(0.05, 0.05 * 0.05, 0.0), 0.05);
/// ```
pub fn shrunk_residual(y: f64, var_y: f64, factor: f64) -> f64 {
    if !(factor > 0.0 && var_y.is_finite() && var_y > 0.0) || y == 0.0 {
        return y;
    }
    let y2 = y * y;
    y * y2 / (y2 + factor * var_y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gain_rises_with_the_readings_distance_in_sigma() {
        let var = 0.04_f64.powi(2);
        let mut last = 0.0;
        for k in 1..=20 {
            let y = 0.01 * k as f64;
            let g = shrunk_residual(y, var, 2.0) / y;
            assert!(g > last && g < 1.0, "gain {g} at {y}");
            last = g;
            // the same shrink on the other side
            assert_eq!(shrunk_residual(-y, var, 2.0), -shrunk_residual(y, var, 2.0));
        }
        // at 5σ with s = 2: 25/27
        assert!((last - 25.0 / 27.0).abs() < 1e-12, "{last}");
    }

    #[test]
    fn no_variance_no_shrink() {
        assert_eq!(shrunk_residual(0.1, f64::NAN, 1.0), 0.1);
        assert_eq!(shrunk_residual(0.1, 0.0, 1.0), 0.1);
        assert_eq!(shrunk_residual(0.0, 1.0, 1.0), 0.0);
    }
}
