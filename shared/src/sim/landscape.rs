//! The simulator's ground truth on a 2-D voltage grid: how far each point is
//! from the targets, for the teaching mode's heat map. It reads the truth,
//! so it is for showing what the tuner cannot see, never for tuning
//! (ARCHITECTURE.md, invariant 7).

use crate::parameter::ParameterSpec;
use crate::protocol::{Request, Response};

use super::SimulatedDevice;

/// Distance to the targets on a grid in the plane of two gates.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorGrid {
    /// Grid voltages of the x gate, mV.
    pub xs: Vec<f64>,
    /// Grid voltages of the y gate, mV.
    pub ys: Vec<f64>,
    /// Row-major (y, x): the largest `|p − target| / tolerance` over the
    /// targeted parameters (≤ 1: every one in its band); NaN where the
    /// device refuses the voltages (outside a gate's limits).
    pub error: Vec<f64>,
}

impl SimulatedDevice {
    /// The noiseless truth on an `n`×`n` grid, ±`half_mv` around the present
    /// voltages of gates `gx` and `gy` (the other gates where they are),
    /// against the targets and tolerances of `parameters` (any parameter
    /// the simulator knows, [`super::Truth::PARAMETERS`]; the others are
    /// skipped). `None` if a gate is unknown or no parameter has a target
    /// the simulator can evaluate. The device itself is not changed.
    ///
    /// ```
    /// use spintune::driver::SimulationConfig;
    /// let cfg = SimulationConfig::paper_default();
    /// let device = cfg.simulated_device().unwrap();
    /// let grid = device.error_grid("N", "T", 10.0, 5, &cfg.tuner.top().parameters).unwrap();
    /// assert_eq!((grid.xs.len(), grid.ys.len(), grid.error.len()), (5, 5, 25));
    /// assert!(grid.error.iter().all(|e| *e >= 0.0));
    /// ```
    pub fn error_grid(
        &self,
        gx: &str,
        gy: &str,
        half_mv: f64,
        n: usize,
        parameters: &[ParameterSpec],
    ) -> Option<ErrorGrid> {
        let v0 = self.voltages_mv();
        let (cx, cy) = (*v0.get(gx)?, *v0.get(gy)?);
        let truth = self.truth();
        let bands: Vec<(&str, f64, f64)> = parameters
            .iter()
            .filter_map(|p| {
                let t = p.target?;
                truth.get(&p.name)?;
                Some((p.name.as_str(), t, p.tolerance.half_width(t).max(1e-12)))
            })
            .collect();
        if bands.is_empty() {
            return None;
        }
        let n = n.max(2);
        let step = 2.0 * half_mv / (n - 1) as f64;
        let xs: Vec<f64> = (0..n).map(|i| cx - half_mv + step * i as f64).collect();
        let ys: Vec<f64> = (0..n).map(|j| cy - half_mv + step * j as f64).collect();
        let mut probe = self.clone();
        let mut error = vec![f64::NAN; n * n];
        for (j, y) in ys.iter().enumerate() {
            for (i, x) in xs.iter().enumerate() {
                let set = Request::SetVoltages {
                    voltages_mv: [(gx.to_string(), *x), (gy.to_string(), *y)].into(),
                };
                if let Response::VoltagesSet { .. } = probe.execute(&set) {
                    let t = probe.truth();
                    error[j * n + i] = bands
                        .iter()
                        .filter_map(|(name, target, tol)| Some((t.get(name)? - target).abs() / tol))
                        .fold(0.0, f64::max);
                }
            }
        }
        Some(ErrorGrid { xs, ys, error })
    }
}
