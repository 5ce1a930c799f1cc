//! When a measured array cell counts in band: [`InBandRule`].
//!
//! The joint array loop stops on the first iteration that finds every cell
//! in band. A cell hovering just outside its band reads inside about as
//! often as its noise allows (a `w` scan's σ is about 5 %, half the default
//! band of ±10 %), so a rule that trusts one reading stops with cells truly
//! out. The filter's estimate ([`super::array::JointArrayTuner::estimate`]:
//! each measurement combined with the value its row predicted before it,
//! from the earlier measurements and the learned rows, trusted as far as
//! the row's predictions came true) weighs that reading against what the
//! lab already knew about the cell.
//!
//! A cell that has just entered its band near the edge is scanned once
//! more, where it is, before the run stops ([`to_confirm`]): two readings
//! in band are much less likely than one for a cell truly just outside.
//!
//! A changed cell's neighbours, pushed by its crosstalk, count in band
//! only a margin inside their edges ([`inside_margin`]), so that they stop
//! well inside rather than where they first read in again.

use serde::{Deserialize, Serialize};

use super::array::Measured;

/// When a measured cell counts in band
/// ([`super::array_run::ArrayRunSettings::in_band`]). A parameter is within
/// its band when `|x − target| ≤ relative_tolerance · target` (the band the
/// records report). A parameter without an estimate (no prediction yet: the
/// first measurement after the start) is judged on its measurement under
/// every rule; a parameter without a measurement (a failed fit, or an error
/// bar wider than the band) is never in band.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InBandRule {
    /// Every parameter measured within its band.
    #[default]
    Measured,
    /// Every parameter measured within its band, and its estimate within it
    /// too: stricter than [`InBandRule::Measured`].
    MeasuredAndEstimate,
    /// Every parameter's estimate within its band (a measurement just
    /// outside may pass when the earlier ones put it inside).
    Estimate,
}

/// Whether `value` lies within `relative_tolerance · target` of `target`
/// (edges included): the band a measured parameter is judged against.
///
/// ```
/// use spintune::tuner::in_band::within_band;
/// assert!(within_band(198.0, 180.0, 0.1) && !within_band(198.1, 180.0, 0.1));
/// ```
pub fn within_band(value: f64, target: f64, relative_tolerance: f64) -> bool {
    (value - target).abs() <= relative_tolerance * target
}

impl InBandRule {
    /// Whether a cell is in band: `values` its measurements (value, unit²
    /// variance; `None` not measured), `estimates` the filter's estimate of
    /// each (`None` without a prediction), `targets` (unit) and the band's
    /// `relative_tolerance`, per parameter.
    ///
    /// ```
    /// use spintune::tuner::in_band::InBandRule;
    /// // t_sr on target; w measured 8 % high but estimated 12 % high
    /// let values = [Some((20.0, 0.1)), Some((194.4, 81.0))];
    /// let estimates = [Some(20.0), Some(201.6)];
    /// let targets = [20.0, 180.0];
    /// assert!(InBandRule::Measured.in_band(&values, &estimates, &targets, 0.1));
    /// assert!(!InBandRule::MeasuredAndEstimate.in_band(&values, &estimates, &targets, 0.1));
    /// assert!(!InBandRule::Estimate.in_band(&values, &estimates, &targets, 0.1));
    /// ```
    pub fn in_band(
        self,
        values: &[Option<Measured>],
        estimates: &[Option<f64>],
        targets: &[f64],
        relative_tolerance: f64,
    ) -> bool {
        let near = |x: f64, t: f64| within_band(x, t, relative_tolerance);
        targets.iter().enumerate().all(|(p, &t)| {
            let Some(Some((x, _))) = values.get(p) else {
                return false;
            };
            let measured = near(*x, t);
            let estimated = estimates.get(p).copied().flatten().map(|e| near(e, t));
            match self {
                InBandRule::Measured => measured,
                InBandRule::MeasuredAndEstimate => measured && estimated != Some(false),
                InBandRule::Estimate => estimated.unwrap_or(measured),
            }
        })
    }
}

