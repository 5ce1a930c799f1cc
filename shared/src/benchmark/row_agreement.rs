//! How well the joint tuner's learned rows agree with the truth, world
//! side: each cell's own-gate block of its `t_sr` and `w` rows (log space,
//! 1/mV) against the true Jacobian's at the same voltages. The benchmark
//! notes it per timeline point; the strategy never sees it.

use serde::{Deserialize, Serialize};

use super::array_timeline::{CellBand, TimelinePoint};

/// One cell's learned own-gate rows against the true ones, per parameter
/// (`t_sr`, `w`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RowAgreement {
    /// `|g_learned| / |g_true|` (1: the right length).
    pub length_ratio: [f64; 2],
    /// Cosine of the angle between them (1: the right direction).
    pub cosine: [f64; 2],
}

impl RowAgreement {
    /// From the learned and true own-gate rows (`[t_sr, w]`, each over the
    /// cell's own gates in the same order); `None` if a row is empty, of
    /// different lengths, not finite, or a true row is zero.
    ///
    /// ```
    /// use spintune::benchmark::row_agreement::RowAgreement;
    /// let learned = [vec![0.02, 0.0], vec![0.03, 0.03]];
    /// let truth = [vec![0.01, 0.0], vec![0.03, 0.0]];
    /// let a = RowAgreement::new(&learned, &truth).unwrap();
    /// assert_eq!(a.length_ratio[0], 2.0);
    /// assert_eq!(a.cosine[0], 1.0);
    /// assert!((a.length_ratio[1] - 2f64.sqrt()).abs() < 1e-12);
    /// assert!((a.cosine[1] - 0.5f64.sqrt()).abs() < 1e-12); // 45°
    /// assert!(RowAgreement::new(&learned, &[vec![0.0, 0.0], vec![0.1, 0.0]]).is_none());
    /// ```
    pub fn new(learned: &[Vec<f64>; 2], truth: &[Vec<f64>; 2]) -> Option<Self> {
        let mut out = Self {
            length_ratio: [0.0; 2],
            cosine: [0.0; 2],
        };
        for p in 0..2 {
            let (l, t) = (&learned[p], &truth[p]);
            if l.is_empty() || l.len() != t.len() || !l.iter().chain(t).all(|x| x.is_finite()) {
                return None;
            }
            let norm = |x: &[f64]| x.iter().map(|v| v * v).sum::<f64>().sqrt();
            let (nl, nt) = (norm(l), norm(t));
            if nt == 0.0 {
                return None;
            }
            out.length_ratio[p] = nl / nt;
            out.cosine[p] = if nl == 0.0 {
                0.0
            } else {
                l.iter().zip(t).map(|(a, b)| a * b).sum::<f64>() / (nl * nt)
            };
        }
        Some(out)
    }
}

/// Medians over the runs' timelines (`runs`, one per run) and their
/// all-cell changes (`phases`), each cell before it was first measured in
/// band in its phase (the cells still on their way, the last ones longest):
/// `[[length ratio, cosine] of t_sr, … of w]`; `None` without any such
/// point with rows.
///
/// ```
/// use spintune::benchmark::array_timeline::{CellBand::*, TimelinePoint};
/// use spintune::benchmark::row_agreement::{before_band, RowAgreement};
/// let rows = |r: f64| Some(RowAgreement { length_ratio: [1.0, r], cosine: [1.0, 0.9] });
/// let point = |measured: Vec<_>, r: Vec<_>| TimelinePoint {
///     lab_minutes: 0.0, phase: 1, truly_in_band: vec![false; 2], measured, rows: r,
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
