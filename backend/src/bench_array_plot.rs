//! `spintune bench-array --plot FILE`: one run of the joint loop as cells ×
//! lab time, each cell in band or not at every measurement (as the run
//! measured it, and underneath as the world knows it), with the protocol's
//! phases marked ([`spintune::benchmark::array_timeline`]).

use std::path::Path;

use spintune::benchmark::array::ArrayRunResult;
use spintune::benchmark::array_timeline::CellBand;

use crate::cli::CliError;
use crate::plot_palette::TAB10;

/// The phases' names, in protocol order: the cold start, the set-point
/// changes of every cell, then the single-cell changes.
fn phase_name(phase: u32, set_point_changes: u32, single: &[u32]) -> String {
    if phase == 0 {
        "cold start".into()
    } else if phase <= set_point_changes {
        format!("set point {}", phase + 1)
    } else {
        let i = (phase - set_point_changes - 1) as usize;
        single
            .get(i)
            .map_or_else(|| format!("phase {phase}"), |c| format!("cell {c} alone"))
    }
}

/// Draw `run`'s timeline to `path` (PNG). `set_point_changes`: how many
/// all-cell changes follow the cold start; `single`: the cells changed
/// alone after them, in order.
pub fn draw_timeline(
    path: &Path,
    run: &ArrayRunResult,
    set_point_changes: u32,
    single: &[u32],
) -> Result<(), CliError> {
    use plotters::prelude::*;
    crate::bench::register_font()?;
    let err = |e: &dyn std::fmt::Display| CliError::runtime(format!("plot: {e}"));
    let points = &run.timeline;
    let Some(last) = points.last() else {
        return Err(CliError::runtime(
            "plot: the run has no iterations to draw".to_string(),
        ));
    };
    let cells = points.iter().map(|p| p.measured.len()).max().unwrap_or(0);
    // the last measurement is drawn as wide as the one before it
    let widths: Vec<f64> = points
        .windows(2)
        .map(|w| w[1].lab_minutes - w[0].lab_minutes)
        .collect();
    let last_width = widths.last().copied().unwrap_or(1.5).max(0.5);
    let end = last.lab_minutes + last_width;
    let height = 220 + 46 * cells as u32;
    let root = BitMapBackend::new(path, (1400, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let converged = |x: Option<f64>| x.map_or("–".to_string(), |m| format!("{m:.1}"));
    let title = format!(
        "spintune bench-array: {} on {} cells, seed {} — cold start {} lab min, changes {} lab min",
        run.strategy.name(),
        cells,
        run.seed,
        converged(run.cold_start_lab_minutes),
        run.changes
            .iter()
            .chain(&run.single_cell_changes)
            .map(|&c| converged(c))
            .collect::<Vec<_>>()
            .join(" / ")
    );
    let root = root
        .titled(&title, ("sans-serif", 18))
        .map_err(|e| err(&e))?;
    let (plot_area, legend_area) = root.split_vertically(height - 80);
    // cell c is the row at y = cells − 1 − c (cell 0 at the top); room above
    // the rows for the phases' names
    let top = cells as f64 - 0.5 + 0.6;
    let mut chart = ChartBuilder::on(&plot_area)
        .margin(14)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..end, -0.5f64..top)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .disable_y_mesh()
        .light_line_style(TRANSPARENT)
        .x_desc("lab time since the start (min)")
        .y_desc("cell")
        .y_labels(2 * cells + 2)
        .y_label_formatter(&|y| {
            let row = cells as f64 - 1.0 - y;
            if (y - y.round()).abs() < 1e-6 && (0.0..cells as f64).contains(&row.round()) {
                format!("{:.0}", row.round())
            } else {
                String::new()
            }
        })
        .draw()
        .map_err(|e| err(&e))?;
    let measured_colour = |b: CellBand| match b {
        CellBand::InBand => TAB10[2],
        CellBand::OutOfBand => TAB10[1],
        CellBand::NotMeasured => TAB10[5],
    };
    let mut boxes = Vec::new();
    for (i, p) in points.iter().enumerate() {
        let to = p.lab_minutes + widths.get(i).copied().unwrap_or(last_width);
        for (c, &band) in p.measured.iter().enumerate() {
            let y = (cells - 1 - c) as f64 - 0.5;
            // upper part: what the run measured; lower strip: the world
            boxes.push(Rectangle::new(
                [(p.lab_minutes, y + 0.35), (to, y + 0.95)],
                measured_colour(band).filled(),
            ));
            let truth = if p.truly_in_band.get(c).copied().unwrap_or(false) {
                TAB10[2].mix(0.5)
            } else {
                TAB10[3].mix(0.8)
            };
            boxes.push(Rectangle::new(
                [(p.lab_minutes, y + 0.1), (to, y + 0.3)],
                truth.filled(),
            ));
        }
    }
    chart.draw_series(boxes).map_err(|e| err(&e))?;
    // a dashed line and a name where each phase starts
    let mut starts: Vec<(f64, u32)> = Vec::new();
    for p in points {
        if starts.last().is_none_or(|&(_, ph)| ph != p.phase) {
            // the cold start counts from 0 (its initial measurements first)
            let t = if p.phase == 0 { 0.0 } else { p.lab_minutes };
            starts.push((t, p.phase));
        }
    }
    for &(t, phase) in &starts {
        chart
            .draw_series(DashedLineSeries::new(
                [(t, 0.0), (t, top)],
                6,
                4,
                BLACK.mix(0.6).stroke_width(1),
            ))
            .map_err(|e| err(&e))?;
        chart
            .draw_series(std::iter::once(Text::new(
                phase_name(phase, set_point_changes, single),
                (t + 0.3, top - 0.1),
                ("sans-serif", 14),
            )))
            .map_err(|e| err(&e))?;
    }
    // the legend, in a row below the chart
    let mut x = 90;
    for (label, colour) in [
        ("measured in band", TAB10[2].to_rgba()),
        ("measured out of band", TAB10[1].to_rgba()),
        ("a fit failed", TAB10[5].to_rgba()),
        ("lower strip: truly in band (world side)", TAB10[2].mix(0.5)),
        ("truly out of band", TAB10[3].mix(0.8)),
    ] {
        legend_area
            .draw(&Rectangle::new([(x, 30), (x + 18, 44)], colour.filled()))
            .map_err(|e| err(&e))?;
        legend_area
            .draw(&Text::new(label, (x + 24, 30), ("sans-serif", 15)))
            .map_err(|e| err(&e))?;
        x += 34 + 8 * label.chars().count() as i32;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