/// The in-band verdict's hysteresis
/// ([`super::array_run::ArrayRunSettings::stay_in_band_sigma`]): whether a
/// cell that counted in band at its previous measurement (`was_in_band`)
/// still counts on `values` (value, unit² variance per parameter) against
/// `targets`: every parameter measured, each within `sigma` of its
/// reported σ beyond its band's edge (`|x − target| ≤ relative_tolerance ·
/// target + sigma·σ`). Never for a cell that was out, or with `sigma = 0`.
///
/// ```
/// use spintune::tuner::in_band::stays_in_band;
/// let targets = [20.0, 270.0];
/// // w read 12 % high (302.4 µV, σ 20 µV): 5.4 µV (0.27σ) beyond the ±10 % band
/// let values = [Some((20.0, 0.25)), Some((302.4, 400.0))];
/// assert!(stays_in_band(&values, &targets, 0.1, true, 1.0));
/// // a cell that was out does not enter this way; 0 turns it off
/// assert!(!stays_in_band(&values, &targets, 0.1, false, 1.0));
/// assert!(!stays_in_band(&values, &targets, 0.1, true, 0.0));
/// // 25 % high is 40.5 µV (2.03σ) beyond the edge; a failed fit never stays
/// let values = [Some((20.0, 0.25)), Some((337.5, 400.0))];
/// assert!(!stays_in_band(&values, &targets, 0.1, true, 2.0));
/// assert!(!stays_in_band(&[Some((20.0, 0.25)), None], &targets, 0.1, true, 3.0));
/// ```
pub fn stays_in_band(
    values: &[Option<Measured>],
    targets: &[f64],
    relative_tolerance: f64,
    was_in_band: bool,
    sigma: f64,
) -> bool {
    was_in_band
        && sigma > 0.0
        && values.len() == targets.len()
        && values.iter().zip(targets).all(|(m, &t)| {
            m.is_some_and(|(x, var)| {
                (x - t).abs() <= relative_tolerance * t + sigma * var.max(0.0).sqrt()
            })
        })
}

/// The in-band verdict of a **disturbed bystander**
/// ([`super::array_run::ArrayRunSettings::disturbed_margin_sigma`]): whether
/// every parameter of `values` (value, unit² variance) reads at least
/// `sigma` of its reported σ inside its band's edge, the margin at most
/// half the band (`|x − target| ≤ relative_tolerance · target − min(sigma·σ,
/// relative_tolerance · target / 2)`). A cell whose reading sits just
/// inside its edge is truly outside about as often as its noise allows;
/// one read this far inside rarely is. `sigma = 0` is the plain band; a
/// parameter without a value never passes.
///
/// ```
/// use spintune::tuner::in_band::inside_margin;
/// let targets = [20.0, 270.0];
/// // w read 291.3 µV, σ 5.6 µV: 1.02σ inside the 297 µV edge
/// let values = [Some((20.0, 0.04)), Some((291.3, 5.6 * 5.6))];
/// assert!(inside_margin(&values, &targets, 0.1, 1.0));
/// assert!(!inside_margin(&values, &targets, 0.1, 2.0));
/// // σ 20 µV: 2σ would exceed half the band (13.5 µV), which caps it
/// let values = [Some((20.0, 0.04)), Some((283.0, 400.0))];
/// assert!(inside_margin(&values, &targets, 0.1, 2.0));
/// assert!(!inside_margin(&[Some((20.0, 0.04)), None], &targets, 0.1, 0.0));
/// ```
pub fn inside_margin(
    values: &[Option<Measured>],
    targets: &[f64],
    relative_tolerance: f64,
    sigma: f64,
) -> bool {
    values.len() == targets.len()
        && values.iter().zip(targets).all(|(m, &t)| {
            m.is_some_and(|(x, var)| {
                let half = relative_tolerance * t;
                let margin = (sigma * var.max(0.0).sqrt()).min(0.5 * half);
                (x - t).abs() <= half - margin
            })
        })
}

