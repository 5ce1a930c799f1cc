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
use spintune::sim::array::split_gate;
use spintune::tuner::array_run::ArrayAction;

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
