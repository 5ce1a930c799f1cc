//! In-browser mode: the run session and the simulated double dot from
//! `spintune` run inside the page (no server).
//!
//! The page is a thin driver of [`SimulationRun`]: pause, resume, single
//! step, stop and target changes are [`ControlCommand`]s applied by the run
//! session, which owns the run's status. The page keeps only its animation
//! timer: each tick asks for the next iteration while the session is running
//! or stepping, and yields to the browser in between so the page stays
//! responsive.

use leptos::prelude::*;
use spintune::driver::{RunError, SimulationConfig, SimulationRun};
use spintune::estimator::EstimatorKind;
use spintune::parameter::Tolerance;
use spintune::protocol::{ControlCommand, IterationRecord, RunStatus};

use crate::charts;
use crate::history::RunHistory;

use crate::model::{ControlsEnabled, History};
use crate::series::Drawn;
use crate::ui::{Area, Chart, Dashboard, StatusBadge, StatusNote};

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
    /// Virtual-gate matrix of the qubit level (rows PA, PB; columns N, SA,
    /// SB, T; mV of plunger per mV of gate), as a lab would write it down.
    pub compensation: Vec<Vec<f64>>,
    /// Its relative 1σ uncertainty (0.2 = 20 %).
    pub compensation_uncertainty: f64,
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
            compensation: crate::compensation::default_matrix(),
            compensation_uncertainty: 0.2,
        }
    }
}

impl LocalSettings {
    /// The simulation config: the paper's setup with these choices applied
    /// (an invalid virtual-gate matrix is refused, naming the cell).
    pub fn try_config(&self) -> Result<SimulationConfig, String> {
        self.to_config()
            .with_compensation(self.compensation.clone(), self.compensation_uncertainty)
            .map_err(|e| format!("virtual-gate matrix: {e}"))
    }

