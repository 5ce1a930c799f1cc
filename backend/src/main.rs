//! `spintune`: the backend binary. Each subcommand's arguments and
//! implementation live in the library (`spintune_server::cli` and friends);
//! to add a subcommand, add a variant here and one match arm in `main`.

use clap::{Parser, Subcommand};
use spintune_server::cli::{self, CliError};

/// spintune: automated fine-tuning of spin qubits (Kalman-filter gradient tracking).
#[derive(Debug, Parser)]
#[command(name = "spintune", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Start the run server and dashboard (creates a demo run on the simulator
    /// when the store is empty).
    Serve(cli::ServeArgs),
    /// A full tuning run without the browser, from a TOML config.
    Run(cli::RunArgs),
    /// Work with run configs (`spintune config resolve FILE`).
    Config(cli::ConfigArgs),
    /// Export a stored run as CSV or JSON (one row per iteration).
    Export(cli::ExportArgs),
    /// Offline Kalman replay of a recorded sequence (JSON), to choose Q.
    Replay(cli::ReplayArgs),
    /// An untended stretch of lab time on the simulated device: how its slow
    /// drift carries w and t_sr out of their band.
    DriftDay(spintune_server::drift_day::DriftDayArgs),
    /// The paper's set-point benchmark over many seeds, all strategies side by side.
    Bench(spintune_server::bench::BenchArgs),
    /// Keep a tuned qubit in tune for hours of drift, every keep strategy side by side.
    BenchKeep(spintune_server::bench_keep::BenchKeepArgs),
    /// Tune an array of double-dot cells (crosstalk, readout groups), every
    /// array strategy side by side.
    BenchArray(spintune_server::bench_array::BenchArrayArgs),
    /// Load bench of the server: N WebSocket viewers on one run at a fixed rate.
    BenchServer(spintune_server::bench_server::BenchServerArgs),
}

fn main() {
    let cli = Cli::parse();
    let result: Result<(), CliError> = match cli.command {
        Command::Serve(args) => runtime().block_on(cli::serve(args)),
        Command::Run(args) => runtime().block_on(cli::run(args)),
        Command::Config(args) => cli::config(args),
        Command::Export(args) => cli::export(args),
        Command::Replay(args) => cli::replay(args),
        Command::Bench(args) => spintune_server::bench::run(args),
        Command::DriftDay(args) => spintune_server::drift_day::run(args),
        Command::BenchKeep(args) => spintune_server::bench_keep::run(args),
        Command::BenchArray(args) => spintune_server::bench_array::run(args),
        Command::BenchServer(args) => spintune_server::bench_server::main(args),
    };
    if let Err(e) = result {
        eprintln!("error: {}", e.message);
        std::process::exit(e.code);
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap_or_else(|e| {
            eprintln!("error: cannot start the async runtime: {e}");
            std::process::exit(1)
        })
}
