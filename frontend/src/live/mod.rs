//! Live mode: list the server's runs and follow one over its WebSocket
//! (the newest page of history, then live iterations, then older pages
//! fetched in the background from the newest backwards), reconnecting with
//! back-off, resuming at the next missing iteration, and — after the
//! control token is accepted — control it.
//!
//! * [`client`]: every decision (protocol v4, paging, answer correlation,
//!   HTTP fallback, back-off, handshake refusals, unknown runs) as a sans-IO
//!   state machine, tested natively;
//! * `driver`: the IO around it (WebSocket callbacks, HTTP, the timer) and
//!   the signals it updates;
//! * `run_view`: one run's page ([`RunView`]); this file: the run list
//!   ([`LiveMode`]).

pub mod client;
mod driver;
mod run_view;

use std::time::Duration;

use leptos::prelude::*;
use send_wrapper::SendWrapper;
use spintune::protocol::RunSummary;

pub use self::client::{backoff_ms, AuthState, ConnState, PagingMode};
pub use self::run_view::{load_history_http, RunView, OVERLAY_MAX};
use crate::api::{get_json, ApiBase};
use crate::model::{format_lab_time, list_state, status_class, status_label};

/// Live mode: run list on the left, the selected run on the right.
#[component]
pub fn LiveMode(base: ApiBase) -> impl IntoView {
    let runs = RwSignal::new(Vec::<RunSummary>::new());
    let error = RwSignal::new(None::<String>);
    let loaded = RwSignal::new(false);
    let selected = RwSignal::new(initial_run_from_hash());
    let alerts = crate::attention::use_alerts();
    let refresh = {
        let base = base.clone();
        move || {
            let url = base.url("/api/runs");
            leptos::task::spawn_local(async move {
                match get_json::<Vec<RunSummary>>(&url).await {
                    Ok(list) => {
                        list_alerts(alerts, runs, selected, &list);
                        let _ = runs.try_set(list);
                        let _ = error.try_set(None);
                    }
                    Err(e) => {
                        let _ = error.try_set(Some(e.to_string()));
                    }
                }
                let _ = loaded.try_set(true);
            });
        }
    };
    refresh();
    let r2 = refresh.clone();
    if let Ok(handle) = set_interval_with_handle(r2, Duration::from_secs(4)) {
        let handle = SendWrapper::new(handle);
        on_cleanup(move || handle.clear());
    }
    // Open the first run automatically when nothing is selected.
    Effect::new(move |_| {
        if selected.get_untracked().is_none() {
            if let Some(first) = runs.with(|r| r.first().map(|r| r.id)) {
                selected.set(Some(first));
            }
        }
    });
    let mode = use_context::<RwSignal<crate::Mode>>();
    let run_view = move || {
        match selected.get() {
        Some(id) => {
            let _ = window().location().set_hash(&format!("live/{id}"));
            let hint = runs.with_untracked(|r| r.iter().find(|r| r.id == id).map(|r| r.iterations));
            view! { <RunView run=id base=base.clone() total_hint=hint runs=runs /> }.into_any()
        }
        None => view! {
            <div class="empty">
                {move || if error.with(|e| e.is_some()) {
                    view! {
                        <h2>"No spintune server answers at this address."</h2>
                        <p>"Start one with "<code>"spintune serve"</code>" and open the address it prints, or run the whole tuner in this page:"</p>
                        <button class="primary" data-testid="open-local" on:click=move |_| {
                            let _ = window().location().set_hash("local");
                            if let Some(m) = mode { m.set(crate::Mode::Local) }
                        }>"Open the in-browser simulation"</button>
                    }.into_any()
                } else {
                    view! { <p class="hint">"Select a run on the left."</p> }.into_any()
                }}
            </div>
        }.into_any(),
    }
    };
    view! {
        <div class="mode-live">
            <aside class="sidebar">
                <h2>"Runs"</h2>
                <Show when=move || error.with(|e| e.is_some())>
                    <p class="error">{move || error.get().unwrap_or_default()}</p>
                </Show>
                <Show when=move || loaded.get() && error.with(|e| e.is_none()) && runs.with(|r| r.is_empty())>
                    <p class="hint">"The server has no runs."</p>
                </Show>
                <ul class="runs">
                    <For
                        each=move || runs.get()
                        key=|r| (r.id, r.iterations, format!("{:?}", r.status))
                        children=move |r| {
                            let id = r.id;
                            let state = r.status.name();
                            view! {
                                <li>
                                    <button
                                        class="run"
                                        class:selected=move || selected.get() == Some(id)
                                        data-run=id
                                        on:click=move |_| selected.set(Some(id))
                                    >
                                        <span class="run-name">{format!("#{} {}", r.id, r.name)}</span>
                                        <span class="run-meta">
                                            <span class=status_class(&r.status) data-state=state title=status_label(&r.status)>{list_state(&r.status)}</span>
                                            " · "
                                            <span class="run-driver" data-testid="run-driver" title="device driver">
                                                {r.driver.clone().unwrap_or_else(|| "driver ?".to_string())}
                                            </span>
                                            {format!(" · {} it · lab {}", crate::ui::grouped(r.iterations), format_lab_time(r.lab_seconds))}
                                            {if r.tuned { " · tuned" } else { "" }}
                                        </span>
                                    </button>
                                </li>
                            }
                        }
                    />
                </ul>
            </aside>
            <section class="main">{run_view}</section>
        </div>
    }
}

/// Alerts of the runs the page does not follow over a socket, from the
/// run list's statuses (the core decides: [`spintune::alert::status_alert`];
/// the followed run's socket brings its own, with keep-mode alerts too).
fn list_alerts(
    alerts: crate::attention::Alerts,
    runs: RwSignal<Vec<RunSummary>>,
    selected: RwSignal<Option<u64>>,
    list: &[RunSummary],
) {
    let watched = selected.try_get_untracked().flatten();
    let Some(raised) = runs.try_with_untracked(|before| {
        list.iter()
            .filter(|r| Some(r.id) != watched)
            .filter_map(|r| {
                let previous = before.iter().find(|p| p.id == r.id)?;
                spintune::alert::status_alert(&previous.status, r)
            })
            .collect::<Vec<_>>()
    }) else {
        return;
    };
    for alert in raised {
        crate::attention::raise(alerts, alert, None);
    }
}

fn initial_run_from_hash() -> Option<u64> {
    let hash = window().location().hash().ok()?;
    hash.trim_start_matches('#')
        .strip_prefix("live/")?
        .parse()
        .ok()
}
