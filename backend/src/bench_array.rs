//! `spintune bench-array`: an array of K double-dot cells tuned by every
//! array strategy side by side (protocol, strategies and statistics in
//! `spintune::benchmark::array`; this module only runs arrays × seeds in
//! parallel and writes the reports).

use std::path::PathBuf;

use clap::Args;
use serde::Serialize;
use spintune::benchmark::array::{
    markdown, run_strategy, single_change_cells, summarize_array, world, ArrayProtocol,
    ArrayRunResult, ArrayStrategy, ArraySummary,
};
use spintune::benchmark::array_timeline::CellBand;
use spintune::benchmark::cell_trace::error_bar_coverage;
use spintune::benchmark::oracle_twin::{oracle_twin, OracleTwin};
use spintune::benchmark::BenchmarkProtocol;
use spintune::description::layout::Layout;
use spintune::driver::SimulationConfig;
use spintune::sim::array::{ArrayConfig, MAX_CELLS};
use spintune::sim::random::cell_targets_reachable;
use spintune::tuner::array_run::ArrayRunSettings;

use crate::bench_runner::{parallel_map, select_devices, worker_threads, RandomDevices};
use crate::cli::CliError;

/// Most seeds per array.
pub const MAX_SEEDS: u64 = 1_000;

/// Arguments of `spintune bench-array`.
#[derive(Debug, Args)]
pub struct BenchArrayArgs {
    /// Cells in the array (1..=16).
    #[arg(long, default_value_t = 9)]
    pub cells: u32,
    /// Where the cells sit: `chain`, or `ladder` (two rows of cells/2,
    /// numbered row by row; an even number of cells, at least 4).
    #[arg(long, default_value = "chain", value_parser = parse_layout)]
    pub layout: Layout,
    /// Number of noise seeds (seeds 1..=N, at most 1,000).
    #[arg(long, default_value_t = 3)]
    pub seeds: u64,
    /// Comma-separated strategies (default: all): serial, independent, joint, oracle.
    #[arg(long, value_delimiter = ',')]
    pub strategies: Vec<String>,
    /// N arrays whose cell 0 is a random device (instead of the default
    /// device); every array's other cells are drawn around its cell 0.
    #[arg(long)]
    pub random_devices: Option<usize>,
    /// Device seed of the first random device (then +1, +2, …).
    #[arg(long, default_value_t = 1)]
    pub device_seed: u64,
    /// Nearest-neighbour crosstalk fraction (0..=0.9).
    #[arg(long, default_value_t = 0.3)]
    pub nearest: f64,
    /// Next-nearest crosstalk fraction (0..=nearest).
    #[arg(long, default_value_t = 0.05)]
    pub next: f64,
    /// The lab's cross-cell calibration `λ̂` NEAREST,NEXT taken as given,
    /// whatever the world's crosstalk (to measure a calibration that is
    /// wrong) [default: the world's, each off by up to ±20 % per seed].
    #[arg(long, value_name = "NEAREST,NEXT", value_parser = parse_pair)]
    pub cross_calibration: Option<[f64; 2]>,
    /// Cells sharing one sensor readout: readout groups of this many
    /// neighbouring cells (their scans run one after the other), 1..=16.
    #[arg(long, default_value_t = 1)]
    pub cells_per_sensor: u32,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// `joint`/`oracle`: correct a cell's plungers from its lines'
    /// forecast before the line scan when the forecast puts a line beyond
    /// this many mV (0 < MV ≤ 4; 0 turns it off) [default: the protocol's, 1].
    #[arg(long)]
    pub precorrect_lines_mv: Option<f64>,
    /// `joint`/`oracle`: skip the scans of a held cell that shares its
    /// sensor when predicted in band with this many σ (0.5..=10; 0 turns it
    /// off) [default: the protocol's, 1.5].
    #[arg(long)]
    pub skip_confident_sigma: Option<f64>,
    /// The joint loop's settings from this TOML file (an `ArrayRunSettings`
    /// table: `relative_tolerance`, `line_rounds`, `[joint]`, …; every key
    /// optional, errors name the field); `--precorrect-lines-mv` applies over it.
    #[arg(long, value_name = "FILE")]
    pub tuning: Option<PathBuf>,
    /// Write machine-readable results here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Draw one run of the joint loop (`joint`, else `oracle`) on the first
    /// array as cells × lab time, in band or not, to this PNG.
    #[arg(long, value_name = "FILE")]
    pub plot: Option<PathBuf>,
    /// Seed drawn by `--plot` (1..=--seeds).
    #[arg(long, default_value_t = 1)]
    pub plot_seed: u64,
    /// Follow cell K (0..--cells) through every `joint`/`oracle` run: per
    /// iteration its gate voltages, measured and true `t_sr` and `w`, and
    /// the own-gate rows its move was planned with against the true ones,
    /// and where its transition lines truly sat, at the measurement and at
    /// its line scan after the move (printed after the table, and in the
    /// JSON's timeline).
    #[arg(long, value_name = "K")]
    pub trace_cell: Option<u32>,
    /// Also run the oracle on noise seeds N+1..=2N (N = --seeds) and pair
    /// each with the oracle's run on seed s − N of the same array, as
    /// `joint` is paired with the oracle: how often a strategy planning
    /// with the true Jacobian fails "not converged where the oracle
    /// converged" and leaves neighbours out, the noise floor of those
    /// goals (printed after the table; `oracle_twin` in the JSON). Needs
    /// `oracle` in --strategies.
    #[arg(long)]
    pub oracle_twin: bool,
}

