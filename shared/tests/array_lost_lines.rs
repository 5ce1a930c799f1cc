//! A cell's transition lines that leave the line scan's ±4 mV window (a
//! charge rearrangement near its dots) are searched for by the joint array
//! loop the way a single cell's line level searches for them
//! (`NewtonConfig::search`, on in every array cell's tuner): probes that
//! shift the lost line by ±4, ±8 mV through the cell's line Jacobian,
//! scanned in the same iteration. Without the search the array stays
//! stranded on the same world.
//!
//! World side: the simulator's charge rearrangement shifts cell 1's lines
//! and nothing else; the loop only sees its scans fail.

mod support;

use spintune::benchmark::array::{cell_tuner, ArrayProtocol};
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::{EventKind, IterationRecord};
use spintune::sim::array::ArrayDevice;
use spintune::tuner::array_run::ArrayRun;
use spintune::tuner::LevelKind;
use support::array::drive;

/// Three default-population cells, every cell's line search on or off.
fn array(search: bool) -> (ArrayRun, ArrayDevice) {
    let protocol = ArrayProtocol::default();
    let cells = (0..3)
        .map(|c| {
            let mut t = cell_tuner(c, &protocol);
            let idx = t.level_index("chemical_potential").unwrap();
            let LevelKind::Newton(n) = &mut t.levels[idx].kind else {
                unreachable!("an array cell's line level")
            };
            assert!(n.search.is_some(), "array cells search by default");
            if !search {
                n.search = None;
            }
            t
        })
        .collect();
    support::array::three_cells(cells)
}

fn line_events(records: &[IterationRecord]) -> Vec<EventKind> {
    records
        .iter()
        .flat_map(|r| &r.events)
        .filter(|e| e.level == "c1.lines")
        .map(|e| e.kind.clone())
        .collect()
}

/// Iterations and failed evaluations from the jump to back in band (`None`:
/// not within 30 iterations), and cell 1's line events.
fn after_a_jump(search: bool) -> (Option<(usize, u64)>, Vec<EventKind>, ArrayDevice) {
    let (mut run, mut device) = array(search);
    let cold = drive(&mut run, &mut device, 60);
    assert!(cold.last().unwrap().tuned, "search {search}: a cold start");
    let failed_before = cold.last().unwrap().failed_evaluations;
    // line A of cell 1 jumps 7 mV: outside the ±4 mV scan
    assert!(device.rearrange_charges(1, [7.0, 0.0]));
    // a new set point for cell 1 revives the idle run
    run.set_targets(1, PAPER_SET_POINTS[1]).unwrap();
    let after = drive(&mut run, &mut device, 30);
    let last = after.last().unwrap();
    let cost = last
        .tuned
        .then(|| (after.len(), last.failed_evaluations - failed_before));
    eprintln!("search {search}: {cost:?} (iterations, failed evaluations)");
    (cost, line_events(&after), device)
}

#[test]
fn a_cells_lines_lost_in_an_array_are_found_again_sooner_than_without_the_search() {
    let (with, events, device) = after_a_jump(true);
    let probes: Vec<&EventKind> = events
        .iter()
        .filter(|e| matches!(e, EventKind::SearchProbe { .. }))
        .collect();
    assert!(!probes.is_empty(), "{events:?}");
    // each probe shifts line A, the lost one, by ±4, ±8 mV
    for (k, p) in probes.iter().enumerate() {
        let EventKind::SearchProbe {
            parameters,
            offsets,
            ..
        } = p
        else {
            unreachable!()
        };
        assert_eq!(parameters, &["c1.mu_a_mv".to_string()]);
        assert_eq!(offsets[0].abs(), 4.0 * (k / 2 + 1) as f64, "{events:?}");
    }
    assert!(
        events
            .iter()
            .any(|e| matches!(e, EventKind::SearchEnded { found: true, .. })),
        "{events:?}"
    );
    let (iterations, failed) = with.expect("back in band within 30 iterations");
    // independent of the loop's own judgement: cell 1 truly near its new set point
    let t = device.truth(1).unwrap();
    let (t_sr, w) = PAPER_SET_POINTS[1];
    assert!((t.t_sr_ns / t_sr - 1.0).abs() < 0.2, "{t:?}");
    assert!((t.w_uv / w - 1.0).abs() < 0.2, "{t:?}");

    let (without, events, _) = after_a_jump(false);
    assert!(events.is_empty(), "{events:?}");
    if let Some((i, f)) = without {
        assert!(
            iterations < i && failed < f,
            "with {with:?}, without {without:?}"
        );
    }
}
