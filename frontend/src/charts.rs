//! Charts drawn with plotters (on a `<canvas>` through plotters-canvas in the
//! page). Every function draws one figure into a drawing area and labels
//! every axis with its unit.

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use spintune::protocol::{ScanKind, ScanReport};

use crate::axis::nice_range;
use crate::landscape::Landscape;
use crate::model::padded_range;

/// Why a figure could not be drawn (plotters' backend or layout error, as
/// text): the one error type of the drawing layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("drawing failed: {0}")]
pub struct DrawError(pub String);

/// Result of drawing a figure.
pub type DrawResult = Result<(), DrawError>;

pub(crate) const FONT: &str = "sans-serif";

/// Series colours (colour-blind friendly, Okabe–Ito).
pub const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(86, 180, 233),
    RGBColor(230, 159, 0),
    RGBColor(120, 120, 120),
    RGBColor(0, 0, 0),
];

pub(crate) const BAND: RGBColor = RGBColor(0, 158, 115);
pub(crate) const TARGET: RGBColor = RGBColor(0, 110, 80);

pub(crate) fn err<E: std::fmt::Debug>(e: E) -> DrawError {
    DrawError(format!("{e:?}"))
}

/// Pixel rectangle in absolute backend pixels: `(x range, y range)`.
pub type PixelRect = (std::ops::Range<i32>, std::ops::Range<i32>);

/// What a frame (caption, axes, tick labels, grid) of one plot area shows:
/// equal keys draw equal frames.
#[derive(Debug, Clone, PartialEq)]
struct AxesKey {
    caption: String,
    x_desc: String,
    y_desc: String,
    /// Axis ranges as `f64::to_bits`.
    x: (u64, u64),
    y: (u64, u64),
    small: bool,
    /// Address of the x label formatter.
    x_fmt: usize,
}

/// A frame drawn on the background canvas.
#[derive(Debug)]
struct CachedAxes {
    /// The plot area's whole region (absolute pixels).
    region: PixelRect,
    key: AxesKey,
    /// Its data rectangle (absolute pixels).
    plot: PixelRect,
    /// Used in the current draw.
    used: bool,
}

/// The frames a chart holds on its background canvas, by region. Between
/// [`LayerCache::begin`] and [`LayerCache::end`] every plot area drawn marks its
/// frame used; frames not used in a draw are stale (the layout changed).
#[derive(Debug, Default)]
pub struct LayerCache {
    entries: std::cell::RefCell<Vec<CachedAxes>>,
}

impl LayerCache {
    /// A draw begins.
    pub fn begin(&self) {
        for e in self.entries.borrow_mut().iter_mut() {
            e.used = false;
        }
    }

    /// A draw ended: drop the frames it did not use; `true` if there were
    /// any (their pixels are still on the background canvas: clear it,
    /// [`LayerCache::clear`] and draw again).
    pub fn end(&self) -> bool {
        let mut e = self.entries.borrow_mut();
        let n = e.len();
        e.retain(|e| e.used);
        e.len() != n
    }

    /// Forget every frame (the background canvas was cleared).
    pub fn clear(&self) {
        self.entries.borrow_mut().clear();
    }

    /// Cached frames held.
    pub fn len(&self) -> usize {
        self.entries.borrow().len()
    }

    /// Whether no frame is held.
    pub fn is_empty(&self) -> bool {
        self.entries.borrow().is_empty()
    }
}

/// Where a figure is drawn. Single: everything on one area. Layered: the
/// data on `area` (a transparent canvas cleared before every draw) and the
/// frames of the plot areas on a background canvas of the same geometry,
/// redrawn only when a frame's [`AxesKey`] changed ([`LayerCache`]).
pub struct Plot<'a, DB: DrawingBackend> {
    fg: DrawingArea<DB, Shift>,
    bg: Option<(DrawingArea<DB, Shift>, &'a LayerCache)>,
}

impl<'a, DB: DrawingBackend> Plot<'a, DB> {
    /// Everything on `area`.
    pub fn single(area: DrawingArea<DB, Shift>) -> Self {
        Self { fg: area, bg: None }
    }

    /// Data on `fg`, frames on `bg` (same geometry), remembered in `frames`.
    pub fn layered(
        fg: DrawingArea<DB, Shift>,
        bg: DrawingArea<DB, Shift>,
        frames: &'a LayerCache,
    ) -> Self {
        Self {
            fg,
            bg: Some((bg, frames)),
        }
    }

