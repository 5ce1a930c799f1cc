//! A lower level whose scan fails does not retreat toward where its own
//! gates were before the parent moved: those plunger voltages went with the
//! parent's old gates (the virtual-gate compensation moved them since), and
//! moving back toward them takes the transition lines away from where the
//! compensation put them. The level re-tunes its own lower levels (the
//! sensing dot) and scans again instead.

mod support;

use spintune::protocol::{Request, Response, ScanKind, ScanOutcome};
use support::{Lab, Next};

/// On `seed`, fail the line scan of the line level's `nth` call after the
/// first top-level iteration; return the requests between that failure and
/// the next line scan.
fn after_a_failed_line_scan(seed: u64, nth: usize) -> Vec<Request> {
    let mut lab = Lab::recommended(seed, 80, |_| {});
    let (mut iterations, mut line_scans, mut failed) = (0, 0, false);
    let mut between = Vec::new();
    loop {
        match lab.next() {
            Next::Request(request) => {
                let line = matches!(&request, Request::Measure { scan }
                    if scan.kind == ScanKind::ChemicalPotential);
                if failed && line {
                    return between;
                }
                if failed {
                    between.push(request.clone());
                }
                let mut response = lab.execute(&request);
                if line && iterations >= 1 {
                    line_scans += 1;
                    if line_scans == nth {
                        response = Response::Scanned {
                            outcome: ScanOutcome::Failed {
                                reason: "scripted: no step in the scan".into(),
                            },
                            lab_seconds: 38.0,
                        };
                        failed = true;
                    }
                }
                lab.feed(response);
            }
            Next::Record(_) => {
                iterations += 1;
                // a new set point every 4 iterations keeps the levels moving
                if iterations % 4 == 0 {
                    let (t_sr, w) = [(30.0, 220.0), (20.0, 270.0)][iterations / 4 % 2];
                    lab.set_targets(t_sr, w);
                }
            }
            Next::Done => panic!(
                "seed {seed}: the run ended before the check ({iterations} iterations, {line_scans} line scans)"
            ),
        }
    }
}

#[test]
fn a_failed_line_scan_rescans_without_moving_the_plungers_back() {
    for seed in 1..=3 {
        for nth in [1, 2] {
            let between = after_a_failed_line_scan(seed, nth);
            let plunger_moves: Vec<_> = between
                .iter()
                .filter(|r| {
                    matches!(r, Request::SetVoltages { voltages_mv }
                    if voltages_mv.contains_key("PA") || voltages_mv.contains_key("PB"))
                })
                .collect();
            assert!(
                plunger_moves.is_empty(),
                "seed {seed}, failed call {nth}: plungers moved before the next line scan: {plunger_moves:?}"
            );
            // the sensing dot is re-tuned (swept: the failure forces it) first
            assert!(
                between.iter().any(|r| matches!(r, Request::Measure { scan }
                    if scan.kind == ScanKind::SensingDot)),
                "seed {seed}, failed call {nth}: no sensing-dot sweep before the rescan"
            );
        }
    }
}
