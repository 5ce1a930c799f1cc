//! Teaching: two estimators race on the same seeded simulated device.
//!
//! Both racers are [`LocalRunner`]s built from the same [`LocalSettings`]
//! (same seed, device, targets, step limit) except the estimator (and its
//! process noise, so two Q settings can race too). [`Race::step`] advances
//! each racer that is still going by one iteration; a racer is *done* once
//! it is tuned (every parameter in band) or its run is over. The outcome of
//! each is its iterations-to-target and the lab time it took, minutes.

use leptos::prelude::*;
use spintune::estimator::EstimatorKind;

use super::runner::LocalRunner;
use super::settings::LocalSettings;
use crate::charts;
use crate::history::RunHistory;
use crate::series::{self, Drawn, Frame, XAxis};
use crate::ui::{Area, Chart};
use crate::zoom::View;

/// One contestant's choices.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    /// Gradient estimator.
    pub estimator: EstimatorKind,
    /// Factor on both parameters' process noise σ (1 = the settings' Q).
    pub q_scale: f64,
}

/// How a racer did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// Iterations run so far.
    pub iterations: u64,
    /// First iteration with every parameter in band.
    pub tuned_at: Option<u64>,
    /// Lab time until then (or so far), minutes.
    pub lab_minutes: f64,
    /// Tuned, or the run is over.
    pub done: bool,
}

/// One contestant.
pub struct Racer {
    /// What it runs.
    pub entry: Entry,
    /// The run.
    pub runner: LocalRunner,
}

impl Racer {
    fn outcome(&self) -> Outcome {
        let h = &self.runner.history;
        let tuned_at = self.runner.tuned_at;
        let lab_s = match tuned_at {
            Some(k) => h
                .records()
                .iter()
                .find(|r| r.iteration == k)
                .map_or(0.0, |r| r.lab_seconds),
            None => h.last().map_or(0.0, |r| r.lab_seconds),
        };
        Outcome {
            iterations: h.len() as u64,
            tuned_at,
            lab_minutes: lab_s / 60.0,
            done: tuned_at.is_some() || !self.runner.is_advancing(),
        }
    }
}

/// Two racers on the same device.
pub struct Race {
    /// The two contestants, A and B.
    pub racers: [Racer; 2],
}

impl Race {
    /// A race between `a` and `b` with the shared `settings` (seed, device, targets).
    pub fn new(settings: &LocalSettings, a: Entry, b: Entry) -> Result<Self, String> {
        let build = |e: Entry| -> Result<Racer, String> {
            let s = LocalSettings {
                estimator: e.estimator,
                q_tsr: settings.q_tsr * e.q_scale,
                q_w: settings.q_w * e.q_scale,
                paper_cycle: false,
                ..settings.clone()
            };
            Ok(Racer {
                entry: e,
                runner: LocalRunner::new(&s)?,
            })
        };
        Ok(Self {
            racers: [build(a)?, build(b)?],
        })
    }

    /// One iteration of every racer not yet done; whether any advanced.
    pub fn step(&mut self) -> Result<bool, String> {
        let mut any = false;
        for r in &mut self.racers {
            if r.outcome().done {
                continue;
            }
            match r.runner.advance() {
                Ok(Some(_)) => any = true,
                Ok(None) => {}
                Err(e) => return Err(e.to_string()),
            }
        }
        Ok(any)
    }

    /// Both outcomes (A, B).
    pub fn outcomes(&self) -> [Outcome; 2] {
        [self.racers[0].outcome(), self.racers[1].outcome()]
    }

    /// Whether both are done.
    pub fn done(&self) -> bool {
        self.outcomes().iter().all(|o| o.done)
    }
}

