//! The cells' initial measurements run in lockstep: every cell moves its
//! tuning gates (a finite-difference step) in the same batch as the others
//! and scans while its neighbours stand still, even when one cell needs
//! extra requests (a re-sweep of its sensor, a line correction). So every
//! cell's initial gradient is its own plus its neighbours' crosstalk
//! copies in the same proportion (`spintune::tuner::array::lockstep_factor`,
//! what the joint prior's neighbour blocks and its optional lockstep
//! correction assume); out of step, a cell's gradient could come out with
//! the wrong sign.

mod support;

use std::collections::BTreeSet;

use spintune::benchmark::array::{cell_tuner, ArrayProtocol};
use spintune::protocol::Request;
use spintune::sim::array::{parameter_name, split_gate, ArrayConfig, ArrayDevice};
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::{ArrayAction, ArrayRun, ArrayRunSettings};

const TUNING_GATES: [&str; 4] = ["N", "SA", "SB", "T"];

/// The cell and the local names of the tuning gates a request moves
/// (`None`: not a move of tuning gates).
fn tuning_move(request: &Request) -> Option<(u32, BTreeSet<String>)> {
    let Request::SetVoltages { voltages_mv } = request else {
        return None;
    };
    let mut cell = None;
    let mut gates = BTreeSet::new();
    for g in voltages_mv.keys() {
        let (c, local) = split_gate(g)?;
        cell = Some(c);
        if TUNING_GATES.contains(&local) {
            gates.insert(local.to_string());
        }
    }
    (!gates.is_empty()).then_some((cell?, gates))
}

#[test]
fn every_cell_moves_its_tuning_gates_in_the_same_batch() {
    let protocol = ArrayProtocol::default();
    let (mut run, mut device) =
        support::array::three_cells((0..3).map(|c| cell_tuner(c, &protocol)).collect());
    // cell 1's line A starts 2 mV off: its line level needs more requests
    // than its neighbours' before the finite differences begin
    assert!(device.rearrange_charges(1, [2.0, 0.0]));
    let (mut batches, mut moves, mut scans_per_cell) = (0, 0, [0u32; 3]);
    // the initial measurements end before the first iteration
    while let ArrayAction::Execute(batch) = run.poll().unwrap() {
        batches += 1;
        let moved: Vec<_> = batch.iter().filter_map(tuning_move).collect();
        if !moved.is_empty() {
            moves += 1;
            // nothing else in the batch, one move per cell, the same gates
            assert_eq!(moved.len(), batch.len(), "batch {batches}: {batch:?}");
            let cells: BTreeSet<u32> = moved.iter().map(|(c, _)| *c).collect();
            assert_eq!(cells.len(), 3, "batch {batches}: {batch:?}");
            assert!(
                moved.iter().all(|(_, g)| *g == moved[0].1),
                "batch {batches}"
            );
        }
        for r in &batch {
            if let Request::Measure { scan } = r {
                scans_per_cell[scan.cell.unwrap() as usize] += 1;
            }
        }
        let before = device.lab_seconds();
        let answers = device.execute_batch(&batch);
        run.feed(answers, device.lab_seconds() - before).unwrap();
    }
    // the finite differences of four tuning gates happened
    assert!(moves >= 4, "{moves} moves");
    // and some cell scanned more than another (the case the barrier is for)
    assert!(
        scans_per_cell.iter().max() > scans_per_cell.iter().min(),
        "{scans_per_cell:?}"
    );
}

/// A `cells`-cell chain (noise seed 11) run with `settings` through its
/// initial measurements, each batch shown to `on_batch` (with the world)
/// before the world answers it: the run (its joint tuner just built) and
/// the world.
fn through_initial_measurements(
    cells: u32,
    settings: ArrayRunSettings,
    mut on_batch: impl FnMut(&[Request], &ArrayDevice),
) -> (ArrayRun, ArrayDevice) {
    let protocol = ArrayProtocol::default();
    let mut device = spintune::benchmark::array::world(
        &DeviceConfig::default(),
        ArrayConfig::chain(cells, 5, 11),
        |_| true,
    )
    .unwrap();
    let tuners = (0..cells).map(|c| cell_tuner(c, &protocol)).collect();
    let mut run = ArrayRun::new(tuners, &device.gates(), settings, [0.3, 0.05], false).unwrap();
    while run.tuner().is_none() {
        let ArrayAction::Execute(batch) = run.poll().unwrap() else {
            panic!("the initial measurements ended without a joint tuner");
        };
        on_batch(&batch, &device);
        let before = device.lab_seconds();
        let answers = device.execute_batch(&batch);
        run.feed(answers, device.lab_seconds() - before).unwrap();
    }
    (run, device)
}

