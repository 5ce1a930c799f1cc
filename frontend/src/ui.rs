//! Shared view pieces: a plotters canvas component and the dashboard of plots
//! used by both the live and the in-browser mode.

use leptos::html;
use leptos::prelude::*;
use plotters::prelude::*;
use plotters_canvas::CanvasBackend;

use spintune::protocol::{ParameterReport, RunStatus, TunerEvent};

use crate::charts;
use crate::history::RunHistory;
use crate::metrics;
use crate::model::{
    event_is_safety_relevant, event_name, fault_clears_text, fault_kind_text, format_lab_time,
    moved_rows, stale_status_label, status_class, status_hint, status_label, tuned_badge,
};
use crate::schedule;
use crate::series::{self, Drawn, Viewport, XAxis};
use crate::widgets::{FieldError, NumberField};
use crate::zoom::{self, View, YRange};

/// Where a [`Chart`] draws: the data canvas layered over the frame canvas
/// ([`charts::Plot`]).
pub type Area<'a> = charts::Plot<'a, CanvasBackend>;

/// What a chart's figure depends on, compared between updates: the chart is
/// redrawn only when its key changes (e.g. a history's
/// [`RunHistory::rows_version`], the window's bounds as `f64::to_bits`, the
/// x axis). Reading the signals that the key is made of subscribes the chart
/// to them.
pub type ChartKey = Vec<u64>;

/// Key of a time-series chart: the rows drawn, the window and the x axis.
pub fn series_key(h: &RunHistory, w: zoom::Window, axis: XAxis) -> ChartKey {
    vec![
        h.rows_version(),
        w.lo.to_bits(),
        w.hi.to_bits(),
        axis as u64,
    ]
}

/// A chart drawn by plotters on two stacked canvases of the same size: the
/// frames of its plot areas (caption, axes, tick labels, grid) on the lower
/// one, redrawn only when a frame changes ([`charts::Plot`]), the data on the
/// upper, transparent one (cleared on every draw). `key` is read in an effect (subscribing
/// to the signals it reads); when it differs from the key of the latest
/// draw, `draw` is queued for the next animation frame ([`schedule`]), so
/// an update that does not change this chart's inputs costs no drawing,
/// and many updates within one frame cost one draw. `draw` runs untracked.
/// The canvas takes the width of its container and the given height.
/// After each draw it carries `data-iterations` (iterations in view),
/// `data-points` (points of the main series after decimation), `data-ymax`
/// (largest value drawn), `data-y0`/`data-y1` (the y range of the first
/// plot area), `data-rejected` (values drawn marked as rejected by the
/// tuner), `data-overlay-points` (points of a compared run),
/// `data-draws` (number of draws), `data-frames` (plot-area frames held on
/// the frame canvas below it) and, for charts with
/// one plot area, `data-px0`/`data-px1` (its pixel columns, CSS px) and
/// `data-x0`/`data-x1` (its data x range), which the mouse handlers and the
/// end-to-end test read. Each draw's time goes to [`metrics::note_draw`].
#[component]
pub fn Chart<K, F>(
    /// Name for tests and screen readers.
    #[prop(into)]
    name: String,
    /// Height in CSS pixels.
    height: u32,
    /// What the figure depends on (see [`ChartKey`]).
    key: K,
    /// Draws the figure.
    draw: F,
    /// Panels of a multi-panel chart ([`series::panel_grid`]): `height` is
    /// then one row's, and the canvas grows by the rows the width needs.
    #[prop(optional)]
    panels: Option<Signal<usize>>,
) -> impl IntoView
where
    K: Fn() -> ChartKey + 'static,
    F: Fn(&Area) -> Result<Drawn, charts::DrawError> + 'static,
{
    let node = NodeRef::<html::Canvas>::new();
    let back = NodeRef::<html::Canvas>::new();
    let draws = StoredValue::new(0u64);
    let id = schedule::new_id();
    on_cleanup(move || schedule::cancel(id));
    let draw = std::rc::Rc::new(draw);
    let frames = std::rc::Rc::new(charts::LayerCache::default());
    Effect::new(move |prev: Option<Option<ChartKey>>| {
        let k = key();
        let canvas = node.get()?;
        let background = back.get()?;
        if prev.flatten().as_ref() == Some(&k) {
            return Some(k);
        }
        let (draw, frames) = (draw.clone(), frames.clone());
        schedule::request(
            id,
            std::rc::Rc::new(move || {
                // Removed since it asked: nothing to draw.
                if draws.try_get_value().is_none() || !canvas.is_connected() {
                    return;
                }
                let layers = Layers {
                    data: &canvas,
                    frame: &background,
                    frames: &frames,
                };
                untrack(|| {
                    let rows = panels.map(|n| n.get());
                    paint(&layers, height, rows, &*draw, draws)
                });
            }),
        );
        Some(k)
    });
    let file = format!("spintune-{name}.png");
    let save = move |_| {
        if let (Some(data), Some(frame)) = (node.get_untracked(), back.get_untracked()) {
            if let Some(url) = composite(&data, &frame).and_then(|c| c.to_data_url().ok()) {
                download(&url, &file);
            }
        }
    };
    view! {
        <div class="chart-stack">
            <button class="save-png link" title="save this chart with its axes and labels as PNG" data-testid=format!("save-{name}") on:click=save>"PNG"</button>
            <canvas node_ref=back class="chart-frame" aria-hidden="true" style=format!("height:{height}px")></canvas>
            <canvas
                node_ref=node
                class="chart"
                data-chart=name.clone()
                aria-label=name
                style=format!("height:{height}px")
            ></canvas>
        </div>
    }
}

/// One canvas with a chart's frames (axes, labels, grid) and its data on
/// top, as the page shows them: what "save image" should give (each layer
/// alone is half a figure).
pub fn composite(
    data: &web_sys::HtmlCanvasElement,
    frame: &web_sys::HtmlCanvasElement,
) -> Option<web_sys::HtmlCanvasElement> {
    use wasm_bindgen::JsCast;
    let out: web_sys::HtmlCanvasElement =
        document().create_element("canvas").ok()?.dyn_into().ok()?;
    out.set_width(data.width());
    out.set_height(data.height());
    let ctx: web_sys::CanvasRenderingContext2d = out.get_context("2d").ok()??.dyn_into().ok()?;
    ctx.set_fill_style_str("#ffffff");
    ctx.fill_rect(0.0, 0.0, data.width() as f64, data.height() as f64);
    ctx.draw_image_with_html_canvas_element(frame, 0.0, 0.0)
        .ok()?;
    ctx.draw_image_with_html_canvas_element(data, 0.0, 0.0)
        .ok()?;
    Some(out)
}

