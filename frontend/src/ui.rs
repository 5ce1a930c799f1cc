//! Shared view pieces: a plotters canvas component and the dashboard of plots
//! used by both the live and the in-browser mode.

use leptos::html;
use leptos::prelude::*;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_canvas::CanvasBackend;
use wasm_bindgen::JsValue;

use spintune::protocol::{ParameterReport, RunStatus, TunerEvent};

use crate::charts;
use crate::model::{
    event_is_safety_relevant, event_name, format_lab_time, status_class, status_hint, status_label,
    History,
};

/// A drawing function for [`Chart`]: returns how many iterations it drew.
pub type Area = DrawingArea<CanvasBackend, Shift>;

fn note_first_chart(iterations: usize) {
    if iterations == 0 {
        return;
    }
    let w = window();
    let key = JsValue::from_str("spintuneFirstChartMs");
    let already = js_sys::Reflect::get(&w, &key)
        .map(|v| !v.is_undefined())
        .unwrap_or(true);
    if !already {
        let now = w.performance().map(|p| p.now()).unwrap_or(f64::NAN);
        let _ = js_sys::Reflect::set(&w, &key, &JsValue::from_f64(now));
    }
}

/// A `<canvas>` redrawn by plotters whenever the signals read in `draw` change.
/// The canvas takes the width of its container and the given height.
/// After each draw it carries `data-iterations` (iterations drawn) and
/// `data-draws` (number of draws), which the end-to-end test reads.
#[component]
pub fn Chart<F>(
    /// Name for tests and screen readers.
    #[prop(into)]
    name: String,
    /// Height in CSS pixels.
    height: u32,
    /// Draws the figure; returns the number of iterations drawn.
    draw: F,
) -> impl IntoView
where
    F: Fn(&Area) -> Result<usize, String> + 'static,
{
    let node = NodeRef::<html::Canvas>::new();
    let draws = StoredValue::new(0u64);
    Effect::new(move |_| {
        let Some(canvas) = node.get() else {
            return;
        };
        let ratio = window().device_pixel_ratio().clamp(1.0, 2.0);
        let css_w = canvas.client_width().max(320) as f64;
        canvas.set_width((css_w * ratio) as u32);
        canvas.set_height((height as f64 * ratio) as u32);
        let Some(backend) = CanvasBackend::with_canvas_object(canvas.clone()) else {
            return;
        };
        if let Ok(Some(ctx)) = canvas.get_context("2d") {
            use wasm_bindgen::JsCast;
            if let Ok(ctx) = ctx.dyn_into::<web_sys::CanvasRenderingContext2d>() {
                let _ = ctx.scale(ratio, ratio);
            }
        }
        let root = backend.into_drawing_area();
        let root = root.shrink((0, 0), (css_w as u32, height));
        let _ = root.fill(&WHITE);
        let drawn = match draw(&root) {
            Ok(n) => n,
            Err(e) => {
                leptos::logging::warn!("chart {}: {e}", canvas.id());
                0
            }
        };
        let _ = root.present();
        draws.update_value(|d| *d += 1);
        let _ = canvas.set_attribute("data-iterations", &drawn.to_string());
        let _ = canvas.set_attribute("data-draws", &draws.get_value().to_string());
        note_first_chart(drawn);
    });
    view! {
        <canvas
            node_ref=node
            class="chart"
            data-chart=name.clone()
            aria-label=name
            style=format!("height:{height}px")
        ></canvas>
    }
}

fn fmt_num(x: f64) -> String {
    charts::num_label(&x)
}

