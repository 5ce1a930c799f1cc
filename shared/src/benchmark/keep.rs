//! The keep benchmark (issue 23, `spintune bench-keep`): tune once, then
//! keep the qubit in tune for `hours` of lab time while the simulated
//! device drifts, with each keep strategy on the same device and seed.
//!
//! The world's side (what no strategy sees): the device's true `t_sr` and
//! `w` are sampled at least every [`SAMPLE_S`] of lab time (after every
//! request, and inside waits), and a strategy's `fraction_in_band` is the
//! lab time during which every targeted parameter was truly inside its
//! band (±`relative_tolerance`), divided by the keep window (from the
//! first tuned record to `hours` later).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::{
    quantiles, request_kind, world_config, BenchmarkError, BenchmarkProtocol, Harness, Quantiles,
    SeedFailure,
};
use crate::driver::SimulationConfig;
use crate::protocol::{EventKind, KeepPhase, Request, Response};
use crate::session::{Output, RunSession, SessionConfig};
use crate::tuner::{KeepConfig, KeepSchedule, TunerConfig};

/// Longest stretch of lab time between two samples of the truth, s.
pub const SAMPLE_S: f64 = 60.0;
/// A strategy that has not tuned for the first time within this much lab
/// time gives up on the seed (counted as `not_tuned`), s.
pub const MAX_INITIAL_TUNE_S: f64 = 4.0 * 3600.0;

/// A keep strategy. Serialized as its name ([`KeepStrategy::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(into = "String", try_from = "String")]
pub enum KeepStrategy {
    /// The product default: the drift model schedules checks and re-tunes.
    Predictive,
    /// Check every parameter every `seconds` of lab time, re-tune when a
    /// measured value is out of band (`fixed-10min` or `fixed-90s` on the
    /// command line; [`MIN_FIXED_SECONDS`] ..= [`MAX_FIXED_SECONDS`]).
    Fixed {
        /// Interval, lab seconds.
        seconds: u32,
    },
    /// Tune once, then leave it.
    Never,
    /// The predictive schedule at another out-of-band probability (in
    /// basis points, 1 bp = 0.01 %): `predictive@2%` on the command line.
    /// For the cost/in-band frontier; not in [`KeepStrategy::ALL`].
    PredictiveAt {
        /// Out-of-band probability at which a check is due, 0.01 % units
        /// (1 ..= [`MAX_PREDICTIVE_AT_BP`]).
        basis_points: u32,
    },
}

/// Shortest interval of a `fixed-…` strategy, lab seconds (the keep
/// config's [`crate::tuner::MIN_CHECK_INTERVAL_S`]).
pub const MIN_FIXED_SECONDS: u32 = crate::tuner::MIN_CHECK_INTERVAL_S as u32;
/// Longest interval of a `fixed-…` strategy, lab seconds (a day).
pub const MAX_FIXED_SECONDS: u32 = 86_400;

impl From<KeepStrategy> for String {
    fn from(s: KeepStrategy) -> String {
        s.name()
    }
}

impl TryFrom<String> for KeepStrategy {
    type Error = String;
    fn try_from(name: String) -> Result<Self, String> {
        KeepStrategy::parse(&name).ok_or_else(|| format!("unknown keep strategy {name:?}"))
    }
}

/// Highest out-of-band probability of a `predictive@P%` strategy, bp (50 %).
pub const MAX_PREDICTIVE_AT_BP: u32 = 5_000;

impl KeepStrategy {
    /// The strategies run by default, in report order: `predictive`, a
    /// ladder of fixed intervals from 20 s (a check of t_sr and w takes
    /// 33 s, so checking runs nearly back to back) to 60 min, and `never`.
    /// The ladder is what the goal needs: the cheapest fixed interval that
    /// keeps the qubit in band ([`super::keep_goals`]).
    pub const ALL: [KeepStrategy; 13] = [
        KeepStrategy::Predictive,
        KeepStrategy::Fixed { seconds: 20 },
        KeepStrategy::Fixed { seconds: 30 },
        KeepStrategy::Fixed { seconds: 45 },
        KeepStrategy::Fixed { seconds: 60 },
        KeepStrategy::Fixed { seconds: 90 },
        KeepStrategy::Fixed { seconds: 120 },
        KeepStrategy::Fixed { seconds: 180 },
        KeepStrategy::Fixed { seconds: 300 },
        KeepStrategy::Fixed { seconds: 600 },
        KeepStrategy::Fixed { seconds: 1_800 },
        KeepStrategy::Fixed { seconds: 3_600 },
        KeepStrategy::Never,
    ];

