//! The time-series charts of a run (parameters, gradients, gate voltages,
//! lab time), drawn from a [`RunHistory`] over the shared iteration
//! [`Window`], decimated per pixel column ([`crate::decimate`]) so that a run
//! of 100,000 iterations draws a few thousand points and keeps its spikes.
//!
//! The x axis is the iteration number or the lab time (h:mm, [`XAxis`]).
//! Legends are not drawn on the canvas (they would cover data): the page
//! shows them as text next to each chart.

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::charts::{
    bar_width, color, err, int_label, num_label, placeholder, styled_chart, DrawError, Plot, BAND,
    TARGET,
};
use crate::decimate::{min_max, Columns};
use crate::history::{Row, RunHistory};
use crate::model::padded_range;
use crate::zoom::{pin, Window, YRange};

/// What the x axis shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum XAxis {
    /// Iteration number.
    Iteration,
    /// Cumulative lab time, drawn in hours and labelled h:mm.
    LabTime,
}

impl XAxis {
    /// The x coordinate of a row: iteration, or lab time in hours.
    pub fn x(self, r: &Row) -> f64 {
        match self {
            XAxis::Iteration => r.iteration as f64,
            XAxis::LabTime => r.lab_seconds / 3600.0,
        }
    }

    /// Axis description with its unit.
    pub fn desc(self) -> &'static str {
        match self {
            XAxis::Iteration => "iteration",
            XAxis::LabTime => "lab time (h:mm)",
        }
    }
}

/// Lab time in hours as `h:mm` (e.g. `1.5` → `"1:30"`).
pub fn hmm(hours: &f64) -> String {
    if !hours.is_finite() {
        return String::new();
    }
    let m = (hours * 60.0).round() as i64;
    let sign = if m < 0 { "-" } else { "" };
    format!("{sign}{}:{:02}", m.abs() / 60, m.abs() % 60)
}

/// What a time-series chart shows.
#[derive(Clone, Copy)]
pub struct Viewport<'a> {
    /// The run.
    pub history: &'a RunHistory,
    /// Iterations shown.
    pub window: Window,
    /// The x axis.
    pub axis: XAxis,
    /// A second run drawn for comparison (parameters, gradients, gates).
    pub overlay: Option<&'a RunHistory>,
    /// Shift the compared run so that its first set-point change lines up
    /// with this run's ([`RunHistory::first_target_change`]; unshifted when
    /// either run has none).
    pub align: bool,
}

impl Viewport<'_> {
    fn range(&self) -> std::ops::Range<usize> {
        self.history.range(self.window.lo, self.window.hi)
    }

    fn rows(&self) -> &[Row] {
        &self.history.rows()[self.range()]
    }

    /// Column `c` of the history over the rows in the window.
    fn column(&self, c: usize) -> &[f64] {
        self.history.column(c).get(self.range()).unwrap_or(&[])
    }

    /// The x range drawn.
    pub fn x_range(&self) -> (f64, f64) {
        match self.axis {
            XAxis::Iteration => (
                self.window.lo - 0.5,
                self.window.hi.max(self.window.lo + 1.0) + 0.5,
            ),
            XAxis::LabTime => {
                let rows = self.rows();
                let a = rows.first().map_or(0.0, |r| XAxis::LabTime.x(r));
                let b = rows.last().map_or(1.0, |r| XAxis::LabTime.x(r));
                if b - a > 1e-9 {
                    let pad = 0.01 * (b - a);
                    (a - pad, b + pad)
                } else {
                    (a - 0.01, a + 0.01)
                }
            }
        }
    }

    /// How far the compared run is shifted: `(iterations, x units)`.
    pub fn overlay_shift(&self) -> (f64, f64) {
        let Some(o) = self.overlay.filter(|_| self.align) else {
            return (0.0, 0.0);
        };
        let both = self
            .history
            .first_target_change()
            .zip(o.first_target_change());
        let Some((a, b)) = both else {
            return (0.0, 0.0);
        };
        let (ra, rb) = (self.history.row(a), o.row(b));
        let dx = match (ra, rb) {
            (Some(ra), Some(rb)) => self.axis.x(ra) - self.axis.x(rb),
            _ => 0.0,
        };
        (a as f64 - b as f64, dx)
    }

    /// The compared run's column (chosen in its own layout by `col`; none
    /// if it has no such series) over the window, shifted
    /// ([`Viewport::overlay_shift`]) and decimated to `cols` pixel columns.
    fn overlay_line(
        &self,
        col: impl Fn(&crate::history::Layout) -> Option<usize>,
        (x0, x1): (f64, f64),
        cols: usize,
    ) -> Vec<(f64, f64)> {
        let Some(h) = self.overlay else {
            return Vec::new();
        };
        let Some(c) = col(h.layout()) else {
            return Vec::new();
        };
        let (dk, dx) = self.overlay_shift();
        let r = h.range(self.window.lo - dk, self.window.hi - dk);
        let xy: Vec<(f64, f64)> = h.rows()[r.clone()]
            .iter()
            .zip(h.column(c).get(r).unwrap_or(&[]))
            .map(|(row, v)| (self.axis.x(row) + dx, *v))
            .collect();
        min_max(&xy, x0, x1, cols)
    }

    fn x_fmt(&self) -> &'static dyn Fn(&f64) -> String {
        match self.axis {
            XAxis::Iteration => &int_label,
            XAxis::LabTime => &hmm,
        }
    }
}

