//! What every `spintune bench…` command shares: the device (or random
//! devices) under test and the tuner the product strategy runs, the
//! worker pool with its progress bar, and strategy-name parsing. The
//! commands themselves (`bench`, `bench-keep`, `bench-array`) only choose
//! their protocol and report.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use spintune::benchmark::{draw_devices, BenchmarkProtocol};
use spintune::driver::SimulationConfig;
use spintune::sim::DeviceConfig;
use spintune::tuner::TunerConfig;

use crate::cli::CliError;

/// The single-cell benchmarks' device, tuner and worker options
/// (`#[command(flatten)]` into `bench` and `bench-keep`).
#[derive(Debug, Args)]
pub struct DeviceArgs {
    /// Device description (TOML or JSON) overriding the simulator's defaults.
    #[arg(long)]
    pub device: Option<PathBuf>,
    /// Run config (TOML, as for `spintune run`) whose tuner (and its
    /// `tuner.keep` settings) the product strategies run (default: the
    /// built-in default, what `spintune run` does with a config that has no
    /// `tuner` section).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Benchmark N plausible devices drawn around the (default or `--device`)
    /// device instead of that device alone, each with every seed
    /// (distribution: `spintune::sim::random`; devices whose targets lie
    /// outside the gate limits are rejected and redrawn).
    #[arg(long)]
    pub random_devices: Option<usize>,
    /// Device seed of the first random device (then +1, +2, …).
    #[arg(long, default_value_t = 1)]
    pub device_seed: u64,
    /// Relative tolerance band of both parameters, 0 < T < 1 (0.1 = ±10 %).
    #[arg(long, default_value_t = 0.1)]
    pub tolerance: f64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

impl DeviceArgs {
    /// The simulation every device starts from (the paper's default device
    /// or `--device`, validated) and the tuner the product strategies run
    /// (`--config`'s or the recommended one); `--tolerance` checked.
    pub(crate) fn load(&self) -> Result<(SimulationConfig, TunerConfig), CliError> {
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(CliError::input("--tolerance must be in (0, 1)"));
        }
        let mut base = SimulationConfig::paper_default();
        if let Some(path) = &self.device {
            base.device = load_device(path)?;
        }
        base.validate()
            .map_err(|e| CliError::input(e.to_string()))?;
        let product = match &self.config {
            Some(path) => crate::cli::load_config(path)?.simulation.tuner,
            None => SimulationConfig::recommended().tuner,
        };
        Ok((base, product))
    }

    /// The devices to benchmark under `protocol` ([`select_devices`]).
    pub(crate) fn devices(
        &self,
        base: &SimulationConfig,
        protocol: &BenchmarkProtocol,
    ) -> Result<(Vec<DeviceUnderTest>, Option<RandomDevices>), CliError> {
        select_devices(base, protocol, self.random_devices, self.device_seed)
    }
}

/// Worker threads: `requested`, or every core (at least 1).
pub(crate) fn worker_threads(requested: Option<usize>) -> usize {
    requested
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
        .max(1)
}

/// Which random devices were benchmarked.
#[derive(Debug, Serialize)]
pub struct RandomDevices {
    /// Device seeds of the accepted devices.
    pub device_seeds: Vec<u64>,
    /// Devices drawn and rejected (targets outside the gate limits).
    pub rejected: u64,
}

/// A benchmarked device: its device seed (0: the given device) and config.
pub(crate) type DeviceUnderTest = (u64, SimulationConfig);

/// The devices to benchmark: `base` alone (device seed 0), or `n` random
/// devices drawn around it from `device_seed` on (with the report of which).
pub(crate) fn select_devices(
    base: &SimulationConfig,
    protocol: &BenchmarkProtocol,
    random_devices: Option<usize>,
    device_seed: u64,
) -> Result<(Vec<DeviceUnderTest>, Option<RandomDevices>), CliError> {
    let Some(n) = random_devices else {
        return Ok((vec![(0, base.clone())], None));
    };
    let (drawn, rejected) = draw_devices(base, protocol, n, device_seed);
    if drawn.len() < n {
        return Err(CliError::runtime(format!(
            "only {} of {n} random devices have reachable targets ({rejected} rejected)",
            drawn.len()
        )));
    }
    eprintln!("{n} random devices ({rejected} rejected: targets outside the gate limits)");
    let report = RandomDevices {
        device_seeds: drawn.iter().map(|(k, _)| *k).collect(),
        rejected,
    };
    let configs = drawn
        .into_iter()
        .map(|(k, device)| {
            let mut cfg = base.clone();
            cfg.device = device;
            (k, cfg)
        })
        .collect();
    Ok((configs, Some(report)))
}

/// `f` over `work` on `threads` threads with a progress bar; the results
/// in no particular order and the failures' messages.
pub(crate) fn parallel_map<W: Sync, T: Send>(
    work: &[W],
    threads: usize,
    f: impl Fn(&W) -> Result<T, String> + Sync,
) -> (Vec<T>, Vec<String>) {
    let bar = ProgressBar::new(work.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} seeds {pos}/{len} [{bar:30}] {elapsed} (eta {eta}) {msg}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<T>> = Mutex::new(Vec::new());
    let failures: Mutex<Vec<String>> = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(w) = work.get(i) else { break };
                match f(w) {
                    Ok(r) => results.lock().unwrap().push(r),
                    Err(e) => failures.lock().unwrap().push(e),
                }
                bar.inc(1);
            });
        }
    });
    bar.finish_and_clear();
    (
        results.into_inner().unwrap(),
        failures.into_inner().unwrap(),
    )
}

/// The strategies a comma-separated `--strategies` names (`all` when it is
/// empty), or an input error naming the unknown one and the choices (the
/// names of `all`, then `more`, e.g. a pattern the parser also takes).
pub(crate) fn parse_names<T: Copy>(
    names: &[String],
    all: &[T],
    parse: impl Fn(&str) -> Option<T>,
    name: impl Fn(&T) -> String,
    what: &str,
    more: &str,
) -> Result<Vec<T>, CliError> {
    if names.is_empty() {
        return Ok(all.to_vec());
    }
    names
        .iter()
        .map(|n| {
            parse(n.trim()).ok_or_else(|| {
                let choices: Vec<String> = all.iter().map(&name).collect();
                CliError::input(format!(
                    "unknown {what} {n:?}; choose from {}{more}",
                    choices.join(", ")
                ))
            })
        })
        .collect()
}

pub(crate) fn load_device(path: &Path) -> Result<DeviceConfig, CliError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| CliError::input(format!("cannot read {}: {e}", path.display())))?;
    let is_json = path.extension().is_some_and(|e| e == "json");
    let invalid = |m: &dyn std::fmt::Display| {
        CliError::input(format!("invalid device file {}: {m}", path.display()))
    };
    let device: DeviceConfig = if is_json {
        let de = &mut serde_json::Deserializer::from_str(&text);
        serde_path_to_error::deserialize(de)
            .map_err(|e| invalid(&format_args!("at `{}`: {}", e.path(), e.inner())))?
    } else {
        toml::from_str(&text).map_err(|e| invalid(&e))?
    };
    device
        .validate()
        .map_err(|m| CliError::input(format!("invalid device file {}: {m}", path.display())))?;
    Ok(device)
}
