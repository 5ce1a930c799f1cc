//! `spintune bench`: the paper's set-point cycle over many seeds, every
//! strategy side by side (protocol and statistics in `spintune::benchmark`;
//! this module only runs seeds in parallel, shows progress and writes reports).

use std::path::{Path, PathBuf};

use clap::Args;
use serde::Serialize;
use spintune::benchmark::{
    run_seed, summarize, BenchmarkProtocol, SeedResult, Strategy, StrategySummary,
};
use spintune::protocol::IterationRecord;

use crate::bench_runner::{parallel_map, parse_names, worker_threads, DeviceArgs, RandomDevices};
use crate::cli::CliError;

/// Arguments of `spintune bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Number of seeds (seeds 1..=N).
    #[arg(long, default_value_t = 100)]
    pub seeds: u64,
    /// Comma-separated strategies (default: all): default, kalman, kalman-adaptive-q,
    /// kalman-log, kalman-tr, kalman-log-tr, kalman-log-tr-multi,
    /// kalman-log-tr-multi-bare, broyden,
    /// fixed-jacobian, fd-newton, oracle, oracle-log, oracle-log-multi-bare.
    #[arg(long, value_delimiter = ',')]
    pub strategies: Vec<String>,
    /// The device(s), the product's tuner, the band and the worker threads.
    #[command(flatten)]
    pub devices: DeviceArgs,
    /// Write machine-readable results here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Draw one seed's parameter traces and gradient estimates (paper Fig. 3 style) to this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Seed and strategy drawn by `--plot`.
    #[arg(long, default_value_t = 1)]
    pub plot_seed: u64,
    /// Draw where each strategy's lab time per change goes (stacked bars by
    /// scan kind) to this PNG.
    #[arg(long)]
    pub plot_time: Option<PathBuf>,
    /// Step rule of the `-tr` strategies: expected-cost or covariance-direction.
    #[arg(long, default_value = "expected-cost")]
    pub tr_rule: String,
    /// Covariance weight of the `-tr` strategies (0..=100; default 0, the
    /// plain trust region).
    #[arg(long, default_value_t = 0.0)]
    pub covariance_weight: f64,
    /// Moves per iteration of the `-multi` strategies (1..=5).
    #[arg(long, default_value_t = spintune::benchmark::MULTI_MOVES)]
    pub multi_moves: u32,
}

/// The JSON report.
#[derive(Debug, Serialize)]
pub struct BenchReport {
    /// Number of seeds.
    pub seeds: u64,
    /// The protocol used.
    pub protocol: BenchmarkProtocol,
    /// One object per strategy.
    pub strategies: Vec<StrategySummary>,
    /// With `--random-devices`: the devices (statistics are over devices × seeds).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub random_devices: Option<RandomDevices>,
}

