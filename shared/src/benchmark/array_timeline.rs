//! The array benchmark's timeline: every iteration of the joint loop as
//! cells × lab time, in band or not — as the run measured it and as the
//! world knows it (the figure of `spintune bench-array --plot`).

use serde::{Deserialize, Serialize};

use super::cell_trace::CellTrace;
use super::row_agreement::RowAgreement;
use crate::protocol::{EventKind, ParameterReport, TunerEvent};
use crate::sim::array::split_gate;

/// Most points a run's timeline keeps (bounded by construction: the
/// protocol's caps allow fewer iterations; later points are dropped).
pub const MAX_TIMELINE_POINTS: usize = 4_096;

/// One cell at one measurement, as the run measured it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CellBand {
    /// Both parameters measured within target ± tolerance.
    InBand,
    /// Both measured, at least one outside its band (or a second scan of a
    /// cell that had just entered its band read it outside:
    /// [`TimelinePoint::apply_rechecks`]).
    OutOfBand,
    /// A fit failed: no value to compare.
    NotMeasured,
}

/// One iteration of the joint loop.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimelinePoint {
    /// Lab time of the iteration's measurement since the protocol's start, min.
    pub lab_minutes: f64,
    /// Protocol phase: 0 the cold start, then the set-point changes, then
    /// the single-cell changes, in order.
    pub phase: u32,
    /// Per cell, what the measurement said.
    pub measured: Vec<CellBand>,
    /// Per cell, whether its true `t_sr` and `w` were within the band at
    /// the iteration's end (after its moves; world side, never shown to
    /// the strategy).
    pub truly_in_band: Vec<bool>,
    /// Per cell, its learned own-gate rows against the truth at the
    /// measurement: the rows the iteration's move was planned with, the
    /// truth at the voltages the move started from (an iteration without a
    /// move: both at its end). World side; empty where not noted.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rows: Vec<Option<RowAgreement>>,
    /// The cell followed in detail ([`super::array::ArrayProtocol::trace_cell`]),
    /// at the same voltages as `rows`; world side.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trace: Option<CellTrace>,
}

impl TimelinePoint {
    /// The point of an array record's measurement at `lab_seconds` (s since
    /// the protocol's start) with `parameters` (`c{k}.t_sr`, `c{k}.w` in
    /// cell order, each with its target and tolerance) in `phase`, with the
    /// world's `truly_in_band` per cell.
    ///
    /// ```
    /// use spintune::benchmark::array_timeline::{CellBand, TimelinePoint};
    /// use spintune::protocol::ParameterReport;
    /// let p = |name: &str, value: Option<f64>, target: f64| ParameterReport {
    ///     name: name.into(), unit: String::new(), value, std: None,
    ///     target: Some(target), tolerance: Some(0.1 * target),
    /// };
    /// let parameters = [
    ///     p("c0.t_sr", Some(21.0), 20.0), p("c0.w", Some(260.0), 270.0), // in band
    ///     p("c1.t_sr", Some(25.0), 20.0), p("c1.w", Some(270.0), 270.0), // t_sr 25 % off
    ///     p("c2.t_sr", None, 20.0), p("c2.w", Some(270.0), 270.0),       // a failed fit
    /// ];
    /// let point = TimelinePoint::new(90.0, &parameters, 2, vec![true, false, true]);
    /// assert_eq!(point.lab_minutes, 1.5);
    /// assert_eq!(point.measured, [CellBand::InBand, CellBand::OutOfBand, CellBand::NotMeasured]);
    /// ```
    pub fn new(
        lab_seconds: f64,
        parameters: &[ParameterReport],
        phase: u32,
        truly_in_band: Vec<bool>,
    ) -> Self {
        let measured = parameters
            .chunks(2)
            .map(|cell| {
                let mut band = CellBand::InBand;
                for p in cell {
                    match (p.value, p.target, p.tolerance) {
                        (Some(v), Some(t), Some(tol)) => {
                            if (v - t).abs() > tol && band == CellBand::InBand {
                                band = CellBand::OutOfBand;
                            }
                        }
                        _ => return CellBand::NotMeasured,
                    }
                }
                band
            })
            .collect();
        Self {
            lab_minutes: lab_seconds / 60.0,
            phase,
            measured,
            truly_in_band,
            rows: Vec::new(),
            trace: None,
        }
    }

    /// The record's `events` applied: a cell whose entry into its band a
    /// second scan did not confirm ([`EventKind::BandEntryRechecked`] out
    /// of band) was last measured out of band.
    ///
    /// ```
    /// use spintune::benchmark::array_timeline::{CellBand, TimelinePoint};
    /// use spintune::protocol::{EventKind, TunerEvent};
    /// let mut point = TimelinePoint::new(60.0, &[], 1, vec![true, true]);
    /// point.measured = vec![CellBand::InBand, CellBand::InBand];
    /// let recheck = |parameter: &str, in_band| TunerEvent {
    ///     level: "array".into(),
    ///     kind: EventKind::BandEntryRechecked {
    ///         parameter: parameter.into(), value: Some(199.0), std: Some(9.0),
    ///         in_band, unit: "µV".into(),
    ///     },
    /// };
    /// point.apply_rechecks(&[recheck("c0.w", true), recheck("c1.w", false)]);
    /// assert_eq!(point.measured, [CellBand::InBand, CellBand::OutOfBand]);
    /// ```
    pub fn apply_rechecks(&mut self, events: &[TunerEvent]) {
        for e in events {
            if let EventKind::BandEntryRechecked {
                parameter,
                in_band: false,
                ..
            } = &e.kind
            {
                let cell = split_gate(parameter).map(|(c, _)| c as usize);
                if let Some(m) = cell.and_then(|c| self.measured.get_mut(c)) {
                    *m = CellBand::OutOfBand;
                }
            }
        }
    }
}