/// A racer's result line: "tuned at iteration 23 · 41.2 lab min" or progress.
pub fn outcome_text(o: &Outcome) -> String {
    match o.tuned_at {
        Some(k) => format!("tuned at iteration {k} · {:.1} lab min", o.lab_minutes),
        None if o.done => format!(
            "not tuned in {} iterations · {:.1} lab min",
            o.iterations, o.lab_minutes
        ),
        None => format!(
            "racing… iteration {} · {:.1} lab min",
            o.iterations, o.lab_minutes
        ),
    }
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
                    <option value=k.name() selected=move || sel.with(|e| e.estimator == k)>{k.name()}</option>
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

/// The race panel of the in-browser mode: choose two estimators, race them on
/// the device of the sidebar's settings, see both side by side.
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
    let race = StoredValue::new_local(None::<Race>);
    let outcomes = RwSignal::new(None::<[Outcome; 2]>);
    let histories = [
        RwSignal::new(RunHistory::new()),
        RwSignal::new(RunHistory::new()),
    ];
    let overlay_b = RwSignal::new(None::<RunHistory>);
    let error = RwSignal::new(None::<String>);
    let generation = StoredValue::new(0u64);
    let sync = move || {
        race.with_value(|r| {
            let Some(r) = r else { return };
            for (i, h) in histories.iter().enumerate() {
                let src = &r.racers[i].runner.history;
                let n = h.with_untracked(|h| h.len());
                if src.len() > n {
                    h.update(|h| {
                        h.insert(src.records()[n..].iter().cloned());
                    });
                }
            }
            outcomes.set(Some(r.outcomes()));
        });
        overlay_b.set(Some(histories[1].get_untracked()));
    };
    let start = move || {
        generation.update_value(|g| *g += 1);
        let my = generation.get_value();
        match Race::new(
            &settings.get_untracked(),
            a.get_untracked(),
            b.get_untracked(),
        ) {
            Ok(r) => {
                race.set_value(Some(r));
                error.set(None);
            }
            Err(e) => {
                error.set(Some(e));
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
                let res = race
                    .try_update_value(|r| r.as_mut().map(|r| r.step().map(|any| any && !r.done())))
                    .flatten();
                sync();
                match res {
                    Some(Ok(true)) => {}
                    Some(Err(e)) => {
                        error.set(Some(e));
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
                <b>{move || format!("{} {} (Q σ × {})", if i == 0 { "A" } else { "B" }, entry.with(|e| e.estimator.name()), entry.with(|e| e.q_scale))}</b>
                " — "
                <span>{move || outcomes.with(|o| o.map_or_else(|| "press Race".to_string(), |o| outcome_text(&o[i])))}</span>
            </div>
        }
    };
    let param_chart = move |p: usize, name: &'static str| {
        view! {
            <Chart
                name=format!("race-{name}")
                height=240
                key=move || vec![histories[0].with(|h| h.version()), overlay_b.with(|o| o.as_ref().map_or(0, |h| h.version()))]
                draw=move |ar: &Area| {
                    let ov = overlay_b.read();
                    histories[0].with(|h| {
                        let (lo, hi) = match (h.extent(), ov.as_ref().and_then(|o| o.extent())) {
                            (Some(x), Some(y)) => (x.0.min(y.0), x.1.max(y.1)),
                            (Some(x), None) | (None, Some(x)) => x,
                            (None, None) => (0, 10),
                        };
                        let w = View::All.window(lo as f64, hi as f64);
                        series::draw_parameter(ar, &Frame { history: h, window: w, axis: XAxis::Iteration, overlay: ov.as_ref() }, p, 0)
                    })
                }
            />
        }
    };
    view! {
        <section class="race" data-testid="race">
            <h3>"Race two estimators " <small>"(same seed, device, targets and step limit as the sidebar)"</small></h3>
            <div class="race-controls">
                {estimator_select("A", "race-estimator-a", a)}
                {estimator_select("B", "race-estimator-b", b)}
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
                    <div class="legend"><span><i class="swatch a"></i>"A"</span><span><i class="swatch overlay"></i>"B"</span><span><i class="swatch target"></i>"target"</span><span><i class="swatch band"></i>"tolerance band"</span></div>
                </div>
                <div class="chart-box">
                    {param_chart(1, "w")}
                    <div class="legend"><span><i class="swatch a"></i>"A"</span><span><i class="swatch overlay"></i>"B"</span><span><i class="swatch target"></i>"target"</span><span><i class="swatch band"></i>"tolerance band"</span></div>
                </div>
            </div>
            <div class="chart-box">
                <Chart
                    name="race-landscape"
                    height=340
                    key=move || vec![histories[0].with(|h| h.version()), histories[1].with(|h| h.version())]
                    draw=move |ar: &Area| {
                        let n = histories[0].with(|h| h.len()) + histories[1].with(|h| h.len());
                        let (land, other) = race.with_value(|r| match r {
                            Some(r) => (
                                r.racers[0].runner.landscape("SB", "T", 30.0, 25),
                                r.racers[1].runner.landscape_path("SB", "T"),
                            ),
                            None => (None, Vec::new()),
                        });
                        charts::draw_landscape(ar, land.as_ref(), &other).map(|_| Drawn { iterations: n, ..Drawn::default() })
                    }
                />
                <div class="legend"><span><i class="swatch path-a"></i>"path of A"</span><span><i class="swatch path-b"></i>"path of B"</span><span>"colour: distance to target in tolerance units (at A's present voltages)"</span></div>
            </div>
        </section>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn kalman_and_broyden_race_on_the_same_device() {
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
        let mut race = Race::new(&settings, kalman, broyden).unwrap();
        assert!(!race.done());
        assert!(race.step().unwrap());
        // Same seeded device, same start: iteration 0 measured at the same voltages.
        let first = |i: usize| race.racers[i].runner.history.records()[0].clone();
        assert_eq!(first(0).voltages_mv, first(1).voltages_mv);
        assert_eq!(
            race.racers[0].runner.run().tuner().config().top().estimator,
            EstimatorKind::Kalman
        );
        assert_eq!(
            race.racers[1].runner.run().tuner().config().top().estimator,
            EstimatorKind::Broyden
        );
        while race.step().unwrap() {}
        assert!(race.done());
        let [a, b] = race.outcomes();
        eprintln!("race outcomes: A {a:?}, B {b:?}");
        let k = a
            .tuned_at
            .expect("Kalman reaches the target within 80 iterations");
        assert!(k < 60, "{a:?}");
        assert!(a.lab_minutes > 0.0 && b.lab_minutes > 0.0);
        // A done racer is not advanced: A stopped at its tuned iteration.
        assert_eq!(a.iterations, k + 1);
        assert!(outcome_text(&a).starts_with(&format!("tuned at iteration {k} · ")));
        assert!(outcome_text(&a).ends_with("lab min"));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn two_q_settings_race_too() {
        let e = |q| Entry {
            estimator: EstimatorKind::Kalman,
            q_scale: q,
        };
        let race = Race::new(&LocalSettings::default(), e(1.0), e(4.0)).unwrap();
        let q = |i: usize| {
            race.racers[i]
                .runner
                .run()
                .tuner()
                .config()
                .top()
                .parameters[0]
                .process_noise_per_mv
        };
        assert!((q(1) - 4.0 * q(0)).abs() < 1e-12 && q(0) > 0.0);
    }
}
