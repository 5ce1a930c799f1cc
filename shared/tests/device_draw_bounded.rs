//! Drawing a benchmark array ends: random arrays 9001… once hung for ever
//! inside `targets_reachable`, whose SVD (nalgebra's, unbounded) never
//! converged on one candidate cell's Jacobian. The draw now rejects such a
//! candidate: non-finite Jacobians are refused and the SVD is bounded.

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::{draw_devices, BenchmarkProtocol};
use spintune::driver::SimulationConfig;
use spintune::sim::array::cell_devices;
use spintune::sim::gates::default_gates;
use spintune::sim::random::targets_reachable;
use spintune::sim::DeviceConfig;

#[test]
fn the_cells_of_the_random_arrays_from_9001_are_drawn() {
    let protocol = ArrayProtocol::default();
    let mut set_points = protocol.set_points.clone();
    set_points.push(protocol.single_cell_target);
    let gates = default_gates();
    let reachable = |d: &DeviceConfig| {
        targets_reachable(
            d,
            &gates,
            &["N", "SA", "SB", "T"],
            &["PA", "PB"],
            &set_points,
        )
    };
    // as `spintune bench-array --random-devices 3 --device-seed 9001`: three
    // plausible base devices, each array's cells drawn around its own
    let base = SimulationConfig::paper_default();
    let (devices, _) = draw_devices(&base, &BenchmarkProtocol::default(), 3, 9001);
    assert_eq!(devices.len(), 3);
    for (device_seed, device) in &devices {
        let cells = cell_devices(device, 9, *device_seed, reachable);
        assert_eq!(cells.len(), 9, "array {device_seed}");
    }
}