/// Run the benchmark.
pub fn run(args: BenchArgs) -> Result<(), CliError> {
    let strategies = parse_strategies(&args.strategies)?;
    let (base, product) = args.devices.load()?;
    let tr_rule = match args.tr_rule.as_str() {
        "expected-cost" => spintune::solver::StepRule::ExpectedCost,
        "covariance-direction" => spintune::solver::StepRule::CovarianceDirection,
        other => {
            return Err(CliError::input(format!(
                "--tr-rule {other:?}: choose expected-cost or covariance-direction"
            )))
        }
    };
    if !(args.covariance_weight.is_finite()
        && (0.0..=spintune::solver::MAX_COVARIANCE_WEIGHT).contains(&args.covariance_weight))
    {
        return Err(CliError::input("--covariance-weight must be in [0, 100]"));
    }
    if !(1..=spintune::solver::MAX_MOVES_PER_ITERATION).contains(&args.multi_moves) {
        return Err(CliError::input("--multi-moves must be between 1 and 5"));
    }
    let protocol = BenchmarkProtocol {
        relative_tolerance: args.devices.tolerance,
        tr_rule,
        covariance_weight: args.covariance_weight,
        multi_moves: args.multi_moves,
        ..BenchmarkProtocol::default()
    };
    let threads = worker_threads(args.devices.threads);
    let (devices, random_devices) = args.devices.devices(&base, &protocol)?;
    let work: Vec<(usize, u64)> = (0..devices.len())
        .flat_map(|d| (1..=args.seeds).map(move |s| (d, s)))
        .collect();
    let (results, failures) = parallel_map(&work, threads, |&(d, seed)| {
        let (device, cfg) = &devices[d];
        match run_seed(cfg, &product, &protocol, &strategies, seed, false) {
            Ok(mut r) => {
                r.iter_mut().for_each(|x| x.device = *device);
                Ok(r)
            }
            Err(e) => Err(format!("device {device}: {e}")),
        }
    });
    let mut results: Vec<SeedResult> = results.into_iter().flatten().collect();
    results.sort_by_key(|r| {
        (
            r.device,
            r.seed,
            Strategy::ALL.iter().position(|s| *s == r.strategy),
        )
    });
    for f in &failures {
        eprintln!("warning: {f}");
    }
    let summary = summarize(&results, &strategies, protocol.iterations_per_set_point);
    println!(
        "{}",
        markdown_table(
            &summary,
            work.len() as u64 - failures.len() as u64,
            &protocol
        )
    );
    if let Some(path) = &args.plot_time {
        register_font()?;
        crate::bench_time_plot::draw_time_by_kind(path, &summary)?;
        eprintln!("wrote {}", path.display());
    }
    if let Some(path) = &args.json {
        let report = BenchReport {
            seeds: args.seeds,
            protocol: protocol.clone(),
            strategies: summary,
            random_devices,
        };
        let text = serde_json::to_string_pretty(&report).expect("serializable report");
        std::fs::write(path, text)
            .map_err(|e| CliError::runtime(format!("cannot write {}: {e}", path.display())))?;
        eprintln!("wrote {}", path.display());
    }
    if let Some(path) = &args.plot {
        let strategy = strategies[0];
        let r = run_seed(
            &base,
            &product,
            &protocol,
            &[strategy],
            args.plot_seed,
            true,
        )
        .map_err(|e| CliError::runtime(e.to_string()))?;
        draw_figure(path, &r[0].records, strategy.name(), args.plot_seed)?;
        eprintln!("wrote {}", path.display());
    }
    if !failures.is_empty() {
        return Err(CliError::runtime(format!(
            "{} seed(s) failed",
            failures.len()
        )));
    }
    Ok(())
}

fn parse_strategies(names: &[String]) -> Result<Vec<Strategy>, CliError> {
    parse_names(
        names,
        &Strategy::ALL,
        Strategy::from_name,
        |s| s.name().into(),
        "strategy",
        "",
    )
}

/// The markdown table printed at the end.
pub fn markdown_table(
    summary: &[StrategySummary],
    seeds: u64,
    protocol: &BenchmarkProtocol,
) -> String {
    let mut s = format!(
        "Runs (devices × seeds): {seeds}; {} set-point changes per run, {} iterations each, tolerance ±{:.0} %, virtual-gate matrix error ±{:.0} %.\n\n",
        protocol.set_points.len(),
        protocol.iterations_per_set_point,
        protocol.relative_tolerance * 100.0,
        protocol.compensation_error * 100.0
    );
    s.push_str("| strategy | iterations/change median | p90 | max | moves/change median | p90 | lab min/change median | p90 | cold start lab min median | p90 | truly in band at tuned | not converged | limit violations | failed fits | not converged where an oracle converged | ratio to oracle | ratio to oracle-log | truth queries |\n");
    s.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    let ratio = |x: Option<f64>| x.map_or("–".to_string(), |x| format!("{x:.2}"));
    for r in summary {
        s.push_str(&format!(
            "| {} | {:.1} | {:.1} | {:.0} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {} | {} / {} | {} | {} | {} | {} | {} | {} |\n",
            r.name,
            r.iterations_per_change.median,
            r.iterations_per_change.p90,
            r.iterations_per_change.max,
            r.moves_per_change.median,
            r.moves_per_change.p90,
            r.lab_minutes_per_change.median,
            r.lab_minutes_per_change.p90,
            r.cold_start_lab_minutes.median,
            r.cold_start_lab_minutes.p90,
            r.truly_in_band_at_tuned
                .map_or("–".to_string(), |x| format!("{:.3}", x)),
            r.not_converged,
            r.changes,
            r.limit_violations,
            r.failed_fits,
            r.not_converged_where_oracle_converged
                .map_or("–".to_string(), |x| x.to_string()),
            ratio(r.ratio_to_oracle),
            ratio(r.ratio_to_oracle_log),
            r.truth_queries,
        ));
    }
    s.push_str(&time_by_kind_table(summary));
    let kalman: Vec<&StrategySummary> =
        summary.iter().filter(|r| r.consistency.is_some()).collect();
    if !kalman.is_empty() {
        s.push_str("\nFilter consistency (normalised innovation squared; ideal mean 1, 4.6 % beyond 2σ):\n\n");
        s.push_str("| strategy | parameter | NIS mean | beyond 2σ | innovations |\n");
        s.push_str("|---|---|---:|---:|---:|\n");
        for r in kalman {
            for (p, c) in r.consistency.iter().flatten() {
                s.push_str(&format!(
                    "| {} | {p} | {:.2} | {:.1} % | {} |\n",
                    r.name,
                    c.nis_mean,
                    100.0 * c.beyond_2sigma,
                    c.count
                ));
            }
        }
    }
    s
}