/// What a chart drew: for the page's `data-` attributes (read by the tests)
/// and for mapping mouse positions to iterations.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Drawn {
    /// Iterations in the window.
    pub iterations: usize,
    /// Points of the main series drawn (after decimation).
    pub points: usize,
    /// Largest value of the main series drawn (NaN if none).
    pub y_max: f64,
    /// The y range of the (first) plot area (NaN if none).
    pub y_range: (f64, f64),
    /// Values drawn marked as rejected by the tuner (parameter charts;
    /// after decimation), whether inside the y range or pinned to its edge.
    pub rejected: usize,
    /// Points of the compared run drawn (all panels).
    pub overlay_points: usize,
    /// Iterations the compared run is shifted by ([`Viewport::overlay_shift`]).
    pub overlay_shift: f64,
    /// Accepted values drawn pinned to an edge of a manual y range
    /// ([`YRange::Manual`], parameter charts; after decimation).
    pub pinned: usize,
    /// Pixel columns `[left, right]` of the plot area (CSS px), if it has one.
    pub plot_px: Option<(f64, f64)>,
    /// Data x range of the plot area.
    pub x_range: (f64, f64),
    /// Charts of several panels ([`panel_grid`]): the width of one column
    /// of panels (CSS px) and the number of columns; `plot_px` is then the
    /// first panel's.
    pub panels: Option<(f64, usize)>,
}

/// Narrowest a panel of a multi-panel chart may be, CSS px.
pub const MIN_PANEL_PX: f64 = 230.0;

/// `(rows, columns)` for `n` panels in a chart `width` CSS px wide: all in
/// one row when each gets at least [`MIN_PANEL_PX`], else two columns,
/// else one (a phone: one panel per row).
pub fn panel_grid(n: usize, width: f64) -> (usize, usize) {
    let n = n.max(1);
    let cols = if width >= MIN_PANEL_PX * n as f64 {
        n
    } else if n >= 2 && width >= 2.0 * MIN_PANEL_PX {
        2
    } else {
        1
    };
    (n.div_ceil(cols), cols)
}

fn plot_columns<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, y_area: u32) -> usize {
    (area.dim_in_pixel().0.saturating_sub(y_area + 20) as usize).max(50)
}