    /// Name on the command line and in reports.
    ///
    /// ```
    /// use spintune::benchmark::keep::KeepStrategy;
    /// let s = KeepStrategy::parse("predictive@2.5%").unwrap();
    /// assert_eq!(s, KeepStrategy::PredictiveAt { basis_points: 250 });
    /// assert_eq!(s.name(), "predictive@2.5%");
    /// assert_eq!(KeepStrategy::parse("fixed-30min").unwrap().name(), "fixed-30min");
    /// assert!(KeepStrategy::parse("predictive@0%").is_none());
    /// assert!(KeepStrategy::parse("predictive@60%").is_none());
    /// assert_eq!(KeepStrategy::parse("fixed-2min"), Some(KeepStrategy::Fixed { seconds: 120 }));
    /// assert_eq!(KeepStrategy::parse("fixed-90s").unwrap().name(), "fixed-90s");
    /// assert_eq!(KeepStrategy::parse("fixed-120s").unwrap().name(), "fixed-2min");
    /// assert!(KeepStrategy::parse("fixed-0min").is_none());
    /// assert!(KeepStrategy::parse("fixed-9s").is_none());
    /// assert!(KeepStrategy::parse("fixed-1441min").is_none());
    /// ```
    pub fn name(self) -> String {
        match self {
            KeepStrategy::Predictive => "predictive".into(),
            KeepStrategy::Fixed { seconds } if seconds % 60 == 0 => {
                format!("fixed-{}min", seconds / 60)
            }
            KeepStrategy::Fixed { seconds } => format!("fixed-{seconds}s"),
            KeepStrategy::Never => "never".into(),
            KeepStrategy::PredictiveAt { basis_points } => {
                format!("predictive@{}%", f64::from(basis_points) / 100.0)
            }
        }
    }

    /// Parse a name of [`KeepStrategy::name`]; `predictive@P%` takes any P
    /// in (0, 50] % with at most two decimals, `fixed-Nmin` and `fixed-Ns`
    /// any whole interval in [`MIN_FIXED_SECONDS`] ..= [`MAX_FIXED_SECONDS`].
    pub fn parse(name: &str) -> Option<Self> {
        if let Some(n) = name.strip_prefix("fixed-") {
            let seconds = match (n.strip_suffix("min"), n.strip_suffix('s')) {
                (Some(m), _) => m.parse::<u32>().ok()?.checked_mul(60)?,
                (None, Some(s)) => s.parse::<u32>().ok()?,
                (None, None) => return None,
            };
            return (MIN_FIXED_SECONDS..=MAX_FIXED_SECONDS)
                .contains(&seconds)
                .then_some(KeepStrategy::Fixed { seconds });
        }
        if let Some(p) = name.strip_prefix("predictive@") {
            let percent: f64 = p.strip_suffix('%')?.trim().parse().ok()?;
            let bp = (percent * 100.0).round();
            return ((1.0..=f64::from(MAX_PREDICTIVE_AT_BP)).contains(&bp)
                && (bp - percent * 100.0).abs() < 1e-6)
                .then_some(KeepStrategy::PredictiveAt {
                    basis_points: bp as u32,
                });
        }
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The keep config of this strategy, from the product's `keep` (its
    /// settle band, intervals, prior) with the strategy's schedule.
    pub fn keep_config(self, product: &KeepConfig) -> KeepConfig {
        let schedule = match self {
            KeepStrategy::Predictive => product.schedule,
            KeepStrategy::Fixed { seconds } => KeepSchedule::Fixed {
                interval_s: f64::from(seconds),
            },
            KeepStrategy::Never => KeepSchedule::Never,
            KeepStrategy::PredictiveAt { basis_points } => KeepSchedule::Predictive {
                out_of_band_probability: f64::from(basis_points) / 10_000.0,
            },
        };
        let schedule = match (self, schedule) {
            // the product's own schedule may be fixed: predictive is predictive
            (KeepStrategy::Predictive, KeepSchedule::Predictive { .. }) => schedule,
            (KeepStrategy::Predictive, _) => KeepSchedule::default(),
            (_, s) => s,
        };
        KeepConfig {
            schedule,
            ..product.clone()
        }
    }
}

/// What one strategy did on one device and seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeepSeedResult {
    /// Strategy.
    pub strategy: KeepStrategy,
    /// Seed.
    pub seed: u64,
    /// Device seed (0: the given device).
    pub device: u64,
    /// Lab minutes from the start to the first tuned record (`None`: not
    /// tuned within [`MAX_INITIAL_TUNE_S`]; the other fields are then 0).
    pub initial_tune_lab_minutes: Option<f64>,
    /// Fraction of the keep window with every targeted parameter truly in band.
    pub fraction_in_band: f64,
    /// Lab minutes of measurement (everything but waiting) per lab hour of the window.
    pub measurement_minutes_per_hour: f64,
    /// Re-tunes started in the window.
    pub retunes: u64,
    /// Checks in the window.
    pub checks: u64,
    /// Longest stretch truly out of band, lab minutes.
    pub longest_out_of_band_minutes: f64,
    /// `not_back_in_band` alerts raised.
    pub alerts: u64,
    /// Iteration records in the window.
    pub records: u64,
    /// Moves longer than the step limit (must be 0).
    pub limit_violations: u64,
    /// Queries of the simulator's truth by the tuner (must be 0).
    pub truth_queries: u64,
    /// Where the measurement time went: lab minutes per lab hour of the
    /// window, keyed `phase/kind` (phase of the record the request belongs
    /// to: `tuning`, `check`, `retune`; kind: a scan kind, `set_voltages`,
    /// `read_voltages`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub minutes_per_hour_by_kind: BTreeMap<String, f64>,
    /// The day, sampled (with `trace`): for the figure.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub trace: Vec<KeepSample>,
}

