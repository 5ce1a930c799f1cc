//! In-browser mode: the tuner and the simulated double dot from `spintune`
//! run inside the page (no server). The loop yields to the browser between
//! iterations so the page stays responsive.

use leptos::prelude::*;
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::estimator::EstimatorKind;
use spintune::parameter::Tolerance;

use crate::charts;
use crate::model::History;
use crate::ui::{Area, Chart, Dashboard};

/// What the student can choose.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalSettings {
    /// Gradient estimator of the qubit level.
    pub estimator: EstimatorKind,
    /// Process noise σ of the t_sr gradient, ns/mV per mV of step (Q = σ² I).
    pub q_tsr: f64,
    /// Process noise σ of the w gradient, µV/mV per mV of step.
    pub q_w: f64,
    /// Factor on the simulator's white measurement noise (1 = default device).
    pub noise_scale: f64,
    /// Step limit of the Newton solver, mV.
    pub max_step_mv: f64,
    /// Device RNG seed.
    pub seed: u64,
    /// Target t_sr, ns.
    pub target_tsr: f64,
    /// Target w, µV.
    pub target_w: f64,
    /// Relative tolerance of both targets (0.1 = ±10 %).
    pub tolerance: f64,
    /// Iteration limit of a run.
    pub max_iterations: u64,
    /// Pause between iterations, ms (0 still yields to the browser).
    pub delay_ms: u32,
    /// Cycle the paper's set points (21 iterations each) instead of fixed targets.
    pub paper_cycle: bool,
}

impl Default for LocalSettings {
    fn default() -> Self {
        Self {
            estimator: EstimatorKind::Kalman,
            q_tsr: 0.075,
            q_w: 0.3,
            noise_scale: 1.0,
            max_step_mv: 10.0,
            seed: 1,
            target_tsr: 20.0,
            target_w: 270.0,
            tolerance: 0.1,
            max_iterations: 150,
            delay_ms: 150,
            paper_cycle: false,
        }
    }
}

impl LocalSettings {
    /// The simulation config: the paper's setup with these choices applied.
    pub fn to_config(&self) -> SimulationConfig {
        let mut cfg = SimulationConfig::paper_default();
        cfg.name = "in-browser".into();
        cfg.seed = self.seed;
        cfg.tuner.max_iterations = Some(self.max_iterations);
        let noise = &mut cfg.device.noise;
        noise.white_sd *= self.noise_scale;
        noise.white_mu *= self.noise_scale;
        noise.white_w *= self.noise_scale;
        noise.white_tsr *= self.noise_scale;
        let top = cfg.tuner.top_mut();
        top.estimator = self.estimator;
        top.solver.max_step_mv = self.max_step_mv;
        for p in &mut top.parameters {
            match p.name.as_str() {
                "t_sr" => {
                    p.process_noise_per_mv = self.q_tsr;
                    p.target = Some(self.target_tsr);
                    p.tolerance = Tolerance::Relative(self.tolerance);
                }
                "w" => {
                    p.process_noise_per_mv = self.q_w;
                    p.target = Some(self.target_w);
                    p.tolerance = Tolerance::Relative(self.tolerance);
                }
                _ => {}
            }
        }
        if self.paper_cycle {
            // The paper's Fig. 3: the targets above are replaced at iterations 0, 21, 42, …
            cfg.tuner.schedule = spintune::benchmark::paper_schedule(21);
        }
        cfg
    }

    /// A fresh run with these settings.
    pub fn build(&self) -> Result<SimulationRun, String> {
        SimulationRun::new(self.to_config()).map_err(|e| e.to_string())
    }
}

/// Ground truth on a 2-D voltage grid, for the heat map.
#[derive(Debug, Clone, PartialEq)]
pub struct Landscape {
    /// Gate on the x axis.
    pub gx: String,
    /// Gate on the y axis.
    pub gy: String,
    /// Grid voltages on x, mV.
    pub xs: Vec<f64>,
    /// Grid voltages on y, mV.
    pub ys: Vec<f64>,
    /// Row-major (y, x) distance to target in tolerance units.
    pub error: Vec<f64>,
    /// The run's path in this plane, mV.
    pub path: Vec<(f64, f64)>,
    /// Present voltages, mV.
    pub now: (f64, f64),
}

