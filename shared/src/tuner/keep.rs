//! Keep mode (issue 23): once the top level is tuned, keep it in tune while
//! the device drifts, with as little lab time as possible.
//!
//! The run's phases ([`KeepPhase`]): **tuning** (the normal Newton rounds
//! until every targeted parameter is inside the *settle band*,
//! [`KeepConfig::settle_band_fraction`] of its tolerance), then
//! **keeping**: lab time passes ([`Request::Wait`]) until a parameter's
//! next check is due, a **check** measures just the parameters due (the
//! scans that give them, no move), and a check that finds a parameter out
//! of its band — or, for the predictive schedule, predicts it leaves the
//! band before the next check could see it — starts a **retune**: the
//! normal rounds with the learned Jacobian until back inside the settle
//! band. Every check and retune round is an iteration record with a
//! [`KeepReport`].
//!
//! # The drift model (predictive schedule)
//! Each top-level parameter `x` (estimator space: `ln` for log-space
//! parameters) is modelled as a random walk between checks: after a check
//! at `t₀` with posterior `x̂ ± √P`, at time `t` the value is `N(x̂, P +
//! q·(t − t₀))`. The diffusion `q` (estimator unit² / s) is learned online
//! from the checks' innovations `ν = y − x̂` (expected `ν² = P + q·Δt + R`):
//! `q = (q₀·T₀ + Σ (ν² − P − R)) / (T₀ + Σ Δt)`, with a prior `q₀` of
//! [`KeepConfig::prior_drift_band_per_sqrt_hour`] band half-widths per
//! √hour and a prior weight `T₀` of [`PRIOR_WEIGHT_S`]. A parameter's next
//! check is when its probability of being outside the band reaches
//! [`KeepSchedule::Predictive`]'s `out_of_band_probability`, within
//! `[min_check_interval_s, max_check_interval_s]`; a cheap parameter
//! (t_sr, 5 s) is thus checked on its own schedule, not with the expensive
//! one (w, 28 s).
//!
//! # Bounds
//! Records of a long keep: at most one check record per
//! `min_check_interval_s` (≥ [`MIN_CHECK_INTERVAL_S`], so ≤ 360 per lab
//! hour) plus the rounds of re-tunes; waits are cut into pieces of at most
//! [`crate::protocol::MAX_WAIT_SECONDS`].

use serde::{Deserialize, Serialize};

use super::finite_difference::Sample;
use super::{Decision, Op, Tuner};
use crate::config_error::ConfigError;
use crate::parameter::ParameterSpec;
use crate::protocol::{
    EventKind, KeepPhase, KeepReport, ParameterValue, Request, TunerEvent, MAX_WAIT_SECONDS,
};

/// Shortest allowed [`KeepConfig::min_check_interval_s`], s.
pub const MIN_CHECK_INTERVAL_S: f64 = 10.0;
/// Longest allowed check interval (and [`KeepConfig::duration_s`]), s: 30 days.
pub const MAX_KEEP_SECONDS: f64 = 30.0 * 86_400.0;
/// Weight of the drift prior, s of observed drift it counts as (2 h).
pub const PRIOR_WEIGHT_S: f64 = 7_200.0;
/// The learned diffusion never falls below this fraction of the prior's.
pub const DIFFUSION_FLOOR: f64 = 0.25;

/// When keep mode checks (the strategies of `spintune bench-keep`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum KeepSchedule {
    /// Check a parameter when the drift model's probability of it being out
    /// of band reaches `out_of_band_probability`; re-tune when a check finds
    /// it out of band or predicts it out of band by the earliest next check.
    Predictive {
        /// Threshold probability, in (0, 0.5).
        #[serde(default = "default_out_of_band_probability")]
        out_of_band_probability: f64,
    },
    /// Check every parameter every `interval_s`; re-tune when one is out of band.
    Fixed {
        /// Interval, s.
        interval_s: f64,
    },
    /// Tune once, then leave it.
    Never,
}

impl Default for KeepSchedule {
    fn default() -> Self {
        KeepSchedule::Predictive {
            out_of_band_probability: default_out_of_band_probability(),
        }
    }
}

