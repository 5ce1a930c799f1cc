//! spintune dashboard: Leptos (CSR) in wasm.
//!
//! Two modes: **Live** streams a backend run over its WebSocket, **In-browser**
//! runs the whole tuner against the simulated double dot inside the page.

pub mod alerts;
pub mod api;
pub mod array_panel;
pub mod array_view;
pub mod attention;
pub mod axis;
pub mod belief;
pub mod cell_history;
pub mod charts;
pub mod decimate;
pub mod export;
pub mod heat_scale;
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

/// The page's colours: the system's preference (`prefers-color-scheme`), or
/// dark or light as chosen (kept in `localStorage["spintune-theme"]`), set
/// as `data-theme` on `<html>` for the style sheet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Theme {
    /// As the system says.
    Auto,
    /// Dark.
    Dark,
    /// Light.
    Light,
}

impl Theme {
    /// Name in `data-theme` and in storage.
    pub fn name(self) -> &'static str {
        match self {
            Theme::Auto => "auto",
            Theme::Dark => "dark",
            Theme::Light => "light",
        }
    }

    /// The toggle's text.
    pub fn label(self) -> &'static str {
        match self {
            Theme::Auto => "◐ auto",
            Theme::Dark => "☾ dark",
            Theme::Light => "☀ light",
        }
    }

    /// The next one on a click: auto → dark → light → auto.
    pub fn next(self) -> Self {
        match self {
            Theme::Auto => Theme::Dark,
            Theme::Dark => Theme::Light,
            Theme::Light => Theme::Auto,
        }
    }

    fn storage() -> Option<web_sys::Storage> {
        window().local_storage().ok().flatten()
    }

    /// The one chosen last on this browser (auto if none).
    pub fn stored() -> Self {
        match Self::storage()
            .and_then(|s| s.get_item("spintune-theme").ok().flatten())
            .as_deref()
        {
            Some("dark") => Theme::Dark,
            Some("light") => Theme::Light,
            _ => Theme::Auto,
        }
    }

    /// Show and remember it.
    pub fn apply(self) {
        if let Some(html) = document().document_element() {
            let _ = html.set_attribute("data-theme", self.name());
        }
        if let Some(s) = Self::storage() {
            let _ = s.set_item("spintune-theme", self.name());
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
    // The alerts of the runs this page follows (banner, title, favicon).
    let alerts: crate::attention::Alerts = RwSignal::new(crate::alerts::AlertCenter::new());
    provide_context(alerts);
    let go = move |m: Mode| {
        if m == Mode::Local {
            let _ = window().location().set_hash("local");
        }
        mode.set(m);
    };
    let theme = RwSignal::new(Theme::stored());
    Effect::new(move |_| theme.get().apply());
    view! {
        <header class="topbar">
            <h1>"spintune"</h1>
            <span class="subtitle">"Kalman-filter fine-tuning of a double-dot spin qubit"</span>
            <nav class="tabs">
                <button class:active=move || mode.get() == Mode::Live data-testid="tab-live" on:click=move |_| go(Mode::Live)>"Live runs"</button>
                <button class:active=move || mode.get() == Mode::Local data-testid="tab-local" on:click=move |_| go(Mode::Local)>"In-browser simulation"</button>
                <crate::attention::NotifyButton />
                <button class="theme-toggle" data-testid="theme" data-theme=move || theme.get().name()
                    title="colours: as the system says (auto), dark or light"
                    on:click=move |_| theme.update(|t| *t = t.next())>{move || theme.get().label()}</button>
            </nav>
        </header>
        <crate::attention::AlertBanner />
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
