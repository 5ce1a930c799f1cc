//! What a keep-mode run has done so far, from its records alone: the one
//! summary the CLI's progress line, Python and reports share.

use crate::protocol::{EventKind, IterationRecord, KeepPhase};

/// Running tally of a keep-mode run's records (fed in order).
///
/// "In band" here is what the run *measured*: the lab time since it first
/// settled, minus the stretches from a check that found a parameter out of
/// band (or about to leave) to back in band. The simulator's truth is only
/// known to the benchmark (`spintune bench-keep`).
///
/// ```
/// use spintune::driver::{SimulationConfig, SimulationRun};
/// use spintune::tuner::{KeepConfig, KeepTally};
/// let mut cfg = SimulationConfig::recommended();
/// cfg.tuner.keep = Some(KeepConfig { duration_s: Some(3.0 * 3600.0), ..KeepConfig::default() });
/// let mut run = SimulationRun::new(cfg).unwrap();
/// let mut tally = KeepTally::default();
/// while let Some(r) = run.next_iteration().unwrap() {
///     tally.add(&r);
/// }
/// // kept up to the last record (the last wait to the keep's end makes none)
/// let kept = tally.kept_lab_seconds();
/// assert!(kept > 2.0 * 3600.0 && kept <= 3.0 * 3600.0, "{kept}");
/// assert!(tally.checks > 0);
/// assert!(tally.measured_in_band_fraction().unwrap() > 0.5);
/// ```
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeepTally {
    /// Lab time the run first settled in band, s.
    pub keeping_since_s: Option<f64>,
    /// Lab time of the latest record, s.
    pub now_s: f64,
    /// Lab time out of band in finished re-tunes, s.
    pub out_of_band_s: f64,
    /// Lab time out of band in the present re-tune, s.
    pub open_out_of_band_s: f64,
    /// Checks so far.
    pub checks: u64,
    /// Re-tunes started so far.
    pub retunes: u64,
    /// `not_back_in_band` alerts so far.
    pub alerts: u64,
}

impl KeepTally {
    /// Take one record (records without a keep report are ignored).
    pub fn add(&mut self, r: &IterationRecord) {
        let Some(k) = &r.keep else { return };
        self.now_s = r.lab_seconds;
        if k.phase == KeepPhase::Check {
            self.checks += 1;
        }
        if self.keeping_since_s.is_none() && r.tuned && k.phase != KeepPhase::Check {
            self.keeping_since_s = Some(r.lab_seconds);
        }
        for e in &r.events {
            match e.kind {
                EventKind::RetuneStarted { .. } => self.retunes += 1,
                EventKind::BackInBand { after_lab_seconds } => {
                    self.out_of_band_s += after_lab_seconds.max(0.0)
                }
                EventKind::NotBackInBand { .. } => self.alerts += 1,
                _ => {}
            }
        }
        self.open_out_of_band_s = k.out_of_band_lab_seconds.max(0.0);
    }

    /// Lab time from the first settle to the latest record, s (0 before).
    pub fn kept_lab_seconds(&self) -> f64 {
        self.keeping_since_s
            .map_or(0.0, |t| (self.now_s - t).max(0.0))
    }

    /// Fraction of the kept lab time the run measured itself in band
    /// (`None` before it first settled).
    pub fn measured_in_band_fraction(&self) -> Option<f64> {
        let kept = self.kept_lab_seconds();
        (kept > 0.0).then(|| (1.0 - (self.out_of_band_s + self.open_out_of_band_s) / kept).max(0.0))
    }

    /// A progress fragment, e.g. `" | keeping: next check of t_sr in 12.3 lab min | in band 99.2 % of 3.2 lab h (measured) | 14 checks, 2 re-tunes"`.
    pub fn describe(&self, latest: &IterationRecord) -> String {
        let Some(k) = &latest.keep else {
            return String::new();
        };
        let mut s = match (k.phase, k.next_check_lab_seconds) {
            (_, Some(next)) => format!(
                " | keeping: next check of {} in {:.1} lab min",
                if k.next_check.is_empty() {
                    "—".to_string()
                } else {
                    k.next_check.join(", ")
                },
                ((next - latest.lab_seconds) / 60.0).max(0.0)
            ),
            (KeepPhase::Retune, None) => format!(
                " | re-tuning for {:.1} lab min",
                k.out_of_band_lab_seconds / 60.0
            ),
            (_, None) if self.keeping_since_s.is_some() => " | keeping".to_string(),
            (_, None) => " | tuning".to_string(),
        };
        if let Some(f) = self.measured_in_band_fraction() {
            s.push_str(&format!(
                " | in band {:.1} % of {:.2} lab h (measured) | {} checks, {} re-tunes",
                100.0 * f,
                self.kept_lab_seconds() / 3600.0,
                self.checks,
                self.retunes
            ));
        }
        if self.alerts > 0 {
            s.push_str(&format!(" | {} alert(s)", self.alerts));
        }
        s
    }
}
