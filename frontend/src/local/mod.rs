//! In-browser mode: the run session and the simulated double dot from
//! `spintune` run inside the page (no server).
//!
//! The page is a thin driver of [`SimulationRun`]: pause, resume, single
//! step, stop and target changes are [`ControlCommand`]s applied by the run
//! session, which owns the run's status. The page keeps only its animation
//! timer: each tick asks for the next iteration while the session is running
//! or stepping, and yields to the browser in between so the page stays
//! responsive.

//!
//! Files: [`settings`] (what the student chooses → the simulation config),
//! [`runner`] (drives one run through its session), [`compensation`] (the
//! virtual-gate matrix editor), [`race`] (two estimators on one device) and
//! this page. Nothing here imports the live mode, nor the live mode this.

pub mod compensation;
pub mod diagnose;
pub mod race;
pub mod runner;
pub mod settings;

use leptos::prelude::*;
use leptos::reactive::owner::LocalStorage;
use spintune::driver::Halt;
use spintune::estimator::EstimatorKind;
use spintune::protocol::{ControlCommand, RunStatus};

pub use runner::{LocalRunner, Progress};
pub use settings::{Field, LocalSettings};

/// Why the in-browser mode refused something, in plain words (no config
/// paths): the one error type of this mode's boundary with the core.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LocalError {
    /// A sidebar field holds a value it may not.
    #[error("{}: {message}", field.label())]
    Field {
        /// Which field.
        field: Field,
        /// What is allowed.
        message: String,
    },
    /// The core refused the settings (its message, without the config path).
    #[error("these settings do not make a valid tuner: {}", .0.message)]
    Config(spintune::config_error::ConfigError),
    /// The virtual-gate matrix was refused.
    #[error("virtual-gate matrix: {}", compensation_text(.0))]
    Compensation(spintune::driver::CompensationError),
    /// The session refused a control command.
    #[error("{0}")]
    Refused(spintune::session::ControlError),
    /// A target change was refused.
    #[error("{0}")]
    Target(spintune::tuner::TunerError),
    /// The run halted in a way this page does not drive (a bug).
    #[error("{0}")]
    Halted(spintune::driver::Halt),
}

fn compensation_text(e: &spintune::driver::CompensationError) -> String {
    match &e.label {
        Some(l) => format!("{l} (mV/mV): {}", e.error.message),
        None if e.error.field.ends_with("relative_uncertainty") => {
            format!("matrix uncertainty: {}", e.error.message)
        }
        None => e.error.message.clone(),
    }
}

use crate::charts;
use crate::history::RunHistory;
use crate::metrics;
use crate::model::ControlsEnabled;
use crate::series::Drawn;
use crate::ui::{Area, Chart, Dashboard, DashboardHooks, StatusBadge, StatusNote};
use crate::widgets::NumberField;
/// Longest stretch of simulation between two yields to the browser, ms: an
/// iteration (≈ 20 scans and fits) is worked on in slices of about this
/// long, so the page keeps painting and answering while it runs.
pub const SLICE_MS: f64 = 12.0;

/// The in-browser mode's state. It is owned by the page ([`crate::App`]
/// provides it), not by the mode's view: switching to "Live runs" and back
/// keeps a run, its charts and its timer going.
#[derive(Clone, Copy)]
pub struct LocalState {
    settings: RwSignal<LocalSettings>,
    history: RwSignal<RunHistory>,
    /// Mirror of the session's status after each action (None: no run yet).
    status: RwSignal<Option<RunStatus>>,
    tuned_at: RwSignal<Option<u64>>,
    /// The first iteration of the present targets (for [`diagnose`]).
    targets_since: RwSignal<u64>,
    error: RwSignal<Option<String>>,
    note: RwSignal<Option<String>>,
    /// Sidebar fields holding a value that was not applied.
    invalid: RwSignal<Vec<&'static str>>,
    runner: StoredValue<Option<LocalRunner>, LocalStorage>,
    /// Whether a tick loop is alive, and which run it belongs to.
    ticking: StoredValue<bool>,
    generation: StoredValue<u64>,
}