/// Two readings of one parameter at the same voltages (value, unit²
/// variance each) combined by their inverse variances: the pooled value and
/// its variance ([`super::array_run::ArrayRunSettings::pool_confirmations`]).
/// A reading without a positive finite variance weighs as the other.
///
/// ```
/// use spintune::tuner::in_band::pooled_reading;
/// // w read 300 µV then 280 µV, σ 20 µV each: 290 µV, σ 20/√2 µV
/// let (x, var) = pooled_reading((300.0, 400.0), (280.0, 400.0));
/// assert!((x - 290.0).abs() < 1e-12 && (var - 200.0).abs() < 1e-12);
/// // the surer reading weighs four times as much
/// let (x, _) = pooled_reading((300.0, 400.0), (250.0, 100.0));
/// assert!((x - 260.0).abs() < 1e-12);
/// ```
pub fn pooled_reading(a: Measured, b: Measured) -> Measured {
    let usable = |v: f64| v.is_finite() && v > 0.0;
    let (va, vb) = match (usable(a.1), usable(b.1)) {
        (true, true) => (a.1, b.1),
        (true, false) => (a.1, a.1),
        (false, true) => (b.1, b.1),
        (false, false) => (1.0, 1.0),
    };
    let (wa, wb) = (1.0 / va, 1.0 / vb);
    ((wa * a.0 + wb * b.0) / (wa + wb), 1.0 / (wa + wb))
}

/// The parameters (by index) measured outside their band: those a cell
/// counting in band only by [`stays_in_band`] confirms before the run
/// stops when [`super::array_run::ArrayRunSettings::pool_confirmations`]
/// is on. A parameter without a value is not listed.
///
/// ```
/// use spintune::tuner::in_band::beyond_band;
/// let targets = [20.0, 270.0];
/// assert_eq!(beyond_band(&[Some((20.5, 0.25)), Some((302.4, 400.0))], &targets, 0.1), [1]);
/// assert!(beyond_band(&[Some((20.5, 0.25)), None], &targets, 0.1).is_empty());
/// ```
pub fn beyond_band(
    values: &[Option<Measured>],
    targets: &[f64],
    relative_tolerance: f64,
) -> Vec<usize> {
    values
        .iter()
        .zip(targets)
        .enumerate()
        .filter(|(_, (m, &t))| m.is_some_and(|(x, _)| !within_band(x, t, relative_tolerance)))
        .map(|(p, _)| p)
        .collect()
}