/// Drives a [`SimulationRun`] and collects its records.
pub struct LocalRunner {
    run: SimulationRun,
    /// Iterations so far.
    pub history: History,
    /// First iteration at which every parameter was in band since the last target change.
    pub tuned_at: Option<u64>,
    /// Iteration of the last target change.
    pub targets_since: u64,
    /// The run has ended (iteration limit).
    pub finished: bool,
}

impl LocalRunner {
    /// Start from settings.
    pub fn new(settings: &LocalSettings) -> Result<Self, String> {
        Ok(Self {
            run: settings.build()?,
            history: History::new(),
            tuned_at: None,
            targets_since: 0,
            finished: false,
        })
    }

    /// One iteration. `Ok(false)` when the run has ended.
    pub fn step(&mut self) -> Result<bool, String> {
        if self.finished {
            return Ok(false);
        }
        match self.run.next_iteration().map_err(|e| e.to_string())? {
            Some(rec) => {
                if rec.tuned && self.tuned_at.is_none() && rec.iteration >= self.targets_since {
                    self.tuned_at = Some(rec.iteration);
                }
                self.history.push(rec);
                Ok(true)
            }
            None => {
                self.finished = true;
                Ok(false)
            }
        }
    }

    /// The simulator's noiseless truth on an `n`×`n` grid in the (`gx`, `gy`)
    /// plane, ±`half_mv` around the present voltages (other gates fixed):
    /// the larger of `|p − p*| / tolerance` over t_sr and w (≤ 1: in band).
    pub fn landscape(&self, gx: &str, gy: &str, half_mv: f64, n: usize) -> Option<Landscape> {
        let device = self.run.device();
        let v0 = device.voltages_mv().clone();
        let (cx, cy) = (*v0.get(gx)?, *v0.get(gy)?);
        let top = self.run.tuner().config().top();
        let band = |name: &str| {
            let p = top.parameters.iter().find(|p| p.name == name)?;
            let t = p.target?;
            Some((t, p.tolerance.half_width(t).max(1e-12)))
        };
        let (t_tsr, tol_tsr) = band("t_sr")?;
        let (t_w, tol_w) = band("w")?;
        let step = 2.0 * half_mv / (n.max(2) - 1) as f64;
        let xs: Vec<f64> = (0..n).map(|i| cx - half_mv + step * i as f64).collect();
        let ys: Vec<f64> = (0..n).map(|j| cy - half_mv + step * j as f64).collect();
        let mut probe = device.clone();
        let mut error = vec![f64::NAN; n * n];
        for (j, y) in ys.iter().enumerate() {
            for (i, x) in xs.iter().enumerate() {
                let set = spintune::protocol::Request::SetVoltages {
                    voltages_mv: [(gx.to_string(), *x), (gy.to_string(), *y)].into(),
                };
                if let spintune::protocol::Response::VoltagesSet { .. } = probe.execute(&set) {
                    let t = probe.truth();
                    error[j * n + i] =
                        ((t.t_sr_ns - t_tsr).abs() / tol_tsr).max((t.w_uv - t_w).abs() / tol_w);
                }
            }
        }
        let path = self
            .history
            .records()
            .iter()
            .filter_map(|r| Some((*r.voltages_mv.get(gx)?, *r.voltages_mv.get(gy)?)))
            .collect();
        Some(Landscape {
            gx: gx.to_string(),
            gy: gy.to_string(),
            xs,
            ys,
            error,
            path,
            now: (cx, cy),
        })
    }

