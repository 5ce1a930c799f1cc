//! spintune backend: run server (axum + WebSocket), run manager driving the
//! core's sans-IO tuner through async devices, durable SQLite store, and the
//! headless CLI (`spintune run | serve | export | replay | bench-server`).
//!
//! See [`server`] for the HTTP/WebSocket API and [`config`] for run configs.

pub mod bench;
pub mod bench_server;
pub mod cli;
pub mod config;
pub mod devices;
pub(crate) mod export;
pub mod replay;
pub(crate) mod run;
pub mod server;
pub mod store;
