//! A cell that has just entered its band near the edge is scanned once
//! more before the joint loop stops (`ArrayRunSettings::confirm_entry_sigma`),
//! checked from outside: the 3-cell world through the paper's set points,
//! every record's rechecks derived again from its own parameter reports and
//! the record before it, and every recheck's batch read off the requests.
//! Then single-cell changes with the bystander rule
//! (`ArrayRunSettings::confirm_bystander_sigma`): the cells whose targets
//! did not change are rechecked near their edge with the wider margin,
//! whether or not they were in band before.

mod support;

use spintune::benchmark::array::ArrayProtocol;
use spintune::benchmark::PAPER_SET_POINTS;
use spintune::protocol::{EventKind, IterationRecord, ParameterReport, Request, ScanKind};
use spintune::sim::array::split_gate;
use spintune::sim::DeviceConfig;
use support::array::{chain_world, joint_in_lab, through_changes, TargetChange};

/// One iteration: its record and the batches it sent.
struct Iteration {
    record: IterationRecord,
    batches: Vec<Vec<Request>>,
}

/// The confirmation settings under test.
#[derive(Clone, Copy)]
struct Rules {
    /// `confirm_entry_sigma`.
    sigma: f64,
    /// `confirm_in_band_cells`.
    in_band_cells: bool,
    /// `confirm_bystander_sigma`.
    bystander_sigma: f64,
}

const DEFAULT_RULES: Rules = Rules {
    sigma: 1.0,
    in_band_cells: false,
    bystander_sigma: 0.0,
};

/// The paper's set points, every cell at once.
fn paper_phases() -> Vec<TargetChange> {
    PAPER_SET_POINTS.iter().map(|&t| (None, t)).collect()
}

/// A cold start to the paper's first set point, then each of the three
/// cells alone to (70 ns, 180 µV) and back: two bystanders every change.
fn single_cell_phases() -> Vec<TargetChange> {
    let mut phases = vec![(None, PAPER_SET_POINTS[0])];
    for c in [1, 0, 2] {
        phases.push((Some(c), (70.0, 180.0)));
        phases.push((Some(c), PAPER_SET_POINTS[0]));
    }
    phases
}

fn run(seed: u64, rules: Rules, phases: &[TargetChange]) -> Vec<Iteration> {
    let mut protocol = ArrayProtocol::default();
    protocol.tuning.confirm_entry_sigma = rules.sigma;
    protocol.tuning.confirm_in_band_cells = rules.in_band_cells;
    protocol.tuning.confirm_bystander_sigma = rules.bystander_sigma;
    // the verdicts here are the plain band's (the disturbed neighbours'
    // margin has its own test, array_disturbed_margin.rs)
    protocol.tuning.disturbed_margin_sigma = 0.0;
    let (mut run, mut lab) = joint_in_lab(
        chain_world(&DeviceConfig::default(), 3, seed),
        &protocol,
        seed,
    );
    let batches = std::cell::RefCell::new(Vec::new());
    let mut records = Vec::new();
    through_changes(
        &mut run,
        &mut lab,
        phases,
        |b| batches.borrow_mut().push(b.to_vec()),
        |_, r| records.push((r.clone(), batches.borrow().len())),
    );
    let batches = batches.into_inner();
    let mut from = 0;
    records
        .into_iter()
        .map(|(record, to)| {
            let it = Iteration {
                record,
                batches: batches[from..to].to_vec(),
            };
            from = to;
            it
        })
        .collect()
}

fn in_band(p: &ParameterReport) -> bool {
    match (p.value, p.target, p.tolerance) {
        (Some(x), Some(t), Some(tol)) => {
            (x - t).abs() <= tol && p.std.is_some_and(|s| s <= 0.1 * x)
        }
        _ => false,
    }
}

fn is_parameter_scan(q: &Request) -> bool {
    matches!(q, Request::Measure { scan } if matches!(scan.kind, ScanKind::ReloadTime | ScanKind::TransitionWidth))
}

/// (cell, parameter name, in band) of each recheck in `r`.
fn rechecks(r: &IterationRecord) -> Vec<(u32, String, bool)> {
    r.events
        .iter()
        .filter_map(|e| match &e.kind {
            EventKind::BandEntryRechecked {
                parameter, in_band, ..
            } => {
                let (c, name) = split_gate(parameter)?;
                Some((c, name.to_string(), *in_band))
            }
            _ => None,
        })
        .collect()
}

