//! spintune backend: run server (axum + WebSocket), run manager driving the
//! core's sans-IO tuner through async devices, durable SQLite store, and the
//! headless CLI (`spintune run | serve | export | replay | bench-server`).
//!
//! See [`server`] for the HTTP/WebSocket API and [`config`] for run configs.

// What the binary (`main.rs`), the integration tests and the workspace's
// `tests` crate name; everything else is `pub(crate)`, so that rustc and
// clippy report what nothing uses.
pub mod alerts;
pub mod bench;
pub mod bench_array;
pub mod bench_array_plot;
pub mod bench_keep;
pub mod bench_runner;
pub mod bench_server;
pub mod bench_time_plot;
pub mod cli;
pub mod config;
pub(crate) mod devices;
pub mod drift_day;
pub(crate) mod export;
pub mod plot_palette;
pub mod replay;
pub(crate) mod run;
pub mod server;
pub mod store;

/// The SCPI driver's TCP client and the instruments' error type (for the
/// driver's tests against a fake instrument, `tests/scpi.rs`).
pub use devices::{scpi::ScpiSource, DeviceError};
