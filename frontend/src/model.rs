//! Client-side state that does not depend on the DOM: the de-duplicated
//! iteration history of one run, and helpers that turn records into series.

use spintune::protocol::{GradientReport, IterationRecord, RunStatus};

/// What happened when a record was offered to a [`History`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Push {
    /// Appended as the next iteration.
    Appended,
    /// Already known (iteration below the next expected one); ignored.
    Duplicate,
    /// Iterations are missing between the last known one and this record; ignored.
    /// The caller should resubscribe from `expected`.
    Gap {
        /// The iteration that should have come next.
        expected: u64,
        /// The iteration that arrived.
        got: u64,
    },
}

/// The iterations of one run, strictly consecutive, oldest first.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct History {
    records: Vec<IterationRecord>,
}

impl History {
    /// An empty history.
    pub fn new() -> Self {
        Self::default()
    }

    /// All records, oldest first.
    pub fn records(&self) -> &[IterationRecord] {
        &self.records
    }

    /// The latest record.
    pub fn last(&self) -> Option<&IterationRecord> {
        self.records.last()
    }

    /// Number of records.
    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// Whether there are no records.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// The iteration to ask the server for next (`?from=`): last + 1, or 0.
    pub fn next_iteration(&self) -> u64 {
        self.records.last().map_or(0, |r| r.iteration + 1)
    }

    /// Offer one record. The first record of an empty history is accepted
    /// whatever its number (a server may start a history later than 0).
    pub fn push(&mut self, record: IterationRecord) -> Push {
        if self.records.is_empty() {
            self.records.push(record);
            return Push::Appended;
        }
        let expected = self.next_iteration();
        if record.iteration < expected {
            Push::Duplicate
        } else if record.iteration > expected {
            Push::Gap {
                expected,
                got: record.iteration,
            }
        } else {
            self.records.push(record);
            Push::Appended
        }
    }

    /// Offer records in order; stops at the first gap and reports it.
    /// Returns the number appended.
    pub fn extend(
        &mut self,
        records: impl IntoIterator<Item = IterationRecord>,
    ) -> Result<usize, Push> {
        let mut n = 0;
        for r in records {
            match self.push(r) {
                Push::Appended => n += 1,
                Push::Duplicate => {}
                gap @ Push::Gap { .. } => return Err(gap),
            }
        }
        Ok(n)
    }

    /// Forget everything.
    pub fn clear(&mut self) {
        self.records.clear();
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

/// Short human label of a run status.
pub fn status_label(s: &RunStatus) -> String {
    match s {
        RunStatus::Running => "running".into(),
        RunStatus::Paused => "paused".into(),
        RunStatus::Finished => "finished".into(),
        RunStatus::Stopped => "stopped".into(),
        RunStatus::Interrupted => "interrupted".into(),
        RunStatus::Failed { message } => format!("failed: {message}"),
    }
}

/// Whether a run in this state will never produce new iterations by itself.
pub fn status_is_final(s: &RunStatus) -> bool {
    matches!(s, RunStatus::Finished | RunStatus::Stopped)
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

/// Deterministic fake records for tests and previews: two parameters over
/// four gates, approaching their targets.
pub fn fake_records(n: u64) -> Vec<IterationRecord> {
    use spintune::protocol::{ParameterReport, RawScan, ScanKind, ScanReport, Trace};
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
                events: if k == 3 {
                    vec!["step clipped to 10 mV".into()]
                } else {
                    vec![]
                },
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn history_dedups_and_detects_gaps() {
        let recs = fake_records(6);
        let mut h = History::new();
        assert_eq!(h.next_iteration(), 0);
        assert_eq!(h.extend(recs[0..3].iter().cloned()), Ok(3));
        // Reconnect overlap: 1..4 → 1, 2 duplicates, 3 appended.
        assert_eq!(h.extend(recs[1..4].iter().cloned()), Ok(1));
        assert_eq!(h.next_iteration(), 4);
        assert_eq!(
            h.push(recs[5].clone()),
            Push::Gap {
                expected: 4,
                got: 5
            }
        );
        assert_eq!(h.len(), 4);
        assert_eq!(h.push(recs[4].clone()), Push::Appended);
        let its: Vec<u64> = h.records().iter().map(|r| r.iteration).collect();
        assert_eq!(its, vec![0, 1, 2, 3, 4]);
    }

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
}
