//! Client-side state that does not depend on the DOM: labels of statuses,
//! faults and events, which controls a status enables, and helpers that turn
//! records into numbers (the one history type is `history::RunHistory`).

use spintune::protocol::{
    ClearedBy, EventKind, Fault, FaultKind, GradientReport, IterationRecord, MovedGate, RunStatus,
};

/// Why a typed value is not applied, in plain words for the person typing
/// (e.g. "not a number", "must be between 0 and 1 (0.1 = ±10 % of the
/// target)"); shown next to the field as it is ([`std::fmt::Display`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct FieldError {
    /// The reason.
    pub message: String,
}

impl FieldError {
    /// A refusal with this reason.
    pub fn new(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
        }
    }
}

/// ±1σ of each gradient element: `√diag C` (None when the estimator has no covariance).
pub fn gradient_sigmas(g: &GradientReport) -> Option<Vec<f64>> {
    let c = g.covariance.as_ref()?;
    Some(
        (0..g.gradient.len())
            .map(|i| {
                c.get(i)
                    .and_then(|row| row.get(i))
                    .map_or(f64::NAN, |v| v.max(0.0).sqrt())
            })
            .collect(),
    )
}

/// Short human label of a run status, as the run header, the run list and
/// the in-browser mode show it. A fault names its kind in words, its message
/// and what clears it ([`fault_summary`]).
pub fn status_label(s: &RunStatus) -> String {
    match s {
        RunStatus::Running => "running".into(),
        RunStatus::Stepping => "stepping (one iteration)".into(),
        RunStatus::Paused => "paused".into(),
        RunStatus::Stopping => "stopping".into(),
        RunStatus::Faulted { fault } => format!("faulted — {}", fault_summary(fault)),
        RunStatus::Finished => "finished".into(),
        RunStatus::Stopped => "stopped".into(),
        RunStatus::Interrupted => "interrupted".into(),
        RunStatus::Failed { message } => format!("failed: {message}"),
    }
}

/// A fault's kind in words, for a person (the dashboard's name of each
/// [`FaultKind`]).
pub fn fault_kind_text(kind: FaultKind) -> &'static str {
    match kind {
        FaultKind::Disconnected => "Device disconnected",
        FaultKind::Device => "Instrument fault",
        FaultKind::Readback => "Read-back refused",
        FaultKind::Moved => "Gates moved",
        FaultKind::Safety => "Request refused by the safety check",
        FaultKind::Response => "Unexpected answer from the device",
    }
}

/// What clears a fault, for a person. Derived only from what the server (or
/// the in-browser session) states in [`Fault::cleared_by`]: the policy itself
/// is the core's ([`FaultKind::cleared_by`]), not the dashboard's.
pub fn fault_clears_text(cleared_by: ClearedBy) -> &'static str {
    match cleared_by {
        ClearedBy::Reconnect => "resumes by itself when the lab bridge reconnects (or Resume)",
        ClearedBy::Resume => "needs a person: check the instrument, then Resume",
        ClearedBy::AcceptPositions => {
            "needs a person: confirm the new positions (Accept positions) or put the gates back and Resume"
        }
    }
}

/// A fault in one line: its kind in words, its message and what clears it,
/// e.g. "Instrument fault: leakage on SB — needs a person: check the
/// instrument, then Resume".
pub fn fault_summary(fault: &Fault) -> String {
    format!(
        "{}: {} — {}",
        fault_kind_text(fault.kind),
        fault.message,
        fault_clears_text(fault.cleared_by)
    )
}

/// One row of the moved-gates table (a [`FaultKind::Moved`] fault), as shown.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MovedRow {
    /// Gate name.
    pub gate: String,
    /// Where the run left the gate, mV: a point ("-400.00") or a range
    /// ("-410.00 … -390.00").
    pub left: String,
    /// What the instrument reads now, mV.
    pub read: String,
    /// Read-back minus the nearest point where the run left the gate, mV,
    /// signed ("+50.00").
    pub difference: String,
}

