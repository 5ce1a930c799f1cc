//! `spintune bench-keep`: keep a tuned qubit in tune for H lab hours while
//! the simulated device drifts, every keep strategy side by side (protocol
//! and statistics in `spintune::benchmark::keep`; this module only runs
//! seeds in parallel, shows progress, writes reports and draws a day).

use std::path::{Path, PathBuf};

use clap::Args;
use serde::Serialize;
use spintune::benchmark::keep::{
    run_keep_seed, summarize_keep, KeepSample, KeepSeedResult, KeepStrategy, KeepSummary,
};
use spintune::benchmark::keep_goals::KeepGoals;
use spintune::benchmark::BenchmarkProtocol;

use crate::bench_runner::{parallel_map, worker_threads, DeviceArgs, RandomDevices};
use crate::cli::CliError;

/// Longest keep window, lab hours (a week).
pub const MAX_HOURS: f64 = 168.0;
/// Most seeds per device.
pub const MAX_SEEDS: u64 = 10_000;

/// Arguments of `spintune bench-keep`.
#[derive(Debug, Args)]
pub struct BenchKeepArgs {
    /// Lab hours kept after the first tuned point (0 < H ≤ 168).
    #[arg(long, default_value_t = 24.0)]
    pub hours: f64,
    /// Number of seeds (seeds 1..=N, at most 10,000).
    #[arg(long, default_value_t = 20)]
    pub seeds: u64,
    /// Comma-separated strategies (default: predictive, the fixed intervals
    /// 20s, 30s, 45s, 1min, 90s, 2min, 3min, 5min, 10min, 30min, 60min, and
    /// never); also `predictive@P%`, the predictive
    /// schedule at out-of-band probability P (e.g. `predictive@2%`), and
    /// `fixed-Nmin` / `fixed-Ns`, any whole interval from 10 s to a day
    /// (e.g. `fixed-2min`, `fixed-90s`), for the frontier of lab time
    /// against time in band.
    #[arg(long, value_delimiter = ',')]
    pub strategies: Vec<String>,
    /// The device(s), the tuner (and its `tuner.keep` settings), the band
    /// and the worker threads.
    #[command(flatten)]
    pub devices: DeviceArgs,
    /// Write machine-readable results here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write every run's result, with its day sampled every lab minute
    /// (true t_sr and w, checks, re-tunes), to this JSON file (for analysis;
    /// about 1,500 samples per run and 24 lab hours).
    #[arg(long)]
    pub runs_json: Option<PathBuf>,
    /// Draw one seed's day (true t_sr and w, band, checks, re-tunes) to this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Seed drawn by `--plot` (its first strategy).
    #[arg(long, default_value_t = 1)]
    pub plot_seed: u64,
}

/// The JSON report.
#[derive(Debug, Serialize)]
pub struct BenchKeepReport {
    /// Lab hours kept.
    pub hours: f64,
    /// Seeds per device.
    pub seeds: u64,
    /// Relative tolerance of both parameters.
    pub relative_tolerance: f64,
    /// One object per strategy.
    pub strategies: Vec<KeepSummary>,
    /// Issue 23's goals judged on these strategies.
    pub goals: KeepGoals,
    /// With `--random-devices`: the devices.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub random_devices: Option<RandomDevices>,
}

