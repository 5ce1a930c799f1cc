//! # spintune — the pure core
//!
//! Automated fine-tuning of gate-defined quantum-dot spin qubits after Teske
//! et al., "A Machine Learning Approach for Automated Fine-Tuning of
//! Semiconductor Spin Qubits" (APL 2019): a Kalman filter per parameter tracks
//! the gradient over the gate voltages ([`kalman`]), a quasi-Newton solver
//! moves the gates in limited steps ([`solver`]), and a sans-IO state machine
//! ([`tuner`]) runs the hierarchy sensing dot → chemical potentials → qubit
//! parameters. [`sim`] is a simulated double dot producing raw scans that
//! [`fit`] evaluates; [`driver`] wires tuner and simulator together. Both
//! `sim` and `fit` compute with [`detmath`], so results are bit-identical
//! natively and in wasm; `fit` does not depend on `sim`.
//!
//! This crate does no IO (no files, sockets, clocks or threads) and builds for
//! `wasm32-unknown-unknown` unchanged.
//!
//! Units: gate voltages in mV everywhere (`_mv`), times in s or ns as named,
//! `t_sr` in ns, `w` in µV, gradients in parameter unit per mV.
#![warn(missing_docs)]

pub mod alert;
pub mod benchmark;
pub mod config_error;
pub mod config_merge;
pub mod decomposition;
pub mod description;
pub mod detmath;
pub mod driver;
pub mod estimator;
pub mod fit;
pub mod kalman;
pub mod lifecycle;
pub mod parameter;
pub mod protocol;
pub mod run_config;
pub mod safety;
pub mod session;
pub mod sim;
pub mod solver;
pub mod strict_json;
pub mod tuner;

pub use config_error::ConfigError;
