//! Lines that leave the line scan's window (a charge rearrangement near the
//! dots) are searched for and found again (`NewtonConfig::search`, the
//! recommended config's line level); without the search the run stays
//! stranded. A search that cannot find them gives up, moves the plungers
//! back and does not start again until a scan works.
//!
//! World side: the simulator's charge rearrangement shifts both lines and
//! nothing else; the tuner only sees its scans fail.

use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::{EventKind, IterationRecord};
use spintune::tuner::LevelKind;

/// The recommended config on `seed`, with the line search on or off.
fn run(seed: u64, search: bool) -> SimulationRun {
    let mut cfg = SimulationConfig::recommended();
    cfg.seed = seed;
    let idx = cfg.tuner.level_index("chemical_potential").unwrap();
    let LevelKind::Newton(n) = &mut cfg.tuner.levels[idx].kind else {
        unreachable!("the recommended config's line level")
    };
    assert!(n.search.is_some(), "the recommended config searches");
    if !search {
        n.search = None;
    }
    SimulationRun::new(cfg).unwrap()
}

fn tune(run: &mut SimulationRun, max: u32) -> Vec<IterationRecord> {
    let mut out = Vec::new();
    for _ in 0..max {
        let rec = run.next_iteration().unwrap().unwrap();
        let tuned = rec.tuned;
        out.push(rec);
        if tuned {
            break;
        }
    }
    out
}

fn events(records: &[IterationRecord]) -> Vec<EventKind> {
    records
        .iter()
        .flat_map(|r| r.events.iter().map(|e| e.kind.clone()))
        .collect()
}

fn plungers(run: &SimulationRun) -> [f64; 2] {
    let v = run.device().voltages_mv();
    [v["PA"], v["PB"]]
}

#[test]
fn lines_seven_mv_off_are_found_again_and_the_qubit_is_retuned() {
    for seed in [1, 2, 3] {
        let mut run = run(seed, true);
        let first = tune(&mut run, 60);
        assert!(first.last().unwrap().tuned, "seed {seed}: tunes first");
        // line A 7 mV up: outside the ±4 mV scan
        run.device_mut().rearrange_charges([7.0, 0.0]);
        // until back in band with the lines found again (the qubit's scans
        // may pass before the line level's next scan confirms the lines)
        let mut after = Vec::new();
        for _ in 0..60 {
            let rec = run.next_iteration().unwrap().unwrap();
            let found = rec
                .events
                .iter()
                .any(|e| matches!(e.kind, EventKind::SearchEnded { found: true, .. }));
            let tuned = rec.tuned;
            after.push(rec);
            if tuned && found {
                break;
            }
            if found {
                // found: tune on until in band
                after.extend(tune(&mut run, 30));
                break;
            }
        }
        let ev = events(&after);
        let probes: Vec<&EventKind> = ev
            .iter()
            .filter(|e| matches!(e, EventKind::SearchProbe { .. }))
            .collect();
        assert!(!probes.is_empty(), "seed {seed}: searched");
        // only line A is searched for (line B's trace still gives its value);
        // it was last seen near its target 0 mV, so the first probe goes ±4 mV
        let EventKind::SearchProbe {
            probe,
            parameters,
            offsets,
        } = probes[0]
        else {
            unreachable!()
        };
        assert_eq!(
            (*probe, parameters.as_slice()),
            (1, ["mu_a_mv".to_string()].as_slice())
        );
        assert_eq!(offsets[0].abs(), 4.0);
        assert!(
            ev.iter()
                .any(|e| matches!(e, EventKind::SearchEnded { found: true, .. })),
            "seed {seed}: found again: {ev:?}"
        );
        let last = after.last().unwrap();
        assert!(last.tuned, "seed {seed}: the qubit is back in band");
        // the lines are back near their targets: line A measured within its tolerance
        let mu_a = last
            .parameters
            .iter()
            .find(|p| p.name == "mu_a_mv")
            .and_then(|p| p.value);
        if let Some(mu_a) = mu_a {
            assert!(mu_a.abs() < 1.0, "seed {seed}: mu_a {mu_a} mV");
        }
    }
}

