//! The sensing-dot level of the recommended config parks on a predicted
//! flank instead of sweeping when its learned model is confident
//! (`SensingDotConfig::prediction`). Checked against the simulator's truth
//! (world side): where it parks without a sweep the sensor reads out about
//! as well as where a sweep put it; skipping happens, and saves sweeps
//! against the same run that always sweeps.

mod support;

use spintune::driver::SimulationConfig;
use spintune::protocol::{Request, Response, ScanKind, ScanOutcome};
use spintune::tuner::LevelKind;
use support::{mean, Lab, Next};

#[derive(Default)]
struct Outcome {
    /// Predicted flanks checked by the next sweep: count, NIS sum, beyond 2σ.
    checked: (u64, f64, u64),
    /// The true readout contrast (0..1) right after each park without a sweep.
    skipped: Vec<f64>,
    /// The same right after each park that followed a sweep.
    swept: Vec<f64>,
    sweeps: u64,
}

/// The recommended config on `seed`, with the flank prediction on or off.
fn lab(seed: u64, predict: bool, iterations: u64) -> Lab {
    Lab::recommended(seed, iterations, |cfg: &mut SimulationConfig| {
        let idx = cfg.tuner.level_index("sensing_dot").unwrap();
        let LevelKind::SensingDot(sd) = &mut cfg.tuner.levels[idx].kind else {
            unreachable!("the recommended config's sensing-dot level")
        };
        assert!(sd.prediction.is_some(), "the recommended config predicts");
        assert_eq!(sd.gate, "SD1");
        if !predict {
            sd.prediction = None;
        }
    })
}

/// Drive the recommended config on `seed` for `iterations` top-level
/// iterations. A park is a set of the sensing gate alone; it follows a
/// sweep (the level found the flank) or not (the level predicted it).
fn drive(seed: u64, predict: bool, iterations: u64) -> Outcome {
    let mut lab = lab(seed, predict, iterations);
    let mut out = Outcome::default();
    let mut last_was_sweep = false;
    let mut done = 0;
    loop {
        match lab.next() {
            Next::Request(request) => {
                let park = matches!(&request, Request::SetVoltages { voltages_mv }
                    if voltages_mv.len() == 1 && voltages_mv.contains_key("SD1"));
                let sweep = matches!(&request, Request::Measure { scan }
                    if scan.kind == ScanKind::SensingDot);
                let response = lab.execute(&request);
                if park {
                    let contrast = lab.device.truth().sd_contrast;
                    if last_was_sweep {
                        out.swept.push(contrast);
                    } else {
                        out.skipped.push(contrast);
                    }
                }
                out.sweeps += u64::from(sweep);
                // the session's read-backs come between a sweep and its park
                if !matches!(request, Request::ReadVoltages { .. }) {
                    last_was_sweep = sweep;
                }
                lab.feed(response);
            }
            Next::Record(_) => {
                done += 1;
                if done >= iterations {
                    let tuner = lab.session.tuner();
                    let level = tuner.config().level_index("sensing_dot").unwrap();
                    if let Some(c) = tuner.flank_consistency(level) {
                        out.checked = (c.count, c.nis_sum, c.beyond_2sigma);
                    }
                    return out;
                }
            }
            Next::Done => return out,
        }
    }
}

#[test]
fn parks_without_a_sweep_read_out_about_as_well_as_after_one() {
    let (mut skipped, mut swept) = (Vec::new(), Vec::new());
    for seed in 1..=6 {
        let o = drive(seed, true, 25);
        skipped.extend(o.skipped);
        swept.extend(o.swept);
    }
    assert!(skipped.len() >= 20, "skips happen: {}", skipped.len());
    let (m_skip, m_sweep) = (mean(&skipped), mean(&swept));
    eprintln!(
        "{} skips, contrast mean {m_skip:.3}; {} sweeps, {m_sweep:.3}",
        skipped.len(),
        swept.len()
    );
    // the prediction's std is at most 0.3 mV on a 1 mV wide peak: the park
    // is on the flank, a little less steep on average than a sweep's
    assert!(m_skip >= 0.8 * m_sweep, "{m_skip} vs {m_sweep}");
    let poor = skipped.iter().filter(|&&c| c < 0.3).count();
    assert!(
        poor * 10 <= skipped.len(),
        "{poor} of {} skipped parks read out below 0.3 contrast",
        skipped.len()
    );
}