impl MovedRow {
    /// The row of one moved gate.
    pub fn new(g: &MovedGate) -> Self {
        let (lo, hi) = if g.left_from_mv <= g.left_to_mv {
            (g.left_from_mv, g.left_to_mv)
        } else {
            (g.left_to_mv, g.left_from_mv)
        };
        let left = if lo == hi {
            format!("{lo:.2}")
        } else {
            format!("{lo:.2} … {hi:.2}")
        };
        // Distance to the nearest point of where the run left the gate.
        let difference = if g.read_mv < lo {
            g.read_mv - lo
        } else if g.read_mv > hi {
            g.read_mv - hi
        } else {
            0.0
        };
        MovedRow {
            gate: g.gate.clone(),
            left,
            read: format!("{:.2}", g.read_mv),
            difference: format!("{difference:+.2}"),
        }
    }
}

/// The rows of the moved-gates table of a fault (empty unless it reports
/// moved gates).
pub fn moved_rows(fault: &Fault) -> Vec<MovedRow> {
    fault.moved.iter().map(MovedRow::new).collect()
}

/// The short state shown in the run list: the status name, except a fault,
/// which reads "paused by fault" (the full label is the tooltip).
pub fn list_state(s: &RunStatus) -> &'static str {
    match s {
        RunStatus::Faulted { .. } => "paused by fault",
        other => other.name(),
    }
}

/// CSS classes of a status badge: `status status-<name>` (e.g.
/// `status status-faulted`), so every state can be styled on its own.
pub fn status_class(s: &RunStatus) -> String {
    format!("status status-{}", s.name())
}

/// A sentence explaining what a status means for the user, if it needs one.
pub fn status_hint(s: &RunStatus) -> Option<&'static str> {
    match s {
        RunStatus::Running | RunStatus::Paused | RunStatus::Stopped => None,
        RunStatus::Stepping => Some("Running one more iteration, then the run pauses."),
        RunStatus::Stopping => {
            Some("Stop acknowledged: the answer to the request at the device is still recorded; nothing new is sent.")
        }
        RunStatus::Faulted { fault } => Some(match fault.cleared_by {
            ClearedBy::AcceptPositions => {
                "The run paused itself and sends nothing. Accept positions adopts what the instrument reads and leaves the run paused; Resume then reads every gate again and continues from there (Resume without accepting only reads the gates again)."
            }
            ClearedBy::Reconnect | ClearedBy::Resume => {
                "The run paused itself and sends nothing. Resume or Single step reads every gate back first, then checks and retries the request that failed."
            }
        }),
        RunStatus::Finished => Some("The tuner reached its goal or its iteration limit."),
        RunStatus::Interrupted => {
            Some("The server went away while this run was active; resume to continue from the last stored iteration.")
        }
        RunStatus::Failed { .. } => {
            Some("The server cannot continue this run; resume retries from the last stored checkpoint.")
        }
    }
}

/// Whether a run in this state will never produce new iterations by itself
/// (`finished` or `stopped`).
pub fn status_is_final(s: &RunStatus) -> bool {
    s.is_terminal()
}

/// Which run controls make sense in a status: a button is enabled exactly
/// where its command would change the run, by the core's one lifecycle table
/// ([`RunStatus::is_changed_by`], `spintune::lifecycle`); the dashboard does
/// not state the rule again.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControlsEnabled {
    /// Pause (running, stepping, a faulted, interrupted or failed run).
    pub pause: bool,
    /// Resume (paused, faulted, interrupted, failed; stepping: keep running).
    pub resume: bool,
    /// Single step (those, and running: finish this iteration, then pause).
    pub step: bool,
    /// Stop for good.
    pub stop: bool,
    /// Change targets (refused by a stopped or stopping run).
    pub targets: bool,
    /// Accept the positions the instrument reads (only a run faulted because
    /// gates moved, [`FaultKind::Moved`]).
    pub accept_positions: bool,
}

impl ControlsEnabled {
    /// Everything enabled (status unknown: the server decides), except
    /// accepting positions, which only a known moved fault offers.
    pub const ALL: ControlsEnabled = ControlsEnabled {
        pause: true,
        resume: true,
        step: true,
        stop: true,
        targets: true,
        accept_positions: false,
    };

    /// The controls that apply in status `s` (what the run session accepts
    /// and would act on).
    pub fn for_status(s: &RunStatus) -> Self {
        use spintune::protocol::ControlCommand as C;
        let target = C::SetTarget {
            parameter: String::new(),
            target: None,
            tolerance: None,
        };
        ControlsEnabled {
            pause: s.is_changed_by(&C::Pause),
            resume: s.is_changed_by(&C::Resume),
            step: s.is_changed_by(&C::Step),
            stop: s.is_changed_by(&C::Stop),
            targets: s.is_changed_by(&target),
            accept_positions: s.is_changed_by(&C::AcceptPositions),
        }
    }
}