#[test]
fn without_the_search_lines_seven_mv_off_strand_the_run() {
    let mut run = run(1, false);
    assert!(tune(&mut run, 60).last().unwrap().tuned);
    run.device_mut().rearrange_charges([7.0, 0.0]);
    let after = tune(&mut run, 40);
    assert!(!after.iter().any(|r| r.tuned), "stranded without a search");
    assert!(!events(&after)
        .iter()
        .any(|e| matches!(e, EventKind::SearchProbe { .. })));
}

#[test]
fn a_search_that_cannot_find_the_lines_gives_up_moves_back_and_waits() {
    let mut run = run(1, true);
    assert!(tune(&mut run, 60).last().unwrap().tuned);
    let before = plungers(&run);
    // 40 mV: beyond the 4 probes' reach (±4, ±8 mV, windows of ±4 mV)
    run.device_mut().rearrange_charges([40.0, 40.0]);
    let mut records = Vec::new();
    let mut gave_up_at = None;
    for i in 0..80 {
        let rec = run.next_iteration().unwrap().unwrap();
        let given_up = rec
            .events
            .iter()
            .any(|e| matches!(e.kind, EventKind::SearchEnded { found: false, .. }));
        records.push(rec);
        if given_up {
            gave_up_at = Some(i);
            break;
        }
    }
    let at = gave_up_at.expect("the search gives up");
    let ev = events(&records);
    let probes = ev
        .iter()
        .filter(|e| matches!(e, EventKind::SearchProbe { .. }))
        .count();
    assert_eq!(probes, 4, "{ev:?}");
    assert!(
        ev.iter().any(|e| matches!(
            e,
            EventKind::SearchEnded {
                probes: 4,
                found: false
            }
        )),
        "at {at}"
    );
    // back where the search started: the plungers within the qubit level's
    // compensation of its own moves meanwhile (a few mV at most)
    let now = plungers(&run);
    for (a, b) in now.iter().zip(before) {
        assert!((a - b).abs() < 3.0, "plungers {now:?} vs {before:?}");
    }
    // no new search while the lines stay lost
    let later: Vec<IterationRecord> = (0..10)
        .map(|_| run.next_iteration().unwrap().unwrap())
        .collect();
    assert!(!events(&later)
        .iter()
        .any(|e| matches!(e, EventKind::SearchProbe { .. })));
}

/// A line outside the window from the very first scan has no measured
/// gradient (its finite differences failed): the search assumes it moves
/// with its own plunger like the other line does with its own, finds it,
/// then measures the level's gradient again, and the run tunes with line A
/// centred.
#[test]
fn a_line_lost_before_the_first_scan_is_found_and_its_gradient_measured() {
    for seed in [1, 3] {
        let mut run = run(seed, true);
        run.device_mut().rearrange_charges([4.5, 0.0]);
        let records = tune(&mut run, 60);
        let ev = events(&records);
        assert!(
            ev.iter().any(|e| matches!(e, EventKind::FiniteDifferenceFailed { parameter } if parameter == "mu_a_mv")),
            "seed {seed}: line A's gradient could not be measured at first"
        );
        assert!(
            ev.iter()
                .any(|e| matches!(e, EventKind::SearchEnded { found: true, .. })),
            "seed {seed}: {ev:?}"
        );
        assert!(records.last().unwrap().tuned, "seed {seed}: tuned");
        // world side: line A is back at its target (the re-measured gradient
        // lets the level centre it), where the scans see it
        let (t, d) = (run.device().truth(), run.device().drift());
        let line_a = t.mu_a_mv + d.mu_a_mv + d.jump_mu_mv[0];
        assert!(line_a.abs() < 0.5, "seed {seed}: line A at {line_a} mV");
    }
}