/// The JSON report.
#[derive(Debug, Serialize)]
pub struct BenchArrayReport {
    /// Cells per array.
    pub cells: u32,
    /// Where they sit (left out for a chain).
    #[serde(skip_serializing_if = "Layout::is_chain")]
    pub layout: Layout,
    /// Seeds per array.
    pub seeds: u64,
    /// The protocol.
    pub protocol: ArrayProtocol,
    /// One object per strategy.
    pub strategies: Vec<ArraySummary>,
    /// Every run.
    pub runs: Vec<ArrayRunResult>,
    /// With `--random-devices`: the devices of cell 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub random_devices: Option<RandomDevices>,
    /// With `--oracle-twin`: the oracle against itself (its runs on seeds
    /// above `seeds` are not in `runs`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub oracle_twin: Option<OracleTwin>,
}

/// Run `spintune bench-array`.
pub fn run(args: BenchArrayArgs) -> Result<(), CliError> {
    if !(1..=MAX_CELLS).contains(&args.cells) {
        return Err(CliError::input(format!(
            "--cells must be between 1 and {MAX_CELLS}"
        )));
    }
    if !(1..=MAX_SEEDS).contains(&args.seeds) {
        return Err(CliError::input(format!(
            "--seeds must be between 1 and {MAX_SEEDS}"
        )));
    }
    let strategies = parse_strategies(&args.strategies)?;
    if args.oracle_twin && !strategies.contains(&ArrayStrategy::Oracle) {
        return Err(CliError::input(
            "--oracle-twin pairs the oracle with itself: add oracle to --strategies".to_string(),
        ));
    }
    let plotted = [ArrayStrategy::Joint, ArrayStrategy::Oracle]
        .into_iter()
        .find(|s| strategies.contains(s));
    if args.plot.is_some() {
        if plotted.is_none() {
            return Err(CliError::input(
                "--plot draws the joint loop: add joint or oracle to --strategies".to_string(),
            ));
        }
        if !(1..=args.seeds).contains(&args.plot_seed) {
            return Err(CliError::input(format!(
                "--plot-seed must be between 1 and --seeds ({})",
                args.seeds
            )));
        }
    }
    let mut protocol = ArrayProtocol::default();
    if let Some(path) = &args.tuning {
        protocol.tuning = read_tuning(path)?;
    }
    if let Some(mv) = args.precorrect_lines_mv {
        protocol.tuning.precorrect_lines_mv = (mv != 0.0).then_some(mv);
    }
    if let Some(k) = args.skip_confident_sigma {
        protocol.tuning.skip_confident_sigma = (k != 0.0).then_some(k);
    }
    if let Some(l) = args.cross_calibration {
        protocol.cross_calibration = Some(l);
    }
    if let Some(c) = args.trace_cell {
        if c >= args.cells {
            return Err(CliError::input(format!(
                "--trace-cell {c}: the cells are 0..{} (--cells {})",
                args.cells, args.cells
            )));
        }
        protocol.trace_cell = Some(c);
    }
    protocol.validate().map_err(|e| {
        CliError::input(format!(
            "--tuning / --precorrect-lines-mv / --skip-confident-sigma / --cross-calibration: {e}"
        ))
    })?;
    let base = SimulationConfig::paper_default();
    let bench_protocol = BenchmarkProtocol::default();
    let (devices, random_devices) = select_devices(
        &base,
        &bench_protocol,
        args.random_devices,
        args.device_seed,
    )?;
    let mut probe = ArrayConfig::chain(args.cells, 0, 0);
    probe.layout = args.layout;
    probe
        .grid()
        .map_err(|e| CliError::input(format!("--cells {} --layout ladder: {e}", args.cells)))?;
    probe.crosstalk.nearest = args.nearest;
    probe.crosstalk.next = args.next;
    probe
        .validate()
        .map_err(|e| CliError::input(format!("--nearest/--next: {e}")))?;
    if !(1..=MAX_CELLS).contains(&args.cells_per_sensor) {
        return Err(CliError::input(format!(
            "--cells-per-sensor {} outside 1..={MAX_CELLS}",
            args.cells_per_sensor
        )));
    }
    if args.cells_per_sensor > 1 {
        let cells: Vec<u32> = (0..args.cells).collect();
        probe.readout_groups = Some(
            cells
                .chunks(args.cells_per_sensor as usize)
                .map(<[u32]>::to_vec)
                .collect(),
        );
    }
    let threads = worker_threads(args.threads);
    let mut set_points = protocol.set_points.clone();
    set_points.push(protocol.single_cell_target);
    let reachable = |d: &spintune::sim::DeviceConfig| cell_targets_reachable(d, &set_points);
    let twin_seeds = if args.oracle_twin { args.seeds } else { 0 };
    let work: Vec<(usize, u64, ArrayStrategy)> = (0..devices.len())
        .flat_map(|d| {
            (1..=args.seeds + twin_seeds).flat_map(move |s| ArrayStrategy::ALL.map(|k| (d, s, k)))
        })
        .filter(|(_, _, k)| strategies.contains(k))
        .filter(|&(_, s, k)| s <= args.seeds || k == ArrayStrategy::Oracle)
        .collect();
    let (mut results, failures) = parallel_map(&work, threads, |&(d, seed, strategy)| {
        let (device, cfg) = &devices[d];
        let config = ArrayConfig {
            seed,
            device_seed: *device,
            ..probe.clone()
        };
        let array =
            world(&cfg.device, config, reachable).map_err(|e| format!("device {device}: {e}"))?;
        run_strategy(strategy, array, &protocol)
            .map_err(|e| format!("device {device}, seed {seed}, {}: {e}", strategy.name()))
    });
    results.sort_by_key(|r| (r.device, r.seed, r.strategy));
    for f in &failures {
        eprintln!("warning: {f}");
    }
    let twin = oracle_twin(&results, args.seeds);
    results.retain(|r| r.seed <= args.seeds);
    let summary = summarize_array(&results, &strategies);
    let readout = match args.cells_per_sensor {
        1 => "one sensor per cell".to_string(),
        n => format!("{n} neighbouring cells per sensor"),
    };
    let calibration = match args.cross_calibration {
        Some([a, b]) => format!("the lab's calibration λ̂ taken as {a} / {b}"),
        None => "the lab's calibration λ̂ the world's ± 20 %".to_string(),
    };
    println!(
        "Arrays: {} × {} seeds, {} cells{}, crosstalk nearest {} / next {} ({calibration}), {readout}.\n",
        devices.len(),
        args.seeds,
        args.cells,
        match args.layout {
            Layout::Chain => "",
            Layout::Ladder => " in a ladder of two rows",
        },
        args.nearest,
        args.next
    );
    println!("{}", markdown(&summary));
    if let Some(t) = &twin {
        println!(
            "The oracle against itself (noise seeds {}..={} paired with 1..={} on the same arrays): {} not converged where the oracle converged ({} not converged), {} neighbours left out of band, {} runs.\n",
            args.seeds + 1,
            2 * args.seeds,
            args.seeds,
            t.not_converged_where_oracle_converged,
            t.not_converged,
            t.neighbours_left_out_of_band,
            t.runs
        );
    }
    if let Some(c) = args.trace_cell {
        print_traces(&results, c);
    }
    if let (Some(path), Some(strategy)) = (&args.plot, plotted) {
        let first = devices.first().map(|d| d.0);
        let run = results
            .iter()
            .find(|r| r.strategy == strategy && r.seed == args.plot_seed && Some(r.device) == first)
            .ok_or_else(|| CliError::runtime("--plot: the drawn run failed".to_string()))?;
        let single = single_change_cells(args.cells, protocol.single_cell_changes);
        crate::bench_array_plot::draw_timeline(
            path,
            run,
            protocol.set_points.len().saturating_sub(1) as u32,
            &single,
        )?;
    }
    if let Some(path) = &args.json {
        let report = BenchArrayReport {
            cells: args.cells,
            layout: args.layout,
            seeds: args.seeds,
            protocol,
            strategies: summary,
            runs: results,
            random_devices,
            oracle_twin: twin,
        };
        let text = serde_json::to_string_pretty(&report).expect("serializable report");
        std::fs::write(path, text)
            .map_err(|e| CliError::runtime(format!("cannot write {}: {e}", path.display())))?;
    }
    if !failures.is_empty() {
        return Err(CliError::runtime(format!("{} runs failed", failures.len())));
    }
    Ok(())
}