/// What must be rechecked: when every cell reads in band, each parameter
/// within one σ of its band's edge of a cell not in band at the record
/// before (`before`; a cell whose targets were set since, in `reset`,
/// counts as not in band; a failed recheck counts out), or of any cell
/// with `in_band_cells` (`ArrayRunSettings::confirm_in_band_cells`); and
/// of each `bystander` cell (targets not set since the run last stopped
/// tuned) each parameter within `bystander_sigma` of its edge, whether or
/// not it was in band before (when `bystander_sigma > 0`).
fn expected_rechecks(
    r: &IterationRecord,
    before: Option<&IterationRecord>,
    reset: &[bool],
    bystander: &[bool],
    rules: Rules,
) -> Vec<(u32, String)> {
    let cells = r.parameters.chunks(2).collect::<Vec<_>>();
    if !cells.iter().all(|c| c.iter().all(in_band)) {
        return Vec::new();
    }
    let was_in = |c: usize| {
        !reset[c]
            && before.is_some_and(|b| {
                b.parameters[2 * c..2 * c + 2].iter().all(in_band)
                    && !rechecks(b).iter().any(|(k, _, ok)| *k as usize == c && !ok)
            })
    };
    let mut out = Vec::new();
    for (c, ps) in cells.iter().enumerate() {
        let margin = if bystander[c] && rules.bystander_sigma > 0.0 {
            rules.bystander_sigma
        } else if was_in(c) && !rules.in_band_cells {
            continue;
        } else {
            rules.sigma
        };
        for p in ps.iter() {
            let (x, t, s) = (p.value.unwrap(), p.target.unwrap(), p.std.unwrap());
            if (x - t).abs() + margin * s > 0.1 * t {
                out.push((c as u32, split_gate(&p.name).unwrap().1.to_string()));
            }
        }
    }
    out
}

/// Over the worlds `seeds`: the rechecks are exactly those the rule names,
/// each is one scan of its parameter in the batch right after the
/// measurement (nothing set in between), a run stops only when every
/// recheck read in band, and one that read out sends the iteration on to
/// its move. Returns the stops confirmed, the stops refused and the
/// rechecks of cells in band at the iteration before.
fn check_rechecks(seeds: &[u64], rules: Rules, phases: &[TargetChange]) -> Tally {
    let mut tally = Tally::default();
    let cells = 3;
    for &seed in seeds {
        let iterations = run(seed, rules, phases);
        let mut before: Option<&IterationRecord> = None;
        let mut in_phase = 0;
        let mut phase = 0;
        // targets set since `before` / since the run last stopped tuned
        let mut reset = vec![true; cells];
        let mut changed = vec![true; cells];
        for it in &iterations {
            let r = &it.record;
            let got: Vec<(u32, String)> = rechecks(r).into_iter().map(|(c, p, _)| (c, p)).collect();
            let bystander: Vec<bool> = changed.iter().map(|c| !c).collect();
            assert_eq!(
                got,
                expected_rechecks(r, before, &reset, &bystander, rules),
                "seed {seed} iteration {}",
                r.iteration
            );
            let entry_rule = expected_rechecks(r, before, &reset, &bystander, DEFAULT_RULES);
            tally.beyond_entry_rule +=
                got.iter().filter(|g| !entry_rule.contains(g)).count() as u32;
            tally.of_bystanders += got.iter().filter(|g| bystander[g.0 as usize]).count() as u32;
            if !got.is_empty() {
                // the iteration's measurement: every cell's t_sr and w
                // (the first iteration's batches start with the initial
                // measurements', one request per cell)
                let m = it
                    .batches
                    .iter()
                    .rposition(|b| b.len() == 6 && b.iter().all(is_parameter_scan))
                    .expect("the iteration's measurement");
                let scans: Vec<(u32, ScanKind)> = it.batches[m + 1]
                    .iter()
                    .map(|q| match q {
                        Request::Measure { scan } => (scan.cell.unwrap(), scan.kind),
                        other => panic!("a recheck batch sent {other:?}"),
                    })
                    .collect();
                let want: Vec<(u32, ScanKind)> = got
                    .iter()
                    .map(|(c, p)| {
                        let kind = if p == "t_sr" {
                            ScanKind::ReloadTime
                        } else {
                            ScanKind::TransitionWidth
                        };
                        (*c, kind)
                    })
                    .collect();
                assert_eq!(scans, want, "seed {seed} iteration {}", r.iteration);
                let all_in = rechecks(r).iter().all(|(_, _, ok)| *ok);
                assert_eq!(r.tuned, all_in, "seed {seed} iteration {}", r.iteration);
                if all_in {
                    tally.confirmed += 1;
                    assert_eq!(
                        it.batches.len(),
                        m + 2,
                        "a confirmed stop sends nothing more"
                    );
                } else {
                    tally.refused += 1;
                    assert!(
                        it.batches[m + 2]
                            .iter()
                            .any(|q| matches!(q, Request::SetVoltages { .. })),
                        "a refused stop moves on"
                    );
                }
            }
            if r.tuned {
                assert!(r.parameters.iter().all(in_band));
            }
            // the next phase (`through_changes`: tuned, or 40 iterations)
            // starts on its change's targets
            if r.tuned {
                changed = vec![false; cells];
            }
            reset = vec![false; cells];
            in_phase += 1;
            if r.tuned || in_phase >= 40 {
                in_phase = 0;
                phase += 1;
                match phases.get(phase) {
                    Some((Some(c), _)) => {
                        reset[*c] = true;
                        changed[*c] = true;
                    }
                    Some((None, _)) => {
                        reset = vec![true; cells];
                        changed = vec![true; cells];
                    }
                    None => {}
                }
            }
            before = Some(r);
        }
    }
    tally
}

