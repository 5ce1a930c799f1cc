//! The simulated double quantum dot: physics, raw scans, noise and the lab
//! clock (ARCHITECTURE.md, "The simulated device"). No IO; randomness only from the
//! seeded `ChaCha8Rng` inside [`SimulatedDevice`]; transcendental functions
//! from [`crate::detmath`] so data are bit-identical on native and wasm.
//!
//! Physics (all voltages mV, `d_g` = deviation from the reference):
//! - t_c (µeV) and Γ (1/ns) are [`config::ExpModel`]s: exponentials of a
//!   linear plus quadratic (cross-term) form in `d`. t_sr = 1/Γ.
//! - Excess charge across the inter-dot transition:
//!   `½(1 − ε/Ω·tanh(Ω/2kT))`, `Ω = √(ε² + 4t_c²)`, `ε = α·detuning`.
//!   w (µV) is defined as the width of the tanh-step fit to this lineshape
//!   on the centred detuning grid ([`Truth::W_DEFINITION`]).
//! - Transition lines: linear (nominal) crosstalk matrix plus quadratic terms;
//!   0 mV at the start voltages. Off-centre lines shift the w step, shrink
//!   both signals and lengthen the apparent t_sr.
//! - Sensing dot: comb of `sech²` Coulomb peaks in a potential that every
//!   gate shifts; the readout step is `G'(u)·charge_shift`.
//! - Noise: white per point, Ornstein–Uhlenbeck drifts of line positions,
//!   sensing-dot potential and signal offset, and charge jumps (Poisson)
//!   that shift the sensing dot persistently, also in the middle of a scan.

pub mod array;
pub mod calibration;
pub mod clock;
pub mod config;
pub mod device;
pub mod gates;
pub mod landscape;
pub(crate) mod model;
pub mod noise;
pub mod random;
pub mod scans;

pub use calibration::{calibrate_reference, CalibrationError};
pub use clock::LabClock;
pub use config::{DeviceConfig, SlowDrift};
pub use device::{SimulatedDevice, Truth};
pub use gates::default_gates;
pub use landscape::ErrorGrid;
pub use noise::DriftState;
