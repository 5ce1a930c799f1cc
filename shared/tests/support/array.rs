//! What the array tests share: the joint loop on a 3-cell world of the
//! default population (cell 0 the default device, device seed 5, noise
//! seed 11), at the benchmark's default settings and the world's crosstalk
//! as the lab's calibration.

use spintune::benchmark::array::{cell_tuner, lab_cross_calibration, world, ArrayProtocol, Lab};
use spintune::protocol::{IterationRecord, ParameterReport, Request, ScanKind};
use spintune::sim::array::{ArrayConfig, ArrayDevice};
use spintune::sim::DeviceConfig;
use spintune::tuner::array_run::{ArrayAction, ArrayRun, ArrayRunSettings};
use spintune::tuner::TunerConfig;

/// A chain of `cells` cells around `base` (device seed 5), noise seed
/// `seed`, every cell with its own sensor.
pub fn chain_world(base: &DeviceConfig, cells: u32, seed: u64) -> ArrayDevice {
    world(base, ArrayConfig::chain(cells, 5, seed), |_| true).unwrap()
}

/// The world and a joint loop with one tuner per cell (`cells.len()` = 3).
pub fn three_cells(cells: Vec<TunerConfig>) -> (ArrayRun, ArrayDevice) {
    three_cells_with(cells, ArrayProtocol::default().run_settings())
}

/// [`three_cells`] with the joint loop's `settings`.
pub fn three_cells_with(
    cells: Vec<TunerConfig>,
    settings: ArrayRunSettings,
) -> (ArrayRun, ArrayDevice) {
    let device = world(
        &DeviceConfig::default(),
        ArrayConfig::chain(3, 5, 11),
        |_| true,
    )
    .unwrap();
    let run = ArrayRun::new(cells, &device.gates(), settings, [0.3, 0.05], false).unwrap();
    (run, device)
}

/// The 3-cell chain of [`three_cells_with`] with the recommended tuner per
/// cell, tuned from cold.
pub fn three_cells_tuned(settings: ArrayRunSettings) -> (ArrayRun, ArrayDevice) {
    let protocol = ArrayProtocol::default();
    let cells = (0..3).map(|c| cell_tuner(c, &protocol)).collect();
    let (mut run, mut device) = three_cells_with(cells, settings);
    until_tuned(&mut run, &mut device);
    (run, device)
}

/// The joint loop as the benchmark runs it on `array` with `protocol`'s
/// settings and the lab's calibration the benchmark draws for `seed`,
/// against the world's `Lab` with the truth sealed.
pub fn joint_in_lab(array: ArrayDevice, protocol: &ArrayProtocol, seed: u64) -> (ArrayRun, Lab) {
    let lambda = lab_cross_calibration(array.config(), protocol, seed);
    let cells = (0..array.cells())
        .map(|c| cell_tuner(c, protocol))
        .collect();
    let run = ArrayRun::new(
        cells,
        &array.gates(),
        protocol.run_settings(),
        lambda,
        false,
    )
    .unwrap();
    let mut lab = Lab::new(array);
    lab.device.seal_truth();
    (run, lab)
}

/// Drive `run` against `lab` through `set_points`: each phase until its
/// record says tuned, the run idles or 40 iterations pass; then every cell
/// gets the next set point. `on_batch` sees each batch before the world
/// answers it; `on_iteration` each record at its iteration's end, with the
/// world as it is then. Every move the world refused is in
/// `lab.violations`.
pub fn through_set_points(
    run: &mut ArrayRun,
    lab: &mut Lab,
    set_points: &[(f64, f64)],
    on_batch: impl FnMut(&[Request]),
    on_iteration: impl FnMut(&Lab, &IterationRecord),
) {
    let changes: Vec<TargetChange> = set_points.iter().map(|&t| (None, t)).collect();
    through_changes(run, lab, &changes, on_batch, on_iteration);
}

/// A phase's target change: the cell whose targets change (`None`: every
/// cell) and its new targets (t_sr ns, w µV).
pub type TargetChange = (Option<usize>, (f64, f64));

/// [`through_set_points`] with each phase's change of its own: the first
/// phase runs on the run's own targets, each later one starts with its
/// change applied.
pub fn through_changes(
    run: &mut ArrayRun,
    lab: &mut Lab,
    changes: &[TargetChange],
    mut on_batch: impl FnMut(&[Request]),
    mut on_iteration: impl FnMut(&Lab, &IterationRecord),
) {
    let (mut phase, mut iterations) = (0, 0);
    while phase < changes.len() {
        let phase_over = match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                on_batch(&batch);
                let before = lab.device.lab_seconds();
                let answers = lab.batch(&batch);
                run.feed(answers, lab.device.lab_seconds() - before)
                    .unwrap();
                false
            }
            ArrayAction::Iteration(record) => {
                on_iteration(lab, &record);
                iterations += 1;
                record.tuned || iterations >= 40
            }
            ArrayAction::Idle => true,
        };
        if phase_over {
            phase += 1;
            iterations = 0;
            match changes.get(phase) {
                Some(&(Some(c), targets)) => run.set_targets(c, targets).unwrap(),
                Some(&(None, targets)) => {
                    for c in 0..run.targets().len() {
                        run.set_targets(c, targets).unwrap();
                    }
                }
                None => {}
            }
        }
    }
}

