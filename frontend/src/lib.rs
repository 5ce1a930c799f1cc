//! spintune dashboard: Leptos (CSR) in wasm.
//!
//! Two modes: **Live** streams a backend run over its WebSocket, **In-browser**
//! runs the whole tuner against the simulated double dot inside the page.

pub mod api;
pub mod axis;
pub mod charts;
pub mod decimate;
pub mod history;
pub mod landscape;
pub mod live;
pub mod local;
pub mod metrics;
pub mod model;
pub mod schedule;
pub mod series;
pub mod ui;
pub mod widgets;
pub mod zoom;

use leptos::prelude::*;

use crate::api::ApiBase;
use crate::live::LiveMode;
use crate::local::LocalMode;

/// Which half of the app is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Stream a backend run.
    Live,
    /// Tune the simulated dot in the page.
    Local,
}

impl Mode {
    /// From `location.hash`: `#local` → Local, anything else → Live.
    pub fn from_hash(hash: &str) -> Self {
        if hash.trim_start_matches('#').starts_with("local") {
            Mode::Local
        } else {
            Mode::Live
        }
    }
}

/// The whole page.
#[component]
pub fn App(
    #[prop(optional)] base: Option<ApiBase>,
    #[prop(optional)] mode: Option<Mode>,
) -> impl IntoView {
    let base = base.unwrap_or_else(ApiBase::from_location);
    let initial =
        mode.unwrap_or_else(|| Mode::from_hash(&window().location().hash().unwrap_or_default()));
    let mode = RwSignal::new(initial);
    provide_context(mode);
    // The in-browser mode's run lives as long as the page, not the tab.
    provide_context(crate::local::LocalState::new());
    let go = move |m: Mode| {
        if m == Mode::Local {
            let _ = window().location().set_hash("local");
        }
        mode.set(m);
    };
    view! {
        <header class="topbar">
            <h1>"spintune"</h1>
            <span class="subtitle">"Kalman-filter fine-tuning of a double-dot spin qubit"</span>
            <nav class="tabs">
                <button class:active=move || mode.get() == Mode::Live data-testid="tab-live" on:click=move |_| go(Mode::Live)>"Live runs"</button>
                <button class:active=move || mode.get() == Mode::Local data-testid="tab-local" on:click=move |_| go(Mode::Local)>"In-browser simulation"</button>
            </nav>
        </header>
        {move || match mode.get() {
            Mode::Live => view! { <LiveMode base=base.clone() /> }.into_any(),
            Mode::Local => view! { <LocalMode /> }.into_any(),
        }}
    }
}

/// Entry point of the wasm binary: mount [`App`] on `<body>`.
pub fn start() {
    console_error_panic_hook::set_once();
    leptos::mount::mount_to_body(|| view! { <App /> });
}

#[cfg(all(test, target_arch = "wasm32"))]
wasm_bindgen_test::wasm_bindgen_test_configure!(run_in_browser);