/// Every traced run's cell `c`, one line per iteration.
fn print_traces(results: &[ArrayRunResult], c: u32) {
    for r in results
        .iter()
        .filter(|r| r.timeline.iter().any(|p| p.trace.is_some()))
    {
        println!(
            "\nCell {c}, {} on device {} seed {} (phase, lab min since the start, what the iteration's measurement said of the cell):",
            r.strategy.name(),
            r.device,
            r.seed
        );
        for p in &r.timeline {
            if let Some(t) = &p.trace {
                let verdict = match p.measured.get(c as usize) {
                    Some(CellBand::InBand) => "in band",
                    Some(CellBand::OutOfBand) => "out of band",
                    Some(CellBand::NotMeasured) | None => "not measured",
                };
                println!(
                    "{} {:6.1} {verdict:12} | {}",
                    p.phase,
                    p.lab_minutes,
                    t.line()
                );
            }
        }
    }
    let traces = results
        .iter()
        .flat_map(|r| &r.timeline)
        .filter_map(|p| p.trace.as_ref());
    let coverage = error_bar_coverage(traces);
    let part = |p: usize, name: &str| match coverage[p] {
        Some((f, n)) => format!("{name} {:.0} % of {n}", 100.0 * f),
        None => format!("{name} never measured"),
    };
    println!(
        "\nCell {c}'s scans within 1 reported σ of the truth (Gaussian error bars: 68 %): {}, {}",
        part(0, "t_sr"),
        part(1, "w")
    );
}

