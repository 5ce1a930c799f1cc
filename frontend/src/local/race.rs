//! Teaching: two estimators race on the same seeded simulated devices,
//! over several seeds and through target changes.
//!
//! Every racer is a [`LocalRunner`] built from the sidebar's
//! [`LocalSettings`] (device, step limit, noise, iteration limit) except the
//! estimator (and its process noise, so two Q settings can race too) and the
//! seed: each of the two contestants runs on the seeds `seed`, `seed + 1`, …
//! (the same devices for both). A racer works through the paper's set
//! points ([`PAPER_SET_POINTS`], the first [`Race::set_points`] of them):
//! when it is tuned (every parameter in band) the targets move to the next
//! set point, as a lab would after a tune; it is *done* after the last one
//! or when its run is over. What counts is the lab time it took, minutes,
//! summarised per contestant over the seeds (mean, spread).

use leptos::prelude::*;
use leptos::reactive::owner::LocalStorage;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::driver::Halt;
use spintune::estimator::EstimatorKind;

use super::runner::{LocalRunner, Progress};
use super::settings::LocalSettings;
use super::{estimator_label, LocalError, SLICE_MS};
use crate::charts;
use crate::history::RunHistory;
use crate::metrics;
use crate::series::{self, Drawn, Viewport, XAxis};
use crate::ui::{Area, Chart};
use crate::widgets::{FieldError, NumberField};
use crate::zoom::View;

/// One contestant's choices.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    /// Gradient estimator.
    pub estimator: EstimatorKind,
    /// Factor on both parameters' process noise σ (1 = the settings' Q).
    pub q_scale: f64,
}

/// How one racer (one contestant on one seed) did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// Iterations run so far.
    pub iterations: u64,
    /// Set points reached (tuned) so far.
    pub reached: usize,
    /// Lab time until the last set point was reached (or so far), minutes.
    pub lab_minutes: f64,
    /// Every set point reached, or the run is over.
    pub done: bool,
}

/// One contestant on one seed.
pub struct Racer {
    /// What it runs.
    pub entry: Entry,
    /// Contestant: 0 (A) or 1 (B).
    pub side: usize,
    /// The device's seed.
    pub seed: u64,
    /// The run.
    pub runner: LocalRunner,
    /// Its records.
    pub history: RunHistory,
    reached: usize,
    over: bool,
}

impl Racer {
    fn outcome(&self, set_points: usize) -> Outcome {
        let lab_s = self.history.rows().last().map_or(0.0, |r| r.lab_seconds);
        Outcome {
            iterations: self.history.len() as u64,
            reached: self.reached,
            lab_minutes: lab_s / 60.0,
            done: self.reached >= set_points || self.over,
        }
    }
}

/// Summary of one contestant over its seeds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    /// Seeds raced.
    pub seeds: usize,
    /// Seeds done.
    pub done: usize,
    /// Seeds that reached every set point.
    pub finished: usize,
    /// Mean lab time of the finished seeds, minutes (NaN if none).
    pub mean_minutes: f64,
    /// Their standard deviation, minutes (0 for one seed).
    pub sd_minutes: f64,
    /// Their smallest and largest lab time, minutes.
    pub range_minutes: (f64, f64),
    /// Iterations over all seeds.
    pub iterations: u64,
}

/// Two contestants on `seeds` devices each.
pub struct Race {
    /// Every racer: A's seeds, then B's.
    pub racers: Vec<Racer>,
    /// Set points each racer works through.
    pub set_points: usize,
    tolerance: f64,
    cursor: usize,
}