/// The joint loop's settings as a file written before any of the optional
/// fields existed (only the four every version had): what an old config
/// or checkpoint holds.
pub fn oldest_settings() -> ArrayRunSettings {
    serde_json::from_value(serde_json::json!({
        "relative_tolerance": 0.1, "line_rounds": 1, "moves_per_iteration": 1,
        "line_tolerance_mv": 0.1
    }))
    .unwrap()
}

/// Limits of ±2000 mV and a 10 mV step on every gate of `gates`: wide
/// enough that a planned move is cut only by its own step limit.
pub fn wide_limits(gates: &[String]) -> spintune::safety::SafetyLimits {
    spintune::safety::SafetyLimits::new(
        &gates
            .iter()
            .map(|g| spintune::safety::GateSpec {
                name: g.clone(),
                min_mv: -2000.0,
                max_mv: 2000.0,
                max_step_mv: 10.0,
                initial_mv: 0.0,
            })
            .collect::<Vec<_>>(),
    )
}

/// Drive `run` against `device` until it is measured in band, idles or
/// `max` iterations end; the records of those iterations.
pub fn drive(run: &mut ArrayRun, device: &mut ArrayDevice, max: u32) -> Vec<IterationRecord> {
    let mut records = Vec::new();
    loop {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(record) => {
                let tuned = record.tuned;
                records.push(*record);
                if tuned || records.len() as u32 >= max {
                    return records;
                }
            }
            ArrayAction::Idle => return records,
        }
    }
}

/// Drive `run` against `device` until a record says tuned or the run
/// idles (a cold start, or the end of a phase); at most 2000 polls.
pub fn until_tuned(run: &mut ArrayRun, device: &mut ArrayDevice) {
    for _ in 0..2000 {
        match run.poll().unwrap() {
            ArrayAction::Execute(batch) => {
                let before = device.lab_seconds();
                let answers = device.execute_batch(&batch);
                run.feed(answers, device.lab_seconds() - before).unwrap();
            }
            ArrayAction::Iteration(record) if record.tuned => return,
            ArrayAction::Iteration(_) => {}
            ArrayAction::Idle => return,
        }
    }
    panic!("not tuned within 2000 polls");
}

/// Whether `request` is a `t_sr` or `w` scan of cell `cell`.
pub fn is_measurement_of(request: &Request, cell: u32) -> bool {
    matches!(request, Request::Measure { scan }
        if scan.cell == Some(cell)
            && matches!(scan.kind, ScanKind::ReloadTime | ScanKind::TransitionWidth))
}

/// Whether `request` is a line scan of cell `cell`.
pub fn is_line_scan_of(request: &Request, cell: u32) -> bool {
    matches!(request, Request::Measure { scan }
        if scan.cell == Some(cell) && scan.kind == ScanKind::ChemicalPotential)
}

/// Whether `request` sets cell `cell`'s plungers (`c{cell}.PA`, `c{cell}.PB`)
/// and no other gate of it: a line correction, a search probe, or a move
/// that only compensates the neighbours' crosstalk.
pub fn sets_only_plungers_of(request: &Request, cell: u32) -> bool {
    let Request::SetVoltages { voltages_mv } = request else {
        return false;
    };
    let prefix = format!("c{cell}.");
    let plungers = [format!("c{cell}.PA"), format!("c{cell}.PB")];
    let own: Vec<&String> = voltages_mv
        .keys()
        .filter(|g| g.starts_with(&prefix))
        .collect();
    !own.is_empty() && own.iter().all(|g| plungers.contains(g))
}

/// The records of the joint loop on `array` with `protocol` and noise
/// `seed`, through `changes` ([`through_changes`]).
pub fn records_through(
    array: ArrayDevice,
    protocol: &ArrayProtocol,
    seed: u64,
    changes: &[TargetChange],
) -> Vec<IterationRecord> {
    let (mut run, mut lab) = joint_in_lab(array, protocol, seed);
    let mut out = Vec::new();
    through_changes(
        &mut run,
        &mut lab,
        changes,
        |_| {},
        |_, r| out.push(r.clone()),
    );
    out
}

/// A report's value, σ, target and half band (unit), when its error bar
/// is within the band (the loop does not act on a wider one: never in
/// band).
pub fn usable_report(p: &ParameterReport) -> Option<(f64, f64, f64, f64)> {
    let (x, s, t, tol) = (p.value?, p.std?, p.target?, p.tolerance?);
    (x > 0.0 && s <= tol / t * x).then_some((x, s, t, tol))
}

/// Every record's `tuned` equals the verdict derived for it (`verdicts`,
/// one per record, in order); `at` names the run in a failure.
pub fn assert_tuned_as_derived(
    records: &[IterationRecord],
    verdicts: impl IntoIterator<Item = bool>,
    at: &str,
) {
    let verdicts: Vec<bool> = verdicts.into_iter().collect();
    assert_eq!(
        records.len(),
        verdicts.len(),
        "{at}: one verdict per record"
    );
    for (r, v) in records.iter().zip(verdicts) {
        assert_eq!(r.tuned, v, "{at}, iteration {}", r.iteration);
    }
}