/// Let the browser download `url` (a data: or blob: URL) as `file`.
pub fn download(url: &str, file: &str) {
    use wasm_bindgen::JsCast;
    let Some(a) = document()
        .create_element("a")
        .ok()
        .and_then(|a| a.dyn_into::<web_sys::HtmlAnchorElement>().ok())
    else {
        return;
    };
    a.set_href(url);
    a.set_download(file);
    a.click();
}

/// Download `text` as a file of type `mime`.
pub fn download_text(text: &str, file: &str, mime: &str) {
    let parts = js_sys::Array::of1(&wasm_bindgen::JsValue::from_str(text));
    let opts = web_sys::BlobPropertyBag::new();
    opts.set_type(mime);
    let Ok(blob) = web_sys::Blob::new_with_str_sequence_and_options(&parts, &opts) else {
        return;
    };
    if let Ok(url) = web_sys::Url::create_object_url_with_blob(&blob) {
        download(&url, file);
        let _ = web_sys::Url::revoke_object_url(&url);
    }
}

/// The two canvases of a [`Chart`] and the frames held on the lower one.
struct Layers<'a> {
    /// Data (transparent, on top; carries the `data-` attributes).
    data: &'a web_sys::HtmlCanvasElement,
    /// Frames (captions, axes, tick labels, grids), below.
    frame: &'a web_sys::HtmlCanvasElement,
    frames: &'a charts::LayerCache,
}

/// Set `canvas` to `w` × `h` device pixels (only if different: writing the
/// size resets the canvas and invalidates the page's layout) and its
/// context's transform to `ratio`; `true` if the size changed.
fn prepare(canvas: &web_sys::HtmlCanvasElement, w: u32, h: u32, ratio: f64, clear: bool) -> bool {
    let resized = canvas.width() != w || canvas.height() != h;
    if canvas.width() != w {
        canvas.set_width(w);
    }
    if canvas.height() != h {
        canvas.set_height(h);
    }
    if let Ok(Some(ctx)) = canvas.get_context("2d") {
        use wasm_bindgen::JsCast;
        if let Ok(ctx) = ctx.dyn_into::<web_sys::CanvasRenderingContext2d>() {
            if clear && !resized {
                let _ = ctx.set_transform(1.0, 0.0, 0.0, 1.0, 0.0, 0.0);
                ctx.clear_rect(0.0, 0.0, w as f64, h as f64);
            }
            let _ = ctx.set_transform(ratio, 0.0, 0.0, ratio, 0.0, 0.0);
        }
    }
    resized
}

