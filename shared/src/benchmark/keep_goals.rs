//! Issue 23's goals for a keep benchmark, judged from its summaries (one
//! rule, used by `spintune bench-keep`'s report and its JSON).
//!
//! The goals (24 lab hours):
//! * `never` is truly in band at most [`NEVER_MAX_IN_BAND`] of the time
//!   (the drift is real);
//! * `predictive` is in band at least [`IN_BAND_GOAL`] of the time;
//! * its measurement time is at most [`MAX_TIME_RATIO`] of the cheapest
//!   fixed-interval strategy that also reaches [`IN_BAND_GOAL`]; if no
//!   fixed interval measured does, `predictive` must beat every fixed
//!   interval on time in band at no more measurement time;
//! * no strategy violates a limit, none but the oracle queries the truth.
//!
//! Which fixed intervals exist is the caller's choice (`fixed-Nmin`,
//! `fixed-Ns`): the verdict names the cheapest one that reached the goal,
//! so it is only as good as the intervals that were run.

use serde::{Deserialize, Serialize};

use super::keep::KeepSummary;

/// Highest mean time in band of `never` (the drift must be real).
pub const NEVER_MAX_IN_BAND: f64 = 0.7;
/// Mean time in band `predictive` must reach.
pub const IN_BAND_GOAL: f64 = 0.99;
/// Highest ratio of `predictive`'s measurement time to that of the
/// cheapest fixed interval reaching [`IN_BAND_GOAL`].
pub const MAX_TIME_RATIO: f64 = 1.0 / 3.0;

/// The fixed interval the measurement-time goal compares against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FixedReference {
    /// Strategy name (`fixed-1min`, …).
    pub name: String,
    /// Its mean time in band.
    pub fraction_in_band: f64,
    /// Its measurement minutes per lab hour.
    pub measurement_minutes_per_hour: f64,
}

/// The verdict on each goal (`None`: the strategies it needs were not run).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeepGoals {
    /// `never`'s time in band ≤ [`NEVER_MAX_IN_BAND`].
    pub drift_is_real: Option<bool>,
    /// `predictive`'s time in band ≥ [`IN_BAND_GOAL`].
    pub predictive_in_band: Option<bool>,
    /// The cheapest fixed interval with time in band ≥ [`IN_BAND_GOAL`].
    pub cheapest_fixed_in_band: Option<FixedReference>,
    /// `predictive`'s measurement time over that fixed interval's.
    pub time_ratio: Option<f64>,
    /// The measurement-time goal: `time_ratio` ≤ [`MAX_TIME_RATIO`], or,
    /// with no fixed interval in band, `predictive` ahead of every fixed
    /// interval on time in band at no more measurement time.
    pub measurement_time: Option<bool>,
    /// No limit violation and no truth query in any strategy.
    pub safe: bool,
}

impl KeepGoals {
    /// Judge `summary` (the strategies of one benchmark run).
    ///
    /// ```
    /// use spintune::benchmark::keep::KeepSummary;
    /// use spintune::benchmark::keep_goals::KeepGoals;
    /// use spintune::benchmark::Quantiles;
    /// let s = |name: &str, in_band: f64, minutes: f64| KeepSummary {
    ///     name: name.into(), runs: 1, not_tuned: 0, fraction_in_band: in_band,
    ///     fraction_in_band_low: Quantiles::nan(), measurement_minutes_per_hour: minutes,
    ///     retunes_per_day: 0.0, checks_per_day: 0.0,
    ///     longest_out_of_band_minutes: Quantiles::nan(), alerts: 0,
    ///     limit_violations: 0, truth_queries: 0, minutes_per_hour_by_kind: Default::default(),
    /// };
    /// let goals = KeepGoals::judge(&[
    ///     s("predictive", 0.995, 5.0),
    ///     s("fixed-1min", 0.991, 22.0),
    ///     s("fixed-2min", 0.992, 14.0), // in band and cheaper: the reference
    ///     s("fixed-10min", 0.96, 4.0),  // cheaper, but not in band
    ///     s("never", 0.3, 0.0),
    /// ]);
    /// assert_eq!(goals.cheapest_fixed_in_band.unwrap().name, "fixed-2min");
    /// assert!((goals.time_ratio.unwrap() - 5.0 / 14.0).abs() < 1e-12);
    /// assert_eq!(goals.measurement_time, Some(false)); // 0.36 > 1/3
    /// assert_eq!(goals.drift_is_real, Some(true));
    /// assert!(goals.safe);
    /// ```
    pub fn judge(summary: &[KeepSummary]) -> Self {
        let find = |name: &str| summary.iter().find(|s| s.name == name);
        let fixed: Vec<&KeepSummary> = summary
            .iter()
            .filter(|s| s.name.starts_with("fixed-"))
            .collect();
        let predictive = find("predictive");
        let cheapest = fixed
            .iter()
            .filter(|s| s.fraction_in_band >= IN_BAND_GOAL)
            .min_by(|a, b| {
                a.measurement_minutes_per_hour
                    .total_cmp(&b.measurement_minutes_per_hour)
            })
            .map(|s| FixedReference {
                name: s.name.clone(),
                fraction_in_band: s.fraction_in_band,
                measurement_minutes_per_hour: s.measurement_minutes_per_hour,
            });
        let time_ratio = match (predictive, &cheapest) {
            (Some(p), Some(f)) if f.measurement_minutes_per_hour > 0.0 => {
                Some(p.measurement_minutes_per_hour / f.measurement_minutes_per_hour)
            }
            _ => None,
        };
        let measurement_time = match (predictive, &cheapest) {
            (None, _) => None,
            (Some(_), Some(_)) => time_ratio.map(|r| r <= MAX_TIME_RATIO),
            (Some(_), None) if fixed.is_empty() => None,
            (Some(p), None) => Some(fixed.iter().all(|f| {
                p.fraction_in_band > f.fraction_in_band
                    && p.measurement_minutes_per_hour <= f.measurement_minutes_per_hour
            })),
        };
        KeepGoals {
            drift_is_real: find("never").map(|n| n.fraction_in_band <= NEVER_MAX_IN_BAND),
            predictive_in_band: predictive.map(|p| p.fraction_in_band >= IN_BAND_GOAL),
            cheapest_fixed_in_band: cheapest,
            time_ratio,
            measurement_time,
            safe: summary
                .iter()
                .all(|s| s.limit_violations == 0 && s.truth_queries == 0),
        }
    }