/// The series at data offset `o` of `rows` (σ at `o + 1` when `sigma`):
/// `(line, bands, points)`. Up to `2 × cols` rows are returned as they are
/// (`points`: `(x, value, σ)` for error bars); more are decimated per pixel
/// column (min/max of the values, envelope of value ± σ) from the history's
/// min/max pyramid in O(columns × log n) ([`RunHistory::decimate`]; one
/// pass over the rows with [`Columns`] if the column has none) and `points`
/// is `None`.
#[allow(clippy::type_complexity)]
fn series_of(
    f: &Viewport<'_>,
    o: usize,
    sigma: bool,
    (x0, x1): (f64, f64),
    cols: usize,
) -> (
    Vec<(f64, f64)>,
    Vec<(f64, f64, f64)>,
    Option<Vec<(f64, f64, f64)>>,
) {
    let rows = f.rows();
    let vals = f.column(o);
    let sds = if sigma { f.column(o + 1) } else { &[] };
    let sd = |i: usize| sds.get(i).copied().filter(|s| s.is_finite()).unwrap_or(0.0);
    // A value the tuner rejected is not part of the series (drawn apart).
    let start = f.range().start;
    let val = |i: usize| {
        if f.history.is_rejected(o, start + i) {
            f64::NAN
        } else {
            vals[i]
        }
    };
    let axis = f.axis;
    if rows.len() <= 2 * cols {
        let pts: Vec<(f64, f64, f64)> = rows
            .iter()
            .enumerate()
            .map(|(i, r)| (axis.x(r), val(i), sd(i)))
            .filter(|(_, v, _)| v.is_finite())
            .collect();
        let line = pts.iter().map(|&(x, v, _)| (x, v)).collect();
        let bands = pts.iter().map(|&(x, v, s)| (x, v - s, v + s)).collect();
        return (line, bands, Some(pts));
    }
    if let Some(out) = f
        .history
        .decimate(o, f.range(), |r| axis.x(r), (x0, x1), cols)
    {
        return (out.0, out.1, None);
    }
    let mut c = Columns::new(x0, x1, cols);
    for (i, r) in rows.iter().enumerate() {
        let (v, s) = (val(i), sd(i));
        c.push(axis.x(r), v, v - s, v + s);
    }
    let (line, bands) = c.finish();
    (line, bands, None)
}

/// The ±1σ envelope of a decimated series (`(x, lower, upper)` per pixel
/// column) as filled polygons, one per run of adjacent columns (a gap of
/// missing values splits it; a lone column is a vertical line): one canvas
/// fill per run instead of one stroke per pixel column.
fn draw_band<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    bands: &[(f64, f64, f64)],
    (x0, x1): (f64, f64),
    cols: usize,
    c: RGBColor,
) -> Result<(), DrawError> {
    let gap = 2.5 * (x1 - x0) / cols.max(1) as f64;
    let style = c.mix(0.25);
    let mut start = 0;
    for i in 1..=bands.len() {
        if i < bands.len() && bands[i].0 - bands[i - 1].0 <= gap {
            continue;
        }
        let run = &bands[start..i];
        start = i;
        if let [(x, lo, hi)] = run {
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(*x, *lo), (*x, *hi)],
                    style.stroke_width(1),
                )))
                .map_err(err)?;
        } else if !run.is_empty() {
            let outline: Vec<(f64, f64)> = run
                .iter()
                .map(|b| (b.0, b.2))
                .chain(run.iter().rev().map(|b| (b.0, b.1)))
                .collect();
            chart
                .draw_series(std::iter::once(Polygon::new(outline, style.filled())))
                .map_err(err)?;
        }
    }
    Ok(())
}

/// Segments of constant (target, tolerance) over rows: `(x from, x to, target, half-width)`.
/// `targets` and `tolerances` are the parameter's columns over `rows`.
pub fn target_segments(
    rows: &[Row],
    targets: &[f64],
    tolerances: &[f64],
    axis: XAxis,
) -> Vec<(f64, f64, f64, f64)> {
    let mut out: Vec<(f64, f64, f64, f64)> = Vec::new();
    for ((r, &t), &tol) in rows.iter().zip(targets).zip(tolerances) {
        if !t.is_finite() {
            continue;
        }
        let tol = if tol.is_finite() { tol } else { 0.0 };
        let x = axis.x(r);
        match out.last_mut() {
            Some(last) if last.2 == t && last.3 == tol => last.1 = x,
            _ => out.push((x, x, t, tol)),
        }
    }
    out
}

