//! `spintune drift-day`: an untended stretch of lab time on the simulated
//! device (nothing moved, nothing measured), to see how its slow drift of
//! t_c and Γ carries w and t_sr out of a ±10 % band
//! (`spintune::sim::SlowDrift`). Prints when each device first leaves the
//! band and draws t_sr and w relative to their start values over lab hours.

use std::path::PathBuf;

use clap::Args;
use spintune::sim::{default_gates, DeviceConfig, SimulatedDevice};

use crate::cli::CliError;

/// Arguments of `spintune drift-day`.
#[derive(Debug, Args)]
pub struct DriftDayArgs {
    /// First device seed (then +1, +2, … for `--devices`).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of devices (seeds) drawn, 1..=10.
    #[arg(long, default_value_t = 5)]
    pub devices: u64,
    /// Lab hours, 1..=168.
    #[arg(long, default_value_t = 24.0)]
    pub hours: f64,
    /// Device description (TOML or JSON) overriding the simulator's defaults.
    #[arg(long)]
    pub device: Option<PathBuf>,
    /// Draw the traces to this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// One device's day: `(hours, t_sr / t_sr(0), w / w(0))` every 5 minutes.
type Trace = Vec<(f64, f64, f64)>;

/// Run `spintune drift-day`.
pub fn run(args: DriftDayArgs) -> Result<(), CliError> {
    if !(1..=10).contains(&args.devices) {
        return Err(CliError::input("--devices must be between 1 and 10"));
    }
    if !(args.hours.is_finite() && (1.0..=168.0).contains(&args.hours)) {
        return Err(CliError::input("--hours must be between 1 and 168"));
    }
    let config = match &args.device {
        Some(p) => crate::bench_runner::load_device(p)?,
        None => DeviceConfig::default(),
    };
    config
        .validate()
        .map_err(|e| CliError::input(e.within("device").to_string()))?;
    let mut traces = Vec::new();
    println!("device seed | leaves ±10 % after (lab h)");
    for seed in args.seed..args.seed + args.devices {
        let mut dev = SimulatedDevice::new(config.clone(), &default_gates(), seed)
            .map_err(|e| CliError::input(e.to_string()))?;
        let start = dev.truth();
        let mut trace: Trace = vec![(0.0, 1.0, 1.0)];
        let mut left: Option<f64> = None;
        let steps = (args.hours * 12.0).round() as u64;
        for k in 1..=steps {
            dev.idle(300.0);
            let now = dev.truth();
            let (t, w) = (now.t_sr_ns / start.t_sr_ns, now.w_uv / start.w_uv);
            let h = k as f64 / 12.0;
            if left.is_none() && ((t - 1.0).abs() > 0.1 || (w - 1.0).abs() > 0.1) {
                left = Some(h);
            }
            trace.push((h, t, w));
        }
        match left {
            Some(h) => println!("{seed} | {h:.2}"),
            None => println!("{seed} | stays within {:.0} h", args.hours),
        }
        traces.push((seed, trace));
    }
    if let Some(path) = &args.plot {
        draw(path, &traces, args.hours)?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

fn draw(path: &std::path::Path, traces: &[(u64, Trace)], hours: f64) -> Result<(), CliError> {
    use plotters::prelude::*;
    crate::bench::register_font()?;
    let err = |e: &dyn std::fmt::Display| CliError::runtime(format!("plot: {e}"));
    let root = BitMapBackend::new(path, (1100, 800)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let root = root
        .titled(
            "spintune drift-day: an untended device, relative to its start (±10 % band shaded)",
            ("sans-serif", 22),
        )
        .map_err(|e| err(&e))?;
    let panels = root.split_evenly((2, 1));
    let colors = &crate::plot_palette::TAB10[..5];
    for (pi, name) in ["t_sr / t_sr(0)", "w / w(0)"].into_iter().enumerate() {
        let value = |p: &(f64, f64, f64)| if pi == 0 { p.1 } else { p.2 };
        let (lo, hi) = traces
            .iter()
            .flat_map(|(_, t)| t.iter().map(value))
            .fold((0.85f64, 1.15f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
        let mut chart = ChartBuilder::on(&panels[pi])
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..hours, (lo - 0.02)..(hi + 0.02))
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("lab time (h)")
            .y_desc(format!("{name} (1)"))
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(0.0, 0.9), (hours, 1.1)],
                RGBColor(200, 200, 200).mix(0.35).filled(),
            )))
            .map_err(|e| err(&e))?;
        for (i, (seed, trace)) in traces.iter().enumerate() {
            let color = colors[i % colors.len()];
            chart
                .draw_series(LineSeries::new(
                    trace.iter().map(|p| (p.0, value(p))),
                    color.stroke_width(2),
                ))
                .map_err(|e| err(&e))?
                .label(format!("device seed {seed}"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))
}