    /// Change both targets (and tolerance) of the running tuner.
    pub fn set_targets(&mut self, t_sr: f64, w: f64, tolerance: f64) -> Result<(), String> {
        let tol = Some(Tolerance::Relative(tolerance));
        let tuner = self.run.tuner_mut();
        tuner
            .set_target("t_sr", Some(t_sr), tol)
            .map_err(|e| e.to_string())?;
        tuner
            .set_target("w", Some(w), tol)
            .map_err(|e| e.to_string())?;
        self.tuned_at = None;
        self.targets_since = self.history.next_iteration();
        Ok(())
    }
}

/// A labelled numeric input bound to a field of the settings.
#[component]
fn NumberField(
    label: &'static str,
    unit: &'static str,
    testid: &'static str,
    step: &'static str,
    get: Signal<f64>,
    set: Callback<f64>,
) -> impl IntoView {
    view! {
        <label class="field">
            <span class="field-label">{label}</span>
            <span class="field-input">
                <input type="number" step=step data-testid=testid
                    prop:value=move || get.get().to_string()
                    on:change=move |ev| {
                        if let Ok(v) = event_target_value(&ev).trim().parse::<f64>() {
                            if v.is_finite() { set.run(v) }
                        }
                    } />
                <span class="unit">{unit}</span>
            </span>
        </label>
    }
}