/// Y range of a decimated series with bands: every value counts (a spike
/// must stay in view), band bounds only where the band is not much wider
/// than the median band (distrusted fits are clipped at the frame).
fn value_range(
    line: &[(f64, f64)],
    bands: &[(f64, f64, f64)],
    extra: impl Iterator<Item = f64>,
) -> (f64, f64) {
    let mut widths: Vec<f64> = bands.iter().map(|b| b.2 - b.1).collect();
    widths.sort_by(|a, b| a.total_cmp(b));
    let median = widths.get(widths.len() / 2).copied().unwrap_or(0.0);
    let trusted = bands
        .iter()
        .filter(|b| b.2 - b.1 <= 5.0 * median + 1e-300)
        .flat_map(|b| [b.1, b.2]);
    padded_range(line.iter().map(|p| p.1).chain(trusted).chain(extra), 0.08)
}

/// One parameter against the x axis: measured values with ±1σ (error bars,
/// or per-column bands when decimated), the target line and its tolerance
/// band; the overlay run's values as a grey line. Values the tuner rejected
/// ([`crate::history::rejects`]: too uncertain, outlier-gated, update
/// refused) are hollow grey circles without error bars and do not set the y
/// range (one such value of 238 ± 288 ns would hide every tolerance band);
/// those outside it are pinned to the nearer edge as hollow triangles.
///
/// `y` chooses the y range ([`YRange`]): robust (the above), full (rejected
/// values and every band too) or typed; with a typed range, accepted values
/// outside it are pinned to the nearer edge as filled triangles (error bars,
/// bands and the compared run are cut at the edge, targets outside are not
/// drawn). The axis keeps its unit in every case.
pub fn draw_parameter<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    f: &Viewport<'_>,
    p: usize,
    series: usize,
    y: YRange,
) -> Result<Drawn, DrawError> {
    let layout = f.history.layout();
    let Some((name, unit)) = layout.parameters.get(p) else {
        return placeholder(plot.area(), "parameter", "waiting for measurements…")
            .map(|_| Drawn::default());
    };
    let title = format!("{name} ({unit})");
    let o = layout.param(p);
    let rows = f.rows();
    let (x0, x1) = f.x_range();
    let cols = plot_columns(plot.area(), 62);
    let (line, bands, pts) = crate::metrics::phase(crate::metrics::Phase::Decimate, || {
        series_of(f, o, true, (x0, x1), cols)
    });
    let (rejected, _, _) = crate::metrics::phase(crate::metrics::Phase::Decimate, || {
        series_of(f, layout.rejected(p), false, (x0, x1), cols)
    });
    if line.is_empty() && rejected.is_empty() {
        return placeholder(plot.area(), &title, "waiting for measurements…").map(|_| Drawn {
            iterations: rows.len(),
            ..Drawn::default()
        });
    }
    let targets: Vec<(f64, f64, f64, f64)> = f
        .history
        .target_runs(p, f.range())
        .into_iter()
        .map(|r| {
            let all = f.history.rows();
            (
                f.axis.x(&all[r.first]),
                f.axis.x(&all[r.last]),
                r.target,
                r.tolerance,
            )
        })
        .collect();
    let overlay = f.overlay_line(|l| l.param_index(name).map(|q| l.param(q)), (x0, x1), cols);
    let auto = value_range(
        &line,
        &bands,
        targets
            .iter()
            .flat_map(|&(_, _, t, tol)| [t - tol, t + tol])
            .chain(overlay.iter().map(|p| p.1))
            // only rejected values in view: they are all there is to show
            .chain(
                line.is_empty()
                    .then_some(rejected.iter().map(|p| p.1))
                    .into_iter()
                    .flatten(),
            ),
    );
    let full = || {
        padded_range(
            line.iter()
                .map(|p| p.1)
                .chain(bands.iter().flat_map(|b| [b.1, b.2]))
                .chain(pts.iter().flatten().flat_map(|p| [p.1 - p.2, p.1 + p.2]))
                .chain(
                    targets
                        .iter()
                        .flat_map(|&(_, _, t, tol)| [t - tol, t + tol]),
                )
                .chain(overlay.iter().map(|p| p.1))
                .chain(rejected.iter().map(|p| p.1)),
            0.08,
        )
    };
    let (y0, y1) = match y {
        YRange::Full => full(),
        _ => y.resolve(auto, auto),
    };
    // A typed range cuts what lies outside it at its edges.
    let manual = matches!(y, YRange::Manual(..));
    let cut = |v: f64| if manual { pin(v, (y0, y1)).0 } else { v };
    let mut pinned: Vec<(f64, f64)> = Vec::new();
    let (line, bands, pts, overlay, targets) = if manual {
        pinned.extend(
            line.iter()
                .filter(|p| pin(p.1, (y0, y1)).1)
                .map(|&(x, v)| (x, cut(v))),
        );
        (
            line.iter().map(|&(x, v)| (x, cut(v))).collect(),
            bands
                .iter()
                .map(|&(x, lo, hi)| (x, cut(lo), cut(hi)))
                .collect(),
            pts,
            overlay.iter().map(|&(x, v)| (x, cut(v))).collect(),
            targets
                .into_iter()
                .filter(|t| !pin(t.2, (y0, y1)).1)
                .collect(),
        )
    } else {
        (line, bands, pts, overlay, targets)
    };
    let mut chart = styled_chart(
        plot,
        &format!(
            "{title} vs {}",
            match f.axis {
                XAxis::Iteration => "iteration",
                XAxis::LabTime => "lab time",
            }
        ),
        f.axis.desc(),
        &title,
        x0..x1,
        y0..y1,
        false,
        f.x_fmt(),
    )?;
    let half = match f.axis {
        XAxis::Iteration => 0.5,
        XAxis::LabTime => 0.0,
    };
    chart
        .draw_series(targets.iter().map(|&(a, b, t, tol)| {
            Rectangle::new(
                [(a - half, t - tol), (b + half, t + tol)],
                BAND.mix(0.16).filled(),
            )
        }))
        .map_err(err)?;
    chart
        .draw_series(targets.iter().map(|&(a, b, t, _)| {
            PathElement::new(vec![(a - half, t), (b + half, t)], TARGET.stroke_width(2))
        }))
        .map_err(err)?;
    draw_overlay(&mut chart, &overlay)?;
    let c = color(series);
    if let Some(pts) = &pts {
        chart
            .draw_series(LineSeries::new(
                line.iter().copied(),
                c.mix(0.5).stroke_width(1),
            ))
            .map_err(err)?;
        chart
            .draw_series(pts.iter().filter(|p| !manual || !pin(p.1, (y0, y1)).1).map(
                |&(k, v, s)| {
                    ErrorBar::new_vertical(
                        k,
                        cut(v - s),
                        v,
                        cut(v + s),
                        c.filled(),
                        bar_width(pts.len()),
                    )
                },
            ))
            .map_err(err)?;
    } else {
        draw_band(&mut chart, &bands, (x0, x1), cols, c)?;
        chart
            .draw_series(LineSeries::new(line.iter().copied(), c.stroke_width(1)))
            .map_err(err)?;
    }
    draw_rejected(&mut chart, &rejected, (y0, y1))?;
    chart
        .draw_series(
            pinned
                .iter()
                .map(|&p| TriangleMarker::new(p, 4, c.filled())),
        )
        .map_err(err)?;
    let px = chart.plotting_area().get_pixel_range().0;
    Ok(Drawn {
        iterations: rows.len(),
        points: line.len(),
        y_max: line.iter().map(|p| p.1).fold(f64::NAN, f64::max),
        y_range: (y0, y1),
        rejected: rejected.len(),
        overlay_points: overlay.len(),
        overlay_shift: f.overlay_shift().0,
        pinned: pinned.len(),
        plot_px: Some((px.start as f64, px.end as f64)),
        x_range: (x0, x1),
        panels: None,
    })
}