/// Run `spintune bench-keep`.
pub fn run(args: BenchKeepArgs) -> Result<(), CliError> {
    if !(args.hours.is_finite() && args.hours > 0.0 && args.hours <= MAX_HOURS) {
        return Err(CliError::input(format!(
            "--hours must be more than 0 and at most {MAX_HOURS}"
        )));
    }
    if !(1..=MAX_SEEDS).contains(&args.seeds) {
        return Err(CliError::input(format!(
            "--seeds must be between 1 and {MAX_SEEDS}"
        )));
    }
    let strategies = parse_strategies(&args.strategies)?;
    let (base, product) = args.devices.load()?;
    let protocol = BenchmarkProtocol {
        relative_tolerance: args.devices.tolerance,
        ..BenchmarkProtocol::default()
    };
    let threads = worker_threads(args.devices.threads);
    let (devices, random_devices) = args.devices.devices(&base, &protocol)?;
    let work: Vec<(usize, u64, KeepStrategy)> = (0..devices.len())
        .flat_map(|d| {
            let strategies = &strategies;
            (1..=args.seeds).flat_map(move |s| strategies.iter().map(move |&k| (d, s, k)))
        })
        .collect();
    let (mut results, failures) = parallel_map(&work, threads, |&(d, seed, strategy)| {
        let (device, cfg) = &devices[d];
        let trace = args.runs_json.is_some();
        run_keep_seed(cfg, &product, strategy, &protocol, args.hours, seed, trace)
            .map(|mut r| {
                r.device = *device;
                r
            })
            .map_err(|e| format!("device {device}, {}: {e}", strategy.name()))
    });
    let order = |k: KeepStrategy| strategies.iter().position(|&s| s == k);
    results.sort_by_key(|r| (r.device, r.seed, order(r.strategy)));
    for f in &failures {
        eprintln!("warning: {f}");
    }
    if let Some(path) = &args.runs_json {
        let text = serde_json::to_string(&results).expect("serializable results");
        std::fs::write(path, text)
            .map_err(|e| CliError::runtime(format!("cannot write {}: {e}", path.display())))?;
        eprintln!("wrote {}", path.display());
    }
    let summary = summarize_keep(&results, &strategies, args.hours);
    println!(
        "{}",
        markdown_table(&summary, devices.len() as u64 * args.seeds, &args)
    );
    if let Some(path) = &args.json {
        let report = BenchKeepReport {
            hours: args.hours,
            seeds: args.seeds,
            relative_tolerance: args.devices.tolerance,
            goals: KeepGoals::judge(&summary),
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
        let r = run_keep_seed(
            &devices[0].1,
            &product,
            strategy,
            &protocol,
            args.hours,
            args.plot_seed,
            true,
        )
        .map_err(|e| CliError::runtime(e.to_string()))?;
        let targets = product
            .top()
            .parameters
            .iter()
            .filter_map(|p| Some((p.name.clone(), p.target?)))
            .collect::<Vec<_>>();
        draw_day(path, &r, &targets, args.devices.tolerance, args.hours)?;
        eprintln!("wrote {}", path.display());
    }
    if !failures.is_empty() {
        return Err(CliError::runtime(format!(
            "{} run(s) failed",
            failures.len()
        )));
    }
    Ok(())
}

fn parse_strategies(names: &[String]) -> Result<Vec<KeepStrategy>, CliError> {
    crate::bench_runner::parse_names(
        names,
        &KeepStrategy::ALL,
        KeepStrategy::parse,
        |s| s.name(),
        "keep strategy",
        ", or predictive@P% (0.01 % ≤ P ≤ 50 %), or fixed-Nmin / fixed-Ns (10 s to 1 day)",
    )
}

/// The markdown table printed at the end.
pub fn markdown_table(summary: &[KeepSummary], runs: u64, args: &BenchKeepArgs) -> String {
    let mut s = format!(
        "Runs (devices × seeds): {runs}; {:.0} lab hours kept after the first tuned point, tolerance ±{:.0} %.\n\n",
        args.hours,
        args.devices.tolerance * 100.0
    );
    s.push_str("| strategy | fraction in band (mean) | median | p10 | min | measurement min/h | re-tunes/day | checks/day | longest out of band, min (median) | p90 | max | alerts | not tuned | limit violations | truth queries |\n");
    s.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for r in summary {
        s.push_str(&format!(
            "| {} | {:.4} | {:.4} | {:.4} | {:.4} | {:.2} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {} | {} | {} | {} |\n",
            r.name,
            r.fraction_in_band,
            r.fraction_in_band_low.median,
            r.fraction_in_band_low.p90,
            r.fraction_in_band_low.max,
            r.measurement_minutes_per_hour,
            r.retunes_per_day,
            r.checks_per_day,
            r.longest_out_of_band_minutes.median,
            r.longest_out_of_band_minutes.p90,
            r.longest_out_of_band_minutes.max,
            r.alerts,
            r.not_tuned,
            r.limit_violations,
            r.truth_queries,
        ));
    }
    s.push_str(&time_by_kind_table(summary));
    s.push_str("\nGoals (issue 23, judged on the strategies above):\n\n");
    for line in KeepGoals::judge(summary).lines() {
        s.push_str(&format!("- {line}\n"));
    }
    s
}

/// Where each strategy's measurement time goes: lab min per lab hour,
/// grouped from the JSON's `phase/kind` keys (mean over runs).
fn time_by_kind_table(summary: &[KeepSummary]) -> String {
    const GROUPS: [(&str, &[&str]); 7] = [
        ("check: t_sr scans", &["check/reload_time"]),
        ("check: w scans", &["check/transition_width"]),
        (
            "check: lower levels, read-backs",
            &[
                "check/sensing_dot",
                "check/chemical_potential",
                "check/set_voltages",
                "check/read_voltages",
            ],
        ),
        (
            "re-tune: t_sr + w scans",
            &["retune/reload_time", "retune/transition_width"],
        ),
        (
            "re-tune: lower levels",
            &["retune/sensing_dot", "retune/chemical_potential"],
        ),
        (
            "re-tune: moves, read-backs",
            &["retune/set_voltages", "retune/read_voltages"],
        ),
        ("settling after the first tuned point", &["tuning/"]),
    ];
    if summary
        .iter()
        .all(|r| r.minutes_per_hour_by_kind.is_empty())
    {
        return String::new();
    }
    let mut s =
        String::from("\nWhere the measurement time goes (lab min per lab hour):\n\n| strategy |");
    for (name, _) in GROUPS {
        s.push_str(&format!(" {name} |"));
    }
    s.push_str("\n|---|");
    s.push_str(&"---:|".repeat(GROUPS.len()));
    s.push('\n');
    for r in summary {
        s.push_str(&format!("| {} |", r.name));
        for (_, keys) in GROUPS {
            let v: f64 = r
                .minutes_per_hour_by_kind
                .iter()
                .filter(|(k, _)| keys.iter().any(|p| k.starts_with(p)))
                .map(|(_, v)| v)
                .sum::<f64>()
                + 0.0; // an empty sum is −0.0
            s.push_str(&format!(" {v:.2} |"));
        }
        s.push('\n');
    }
    s
}

/// A day of one run: true t_sr and w relative to their targets, the band,
/// and the lab times of checks and re-tunes.
fn draw_day(
    path: &Path,
    r: &KeepSeedResult,
    targets: &[(String, f64)],
    tolerance: f64,
    hours: f64,
) -> Result<(), CliError> {
    use plotters::prelude::*;
    crate::bench::register_font()?;
    let err = |e: &dyn std::fmt::Display| CliError::runtime(format!("plot: {e}"));
    let target = |name: &str| {
        targets
            .iter()
            .find(|(n, _)| n == name)
            .map_or(f64::NAN, |t| t.1)
    };
    let (t_sr0, w0) = (target("t_sr"), target("w"));
    let root = BitMapBackend::new(path, (1200, 900)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let title = format!(
        "spintune bench-keep: {} on seed {}, {:.0} lab h — fraction in band {:.3}, {:.2} measurement min/h, {} checks, {} re-tunes",
        r.strategy.name(),
        r.seed,
        hours,
        r.fraction_in_band,
        r.measurement_minutes_per_hour,
        r.checks,
        r.retunes
    );
    let root = root
        .titled(&title, ("sans-serif", 18))
        .map_err(|e| err(&e))?;
    let panels = root.split_evenly((2, 1));
    let kept: Vec<&KeepSample> = r.trace.iter().filter(|s| s.hours >= 0.0).collect();
    for (pi, (name, unit)) in [("t_sr", "ns"), ("w", "µV")].into_iter().enumerate() {
        let target = if pi == 0 { t_sr0 } else { w0 };
        let value = |s: &KeepSample| if pi == 0 { s.t_sr_ns } else { s.w_uv };
        let (lo, hi) = kept.iter().map(|s| value(s)).fold(
            (
                target * (1.0 - 1.5 * tolerance),
                target * (1.0 + 1.5 * tolerance),
            ),
            |(lo, hi), v| (lo.min(v), hi.max(v)),
        );
        let mut chart = ChartBuilder::on(&panels[pi])
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(80)
            .build_cartesian_2d(0f64..hours, lo..hi)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .light_line_style(TRANSPARENT)
            .x_desc("lab time since first tuned (h)")
            .y_desc(format!("true {name} ({unit})"))
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [
                    (0.0, target * (1.0 - tolerance)),
                    (hours, target * (1.0 + tolerance)),
                ],
                RGBColor(120, 200, 120).mix(0.25).filled(),
            )))
            .map_err(|e| err(&e))?
            .label(format!("±{:.0} % band", tolerance * 100.0))
            .legend(|(x, y)| {
                Rectangle::new(
                    [(x, y - 5), (x + 20, y + 5)],
                    RGBColor(120, 200, 120).mix(0.25).filled(),
                )
            });
        chart
            .draw_series(LineSeries::new(
                kept.iter().map(|s| (s.hours, value(s))),
                RGBColor(31, 119, 180).stroke_width(2),
            ))
            .map_err(|e| err(&e))?
            .label(format!("true {name} (world side)"))
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RGBColor(31, 119, 180)));
        for (mark, color, label) in [
            ("check", RGBColor(90, 90, 90), "check"),
            ("retune", RGBColor(214, 39, 40), "re-tune started"),
        ] {
            chart
                .draw_series(
                    kept.iter()
                        .filter(|s| s.mark == mark)
                        .map(|s| Circle::new((s.hours, value(s)), 3, color.filled())),
                )
                .map_err(|e| err(&e))?
                .label(label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 3, color.filled()));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))
}