/// The `snake_case` name of an event kind, as in its JSON `event` tag.
pub fn event_name(e: &EventKind) -> &'static str {
    match e {
        EventKind::NotRepresentable { .. } => "not_representable",
        EventKind::FiniteDifferenceFailed { .. } => "finite_difference_failed",
        EventKind::InitialGradientRejected { .. } => "initial_gradient_rejected",
        EventKind::TooUncertain { .. } => "too_uncertain",
        EventKind::OutlierGated { .. } => "outlier_gated",
        EventKind::StepLimited { .. } => "step_limited",
        EventKind::NoMeasurement { .. } => "no_measurement",
        EventKind::UpdateRejected { .. } => "update_rejected",
        EventKind::EvaluationFailed { .. } => "evaluation_failed",
        EventKind::ScheduledTargetNotApplied { .. } => "scheduled_target_not_applied",
        EventKind::MoveRefused { .. } => "move_refused",
        EventKind::InstrumentMoved { .. } => "instrument_moved",
        EventKind::ConfirmationSkipped { .. } => "confirmation_skipped",
        EventKind::SweepSkipped { .. } => "sweep_skipped",
        EventKind::MeasurementSkipped { .. } => "measurement_skipped",
        EventKind::KeepCheck { .. } => "keep_check",
        EventKind::BandEntryRechecked { .. } => "band_entry_rechecked",
        EventKind::RetuneStarted { .. } => "retune_started",
        EventKind::BackInBand { .. } => "back_in_band",
        EventKind::NotBackInBand { .. } => "not_back_in_band",
        EventKind::SearchProbe { .. } => "search_probe",
        EventKind::SearchEnded { .. } => "search_ended",
    }
}

/// Whether an event matters for the device's safety or the trust in a
/// measurement (highlighted in the event list): the instrument was not where
/// the run expected it, a move was refused, a scan could not be evaluated, a
/// measurement was gated as an outlier, or a search for lost lines gave up.
pub fn event_is_safety_relevant(e: &EventKind) -> bool {
    matches!(
        e,
        EventKind::InstrumentMoved { .. }
            | EventKind::MoveRefused { .. }
            | EventKind::EvaluationFailed { .. }
            | EventKind::OutlierGated { .. }
            | EventKind::SearchEnded { found: false, .. }
    )
}

/// Lab time for display, e.g. `"12.5 min"` or `"1 h 03 min"`.
pub fn format_lab_time(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "–".into();
    }
    let minutes = seconds / 60.0;
    if minutes < 60.0 {
        format!("{minutes:.1} min")
    } else {
        let h = (minutes / 60.0).floor();
        format!("{h:.0} h {:02.0} min", minutes - 60.0 * h)
    }
}

/// Keep mode's state after the newest iteration, in plain words: the
/// phase and the next planned check, e.g. `keep: checked · next check of
/// t_sr, w at lab time 1 h 05 min`.
pub fn keep_label(keep: &spintune::protocol::KeepReport) -> String {
    use spintune::protocol::KeepPhase;
    let mut s = match keep.phase {
        KeepPhase::Tuning => "keep: tuning to the targets".to_string(),
        // a check that found a parameter out of band (or about to leave)
        // ends keeping: no next check is planned until the re-tune is done
        KeepPhase::Check if keep.next_check_lab_seconds.is_none() => {
            "keep: checked, re-tuning".to_string()
        }
        KeepPhase::Check => "keep: checked, in band".to_string(),
        KeepPhase::Retune => format!(
            "keep: re-tuning (out of band for {})",
            format_lab_time(keep.out_of_band_lab_seconds)
        ),
    };
    if let Some(at) = keep.next_check_lab_seconds {
        let what = if keep.next_check.is_empty() {
            "the parameters".to_string()
        } else {
            keep.next_check.join(", ")
        };
        s.push_str(&format!(
            " · next check of {what} at lab time {}",
            format_lab_time(at)
        ));
    }
    s
}