/// The compared run: a thin grey line.
fn draw_overlay<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    points: &[(f64, f64)],
) -> Result<(), DrawError> {
    if !points.is_empty() {
        chart
            .draw_series(LineSeries::new(
                points.iter().copied(),
                RGBColor(110, 110, 110).stroke_width(1),
            ))
            .map_err(err)?;
    }
    Ok(())
}

/// Colour of the values the tuner rejected.
pub const REJECTED: RGBColor = RGBColor(120, 120, 120);

/// Values the tuner rejected: hollow grey circles inside `[y0, y1]`, hollow
/// triangles pinned to the nearer edge outside it.
fn draw_rejected<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    points: &[(f64, f64)],
    (y0, y1): (f64, f64),
) -> Result<(), DrawError> {
    let style = REJECTED.stroke_width(1);
    let inside = |v: f64| v >= y0 && v <= y1;
    chart
        .draw_series(
            points
                .iter()
                .filter(|p| inside(p.1))
                .map(|&p| Circle::new(p, 3, style)),
        )
        .map_err(err)?;
    chart
        .draw_series(
            points
                .iter()
                .filter(|p| !inside(p.1))
                .map(|&(x, v)| TriangleMarker::new((x, v.clamp(y0, y1)), 4, style)),
        )
        .map_err(err)?;
    Ok(())
}

