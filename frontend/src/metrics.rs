//! Main-thread cost of the dashboard, measured in the page and published on
//! `window.__spintune_metrics` for the end-to-end test and BUDGET.md:
//!
//! * `firstChartMs` — `performance.now()` (ms since navigation start) when
//!   the first chart with at least one iteration was drawn;
//! * `updateMs` — total chart drawing time (ms) of the latest *update*: one
//!   animation frame in which at least one chart was redrawn (charts draw
//!   only when their inputs changed and at most once per frame, see
//!   [`crate::schedule`]; so an update is everything the live iterations,
//!   pages of history or changes of the view that arrived within one frame
//!   cost), `maxUpdateMs` the largest over the finished updates, `updates`
//!   how many began;
//! * `decimateMs` / `axesMs` — of `updateMs`, the time spent decimating
//!   series and drawing frames (caption, axes, tick labels, grid): the rest
//!   is drawing the data;
//! * `recentUpdateMs` / `recentAxesMs` — the last [`RECENT_UPDATES`]
//!   finished updates (oldest first): drawing time and, of it, frames, ms.
//!   A change that needs more than one frame's budget is drawn over
//!   consecutive frames ([`crate::schedule`]): its cost is the sum of its
//!   entries, and each entry is what one frame cost;
//! * `localSliceMs` / `maxLocalSliceMs` / `localSlices` — the in-browser
//!   mode's simulation between two yields to the browser (a slice of an
//!   iteration, `local::SLICE_MS`): the latest, the largest, how many;
//! * `wasmMemoryBytes` — size of the module's linear memory
//!   (`WebAssembly.Memory.buffer.byteLength`), bytes.

use std::cell::RefCell;
use std::collections::VecDeque;

use wasm_bindgen::{JsCast, JsValue};

#[derive(Default)]
struct Metrics {
    updates: u64,
    current_ms: f64,
    max_ms: f64,
    decimate_ms: f64,
    axes_ms: f64,
    first_chart_ms: Option<f64>,
    /// (update ms, frames ms) of the last finished updates.
    recent: VecDeque<(f64, f64)>,
    /// In-browser simulation slices: latest, largest (ms), count.
    slice_ms: f64,
    max_slice_ms: f64,
    slices: u64,
}

/// Finished updates kept in `recentUpdateMs` (bounded).
pub const RECENT_UPDATES: usize = 64;

thread_local! {
    static METRICS: RefCell<Metrics> = RefCell::new(Metrics::default());
}

/// `performance.now()`, ms (NaN outside a browser).
pub fn now_ms() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(f64::NAN, |p| p.now())
}

/// A new update begins (its chart draws are summed from now on).
pub fn begin_update() {
    METRICS.with(|m| {
        let mut m = m.borrow_mut();
        if m.current_ms > m.max_ms && m.updates > 0 {
            m.max_ms = m.current_ms;
        }
        m.updates += 1;
        m.current_ms = 0.0;
        m.decimate_ms = 0.0;
        m.axes_ms = 0.0;
    });
}

/// The update begun by [`begin_update`] is finished (its charts drew).
pub fn end_update() {
    METRICS.with(|m| {
        let mut m = m.borrow_mut();
        if m.recent.len() == RECENT_UPDATES {
            m.recent.pop_front();
        }
        let entry = (m.current_ms, m.axes_ms);
        m.recent.push_back(entry);
    });
}

/// A chart was drawn in `ms`, showing `iterations` iterations.
pub fn note_draw(ms: f64, iterations: usize) {
    METRICS.with(|m| {
        let mut m = m.borrow_mut();
        if ms.is_finite() {
            m.current_ms += ms;
        }
        if iterations > 0 && m.first_chart_ms.is_none() {
            m.first_chart_ms = Some(now_ms());
        }
    });
    publish();
}

/// A slice of the in-browser simulation took `ms` on the main thread.
pub fn note_local_slice(ms: f64) {
    if !ms.is_finite() {
        return;
    }
    METRICS.with(|m| {
        let mut m = m.borrow_mut();
        m.slice_ms = ms;
        m.max_slice_ms = m.max_slice_ms.max(ms);
        m.slices += 1;
    });
    publish();
}

/// What part of a chart draw a [`phase`] timed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Decimating a series to pixel columns.
    Decimate,
    /// Caption, axes, tick labels and grid of a plot area.
    Axes,
}

/// Run `f`, adding its time to `phase` of the current update.
pub fn phase<T>(phase: Phase, f: impl FnOnce() -> T) -> T {
    let t0 = now_ms();
    let out = f();
    let ms = now_ms() - t0;
    if ms.is_finite() {
        METRICS.with(|m| {
            let mut m = m.borrow_mut();
            match phase {
                Phase::Decimate => m.decimate_ms += ms,
                Phase::Axes => m.axes_ms += ms,
            }
        });
    }
    out
}

fn wasm_memory_bytes() -> f64 {
    wasm_bindgen::memory()
        .dyn_into::<js_sys::WebAssembly::Memory>()
        .ok()
        .and_then(|m| m.buffer().dyn_into::<js_sys::ArrayBuffer>().ok())
        .map_or(f64::NAN, |b| b.byte_length() as f64)
}

/// Write the numbers to `window.__spintune_metrics` (and the first-chart
/// time also to `window.spintuneFirstChartMs`, as before).
pub fn publish() {
    let Some(w) = web_sys::window() else { return };
    let obj = js_sys::Object::new();
    let set = |k: &str, v: f64| {
        let _ = js_sys::Reflect::set(&obj, &JsValue::from_str(k), &JsValue::from_f64(v));
    };
    let first = METRICS.with(|m| {
        let m = m.borrow();
        set("updates", m.updates as f64);
        set("updateMs", m.current_ms);
        set("maxUpdateMs", m.max_ms);
        set("decimateMs", m.decimate_ms);
        set("axesMs", m.axes_ms);
        set("firstChartMs", m.first_chart_ms.unwrap_or(f64::NAN));
        set("localSliceMs", m.slice_ms);
        set("maxLocalSliceMs", m.max_slice_ms);
        set("localSlices", m.slices as f64);
        let list = |f: fn(&(f64, f64)) -> f64| {
            m.recent
                .iter()
                .map(|e| JsValue::from_f64(f(e)))
                .collect::<js_sys::Array>()
        };
        let _ = js_sys::Reflect::set(&obj, &"recentUpdateMs".into(), &list(|e| e.0));
        let _ = js_sys::Reflect::set(&obj, &"recentAxesMs".into(), &list(|e| e.1));
        m.first_chart_ms
    });
    set("wasmMemoryBytes", wasm_memory_bytes());
    let _ = js_sys::Reflect::set(&w, &JsValue::from_str("__spintune_metrics"), &obj);
    if let Some(first) = first {
        let _ = js_sys::Reflect::set(
            &w,
            &JsValue::from_str("spintuneFirstChartMs"),
            &JsValue::from_f64(first),
        );
    }
}