/// Each cell's initial own-gate `t_sr` row (log space) projected on the
/// truth's at the voltages where the initial measurements ended:
/// `⟨learned, true⟩ / |true|²` (1: its own gradient exactly), cells 1..=3
/// of a 5-cell chain (each with two nearest neighbours), unpooled.
fn interior_row_ratios(staggered: bool) -> Vec<f64> {
    let mut settings = ArrayProtocol::default().run_settings();
    settings.pool_initial_gradients = false;
    settings.staggered_differences = staggered;
    let (run, device) = through_initial_measurements(5, settings, |_, _| {});
    let tuner = run.tuner().unwrap();
    let gates: Vec<&str> = tuner.gates().iter().map(String::as_str).collect();
    let learned = tuner.jacobian();
    (1..=3u32)
        .map(|c| {
            let name = parameter_name(c, "t_sr");
            let truth = device.true_jacobian(&gates, &[name.as_str()]).unwrap();
            let value = device.truth(c).unwrap().get("t_sr").unwrap();
            let own: Vec<usize> = (0..gates.len())
                .filter(|&g| split_gate(gates[g]).is_some_and(|(k, _)| k == c))
                .collect();
            let (mut dot, mut norm) = (0.0, 0.0);
            for &g in &own {
                let t = truth[(0, g)] / value;
                dot += learned[(2 * c as usize, g)] * t;
                norm += t * t;
            }
            dot / norm
        })
        .collect()
}

/// Staggered repetitions (`ArrayRunSettings::staggered_differences`) take
/// the nearest neighbours' crosstalk out of the initial rows. In lockstep
/// a cell two cells from either end measures `1 + 2·0.3 + 2·0.05 = 1.7`
/// times its own gradient at this crosstalk (`lockstep_factor`; the
/// world's copies are not exactly the cell's own gradient, so only
/// roughly), one cell from an end 1.65; staggered over the two
/// repetitions (`staggered_mirror`), the nearest neighbours' copies
/// cancel, leaving `1 + 2·0.05 = 1.1` and `1.05`.
#[test]
fn staggered_repetitions_measure_a_cell_s_own_gradient() {
    let lockstep = interior_row_ratios(false);
    let staggered = interior_row_ratios(true);
    eprintln!(
        "interior t_sr rows / own gradient: lockstep {lockstep:.2?}, staggered {staggered:.2?}"
    );
    let mean = |x: &[f64]| x.iter().sum::<f64>() / x.len() as f64;
    assert!(mean(&lockstep) > 1.4, "lockstep {lockstep:?}");
    assert!(
        (mean(&staggered) - 1.07).abs() < 0.2,
        "staggered {staggered:?}"
    );
}

/// The longest offset of any tuning gate from where it started, mV, over
/// the initial measurements of a 3-cell chain with the given
/// `finite_difference_step_mv` (the solver has not moved yet, so every
/// tuning-gate offset is a finite difference's).
fn longest_initial_offset_mv(step_mv: Option<f64>) -> f64 {
    let mut settings = ArrayProtocol::default().run_settings();
    settings.finite_difference_step_mv = step_mv;
    let mut longest: f64 = 0.0;
    through_initial_measurements(3, settings, |batch, device| {
        let start = |gate: &str| {
            device
                .gates()
                .into_iter()
                .find(|g| g.name == gate)
                .map(|g| g.initial_mv)
                .unwrap()
        };
        for r in batch {
            if let Request::SetVoltages { voltages_mv } = r {
                for (g, v) in voltages_mv {
                    if split_gate(g).is_some_and(|(_, l)| TUNING_GATES.contains(&l)) {
                        longest = longest.max((v - start(g)).abs());
                    }
                }
            }
        }
    });
    longest
}

/// The initial offset is the run's `finite_difference_step_mv` (3 mV by
/// default), never longer than the cell tuner's own (6 mV, what `None`
/// keeps): a longer setting is cut to it rather than exceed what the
/// description derived from the gates' step limits.
#[test]
fn initial_offsets_follow_the_setting_capped_at_the_cell_tuner_s() {
    let protocol = ArrayProtocol::default();
    let own = match &cell_tuner(0, &protocol).top().initial_gradient {
        spintune::tuner::InitialGradient::FiniteDifference { step_mv, .. } => *step_mv,
        other => panic!("the cell tuner starts from {other:?}"),
    };
    assert_eq!(own, 6.0);
    assert_eq!(protocol.run_settings().finite_difference_step_mv, Some(3.0));
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
    let default = longest_initial_offset_mv(Some(3.0));
    assert!(close(default, 3.0), "default {default} mV");
    let shorter = longest_initial_offset_mv(Some(2.0));
    assert!(close(shorter, 2.0), "2 mV setting: {shorter} mV");
    let none = longest_initial_offset_mv(None);
    assert!(close(none, own), "None: {none} mV");
    let longer = longest_initial_offset_mv(Some(8.0));
    assert!(close(longer, own), "8 mV setting: {longer} mV");
}