/// One panel per tuning gate ([`panel_grid`] over the plot's width) and
/// what a chart of such panels reports before any is drawn (its iterations,
/// x range and panel size; no y range yet).
fn gate_panels<'a, DB: DrawingBackend>(
    plot: &Plot<'a, DB>,
    f: &Viewport<'_>,
) -> (Vec<Plot<'a, DB>>, Drawn) {
    let width = plot.area().dim_in_pixel().0 as f64;
    let grid = panel_grid(f.history.layout().gates.len(), width);
    let drawn = Drawn {
        iterations: f.rows().len(),
        y_max: f64::NAN,
        x_range: f.x_range(),
        panels: Some((width / grid.1 as f64, grid.1)),
        ..Drawn::default()
    };
    (plot.split_evenly(grid), drawn)
}

/// Every element of one parameter's gradient, ±1σ `√diag C` (one panel per gate).
pub fn draw_gradient<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    f: &Viewport<'_>,
    g: usize,
) -> Result<Drawn, DrawError> {
    let layout = f.history.layout();
    let Some((name, unit)) = layout.gradients.get(g) else {
        return placeholder(plot.area(), "gradient", "waiting for a gradient estimate…")
            .map(|_| Drawn::default());
    };
    let (x0, x1) = f.x_range();
    let (panels, mut drawn) = gate_panels(plot, f);
    for (gi, (gate, panel)) in layout.gates.iter().zip(panels.iter()).enumerate() {
        let o = layout.grad(g, gi);
        let cols = plot_columns(panel.area(), 58);
        let (line, bands, pts) = crate::metrics::phase(crate::metrics::Phase::Decimate, || {
            series_of(f, o, true, (x0, x1), cols)
        });
        // The compared run's element, if its gradient has the same unit.
        let overlay = f.overlay_line(
            |l| {
                let g2 = l.gradients.iter().position(|x| x == &layout.gradients[g])?;
                let j = l.gates.iter().position(|x| x == gate)?;
                Some(l.grad(g2, j))
            },
            (x0, x1),
            cols,
        );
        drawn.overlay_points += overlay.len();
        let (y0, y1) = value_range(&line, &bands, overlay.iter().map(|p| p.1));
        let mut chart = styled_chart(
            panel,
            &format!("∂{name}/∂V_{gate}"),
            f.axis.desc(),
            unit.as_str(),
            x0..x1,
            y0..y1,
            true,
            f.x_fmt(),
        )?;
        draw_overlay(&mut chart, &overlay)?;
        let c = color(gi);
        if let Some(pts) = &pts {
            chart
                .draw_series(pts.iter().map(|&(k, v, s)| {
                    ErrorBar::new_vertical(
                        k,
                        v - s,
                        v,
                        v + s,
                        c.mix(0.55).filled(),
                        bar_width(pts.len()),
                    )
                }))
                .map_err(err)?;
        } else {
            draw_band(&mut chart, &bands, (x0, x1), cols, c)?;
        }
        chart
            .draw_series(LineSeries::new(line.iter().copied(), c.mix(0.8)))
            .map_err(err)?;
        if gi == 0 {
            drawn.points = line.len();
            drawn.y_range = (y0, y1);
            let px = chart.plotting_area().get_pixel_range().0;
            drawn.plot_px = Some((px.start as f64, px.end as f64));
        }
    }
    Ok(drawn)
}