    /// One line per goal, for a report (markdown list).
    pub fn lines(&self) -> Vec<String> {
        let mark = |v: Option<bool>| match v {
            Some(true) => "✔",
            Some(false) => "✘",
            None => "– (not run)",
        };
        let mut out = vec![
            format!(
                "`never` in band ≤ {NEVER_MAX_IN_BAND}: {}",
                mark(self.drift_is_real)
            ),
            format!(
                "`predictive` in band ≥ {IN_BAND_GOAL}: {}",
                mark(self.predictive_in_band)
            ),
        ];
        out.push(match (&self.cheapest_fixed_in_band, self.time_ratio) {
            (Some(f), Some(r)) => format!(
                "cheapest fixed interval in band ≥ {IN_BAND_GOAL}: {} ({:.4} at {:.2} min/h); \
                 `predictive` spends {r:.2}× its measurement time (goal ≤ 1/3): {}",
                f.name,
                f.fraction_in_band,
                f.measurement_minutes_per_hour,
                mark(self.measurement_time)
            ),
            _ => format!(
                "no fixed interval run reached {IN_BAND_GOAL} in band; `predictive` ahead of \
                 every one at no more measurement time: {}",
                mark(self.measurement_time)
            ),
        });
        out.push(format!(
            "0 limit violations, 0 truth queries: {}",
            mark(Some(self.safe))
        ));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::benchmark::Quantiles;

    fn summary(name: &str, in_band: f64, minutes: f64) -> KeepSummary {
        KeepSummary {
            name: name.into(),
            runs: 4,
            not_tuned: 0,
            fraction_in_band: in_band,
            fraction_in_band_low: Quantiles::nan(),
            measurement_minutes_per_hour: minutes,
            retunes_per_day: 0.0,
            checks_per_day: 0.0,
            longest_out_of_band_minutes: Quantiles::nan(),
            alerts: 0,
            limit_violations: 0,
            truth_queries: 0,
            minutes_per_hour_by_kind: Default::default(),
        }
    }

    #[test]
    fn the_ratio_is_against_the_cheapest_fixed_interval_in_band() {
        let g = KeepGoals::judge(&[
            summary("predictive", 0.995, 6.0),
            summary("fixed-20s", 0.993, 38.0),
            summary("fixed-1min", 0.991, 24.0),
            summary("fixed-10min", 0.95, 4.0),
        ]);
        assert_eq!(
            g.cheapest_fixed_in_band.as_ref().unwrap().name,
            "fixed-1min"
        );
        assert_eq!(g.time_ratio, Some(0.25));
        assert_eq!(g.measurement_time, Some(true));
        assert_eq!(g.predictive_in_band, Some(true));
        assert_eq!(g.drift_is_real, None);
    }

    #[test]
    fn with_no_fixed_interval_in_band_predictive_must_win_at_no_more_time() {
        let fixed = [
            summary("fixed-10min", 0.96, 4.2),
            summary("fixed-60min", 0.86, 1.1),
        ];
        let ahead = summary("predictive", 0.996, 1.0);
        let costly = summary("predictive", 0.996, 4.6);
        let g = KeepGoals::judge(&[ahead, fixed[0].clone(), fixed[1].clone()]);
        assert_eq!(g.cheapest_fixed_in_band, None);
        assert_eq!(g.measurement_time, Some(true));
        let g = KeepGoals::judge(&[costly, fixed[0].clone(), fixed[1].clone()]);
        assert_eq!(g.measurement_time, Some(false));
    }

    #[test]
    fn a_violation_or_truth_query_anywhere_fails_safety() {
        let mut bad = summary("fixed-30min", 0.9, 2.0);
        bad.limit_violations = 1;
        assert!(!KeepGoals::judge(&[summary("predictive", 0.99, 3.0), bad.clone()]).safe);
        bad.limit_violations = 0;
        bad.truth_queries = 2;
        assert!(!KeepGoals::judge(&[bad]).safe);
        assert!(KeepGoals::judge(&[summary("never", 0.8, 0.0)]).safe);
        assert_eq!(
            KeepGoals::judge(&[summary("never", 0.8, 0.0)]).drift_is_real,
            Some(false)
        );
    }
}