fn default_out_of_band_probability() -> f64 {
    // chosen on random devices (`bench-keep --random-devices 5 --device-seed
    // 500 --seeds 4`): 0.003 / 0.005 / 0.01 kept 0.990 / 0.989 / 0.985 in
    // band at 7.1 / 5.7 / 5.2 measurement min per hour
    0.005
}
fn default_settle_band_fraction() -> f64 {
    0.5
}
fn default_min_check_interval_s() -> f64 {
    120.0
}
fn default_max_check_interval_s() -> f64 {
    3600.0
}
fn default_alert_after_s() -> f64 {
    1800.0
}
fn default_prior_drift() -> f64 {
    0.75
}
fn default_batch_window_s() -> f64 {
    300.0
}
fn default_skip_confirmation_sigma() -> Option<f64> {
    Some(2.0)
}

/// Keep-mode settings (`tuner.keep` in a run config). Every field has a default.
///
/// ```
/// use spintune::tuner::{KeepConfig, KeepSchedule};
/// let k: KeepConfig = serde_json::from_str(r#"{"duration_s": 86400}"#).unwrap();
/// assert!(matches!(k.schedule, KeepSchedule::Predictive { .. }));
/// assert_eq!(k.settle_band_fraction, 0.5);
/// k.validate().unwrap();
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeepConfig {
    /// When to check (default: predictive, 0.5 %).
    #[serde(default)]
    pub schedule: KeepSchedule,
    /// Tuning and re-tuning end when every targeted parameter is within this
    /// fraction of its tolerance band (in (0, 1]; default 0.5): the tuner
    /// settles near the target so drift takes longer to reach the edge.
    #[serde(default = "default_settle_band_fraction")]
    pub settle_band_fraction: f64,
    /// Shortest time between two checks of a parameter, s (≥ 10, default 120).
    #[serde(default = "default_min_check_interval_s")]
    pub min_check_interval_s: f64,
    /// Longest time between two checks of a parameter, s (default 1 h, at most 30 days).
    #[serde(default = "default_max_check_interval_s")]
    pub max_check_interval_s: f64,
    /// Lab time out of band (from the check that found it) after which a
    /// re-tune raises [`EventKind::NotBackInBand`], s (default 30 min).
    #[serde(default = "default_alert_after_s")]
    pub alert_after_s: f64,
    /// Keep for this much lab time after first tuned, then finish, s
    /// (`None`: until stopped; at most 30 days).
    #[serde(default)]
    pub duration_s: Option<f64>,
    /// Prior drift of every parameter, in band half-widths per √hour
    /// (default 0.75): the first checks' schedule before any drift is seen.
    #[serde(default = "default_prior_drift")]
    pub prior_drift_band_per_sqrt_hour: f64,
    /// A check also measures every parameter due within this much lab time, s (default 300).
    #[serde(default = "default_batch_window_s")]
    pub batch_window_s: f64,
    /// A re-tune round whose step the filter predicts lands every targeted
    /// parameter inside the settle band, this many predicted standard
    /// deviations inside the tolerance band, ends the re-tune without a
    /// confirming measurement (the drift models start from the prediction
    /// and its variance, so the next check comes early); `None`: always
    /// confirm (default 2).
    #[serde(default = "default_skip_confirmation_sigma")]
    pub skip_confirmation_sigma: Option<f64>,
}

impl Default for KeepConfig {
    fn default() -> Self {
        Self {
            schedule: KeepSchedule::default(),
            settle_band_fraction: default_settle_band_fraction(),
            min_check_interval_s: default_min_check_interval_s(),
            max_check_interval_s: default_max_check_interval_s(),
            alert_after_s: default_alert_after_s(),
            duration_s: None,
            prior_drift_band_per_sqrt_hour: default_prior_drift(),
            batch_window_s: default_batch_window_s(),
            skip_confirmation_sigma: default_skip_confirmation_sigma(),
        }
    }
}