/// The tuning gates' voltages (one panel per gate).
pub fn draw_gates<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    f: &Viewport<'_>,
) -> Result<Drawn, DrawError> {
    let layout = f.history.layout();
    if layout.gates.is_empty() {
        return placeholder(plot.area(), "gate voltages", "waiting for data…")
            .map(|_| Drawn::default());
    }
    let (x0, x1) = f.x_range();
    let (panels, mut drawn) = gate_panels(plot, f);
    for (gi, (gate, panel)) in layout.gates.iter().zip(panels.iter()).enumerate() {
        let o = layout.gate(gi);
        let cols = plot_columns(panel.area(), 58);
        let (line, _, _) = crate::metrics::phase(crate::metrics::Phase::Decimate, || {
            series_of(f, o, false, (x0, x1), cols)
        });
        let overlay = f.overlay_line(
            |l| l.gates.iter().position(|x| x == gate).map(|j| l.gate(j)),
            (x0, x1),
            cols,
        );
        drawn.overlay_points += overlay.len();
        let (y0, y1) = padded_range(line.iter().chain(&overlay).map(|p| p.1), 0.1);
        let mut chart = styled_chart(
            panel,
            &format!("V_{gate}"),
            f.axis.desc(),
            "voltage (mV)",
            x0..x1,
            y0..y1,
            true,
            f.x_fmt(),
        )?;
        draw_overlay(&mut chart, &overlay)?;
        let c = color(gi);
        chart
            .draw_series(LineSeries::new(line.iter().copied(), c.stroke_width(2)))
            .map_err(err)?;
        if line.len() <= 60 {
            chart
                .draw_series(line.iter().map(|&p| Circle::new(p, 2, c.filled())))
                .map_err(err)?;
        }
        if gi == 0 {
            drawn.points = line.len();
            drawn.y_range = (y0, y1);
            let px = chart.plotting_area().get_pixel_range().0;
            drawn.plot_px = Some((px.start as f64, px.end as f64));
        }
    }
    Ok(drawn)
}

/// Cumulative lab time against iteration (the map between the two x axes);
/// tuned iterations marked green.
pub fn draw_lab_time<DB: DrawingBackend>(
    plot: &Plot<'_, DB>,
    f: &Viewport<'_>,
) -> Result<Drawn, DrawError> {
    let rows = f.rows();
    if rows.is_empty() {
        return placeholder(plot.area(), "lab time", "waiting for data…").map(|_| Drawn::default());
    }
    let long = rows.last().map_or(0.0, |r| r.lab_seconds) > 2.0 * 3600.0;
    let (scale, unit) = if long { (3600.0, "h") } else { (60.0, "min") };
    let (x0, x1) = (f.window.lo - 0.5, f.window.hi.max(f.window.lo + 1.0) + 0.5);
    let cols = plot_columns(plot.area(), 62);
    let line: Vec<(f64, f64)> = if rows.len() <= 2 * cols {
        rows.iter()
            .map(|r| (r.iteration as f64, r.lab_seconds / scale))
            .collect()
    } else {
        f.history
            .decimate_lab_time(f.range(), |r| r.iteration as f64, (x0, x1), cols, false)
            .into_iter()
            .map(|(x, s)| (x, s / scale))
            .collect()
    };
    let (y0, y1) = padded_range(line.iter().map(|p| p.1), 0.05);
    let mut chart = styled_chart(
        plot,
        "cumulative lab time",
        "iteration",
        &format!("lab time ({unit})"),
        x0..x1,
        y0.max(0.0)..y1,
        false,
        &int_label,
    )?;
    chart
        .draw_series(LineSeries::new(
            line.iter().copied(),
            color(6).stroke_width(2),
        ))
        .map_err(err)?;
    let tuned: Vec<(f64, f64)> = if rows.len() <= 2 * cols {
        let xy: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.tuned)
            .map(|r| (r.iteration as f64, r.lab_seconds / scale))
            .collect();
        min_max(&xy, x0, x1, cols / 4)
    } else {
        f.history
            .decimate_lab_time(f.range(), |r| r.iteration as f64, (x0, x1), cols / 4, true)
            .into_iter()
            .map(|(x, s)| (x, s / scale))
            .collect()
    };
    chart
        .draw_series(tuned.iter().map(|&p| Circle::new(p, 3, BAND.filled())))
        .map_err(err)?;
    let px = chart.plotting_area().get_pixel_range().0;
    Ok(Drawn {
        iterations: rows.len(),
        points: line.len(),
        y_max: line.iter().map(|p| p.1).fold(f64::NAN, f64::max),
        y_range: (y0.max(0.0), y1),
        rejected: 0,
        overlay_points: 0,
        overlay_shift: 0.0,
        pinned: 0,
        plot_px: Some((px.start as f64, px.end as f64)),
        x_range: (x0, x1),
        panels: None,
    })
}