/// One sample of the world's truth and of what the tuner did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeepSample {
    /// Lab hours since the keep window opened (negative: initial tuning).
    pub hours: f64,
    /// True t_sr, ns.
    pub t_sr_ns: f64,
    /// True w, µV.
    pub w_uv: f64,
    /// What happened at this sample: `check`, `retune` or empty.
    pub mark: String,
}

/// Run one keep strategy on one seed: the world is `base` with the product
/// tuner (`product`, its compensation perturbed as in [`super::run_seed`]),
/// `protocol.relative_tolerance` on the targeted parameters, kept for
/// `hours` of lab time after the first tuned record.
pub fn run_keep_seed(
    base: &SimulationConfig,
    product: &TunerConfig,
    strategy: KeepStrategy,
    protocol: &BenchmarkProtocol,
    hours: f64,
    seed: u64,
    trace: bool,
) -> Result<KeepSeedResult, BenchmarkError> {
    let err = |cause: SeedFailure| BenchmarkError {
        seed,
        strategy: None,
        cause,
    };
    let mut world = base.clone();
    world.tuner = product.clone();
    let mut cfg = world_config(&world, protocol, seed);
    cfg.tuner.max_iterations = None;
    let product_keep = product.keep.clone().unwrap_or_default();
    cfg.tuner.keep = Some(KeepConfig {
        duration_s: Some(hours * 3600.0),
        ..strategy.keep_config(&product_keep)
    });
    let targets: Vec<(String, f64, f64)> = cfg
        .tuner
        .top()
        .parameters
        .iter()
        .filter_map(|p| {
            let t = p.target?;
            Some((p.name.clone(), t, p.tolerance.half_width(t)))
        })
        .collect();
    let mut device = cfg.simulated_device().map_err(|e| err(e.into()))?;
    device.seal_truth();
    let top = cfg.tuner.top();
    let mut h = Harness {
        top_gates: top.gates.clone(),
        max_step_mv: top.solver.max_step_mv,
        session: RunSession::new(cfg.tuner.clone(), SessionConfig::default())
            .map_err(|e| err(e.into()))?,
        device,
        moves: 0,
        violations: 0,
        lab_by_kind: BTreeMap::new(),
    };
    let mut r = KeepSeedResult {
        strategy,
        seed,
        device: 0,
        initial_tune_lab_minutes: None,
        fraction_in_band: 0.0,
        measurement_minutes_per_hour: 0.0,
        retunes: 0,
        checks: 0,
        longest_out_of_band_minutes: 0.0,
        alerts: 0,
        records: 0,
        limit_violations: 0,
        truth_queries: 0,
        minutes_per_hour_by_kind: BTreeMap::new(),
        trace: Vec::new(),
    };
    // lab seconds of the iteration in progress, by request kind
    let mut pending: BTreeMap<&'static str, f64> = BTreeMap::new();
    let mut w = World {
        targets,
        trace,
        window: None,
        in_band_s: 0.0,
        window_s: 0.0,
        waited_s: 0.0,
        out_streak_s: 0.0,
        longest_out_s: 0.0,
        mark: String::new(),
        samples: Vec::new(),
    };
    loop {
        match h.session.poll() {
            Output::Execute(request) => {
                let response = if let Request::Wait { seconds } = request {
                    // in pieces, so the truth is sampled inside long waits
                    let mut left = seconds;
                    let mut total = 0.0;
                    while left > 1e-9 {
                        let dt = left.min(SAMPLE_S);
                        match h.device.execute(&Request::Wait { seconds: dt }) {
                            Response::Waited { lab_seconds } => total += lab_seconds,
                            other => return Err(err(SeedFailure::Unexpected(other))),
                        }
                        left -= dt;
                        if w.window.is_some() {
                            w.waited_s += dt;
                        }
                        w.account(&h, dt);
                    }
                    Response::Waited { lab_seconds: total }
                } else {
                    let t0 = h.device.lab_seconds();
                    let response = h.execute(&request);
                    let dt = h.device.lab_seconds() - t0;
                    w.account(&h, dt);
                    *pending.entry(request_kind(&request)).or_default() += dt;
                    response
                };
                h.session.feed(response).map_err(|e| err(e.into()))?;
            }
            Output::Commit(record) => {
                let now = h.device.lab_seconds();
                // this record's requests ran inside the window only if it was open before
                let iteration = std::mem::take(&mut pending);
                if w.window.is_some() {
                    let phase = match record.keep.as_ref().map(|k| k.phase) {
                        Some(KeepPhase::Check) => "check",
                        Some(KeepPhase::Retune) => "retune",
                        Some(KeepPhase::Tuning) | None => "tuning",
                    };
                    for (kind, dt) in iteration {
                        *r.minutes_per_hour_by_kind
                            .entry(format!("{phase}/{kind}"))
                            .or_default() += dt;
                    }
                }
                if w.window.is_none() && record.tuned {
                    w.window = Some(now);
                    r.initial_tune_lab_minutes = Some(now / 60.0);
                }
                if w.window.is_some() {
                    r.records += 1;
                    if record.keep.as_ref().map(|k| k.phase) == Some(KeepPhase::Check) {
                        r.checks += 1;
                        w.mark = "check".into();
                    }
                    for e in &record.events {
                        match e.kind {
                            EventKind::RetuneStarted { .. } => {
                                r.retunes += 1;
                                w.mark = "retune".into();
                            }
                            EventKind::NotBackInBand { .. } => r.alerts += 1,
                            _ => {}
                        }
                    }
                }
            }
            Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
            Output::Wait => {
                return Err(err(SeedFailure::Waiting(h.session.status())));
            }
            Output::Done(_) => break,
        }
        if w.window.is_none() && h.device.lab_seconds() > MAX_INITIAL_TUNE_S {
            break;
        }
    }
    if w.window.is_some() && w.window_s > 0.0 {
        r.fraction_in_band = w.in_band_s / w.window_s;
        r.measurement_minutes_per_hour = (w.window_s - w.waited_s) / 60.0 / (w.window_s / 3600.0);
        r.longest_out_of_band_minutes = w.longest_out_s / 60.0;
        let hours = w.window_s / 3600.0;
        for v in r.minutes_per_hour_by_kind.values_mut() {
            *v /= 60.0 * hours;
        }
    }
    r.limit_violations = h.violations;
    r.truth_queries = h.device.truth_queries();
    r.trace = w.samples;
    Ok(r)
}