impl KeepConfig {
    /// Check every field's range; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let range = |field: &str, v: f64, lo: f64, hi: f64, closed_lo: bool| {
            let ok = v.is_finite() && (if closed_lo { v >= lo } else { v > lo }) && v <= hi;
            if ok {
                Ok(())
            } else {
                let open = if closed_lo { "[" } else { "(" };
                Err(ConfigError::new(
                    field,
                    format!("must be a number in {open}{lo}, {hi}], got {v}"),
                ))
            }
        };
        match self.schedule {
            KeepSchedule::Predictive {
                out_of_band_probability,
            } => range(
                "schedule.out_of_band_probability",
                out_of_band_probability,
                0.0,
                0.5,
                false,
            )?,
            KeepSchedule::Fixed { interval_s } => range(
                "schedule.interval_s",
                interval_s,
                MIN_CHECK_INTERVAL_S,
                MAX_KEEP_SECONDS,
                true,
            )?,
            KeepSchedule::Never => {}
        }
        range(
            "settle_band_fraction",
            self.settle_band_fraction,
            0.0,
            1.0,
            false,
        )?;
        range(
            "min_check_interval_s",
            self.min_check_interval_s,
            MIN_CHECK_INTERVAL_S,
            MAX_KEEP_SECONDS,
            true,
        )?;
        range(
            "max_check_interval_s",
            self.max_check_interval_s,
            self.min_check_interval_s,
            MAX_KEEP_SECONDS,
            true,
        )?;
        range(
            "alert_after_s",
            self.alert_after_s,
            0.0,
            MAX_KEEP_SECONDS,
            false,
        )?;
        if let Some(d) = self.duration_s {
            range("duration_s", d, 0.0, MAX_KEEP_SECONDS, false)?;
        }
        range(
            "prior_drift_band_per_sqrt_hour",
            self.prior_drift_band_per_sqrt_hour,
            0.0,
            100.0,
            false,
        )?;
        range(
            "batch_window_s",
            self.batch_window_s,
            0.0,
            MAX_KEEP_SECONDS,
            true,
        )?;
        if let Some(k) = self.skip_confirmation_sigma {
            range("skip_confirmation_sigma", k, 0.0, 10.0, true)?;
        }
        Ok(())
    }
}

/// One parameter's random-walk drift model (estimator space).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DriftModel {
    /// Posterior mean after the last check (estimator units).
    pub mean: f64,
    /// Its variance (estimator units²).
    pub variance: f64,
    /// Lab time of the last check, s.
    pub at_s: f64,
    /// Prior diffusion, estimator units² per s.
    pub prior_diffusion: f64,
    /// Σ (ν² − P − R) over the checks so far (estimator units²).
    pub excess_sum: f64,
    /// Σ Δt between checks so far, s.
    pub dt_sum: f64,
}

impl DriftModel {
    /// A model that starts at `value ± √variance` at `at_s`, with prior
    /// diffusion `prior_diffusion` (estimator units²/s).
    pub fn new(value: f64, variance: f64, at_s: f64, prior_diffusion: f64) -> Self {
        Self {
            mean: value,
            variance: variance.max(0.0),
            at_s,
            prior_diffusion,
            excess_sum: 0.0,
            dt_sum: 0.0,
        }
    }

    /// The learned diffusion, estimator units² per s (never below
    /// `DIFFUSION_FLOOR` of the prior: a quiet stretch does not make the
    /// model blind to the next jump).
    pub fn diffusion(&self) -> f64 {
        let q = (self.prior_diffusion * PRIOR_WEIGHT_S + self.excess_sum)
            / (PRIOR_WEIGHT_S + self.dt_sum);
        q.max(DIFFUSION_FLOOR * self.prior_diffusion)
    }

    /// Predicted mean and variance at lab time `t_s`.
    pub fn predict(&self, t_s: f64) -> (f64, f64) {
        let dt = (t_s - self.at_s).max(0.0);
        (self.mean, self.variance + self.diffusion() * dt)
    }

    /// Probability of lying outside `[lo, hi]` at lab time `t_s`.
    pub fn out_of_band_probability(&self, t_s: f64, lo: f64, hi: f64) -> f64 {
        let (m, v) = self.predict(t_s);
        let s = v.sqrt();
        if s.is_nan() || s <= 0.0 {
            return if (lo..=hi).contains(&m) { 0.0 } else { 1.0 };
        }
        normal_cdf((lo - m) / s) + normal_cdf((m - hi) / s)
    }

    /// Earliest lab time in `[at_s + min_s, at_s + max_s]` at which the
    /// out-of-band probability reaches `threshold` (bisection; the
    /// probability grows with time while the mean is inside the band).
    pub fn due(&self, lo: f64, hi: f64, threshold: f64, min_s: f64, max_s: f64) -> f64 {
        let (a, b) = (self.at_s + min_s, self.at_s + max_s);
        if self.out_of_band_probability(a, lo, hi) >= threshold {
            return a;
        }
        if self.out_of_band_probability(b, lo, hi) < threshold {
            return b;
        }
        let (mut lo_t, mut hi_t) = (a, b);
        for _ in 0..40 {
            let mid = 0.5 * (lo_t + hi_t);
            if self.out_of_band_probability(mid, lo, hi) >= threshold {
                hi_t = mid;
            } else {
                lo_t = mid;
            }
        }
        hi_t
    }