/// Numbers for the y-axis-free parts of the page.
pub fn fmt(x: f64) -> String {
    num_label(&x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn panels_collapse_to_two_columns_then_one_on_narrow_screens() {
        assert_eq!(panel_grid(4, 1100.0), (1, 4));
        assert_eq!(panel_grid(4, 700.0), (2, 2));
        assert_eq!(panel_grid(4, 400.0), (4, 1));
        assert_eq!(panel_grid(0, 400.0), (1, 1));
        assert_eq!(panel_grid(3, 500.0), (2, 2));
    }
    use crate::model::fake_records;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn lab_time_labels_and_target_segments() {
        assert_eq!(hmm(&1.5), "1:30");
        assert_eq!(hmm(&0.0), "0:00");
        assert_eq!(hmm(&27.999), "28:00");
        let mut recs = fake_records(5);
        recs[3].parameters[0].target = Some(70.0);
        recs[4].parameters[0].target = Some(70.0);
        let mut h = RunHistory::new();
        h.insert(recs);
        let o = h.layout().param(0);
        let (t, tol) = (h.column(o + 2), h.column(o + 3));
        let segs = target_segments(h.rows(), t, tol, XAxis::Iteration);
        assert_eq!(segs, vec![(0.0, 2.0, 20.0, 2.0), (3.0, 4.0, 70.0, 2.0)]);
        let segs = target_segments(h.rows(), t, tol, XAxis::LabTime);
        assert_eq!(segs[1].0, (60.0 * 3.0 + 30.0) / 3600.0);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn target_runs_kept_by_the_history_match_a_scan_of_every_window() {
        let mut recs = fake_records(60);
        for (k, r) in recs.iter_mut().enumerate() {
            r.parameters[0].target = match k {
                0..=9 => Some(20.0),
                10..=14 => None,
                15..=29 => Some(20.0),
                30..=44 => Some(70.0),
                _ => Some(45.0),
            };
        }
        let mut h = RunHistory::new();
        // Newest first, then older pages, then live records one by one.
        h.insert(recs[40..50].to_vec());
        h.insert(recs[0..40].to_vec());
        for r in &recs[50..60] {
            h.insert([r.clone()]);
        }
        let o = h.layout().param(0);
        for (a, b) in [
            (0, 60),
            (0, 12),
            (11, 14),
            (12, 33),
            (31, 60),
            (59, 60),
            (45, 46),
        ] {
            let rows = &h.rows()[a..b];
            let expect = target_segments(
                rows,
                &h.column(o + 2)[a..b],
                &h.column(o + 3)[a..b],
                XAxis::Iteration,
            );
            let got: Vec<_> = h
                .target_runs(0, a..b)
                .into_iter()
                .map(|r| (r.first as f64, r.last as f64, r.target, r.tolerance))
                .collect();
            assert_eq!(got, expect, "rows {a}..{b}");
        }
    }
}
