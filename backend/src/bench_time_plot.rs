//! `spintune bench --plot-time FILE`: where a change's lab time goes, one
//! stacked bar per strategy (mean lab seconds per converged change by scan
//! kind, [`StrategySummary::lab_seconds_per_change_by_kind`]).

use std::path::Path;

use spintune::benchmark::StrategySummary;

use crate::cli::CliError;

/// The kinds drawn, in stacking order, with their legend labels.
pub(crate) const KINDS: [(&str, &str); 6] = [
    ("sensing_dot", "sensing-dot sweeps"),
    ("chemical_potential", "chemical-potential scans"),
    ("transition_width", "w scans"),
    ("reload_time", "t_sr scans"),
    ("set_voltages", "moves"),
    ("read_voltages", "read-backs"),
];

/// Draw the bars of `summary` (in its order, top to bottom) to `path` (PNG).
/// The caller registers the font first (`bench::register_font`).
pub fn draw_time_by_kind(path: &Path, summary: &[StrategySummary]) -> Result<(), CliError> {
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| CliError::runtime(format!("plot: {e}"));
    let n = summary.len().max(1);
    let height = 160 + 44 * n as u32;
    let root = BitMapBackend::new(path, (1100, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let max_s = summary
        .iter()
        .map(|s| s.lab_seconds_per_change_by_kind.values().sum::<f64>())
        .fold(60.0, f64::max);
    let names: Vec<String> = summary.iter().map(|s| s.name.clone()).collect();
    // bars top to bottom in the summary's order: row i is drawn at n − 1 − i
    let row = |i: usize| (n - 1 - i) as i32;
    let mut chart = ChartBuilder::on(&root)
        .margin(16)
        .caption(
            "Where a change's lab time goes (mean per converged change)",
            ("sans-serif", 24),
        )
        .x_label_area_size(45)
        .y_label_area_size(230)
        // room on the right for the legend
        .build_cartesian_2d(0f64..max_s * 1.5, (0..n as i32 - 1).into_segmented())
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .disable_y_mesh()
        .x_desc("lab time per change (s)")
        .y_labels(n)
        .y_label_formatter(&|y| match y {
            SegmentValue::CenterOf(v) => usize::try_from(n as i32 - 1 - v)
                .ok()
                .and_then(|i| names.get(i).cloned())
                .unwrap_or_default(),
            _ => String::new(),
        })
        .draw()
        .map_err(|e| err(&e))?;
    // per kind: sweeps purple, lines blue, w orange, t_sr green, moves grey, read-backs red
    let colors = [4, 0, 1, 2, 5, 3].map(|i| crate::plot_palette::TAB10[i]);
    for (k, ((kind, label), color)) in KINDS.iter().zip(colors).enumerate() {
        let seconds = |s: &StrategySummary, kind: &str| {
            s.lab_seconds_per_change_by_kind
                .get(kind)
                .copied()
                .unwrap_or(0.0)
        };
        if summary.iter().all(|s| seconds(s, kind) <= 0.0) {
            continue; // e.g. no read-backs in the simulator's benchmark
        }
        let bars: Vec<(i32, f64, f64)> = summary
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let before: f64 = KINDS[..k].iter().map(|(kk, _)| seconds(s, kk)).sum();
                (row(i), before, before + seconds(s, kind))
            })
            .collect();
        chart
            .draw_series(bars.into_iter().map(|(y, x0, x1)| {
                Rectangle::new(
                    [
                        (x0, SegmentValue::Exact(y)),
                        (x1, SegmentValue::Exact(y + 1)),
                    ],
                    color.filled(),
                )
            }))
            .map_err(|e| err(&e))?
            .label(*label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], color.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