/// The teaching demo.
#[component]
pub fn LocalMode() -> impl IntoView {
    let settings = RwSignal::new(LocalSettings::default());
    let history = RwSignal::new(History::new());
    let running = RwSignal::new(false);
    let status = RwSignal::new(String::from("ready: press Run"));
    let tuned_at = RwSignal::new(None::<u64>);
    let error = RwSignal::new(None::<String>);
    let runner = StoredValue::new_local(None::<LocalRunner>);
    let generation = StoredValue::new(0u64);

    let sync = move || {
        runner.with_value(|r| {
            if let Some(r) = r {
                history.set(r.history.clone());
                tuned_at.set(r.tuned_at);
            }
        })
    };
    let ensure = move || -> bool {
        if runner.with_value(|r| r.is_some()) {
            return true;
        }
        match LocalRunner::new(&settings.get_untracked()) {
            Ok(r) => {
                runner.set_value(Some(r));
                error.set(None);
                true
            }
            Err(e) => {
                error.set(Some(format!("invalid settings: {e}")));
                false
            }
        }
    };
    // One iteration; false when the loop must stop.
    let step_once = move || -> bool {
        if !ensure() {
            return false;
        }
        let res = runner
            .try_update_value(|r| r.as_mut().map(|r| r.step()))
            .flatten();
        match res {
            Some(Ok(true)) => {
                sync();
                true
            }
            Some(Ok(false)) => {
                status.set("finished: iteration limit reached (Reset to start again)".into());
                false
            }
            Some(Err(e)) => {
                error.set(Some(e));
                false
            }
            None => false,
        }
    };
    let run = move || {
        if running.get_untracked() {
            return;
        }
        running.set(true);
        status.set("running".into());
        generation.update_value(|g| *g += 1);
        let my_gen = generation.get_value();
        leptos::task::spawn_local(async move {
            loop {
                // Yield first: lets the page paint between iterations.
                let delay = settings.try_with_untracked(|s| s.delay_ms).unwrap_or(0);
                gloo_timers::future::TimeoutFuture::new(delay).await;
                let alive = running.try_get_untracked().unwrap_or(false)
                    && generation.try_get_value() == Some(my_gen);
                if !alive {
                    break;
                }
                if !step_once() {
                    let _ = running.try_set(false);
                    break;
                }
            }
        });
    };
    let pause = move || {
        running.set(false);
        status.set("paused".into());
    };
    let step = move || {
        pause();
        if step_once() {
            status.set("paused after a single step".into());
        }
    };
    let reset = move || {
        running.set(false);
        generation.update_value(|g| *g += 1);
        runner.set_value(None);
        history.set(History::new());
        tuned_at.set(None);
        error.set(None);
        status.set("ready: press Run".into());
    };
    let apply_targets = move || {
        let s = settings.get_untracked();
        let res = runner
            .try_update_value(|r| {
                r.as_mut()
                    .map(|r| r.set_targets(s.target_tsr, s.target_w, s.tolerance))
            })
            .flatten();
        match res {
            Some(Err(e)) => error.set(Some(e)),
            _ => {
                tuned_at.set(None);
                status.set(if running.get_untracked() {
                    "running (new targets)".into()
                } else {
                    "new targets set".into()
                });
            }
        }
    };

    macro_rules! field {
        ($f:ident) => {
            (
                Signal::derive(move || settings.with(|s| s.$f as f64)),
                Callback::new(move |v: f64| settings.update(|s| s.$f = v as _)),
            )
        };
    }
    let (q_tsr, set_q_tsr) = field!(q_tsr);
    let (q_w, set_q_w) = field!(q_w);
    let (noise, set_noise) = field!(noise_scale);
    let (max_step, set_max_step) = field!(max_step_mv);
    let (seed, set_seed) = field!(seed);
    let (t_tsr, set_t_tsr) = field!(target_tsr);
    let (t_w, set_t_w) = field!(target_w);
    let (tol, set_tol) = field!(tolerance);
    let (delay, set_delay) = field!(delay_ms);
    let (max_it, set_max_it) = field!(max_iterations);

    let tuned_text = move || match tuned_at.get() {
        Some(k) => format!("tuned at iteration {k}"),
        None => "not tuned yet".into(),
    };
    view! {
        <div class="mode-local">
            <aside class="sidebar">
                <h2>"Simulated double dot"</h2>
                <div class="buttons">
                    <button class="primary" data-testid="local-run" disabled=move || running.get() on:click=move |_| run()>"Run"</button>
                    <button data-testid="local-pause" disabled=move || !running.get() on:click=move |_| pause()>"Pause"</button>
                    <button data-testid="local-step" on:click=move |_| step()>"Step"</button>
                    <button data-testid="local-reset" on:click=move |_| reset()>"Reset"</button>
                </div>
                <p class="local-status" data-testid="local-status">{move || status.get()} " · " <b data-testid="local-tuned">{tuned_text}</b></p>
                {move || error.get().map(|e| view! { <p class="error" data-testid="local-error">{e}</p> })}
                <fieldset>
                    <legend>"Targets (apply any time)"</legend>
                    <NumberField label="t_sr target" unit="ns" testid="local-target-tsr" step="1" get=t_tsr set=set_t_tsr />
                    <NumberField label="w target" unit="µV" testid="local-target-w" step="5" get=t_w set=set_t_w />
                    <NumberField label="tolerance" unit="× target" testid="local-tolerance" step="0.01" get=tol set=set_tol />
                    <button data-testid="local-apply-targets" on:click=move |_| apply_targets()>"Apply targets"</button>
                </fieldset>
                <fieldset>
                    <legend>"Tuner and device (apply on Reset)"</legend>
                    <label class="field">
                        <span class="field-label">"estimator"</span>
                        <select data-testid="local-estimator" on:change=move |ev| {
                            if let Some(k) = EstimatorKind::from_name(&event_target_value(&ev)) {
                                settings.update(|s| s.estimator = k);
                            }
                        }>
                            {EstimatorKind::ALL.into_iter().map(|k| view! {
                                <option value=k.name() selected=move || settings.with(|s| s.estimator == k)>{k.name()}</option>
                            }).collect_view()}
                        </select>
                    </label>
                    <NumberField label="Q σ of ∂t_sr/∂V" unit="ns/mV per mV" testid="local-q-tsr" step="0.005" get=q_tsr set=set_q_tsr />
                    <NumberField label="Q σ of ∂w/∂V" unit="µV/mV per mV" testid="local-q-w" step="0.05" get=q_w set=set_q_w />
                    <NumberField label="measurement noise" unit="× default" testid="local-noise" step="0.25" get=noise set=set_noise />
                    <NumberField label="step limit" unit="mV" testid="local-max-step" step="1" get=max_step set=set_max_step />
                    <NumberField label="seed" unit="" testid="local-seed" step="1" get=seed set=set_seed />
                    <NumberField label="iteration limit" unit="" testid="local-max-iterations" step="10" get=max_it set=set_max_it />
                    <NumberField label="pause between iterations" unit="ms" testid="local-delay" step="50" get=delay set=set_delay />
                    <label class="field">
                        <input type="checkbox" data-testid="local-paper-cycle"
                            prop:checked=move || settings.with(|s| s.paper_cycle)
                            on:change=move |ev| settings.update(|s| s.paper_cycle = event_target_checked(&ev)) />
                        <span class="field-label">"cycle the paper's set points (21 iterations each, as in its Fig. 3)"</span>
                    </label>
                </fieldset>
                <Explanation />
            </aside>
            <section class="main">
                <Dashboard history=history />
                <h3>"Simulator ground truth " <small>"(what the tuner cannot see)"</small></h3>
                <div class="grid2">
                    <Chart
                        name="landscape"
                        height=340
                        draw=move |a: &Area| {
                            let n = history.with(|h| h.len());
                            let land = runner.with_value(|r| r.as_ref().and_then(|r| r.landscape("SB", "T", 30.0, 25)));
                            charts::draw_landscape(a, land.as_ref()).map(|_| n)
                        }
                    />
                    <div class="explain landscape-text">
                        <p><b>"Heat map."</b>" Colour: how far the true t_sr and w are from their targets, in units of the tolerance (the larger of the two), when only V_SB and V_T are changed from the present voltages. Inside the green region both parameters are in band."</p>
                        <p>"The line is the tuner's path projected onto this plane (it also moves N and SA, so the map shifts as it goes). Light cells are far from the goal; the step limit keeps every move short because the map is curved: gradients measured here are wrong a few tens of mV away."</p>
                    </div>
                </div>
            </section>
        </div>
    }
}

