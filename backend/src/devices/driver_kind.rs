//! Which device a run drives (`driver` in a run config).

use serde::{Deserialize, Serialize};

/// Which device a run drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DriverKind {
    /// The embedded simulated double dot (`spintune::sim`).
    #[default]
    Simulator,
    /// A SCPI DC voltage source over raw TCP sets the gates
    /// ([`super::scpi`]); measurements come from `scpi.measure`.
    Scpi,
    /// An external lab script connected over WebSocket sets gates and
    /// measures ([`super::bridge`]).
    Bridge,
}