impl LocalState {
    /// No run yet, the default settings.
    pub fn new() -> Self {
        Self {
            settings: RwSignal::new(LocalSettings::default()),
            history: RwSignal::new(RunHistory::new()),
            status: RwSignal::new(None),
            tuned_at: RwSignal::new(None),
            targets_since: RwSignal::new(0),
            error: RwSignal::new(None),
            note: RwSignal::new(None),
            invalid: RwSignal::new(Vec::new()),
            runner: StoredValue::new_local(None),
            ticking: StoredValue::new(false),
            generation: StoredValue::new(0),
        }
    }
}

impl Default for LocalState {
    fn default() -> Self {
        Self::new()
    }
}

/// The teaching demo (its state from the page's context, or its own).
#[component]
pub fn LocalMode() -> impl IntoView {
    let st = use_context::<LocalState>().unwrap_or_default();
    let LocalState {
        settings,
        history,
        status,
        tuned_at,
        targets_since,
        error,
        note,
        invalid,
        runner,
        ticking,
        generation,
    } = st;

    // Copy what changed in the runner into the signals.
    let sync = move || {
        runner.with_value(|r| {
            let Some(r) = r else { return };
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
        if !invalid.with_untracked(|v| v.is_empty()) {
            error.set(Some(
                "a setting above is not valid: fix the marked field first".into(),
            ));
            return false;
        }
        match LocalRunner::new(&settings.get_untracked()) {
            Ok(r) => {
                runner.set_value(Some(r));
                history.set(RunHistory::new());
                targets_since.set(0);
                error.set(None);
                true
            }
            // The matrix editor marks the cell and says why.
            Err(LocalError::Compensation(_)) => {
                error.set(Some(
                    "the virtual-gate matrix is not valid: fix the marked cell first".into(),
                ));
                false
            }
            Err(e) => {
                error.set(Some(e.to_string()));
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
            Some(Err(e)) => error.set(Some(e.to_string())),
            Some(Ok(_)) => error.set(None),
            None => {}
        }
        sync();
    };
    // One slice of work: part of an iteration, or its end. `Some(recorded)`
    // while the timer should keep ticking.
    let tick = move || -> Option<bool> {
        let t0 = metrics::now_ms();
        let res = runner
            .try_update_value(|r| {
                r.as_mut().map(|r| {
                    history
                        .try_update(|h| r.advance_for(h, SLICE_MS, &metrics::now_ms))
                        .unwrap_or(Ok(Progress::Over))
                })
            })
            .flatten();
        metrics::note_local_slice(metrics::now_ms() - t0);
        let (broken, recorded) = match res {
            None => return None,
            Some(Ok(Progress::Recorded(_))) => (false, true),
            Some(Ok(Progress::Working)) => (false, false),
            // over, paused (also after a single step) or faulted: the
            // session's status says which
            Some(Ok(Progress::Over) | Err(Halt::Paused | Halt::Fault(_))) => (false, true),
            // a bug in this driver: stop ticking rather than repeat it
            Some(Err(e @ Halt::Session(_))) => {
                error.set(Some(LocalError::Halted(e).to_string()));
                (true, true)
            }
        };
        sync();
        (!broken && runner.with_value(|r| r.as_ref().is_some_and(|r| r.is_advancing())))
            .then_some(recorded)
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
            let mut pause = true;
            loop {
                // Yield first: lets the page paint between slices; the
                // chosen pause only between iterations.
                let delay = if pause {
                    settings.try_with_untracked(|s| s.delay_ms).unwrap_or(0)
                } else {
                    0
                };
                gloo_timers::future::TimeoutFuture::new(delay).await;
                if generation.try_get_value() != Some(my_gen) {
                    // reset: a new run owns the timer
                    break;
                }
                match tick() {
                    Some(recorded) => pause = recorded,
                    None => {
                        ticking.set_value(false);
                        break;
                    }
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
        targets_since.set(0);
        error.set(None);
        note.set(None);
    };
    // A run left ticking while the page showed the live runs: its timer
    // is still alive (owned by the page); nothing to restart here.
    let apply_targets = move || {
        if !invalid.with_untracked(|v| v.is_empty()) {
            error.set(Some(
                "a setting above is not valid: fix the marked field first".into(),
            ));
            return;
        }
        let s = settings.get_untracked();
        let res = runner
            .try_update_value(|r| {
                r.as_mut()
                    .map(|r| r.set_targets(s.target_tsr, s.target_w, s.tolerance))
            })
            .flatten();
        match res {
            Some(Err(e)) => error.set(Some(e.to_string())),
            Some(Ok(_)) => {
                error.set(None);
                targets_since.set(history.with_untracked(|h| h.extent().map_or(0, |e| e.1 + 1)));
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
    let diagnosis = Memo::new(move |_| {
        let t = tuned_at.get();
        let since = targets_since.get();
        history.with(|h| settings.with_untracked(|s| diagnose::why_not_tuned(s, h, t, since)))
    });

    macro_rules! field {
        ($f:ident, $field:expr) => {
            (
                Signal::derive(move || settings.with(|s| s.$f as f64)),
                Callback::new(move |v: f64| settings.update(|s| s.$f = v as _)),
                Callback::new(move |v: f64| $field.check(v)),
            )
        };
    }
    let (q_tsr, set_q_tsr, ck_q_tsr) = field!(q_tsr, Field::QTsr);
    let (q_w, set_q_w, ck_q_w) = field!(q_w, Field::QW);
    let (noise, set_noise, ck_noise) = field!(noise_scale, Field::Noise);
    let (max_step, set_max_step, ck_max_step) = field!(max_step_mv, Field::MaxStep);
    let (seed, set_seed, ck_seed) = field!(seed, Field::Seed);
    let (t_tsr, set_t_tsr, ck_t_tsr) = field!(target_tsr, Field::TargetTsr);
    let (t_w, set_t_w, ck_t_w) = field!(target_w, Field::TargetW);
    let (tol, set_tol, ck_tol) = field!(tolerance, Field::Tolerance);
    let (delay, set_delay, ck_delay) = field!(delay_ms, Field::Delay);
    let (max_it, set_max_it, ck_max_it) = field!(max_iterations, Field::MaxIterations);

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
                {move || diagnosis.get().map(|d| view! { <p class="notice" data-testid="local-diagnosis">{d}</p> })}
                <fieldset>
                    <legend>"Targets (apply any time)"</legend>
                    <NumberField label="t_sr target" unit="ns" testid="local-target-tsr" step="1" get=t_tsr set=set_t_tsr check=ck_t_tsr invalid=invalid
                        title="t_sr: the singlet reload time, ns — how long the dot takes to reload a singlet from the leads (1/Γ of the lead tunnel rate)" />
                    <NumberField label="w target" unit="µV" testid="local-target-w" step="5" get=t_w set=set_t_w check=ck_t_w invalid=invalid
                        title="w: the width of the inter-dot transition, µV (detuning) — set by the inter-dot tunnel coupling and temperature" />
                    <NumberField label="tolerance" unit="× target" testid="local-tolerance" step="0.01" get=tol set=set_tol check=ck_tol invalid=invalid />
                    <button data-testid="local-apply-targets" disabled=move || !enabled.get().targets on:click=move |_| apply_targets()>"Apply targets"</button>
                </fieldset>
                <fieldset>
                    <legend>"Tuner and device (apply on Reset)"</legend>
                    <label class="field">
                        <span class="field-label">"step rule"</span>
                        <select data-testid="local-rule" on:change=move |ev| {
                            if let Some(r) = settings::Rule::from_name(&event_target_value(&ev)) {
                                settings.update(|s| s.rule = r);
                            }
                        }>
                            {settings::Rule::ALL.into_iter().map(|r| view! {
                                <option value=r.name() selected=move || settings.with(|s| s.rule == r)>{r.label()}</option>
                            }).collect_view()}
                        </select>
                    </label>
                    <label class="field">
                        <span class="field-label">"estimator"</span>
                        <select data-testid="local-estimator" on:change=move |ev| {
                            if let Some(k) = EstimatorKind::from_name(&event_target_value(&ev)) {
                                settings.update(|s| s.estimator = k);
                            }
                        }>
                            {EstimatorKind::ALL.into_iter().map(|k| view! {
                                <option value=k.name() selected=move || settings.with(|s| s.estimator == k)>{estimator_label(k)}</option>
                            }).collect_view()}
                        </select>
                    </label>
                    <NumberField label="Q σ of ∂t_sr/∂V" unit="ns/mV per mV" testid="local-q-tsr" step="0.005" get=q_tsr set=set_q_tsr check=ck_q_tsr invalid=invalid />
                    <NumberField label="Q σ of ∂w/∂V" unit="µV/mV per mV" testid="local-q-w" step="0.05" get=q_w set=set_q_w check=ck_q_w invalid=invalid />
                    <NumberField label="measurement noise" unit="× default" testid="local-noise" step="0.25" get=noise set=set_noise check=ck_noise invalid=invalid />
                    <NumberField label="step limit" unit="mV" testid="local-max-step" step="1" get=max_step set=set_max_step check=ck_max_step invalid=invalid />
                    <NumberField label="seed" unit="" testid="local-seed" step="1" get=seed set=set_seed check=ck_seed invalid=invalid />
                    <NumberField label="iteration limit" unit="" testid="local-max-iterations" step="10" get=max_it set=set_max_it check=ck_max_it invalid=invalid />
                    <NumberField label="pause between iterations" unit="ms" testid="local-delay" step="50" get=delay set=set_delay check=ck_delay invalid=invalid />
                    <compensation::CompensationEditor settings=settings />
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
                <Dashboard history=history hooks=DashboardHooks { status: Some(status.into()), ..DashboardHooks::default() } />
                <h3>"Simulator ground truth " <small>"(what the tuner cannot see)"</small></h3>
                <div class="grid2">
                    <Chart
                        name="landscape"
                        height=340
                        key=move || vec![history.with(|h| h.version())]
                        draw=move |a: &Area| {
                            history.with(|h| {
                                let land = runner.with_value(|r| r.as_ref().and_then(|r| r.landscape(h, "SB", "T", 30.0, 25)));
                                charts::draw_landscape(a, land.as_ref(), &[]).map(|_| Drawn { iterations: h.len(), ..Drawn::default() })
                            })
                        }
                    />
                    <div class="explain landscape-text">
                        <p><b>"Heat map."</b>" Colour: how far the true t_sr and w are from their targets, in units of the tolerance (the larger of the two), when only V_SB and V_T are changed from the present voltages. Inside the green region both parameters are in band."</p>
                        <p>"The line is the tuner's path projected onto this plane (it also moves N and SA, so the map shifts as it goes). Light cells are far from the goal; the step limit keeps every move short because the map is curved: gradients measured here are wrong a few tens of mV away."</p>
                    </div>
                </div>
                <race::RacePanel settings=settings />
            </section>
        </div>
    }
}

/// An estimator's name in the lists; the oracle says that it is a reference
/// only (it reads the simulator's truth, which no lab has).
pub fn estimator_label(k: EstimatorKind) -> String {
    if k.name() == "oracle" {
        "oracle (knows the true device; reference only)".to_string()
    } else {
        k.name().to_string()
    }
}

/// What the student is looking at.
#[component]
fn Explanation() -> impl IntoView {
    view! {
        <details class="explain" open>
            <summary>"What am I looking at?"</summary>
            <p>"The tuner moves four gate voltages (N, SA, SB, T) until the reload time "<i>"t_sr"</i>" and the inter-dot transition width "<i>"w"</i>" sit inside their tolerance bands (green)."</p>
            <p><b><i>"t_sr"</i>" (ns)"</b>" is the singlet reload time: how long the double dot takes to load a fresh singlet from its leads (1/Γ of the lead tunnel rate). "<b><i>"w"</i>" (µV)"</b>" is the width of the inter-dot transition in detuning, set by the tunnel coupling between the dots (and the temperature). Both are fitted from a raw scan each iteration; the qubit needs both at their targets."</p>
            <p><b>"Gradient."</b>" Each panel of the gradient plot is one element of the Jacobian: how much a parameter changes per mV on one gate. The tuner never measures it directly after the start; a Kalman filter infers it from how the parameters responded to each step."</p>
            <p><b>"Error bars."</b>" ±1σ is the square root of the filter's covariance diagonal: how unsure the filter is. Steps shrink it along the direction moved; the process noise Q grows it again with every step, by an amount that scales with the step's length (Q σ is per mV moved), so the filter keeps learning when the device changes. Large Q: fast but jumpy; tiny Q: smooth but slow to notice a changed gradient. Broyden has no noise model (no error bars); fixed-jacobian never learns."</p>
            <p><b>"Step limit."</b>" The gradient is only valid near the present voltages (tunnel couplings depend exponentially on them), so each Newton step is cut to a maximal length, as in the paper (10 mV). Larger limits converge faster when the model is right and overshoot when it is not."</p>
            <p><b>"Noise."</b>" Each parameter comes from a fit to a noisy raw scan (bottom). More noise means larger measurement error bars and a filter that trusts each measurement less."</p>
        </details>
    }
}
