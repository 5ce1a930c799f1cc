//! One run's page: title, connection badge, notice, status, the token form
//! or the controls, paging mode, comparison and export, and the dashboard.
//! Its connection is a [`Driver`] around the sans-IO client.

use leptos::prelude::*;
use send_wrapper::SendWrapper;
use spintune::description::layout::CellGrid;
use spintune::driver::array::ArraySimulationConfig;
use spintune::parameter::Tolerance;
use spintune::protocol::{
    ControlCommand, IterationRecord, RunStatus, RunSummary, MAX_HISTORY_PAGE,
};

use super::client::{AuthState, ConnState, Event, PagingMode};
use super::driver::{Driver, Signals};
use crate::api::{get_json, ApiBase, ApiError};
use crate::array_panel::ArrayOverview;
use crate::history::RunHistory;
use crate::model::{ControlsEnabled, Followed};
use crate::ui::{Dashboard, DashboardHooks, StatusBadge, StatusNote};

/// Most iterations of a compared run loaded (its newest), to bound memory.
pub const OVERLAY_MAX: u64 = 20_000;

/// The newest `max` iterations of run `id`, over HTTP in pages of
/// [`MAX_HISTORY_PAGE`] (scans dropped on arrival).
pub async fn load_history_http(base: &ApiBase, id: u64, max: u64) -> Result<RunHistory, ApiError> {
    let summary: RunSummary = get_json(&base.url(&format!("/api/runs/{id}"))).await?;
    let mut h = RunHistory::new();
    h.set_total(summary.iterations);
    let mut from = summary.iterations.saturating_sub(max);
    while from < summary.iterations {
        let limit = MAX_HISTORY_PAGE as u64;
        let page: Vec<IterationRecord> = get_json(&base.url(&format!(
            "/api/runs/{id}/iterations?from={from}&limit={limit}"
        )))
        .await?;
        if page.is_empty() {
            break;
        }
        h.insert(page);
        from += limit;
    }
    Ok(h)
}

/// The part of `GET /api/runs/{id}/config` the page reads: an array run's
/// config (the server's `RunConfig.array`; other fields ignored).
#[derive(serde::Deserialize)]
struct ServedConfig {
    #[serde(default)]
    array: Option<ArraySimulationConfig>,
}

