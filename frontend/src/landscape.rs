//! The simulator's ground truth on a voltage grid (data for the heat map).

/// Ground truth on a 2-D voltage grid, for the heat map.
#[derive(Debug, Clone, PartialEq)]
pub struct Landscape {
    /// Gate on the x axis.
    pub gx: String,
    /// Gate on the y axis.
    pub gy: String,
    /// Grid voltages on x, mV.
    pub xs: Vec<f64>,
    /// Grid voltages on y, mV.
    pub ys: Vec<f64>,
    /// Row-major (y, x) distance to target in tolerance units.
    pub error: Vec<f64>,
    /// The run's path in this plane, mV.
    pub path: Vec<(f64, f64)>,
    /// Present voltages, mV.
    pub now: (f64, f64),
}