/// "t_sr 19.5 ± 0.6 ns → 20 ± 2" for the stats line.
fn param_summary(p: &ParameterReport) -> impl IntoView {
    let value = match (p.value, p.std) {
        (Some(v), Some(s)) => format!("{} ± {} {}", fmt_num(v), fmt_num(s), p.unit),
        (Some(v), None) => format!("{} {}", fmt_num(v), p.unit),
        _ => "no valid measurement".to_string(),
    };
    let target = match (p.target, p.tolerance) {
        (Some(t), Some(tol)) => format!("target {} ± {} {}", fmt_num(t), fmt_num(tol), p.unit),
        (Some(t), None) => format!("target {} {}", fmt_num(t), p.unit),
        _ => "no target".to_string(),
    };
    view! {
        <span class="stat" data-testid=format!("param-{}", p.name)>
            <i>{p.name.clone()}</i>" " <b>{value}</b>" " <span class="target-text">{format!("({target})")}</span>
        </span>
    }
}

/// Headline numbers of a history.
#[component]
pub fn Stats(history: RwSignal<History>) -> impl IntoView {
    let last = move || {
        history.with(|h| {
            h.last()
                .map(|r| (r.iteration, r.lab_seconds, r.tuned, r.failed_evaluations))
        })
    };
    view! {
        <div class="stats">
            {move || match last() {
                None => view! { <span class="stat">"no iterations yet"</span> }.into_any(),
                Some((k, lab, tuned, failed)) => view! {
                    <span class="stat">"iteration " <b data-testid="iteration">{k}</b></span>
                    <span class="stat">"lab time " <b data-testid="lab-time">{format_lab_time(lab)}</b></span>
                    <span class="stat">"failed fits " <b>{failed}</b></span>
                    {move || history.with(|h| h.last().map(|r| r.parameters.iter().map(param_summary).collect_view()))}
                    <span class=if tuned { "badge ok" } else { "badge" } data-testid="tuned">
                        {if tuned { "tuned: all parameters in band" } else { "tuning…" }}
                    </span>
                }.into_any(),
            }}
        </div>
    }
}

/// The plots of one run: parameters, gradients, gates, latest scans, lab time.
#[component]
pub fn Dashboard(history: RwSignal<History>) -> impl IntoView {
    let names = Memo::new(move |_| {
        history.with(|h| {
            h.last()
                .map(|r| {
                    r.parameters
                        .iter()
                        .map(|p| p.name.clone())
                        .collect::<Vec<_>>()
                })
                .unwrap_or_default()
        })
    });
    let scan_count = Memo::new(move |_| history.with(|h| h.last().map_or(0, |r| r.scans.len())));
    let events = Memo::new(move |_| {
        history.with(|h| {
            h.records()
                .iter()
                .rev()
                .flat_map(|r| r.events.iter().map(move |e| (r.iteration, e.clone())))
                .take(6)
                .collect::<Vec<_>>()
        })
    });
    view! {
        <div class="dashboard">
            <Stats history=history />
            <Show when=move || history.with(|h| h.is_empty())>
                <p class="hint">"Waiting for the first iteration…"</p>
            </Show>
            <h3>"Parameters"</h3>
            <div class="grid2">
                <For
                    each=move || names.get().into_iter().enumerate()
                    key=|(i, n)| (*i, n.clone())
                    children=move |(i, name)| {
                        let n2 = name.clone();
                        view! {
                            <Chart
                                name=format!("parameter-{name}")
                                height=270
                                draw=move |a: &Area| history.with(|h| charts::draw_parameter(a, h.records(), &n2, i).map(|_| h.len()))
                            />
                        }
                    }
                />
            </div>
            <h3>"Gradient estimates " <small>"(error bars: ±1σ = √diag C of the estimator)"</small></h3>
            <For
                each=move || names.get()
                key=|n| n.clone()
                children=move |name| {
                    let n2 = name.clone();
                    view! {
                        <Chart
                            name=format!("gradient-{name}")
                            height=210
                            draw=move |a: &Area| history.with(|h| charts::draw_gradient(a, h.records(), &n2).map(|_| h.len()))
                        />
                    }
                }
            />
            <h3>"Gate voltages"</h3>
            <Chart
                name="gates"
                height=200
                draw=move |a: &Area| history.with(|h| charts::draw_gates(a, h.records()).map(|_| h.len()))
            />
            <h3>"Latest scans and fits"</h3>
            <div class="grid2">
                <For
                    each=move || 0..scan_count.get().max(1)
                    key=|i| *i
                    children=move |i| view! {
                        <Chart
                            name=format!("scan-{i}")
                            height=250
                            draw=move |a: &Area| history.with(|h| {
                                let last = h.last();
                                charts::draw_scan(a, last.and_then(|r| r.scans.get(i)), last.map(|r| r.iteration)).map(|_| h.len())
                            })
                        />
                    }
                />
                <Chart
                    name="lab-time"
                    height=250
                    draw=move |a: &Area| history.with(|h| charts::draw_lab_time(a, h.records()).map(|_| h.len()))
                />
            </div>
            <Show when=move || !events.with(|e| e.is_empty())>
                <h3>"Recent events"</h3>
                <ul class="events" data-testid="events">
                    {move || events.get().into_iter().map(|(k, e)| event_item(k, e)).collect_view()}
                </ul>
            </Show>
        </div>
    }
}