/// One run: connection state, summary, controls, plots.
#[component]
pub fn RunView(
    run: u64,
    base: ApiBase,
    /// Iterations the server holds (from the run list), if known: the
    /// first socket asks only for the newest page.
    #[prop(optional_no_strip)]
    total_hint: Option<u64>,
    /// The run list (to pick a run to compare with).
    #[prop(optional)]
    runs: Option<RwSignal<Vec<RunSummary>>>,
) -> impl IntoView {
    let sig = Signals::new();
    let export_base = base.clone();
    let overlay_base = base.clone();
    let config_base = base.clone();
    let driver = Driver::start(run, total_hint, base, sig);
    {
        let driver = SendWrapper::new(driver.clone());
        on_cleanup(move || driver.feed(Event::Shutdown));
    }
    let driver = StoredValue::new(SendWrapper::new(driver));
    let feed = move |event: Event| driver.with_value(|d| d.feed(event));
    let token_input = RwSignal::new(String::new());
    let unlock = move || {
        feed(Event::Unlock {
            token: token_input.get_untracked(),
        })
    };
    let control = move |command: ControlCommand| feed(Event::Control(command));
    let title = move || {
        sig.summary.with(|s| match s {
            Some(s) => format!("Run #{} — {}", s.id, s.name),
            None => format!("Run #{run}"),
        })
    };
    let status = Signal::derive(move || sig.summary.with(|s| s.as_ref().map(|s| s.status.clone())));
    // The run list in the sidebar shows what the socket just said about
    // this run (not what its next poll, seconds later, will say).
    if let Some(runs) = runs {
        Effect::new(move |_| {
            let Some(summary) = sig.summary.get() else {
                return;
            };
            let stale = runs
                .with_untracked(|list| list.iter().any(|e| e.id == summary.id && *e != summary));
            if stale {
                runs.update(|list| {
                    if let Some(entry) = list.iter_mut().find(|e| e.id == summary.id) {
                        *entry = summary;
                    }
                });
            }
        });
    }
    let want_scans = Callback::new(move |k: u64| feed(Event::WantScans(k)));
    let hooks = DashboardHooks {
        want_scans: Some(want_scans),
        status: Some(status),
    };
    let connected = Signal::derive(move || sig.conn.with(|c| *c == ConnState::Open));
    // A run of an array of cells (its parameters are named per cell): the
    // array overview instead of the single-cell charts.
    let is_array = Memo::new(move |_| {
        sig.history.with(|h| {
            crate::array_view::cells(h.layout().parameters.iter().map(|p| p.0.as_str())).is_some()
        })
    });
    // How the cells sit (a ladder's two rows): from the run's config,
    // fetched once the run shows as an array. Unknown (tiles in one
    // wrapping row) until it arrives, or if it cannot be read.
    let grid = RwSignal::new(None::<CellGrid>);
    let grid_requested = StoredValue::new(false);
    Effect::new(move |_| {
        if !is_array.get() || grid_requested.get_value() {
            return;
        }
        grid_requested.set_value(true);
        let url = config_base.url(&format!("/api/runs/{run}/config"));
        leptos::task::spawn_local(async move {
            if let Ok(served) = get_json::<ServedConfig>(&url).await {
                let _ = grid.try_set(served.array.and_then(|a| a.grid().ok()));
            }
        });
    });
    let paging_note = move || match sig.paging.get() {
        PagingMode::Socket => "history pages over the socket",
        PagingMode::Http => "history pages over HTTP (server without socket paging)",
    };
    // Compare with another run: its newest iterations, over HTTP.
    let overlay = RwSignal::new(None::<RunHistory>);
    let overlay_id = RwSignal::new(None::<u64>);
    let pick_overlay = move |id: Option<u64>| {
        overlay_id.set(id);
        overlay.set(None);
        let Some(id) = id else { return };
        let base = overlay_base.clone();
        leptos::task::spawn_local(async move {
            let h = load_history_http(&base, id, OVERLAY_MAX).await;
            if overlay_id.try_get_untracked() == Some(Some(id)) {
                let _ = overlay.try_set(h.ok());
            }
        });
    };
    let other_runs = move || {
        runs.map(|r| {
            r.with(|r| {
                r.iter()
                    .filter(|s| s.id != run)
                    .map(|s| (s.id, s.name.clone()))
                    .collect::<Vec<_>>()
            })
        })
        .unwrap_or_default()
    };
    view! {
        <div class="run-view">
            <header class="run-head">
                <h2>{title}</h2>
                <StatusBadge status testid="run-status" unknown="…" connected />
                <span class=move || sig.conn.with(|c| c.class()) data-testid="connection">{move || sig.conn.with(|c| c.label())}</span>
            </header>
            {move || sig.notice.get().map(|n| view! {
                <p class="notice">{n} <button class="link" on:click=move |_| sig.notice.set(None)>"dismiss"</button></p>
            })}
            <StatusNote status />
            <div class="control-panel">
                {move || match sig.auth.get() {
                    AuthState::Ok => view! {
                        <Controls history=sig.history status on_command=Callback::new(control) />
                    }.into_any(),
                    state => view! {
                        <div class="readonly" data-testid="readonly">
                            <p><b>"Read-only view."</b> " Enter the control token printed by "<code>"spintune serve"</code>" to change targets, pause, step or stop this run."</p>
                            <form class="token" on:submit=move |ev| { ev.prevent_default(); unlock(); }>
                                <input type="password" placeholder="control token" data-testid="token"
                                    prop:value=move || token_input.get()
                                    on:input=move |ev| token_input.set(event_target_value(&ev)) />
                                <button type="submit" data-testid="unlock">"Unlock controls"</button>
                            </form>
                            {match state {
                                AuthState::Pending => Some(view! { <p class="hint">"checking token…"</p> }.into_any()),
                                AuthState::Refused(m) => Some(view! { <p class="error" data-testid="auth-error">{format!("Token refused: {m}")}</p> }.into_any()),
                                _ => None,
                            }}
                        </div>
                    }.into_any(),
                }}
            </div>
            <div class="run-tools">
                <span class="paging" data-testid="paging" data-mode=move || format!("{:?}", sig.paging.get()).to_lowercase()>{paging_note}</span>
                // (an array run's overview compares with nothing)
                <label style:display=move || if is_array.get() { "none" } else { "" }>"compare with "
                    <select data-testid="overlay" on:change=move |ev| pick_overlay(event_target_value(&ev).parse().ok())>
                        <option value="">"no other run"</option>
                        {move || other_runs().into_iter().map(|(id, name)| view! { <option value=id.to_string()>{format!("#{id} {name}")}</option> }).collect_view()}
                    </select>
                </label>
                <span class="export">"export "
                    <a data-testid="export-csv" href=export_base.url(&format!("/api/runs/{run}/export?format=csv")) download=format!("run-{run}.csv")>"CSV"</a>
                    " · "
                    <a data-testid="export-json" href=export_base.url(&format!("/api/runs/{run}/export?format=json")) download=format!("run-{run}.json")>"JSON"</a>
                </span>
            </div>
            {move || if is_array.get() {
                view! { <ArrayOverview history=sig.history status=status grid=grid /> }.into_any()
            } else {
                view! { <Dashboard history=sig.history overlay=overlay hooks=hooks /> }.into_any()
            }}
        </div>
    }
}