fn parse_strategies(names: &[String]) -> Result<Vec<ArrayStrategy>, CliError> {
    crate::bench_runner::parse_names(
        names,
        &ArrayStrategy::ALL,
        ArrayStrategy::from_name,
        |s| s.name().into(),
        "array strategy",
        "",
    )
}

/// An `ArrayRunSettings` from a TOML file, merged key by key into the
/// default (errors name the file and the field).
fn read_tuning(path: &std::path::Path) -> Result<ArrayRunSettings, CliError> {
    let bad = |m: String| CliError::input(format!("--tuning {}: {m}", path.display()));
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let user: serde_json::Value = toml::from_str(&text)
        .map_err(|e| bad(format!("invalid TOML: {}", e.to_string().trim())))?;
    let mut merged =
        serde_json::to_value(ArrayRunSettings::default()).map_err(|e| bad(e.to_string()))?;
    spintune::config_merge::merge(&mut merged, user);
    serde_path_to_error::deserialize(merged)
        .map_err(|e| bad(format!("invalid at `{}`: {}", e.path(), e.inner())))
}

/// `A,B` → `[A, B]` (two finite numbers).
/// `chain` or `ladder`.
fn parse_layout(text: &str) -> Result<Layout, String> {
    match text {
        "chain" => Ok(Layout::Chain),
        "ladder" => Ok(Layout::Ladder),
        other => Err(format!("{other:?}: chain or ladder")),
    }
}

fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let parts: Vec<&str> = text.split(',').collect();
    let [a, b] = parts[..] else {
        return Err(format!("{text:?}: two numbers NEAREST,NEXT, e.g. 0.3,0.05"));
    };
    let num = |t: &str| {
        t.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{t:?} is not a finite number"))
    };
    Ok([num(a)?, num(b)?])
}