/// How the cells of `phase` came into band: the iterations of the phase
/// (its timeline points, counted from 1) until the first cell, half the
/// cells (rounded up) and every cell were measured in band at once.
/// `None` if no point of the phase had every cell in band (the phase did
/// not converge, or its points were dropped).
///
/// It tells a slow approach from a long tail: a tuner whose cells enter
/// the band together has the three counts close; one whose last cells
/// lag has `every` far beyond `first`.
///
/// ```
/// use spintune::benchmark::array_timeline::{band_entry, CellBand::*, TimelinePoint};
/// let point = |phase, measured: Vec<_>| TimelinePoint {
///     lab_minutes: 0.0, phase, truly_in_band: vec![true; measured.len()], measured,
///     rows: Vec::new(), trace: None,
/// };
/// let points = [
///     point(0, vec![InBand, InBand, InBand]),
///     point(1, vec![OutOfBand, OutOfBand, OutOfBand]),
///     point(1, vec![InBand, NotMeasured, OutOfBand]),
///     point(1, vec![InBand, InBand, OutOfBand]),
///     point(1, vec![InBand, OutOfBand, OutOfBand]),
///     point(1, vec![InBand, InBand, InBand]),
/// ];
/// assert_eq!(band_entry(&points, 1), Some([2, 3, 5]));
/// assert_eq!(band_entry(&points, 0), Some([1, 1, 1]));
/// assert_eq!(band_entry(&points[..5], 1), None);
/// ```
pub fn band_entry(points: &[TimelinePoint], phase: u32) -> Option<[usize; 3]> {
    let in_band: Vec<(usize, usize)> = points
        .iter()
        .filter(|p| p.phase == phase)
        .map(|p| {
            let n = p.measured.len();
            let k = p
                .measured
                .iter()
                .filter(|&&b| b == CellBand::InBand)
                .count();
            (k, n)
        })
        .collect();
    let first_with = |enough: &dyn Fn(usize, usize) -> bool| {
        in_band
            .iter()
            .position(|&(k, n)| n > 0 && enough(k, n))
            .map(|i| i + 1)
    };
    let every = first_with(&|k, n| k == n)?;
    let first = first_with(&|k, _| k >= 1)?;
    let half = first_with(&|k, n| 2 * k >= n)?;
    Some([first, half, every])
}

/// Medians over the runs' timelines (`runs`, one per run) and their
/// all-cell changes (`phases`), each cell before it was first measured in
/// band in its phase (the cells still on their way, the last ones longest):
/// `[[length ratio, cosine] of t_sr, … of w]`; `None` without any such
/// point with rows.
///
/// ```
/// use spintune::benchmark::array_timeline::{before_band, CellBand::*, TimelinePoint};
/// use spintune::benchmark::row_agreement::RowAgreement;
/// let rows = |r: f64| Some(RowAgreement { length_ratio: [1.0, r], cosine: [1.0, 0.9] });
/// let point = |measured: Vec<_>, r: Vec<_>| TimelinePoint {
///     lab_minutes: 0.0, phase: 1, truly_in_band: vec![false; 2], measured, rows: r,
///     trace: None,
/// };
/// let points = [
///     point(vec![OutOfBand, OutOfBand], vec![rows(2.0), rows(1.5)]),
///     point(vec![InBand, OutOfBand], vec![rows(9.0), rows(1.2)]), // cell 0 in: not counted
///     point(vec![OutOfBand, InBand], vec![rows(9.0), rows(9.0)]), // neither: both were in
/// ];
/// let [t_sr, w] = before_band(&[&points[..]], &[1]).unwrap();
/// assert_eq!(t_sr, [1.0, 1.0]);
/// assert_eq!(w, [1.5, 0.9]); // median of 2.0, 1.5, 1.2
/// ```
pub fn before_band(runs: &[&[TimelinePoint]], phases: &[u32]) -> Option<[[f64; 2]; 2]> {
    let mut samples: [[Vec<f64>; 2]; 2] = Default::default();
    for (points, &phase) in runs.iter().flat_map(|r| phases.iter().map(move |p| (r, p))) {
        let mut entered: Vec<bool> = Vec::new();
        for p in points.iter().filter(|p| p.phase == phase) {
            entered.resize(p.measured.len(), false);
            for (c, band) in p.measured.iter().enumerate() {
                entered[c] |= *band == CellBand::InBand;
                if entered[c] {
                    continue;
                }
                if let Some(Some(a)) = p.rows.get(c) {
                    for (q, sample) in samples.iter_mut().enumerate() {
                        sample[0].push(a.length_ratio[q]);
                        sample[1].push(a.cosine[q]);
                    }
                }
            }
        }
    }
    let median = |x: &mut Vec<f64>| {
        x.sort_by(f64::total_cmp);
        x[x.len() / 2]
    };
    if samples[0][0].is_empty() {
        return None;
    }
    Some(samples.map(|mut q| [median(&mut q[0]), median(&mut q[1])]))
}