    /// The data area (for placeholders and elements without a frame).
    pub fn area(&self) -> &DrawingArea<DB, Shift> {
        &self.fg
    }

    /// Split into `(rows, cols)` equal plots (as `DrawingArea::split_evenly`).
    pub fn split_evenly(&self, rc: (usize, usize)) -> Vec<Plot<'a, DB>> {
        let fg = self.fg.split_evenly(rc);
        match &self.bg {
            None => fg.into_iter().map(Plot::single).collect(),
            Some((bg, frames)) => fg
                .into_iter()
                .zip(bg.split_evenly(rc))
                .map(|(f, b)| Plot::layered(f, b, frames))
                .collect(),
        }
    }
}

fn region<DB: DrawingBackend>(a: &DrawingArea<DB, Shift>) -> PixelRect {
    a.get_pixel_range()
}

/// A linear chart on `plot` in the dashboard's style: caption, axis
/// descriptions with units, light grid, number formatting. `small` is for the
/// rows of per-gate panels; `x_fmt` labels the x axis (e.g. whole
/// iterations or lab time h:mm). The y range is widened to [`nice_range`](crate::axis::nice_range).
/// On a layered plot the frame is drawn on the background only if it
/// changed, and the returned chart draws on the data canvas.
#[allow(clippy::too_many_arguments)]
pub(crate) fn styled_chart<'a, DB: DrawingBackend>(
    plot: &'a Plot<'_, DB>,
    caption: &str,
    x_desc: &str,
    y_desc: &str,
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    small: bool,
    x_fmt: &dyn Fn(&f64) -> String,
) -> Result<ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>, DrawError> {
    let (y0, y1) = nice_range(y.start, y.end);
    let y = y0..y1;
    let Some((bg, frames)) = &plot.bg else {
        return crate::metrics::phase(crate::metrics::Phase::Axes, || {
            styled_chart_inner(&plot.fg, caption, x_desc, y_desc, x, y, small, x_fmt)
        });
    };
    let key = AxesKey {
        caption: caption.to_string(),
        x_desc: x_desc.to_string(),
        y_desc: y_desc.to_string(),
        x: (x.start.to_bits(), x.end.to_bits()),
        y: (y.start.to_bits(), y.end.to_bits()),
        small,
        x_fmt: x_fmt as *const dyn Fn(&f64) -> String as *const () as usize,
    };
    let reg = region(&plot.fg);
    let held = {
        let mut entries = frames.entries.borrow_mut();
        entries
            .iter_mut()
            .find(|e| e.region == reg && e.key == key)
            .map(|e| {
                e.used = true;
                e.plot.clone()
            })
    };
    let rect = match held {
        Some(r) => r,
        None => {
            let r = crate::metrics::phase(crate::metrics::Phase::Axes, || {
                bg.fill(&WHITE).map_err(err)?;
                let c = styled_chart_inner(
                    bg,
                    caption,
                    x_desc,
                    y_desc,
                    x.clone(),
                    y.clone(),
                    small,
                    x_fmt,
                )?;
                Ok::<_, DrawError>(c.plotting_area().get_pixel_range())
            })?;
            let mut entries = frames.entries.borrow_mut();
            entries.retain(|e| e.region != reg);
            entries.push(CachedAxes {
                region: reg.clone(),
                key,
                plot: r.clone(),
                used: true,
            });
            r
        }
    };
    // The same data rectangle on the data canvas, without drawing a frame.
    let m = |v: i32| v.max(0) as u32;
    ChartBuilder::on(&plot.fg)
        .margin_left(m(rect.0.start - reg.0.start))
        .margin_right(m(reg.0.end - rect.0.end))
        .margin_top(m(rect.1.start - reg.1.start))
        .margin_bottom(m(reg.1.end - rect.1.end))
        .build_cartesian_2d(x, y)
        .map_err(err)
}