impl Race {
    /// A race between `a` and `b` with the shared `settings`, on the seeds
    /// `settings.seed ..+ seeds`, through the first `set_points` of the
    /// paper's set points (1 to 5).
    pub fn new(
        settings: &LocalSettings,
        a: Entry,
        b: Entry,
        seeds: usize,
        set_points: usize,
    ) -> Result<Self, LocalError> {
        let set_points = set_points.clamp(1, PAPER_SET_POINTS.len());
        let (t_sr, w) = PAPER_SET_POINTS[0];
        let mut racers = Vec::new();
        for (side, e) in [a, b].into_iter().enumerate() {
            for i in 0..seeds.max(1) as u64 {
                let s = LocalSettings {
                    estimator: e.estimator,
                    q_tsr: settings.q_tsr * e.q_scale,
                    q_w: settings.q_w * e.q_scale,
                    paper_cycle: false,
                    seed: settings.seed + i,
                    target_tsr: t_sr,
                    target_w: w,
                    ..settings.clone()
                };
                racers.push(Racer {
                    entry: e,
                    side,
                    seed: s.seed,
                    runner: LocalRunner::new(&s)?,
                    history: RunHistory::new(),
                    reached: 0,
                    over: false,
                });
            }
        }
        Ok(Self {
            racers,
            set_points,
            tolerance: settings.tolerance,
            cursor: 0,
        })
    }

    /// Work for about `budget_ms` (by `now`) on the next racer not done
    /// (round robin); a whole iteration of each with an unlimited budget.
    /// Whether any racer is still going.
    pub fn step(&mut self, budget_ms: f64, now: &dyn Fn() -> f64) -> Result<bool, LocalError> {
        let n = self.racers.len();
        let (set_points, tolerance) = (self.set_points, self.tolerance);
        let Some(i) = (0..n)
            .map(|d| (self.cursor + d) % n)
            .find(|&i| !self.racers[i].outcome(set_points).done)
        else {
            return Ok(false);
        };
        let r = &mut self.racers[i];
        match r.runner.advance_for(&mut r.history, budget_ms, now) {
            Ok(Progress::Working) => return Ok(true),
            Ok(Progress::Recorded(_)) => {
                if r.runner.tuned_at.is_some() {
                    r.reached += 1;
                    if r.reached < set_points {
                        let (t_sr, w) = PAPER_SET_POINTS[r.reached];
                        r.runner.set_targets(t_sr, w, tolerance)?;
                    }
                }
            }
            Ok(Progress::Over) | Err(Halt::Paused | Halt::Fault(_)) => r.over = true,
            Err(e @ Halt::Session(_)) => return Err(LocalError::Halted(e)),
        }
        self.cursor = (i + 1) % n;
        Ok(!self.done())
    }

    /// Every racer's outcome, in the order of [`Race::racers`].
    pub fn outcomes(&self) -> Vec<Outcome> {
        self.racers
            .iter()
            .map(|r| r.outcome(self.set_points))
            .collect()
    }