/// Finite min/max of some values, padded by `pad` of the span (and never empty).
pub fn padded_range(values: impl IntoIterator<Item = f64>, pad: f64) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.into_iter().filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let span = hi - lo;
    if span > 1e-12 * hi.abs().max(lo.abs()).max(1e-300) {
        (lo - pad * span, hi + pad * span)
    } else {
        // A single value: centre it in a small window.
        let half = if hi.abs() > 0.0 { 0.1 * hi.abs() } else { 1.0 };
        (lo - half, hi + half)
    }
}

/// The tuned badge of the headline: the newest record's `tuned` read with
/// the run's status (`None`: not known, e.g. the in-browser mode before a
/// run). "tuning…" only while the run iterates; a paused, faulted or ended
/// run out of band says so. `(text, in band)`.
pub fn tuned_badge(tuned: bool, status: Option<&RunStatus>) -> (&'static str, bool) {
    if tuned {
        return ("tuned: all parameters in band", true);
    }
    let text = match status {
        None | Some(RunStatus::Running | RunStatus::Stepping) => "tuning…",
        Some(RunStatus::Paused | RunStatus::Faulted { .. }) => "not in band (paused)",
        Some(RunStatus::Stopping) => "not in band (stopping)",
        Some(_) => "not in band when the run ended",
    };
    (text, false)
}

/// The run status badge while the page is not connected to the server:
/// a status that is not final is only the last one known (the run may have
/// moved on, or the server be down), so the badge says so instead of
/// showing a live-looking "running". `None`: show the status as it is.
pub fn stale_status_label(status: &RunStatus, connected: bool) -> Option<String> {
    (!connected && !status_is_final(status))
        .then(|| format!("{} (last known; not connected)", status.name()))
}

/// One number of an editor that shows the run's current value unless the
/// user is editing it (e.g. a target editor during a scheduled target
/// change). `shown(run)` is what the input displays; what Apply sends is
/// [`Followed::shown`] too, so a field the user did not touch sends the
/// run's current value, never a stale one.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Followed {
    /// Shows the run's value.
    #[default]
    Following,
    /// The user typed this and has not applied it.
    Editing(String),
    /// Applied: shown until the run's value changes from `then` (the change
    /// arrived, or another one did), then following again.
    Sent {
        /// What was applied.
        text: String,
        /// The run's value when it was applied.
        then: Option<f64>,
    },
}

impl Followed {
    /// The run's value as the input shows it (empty for none).
    pub fn text_of(value: Option<f64>) -> String {
        value.map(|v| format!("{v}")).unwrap_or_default()
    }

    /// What the input shows while the run's value is `run`.
    pub fn shown(&self, run: Option<f64>) -> String {
        match self {
            Followed::Editing(t) => t.clone(),
            Followed::Sent { text, then } if *then == run => text.clone(),
            _ => Self::text_of(run),
        }
    }

    /// Whether the user has typed something not yet applied.
    pub fn is_editing(&self) -> bool {
        matches!(self, Followed::Editing(_))
    }

    /// The user typed `text`.
    pub fn edit(&mut self, text: String) {
        *self = Followed::Editing(text);
    }

    /// Apply was pressed while the run's value was `run`.
    pub fn sent(&mut self, run: Option<f64>) {
        *self = Followed::Sent {
            text: self.shown(run),
            then: run,
        };
    }
}