    /// A check measured `y ± √r` at lab time `t_s`: learn the diffusion
    /// from the innovation, then the Kalman update of the level.
    pub fn update(&mut self, y: f64, r: f64, t_s: f64) {
        if !(y.is_finite() && r.is_finite() && r >= 0.0) {
            return;
        }
        let dt = (t_s - self.at_s).max(0.0);
        let nu = y - self.mean;
        // Winsorised at 3σ of the prediction: a jump raises the diffusion,
        // but one wild value cannot make the model expect wild drift for hours.
        let s_pred = self.variance + self.diffusion() * dt + r;
        let nu2 = (nu * nu).min(9.0 * s_pred);
        self.excess_sum += nu2 - self.variance - r;
        self.dt_sum += dt;
        let (m, p) = self.predict(t_s);
        let s = p + r;
        let k = if s > 0.0 { p / s } else { 0.0 };
        self.mean = m + k * (y - m);
        self.variance = (1.0 - k) * p;
        self.at_s = t_s;
    }

    /// The parameter was re-tuned: it is now at `y ± √r` (the learned
    /// diffusion stays).
    pub fn restart(&mut self, y: f64, r: f64, t_s: f64) {
        self.mean = y;
        self.variance = r.max(0.0);
        self.at_s = t_s;
    }
}

/// Standard normal CDF Φ(x).
fn normal_cdf(x: f64) -> f64 {
    0.5 * libm::erfc(-x / std::f64::consts::SQRT_2)
}

/// The band `[lo, hi]` of a targeted parameter in estimator space and its
/// half-width there (band units for the drift prior).
fn estimator_band(p: &ParameterSpec) -> Option<(f64, f64)> {
    let t = p.target?;
    let h = p.tolerance.half_width(t);
    let lo = p.transform.forward_value(t - h)?;
    let hi = p.transform.forward_value(t + h)?;
    (lo.is_finite() && hi.is_finite() && hi > lo).then_some((lo, hi))
}

/// Keep mode's state inside the tuner (serialized with it: a restored run
/// resumes keeping).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct KeepState {
    /// Tuning, Keeping (between checks; `Check` records) or Retune.
    phase: Phase,
    /// Per top-level parameter (config order), once first tuned.
    models: Vec<Option<DriftModel>>,
    /// Lab time of the last check of each parameter, s.
    last_check_s: Vec<f64>,
    /// Parameters of the check in flight.
    checking: Vec<usize>,
    /// Whether the check in flight already re-tuned the lower levels.
    check_retried: bool,
    /// Whether the iteration now ending is a check.
    in_check: bool,
    /// Lab time when first tuned, s.
    keeping_since_s: Option<f64>,
    /// Lab time of the check that started the present re-tune, s.
    out_since_s: Option<f64>,
    /// Whether the present re-tune has raised its alert.
    alerted: bool,
    /// Whether the next re-tune round starts from the check's values
    /// (measuring only what the check did not).
    #[serde(default)]
    from_check: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
enum Phase {
    Tuning,
    Keeping,
    Retune,
}

/// What keep mode does next when no level is active.
pub(super) enum KeepNext {
    /// Run the normal top-level round (tuning or re-tuning).
    Tune,
    /// Let lab time pass.
    Wait(Request),
    /// Run these operations on the top level (a check, or a re-tune round
    /// that starts from a check's values).
    Check(Vec<Op>),
    /// The keep duration is over.
    Finish,
}

impl KeepState {
    pub(super) fn new(parameters: usize) -> Self {
        Self {
            phase: Phase::Tuning,
            models: vec![None; parameters],
            last_check_s: vec![0.0; parameters],
            checking: Vec::new(),
            check_retried: false,
            in_check: false,
            keeping_since_s: None,
            out_since_s: None,
            alerted: false,
            from_check: false,
        }
    }

    /// Whether the run is between checks (not tuning or re-tuning).
    pub(super) fn is_keeping(&self) -> bool {
        self.phase == Phase::Keeping
    }

    /// A target changed: tune to it (the drift models restart when tuned).
    pub(super) fn target_changed(&mut self) {
        if self.phase == Phase::Keeping {
            self.phase = Phase::Tuning;
        }
    }
}

impl Tuner {
    fn keep_config(&self) -> Option<&KeepConfig> {
        self.config.keep.as_ref()
    }

    /// The fraction of the tolerance band within which the top level counts
    /// as tuned: the keep config's settle band while (re-)tuning, else 1.
    pub(super) fn band_scale(&self, level: usize) -> f64 {
        match (level, self.keep_config(), &self.keep) {
            (0, Some(k), Some(s)) if !s.is_keeping() => k.settle_band_fraction,
            _ => 1.0,
        }
    }

