//! What the array tests share: the joint loop on a 3-cell world of the
//! default population (cell 0 the default device, device seed 5, noise
//! seed 11), at the benchmark's default settings and the world's crosstalk
//! as the lab's calibration.

use spintune::benchmark::array::{world, ArrayProtocol};
use spintune::sim::array::{ArrayConfig, ArrayDevice};
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::ArrayRun;
use spintune::tuner::TunerConfig;

/// The world and a joint loop with one tuner per cell (`cells.len()` = 3).
pub fn three_cells(cells: Vec<TunerConfig>) -> (ArrayRun, ArrayDevice) {
    let protocol = ArrayProtocol::default();
    let device = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(3, 5, 11),
        |_| true,
    )
    .unwrap();
    let run = ArrayRun::new(
        cells,
        &device.gates(),
        protocol.run_settings(),
        [0.3, 0.05],
        false,
    )
    .unwrap();
    (run, device)
}