/// Draw `draw` on the chart's canvases (CSS height `height` px) and publish
/// what it drew. The data canvas is cleared; the frame canvas keeps the
/// frames whose inputs did not change.
fn paint(
    layers: &Layers<'_>,
    height: u32,
    panels: Option<usize>,
    draw: &dyn Fn(&Area) -> Result<Drawn, charts::DrawError>,
    draws: StoredValue<u64>,
) {
    let t0 = metrics::now_ms();
    let canvas = layers.data;
    let ratio = window().device_pixel_ratio().clamp(1.0, 2.0);
    let css_w = canvas.client_width().max(200) as f64;
    let height = match panels {
        Some(n) => height * series::panel_grid(n, css_w).0 as u32,
        None => height,
    };
    let style = format!("height:{height}px");
    for c in [canvas, layers.frame] {
        if c.get_attribute("style").as_deref() != Some(style.as_str()) {
            let _ = c.set_attribute("style", &style);
        }
    }
    let (w, h) = ((css_w * ratio) as u32, (height as f64 * ratio) as u32);
    prepare(canvas, w, h, ratio, true);
    if prepare(layers.frame, w, h, ratio, false) {
        layers.frames.clear();
    }
    let root = |c: &web_sys::HtmlCanvasElement| {
        CanvasBackend::with_canvas_object(c.clone())
            .map(|b| b.into_drawing_area().shrink((0, 0), (css_w as u32, height)))
    };
    let (Some(data), Some(frame)) = (root(canvas), root(layers.frame)) else {
        return;
    };
    if layers.frames.is_empty() {
        let _ = frame.fill(&WHITE);
    }
    let plot = charts::Plot::layered(data.clone(), frame.clone(), layers.frames);
    let run = || {
        layers.frames.begin();
        let drawn = match draw(&plot) {
            Ok(d) => d,
            Err(e) => {
                leptos::logging::warn!("chart {}: {e}", canvas.id());
                Drawn::default()
            }
        };
        (drawn, layers.frames.end())
    };
    let (mut drawn, stale) = run();
    if stale {
        // The layout changed (e.g. a panel fewer): stale frames are still
        // on the frame canvas. Clear both and draw everything once more.
        layers.frames.clear();
        let _ = frame.fill(&WHITE);
        prepare(canvas, w, h, ratio, true);
        drawn = run().0;
    }
    let _ = data.present();
    let _ = frame.present();
    draws.update_value(|d| *d += 1);
    let set = |k: &str, v: String| {
        let _ = canvas.set_attribute(k, &v);
    };
    set("data-iterations", drawn.iterations.to_string());
    set("data-points", drawn.points.to_string());
    set("data-ymax", drawn.y_max.to_string());
    set("data-y0", drawn.y_range.0.to_string());
    set("data-y1", drawn.y_range.1.to_string());
    set("data-rejected", drawn.rejected.to_string());
    set("data-overlay-points", drawn.overlay_points.to_string());
    set("data-overlay-shift", drawn.overlay_shift.to_string());
    set("data-pinned", drawn.pinned.to_string());
    set("data-draws", draws.get_value().to_string());
    set("data-frames", layers.frames.len().to_string());
    if let Some((a, b)) = drawn.plot_px {
        set("data-px0", a.to_string());
        set("data-px1", b.to_string());
        set("data-x0", drawn.x_range.0.to_string());
        set("data-x1", drawn.x_range.1.to_string());
    }
    if let Some((w, cols)) = drawn.panels {
        set("data-panel-w", w.to_string());
        set("data-cols", cols.to_string());
    }
    metrics::note_draw(metrics::now_ms() - t0, drawn.iterations);
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

/// Headline numbers of a history (its newest record); the tuned badge reads
/// the run's `status` too ([`tuned_badge`]).
#[component]
pub fn Stats(
    history: RwSignal<RunHistory>,
    /// The run's status (`None`: not known).
    status: Option<Signal<Option<RunStatus>>>,
) -> impl IntoView {
    let last = Memo::new(move |_| history.with(|h| h.latest().cloned()));
    view! {
        <div class="stats">
            {move || match last.get() {
                None => view! { <span class="stat">"no iterations yet"</span> }.into_any(),
                Some(r) => view! {
                    <span class="stat">"iteration " <b data-testid="iteration">{r.iteration}</b></span>
                    <span class="stat">"lab time " <b data-testid="lab-time">{format_lab_time(r.lab_seconds)}</b></span>
                    <span class="stat">"failed fits " <b>{r.failed_evaluations}</b></span>
                    {r.parameters.iter().map(param_summary).collect_view()}
                    {move || {
                        let (text, ok) = match status {
                            Some(s) => s.with(|s| tuned_badge(r.tuned, s.as_ref())),
                            None => tuned_badge(r.tuned, None),
                        };
                        view! { <span class=if ok { "badge ok" } else { "badge" } data-testid="tuned">{text}</span> }
                    }}
                    {r.keep.as_ref().map(|k| view! {
                        <span class="stat keep" data-testid="keep" data-phase=format!("{:?}", k.phase).to_lowercase()>{crate::model::keep_label(k)}</span>
                    })}
                }.into_any(),
            }}
        </div>
    }
}

/// Thousands separators: 100000 → "100,000".
pub fn grouped(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i) % 3 == 0 {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// The iteration at CSS pixel `px` of a chart canvas (from its `data-px*`
/// and `data-x*` attributes), in the given x axis.
fn iteration_at(canvas: &web_sys::Element, px: f64, axis: XAxis, h: &RunHistory) -> Option<f64> {
    let num = |k: &str| canvas.get_attribute(k)?.parse::<f64>().ok();
    // A multi-panel chart: every panel column has the first one's x axis.
    let px = match num("data-panel-w") {
        Some(w) if w > 0.0 => px - (px / w).floor() * w,
        _ => px,
    };
    let x = zoom::pixel_to_data(
        px,
        num("data-px0")?,
        num("data-px1")?,
        num("data-x0")?,
        num("data-x1")?,
    );
    match axis {
        XAxis::Iteration => Some(x),
        XAxis::LabTime => h.at_lab_seconds(x * 3600.0).map(|k| k as f64),
    }
}

/// Text legend under a parameter chart (legends never cover data).
fn parameter_legend(i: usize, overlay: bool) -> impl IntoView {
    let c = charts::color(i);
    let css = format!("background: rgb({},{},{})", c.0, c.1, c.2);
    view! {
        <div class="legend">
            <span><i class="swatch" style=css></i>"measured ±1σ (decimated: min/max per pixel column)"</span>
            <span><i class="swatch target"></i>"target"</span>
            <span><i class="swatch band"></i>"tolerance band"</span>
            <span title="too uncertain, outlier-gated or refused by the estimator: not acted on, and not setting the y range (▵ at the edge: outside it)"><i class="swatch rejected"></i>"rejected by the tuner"</span>
            {overlay.then(|| view! { <span><i class="swatch overlay"></i>"compared run"</span> })}
        </div>
    }
}

/// The y range of one parameter chart ([`YRange`]): robust (auto), full
/// (rejected values too) or a typed min–max in the chart's unit. Manual
/// starts from the range drawn; a min not below the max is refused with
/// the reason. Test ids: `yrange-<name>`, `yrange-<name>-min`, `-max`.
#[component]
fn YRangeControl(
    name: String,
    unit: String,
    y_range: RwSignal<YRange>,
    drawn_y: StoredValue<(f64, f64)>,
) -> impl IntoView {
    // NumberField takes 'static ids: a few bytes per parameter chart, made
    // again only when a run with other parameters is shown.
    let id: &'static str = Box::leak(format!("yrange-{name}").into_boxed_str());
    let id_min: &'static str = Box::leak(format!("{id}-min").into_boxed_str());
    let id_max: &'static str = Box::leak(format!("{id}-max").into_boxed_str());
    let unit: &'static str = Box::leak(unit.into_boxed_str());
    let bounds = move || match y_range.get() {
        YRange::Manual(lo, hi) => (lo, hi),
        _ => drawn_y.get_value(),
    };
    let lo = Signal::derive(move || bounds().0);
    let hi = Signal::derive(move || bounds().1);
    let set_lo = Callback::new(move |v: f64| {
        if let Some(r) = YRange::manual(v, hi.get_untracked()) {
            y_range.set(r);
        }
    });
    let set_hi = Callback::new(move |v: f64| {
        if let Some(r) = YRange::manual(lo.get_untracked(), v) {
            y_range.set(r);
        }
    });
    let check_lo = Callback::new(move |v: f64| {
        if v < hi.get_untracked() {
            Ok(())
        } else {
            Err(FieldError::new("must be below the max"))
        }
    });
    let check_hi = Callback::new(move |v: f64| {
        if v > lo.get_untracked() {
            Ok(())
        } else {
            Err(FieldError::new("must be above the min"))
        }
    });
    view! {
        <div class="yrange">
            <label class="field" title="auto: the accepted values, trusted bands and targets (rejected values do not widen it); full: everything, rejected values too; manual: type min and max (values outside are pinned to the edge as ▲/▼)">
                <span class="field-label">"y range"</span>
                <select data-testid=id on:change=move |ev| {
                    match event_target_value(&ev).as_str() {
                        "full" => y_range.set(YRange::Full),
                        "manual" => {
                            let (a, b) = drawn_y.get_value();
                            y_range.set(YRange::manual(a, b).unwrap_or(YRange::Manual(0.0, 1.0)));
                        }
                        _ => y_range.set(YRange::Auto),
                    }
                }>
                    <option value="auto" selected=move || y_range.get() == YRange::Auto>"auto (robust)"</option>
                    <option value="full" selected=move || y_range.get() == YRange::Full>"full (rejected too)"</option>
                    <option value="manual" selected=move || matches!(y_range.get(), YRange::Manual(..))>"manual min–max"</option>
                </select>
            </label>
            <Show when=move || matches!(y_range.get(), YRange::Manual(..))>
                <NumberField label="min" unit=unit testid=id_min step="any" get=lo set=set_lo check=check_lo />
                <NumberField label="max" unit=unit testid=id_max step="any" get=hi set=set_hi check=check_hi />
            </Show>
        </div>
    }
}

/// "What the filter believes" ([`crate::belief`]), for students: at the
/// inspected iteration (else the latest) each gradient element ∂p/∂V ±1σ
/// with its unit, the gates' move since the previous iteration and, per
/// parameter, the change the filter predicted (g·Δv) next to the one
/// measured, in plain words.
#[component]
fn BeliefPanel(history: RwSignal<RunHistory>, inspected: RwSignal<Option<u64>>) -> impl IntoView {
    let belief = Memo::new(move |_| {
        let k = inspected
            .get()
            .or_else(|| history.with(|h| h.rows().last().map(|r| r.iteration)))?;
        history.with(|h| crate::belief::belief(h, k))
    });
    let pm = |v: f64, s: f64| {
        if s.is_finite() {
            format!("{} ± {}", series::fmt(v), series::fmt(s))
        } else {
            series::fmt(v)
        }
    };
    view! {
        <Show when=move || belief.with(|b| b.is_some())>
            <section class="belief" data-testid="belief"
                data-iteration=move || belief.with(|b| b.as_ref().map(|b| b.iteration.to_string()).unwrap_or_default())>
                <h3>{move || belief.with(|b| b.as_ref().map(|b| format!("What the filter believes at iteration {}", b.iteration)).unwrap_or_default())}</h3>
                <p class="hint">"How the measured parameters change when each gate moves by 1 mV (±1σ: how unsure the filter still is). A gradient in 1/mV is of ln p (log space): 0.01 /mV means p grows by about 1 % per mV."
                    {move || if inspected.get().is_some() { " Showing the inspected iteration." } else { " Showing the latest iteration; click a chart to pick another." }}</p>
                <div class="belief-table">
                <table data-testid="belief-gradients">
                    <thead><tr>
                        <th>"∂p/∂V"</th>
                        {move || belief.with(|b| b.as_ref().and_then(|b| b.gradients.first()).map(|g| g.elements.iter().map(|e| view! { <th>{e.gate.clone()}</th> }).collect_view()))}
                        <th>"unit"</th>
                    </tr></thead>
                    <tbody>
                        {move || belief.with(|b| b.as_ref().map(|b| b.gradients.iter().map(|g| view! {
                            <tr>
                                <th>{g.parameter.clone()}</th>
                                {g.elements.iter().map(|e| view! { <td>{pm(e.value, e.sigma)}</td> }).collect_view()}
                                <td>{g.unit.clone()}</td>
                            </tr>
                        }).collect_view()))}
                    </tbody>
                </table>
                </div>
                {move || belief.with(|b| b.as_ref().map(|b| match b.previous {
                    None => view! { <p data-testid="belief-moves">"No previous iteration loaded: nothing to compare a prediction with."</p> }.into_any(),
                    Some(j) => {
                        let moves = b.moves.iter().map(|(g, d)| format!("{g} {} mV", series::fmt(*d))).collect::<Vec<_>>().join(", ");
                        view! {
                            <p data-testid="belief-moves">{format!("Between iteration {j} and {} the gates moved by Δv: {moves}. With the gradient it held after iteration {j}, the filter predicted:", b.iteration)}</p>
                            <ul>
                                {b.predictions.iter().map(|p| view! { <li data-testid="belief-prediction">{crate::belief::sentence(p)}</li> }).collect_view()}
                            </ul>
                        }.into_any()
                    }
                }))}
            </section>
        </Show>
    }
}

/// What the dashboard shows besides the history: callbacks of its owner.
#[derive(Clone, Copy, Default)]
pub struct DashboardHooks {
    /// Called when the user inspects an iteration whose scans are not held
    /// (the live mode asks the server for them).
    pub want_scans: Option<Callback<u64>>,
    /// The run's status, for the tuned badge (`None`: not known).
    pub status: Option<Signal<Option<RunStatus>>>,
}

/// The plots of one run: parameters, gradients, gates, scans, lab time,
/// with a shared zoomable iteration window ([`View`]), a lab-time x axis,
/// hover read-out and an inspector for one iteration.
#[component]
pub fn Dashboard(
    history: RwSignal<RunHistory>,
    /// A second run drawn for comparison on the parameter, gradient and
    /// gate charts.
    #[prop(optional)]
    overlay: Option<RwSignal<Option<RunHistory>>>,
    #[prop(optional)] hooks: DashboardHooks,
) -> impl IntoView {
    let view_sel = RwSignal::new(View::All);
    let axis = RwSignal::new(XAxis::Iteration);
    // The compared run: shown, its version and whether it is aligned on
    // the first set-point change (part of the charts' keys).
    let align = RwSignal::new(false);
    let has_overlay = move || overlay.is_some_and(|o| o.with(|o| o.is_some()));
    let overlay_key = move || {
        overlay.map_or(0, |o| o.with(|o| o.as_ref().map_or(0, |h| h.version()))) * 2
            + align.get() as u64
    };
    let inspected = RwSignal::new(None::<u64>);
    let hover = RwSignal::new(None::<Hover>);
    // The window's width in steps of 40 CSS px: the charts redraw (and
    // multi-panel charts re-flow) when it changes.
    let width = RwSignal::new(viewport_width_step());
    let resize = window_event_listener(leptos::ev::resize, move |_| {
        let w = viewport_width_step();
        if width.get_untracked() != w {
            width.set(w);
        }
    });
    on_cleanup(move || resize.remove());
    let drag_from = StoredValue::new(None::<f64>);
    let extent = Memo::new(move |_| history.with(|h| h.extent()));
    let window_m = Memo::new(move |_| {
        let (a, b) = extent.get().unwrap_or((0, 10));
        view_sel.get().window(a as f64, b.max(a) as f64)
    });
    // What the charts draw: while the window follows new iterations (whole
    // run, last N), its end grows in steps so that the x axis (and the
    // charts' frames) change rarely during a live run.
    let draw_window = Memo::new(move |_| {
        let w = window_m.get();
        match view_sel.get() {
            View::All | View::Last(_) => zoom::grow_in_steps(w),
            View::Fixed(_) => w,
        }
    });
    let set_view = move |v: View| {
        view_sel.set(v);
    };
    let zoom_by = move |factor: f64, center: Option<f64>| {
        if let Some((a, b)) = extent.get_untracked() {
            set_view(
                view_sel
                    .get_untracked()
                    .zoom(factor, center, a as f64, b as f64),
            );
        }
    };
    let pan_by = move |fraction: f64| {
        if let Some((a, b)) = extent.get_untracked() {
            set_view(view_sel.get_untracked().pan(fraction, a as f64, b as f64));
        }
    };
    let inspect = move |k: u64| {
        inspected.set(Some(k));
        if history.with_untracked(|h| h.scans(k).is_none()) {
            if let Some(cb) = hooks.want_scans {
                cb.run(k);
            }
        }
    };
    let on_key = move |ev: leptos::ev::KeyboardEvent| {
        let handled = match ev.key().as_str() {
            "+" | "=" => {
                zoom_by(0.5, None);
                true
            }
            "-" | "_" => {
                zoom_by(2.0, None);
                true
            }
            "ArrowLeft" => {
                pan_by(-0.25);
                true
            }
            "ArrowRight" => {
                pan_by(0.25);
                true
            }
            "0" | "Home" => {
                set_view(View::All);
                true
            }
            "Escape" => {
                inspected.set(None);
                true
            }
            _ => false,
        };
        if handled {
            ev.prevent_default();
        }
    };
    let names = Memo::new(move |_| {
        history.with(|h| {
            h.layout()
                .parameters
                .iter()
                .map(|p| p.0.clone())
                .collect::<Vec<_>>()
        })
    });
    let gradients = Memo::new(move |_| {
        history.with(|h| {
            h.layout()
                .gradients
                .iter()
                .map(|g| g.0.clone())
                .collect::<Vec<_>>()
        })
    });
    let n_gates = Signal::derive(move || history.with(|h| h.layout().gates.len()));
    let latest_scans =
        Memo::new(move |_| history.with(|h| h.latest_scans().map_or(0, |(_, s)| s.len())));
    let events = Memo::new(move |_| history.with(|h| h.recent_events(6)));
    let loaded = move || {
        history.with(|h| {
            format!(
                "loaded {} / {} iterations",
                grouped(h.len() as u64),
                grouped(h.total())
            )
        })
    };
    let complete = move || history.with(|h| h.len() as u64 >= h.total());
    let showing = move || {
        let w = window_m.get();
        let (a, b) = (w.lo.ceil().max(0.0) as u64, w.hi.floor().max(0.0) as u64);
        match axis.get() {
            XAxis::Iteration => format!("iterations {}–{}", grouped(a), grouped(b)),
            XAxis::LabTime => history.with(|h| {
                let lab = |k: u64| h.nearest(k as f64).map_or(0.0, |r| r.lab_seconds / 3600.0);
                format!(
                    "iterations {}–{} (lab time {}–{} h:mm)",
                    grouped(a),
                    grouped(b),
                    series::hmm(&lab(a)),
                    series::hmm(&lab(b))
                )
            }),
        }
    };
    // Mouse on a chart: drag to zoom, click to inspect, double-click to reset, hover to read.
    let mouse_down = move |ev: leptos::ev::MouseEvent| {
        drag_from.set_value(Some(ev.offset_x() as f64));
    };
    let mouse_up = move |ev: leptos::ev::MouseEvent| {
        let Some(a) = drag_from.get_value() else {
            return;
        };
        drag_from.set_value(None);
        let Some(canvas) = ev.target().and_then(|t| {
            use wasm_bindgen::JsCast;
            t.dyn_into::<web_sys::Element>().ok()
        }) else {
            return;
        };
        let b = ev.offset_x() as f64;
        let ax = axis.get_untracked();
        history.with_untracked(|h| {
            let ka = iteration_at(&canvas, a, ax, h);
            let kb = iteration_at(&canvas, b, ax, h);
            if (a - b).abs() < 4.0 {
                if let Some(r) = kb.and_then(|k| h.nearest(k)) {
                    let k = r.iteration;
                    // release the borrow before signalling
                    leptos::task::spawn_local(async move { inspect(k) });
                }
            } else if let (Some(ka), Some(kb)) = (ka, kb) {
                let w = zoom::Window {
                    lo: ka.min(kb),
                    hi: ka.max(kb),
                };
                set_view(View::Fixed(w));
            }
        });
    };
    let mouse_move = move |ev: leptos::ev::MouseEvent| {
        let Some(canvas) = ev.target().and_then(|t| {
            use wasm_bindgen::JsCast;
            t.dyn_into::<web_sys::Element>().ok()
        }) else {
            return;
        };
        let k = history.with_untracked(|h| {
            iteration_at(&canvas, ev.offset_x() as f64, axis.get_untracked(), h)
                .and_then(|k| h.nearest(k))
                .map(|r| r.iteration)
        });
        let next = k.map(|k| Hover {
            iteration: k,
            chart: canvas.get_attribute("data-chart").unwrap_or_default(),
            at: (ev.client_x() as f64, ev.client_y() as f64),
        });
        if hover.with_untracked(|h| *h != next) {
            hover.set(next);
        }
    };
    let readout = move || {
        if let Some(h) = hover.get() {
            return Some(history.with(|hist| {
                let mut t = readout_text(hist, h.iteration);
                if let Some(g) = h.chart.strip_prefix("gradient-") {
                    t.push_str(" · ");
                    t.push_str(&gradient_readout(hist, h.iteration, g));
                }
                t
            }));
        }
        let k = inspected.get()?;
        Some(history.with(|h| readout_text(h, k)))
    };
    // Next to the pointer while hovering (kept inside the window).
    let readout_style = move || {
        hover.with(|h| {
            h.as_ref().map_or_else(String::new, |h| {
                let (vw, vh) = (
                    window()
                        .inner_width()
                        .ok()
                        .and_then(|v| v.as_f64())
                        .unwrap_or(1000.0),
                    window()
                        .inner_height()
                        .ok()
                        .and_then(|v| v.as_f64())
                        .unwrap_or(800.0),
                );
                let w = (vw - 16.0).min(420.0);
                let left = (h.at.0 + 14.0).min(vw - w - 8.0).max(8.0);
                let top = if h.at.1 + 120.0 > vh {
                    h.at.1 - 110.0
                } else {
                    h.at.1 + 16.0
                };
                format!("left:{left:.0}px;top:{top:.0}px;max-width:{w:.0}px")
            })
        })
    };
    view! {
        <div class="dashboard">
            <Stats history=history status=hooks.status />
            <Show when=move || history.with(|h| h.is_empty())>
                <p class="hint">"Waiting for the first iteration…"</p>
            </Show>
            <div class="viewbar" role="toolbar" aria-label="iteration window">
                <span class=move || if complete() { "loaded done" } else { "loaded" } data-testid="loaded">{loaded}</span>
                <button data-testid="zoom-in" title="zoom in (+)" on:click=move |_| zoom_by(0.5, None)>"+"</button>
                <button data-testid="zoom-out" title="zoom out (−)" on:click=move |_| zoom_by(2.0, None)>"−"</button>
                <button data-testid="pan-left" title="older (←)" on:click=move |_| pan_by(-0.25)>"◀"</button>
                <button data-testid="pan-right" title="newer (→)" on:click=move |_| pan_by(0.25)>"▶"</button>
                <button data-testid="zoom-reset" title="whole run (0, or double-click a chart)" on:click=move |_| set_view(View::All)>"all"</button>
                <label>"window "
                    <select data-testid="window-last" on:change=move |ev| {
                        let v = event_target_value(&ev);
                        set_view(v.parse::<u64>().map_or(View::All, View::Last));
                    }>
                        <option value="all" selected=move || view_sel.get() == View::All>"whole run"</option>
                        {[100u64, 1_000, 10_000].into_iter().map(|n| view! {
                            <option value=n.to_string() selected=move || view_sel.get() == View::Last(n)>{format!("last {} iterations", grouped(n))}</option>
                        }).collect_view()}
                    </select>
                </label>
                <label>"x axis "
                    <select data-testid="x-axis" on:change=move |ev| {
                        axis.set(if event_target_value(&ev) == "lab" { XAxis::LabTime } else { XAxis::Iteration });
                    }>
                        <option value="iteration">"iteration"</option>
                        <option value="lab">"lab time (h:mm)"</option>
                    </select>
                </label>
                <button data-testid="export-window-csv" title="the iterations in the window, every number with its unit, as CSV"
                    on:click=move |_| {
                        let w = window_m.get_untracked();
                        let csv = history.with_untracked(|h| crate::export::window_csv(h, w.lo, w.hi));
                        download_text(&csv, "spintune-window.csv", "text/csv");
                    }>"CSV of the window"</button>
                <Show when=has_overlay>
                    <label title="shift the compared run so that its first set-point change lines up with this run's (unshifted if either has none)">
                        <input type="checkbox" data-testid="overlay-align" prop:checked=move || align.get()
                            on:change=move |ev| align.set(event_target_checked(&ev)) />
                        " align the compared run on the first set-point change"
                    </label>
                </Show>
                <span class="showing" data-testid="showing">{showing}</span>
            </div>
            <p class="readout" class:floating=move || hover.with(|h| h.is_some()) style=readout_style data-testid="readout"
                data-chart=move || hover.with(|h| h.as_ref().map(|h| h.chart.clone()).unwrap_or_default())>{move || readout().unwrap_or_else(|| "Hover a chart to read values; click to inspect an iteration; drag to zoom; double-click to show the whole run. Keys on the charts: + − ← → 0.".into())}</p>
            <div class="timeseries" tabindex="0" data-testid="charts" aria-label="run charts: + and − zoom, arrow keys pan, 0 resets"
                on:keydown=on_key
                on:dblclick=move |_| set_view(View::All)
                on:mouseleave=move |_| hover.set(None)
            >
                <h3>"Parameters"</h3>
                <div class="grid2">
                    <For
                        each=move || names.get().into_iter().enumerate()
                        key=|(i, n)| (*i, n.clone())
                        children=move |(i, name)| {
                            let y_range = RwSignal::new(YRange::Auto);
                            let drawn_y = StoredValue::new((f64::NAN, f64::NAN));
                            let unit = history.with_untracked(|h| h.layout().parameters.get(i).map(|p| p.1.clone()).unwrap_or_default());
                            view! {
                                <div class="chart-box" on:mousedown=mouse_down on:mouseup=mouse_up on:mousemove=mouse_move>
                                    <Chart
                                        name=format!("parameter-{name}")
                                        height=270
                                        key=move || {
                                            let mut k = history.with(|h| series_key(h, draw_window.get(), axis.get()));
                                            k.push(width.get());
                                            k.push(overlay_key());
                                            k.extend(y_range.get().key());
                                            k
                                        }
                                        draw=move |a: &Area| {
                                            let w = draw_window.get();
                                            let ax = axis.get();
                                            let ov = overlay.map(|o| o.read());
                                            let drawn = history.with(|h| {
                                                let f = Viewport { history: h, window: w, axis: ax, overlay: ov.as_ref().and_then(|o| o.as_ref()), align: align.get() };
                                                series::draw_parameter(a, &f, i, i, y_range.get_untracked())
                                            });
                                            if let Ok(d) = &drawn {
                                                drawn_y.set_value(d.y_range);
                                            }
                                            drawn
                                        }
                                    />
                                    {move || parameter_legend(i, has_overlay())}
                                    <YRangeControl name=name.clone() unit=unit.clone() y_range=y_range drawn_y=drawn_y />
                                </div>
                            }
                        }
                    />
                </div>
                <h3>"Gradient estimates " <small>"(bars and bands: ±1σ = √diag C of the estimator)"</small></h3>
                <For
                    each=move || gradients.get().into_iter().enumerate()
                    key=|(i, n)| (*i, n.clone())
                    children=move |(g, name)| view! {
                        <div class="chart-box" on:mousedown=mouse_down on:mouseup=mouse_up on:mousemove=mouse_move>
                        <Chart
                            name=format!("gradient-{name}")
                            height=210
                            panels=n_gates
                            key=move || { let mut k = history.with(|h| series_key(h, draw_window.get(), axis.get())); k.push(width.get()); k.push(overlay_key()); k }
                            draw=move |a: &Area| {
                                let w = draw_window.get();
                                let ax = axis.get();
                                let ov = overlay.map(|o| o.read());
                                history.with(|h| series::draw_gradient(a, &Viewport { history: h, window: w, axis: ax, overlay: ov.as_ref().and_then(|o| o.as_ref()), align: align.get() }, g))
                            }
                        />
                        {move || has_overlay().then(|| view! { <div class="legend"><span><i class="swatch overlay"></i>"compared run (same unit only)"</span></div> })}
                        </div>
                    }
                />
                <BeliefPanel history=history inspected=inspected />
                <h3>"Gate voltages"</h3>
                <div class="chart-box" on:mousedown=mouse_down on:mouseup=mouse_up on:mousemove=mouse_move>
                <Chart
                    name="gates"
                    height=200
                    panels=n_gates
                    key=move || { let mut k = history.with(|h| series_key(h, draw_window.get(), axis.get())); k.push(width.get()); k.push(overlay_key()); k }
                    draw=move |a: &Area| {
                        let w = draw_window.get();
                        let ax = axis.get();
                        let ov = overlay.map(|o| o.read());
                        history.with(|h| series::draw_gates(a, &Viewport { history: h, window: w, axis: ax, overlay: ov.as_ref().and_then(|o| o.as_ref()), align: align.get() }))
                    }
                />
                {move || has_overlay().then(|| view! { <div class="legend"><span><i class="swatch overlay"></i>"compared run"</span></div> })}
                </div>
                <div class="chart-box" on:mousedown=mouse_down on:mouseup=mouse_up on:mousemove=mouse_move>
                    <Chart
                        name="lab-time"
                        height=220
                        key=move || { let mut k = history.with(|h| series_key(h, draw_window.get(), XAxis::Iteration)); k.push(width.get()); k }
                        draw=move |a: &Area| {
                            let w = draw_window.get();
                            history.with(|h| series::draw_lab_time(a, &Viewport { history: h, window: w, axis: XAxis::Iteration, overlay: None, align: false }))
                        }
                    />
                    <div class="legend"><span><i class="swatch lab"></i>"cumulative lab time"</span><span><i class="swatch band"></i>"tuned"</span></div>
                </div>
            </div>
            <Show when=move || inspected.get().is_some()>
                <Inspector history inspected />
            </Show>
            <h3>"Latest scans and fits"</h3>
            <div class="grid2">
                <For
                    each=move || 0..latest_scans.get().max(1)
                    key=|i| *i
                    children=move |i| view! {
                        <div class="chart-box">
                            <Chart
                                name=format!("scan-{i}")
                                height=250
                                key=move || history.with(|h| h.latest_scans_key().map_or(vec![0], |(k, n)| vec![1, k, n as u64]))
                                draw=move |a: &Area| history.with(|h| {
                                    let latest = h.latest_scans();
                                    charts::draw_scan(a, latest.and_then(|(_, s)| s.get(i)), latest.map(|(k, _)| k))
                                        .map(|_| Drawn { iterations: latest.map_or(0, |_| h.len()), ..Drawn::default() })
                                })
                            />
                            {move || history.with(|h| scan_legend(h.latest_scans().and_then(|(_, s)| s.get(i))))}
                        </div>
                    }
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

/// Where the pointer is over a chart: the iteration under it, the chart
/// (`data-chart`) and the pointer's position in the window (CSS px).
#[derive(Debug, Clone, PartialEq)]
struct Hover {
    iteration: u64,
    chart: String,
    at: (f64, f64),
}

/// `window.innerWidth` in steps of 40 CSS px.
fn viewport_width_step() -> u64 {
    let w = window()
        .inner_width()
        .ok()
        .and_then(|v| v.as_f64())
        .unwrap_or(0.0);
    (w / 40.0).round().max(0.0) as u64
}

/// The estimate of parameter `name`'s gradient at iteration `k`, every
/// gate, ±1σ with units (the hover read-out over a gradient chart), e.g.
/// "∂t_sr/∂V_N 0.52 ± 0.08 ns/mV".
pub fn gradient_readout(h: &RunHistory, k: u64, name: &str) -> String {
    let l = h.layout();
    let (Some(g), Some(d)) = (l.gradients.iter().position(|x| x.0 == name), h.values(k)) else {
        return String::new();
    };
    let unit = &l.gradients[g].1;
    l.gates
        .iter()
        .enumerate()
        .map(|(gi, gate)| {
            let o = l.grad(g, gi);
            let (v, s) = (d[o], d[o + 1]);
            if !v.is_finite() {
                format!("∂{name}/∂V_{gate} –")
            } else if s.is_finite() {
                format!("∂{name}/∂V_{gate} {} ± {} {unit}", fmt_num(v), fmt_num(s))
            } else {
                format!("∂{name}/∂V_{gate} {} {unit}", fmt_num(v))
            }
        })
        .collect::<Vec<_>>()
        .join(" · ")
}

/// Values of iteration `k` with units, for the hover read-out.
pub fn readout_text(h: &RunHistory, k: u64) -> String {
    let (Some(r), Some(d)) = (h.row(k), h.values(k)) else {
        return format!("iteration {k}: not loaded");
    };
    let l = h.layout();
    let mut parts = vec![
        format!("iteration {}", grouped(k)),
        format!("lab time {}", format_lab_time(r.lab_seconds)),
    ];
    for (i, (name, unit)) in l.parameters.iter().enumerate() {
        let o = l.param(i);
        let (v, s) = (d[o], d[o + 1]);
        let rejected = if d[l.rejected(i)].is_finite() {
            " (rejected)"
        } else {
            ""
        };
        if v.is_finite() {
            parts.push(format!(
                "{name} {} ± {} {unit}{rejected}",
                fmt_num(v),
                fmt_num(s)
            ));
        } else {
            parts.push(format!("{name} –"));
        }
    }
    for (i, gate) in l.gates.iter().enumerate() {
        parts.push(format!("V_{gate} {} mV", fmt_num(d[l.gate(i)])));
    }
    parts.join(" · ")
}

fn scan_legend(scan: Option<&spintune::protocol::ScanReport>) -> impl IntoView {
    scan.map(|s| {
        let data = s
            .raw
            .traces
            .iter()
            .enumerate()
            .map(|(i, t)| (format!("data: {}", t.label), charts::color(i + 4)));
        let fits = s
            .fit
            .iter()
            .enumerate()
            .map(|(i, t)| (t.label.clone(), charts::color(i + 1)));
        view! {
            <div class="legend">
                {data.chain(fits).map(|(label, c)| view! {
                    <span><i class="swatch" style=format!("background: rgb({},{},{})", c.0, c.1, c.2)></i>{label}</span>
                }).collect_view()}
            </div>
        }
    })
}

/// One inspected iteration: its numbers, step, events and scans with fits
/// (asked from the server when not held).
#[component]
fn Inspector(history: RwSignal<RunHistory>, inspected: RwSignal<Option<u64>>) -> impl IntoView {
    let k = move || inspected.get().unwrap_or(0);
    // A click on a chart far above must not open it off-screen: bring it
    // into view (the least scrolling that shows it) whenever it changes.
    let node = NodeRef::<html::Section>::new();
    Effect::new(move |_| {
        let _ = inspected.get();
        if let Some(el) = node.get() {
            let opts = web_sys::ScrollIntoViewOptions::new();
            opts.set_block(web_sys::ScrollLogicalPosition::Nearest);
            el.scroll_into_view_with_scroll_into_view_options(&opts);
        }
    });
    let details = move || {
        let k = k();
        history.with(|h| {
            let (Some(r), Some(d)) = (h.row(k), h.values(k)) else {
                return view! { <p class="hint">{format!("iteration {k} is not loaded yet")}</p> }.into_any();
            };
            let l = h.layout();
            let params = l
                .parameters
                .iter()
                .enumerate()
                .map(|(i, (name, unit))| {
                    let o = l.param(i);
                    format!(
                        "{name}: {} ± {} {unit}{} (target {} ± {} {unit})",
                        fmt_num(d[o]),
                        fmt_num(d[o + 1]),
                        if d[l.rejected(i)].is_finite() { ", rejected by the tuner" } else { "" },
                        fmt_num(d[o + 2]),
                        fmt_num(d[o + 3])
                    )
                })
                .collect_view();
            let step = l
                .gates
                .iter()
                .enumerate()
                .map(|(i, g)| format!("ΔV_{g} {} mV", fmt_num(d[l.gate(i) + 1])))
                .collect::<Vec<_>>()
                .join(", ");
            let events = h.events(k).to_vec();
            view! {
                <ul class="inspect-values">
                    <li>{format!("lab time {} ({} h:mm)", format_lab_time(r.lab_seconds), series::hmm(&(r.lab_seconds / 3600.0)))}</li>
                    {params.into_iter().map(|p| view! { <li>{p}</li> }).collect_view()}
                    <li data-testid="inspect-step">{format!("step: {step}")}</li>
                    <li>{if r.tuned { "tuned: all parameters in band" } else { "not tuned" }}</li>
                </ul>
                {if events.is_empty() {
                    view! { <p class="hint">"no events in this iteration"</p> }.into_any()
                } else {
                    view! { <ul class="events">{events.into_iter().map(|e| event_item(k, e)).collect_view()}</ul> }.into_any()
                }}
            }
            .into_any()
        })
    };
    let n_scans = Memo::new(move |_| {
        let k = k();
        history.with(|h| h.scans(k).map(|s| s.len()))
    });
    view! {
        <section class="inspector" node_ref=node data-testid="inspector" data-iteration=move || k().to_string()>
            <h3>{move || format!("Iteration {} ", grouped(k()))}
                <button class="link" on:click=move |_| inspected.set(None)>"close"</button>
            </h3>
            {details}
            {move || match n_scans.get() {
                None => view! { <p class="hint" data-testid="inspect-scans-loading">"loading this iteration's scans…"</p> }.into_any(),
                Some(0) => view! { <p class="hint">"no scans stored for this iteration"</p> }.into_any(),
                Some(n) => view! {
                    <div class="grid2" data-testid="inspect-scans">
                        {(0..n).map(|i| view! {
                            <div class="chart-box">
                                <Chart
                                    name=format!("inspect-scan-{i}")
                                    height=230
                                    key=move || { let k = k(); history.with(|h| vec![k, h.scans(k).map_or(0, |s| s.len() as u64 + 1)]) }
                                    draw=move |a: &Area| {
                                        let k = k();
                                        history.with(|h| charts::draw_scan(a, h.scans(k).and_then(|s| s.get(i)), Some(k)).map(|_| Drawn { iterations: 1, ..Drawn::default() }))
                                    }
                                />
                                {move || { let k = k(); history.with(|h| scan_legend(h.scans(k).and_then(|s| s.get(i)))) }}
                            </div>
                        }).collect_view()}
                    </div>
                }.into_any(),
            }}
        </section>
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
    /// Whether the page is connected to whoever owns the status (default
    /// yes). When not, a status that is not final is shown grey as the last
    /// one known ([`stale_status_label`]), with `data-stale="true"`.
    #[prop(optional, into)]
    connected: Option<Signal<bool>>,
) -> impl IntoView {
    let connected = move || connected.is_none_or(|c| c.get());
    let stale =
        move || status.with(|s| s.as_ref().and_then(|s| stale_status_label(s, connected())));
    view! {
        <span
            class=move || {
                if stale().is_some() {
                    return "status status-unknown status-stale".to_string();
                }
                status.with(|s| s.as_ref().map_or_else(|| "status status-unknown".to_string(), status_class))
            }
            data-state=move || status.with(|s| s.as_ref().map_or("unknown", |s| s.name()))
            data-stale=move || stale().is_some().to_string()
            data-testid=testid
            title=move || status.with(|s| s.as_ref().map(status_label))
        >
            {move || stale().unwrap_or_else(|| status.with(|s| s.as_ref().map_or_else(|| unknown.clone(), status_label)))}
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
                RunStatus::Faulted { fault } => {
                    let rows = moved_rows(fault);
                    let table = (!rows.is_empty()).then(|| view! {
                        <table class="moved" data-testid="moved-gates">
                            <thead><tr>
                                <th>"gate"</th>
                                <th class="num">"where the run left it (mV)"</th>
                                <th class="num">"reads now (mV)"</th>
                                <th class="num">"difference (mV)"</th>
                            </tr></thead>
                            <tbody>
                                {rows.into_iter().map(|r| view! {
                                    <tr data-gate=r.gate.clone()>
                                        <td class="gate">{r.gate.clone()}</td>
                                        <td class="num left">{r.left}</td>
                                        <td class="num read">{r.read}</td>
                                        <td class="num diff">{r.difference}</td>
                                    </tr>
                                }).collect_view()}
                            </tbody>
                        </table>
                    });
                    view! {
                        <div class="status-note fault" role="alert" data-testid="fault"
                            data-fault=fault.kind.name() data-cleared-by=fault.cleared_by.name()>
                            <b>{format!("⚠ {}", fault_kind_text(fault.kind))}</b>
                            {format!(": {}", fault.message)}
                            <div class="clears" data-testid="fault-clears">
                                <b>"What clears it: "</b>{fault_clears_text(fault.cleared_by)}
                            </div>
                            {table}
                            <div class="hint">{hint}</div>
                        </div>
                    }
                    .into_any()
                }
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