/// Where a change's lab time goes: mean lab s per converged change by scan kind.
fn time_by_kind_table(summary: &[StrategySummary]) -> String {
    const COLUMNS: [(&str, &str); 6] = crate::bench_time_plot::KINDS;
    let mut s = String::from(
        "\nWhere a change's lab time goes (mean lab s per converged change):\n\n| strategy |",
    );
    for (_, title) in COLUMNS {
        s.push_str(&format!(" {title} |"));
    }
    s.push_str(" total, min |\n|---|");
    s.push_str(&"---:|".repeat(COLUMNS.len() + 1));
    s.push('\n');
    for r in summary {
        let by = &r.lab_seconds_per_change_by_kind;
        s.push_str(&format!("| {} |", r.name));
        for (kind, _) in COLUMNS {
            s.push_str(&format!(" {:.0} |", by.get(kind).copied().unwrap_or(0.0)));
        }
        s.push_str(&format!(" {:.2} |\n", by.values().sum::<f64>() / 60.0));
    }
    s
}

/// Paper Fig. 3 style: parameters with targets and ±1σ, gradient elements with ±1σ.
fn draw_figure(
    path: &Path,
    records: &[IterationRecord],
    strategy: &str,
    seed: u64,
) -> Result<(), CliError> {
    use plotters::prelude::*;
    register_font()?;
    let err = |e: &dyn std::fmt::Display| CliError::runtime(format!("plot: {e}"));
    let root = BitMapBackend::new(path, (1200, 1500)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let root = root
        .titled(
            &format!("spintune bench: {strategy}, seed {seed} (paper Fig. 3 style)"),
            ("sans-serif", 26),
        )
        .map_err(|e| err(&e))?;
    let panels = root.split_evenly((4, 1));
    let colors = &crate::plot_palette::TAB10[..4];
    let n = records.len() as f64;
    for (pi, (name, unit)) in [("t_sr", "ns"), ("w", "µV")].into_iter().enumerate() {
        // parameter panel
        let pts: Vec<(f64, f64, f64, Option<f64>, f64)> = records
            .iter()
            .filter_map(|r| {
                let p = r.parameters.iter().find(|p| p.name == name)?;
                Some((
                    r.iteration as f64,
                    p.value?,
                    p.std.unwrap_or(0.0),
                    p.target,
                    p.tolerance.unwrap_or(0.0),
                ))
            })
            .collect();
        // Scale to the targets and to the trustworthy points: a failed fit with a huge
        // error bar is drawn (clipped), but does not squash everything else.
        let (lo, hi) = pts
            .iter()
            .filter(|p| p.3.is_none_or(|_| p.2 <= 3.0 * p.4.max(1e-12)))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                (
                    lo.min(p.1 - p.2).min(p.3.unwrap_or(p.1) - p.4),
                    hi.max(p.1 + p.2).max(p.3.unwrap_or(p.1) + p.4),
                )
            });
        let pad = (hi - lo).max(1e-9) * 0.08;
        let mut chart = ChartBuilder::on(&panels[pi])
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .caption(format!("({}) {name}", ['a', 'b'][pi]), ("sans-serif", 20))
            .build_cartesian_2d(0f64..n, (lo - pad)..(hi + pad))
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("iteration k")
            .y_desc(format!("{name} ({unit})"))
            .draw()
            .map_err(|e| err(&e))?;
        // target and tolerance band
        chart
            .draw_series(pts.iter().filter_map(|p| {
                let t = p.3?;
                Some(Rectangle::new(
                    [(p.0 - 0.5, t - p.4), (p.0 + 0.5, t + p.4)],
                    RGBColor(170, 200, 255).filled(),
                ))
            }))
            .map_err(|e| err(&e))?
            .label("target ± tolerance")
            .legend(|(x, y)| {
                Rectangle::new(
                    [(x, y - 5), (x + 15, y + 5)],
                    RGBColor(170, 200, 255).filled(),
                )
            });
        chart
            .draw_series(
                pts.iter().map(|p| {
                    ErrorBar::new_vertical(p.0, p.1 - p.2, p.1, p.1 + p.2, RED.filled(), 6)
                }),
            )
            .map_err(|e| err(&e))?;
        chart
            .draw_series(LineSeries::new(
                pts.iter().map(|p| (p.0, p.1)),
                RED.stroke_width(2),
            ))
            .map_err(|e| err(&e))?
            .label(format!("measured {name} ± 1σ"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 15, y)], RED.stroke_width(2)));
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(|e| err(&e))?;

        // gradient panel
        let grads: Vec<(f64, Vec<(f64, f64)>)> = records
            .iter()
            .filter_map(|r| {
                let g = r.gradients.iter().find(|g| g.parameter == name)?;
                let sd = |j: usize| {
                    g.covariance
                        .as_ref()
                        .map_or(0.0, |c| c[j][j].max(0.0).sqrt())
                };
                Some((
                    r.iteration as f64,
                    g.gradient
                        .iter()
                        .enumerate()
                        .map(|(j, &x)| (x, sd(j)))
                        .collect(),
                ))
            })
            .collect();
        let gates = records.first().map(|r| r.gates.clone()).unwrap_or_default();
        let unit_g = records
            .first()
            .and_then(|r| r.gradients.iter().find(|g| g.parameter == name))
            .map_or(String::new(), |g| g.unit.clone());
        let (glo, ghi) = grads
            .iter()
            .flat_map(|(_, v)| v.iter())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &(x, s)| {
                (lo.min(x - s), hi.max(x + s))
            });
        let gpad = (ghi - glo).max(1e-9) * 0.08;
        let mut chart = ChartBuilder::on(&panels[2 + pi])
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .caption(
                format!("({}) gradient of {name}, ±1σ = √diag C", ['c', 'd'][pi]),
                ("sans-serif", 20),
            )
            .build_cartesian_2d(0f64..n, (glo - gpad)..(ghi + gpad))
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("iteration k")
            .y_desc(format!("∂{name}/∂V ({unit_g})"))
            .draw()
            .map_err(|e| err(&e))?;
        for (j, gate) in gates.iter().enumerate() {
            let c = colors[j % colors.len()];
            chart
                .draw_series(grads.iter().map(|(k, v)| {
                    let (x, s) = v[j];
                    ErrorBar::new_vertical(*k, x - s, x, x + s, c.filled(), 5)
                }))
                .map_err(|e| err(&e))?;
            chart
                .draw_series(LineSeries::new(
                    grads.iter().map(|(k, v)| (*k, v[j].0)),
                    c.stroke_width(2),
                ))
                .map_err(|e| err(&e))?
                .label(gate.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 15, y)], c.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// plotters draws text with a font we hand it: the first of the usual system sans fonts.
pub(crate) fn register_font() -> Result<(), CliError> {
    const CANDIDATES: [&str; 4] = [
        "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
        "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
        "/usr/share/fonts/dejavu/DejaVuSans.ttf",
        "/usr/share/fonts/TTF/DejaVuSans.ttf",
    ];
    for path in CANDIDATES {
        if let Ok(bytes) = std::fs::read(path) {
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            return plotters::style::register_font(
                "sans-serif",
                plotters::style::FontStyle::Normal,
                bytes,
            )
            .map_err(|_| CliError::runtime(format!("{path} is not a usable font")));
        }
    }
    Err(CliError::runtime(
        "no TrueType font found for the plot: install fonts-dejavu-core (apt-get install fonts-dejavu-core)",
    ))
}