/// The parameters of a cell measured in band that are scanned once more
/// before the run stops ([`super::array_run::ArrayRunSettings::confirm_entry_sigma`]):
/// none when its previous measurement was in band (`was_in_band`; not so
/// when it was out, never measured, or against other targets) or when
/// `sigma = 0`; else those (by index) within `sigma` of their reported
/// error bars of the band's edge (`|x − target| + sigma·σ > relative_tolerance
/// · target`, `σ` the square root of the measured variance).
///
/// ```
/// use spintune::tuner::in_band::to_confirm;
/// // w read 6 % high with σ = 5 % (9 µV): 1σ from the edge of a ±10 % band
/// let values = [Some((20.0, 0.01)), Some((190.8, 81.0))];
/// let targets = [20.0, 180.0];
/// assert_eq!(to_confirm(&values, &targets, 0.1, false, 1.0), [1]);
/// // in band at the previous measurement, or not asked for: nothing
/// assert!(to_confirm(&values, &targets, 0.1, true, 1.0).is_empty());
/// assert!(to_confirm(&values, &targets, 0.1, false, 0.0).is_empty());
/// // read 2 % high: more than 1σ inside
/// let values = [Some((20.0, 0.01)), Some((183.6, 81.0))];
/// assert!(to_confirm(&values, &targets, 0.1, false, 1.0).is_empty());
/// ```
pub fn to_confirm(
    values: &[Option<Measured>],
    targets: &[f64],
    relative_tolerance: f64,
    was_in_band: bool,
    sigma: f64,
) -> Vec<usize> {
    if was_in_band || sigma <= 0.0 {
        return Vec::new();
    }
    values
        .iter()
        .zip(targets)
        .enumerate()
        .filter(|(_, (m, &t))| {
            m.is_some_and(|(x, var)| {
                (x - t).abs() + sigma * var.max(0.0).sqrt() > relative_tolerance * t
            })
        })
        .map(|(p, _)| p)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::to_confirm;
    use super::InBandRule::{self, *};

    const T: [f64; 2] = [20.0, 180.0];

    fn judge(rule: InBandRule, w: Option<f64>, w_estimate: Option<f64>) -> bool {
        rule.in_band(
            &[Some((20.0, 0.1)), w.map(|w| (w, 81.0))],
            &[Some(20.0), w_estimate],
            &T,
            0.1,
        )
    }

    /// The band's edges: 162 and 198 µV around 180 µV are inside, a hair
    /// beyond is out, under every rule alike when measurement and estimate
    /// agree.
    #[test]
    fn the_band_is_relative_to_the_target_edges_included() {
        for rule in [Measured, MeasuredAndEstimate, Estimate] {
            for (w, inside) in [(162.0, true), (198.0, true), (161.9, false), (198.1, false)] {
                assert_eq!(judge(rule, Some(w), Some(w)), inside, "{rule:?} at {w}");
            }
        }
    }

    /// Measurement and estimate on either side of the edge: only the rule
    /// decides.
    #[test]
    fn each_rule_weighs_measurement_and_estimate_as_documented() {
        // measured in, estimated out
        assert!(judge(Measured, Some(190.0), Some(200.0)));
        assert!(!judge(MeasuredAndEstimate, Some(190.0), Some(200.0)));
        assert!(!judge(Estimate, Some(190.0), Some(200.0)));
        // measured out, estimated in
        assert!(!judge(Measured, Some(200.0), Some(190.0)));
        assert!(!judge(MeasuredAndEstimate, Some(200.0), Some(190.0)));
        assert!(judge(Estimate, Some(200.0), Some(190.0)));
    }

    /// Without an estimate the measurement decides; without a measurement
    /// nothing is in band, whatever the estimate says.
    #[test]
    fn a_missing_estimate_defers_to_the_measurement_and_a_missing_value_is_out() {
        for rule in [Measured, MeasuredAndEstimate, Estimate] {
            assert!(judge(rule, Some(190.0), None), "{rule:?}");
            assert!(!judge(rule, Some(200.0), None), "{rule:?}");
            assert!(!judge(rule, None, Some(180.0)), "{rule:?}");
        }
        // every target needs its value
        assert!(!Measured.in_band(&[Some((20.0, 0.1))], &[], &T, 0.1));
    }

    /// A cell entering near either edge of either parameter has that
    /// parameter confirmed; deep inside, or in band before, nothing is. A
    /// parameter without a value has nothing to confirm.
    #[test]
    fn entry_near_an_edge_is_confirmed_parameter_by_parameter() {
        let w = |x: f64| [Some((20.0, 0.01)), Some((x, 81.0))];
        // σ = 9 µV; the band's edges at 162 and 198 µV
        for (x, confirm) in [(188.0, false), (190.0, true), (170.0, true), (172.0, false)] {
            let expected: &[usize] = if confirm { &[1] } else { &[] };
            assert_eq!(to_confirm(&w(x), &T, 0.1, false, 1.0), expected, "w {x}");
            assert!(
                to_confirm(&w(x), &T, 0.1, true, 1.0).is_empty(),
                "w {x}, in before"
            );
        }
        // two σ: 3 µV off is within 18 µV of the edge
        assert_eq!(to_confirm(&w(183.0), &T, 0.1, false, 2.0), [1]);
        // t_sr near its edge (σ 0.3 ns; 1.8 + 0.3 > 2), alone or with w
        let t = |w: f64| [Some((21.8, 0.09)), Some((w, 81.0))];
        assert_eq!(to_confirm(&t(180.0), &T, 0.1, false, 1.0), [0]);
        assert_eq!(to_confirm(&t(191.0), &T, 0.1, false, 1.0), [0, 1]);
        assert!(to_confirm(&[None, Some((180.0, 81.0))], &T, 0.1, false, 1.0).is_empty());
    }
}