/// Control buttons and target/tolerance editors (shown after authentication).
/// A button is enabled only where the run's status accepts it
/// ([`ControlsEnabled::for_status`]; all while the status is unknown).
#[component]
fn Controls(
    history: RwSignal<RunHistory>,
    status: Signal<Option<RunStatus>>,
    on_command: Callback<ControlCommand>,
) -> impl IntoView {
    let enabled = Memo::new(move |_| {
        status.with(|s| {
            s.as_ref()
                .map_or(ControlsEnabled::ALL, ControlsEnabled::for_status)
        })
    });
    let params = Memo::new(move |_| {
        history.with(|h| {
            h.latest()
                .map(|r| {
                    r.parameters
                        .iter()
                        .map(|p| (p.name.clone(), p.unit.clone(), p.target, p.tolerance))
                        .collect::<Vec<_>>()
                })
                .unwrap_or_default()
        })
    });
    view! {
        <div class="controls" data-testid="controls">
            <span class="badge ok">"controls unlocked"</span>
            <button data-testid="pause" disabled=move || !enabled.get().pause on:click=move |_| on_command.run(ControlCommand::Pause)>"Pause"</button>
            <button data-testid="resume" disabled=move || !enabled.get().resume on:click=move |_| on_command.run(ControlCommand::Resume)>"Resume"</button>
            <button data-testid="step" disabled=move || !enabled.get().step on:click=move |_| on_command.run(ControlCommand::Step)>"Single step"</button>
            <button class="danger" data-testid="stop" disabled=move || !enabled.get().stop on:click=move |_| {
                if window().confirm_with_message("Stop this run for good?").unwrap_or(false) {
                    on_command.run(ControlCommand::Stop);
                }
            }>"Stop"</button>
            // Only for a run faulted because gates moved (the table above
            // shows old → new): adopts the read positions, the run stays
            // paused until Resume.
            <Show when=move || enabled.get().accept_positions>
                <button class="primary" data-testid="accept-positions"
                    title="Adopt the positions the instrument reads now (the table above); the run stays paused until Resume, which reads every gate again"
                    on:click=move |_| on_command.run(ControlCommand::AcceptPositions)>"Accept positions"</button>
            </Show>
            <div class="targets">
                <For
                    each=move || params.get()
                    key=|p| p.0.clone()
                    children=move |(name, unit, _, _)| {
                        let n = name.clone();
                        // The run's present target and tolerance (newest record).
                        let current = Signal::derive(move || {
                            params.with(|ps| {
                                ps.iter()
                                    .find(|p| p.0 == n)
                                    .map_or((None, None), |p| (p.2, p.3))
                            })
                        });
                        view! {
                            <TargetEditor name unit current enabled=Signal::derive(move || enabled.get().targets) on_command />
                        }
                    }
                />
            </div>
        </div>
    }
}

/// Edit one parameter's target and tolerance. Each field shows the run's
/// present value (`current`: target, tolerance half-width, from the newest
/// record, so a scheduled change shows) unless the user is editing it
/// ([`Followed`]); Apply sends what the fields show, so a field left alone
/// sends the run's present value.
#[component]
fn TargetEditor(
    name: String,
    unit: String,
    current: Signal<(Option<f64>, Option<f64>)>,
    enabled: Signal<bool>,
    on_command: Callback<ControlCommand>,
) -> impl IntoView {
    let t = RwSignal::new(Followed::default());
    let tol = RwSignal::new(Followed::default());
    let t_text = move || t.with(|f| f.shown(current.get().0));
    let tol_text = move || tol.with(|f| f.shown(current.get().1));
    let err = RwSignal::new(None::<String>);
    let n2 = name.clone();
    let apply = move || {
        let tt = untrack(t_text);
        let target = if tt.trim().is_empty() {
            None
        } else {
            match tt.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => Some(v),
                _ => {
                    err.set(Some("target must be a number".into()));
                    return;
                }
            }
        };
        let tl = untrack(tol_text);
        let tolerance = if tl.trim().is_empty() {
            None
        } else {
            match tl.trim().parse::<f64>() {
                Ok(v) if v.is_finite() && v >= 0.0 => Some(Tolerance::Absolute(v)),
                _ => {
                    err.set(Some("tolerance must be a non-negative number".into()));
                    return;
                }
            }
        };
        err.set(None);
        on_command.run(ControlCommand::SetTarget {
            parameter: n2.clone(),
            target,
            tolerance,
        });
        let (run_t, run_tol) = current.get_untracked();
        t.update(|f| f.sent(run_t));
        tol.update(|f| f.sent(run_tol));
    };
    view! {
        <form class="target" data-parameter=name.clone() on:submit=move |ev| { ev.prevent_default(); apply(); }>
            <b>{name.clone()}</b>
            <label>"target "<input type="number" step="any" data-testid=format!("target-{name}")
                class:edited=move || t.with(Followed::is_editing)
                prop:value=t_text on:input=move |ev| t.update(|f| f.edit(event_target_value(&ev))) />{format!(" {unit}")}</label>
            <label>"± "<input type="number" step="any" min="0" data-testid=format!("tolerance-{name}")
                class:edited=move || tol.with(Followed::is_editing)
                prop:value=tol_text on:input=move |ev| tol.update(|f| f.edit(event_target_value(&ev))) />{format!(" {unit}")}</label>
            <button type="submit" disabled=move || !enabled.get()>"Apply"</button>
            {move || err.get().map(|e| view! { <span class="error">{e}</span> })}
        </form>
    }
}
