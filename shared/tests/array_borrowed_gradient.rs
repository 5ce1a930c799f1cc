//! A cell whose initial finite differences of `w` fail (its transition-
//! width scans at the gate offsets fail) starts the joint tuner with the
//! mean `w` row of the cells that measured theirs
//! (`ArrayRunSettings::borrow_failed_gradients`), and from a zero row
//! without it. With `ArrayRunSettings::pool_initial_gradients` every
//! cell's rows start pooled with the other cells' (`pool_gradients`).

mod support;

use spintune::benchmark::array::{world, ArrayProtocol, Lab};
use spintune::protocol::{Request, Response, ScanKind, ScanOutcome};
use spintune::sim::array::{ArrayConfig, ArrayDevice};
use spintune::sim::DeviceConfig;
use spintune::tuner::array::{lockstep_factor, CellKnowledge};
use spintune::tuner::array_run::{ArrayAction, ArrayRun, ArrayRunSettings};
use spintune::tuner::pooled_gradient::pool_gradients;
use support::array::joint_in_lab;

/// The lab's cross-cell calibration `λ̂` (nearest, next).
const LAMBDA: [f64; 2] = [0.3, 0.05];

/// Answer `requests` from `lab`, except that cell 1's transition-width
/// scans after its first (the base point's) fail; `seen` counts them.
fn answer(lab: &mut Lab, requests: &[Request], seen: &mut u32) -> Vec<Response> {
    let mut answers = lab.batch(requests);
    for (r, a) in requests.iter().zip(answers.iter_mut()) {
        fail_offsets(r, a, seen);
    }
    answers
}

fn fail_offsets(request: &Request, answer: &mut Response, seen: &mut u32) {
    match (request, answer) {
        (Request::Batch { requests }, Response::Batch { responses, .. }) => {
            for (r, a) in requests.iter().zip(responses.iter_mut()) {
                fail_offsets(r, a, seen);
            }
        }
        (Request::Measure { scan }, Response::Scanned { outcome, .. })
            if scan.kind == ScanKind::TransitionWidth
                && ArrayDevice::cell_of(request) == Some(1) =>
        {
            *seen += 1;
            if *seen > 1 {
                *outcome = ScanOutcome::Failed {
                    reason: "no transition in the window".into(),
                };
            }
        }
        _ => {}
    }
}

/// The `w` rows (parameter 1) of cells 0, 1 and 2 once the joint tuner
/// starts, with `borrow` as the setting (and no pooling).
fn w_rows_at_the_start(borrow: bool) -> Vec<Vec<f64>> {
    knowledge_at_the_start(3, borrow, false)
        .iter()
        .map(|c| c.gradient[1].clone())
        .collect()
}

/// Every cell's knowledge once the joint tuner starts, in a world of
/// `cells` cells, with the two settings.
fn knowledge_at_the_start(cells: u32, borrow: bool, pool: bool) -> Vec<CellKnowledge> {
    knowledge_with(cells, |s| {
        s.borrow_failed_gradients = borrow;
        s.pool_initial_gradients = pool;
    })
}

/// Every cell's knowledge once the joint tuner starts, in a world of
/// `cells` cells, with the settings `edit` makes.
fn knowledge_with(cells: u32, edit: impl Fn(&mut ArrayRunSettings)) -> Vec<CellKnowledge> {
    let mut protocol = ArrayProtocol::default();
    edit(&mut protocol.tuning);
    protocol.cross_calibration = Some(LAMBDA);
    let array = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(cells, 5, 11),
        |_| true,
    )
    .unwrap();
    let (mut run, mut lab): (ArrayRun, Lab) = joint_in_lab(array, &protocol, 1);
    let mut seen = 0;
    for _ in 0..500 {
        if let Some(t) = run.tuner() {
            assert!(seen > 1, "cell 1's offsets were scanned");
            return t.cells().to_vec();
        }
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = lab.device.lab_seconds();
                let answers = answer(&mut lab, &batch, &mut seen);
                run.feed(answers, lab.device.lab_seconds() - before)
                    .unwrap();
            }
            ArrayAction::Iteration(_) => {}
            ArrayAction::Idle => panic!("idle before the joint tuner started"),
        }
    }
    panic!("the joint tuner never started");
}

#[test]
fn a_cell_whose_w_finite_differences_failed_borrows_the_mean_w_row() {
    let rows = w_rows_at_the_start(true);
    let measured = |c: usize| rows[c].iter().any(|&g| g != 0.0);
    assert!(measured(0) && measured(2), "{rows:?}");
    for j in 0..rows[1].len() {
        let mean = 0.5 * (rows[0][j] + rows[2][j]);
        assert!((rows[1][j] - mean).abs() < 1e-12, "gate {j}: {rows:?}");
    }
    assert!(measured(1));
    let without = w_rows_at_the_start(false);
    assert!(without[1].iter().all(|&g| g == 0.0), "{without:?}");
    assert_eq!(without[0], rows[0]);
    assert_eq!(without[2], rows[2]);
}

#[test]
fn pooled_rows_are_the_measured_rows_pooled_and_the_failed_row_takes_the_others() {
    let measured = knowledge_at_the_start(4, false, false);
    assert!(measured[1].gradient[1].iter().all(|&g| g == 0.0));
    let pooled = knowledge_at_the_start(4, false, true);
    // in lockstep units: each row pooled divided by its cell's factor
    let mut in_units = measured.clone();
    let lockstep: Vec<f64> = (0..4)
        .map(|k| {
            lockstep_factor(
                &spintune::description::layout::CellGrid::chain(4),
                k,
                LAMBDA,
            )
        })
        .collect();
    pool_gradients(&mut in_units, &lockstep);
    assert_ne!(in_units, pooled);
    assert_eq!(
        knowledge_with(4, |s| s.pool_in_lockstep_units = true),
        in_units
    );
    let mut expected = measured.clone();
    let changed = pool_gradients(&mut expected, &[]);
    assert_eq!(pooled, expected);
    // every cell's rows, both parameters, were pooled: the failed one too
    assert_eq!(changed.len(), 8, "{changed:?}");
    assert!(pooled[1].gradient[1].iter().any(|&g| g != 0.0));
    for (p, m) in pooled.iter().zip(&measured) {
        for (a, b) in p.covariance.iter().zip(&m.covariance) {
            for j in 0..a.len() {
                // a prior only adds information: no gate's variance grows
                assert!(a[j][j] <= b[j][j], "{a:?} against {b:?}");
            }
        }
    }
}