/// Deterministic fake records for tests and previews: two parameters over
/// four gates, approaching their targets.
pub fn fake_records(n: u64) -> Vec<IterationRecord> {
    use spintune::protocol::{ParameterReport, RawScan, ScanKind, ScanReport, Trace, TunerEvent};
    use std::collections::BTreeMap;
    let gates: Vec<String> = ["N", "SA", "SB", "T"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    (0..n)
        .map(|k| {
            let kf = k as f64;
            let decay = (-kf / 6.0).exp();
            let t_sr = 20.0 + 40.0 * decay + 0.8 * (kf * 1.3).sin();
            let w = 270.0 - 60.0 * decay + 4.0 * (kf * 0.7).cos();
            let mut voltages_mv = BTreeMap::new();
            for (i, g) in gates.iter().enumerate() {
                voltages_mv.insert(
                    g.clone(),
                    -500.0 + 20.0 * i as f64 + 8.0 * (1.0 - decay) * (i as f64 - 1.5),
                );
            }
            let cov = |s: f64| {
                (0..4)
                    .map(|i| {
                        (0..4)
                            .map(|j| {
                                if i == j {
                                    s * s * (1.0 + 3.0 * decay)
                                } else {
                                    0.0
                                }
                            })
                            .collect()
                    })
                    .collect()
            };
            let x: Vec<f64> = (0..60).map(|i| -3.0 + i as f64 * 0.1).collect();
            let fit_y: Vec<f64> = x.iter().map(|x| 0.5 * (1.0 - (x / 0.8).tanh())).collect();
            let raw_y: Vec<f64> = fit_y
                .iter()
                .enumerate()
                .map(|(i, y)| y + 0.05 * ((i as f64 * 12.9898 + kf).sin() * 43758.5453).fract())
                .collect();
            IterationRecord {
                iteration: k,
                voltages_mv,
                gates: gates.clone(),
                parameters: vec![
                    ParameterReport {
                        name: "t_sr".into(),
                        unit: "ns".into(),
                        value: Some(t_sr),
                        std: Some(1.5),
                        target: Some(20.0),
                        tolerance: Some(2.0),
                    },
                    ParameterReport {
                        name: "w".into(),
                        unit: "µV".into(),
                        value: Some(w),
                        std: Some(6.0),
                        target: Some(270.0),
                        tolerance: Some(27.0),
                    },
                ],
                gradients: vec![
                    GradientReport {
                        parameter: "t_sr".into(),
                        unit: "ns/mV".into(),
                        gradient: vec![0.5, -0.3 + 0.01 * kf, 0.8, 0.1],
                        covariance: Some(cov(0.075)),
                    },
                    GradientReport {
                        parameter: "w".into(),
                        unit: "µV/mV".into(),
                        gradient: vec![-2.0, 1.5, 3.0 - 0.05 * kf, 0.4],
                        covariance: Some(cov(0.3)),
                    },
                ],
                step_mv: vec![1.0, -1.0, 0.5, 0.0],
                tuned: decay < 0.05,
                lab_seconds: 60.0 * kf + 30.0,
                scan_counts: BTreeMap::from([
                    (ScanKind::TransitionWidth, k + 1),
                    (ScanKind::ReloadTime, k + 1),
                ]),
                failed_evaluations: 0,
                scans: vec![ScanReport {
                    raw: RawScan {
                        kind: ScanKind::TransitionWidth,
                        x_label: "detuning ε (mV)".into(),
                        y_label: "excess charge (a.u.)".into(),
                        traces: vec![Trace {
                            label: "sweep".into(),
                            x: x.clone(),
                            y: raw_y,
                        }],
                    },
                    fit: vec![Trace {
                        label: "fit".into(),
                        x,
                        y: fit_y,
                    }],
                }],
                events: match k {
                    3 => vec![TunerEvent {
                        level: "qubit".into(),
                        kind: EventKind::StepLimited {
                            from_mv: 14.2,
                            to_mv: 10.0,
                        },
                    }],
                    5 => vec![TunerEvent {
                        level: "qubit".into(),
                        kind: EventKind::OutlierGated {
                            parameter: "t_sr".into(),
                            innovation: 9.5,
                            innovation_sigma: 1.2,
                            unit: "ns".into(),
                        },
                    }],
                    _ => vec![],
                },
                keep: None,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn sigma_from_covariance_diagonal() {
        let r = &fake_records(1)[0];
        let s = gradient_sigmas(&r.gradients[0]).unwrap();
        assert_eq!(s.len(), 4);
        assert!((s[0] - 0.075 * 2.0).abs() < 1e-12);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn ranges_and_labels() {
        assert_eq!(padded_range([1.0, 3.0], 0.0), (1.0, 3.0));
        let (lo, hi) = padded_range([5.0, 5.0], 0.0);
        assert!(lo < 5.0 && hi > 5.0);
        assert_eq!(padded_range([f64::NAN], 0.1), (0.0, 1.0));
        assert_eq!(format_lab_time(90.0), "1.5 min");
        assert_eq!(format_lab_time(3600.0 + 180.0), "1 h 03 min");
    }

    #[test]
    fn keep_label_says_the_phase_and_the_next_check() {
        use spintune::protocol::{KeepPhase, KeepReport};
        let check = KeepReport {
            phase: KeepPhase::Check,
            next_check_lab_seconds: Some(3900.0),
            next_check: vec!["t_sr".into(), "w".into()],
            out_of_band_lab_seconds: 0.0,
        };
        assert_eq!(
            keep_label(&check),
            "keep: checked, in band · next check of t_sr, w at lab time 1 h 05 min"
        );
        let retune = KeepReport {
            phase: KeepPhase::Retune,
            next_check_lab_seconds: None,
            next_check: vec![],
            out_of_band_lab_seconds: 90.0,
        };
        assert_eq!(
            keep_label(&retune),
            "keep: re-tuning (out of band for 1.5 min)"
        );
        let failed_check = KeepReport {
            phase: KeepPhase::Check,
            next_check_lab_seconds: None,
            next_check: vec![],
            out_of_band_lab_seconds: 0.0,
        };
        assert_eq!(keep_label(&failed_check), "keep: checked, re-tuning");
    }

    fn every_status() -> Vec<RunStatus> {
        use spintune::protocol::{Fault, FaultKind};
        vec![
            RunStatus::Running,
            RunStatus::Stepping,
            RunStatus::Paused,
            RunStatus::Stopping,
            RunStatus::Faulted {
                fault: Fault::new(FaultKind::Readback, "gate SB reads -410 mV, set -400 mV"),
            },
            RunStatus::Finished,
            RunStatus::Stopped,
            RunStatus::Interrupted,
            RunStatus::Failed {
                message: "store is read-only".into(),
            },
        ]
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn every_status_has_its_own_label_and_class() {
        let all = every_status();
        let labels: Vec<String> = all.iter().map(status_label).collect();
        for (s, l) in all.iter().zip(&labels) {
            assert!(
                l.starts_with(s.name()),
                "{l:?} does not start with {:?}",
                s.name()
            );
            assert_eq!(status_class(s), format!("status status-{}", s.name()));
        }
        let mut unique = labels.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), labels.len(), "{labels:?}");
        // The end-to-end test waits for these words; no label may contain another state's word.
        assert!(!status_label(&RunStatus::Stepping).contains("paused"));
        assert!(!status_label(&RunStatus::Stopping).contains("stopped"));
        assert_eq!(status_label(&all[8]), "failed: store is read-only");
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn faulted_status_is_labelled_with_kind_and_message_and_is_resumable() {
        use spintune::protocol::{Fault, FaultKind};
        let faulted = RunStatus::Faulted {
            fault: Fault::new(FaultKind::Device, "instrument timed out"),
        };
        let label = status_label(&faulted);
        assert_eq!(
            label,
            "faulted — Instrument fault: instrument timed out — needs a person: check the instrument, then Resume"
        );
        assert!(faulted.is_resumable() && !status_is_final(&faulted));
        assert!(status_hint(&faulted).is_some());
        let c = ControlsEnabled::for_status(&faulted);
        assert!(
            c.resume && c.step && c.pause && c.stop && c.targets && !c.accept_positions,
            "{c:?}"
        );
        // Failed is a different thing (red, not amber): its own class.
        assert_ne!(
            status_class(&faulted),
            status_class(&RunStatus::Failed {
                message: "x".into()
            })
        );
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn controls_follow_the_status() {
        for s in every_status() {
            let c = ControlsEnabled::for_status(&s);
            assert_eq!(
                c.resume,
                s.is_resumable() || s == RunStatus::Stepping,
                "{s:?}"
            );
            if s.is_terminal() {
                assert!(!c.pause && !c.resume && !c.step && !c.stop, "{s:?}: {c:?}");
            }
        }
        let running = ControlsEnabled::for_status(&RunStatus::Running);
        assert!(running.pause && !running.resume && running.step && running.stop);
        let paused = ControlsEnabled::for_status(&RunStatus::Paused);
        assert!(!paused.pause && paused.resume && paused.step && paused.stop);
        let stopping = ControlsEnabled::for_status(&RunStatus::Stopping);
        assert_eq!(
            stopping,
            ControlsEnabled {
                pause: false,
                resume: false,
                step: false,
                stop: false,
                targets: false,
                accept_positions: false,
            }
        );
        // A finished run may take a new target (it can revive a run that stopped when tuned).
        assert!(ControlsEnabled::for_status(&RunStatus::Finished).targets);
        // Unknown status: the server decides, but nothing offers to accept positions.
        const { assert!(!ControlsEnabled::ALL.accept_positions) };
    }

    fn moved_fault() -> Fault {
        let mut fault = Fault::new(FaultKind::Moved, "N reads 50 mV from where the run left it");
        fault.moved = vec![
            MovedGate {
                gate: "N".into(),
                left_from_mv: -400.0,
                left_to_mv: -400.0,
                read_mv: -350.0,
            },
            MovedGate {
                gate: "SD1".into(),
                left_from_mv: -610.0,
                left_to_mv: -590.0,
                read_mv: -612.5,
            },
        ];
        fault
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn accept_positions_only_for_a_moved_fault() {
        for s in every_status() {
            assert!(!ControlsEnabled::for_status(&s).accept_positions, "{s:?}");
        }
        for kind in [
            FaultKind::Disconnected,
            FaultKind::Device,
            FaultKind::Readback,
            FaultKind::Safety,
            FaultKind::Response,
        ] {
            let s = RunStatus::Faulted {
                fault: Fault::new(kind, "x"),
            };
            let c = ControlsEnabled::for_status(&s);
            assert!(!c.accept_positions && c.resume, "{kind:?}: {c:?}");
        }
        let moved = RunStatus::Faulted {
            fault: moved_fault(),
        };
        let c = ControlsEnabled::for_status(&moved);
        // Accept, or resume (re-reads the gates), hold or stop.
        assert!(
            c.accept_positions && c.resume && c.step && c.pause && c.stop,
            "{c:?}"
        );
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_fault_says_its_kind_and_what_clears_it() {
        let label = |kind| {
            status_label(&RunStatus::Faulted {
                fault: Fault::new(kind, "m"),
            })
        };
        assert_eq!(
            label(FaultKind::Disconnected),
            "faulted — Device disconnected: m — resumes by itself when the lab bridge reconnects (or Resume)"
        );
        for kind in [
            FaultKind::Device,
            FaultKind::Readback,
            FaultKind::Safety,
            FaultKind::Response,
        ] {
            let l = label(kind);
            assert!(
                l.contains(fault_kind_text(kind)) && l.contains("needs a person"),
                "{l}"
            );
            assert!(!l.contains("by itself"), "{l}");
        }
        let moved = label(FaultKind::Moved);
        assert!(
            moved.starts_with(
                "faulted — Gates moved: m — needs a person: confirm the new positions"
            ),
            "{moved}"
        );
        // The words come from the fault's stated `cleared_by` (the server's
        // policy), not from the kind: an old stored fault without the field
        // reads as needing a person.
        let old: Fault = serde_json::from_str(r#"{"kind":"disconnected","message":"m"}"#).unwrap();
        assert!(fault_summary(&old).contains("needs a person"));
        // Every kind has its own words; no label contains another state's word.
        let kinds = [
            FaultKind::Disconnected,
            FaultKind::Device,
            FaultKind::Readback,
            FaultKind::Moved,
            FaultKind::Safety,
            FaultKind::Response,
        ];
        let mut words: Vec<&str> = kinds.iter().map(|k| fault_kind_text(*k)).collect();
        words.sort();
        words.dedup();
        assert_eq!(words.len(), kinds.len());
        for kind in kinds {
            let l = label(kind);
            for other in [
                "running", "paused", "stopped", "stopping", "finished", "failed",
            ] {
                assert!(!l.contains(other), "{l} contains {other}");
            }
        }
        // A moved fault's hint explains the accept flow.
        let hint = status_hint(&RunStatus::Faulted {
            fault: moved_fault(),
        })
        .unwrap();
        assert!(hint.contains("Accept positions"), "{hint}");
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn moved_rows_show_where_the_run_left_each_gate_and_the_difference() {
        let rows = moved_rows(&moved_fault());
        assert_eq!(
            rows,
            vec![
                MovedRow {
                    gate: "N".into(),
                    left: "-400.00".into(),
                    read: "-350.00".into(),
                    difference: "+50.00".into(),
                },
                MovedRow {
                    gate: "SD1".into(),
                    left: "-610.00 … -590.00".into(),
                    read: "-612.50".into(),
                    difference: "-2.50".into(),
                },
            ]
        );
        // Above a range: the distance to its upper end; a reversed range is ordered.
        let row = MovedRow::new(&MovedGate {
            gate: "T".into(),
            left_from_mv: 10.0,
            left_to_mv: 0.0,
            read_mv: 12.25,
        });
        assert_eq!(
            (row.left.as_str(), row.difference.as_str()),
            ("0.00 … 10.00", "+2.25")
        );
        assert!(moved_rows(&Fault::new(FaultKind::Device, "x")).is_empty());
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn safety_relevant_events() {
        let recs = fake_records(6);
        let step = &recs[3].events[0];
        let gated = &recs[5].events[0];
        assert_eq!(event_name(&step.kind), "step_limited");
        assert!(!event_is_safety_relevant(&step.kind));
        assert_eq!(event_name(&gated.kind), "outlier_gated");
        assert!(event_is_safety_relevant(&gated.kind));
        for kind in [
            EventKind::InstrumentMoved {
                gate: "SB".into(),
                expected_mv: -400.0,
                read_mv: -402.0,
            },
            EventKind::MoveRefused {
                reason: "outside limits".into(),
            },
            EventKind::EvaluationFailed {
                scan: spintune::protocol::ScanKind::ReloadTime,
                reason: "fit diverged".into(),
            },
            EventKind::SearchEnded {
                probes: 4,
                found: false,
            },
        ] {
            assert!(event_is_safety_relevant(&kind), "{kind:?}");
            // the name is the JSON tag
            let json = serde_json::to_value(&kind).unwrap();
            assert_eq!(json["event"], event_name(&kind));
        }
        // a search under way, or one that found its lines, is routine
        for kind in [
            EventKind::SearchProbe {
                probe: 1,
                parameters: vec!["mu_a_mv".into()],
                offsets: vec![4.0],
            },
            EventKind::SearchEnded {
                probes: 2,
                found: true,
            },
        ] {
            assert!(!event_is_safety_relevant(&kind), "{kind:?}");
            let json = serde_json::to_value(&kind).unwrap();
            assert_eq!(json["event"], event_name(&kind));
        }
    }

    /// Issue 25: the target editor follows the run (a scheduled change)
    /// unless the user is editing, and a field left alone sends the run's
    /// current value.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn followed_fields_show_the_runs_value_unless_edited() {
        let mut target = Followed::default();
        let mut tol = Followed::default();
        assert_eq!(target.shown(Some(20.0)), "20");
        // A scheduled change: the untouched field shows the new target.
        assert_eq!(target.shown(Some(70.0)), "70");
        // The user edits only the tolerance; Apply sends the current target.
        tol.edit("3".into());
        assert!(tol.is_editing() && !target.is_editing());
        assert_eq!(
            (target.shown(Some(70.0)), tol.shown(Some(7.0))),
            ("70".into(), "3".into())
        );
        // A change arriving while the user edits does not overwrite the edit.
        assert_eq!(tol.shown(Some(9.0)), "3");
        target.sent(Some(70.0));
        tol.sent(Some(9.0));
        assert_eq!(tol.shown(Some(9.0)), "3", "applied, not yet in a record");
        assert_eq!(tol.shown(Some(3.0)), "3");
        assert_eq!(
            tol.shown(Some(5.0)),
            "5",
            "the run moved on: following again"
        );
        assert_eq!(target.shown(Some(45.0)), "45");
        assert_eq!(Followed::default().shown(None), "");
        // Editing after applying starts a new edit.
        tol.edit("4".into());
        assert_eq!(tol.shown(Some(9.0)), "4");
    }

    /// Issue 25: stopped and finished runs do not say "tuning…"; a status
    /// shown while disconnected is marked as the last one known.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn tuned_badge_and_stale_status_follow_the_run() {
        assert!(tuned_badge(true, Some(&RunStatus::Stopped)).1);
        assert_eq!(tuned_badge(false, None).0, "tuning…");
        assert_eq!(tuned_badge(false, Some(&RunStatus::Running)).0, "tuning…");
        for s in [
            RunStatus::Stopped,
            RunStatus::Finished,
            RunStatus::Interrupted,
        ] {
            let (text, ok) = tuned_badge(false, Some(&s));
            assert!(!ok && !text.contains("tuning"), "{s:?}: {text}");
        }
        assert_eq!(
            tuned_badge(false, Some(&RunStatus::Paused)).0,
            "not in band (paused)"
        );
        assert_eq!(
            stale_status_label(&RunStatus::Running, false).as_deref(),
            Some("running (last known; not connected)")
        );
        assert_eq!(stale_status_label(&RunStatus::Running, true), None);
        assert_eq!(stale_status_label(&RunStatus::Finished, false), None);
    }
}