#[allow(clippy::too_many_arguments)]
fn styled_chart_inner<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    caption: &str,
    x_desc: &str,
    y_desc: &str,
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    small: bool,
    x_fmt: &dyn Fn(&f64) -> String,
) -> Result<ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>, DrawError> {
    let (caption_px, margin, x_area, y_area, label_px, desc_px) = if small {
        (15, 6, 34, 58, 11, 12)
    } else {
        (16, 8, 36, 62, 12, 13)
    };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FONT, caption_px))
        .margin(margin)
        // Room for half of the last x tick label: stepped ranges end on a
        // round number, which gets a label at the right edge.
        .margin_right(margin + if small { 10 } else { 18 })
        .x_label_area_size(x_area)
        .y_label_area_size(y_area)
        .build_cartesian_2d(x, y)
        .map_err(err)?;
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(x_fmt)
        .y_label_formatter(&num_label)
        .light_line_style(RGBColor(238, 238, 238))
        // Grid lines at the labels only: each line is a canvas stroke, and
        // ten light lines per interval (plotters' default) made the grid
        // the largest part of a redraw.
        .max_light_lines(0)
        .label_style((FONT, label_px))
        .axis_desc_style((FONT, desc_px))
        // Each label is a font change, a text measurement and a fill on the
        // canvas: six per axis (plotters' default is ten) keeps a frame
        // cheap enough that the live update which redraws every frame
        // stays within one animation frame (frontend/BUDGET.md).
        .x_labels(6)
        .y_labels(6);
    mesh.draw().map_err(err)?;
    Ok(chart)
}

/// Colour of series `i`.
pub fn color(i: usize) -> RGBColor {
    PALETTE[i % PALETTE.len()]
}

pub(crate) fn placeholder<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    title: &str,
    text: &str,
) -> DrawResult {
    let (w, h) = area.dim_in_pixel();
    area.draw(&Text::new(
        title.to_string(),
        (12, 10),
        (FONT, 16).into_font().style(FontStyle::Bold),
    ))
    .map_err(err)?;
    area.draw(&Text::new(
        text.to_string(),
        (w as i32 / 2 - 80, h as i32 / 2),
        (FONT, 14).into_font().color(&RGBColor(120, 120, 120)),
    ))
    .map_err(err)?;
    Ok(())
}

/// Axis range for values with error bars that is not dominated by a few
/// points with enormous uncertainty (failed or distrusted fits): error bars
/// count only when σ ≤ 5 × the median σ; the rest are clipped at the frame.
pub fn robust_range(points: &[(f64, f64, f64)], extra: impl Iterator<Item = f64>) -> (f64, f64) {
    let mut sig: Vec<f64> = points
        .iter()
        .map(|p| p.2)
        .filter(|s| s.is_finite())
        .collect();
    sig.sort_by(|a, b| a.total_cmp(b));
    let median = sig
        .get(sig.len().saturating_sub(1) / 2)
        .copied()
        .unwrap_or(0.0);
    let limit = 5.0 * median;
    let trusted: Vec<&(f64, f64, f64)> = points
        .iter()
        .filter(|p| p.2 <= limit || p.2 == 0.0)
        .collect();
    let core = trusted.iter().flat_map(|&&(_, v, s)| [v - s, v + s]);
    // Points with enormous σ (distrusted fits) are drawn but clipped at the frame.
    let all = points.iter().map(|p| p.1).filter(|_| trusted.is_empty());
    padded_range(core.chain(all).chain(extra), 0.08)
}

/// Tick label with a sensible number of digits (and no "-0").
pub fn num_label(x: &f64) -> String {
    let a = x.abs();
    let s = if a == 0.0 || a < 1e-12 {
        "0".to_string()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{x:.1e}")
    } else if a >= 100.0 {
        format!("{x:.0}")
    } else if a >= 10.0 {
        format!("{x:.1}")
    } else if a >= 1.0 {
        format!("{x:.2}")
    } else {
        format!("{x:.3}")
    };
    if s.starts_with('-') && s.trim_start_matches(['-', '0', '.']).is_empty() {
        s[1..].to_string()
    } else {
        s
    }
}

pub(crate) fn bar_width(n: usize) -> u32 {
    match n {
        0..=20 => 5,
        21..=40 => 3,
        _ => 0,
    }
}

pub(crate) fn int_label(x: &f64) -> String {
    if (x - x.round()).abs() < 1e-9 {
        format!("{x:.0}")
    } else {
        String::new()
    }
}