/// Every park without a sweep, against the sweep that followed it: the
/// predicted flank's σ is honest for all but the rare charge jump (the
/// simulator's sensor jumps by ~1 mV about once a lab hour, which no model
/// of the gates predicts: one such park makes the NIS mean meaningless, so
/// the check counts innovations beyond 2σ, 4.6 % for a consistent filter).
#[test]
fn predicted_flanks_are_checked_by_the_next_sweep() {
    let (mut n, mut nis, mut beyond) = (0, 0.0, 0);
    for seed in 1..=10 {
        let o = drive(seed, true, 25);
        n += o.checked.0;
        nis += o.checked.1;
        beyond += o.checked.2;
        assert_eq!(drive(seed, false, 25).checked, (0, 0.0, 0));
    }
    let mean = nis / n as f64;
    eprintln!(
        "{n} predicted flanks checked by the next sweep: NIS mean {mean:.2}, {beyond} beyond 2σ"
    );
    assert!(n >= 20, "checked: {n}");
    assert!(
        beyond * 5 <= n,
        "{beyond} of {n} beyond 2σ (NIS mean {mean})"
    );
}

#[test]
fn predicting_the_flank_saves_sweeps() {
    let (mut with, mut without) = (0, 0);
    for seed in 1..=3 {
        with += drive(seed, true, 25).sweeps;
        without += drive(seed, false, 25).sweeps;
    }
    assert!(
        with * 2 <= without,
        "sweeps with prediction {with}, without {without}"
    );
}

/// After a scan fails to evaluate, the sensing dot's next call sweeps (the
/// sensor may be what failed): on several seeds, the w scan after the first
/// skipped sweep fails (`ScanOutcome::Failed`), and the next request of
/// the sensing-dot level (a sweep or a park without one) is a sweep.
#[test]
fn a_failed_scan_makes_the_next_sensing_dot_call_sweep() {
    for seed in 1..=4 {
        let mut lab = lab(seed, true, 25);
        // 0: until a park without a sweep; 1: fail the next w scan; 2: watch
        let (mut phase, mut last_was_sweep) = (0, false);
        let verdict = loop {
            match lab.next() {
                Next::Request(request) => {
                    let park = matches!(&request, Request::SetVoltages { voltages_mv }
                        if voltages_mv.len() == 1 && voltages_mv.contains_key("SD1"));
                    let kind = match &request {
                        Request::Measure { scan } => Some(scan.kind),
                        _ => None,
                    };
                    let sweep = kind == Some(ScanKind::SensingDot);
                    if phase == 2 && (sweep || (park && !last_was_sweep)) {
                        break sweep;
                    }
                    let mut response = lab.execute(&request);
                    if phase == 0 && park && !last_was_sweep {
                        phase = 1;
                    } else if phase == 1 && kind == Some(ScanKind::TransitionWidth) {
                        response = Response::Scanned {
                            outcome: ScanOutcome::Failed {
                                reason: "scripted: no signal".into(),
                            },
                            lab_seconds: 28.0,
                        };
                        phase = 2;
                    }
                    if !matches!(request, Request::ReadVoltages { .. }) {
                        last_was_sweep = sweep;
                    }
                    lab.feed(response);
                }
                Next::Done => panic!("seed {seed}: the run ended before the check"),
                Next::Record(_) => {}
            }
        };
        assert!(
            verdict,
            "seed {seed}: parked without a sweep after a failed scan"
        );
    }
}