/// What [`check_rechecks`] counted.
#[derive(Debug, Default)]
struct Tally {
    /// Stops every recheck confirmed.
    confirmed: u32,
    /// Stops a recheck refused.
    refused: u32,
    /// Rechecks the default rule would not have made.
    beyond_entry_rule: u32,
    /// Rechecks of bystanders.
    of_bystanders: u32,
}

/// Over twelve worlds (with the initial differences at 3 mV the first
/// refused recheck is the twelfth's, seed 22), the default rule: only
/// cells entering their band.
#[test]
fn near_edge_entries_are_scanned_again_before_the_run_stops() {
    let seeds: Vec<u64> = (11..=22).collect();
    let t = check_rechecks(&seeds, DEFAULT_RULES, &paper_phases());
    assert!(t.confirmed > 0 && t.refused > 0, "{t:?}");
    assert_eq!(t.beyond_entry_rule, 0);
}

/// With `confirm_in_band_cells` the cells already in band are rechecked
/// near their edge too, by the same rule otherwise. Over sixteen other
/// worlds, seeds 51…66: under the default `t_sr` floor for the filter
/// alone the readings keep the fit's σ, and with the lines forecast by
/// default a cell in band reads near its edge more rarely still (of seeds
/// 11…70 two worlds have such a recheck, 51 and 66, both here).
#[test]
fn with_in_band_cells_every_near_edge_reading_is_scanned_again() {
    let seeds: Vec<u64> = (51..=66).collect();
    let rules = Rules {
        in_band_cells: true,
        ..DEFAULT_RULES
    };
    let t = check_rechecks(&seeds, rules, &paper_phases());
    assert!(t.confirmed > 0, "{t:?}");
    assert!(
        t.beyond_entry_rule > 0,
        "no cell in band before was rechecked"
    );
}

/// Single-cell changes with the default rules: the bystanders are held to
/// the entry rule like every other cell (the same derivation with
/// `bystander_sigma = 0`).
#[test]
fn without_the_bystander_rule_single_cell_changes_recheck_entries_only() {
    let t = check_rechecks(&[11, 12, 13], DEFAULT_RULES, &single_cell_phases());
    assert!(t.confirmed > 0, "{t:?}");
    assert_eq!(t.beyond_entry_rule, 0);
}

/// `confirm_bystander_sigma = 2`: in single-cell changes the cells whose
/// targets did not change are rechecked within 2σ of their edge whether or
/// not they were in band before; the changed cell keeps the entry rule.
/// Some bystanders are rechecked here that the entry rule would have let
/// stop, and some stops are confirmed.
#[test]
fn bystanders_near_their_edge_are_scanned_again_with_the_wider_margin() {
    let rules = Rules {
        bystander_sigma: 2.0,
        ..DEFAULT_RULES
    };
    let t = check_rechecks(&[11, 12, 13], rules, &single_cell_phases());
    assert!(t.confirmed > 0, "{t:?}");
    assert!(t.of_bystanders > 0 && t.beyond_entry_rule > 0, "{t:?}");
}

/// With `confirm_entry_sigma = 0` nothing is rechecked and a run stops on
/// its first measurement with every cell in band.
#[test]
fn the_rule_off_rechecks_nothing() {
    let off = Rules {
        sigma: 0.0,
        ..DEFAULT_RULES
    };
    for it in run(11, off, &paper_phases()) {
        let r = &it.record;
        assert!(rechecks(r).is_empty());
        assert_eq!(
            r.tuned,
            r.parameters.iter().all(in_band),
            "iteration {}",
            r.iteration
        );
    }
}

#[test]
fn the_rule_is_bounded_and_on_by_default() {
    let p = ArrayProtocol::default();
    assert_eq!(p.tuning.confirm_entry_sigma, 1.0, "the default");
    assert_eq!(p.tuning.confirm_bystander_sigma, 0.0, "off by default");
    type Setter = fn(&mut ArrayProtocol, f64);
    let margins: [(&str, Setter); 2] = [
        ("tuning.confirm_entry_sigma", |q, s| {
            q.tuning.confirm_entry_sigma = s
        }),
        ("tuning.confirm_bystander_sigma", |q, s| {
            q.tuning.confirm_bystander_sigma = s
        }),
    ];
    for (field, set) in margins {
        for bad in [-0.5, 3.5, f64::NAN] {
            let mut q = ArrayProtocol::default();
            set(&mut q, bad);
            assert_eq!(q.validate().unwrap_err().field, field, "{bad}");
        }
        let mut off = ArrayProtocol::default();
        set(&mut off, 0.0);
        assert!(off.validate().is_ok(), "{field} = 0");
    }
}