/// The world's bookkeeping of one run (what no strategy sees).
struct World {
    /// Targeted parameters: name, target, band half-width (parameter units).
    targets: Vec<(String, f64, f64)>,
    trace: bool,
    /// Lab time the keep window opened (first tuned record), s.
    window: Option<f64>,
    in_band_s: f64,
    window_s: f64,
    waited_s: f64,
    out_streak_s: f64,
    longest_out_s: f64,
    /// What the next trace sample marks.
    mark: String,
    samples: Vec<KeepSample>,
}

impl World {
    /// `dt` seconds of lab time passed; the truth now stands for them.
    fn account(&mut self, h: &Harness, dt: f64) {
        let truth = h.device.truth();
        let ok = self
            .targets
            .iter()
            .all(|(name, t, hw)| truth.get(name).is_some_and(|v| (v - t).abs() <= *hw));
        if self.window.is_some() {
            self.window_s += dt;
            if ok {
                self.in_band_s += dt;
                self.out_streak_s = 0.0;
            } else {
                self.out_streak_s += dt;
                self.longest_out_s = self.longest_out_s.max(self.out_streak_s);
            }
        }
        if self.trace {
            let now = h.device.lab_seconds();
            self.samples.push(KeepSample {
                // before the window opens (the initial tuning): -1
                hours: self.window.map_or(-1.0, |w| (now - w) / 3600.0),
                t_sr_ns: truth.t_sr_ns,
                w_uv: truth.w_uv,
                mark: std::mem::take(&mut self.mark),
            });
        }
    }
}