    /// Contestant `side`'s summary over its seeds.
    pub fn summary(&self, side: usize) -> Summary {
        let outs: Vec<Outcome> = self
            .racers
            .iter()
            .filter(|r| r.side == side)
            .map(|r| r.outcome(self.set_points))
            .collect();
        let fin: Vec<f64> = outs
            .iter()
            .filter(|o| o.reached >= self.set_points)
            .map(|o| o.lab_minutes)
            .collect();
        let n = fin.len() as f64;
        let mean = fin.iter().sum::<f64>() / n;
        let sd = if fin.len() > 1 {
            (fin.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
        } else {
            0.0
        };
        Summary {
            seeds: outs.len(),
            done: outs.iter().filter(|o| o.done).count(),
            finished: fin.len(),
            mean_minutes: if fin.is_empty() { f64::NAN } else { mean },
            sd_minutes: sd,
            range_minutes: (
                fin.iter().copied().fold(f64::INFINITY, f64::min),
                fin.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ),
            iterations: outs.iter().map(|o| o.iterations).sum(),
        }
    }

    /// Whether every racer is done.
    pub fn done(&self) -> bool {
        self.outcomes().iter().all(|o| o.done)
    }
}

/// A contestant's result line, e.g. "3 of 3 seeds reached all 3 set points
/// · 41.2 ± 5.3 lab min (mean ± sd; 35.1–47.0)", or its progress.
pub fn summary_text(s: &Summary, set_points: usize) -> String {
    if s.done < s.seeds {
        return format!(
            "racing… {} of {} seeds done · {} iterations",
            s.done, s.seeds, s.iterations
        );
    }
    if s.finished == 0 {
        return format!(
            "no seed reached all {set_points} set points ({} iterations)",
            s.iterations
        );
    }
    format!(
        "{} of {} seeds reached all {set_points} set points · {:.1} ± {:.1} lab min (mean ± sd; {:.1}–{:.1})",
        s.finished, s.seeds, s.mean_minutes, s.sd_minutes, s.range_minutes.0, s.range_minutes.1
    )
}

fn estimator_select(
    label: &'static str,
    testid: &'static str,
    sel: RwSignal<Entry>,
) -> impl IntoView {
    view! {
        <label class="field">
            <span class="field-label">{label}</span>
            <select data-testid=testid on:change=move |ev| {
                if let Some(k) = EstimatorKind::from_name(&event_target_value(&ev)) {
                    sel.update(|e| e.estimator = k);
                }
            }>
                {EstimatorKind::ALL.into_iter().map(|k| view! {
                    <option value=k.name() selected=move || sel.with(|e| e.estimator == k)>{estimator_label(k)}</option>
                }).collect_view()}
            </select>
            <span class="field-input">
                <input type="number" step="0.5" min="0" title="factor on the process noise σ (Q)"
                    prop:value=move || sel.with(|e| e.q_scale.to_string())
                    on:change=move |ev| {
                        if let Ok(v) = event_target_value(&ev).trim().parse::<f64>() {
                            if v.is_finite() && v >= 0.0 { sel.update(|e| e.q_scale = v) }
                        }
                    } />
                <span class="unit">"× Q σ"</span>
            </span>
        </label>
    }
}

/// The race panel of the in-browser mode: choose two estimators, race them
/// on several seeded devices through target changes, see the lab time each
/// needed (mean and spread) and seed 1 of both side by side.
#[component]
pub fn RacePanel(settings: RwSignal<LocalSettings>) -> impl IntoView {
    let a = RwSignal::new(Entry {
        estimator: EstimatorKind::Kalman,
        q_scale: 1.0,
    });
    let b = RwSignal::new(Entry {
        estimator: EstimatorKind::Broyden,
        q_scale: 1.0,
    });
    let seeds = RwSignal::new(3.0f64);
    let set_points = RwSignal::new(3.0f64);
    let race = StoredValue::<Option<Race>, LocalStorage>::new_local(None);
    let summaries = RwSignal::new(None::<([Summary; 2], usize)>);
    let histories = [
        RwSignal::new(RunHistory::new()),
        RwSignal::new(RunHistory::new()),
    ];
    let error = RwSignal::new(None::<String>);
    let generation = StoredValue::new(0u64);
    // Seed 1 of A and of B (the first racer of each side) to the charts.
    let sync = move || {
        race.with_value(|r| {
            let Some(r) = r else { return };
            for (side, h) in histories.iter().enumerate() {
                if let Some(src) = r.racers.iter().find(|x| x.side == side) {
                    if h.with_untracked(|h| h.len()) != src.history.len() {
                        h.set(src.history.clone());
                    }
                }
            }
            summaries.set(Some(([r.summary(0), r.summary(1)], r.set_points)));
        });
    };
    let start = move || {
        generation.update_value(|g| *g += 1);
        let my = generation.get_value();
        match Race::new(
            &settings.get_untracked(),
            a.get_untracked(),
            b.get_untracked(),
            seeds.get_untracked() as usize,
            set_points.get_untracked() as usize,
        ) {
            Ok(r) => {
                race.set_value(Some(r));
                error.set(None);
            }
            Err(e) => {
                error.set(Some(e.to_string()));
                return;
            }
        }
        for h in &histories {
            h.set(RunHistory::new());
        }
        leptos::task::spawn_local(async move {
            loop {
                gloo_timers::future::TimeoutFuture::new(0).await;
                if generation.try_get_value() != Some(my) {
                    break;
                }
                let t0 = metrics::now_ms();
                let res = race
                    .try_update_value(|r| r.as_mut().map(|r| r.step(SLICE_MS, &metrics::now_ms)))
                    .flatten();
                metrics::note_local_slice(metrics::now_ms() - t0);
                sync();
                match res {
                    Some(Ok(true)) => {}
                    Some(Err(e)) => {
                        error.set(Some(e.to_string()));
                        break;
                    }
                    _ => break,
                }
            }
        });
    };
    let card = move |i: usize, testid: &'static str| {
        let entry = if i == 0 { a } else { b };
        view! {
            <div class="race-card" data-testid=testid>
                <b>{move || format!("{} {} (Q σ × {})", if i == 0 { "A" } else { "B" }, entry.with(|e| estimator_label(e.estimator)), entry.with(|e| e.q_scale))}</b>
                " — "
                <span>{move || summaries.with(|o| o.as_ref().map_or_else(|| "press Race".to_string(), |(s, n)| summary_text(&s[i], *n)))}</span>
            </div>
        }
    };
    let param_chart = move |p: usize, name: &'static str| {
        view! {
            <Chart
                name=format!("race-{name}")
                height=240
                key=move || vec![histories[0].with(|h| h.version()), histories[1].with(|h| h.version())]
                draw=move |ar: &Area| {
                    let ov = histories[1].read();
                    histories[0].with(|h| {
                        let (lo, hi) = match (h.extent(), ov.extent()) {
                            (Some(x), Some(y)) => (x.0.min(y.0), x.1.max(y.1)),
                            (Some(x), None) | (None, Some(x)) => x,
                            (None, None) => (0, 10),
                        };
                        let w = View::All.window(lo as f64, hi as f64);
                        series::draw_parameter(ar, &Viewport { history: h, window: w, axis: XAxis::Iteration, overlay: Some(&*ov), align: false }, p, 0, crate::zoom::YRange::Auto)
                    })
                }
            />
        }
    };
    let set_seeds = Callback::new(move |v: f64| seeds.set(v));
    let check_seeds = Callback::new(move |v: f64| {
        if v.fract() == 0.0 && (1.0..=10.0).contains(&v) {
            Ok(())
        } else {
            Err(FieldError::new("a whole number from 1 to 10"))
        }
    });
    let set_sp = Callback::new(move |v: f64| set_points.set(v));
    let check_sp = Callback::new(move |v: f64| {
        if v.fract() == 0.0 && (1.0..=PAPER_SET_POINTS.len() as f64).contains(&v) {
            Ok(())
        } else {
            Err(FieldError::new(format!(
                "a whole number from 1 to {}",
                PAPER_SET_POINTS.len()
            )))
        }
    });
    let legend = || {
        view! {
            <div class="legend"><span><i class="swatch a"></i>"A (first seed)"</span><span><i class="swatch overlay"></i>"B (first seed)"</span><span><i class="swatch target"></i>"target"</span><span><i class="swatch band"></i>"tolerance band"</span></div>
        }
    };
    view! {
        <section class="race" data-testid="race">
            <h3>"Race two estimators " <small>"(same devices, step limit and noise as the sidebar; several seeds; through the paper's set points)"</small></h3>
            <p class="hint">"Each contestant tunes the same seeded devices to the paper's first set point (t_sr 20 ns, w 270 µV); once in band, the targets move to the next one (70 ns, 270 µV; then 70 ns, 180 µV; …), as after a tune in the lab. What counts is the lab time, in minutes, to reach them all: the mean and spread over the seeds show whether a difference is more than luck."</p>
            <div class="race-controls">
                {estimator_select("A", "race-estimator-a", a)}
                {estimator_select("B", "race-estimator-b", b)}
                <NumberField label="seeds" unit="devices" testid="race-seeds" step="1" get=seeds.into() set=set_seeds check=check_seeds />
                <NumberField label="set points" unit="of 5" testid="race-set-points" step="1" get=set_points.into() set=set_sp check=check_sp />
                <button class="primary" data-testid="race-start" on:click=move |_| start()>"Race"</button>
            </div>
            {move || error.get().map(|e| view! { <p class="error">{e}</p> })}
            <div class="grid2">
                {card(0, "race-a")}
                {card(1, "race-b")}
            </div>
            <div class="grid2">
                <div class="chart-box">
                    {param_chart(0, "t_sr")}
                    {legend()}
                </div>
                <div class="chart-box">
                    {param_chart(1, "w")}
                    {legend()}
                </div>
            </div>
            <div class="chart-box">
                <Chart
                    name="race-landscape"
                    height=340
                    key=move || vec![histories[0].with(|h| h.version()), histories[1].with(|h| h.version())]
                    draw=move |ar: &Area| {
                        let n = histories[0].with(|h| h.len()) + histories[1].with(|h| h.len());
                        let (land, other) = race.with_value(|r| {
                            let first = |side: usize| r.as_ref().and_then(|r| r.racers.iter().find(|x| x.side == side));
                            (
                                first(0).and_then(|x| x.runner.landscape(&x.history, "SB", "T", 30.0, 25)),
                                first(1).map_or_else(Vec::new, |x| LocalRunner::landscape_path(&x.history, "SB", "T")),
                            )
                        });
                        charts::draw_landscape(ar, land.as_ref(), &other).map(|_| Drawn { iterations: n, ..Drawn::default() })
                    }
                />
                <div class="legend"><span><i class="swatch path-a"></i>"path of A (first seed)"</span><span><i class="swatch path-b"></i>"path of B (first seed)"</span><span>"colour: distance to target in tolerance units (at A's present voltages)"</span></div>
            </div>
        </section>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finish(race: &mut Race) {
        while race.step(f64::INFINITY, &|| 0.0).unwrap() {}
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn kalman_and_broyden_race_on_the_same_devices_through_target_changes() {
        let settings = LocalSettings {
            max_iterations: 80,
            ..LocalSettings::default()
        };
        let kalman = Entry {
            estimator: EstimatorKind::Kalman,
            q_scale: 1.0,
        };
        let broyden = Entry {
            estimator: EstimatorKind::Broyden,
            q_scale: 1.0,
        };
        let mut race = Race::new(&settings, kalman, broyden, 2, 2).unwrap();
        assert_eq!(race.racers.len(), 4);
        assert!(!race.done());
        // One iteration of each racer: A and B on seed s measure at the same voltages.
        for _ in 0..4 {
            race.step(f64::INFINITY, &|| 0.0).unwrap();
        }
        let gates = |i: usize| {
            let h = &race.racers[i].history;
            (0..4)
                .map(|g| h.values(0).unwrap()[h.layout().gate(g)])
                .collect::<Vec<_>>()
        };
        assert_eq!(gates(0), gates(2), "seed 1: same start for A and B");
        assert_eq!(race.racers[1].seed, race.racers[0].seed + 1);
        assert_eq!(
            race.racers[0].runner.tuner().config().top().estimator,
            EstimatorKind::Kalman
        );
        assert_eq!(
            race.racers[2].runner.tuner().config().top().estimator,
            EstimatorKind::Broyden
        );
        finish(&mut race);
        assert!(race.done());
        let (sa, sb) = (race.summary(0), race.summary(1));
        eprintln!("race: A {sa:?}, B {sb:?}");
        assert_eq!(sa.seeds, 2);
        assert_eq!(
            sa.finished, 2,
            "Kalman reaches both set points on both seeds: {sa:?}"
        );
        // Past the first tune: the second set point was a target change.
        let r = &race.racers[0];
        let l = r.history.layout();
        let t = l.param_index("t_sr").unwrap();
        let last = r.history.values(r.history.extent().unwrap().1).unwrap();
        assert_eq!(last[l.param(t) + 2], PAPER_SET_POINTS[1].0);
        assert!(sa.mean_minutes > 0.0 && sa.sd_minutes >= 0.0);
        let text = summary_text(&sa, 2);
        assert!(
            text.starts_with("2 of 2 seeds reached all 2 set points · "),
            "{text}"
        );
        assert!(text.contains("lab min (mean ± sd; "), "{text}");
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn two_q_settings_race_too_and_the_oracle_is_labelled() {
        let e = |q| Entry {
            estimator: EstimatorKind::Kalman,
            q_scale: q,
        };
        let race = Race::new(&LocalSettings::default(), e(1.0), e(4.0), 1, 1).unwrap();
        let q = |i: usize| {
            race.racers[i].runner.tuner().config().top().parameters[0].process_noise_per_mv
        };
        assert!((q(1) - 4.0 * q(0)).abs() < 1e-12 && q(0) > 0.0);
        assert_eq!(
            estimator_label(EstimatorKind::Oracle),
            "oracle (knows the true device; reference only)"
        );
        assert_eq!(estimator_label(EstimatorKind::Kalman), "kalman");
    }
}