    /// The simulation config: the paper's setup with these choices applied
    /// (not validated: see [`LocalSettings::try_config`]).
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
        if let Some(c) = &mut top.compensation {
            c.matrix = self.compensation.clone();
            c.relative_uncertainty = self.compensation_uncertainty;
        }
        if self.paper_cycle {
            // The paper's Fig. 3: the targets above are replaced at iterations 0, 21, 42, …
            cfg.tuner.schedule = spintune::benchmark::paper_schedule(21);
        }
        cfg
    }

    /// A fresh run with these settings.
    pub fn build(&self) -> Result<SimulationRun, String> {
        SimulationRun::new(self.try_config()?).map_err(|e| e.to_string())
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

/// Drives a [`SimulationRun`] and collects its records. Every change of
/// the run's course goes through the session ([`LocalRunner::control`]).
pub struct LocalRunner {
    run: SimulationRun,
    /// Iterations so far.
    pub history: History,
    /// First iteration at which every parameter was in band since the targets
    /// last changed (by the user or by the schedule).
    pub tuned_at: Option<u64>,
}

impl LocalRunner {
    /// Start from settings (the session starts running).
    pub fn new(settings: &LocalSettings) -> Result<Self, String> {
        Ok(Self::from_run(settings.build()?))
    }

    /// Drive an existing run (e.g. one with a specially prepared device).
    pub fn from_run(run: SimulationRun) -> Self {
        Self {
            run,
            history: History::new(),
            tuned_at: None,
        }
    }

    /// The run.
    pub fn run(&self) -> &SimulationRun {
        &self.run
    }

    /// The session's status.
    pub fn status(&self) -> RunStatus {
        self.run.session().status()
    }

    /// Whether the session wants iterations (running or stepping): the
    /// animation timer ticks only then.
    pub fn is_advancing(&self) -> bool {
        matches!(self.status(), RunStatus::Running | RunStatus::Stepping)
    }

    /// One tick of the animation: [`SimulationRun::next_iteration`], with the
    /// record kept. `Ok(Some(k))`: iteration `k` was recorded; `Ok(None)`: the
    /// run is over (finished or stopped); `Err(RunError::Paused)`: paused
    /// (also after a single step); `Err(RunError::Fault(_))`: the session
    /// paused the run with a fault (resumable).
    pub fn advance(&mut self) -> Result<Option<u64>, RunError> {
        let Some(rec) = self.run.next_iteration()? else {
            return Ok(None);
        };
        let k = rec.iteration;
        self.record(rec);
        Ok(Some(k))
    }

    fn record(&mut self, rec: IterationRecord) {
        let targets = |r: &IterationRecord| {
            r.parameters
                .iter()
                .map(|p| (p.target, p.tolerance))
                .collect::<Vec<_>>()
        };
        if self
            .history
            .last()
            .is_some_and(|prev| targets(prev) != targets(&rec))
        {
            self.tuned_at = None;
        }
        if rec.tuned && self.tuned_at.is_none() {
            self.tuned_at = Some(rec.iteration);
        }
        self.history.push(rec);
    }

    /// Apply a control command through the session; the new status, or why
    /// the session refused it (nothing changed then).
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, String> {
        self.run.control(command).map_err(|e| e.to_string())
    }

    /// Change both targets (and the relative tolerance) through the session
    /// (they apply from the next iteration). Both are checked before either
    /// is applied.
    pub fn set_targets(&mut self, t_sr: f64, w: f64, tolerance: f64) -> Result<RunStatus, String> {
        let tolerance = Some(Tolerance::Relative(tolerance));
        let changes = [("t_sr", t_sr), ("w", w)];
        for (parameter, target) in changes {
            self.run
                .tuner()
                .validate_target(parameter, Some(target), tolerance)
                .map_err(|e| e.to_string())?;
        }
        for (parameter, target) in changes {
            self.control(&ControlCommand::SetTarget {
                parameter: parameter.into(),
                target: Some(target),
                tolerance,
            })?;
        }
        self.tuned_at = None;
        Ok(self.status())
    }

    /// The run's path in the (`gx`, `gy`) plane, mV.
    pub fn landscape_path(&self, gx: &str, gy: &str) -> Vec<(f64, f64)> {
        self.history
            .records()
            .iter()
            .filter_map(|r| Some((*r.voltages_mv.get(gx)?, *r.voltages_mv.get(gy)?)))
            .collect()
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
        let path = self.landscape_path(gx, gy);
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
}

/// A labelled numeric input bound to a field of the settings.
#[component]
pub(crate) fn NumberField(
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
    let history = RwSignal::new(RunHistory::new());
    // Mirror of the session's status after each action (None: no run yet).
    let status = RwSignal::new(None::<RunStatus>);
    let tuned_at = RwSignal::new(None::<u64>);
    let error = RwSignal::new(None::<String>);
    let note = RwSignal::new(None::<String>);
    let runner = StoredValue::new_local(None::<LocalRunner>);
    // The animation timer: whether a tick loop is alive, and which run it belongs to.
    let ticking = StoredValue::new(false);
    let generation = StoredValue::new(0u64);

    // Copy what changed in the runner into the signals.
    let sync = move || {
        runner.with_value(|r| {
            let Some(r) = r else { return };
            let known = history.with_untracked(|h| h.len());
            if r.history.len() != known {
                history.update(|h| {
                    if h.len() > r.history.len() {
                        h.clear();
                    }
                    let n = h.len();
                    h.insert(r.history.records()[n..].iter().cloned());
                    h.set_total(r.history.len() as u64);
                });
            }
            if tuned_at.get_untracked() != r.tuned_at {
                tuned_at.set(r.tuned_at);
            }
            let s = Some(r.status());
            if status.with_untracked(|old| *old != s) {
                status.set(s);
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
    // A command for the session; a refusal is shown, nothing else changes.
    let command = move |c: ControlCommand| {
        let res = runner
            .try_update_value(|r| r.as_mut().map(|r| r.control(&c)))
            .flatten();
        match res {
            Some(Err(e)) => error.set(Some(e)),
            Some(Ok(_)) => error.set(None),
            None => {}
        }
        sync();
    };
    // One tick: the next iteration if the session wants one. Returns whether
    // the timer should keep ticking.
    let tick = move || -> bool {
        let res = runner
            .try_update_value(|r| r.as_mut().map(|r| r.advance()))
            .flatten();
        let broken = match res {
            None => return false,
            Some(Ok(Some(_))) => false,
            // over, paused (also after a single step) or faulted: the
            // session's status says which
            Some(Ok(None) | Err(RunError::Paused | RunError::Fault(_))) => false,
            // a bug in this driver: stop ticking rather than repeat it
            Some(Err(e @ RunError::Session(_))) => {
                error.set(Some(e.to_string()));
                true
            }
        };
        sync();
        !broken && runner.with_value(|r| r.as_ref().is_some_and(|r| r.is_advancing()))
    };
    // Start the animation timer unless it is running.
    let kick = move || {
        if ticking.get_value()
            || !runner.with_value(|r| r.as_ref().is_some_and(|r| r.is_advancing()))
        {
            return;
        }
        ticking.set_value(true);
        let my_gen = generation.get_value();
        leptos::task::spawn_local(async move {
            loop {
                // Yield first: lets the page paint between iterations.
                let delay = settings.try_with_untracked(|s| s.delay_ms).unwrap_or(0);
                gloo_timers::future::TimeoutFuture::new(delay).await;
                if generation.try_get_value() != Some(my_gen) {
                    // reset (or unmounted): a new run owns the timer
                    break;
                }
                if !tick() {
                    ticking.set_value(false);
                    break;
                }
            }
        });
    };
    let run = move || {
        note.set(None);
        if runner.with_value(|r| r.is_none()) {
            if !ensure() {
                return;
            }
            sync();
        } else {
            command(ControlCommand::Resume);
        }
        kick();
    };
    let pause = move || command(ControlCommand::Pause);
    let step = move || {
        note.set(None);
        if !ensure() {
            return;
        }
        command(ControlCommand::Step);
        kick();
    };
    let stop = move || command(ControlCommand::Stop);
    let reset = move || {
        generation.update_value(|g| *g += 1);
        ticking.set_value(false);
        runner.set_value(None);
        history.set(RunHistory::new());
        status.set(None);
        tuned_at.set(None);
        error.set(None);
        note.set(None);
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
            Some(Ok(_)) => {
                error.set(None);
                note.set(Some(
                    "new targets: they apply from the next iteration".into(),
                ));
            }
            None => note.set(Some("targets set: the run starts with them".into())),
        }
        sync();
    };
    let enabled = Memo::new(move |_| {
        status.with(|s| match s {
            // no run yet: Run and Step start one
            None => ControlsEnabled {
                pause: false,
                resume: true,
                step: true,
                stop: false,
                targets: true,
                accept_positions: false,
            },
            Some(s) => ControlsEnabled::for_status(s),
        })
    });
    let started = move || status.with(|s| s.is_some());

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
                    <button class="primary" data-testid="local-run" disabled=move || !enabled.get().resume on:click=move |_| run()>
                        {move || if started() { "Resume" } else { "Run" }}
                    </button>
                    <button data-testid="local-pause" disabled=move || !enabled.get().pause on:click=move |_| pause()>"Pause"</button>
                    <button data-testid="local-step" disabled=move || !enabled.get().step on:click=move |_| step()>"Step"</button>
                    <button class="danger" data-testid="local-stop" disabled=move || !enabled.get().stop on:click=move |_| stop()>"Stop"</button>
                    <button data-testid="local-reset" on:click=move |_| reset()>"Reset"</button>
                    // Only for a run faulted because gates moved (the simulator
                    // does not move gates by itself; the rule is the live mode's).
                    <Show when=move || enabled.get().accept_positions>
                        <button data-testid="local-accept-positions" on:click=move |_| command(ControlCommand::AcceptPositions)>"Accept positions"</button>
                    </Show>
                </div>
                <p class="local-status" data-testid="local-status">
                    {move || if started() {
                        view! { <StatusBadge status=status testid="local-state" unknown="" /> }.into_any()
                    } else {
                        view! { <span class="status status-ready" data-state="ready" data-testid="local-state">"ready: press Run"</span> }.into_any()
                    }}
                    " · " <b data-testid="local-tuned">{tuned_text}</b>
                </p>
                <StatusNote status=status />
                {move || error.get().map(|e| view! { <p class="error" data-testid="local-error">{e}</p> })}
                {move || note.get().map(|n| view! { <p class="hint" data-testid="local-note">{n}</p> })}
                <fieldset>
                    <legend>"Targets (apply any time)"</legend>
                    <NumberField label="t_sr target" unit="ns" testid="local-target-tsr" step="1" get=t_tsr set=set_t_tsr />
                    <NumberField label="w target" unit="µV" testid="local-target-w" step="5" get=t_w set=set_t_w />
                    <NumberField label="tolerance" unit="× target" testid="local-tolerance" step="0.01" get=tol set=set_tol />
                    <button data-testid="local-apply-targets" disabled=move || !enabled.get().targets on:click=move |_| apply_targets()>"Apply targets"</button>
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
                    <crate::compensation::CompensationEditor settings=settings />
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
                        key=move || vec![history.with(|h| h.version())]
                        draw=move |a: &Area| {
                            let n = history.with(|h| h.len());
                            let land = runner.with_value(|r| r.as_ref().and_then(|r| r.landscape("SB", "T", 30.0, 25)));
                            charts::draw_landscape(a, land.as_ref(), &[]).map(|_| Drawn { iterations: n, ..Drawn::default() })
                        }
                    />
                    <div class="explain landscape-text">
                        <p><b>"Heat map."</b>" Colour: how far the true t_sr and w are from their targets, in units of the tolerance (the larger of the two), when only V_SB and V_T are changed from the present voltages. Inside the green region both parameters are in band."</p>
                        <p>"The line is the tuner's path projected onto this plane (it also moves N and SA, so the map shifts as it goes). Light cells are far from the goal; the step limit keeps every move short because the map is curved: gradients measured here are wrong a few tens of mV away."</p>
                    </div>
                </div>
                <crate::race::RacePanel settings=settings />
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

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pause_step_resume_stop_go_through_the_session() {
        let mut r = LocalRunner::new(&LocalSettings::default()).unwrap();
        assert_eq!(r.status(), RunStatus::Running);
        assert_eq!(r.advance(), Ok(Some(0)));
        assert_eq!(r.advance(), Ok(Some(1)));

        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert!(!r.is_advancing());
        assert_eq!(r.advance(), Err(RunError::Paused));
        assert_eq!(r.history.len(), 2);

        // A single step: exactly one more iteration, then paused again.
        assert_eq!(r.control(&ControlCommand::Step), Ok(RunStatus::Stepping));
        assert!(r.is_advancing());
        assert_eq!(r.advance(), Ok(Some(2)));
        assert_eq!(r.status(), RunStatus::Paused);
        assert_eq!(r.advance(), Err(RunError::Paused));
        assert_eq!(r.history.len(), 3);

        // A target change while paused goes through the session too.
        assert_eq!(r.set_targets(70.0, 270.0, 0.1), Ok(RunStatus::Paused));
        assert!(r.set_targets(f64::NAN, 270.0, 0.1).is_err());
        assert!(r.set_targets(70.0, 270.0, -1.0).is_err());

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(), Ok(Some(3)));
        let t_sr = r.history.records()[3]
            .parameters
            .iter()
            .find(|p| p.name == "t_sr")
            .unwrap();
        assert_eq!(t_sr.target, Some(70.0));

        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(), Ok(None));
        assert!(r.control(&ControlCommand::Resume).is_err());
        assert_eq!(r.status(), RunStatus::Stopped);
        assert_eq!(r.history.len(), 4);
        let its: Vec<u64> = r.history.records().iter().map(|r| r.iteration).collect();
        assert_eq!(its, vec![0, 1, 2, 3]);
    }

    /// A run whose device refuses to move gate N more than 0.5 mV: the
    /// session pauses the run with a device fault, which is resumable.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_device_fault_pauses_the_run_and_is_resumable() {
        use crate::model::{status_label, ControlsEnabled};
        use spintune::protocol::FaultKind;
        use spintune::session::{RunSession, SessionConfig};
        use spintune::sim::SimulatedDevice;

        let cfg = LocalSettings::default().to_config();
        let mut gates = cfg.tuner.gates.clone();
        let n = gates.iter_mut().find(|g| g.name == "N").unwrap();
        n.min_mv = n.initial_mv - 0.5;
        n.max_mv = n.initial_mv + 0.5;
        let device = SimulatedDevice::new(cfg.device.clone(), &gates, cfg.seed).unwrap();
        let session = RunSession::new(cfg.tuner, SessionConfig::default()).unwrap();
        let mut r = LocalRunner::from_run(SimulationRun::from_parts(session, device));

        let fault = match r.advance() {
            Err(RunError::Fault(f)) => f,
            other => panic!("expected a fault, got {other:?}"),
        };
        assert_eq!(fault.kind, FaultKind::Device);
        assert!(fault.message.contains("\"N\""), "{}", fault.message);
        let status = r.status();
        assert_eq!(
            status,
            RunStatus::Faulted {
                fault: fault.clone()
            }
        );
        assert!(status.is_resumable() && !r.is_advancing());
        let label = status_label(&status);
        assert!(label.starts_with("faulted"), "{label}");
        assert!(
            label.contains("Instrument fault")
                && label.contains(&fault.message)
                && label.contains("needs a person"),
            "{label}"
        );
        assert!(ControlsEnabled::for_status(&status).resume);
        assert!(!ControlsEnabled::for_status(&status).accept_positions);
        assert!(r.history.is_empty());

        // Resume: the session reads the gates back and retries the request,
        // which this device refuses again.
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert!(matches!(r.advance(), Err(RunError::Fault(f)) if f.kind == FaultKind::Device));
        // A faulted run can be held (paused) or stopped by the user.
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert_eq!(r.advance(), Err(RunError::Paused));
        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(), Ok(None));
    }

    /// Gate N moved by hand while the run was paused: resume reads it back
    /// and faults (moved); resume alone re-reads and faults again; accepting
    /// the positions leaves the run paused, and resume continues from them.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_gate_moved_while_paused_needs_its_position_accepted() {
        use crate::model::{moved_rows, status_label, ControlsEnabled};
        use spintune::protocol::{ClearedBy, FaultKind, Request, Response};

        let mut r = LocalRunner::new(&LocalSettings::default()).unwrap();
        assert_eq!(r.advance(), Ok(Some(0)));
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        let left = r.run.device().voltages_mv()["N"];
        let moved_to = left + 5.0;
        let answer = r.run.device_mut().execute(&Request::SetVoltages {
            voltages_mv: [("N".to_string(), moved_to)].into(),
        });
        assert!(matches!(answer, Response::VoltagesSet { .. }), "{answer:?}");

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        let fault = match r.advance() {
            Err(RunError::Fault(f)) => f,
            other => panic!("expected a moved fault, got {other:?}"),
        };
        assert_eq!(fault.kind, FaultKind::Moved);
        assert_eq!(fault.cleared_by, ClearedBy::AcceptPositions);
        let rows = moved_rows(&fault);
        assert_eq!(rows.len(), 1, "{rows:?}");
        assert_eq!(rows[0].gate, "N");
        assert_eq!(rows[0].read, format!("{moved_to:.2}"));
        assert_eq!(rows[0].difference, "+5.00");
        let status = r.status();
        assert!(status_label(&status).contains("Gates moved"));
        let c = ControlsEnabled::for_status(&status);
        assert!(c.accept_positions && c.resume, "{c:?}");

        // Resume without accepting: the gate is read again, still far.
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert!(matches!(r.advance(), Err(RunError::Fault(f)) if f.kind == FaultKind::Moved));
        // Accept: paused, nothing sent until resume.
        assert_eq!(
            r.control(&ControlCommand::AcceptPositions),
            Ok(RunStatus::Paused)
        );
        assert!(!ControlsEnabled::for_status(&r.status()).accept_positions);
        assert!(r.control(&ControlCommand::AcceptPositions).is_err());
        assert_eq!(r.advance(), Err(RunError::Paused));
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(), Ok(Some(1)));
        assert_eq!(r.status(), RunStatus::Running);
    }
}