/// One strategy over many seeds (keys as in the JSON report).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeepSummary {
    /// Strategy name.
    pub name: String,
    /// Seeds (× devices) run.
    pub runs: u64,
    /// Runs that never tuned within [`MAX_INITIAL_TUNE_S`].
    pub not_tuned: u64,
    /// Time-weighted fraction truly in band: mean over runs.
    pub fraction_in_band: f64,
    /// Its quantiles over runs (median, p90 of the *lowest*: `p90` is the
    /// 10th percentile, the bad tail; max is the minimum).
    pub fraction_in_band_low: Quantiles,
    /// Measurement minutes per lab hour: mean over runs.
    pub measurement_minutes_per_hour: f64,
    /// Re-tunes per lab day: mean over runs.
    pub retunes_per_day: f64,
    /// Checks per lab day: mean over runs.
    pub checks_per_day: f64,
    /// Longest stretch out of band, lab minutes: median, p90, max over runs.
    pub longest_out_of_band_minutes: Quantiles,
    /// `not_back_in_band` alerts, total.
    pub alerts: u64,
    /// Must be 0.
    pub limit_violations: u64,
    /// Must be 0.
    pub truth_queries: u64,
    /// Measurement minutes per lab hour by `phase/kind`: mean over runs.
    #[serde(default)]
    pub minutes_per_hour_by_kind: BTreeMap<String, f64>,
}

/// Summaries per strategy, in `strategies`' order.
pub fn summarize_keep(
    results: &[KeepSeedResult],
    strategies: &[KeepStrategy],
    hours: f64,
) -> Vec<KeepSummary> {
    strategies
        .iter()
        .map(|&s| {
            let mine: Vec<&KeepSeedResult> = results.iter().filter(|r| r.strategy == s).collect();
            let tuned: Vec<&&KeepSeedResult> = mine
                .iter()
                .filter(|r| r.initial_tune_lab_minutes.is_some())
                .collect();
            let n = tuned.len().max(1) as f64;
            let mean =
                |f: &dyn Fn(&KeepSeedResult) -> f64| tuned.iter().map(|r| f(r)).sum::<f64>() / n;
            let days = hours / 24.0;
            KeepSummary {
                name: s.name(),
                runs: mine.len() as u64,
                not_tuned: (mine.len() - tuned.len()) as u64,
                fraction_in_band: mean(&|r| r.fraction_in_band),
                fraction_in_band_low: {
                    let low: Vec<f64> = tuned.iter().map(|r| -r.fraction_in_band).collect();
                    let q = quantiles(&low);
                    Quantiles {
                        median: -q.median,
                        p90: -q.p90,
                        max: -q.max,
                    }
                },
                measurement_minutes_per_hour: mean(&|r| r.measurement_minutes_per_hour),
                retunes_per_day: mean(&|r| r.retunes as f64) / days,
                checks_per_day: mean(&|r| r.checks as f64) / days,
                longest_out_of_band_minutes: quantiles(
                    &tuned
                        .iter()
                        .map(|r| r.longest_out_of_band_minutes)
                        .collect::<Vec<_>>(),
                ),
                alerts: mine.iter().map(|r| r.alerts).sum(),
                limit_violations: mine.iter().map(|r| r.limit_violations).sum(),
                truth_queries: mine.iter().map(|r| r.truth_queries).sum(),
                minutes_per_hour_by_kind: {
                    let mut by: BTreeMap<String, f64> = BTreeMap::new();
                    for r in &tuned {
                        for (k, v) in &r.minutes_per_hour_by_kind {
                            *by.entry(k.clone()).or_default() += v / n;
                        }
                    }
                    by
                },
            }
        })
        .collect()
}