/// What the student is looking at.
#[component]
fn Explanation() -> impl IntoView {
    view! {
        <details class="explain" open>
            <summary>"What am I looking at?"</summary>
            <p>"The tuner moves four gate voltages (N, SA, SB, T) until the reload time "<i>"t_sr"</i>" and the inter-dot transition width "<i>"w"</i>" sit inside their tolerance bands (green)."</p>
            <p><b>"Gradient."</b>" Each panel of the gradient plot is one element of the Jacobian: how much a parameter changes per mV on one gate. The tuner never measures it directly after the start; a Kalman filter infers it from how the parameters responded to each step."</p>
            <p><b>"Error bars."</b>" ±1σ is the square root of the filter's covariance diagonal: how unsure the filter is. Steps shrink it along the direction moved; the process noise Q grows it again every iteration, so the filter keeps learning when the device changes. Large Q: fast but jumpy; tiny Q: smooth but slow to notice a changed gradient. Broyden has no noise model (no error bars); fixed-jacobian never learns."</p>
            <p><b>"Step limit."</b>" The gradient is only valid near the present voltages (tunnel couplings depend exponentially on them), so each Newton step is cut to a maximal length, as in the paper (10 mV). Larger limits converge faster when the model is right and overshoot when it is not."</p>
            <p><b>"Noise."</b>" Each parameter comes from a fit to a noisy raw scan (bottom). More noise means larger measurement error bars and a filter that trusts each measurement less."</p>
        </details>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn paper_cycle_switches_targets_at_iteration_21() {
        let settings = LocalSettings {
            paper_cycle: true,
            max_iterations: 22,
            ..LocalSettings::default()
        };
        assert_eq!(settings.to_config().tuner.schedule.len(), 5);
        let mut run = settings.build().unwrap();
        let mut records = Vec::new();
        while let Some(r) = run.next_iteration().unwrap() {
            records.push(r);
        }
        let t_sr_target = |k: usize| {
            records[k]
                .parameters
                .iter()
                .find(|p| p.name == "t_sr")
                .unwrap()
                .target
        };
        assert_eq!(t_sr_target(20), Some(20.0));
        assert_eq!(t_sr_target(21), Some(70.0));
    }
}