/// Title of a scan kind.
pub fn scan_title(kind: ScanKind) -> &'static str {
    match kind {
        ScanKind::SensingDot => "sensing-dot sweep",
        ScanKind::ChemicalPotential => "chemical-potential scan",
        ScanKind::TransitionWidth => "detuning scan (w)",
        ScanKind::ReloadTime => "load curve (t_sr)",
    }
}

/// One raw scan (points) with its fitted curve(s) (lines).
pub fn draw_scan<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    scan: Option<&ScanReport>,
    iteration: Option<u64>,
) -> DrawResult {
    let area = plot.area();
    let Some(scan) = scan else {
        return placeholder(area, "latest scan", "no scan yet");
    };
    let all = scan.raw.traces.iter().chain(scan.fit.iter());
    let (x0, x1) = padded_range(all.clone().flat_map(|t| t.x.iter().copied()), 0.02);
    let (y0, y1) = padded_range(all.flat_map(|t| t.y.iter().copied()), 0.08);
    // The caption is part of the frame (kept while the axes stay); the
    // iteration, which changes with every live scan, is drawn with the data.
    let mut chart = styled_chart(
        plot,
        scan_title(scan.raw.kind),
        scan.raw.x_label.as_str(),
        scan.raw.y_label.as_str(),
        x0..x1,
        y0..y1,
        false,
        &num_label,
    )?;
    for (i, t) in scan.raw.traces.iter().enumerate() {
        let c = color(i + 4);
        chart
            .draw_series(
                t.x.iter()
                    .zip(&t.y)
                    .filter(|(x, y)| x.is_finite() && y.is_finite())
                    .map(|(&x, &y)| Circle::new((x, y), 2, c.mix(0.7).filled())),
            )
            .map_err(err)?
            .label(format!("data: {}", t.label))
            .legend(move |(x, y)| Circle::new((x + 8, y), 3, c.filled()));
    }
    for (i, t) in scan.fit.iter().enumerate() {
        let c = color(i + 1);
        chart
            .draw_series(LineSeries::new(
                t.x.iter()
                    .zip(&t.y)
                    .filter(|(x, y)| x.is_finite() && y.is_finite())
                    .map(|(&x, &y)| (x, y)),
                c.stroke_width(2),
            ))
            .map_err(err)?
            .label(t.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(2)));
    }
    if let Some(k) = iteration {
        use plotters::style::text_anchor::{HPos, Pos, VPos};
        let style = (FONT, 13)
            .into_font()
            .color(&RGBColor(90, 90, 90))
            .pos(Pos::new(HPos::Right, VPos::Top));
        let w = area.dim_in_pixel().0 as i32;
        area.draw(&Text::new(format!("iteration {k}"), (w - 10, 6), style))
            .map_err(err)?;
    }
    if scan.fit.is_empty() {
        area.draw(&Text::new(
            "fit failed",
            (80, 40),
            (FONT, 14).into_font().color(&RGBColor(200, 40, 40)),
        ))
        .map_err(err)?;
    }
    Ok(())
}

/// Colour of a distance-to-target value (tolerance units): greens inside the
/// band (≤ 1), then yellow → red → dark purple on a log scale up to 100.
pub fn error_color(e: f64) -> RGBColor {
    if !e.is_finite() {
        return RGBColor(220, 220, 220);
    }
    let lerp = |a: (u8, u8, u8), b: (u8, u8, u8), t: f64| {
        let t = t.clamp(0.0, 1.0);
        let m = |x: u8, y: u8| (x as f64 + (y as f64 - x as f64) * t).round() as u8;
        RGBColor(m(a.0, b.0), m(a.1, b.1), m(a.2, b.2))
    };
    if e <= 1.0 {
        return lerp((0, 120, 85), (120, 205, 160), e);
    }
    let stops = [(255, 240, 170), (245, 150, 60), (200, 50, 60), (70, 20, 90)];
    let t = (e.log10() / 2.0).clamp(0.0, 1.0) * (stops.len() - 1) as f64;
    let i = (t.floor() as usize).min(stops.len() - 2);
    lerp(stops[i], stops[i + 1], t - i as f64)
}