    /// Per top-level parameter: the lab time its next check is due (`None`
    /// for untargeted parameters and the `never` schedule).
    fn due_times(&self) -> Vec<Option<f64>> {
        let (Some(k), Some(s)) = (self.keep_config(), &self.keep) else {
            return Vec::new();
        };
        let top = self.config.top();
        top.parameters
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let (lo, hi) = estimator_band(p)?;
                match k.schedule {
                    KeepSchedule::Never => None,
                    KeepSchedule::Fixed { interval_s } => Some(s.last_check_s[i] + interval_s),
                    KeepSchedule::Predictive {
                        out_of_band_probability,
                    } => {
                        let m = s.models.get(i)?.as_ref()?;
                        Some(m.due(
                            lo,
                            hi,
                            out_of_band_probability,
                            k.min_check_interval_s,
                            k.max_check_interval_s,
                        ))
                    }
                }
            })
            .collect()
    }

    /// What to do next in keep mode (`None`: keep mode is off).
    pub(super) fn keep_next(&mut self) -> Option<KeepNext> {
        let k = self.keep_config()?.clone();
        let s = self.keep.as_ref()?;
        let now = self.lab_seconds;
        if s.phase != Phase::Keeping {
            if s.phase == Phase::Retune && s.from_check {
                let ops = self.top_round_ops_for_missing();
                self.keep.as_mut().expect("keep state present").from_check = false;
                return Some(KeepNext::Check(ops));
            }
            return Some(KeepNext::Tune);
        }
        let end = match (k.duration_s, s.keeping_since_s) {
            (Some(d), Some(since)) => since + d,
            _ => f64::INFINITY,
        };
        if now >= end - 1e-9 {
            return Some(KeepNext::Finish);
        }
        let due = self.due_times();
        let next = due.iter().flatten().copied().fold(f64::INFINITY, f64::min);
        if next > now + 1e-6 {
            let seconds = (next.min(end) - now).min(MAX_WAIT_SECONDS);
            return Some(KeepNext::Wait(Request::Wait { seconds }));
        }
        let checking: Vec<usize> = due
            .iter()
            .enumerate()
            .filter(|(_, d)| d.is_some_and(|d| d <= now + k.batch_window_s))
            .map(|(i, _)| i)
            .collect();
        let ops = self.check_ops(&checking);
        let s = self.keep.as_mut().expect("keep state present");
        s.checking = checking;
        s.check_retried = false;
        s.in_check = true;
        Some(KeepNext::Check(ops))
    }

    /// The scans that give `parameters` (top level), then the check's decision.
    fn check_ops(&self, parameters: &[usize]) -> Vec<Op> {
        let top = self.config.top();
        let mut kinds = Vec::new();
        for &i in parameters {
            let kind = top.parameters[i].scan;
            if !kinds.contains(&kind) {
                kinds.push(kind);
            }
        }
        let mut ops: Vec<Op> = kinds
            .into_iter()
            .map(|kind| {
                Op::Measure(crate::protocol::ScanRequest {
                    kind,
                    sweep: None,
                    cell: None,
                })
            })
            .collect();
        ops.push(Op::Decide(Decision::KeepCheck));
        ops
    }

    /// The check's scans are in: update the drift models, decide whether
    /// to re-tune, and end the iteration (a `check` record).
    pub(super) fn keep_check(&mut self) -> Option<crate::protocol::IterationRecord> {
        let k = self.keep_config()?.clone();
        let now = self.lab_seconds;
        let (samples, raw) = self.take_check_samples();
        let s = self.keep.as_mut()?;
        let checking = s.checking.clone();
        let top = self.config.top().clone();
        let trusted = |i: usize| {
            let p = &top.parameters[i];
            samples.get(i).copied().flatten().is_some()
                && raw.get(i).cloned().flatten().is_some_and(|v| {
                    p.target
                        .is_some_and(|t| v.variance.sqrt() <= p.tolerance.half_width(t))
                })
        };
        let missing: Vec<usize> = checking.iter().copied().filter(|&i| !trusted(i)).collect();
        if !missing.is_empty() && !s.check_retried {
            // Usually the sensor lost its flank or a line moved: re-tune the
            // lower levels (no move of the top level's gates) and measure again.
            s.check_retried = true;
            let mut ops = self.after_move_ops(0);
            ops.extend(self.check_ops(&checking));
            self.push_ops(ops);
            return None;
        }
        let mut reasons = Vec::new();
        let mut events = Vec::new();
        // Where each checked parameter is believed to be (predictive schedule):
        // the drift model's posterior (the prediction since the last check,
        // corrected by this check's value with its error bar), in parameter
        // units; a single noisy value moves it only as far as its error bar
        // allows. A fixed schedule believes the measured value.
        let mut posterior: Vec<ParameterValue> = Vec::new();
        let model_based = matches!(k.schedule, KeepSchedule::Predictive { .. });
        let s = self.keep.as_mut()?;
        for &i in &checking {
            let p = &top.parameters[i];
            let Some((lo, hi)) = estimator_band(p) else {
                continue;
            };
            let predicted = s
                .models
                .get(i)
                .and_then(Option::as_ref)
                .map_or(0.0, |m| m.out_of_band_probability(now, lo, hi));
            s.last_check_s[i] = now;
            // A value whose error bar is wider than its band says nothing
            // about where the parameter is (as in the tuner's evaluation).
            let value = raw.get(i).cloned().flatten().filter(|v| {
                p.target
                    .is_some_and(|t| v.variance.sqrt() <= p.tolerance.half_width(t))
            });
            let sample = samples
                .get(i)
                .copied()
                .flatten()
                .filter(|_| value.is_some());
            let model = s.models.get_mut(i).and_then(Option::as_mut);
            let believed = match (sample, model) {
                (Some((y, r)), Some(m)) => {
                    m.update(y, r, now);
                    // a fixed schedule is the lab's plain rule: the measured value decides
                    Some(if model_based {
                        (m.mean, m.variance)
                    } else {
                        (y, r)
                    })
                }
                (Some(sample), None) => Some(sample),
                (None, _) => None,
            };
            let in_band = believed.is_some_and(|(m, _)| (lo..=hi).contains(&m));
            events.push(EventKind::KeepCheck {
                parameter: p.name.clone(),
                value: value.as_ref().map(|v| v.value),
                in_band,
                predicted_out_of_band: predicted,
                unit: p.unit.clone(),
            });
            let Some((m, var)) = believed else {
                reasons.push(format!("{}: the check gave no value", p.name));
                continue;
            };
            let (estimate, estimate_var) = p.transform.inverse(m, var);
            posterior.push(ParameterValue {
                name: p.name.clone(),
                value: estimate,
                variance: estimate_var,
            });
            if !in_band {
                reasons.push(format!(
                    "{} is outside its band: measured {:.3} {}, believed {:.3} ± {:.3} {}",
                    p.name,
                    value.as_ref().map_or(f64::NAN, |v| v.value),
                    p.unit,
                    estimate,
                    estimate_var.sqrt(),
                    p.unit
                ));
            } else if let KeepSchedule::Predictive {
                out_of_band_probability,
            } = k.schedule
            {
                // Re-tune early only where a re-tune would move: the
                // estimate is outside the settle band and the model
                // expects the band edge before the next check could come.
                let soon = now + k.min_check_interval_s;
                let model = s.models.get(i).and_then(Option::as_ref);
                let p_out = model.map_or(0.0, |m| m.out_of_band_probability(soon, lo, hi));
                let centre = 0.5 * (lo + hi);
                let settle = k.settle_band_fraction * 0.5 * (hi - lo);
                if (m - centre).abs() > settle && p_out >= out_of_band_probability {
                    reasons.push(format!(
                        "{} = {:.3} {} is predicted to leave its band within {:.0} min (P = {:.0} %)",
                        p.name,
                        estimate,
                        p.unit,
                        k.min_check_interval_s / 60.0,
                        100.0 * p_out
                    ));
                }
            }
        }
        let retune = !reasons.is_empty();
        if retune {
            s.phase = Phase::Retune;
            s.out_since_s = Some(now);
            s.alerted = false;
            events.push(EventKind::RetuneStarted {
                reason: reasons.join("; "),
            });
        }
        for e in events {
            self.note(0, e);
        }
        if retune {
            self.forget_top_references();
            // The re-tune's first round starts from where the checked
            // parameters are believed to be (a fresh measurement would only
            // repeat the check, with new noise).
            if !posterior.is_empty() {
                self.restore_top_measurements(posterior);
                if let Some(s) = self.keep.as_mut() {
                    s.from_check = true;
                }
            }
        }
        self.set_check_snapshot(samples, raw, !retune);
        self.end_iteration(0)
    }

    /// After a top-level record: phase changes, alerts, the record's
    /// [`KeepReport`], and whether the run is finished.
    pub(super) fn keep_after_record(&mut self, record: &mut crate::protocol::IterationRecord) {
        let Some(k) = self.keep_config().cloned() else {
            return;
        };
        let now = self.lab_seconds;
        let top = self.config.top().clone();
        let samples = self.top_snapshot_samples();
        let level = self.config.levels[0].name.clone();
        let retuning = self
            .keep
            .as_ref()
            .is_some_and(|s| !s.in_check && s.phase == Phase::Retune);
        // A re-tune step the filter confidently predicts into the settle band
        // ends the re-tune without a confirming round.
        let skipped: Option<Vec<Option<Sample>>> = match k.skip_confirmation_sigma {
            Some(sigmas) if retuning && !record.tuned => {
                self.top_prediction_after_step().filter(|pred| {
                    top.parameters.iter().enumerate().all(|(i, p)| {
                        let Some((lo, hi)) = estimator_band(p) else {
                            return true;
                        };
                        let Some((m, v)) = pred.get(i).copied().flatten() else {
                            return false;
                        };
                        let centre = 0.5 * (lo + hi);
                        let settle = k.settle_band_fraction * 0.5 * (hi - lo);
                        let sd = v.max(0.0).sqrt();
                        (m - centre).abs() <= settle
                            && m - sigmas * sd >= lo
                            && m + sigmas * sd <= hi
                    })
                })
            }
            _ => None,
        };
        if let Some(pred) = &skipped {
            for (p, v) in top.parameters.iter().zip(pred) {
                let Some((m, var)) = *v else { continue };
                let (value, var) = p.transform.inverse(m, var);
                let std = var.sqrt();
                record.events.push(TunerEvent {
                    level: level.clone(),
                    kind: EventKind::ConfirmationSkipped {
                        parameter: p.name.clone(),
                        predicted: value,
                        std,
                        unit: p.unit.clone(),
                    },
                });
            }
        }
        let settled = record.tuned || skipped.is_some();
        let samples = skipped.unwrap_or(samples);
        let Some(s) = self.keep.as_mut() else { return };
        let record_phase = if s.in_check {
            KeepPhase::Check
        } else if s.phase == Phase::Retune {
            KeepPhase::Retune
        } else {
            KeepPhase::Tuning
        };
        s.in_check = false;
        if matches!(record_phase, KeepPhase::Tuning | KeepPhase::Retune) {
            if settled {
                // Settled: (re)start every drift model at the measured values.
                for (i, p) in top.parameters.iter().enumerate() {
                    let Some((lo, hi)) = estimator_band(p) else {
                        s.models[i] = None;
                        continue;
                    };
                    let Some((y, r)) = samples.get(i).copied().flatten() else {
                        continue;
                    };
                    let band = 0.5 * (hi - lo);
                    let q0 = (k.prior_drift_band_per_sqrt_hour * band).powi(2) / 3600.0;
                    match &mut s.models[i] {
                        Some(m) => m.restart(y, r, now),
                        None => s.models[i] = Some(DriftModel::new(y, r, now, q0)),
                    }
                    s.last_check_s[i] = now;
                }
                if let Some(since) = s.out_since_s.take() {
                    record.events.push(TunerEvent {
                        level: level.clone(),
                        kind: EventKind::BackInBand {
                            after_lab_seconds: now - since,
                        },
                    });
                }
                s.phase = Phase::Keeping;
                s.keeping_since_s.get_or_insert(now);
            } else if let Some(since) = s.out_since_s {
                if !s.alerted && now - since > k.alert_after_s {
                    s.alerted = true;
                    record.events.push(TunerEvent {
                        level: level.clone(),
                        kind: EventKind::NotBackInBand {
                            out_of_band_lab_seconds: now - since,
                            limit_lab_seconds: k.alert_after_s,
                        },
                    });
                }
            }
        }
        let out_of_band_lab_seconds = s.out_since_s.map_or(0.0, |since| now - since);
        let keeping = s.phase == Phase::Keeping;
        let (next_check_lab_seconds, next_check) = if keeping {
            let due = self.due_times();
            let next = due.iter().flatten().copied().fold(f64::INFINITY, f64::min);
            if next.is_finite() {
                let names = due
                    .iter()
                    .zip(&top.parameters)
                    .filter(|(d, _)| d.is_some_and(|d| d <= next + k.batch_window_s))
                    .map(|(_, p)| p.name.clone())
                    .collect();
                (Some(next), names)
            } else {
                (None, Vec::new())
            }
        } else {
            (None, Vec::new())
        };
        record.keep = Some(KeepReport {
            phase: record_phase,
            next_check_lab_seconds,
            next_check,
            out_of_band_lab_seconds,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_random_walk_leaves_the_band_later_the_closer_it_sits_to_the_centre() {
        let q = 1e-6; // units²/s
        let centre = DriftModel::new(0.0, 1e-4, 0.0, q);
        let edge = DriftModel::new(0.08, 1e-4, 0.0, q);
        let t_centre = centre.due(-0.1, 0.1, 0.02, 10.0, 1e6);
        let t_edge = edge.due(-0.1, 0.1, 0.02, 10.0, 1e6);
        assert!(t_edge < t_centre, "{t_edge} vs {t_centre}");
        // independent derivation for the centred walk: P(|x| > 0.1) = 0.02
        // ⇔ 0.1/σ = z(0.99) = 2.3263 ⇒ σ² = (0.1/2.3263)² = P₀ + q·t
        let sigma2 = (0.1f64 / 2.326_348).powi(2);
        let t_expected = (sigma2 - 1e-4) / q;
        assert!(
            (t_centre - t_expected).abs() < 1e-3 * t_expected,
            "{t_centre} vs {t_expected}"
        );
    }

    #[test]
    fn a_noisy_check_moves_the_belief_by_the_kalman_gain_only() {
        // Last check 0.0 ± 0.02 (estimator units), prior diffusion 1e-7 /s;
        // 1000 s later a value of 0.12 ± 0.06, beyond a band edge at 0.1.
        // The innovation first teaches the diffusion:
        //   q = (q₀·T₀ + ν² − P − R) / (T₀ + Δt)
        //     = (1e-7·7200 + 0.0144 − 4e-4 − 3.6e-3) / 8200,
        // then the belief moves by K = P⁻/(P⁻ + R) of the innovation, with
        // P⁻ = P + q·Δt: to about 0.043, inside the band.
        let mut m = DriftModel::new(0.0, 4e-4, 0.0, 1e-7);
        m.update(0.12, 3.6e-3, 1000.0);
        let q = (1e-7 * PRIOR_WEIGHT_S + 0.0144 - 4e-4 - 3.6e-3) / (PRIOR_WEIGHT_S + 1000.0);
        let p_pred = 4e-4 + q * 1000.0;
        let k = p_pred / (p_pred + 3.6e-3);
        assert!(
            (m.mean - k * 0.12).abs() < 1e-9,
            "{} vs {}",
            m.mean,
            k * 0.12
        );
        assert!((m.variance - (1.0 - k) * p_pred).abs() < 1e-12);
        assert!(m.mean > 0.0 && m.mean < 0.05);
    }

    #[test]
    fn the_learned_diffusion_follows_the_observed_drift() {
        // a walk with true diffusion 4× the prior, checked every 10 min
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let (q_true, q_prior, r) = (4e-7, 1e-7, 1e-6);
        let mut m = DriftModel::new(0.0, r, 0.0, q_prior);
        let (mut x, mut t) = (0.0, 0.0);
        let step = Normal::new(0.0, (q_true * 600.0f64).sqrt()).unwrap();
        let noise = Normal::new(0.0, r.sqrt()).unwrap();
        for _ in 0..2000 {
            t += 600.0;
            x += step.sample(&mut rng);
            m.update(x + noise.sample(&mut rng), r, t);
        }
        let q = m.diffusion();
        assert!(
            (q / q_true - 1.0).abs() < 0.15,
            "learned {q} vs true {q_true}"
        );
    }

    #[test]
    fn bad_keep_settings_name_their_field() {
        let mut k = KeepConfig {
            settle_band_fraction: 1.5,
            ..KeepConfig::default()
        };
        assert!(k
            .validate()
            .unwrap_err()
            .to_string()
            .contains("settle_band_fraction"));
        k.settle_band_fraction = 0.5;
        k.max_check_interval_s = 60.0; // below the minimum interval
        assert!(k
            .validate()
            .unwrap_err()
            .to_string()
            .contains("max_check_interval_s"));
        k.max_check_interval_s = 3600.0;
        k.schedule = KeepSchedule::Fixed { interval_s: 1.0 };
        assert!(k
            .validate()
            .unwrap_err()
            .to_string()
            .contains("schedule.interval_s"));
        let e = serde_json::from_str::<KeepConfig>(r#"{"every": 3}"#).unwrap_err();
        assert!(e.to_string().contains("every"));
    }
}