/// One line of the event list: iteration, level and the event's sentence
/// (the text reads as the event's `Display`, `"<level>: <what>"`).
/// Safety-relevant events (the instrument moved, a refused move, a failed
/// evaluation, a gated outlier) carry the class `safety` and a warning sign.
fn event_item(iteration: u64, e: TunerEvent) -> impl IntoView {
    let safety = event_is_safety_relevant(&e.kind);
    view! {
        <li
            class=if safety { "event safety" } else { "event" }
            data-event=event_name(&e.kind)
            data-level=e.level.clone()
            title=if safety { "safety-relevant event" } else { "" }
        >
            <b>{format!("#{iteration} ")}</b>
            {safety.then(|| view! { <span class="event-flag" aria-label="safety-relevant">"⚠ "</span> })}
            <span class="event-level">{e.level.clone()}</span>
            {format!(": {}", e.kind)}
        </li>
    }
}

/// A run status as a badge: `class="status status-<name>"` and
/// `data-state="<name>"` (e.g. `status-faulted`, styled amber; `status-failed`, red).
#[component]
pub fn StatusBadge(
    /// The status (`None`: not known yet).
    #[prop(into)]
    status: Signal<Option<RunStatus>>,
    /// `data-testid` of the badge.
    #[prop(into)]
    testid: String,
    /// Text while the status is not known.
    #[prop(into)]
    unknown: String,
) -> impl IntoView {
    view! {
        <span
            class=move || status.with(|s| s.as_ref().map_or_else(|| "status status-unknown".to_string(), status_class))
            data-state=move || status.with(|s| s.as_ref().map_or("unknown", |s| s.name()))
            data-testid=testid
        >
            {move || status.with(|s| s.as_ref().map_or_else(|| unknown.clone(), status_label))}
        </span>
    }
}

/// What a status means, under the run header: a fault (amber: the run paused
/// itself and can be resumed) or a failure (red) with its message, or a
/// one-line hint for the other states that need one.
#[component]
pub fn StatusNote(
    /// The status (`None`: nothing shown).
    #[prop(into)]
    status: Signal<Option<RunStatus>>,
) -> impl IntoView {
    move || {
        status.with(|s| {
            let s = s.as_ref()?;
            let hint = status_hint(s);
            Some(match s {
                RunStatus::Faulted { fault } => view! {
                    <div class="status-note fault" role="alert" data-testid="fault" data-fault=fault.kind.name()>
                        <b>{format!("⚠ Paused by a {} fault", fault.kind.name())}</b>
                        {format!(": {}", fault.message)}
                        <div class="hint">{hint}</div>
                    </div>
                }
                .into_any(),
                RunStatus::Failed { message } => view! {
                    <div class="status-note failed" role="alert" data-testid="failed">
                        <b>"Run failed"</b>
                        {format!(": {message}")}
                        <div class="hint">{hint}</div>
                    </div>
                }
                .into_any(),
                other => {
                    let h = hint?;
                    view! {
                        <p class=format!("status-note {}", other.name()) data-testid="status-hint">{h}</p>
                    }
                    .into_any()
                }
            })
        })
    }
}