/// Heat map of the ground-truth distance to target over two gates, with the
/// tuner's path (black) and optionally a second run's path (`other`, mV,
/// orange dashes of dots: the estimator race).
pub fn draw_landscape<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    land: Option<&Landscape>,
    other: &[(f64, f64)],
) -> DrawResult {
    let area = plot.area();
    let Some(l) = land else {
        return placeholder(
            area,
            "distance to target",
            "press Run or Step to build the device",
        );
    };
    let n = l.xs.len();
    if n < 2 || l.ys.len() != n {
        return Ok(());
    }
    let (dx, dy) = (l.xs[1] - l.xs[0], l.ys[1] - l.ys[0]);
    let (x0, x1) = (l.xs[0] - dx / 2.0, l.xs[n - 1] + dx / 2.0);
    let (y0, y1) = (l.ys[0] - dy / 2.0, l.ys[n - 1] + dy / 2.0);
    let (main, bar) = area.split_horizontally(area.dim_in_pixel().0.saturating_sub(90));
    let mut chart = ChartBuilder::on(&main)
        .caption(
            format!("distance to target over (V_{}, V_{})", l.gx, l.gy),
            (FONT, 16),
        )
        .margin(8)
        .x_label_area_size(36)
        .y_label_area_size(62)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc(format!("V_{} (mV)", l.gx))
        .y_desc(format!("V_{} (mV)", l.gy))
        .x_label_formatter(&num_label)
        .y_label_formatter(&num_label)
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 13))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(l.ys.iter().enumerate().flat_map(|(j, y)| {
            l.xs.iter().enumerate().map(move |(i, x)| {
                Rectangle::new(
                    [(x - dx / 2.0, y - dy / 2.0), (x + dx / 2.0, y + dy / 2.0)],
                    error_color(l.error[j * n + i]).filled(),
                )
            })
        }))
        .map_err(err)?;
    let in_view: Vec<(f64, f64)> = l
        .path
        .iter()
        .copied()
        .filter(|&(x, y)| (x0..=x1).contains(&x) && (y0..=y1).contains(&y))
        .collect();
    chart
        .draw_series(LineSeries::new(
            in_view.iter().copied(),
            BLACK.stroke_width(2),
        ))
        .map_err(err)?;
    chart
        .draw_series(in_view.iter().map(|&p| Circle::new(p, 3, BLACK.filled())))
        .map_err(err)?;
    let other: Vec<(f64, f64)> = other
        .iter()
        .copied()
        .filter(|&(x, y)| (x0..=x1).contains(&x) && (y0..=y1).contains(&y))
        .collect();
    let oc = PALETTE[1];
    chart
        .draw_series(LineSeries::new(other.iter().copied(), oc.stroke_width(2)))
        .map_err(err)?;
    chart
        .draw_series(
            other
                .iter()
                .map(|&p| TriangleMarker::new(p, 4, oc.filled())),
        )
        .map_err(err)?;
    chart
        .draw_series(std::iter::once(Circle::new(
            l.now,
            7,
            WHITE.stroke_width(3),
        )))
        .map_err(err)?;
    // Colour bar: 0.1 … 100 tolerance units, log scale.
    let mut cb = ChartBuilder::on(&bar)
        .margin_top(40)
        .margin_bottom(44)
        .margin_right(8)
        .y_label_area_size(40)
        .build_cartesian_2d(0.0..1.0, -1.0..2.0)
        .map_err(err)?;
    cb.configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .y_desc("|p − p*| / tol")
        .y_labels(4)
        .y_label_formatter(&|v| format!("{}", 10f64.powf(*v)))
        .label_style((FONT, 11))
        .axis_desc_style((FONT, 12))
        .draw()
        .map_err(err)?;
    cb.draw_series((0..60).map(|k| {
        let a = -1.0 + 3.0 * k as f64 / 60.0;
        let b = a + 3.0 / 60.0;
        Rectangle::new(
            [(0.0, a), (1.0, b)],
            error_color(10f64.powf((a + b) / 2.0)).filled(),
        )
    }))
    .map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn labels_and_robust_range() {
        assert_eq!(num_label(&-0.0001e-9), "0");
        assert_eq!(num_label(&-0.0), "0");
        assert_eq!(num_label(&270.0), "270");
        assert_eq!(num_label(&0.25), "0.250");
        let pts = [
            (0.0, 10.0, 1.0),
            (1.0, 12.0, 1.0),
            (2.0, 11.0, 500.0),
            (3.0, 250.0, 600.0),
        ];
        let (lo, hi) = robust_range(&pts, std::iter::empty());
        assert!(lo > -10.0 && hi < 30.0, "{lo} {hi}");
    }
}
