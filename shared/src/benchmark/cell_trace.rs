//! One cell followed through the joint loop, world side
//! (`spintune bench-array --trace-cell K`): per iteration, where its
//! tuning gates stood when it was measured, what the scans said against
//! the truth there, and the own-gate rows its move was planned with
//! against the true ones. The strategy never sees it; it is how a stalled
//! cell is diagnosed (docs/array.md).

use serde::{Deserialize, Serialize};

/// Parameters of a cell in trace order (`t_sr` ns, `w` µV).
const UNITS: [(&str, &str); 2] = [("t_sr", "ns"), ("w", "µV")];

/// The traced cell at one iteration of the joint loop, taken where the
/// timeline's rows are (where the iteration's move started; an iteration
/// without a move: at its end).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellTrace {
    /// The cell followed.
    pub cell: u32,
    /// Its tuning gates (array names) and their voltages at the
    /// measurement, mV.
    pub voltages_mv: Vec<(String, f64)>,
    /// What its scans measured, `(value, σ)` of `t_sr` (ns) and `w` (µV);
    /// `None` where the fit failed.
    pub measured: [Option<(f64, f64)>; 2],
    /// The world's true `t_sr` (ns) and `w` (µV) at the measurement.
    pub truth: [f64; 2],
    /// The learned own-gate rows the iteration's move was planned with,
    /// `∂ln p/∂V` in 1/mV over [`CellTrace::voltages_mv`]'s gates, `t_sr`
    /// then `w`.
    pub learned_rows: [Vec<f64>; 2],
    /// The true rows at the measurement, same units and order.
    pub true_rows: [Vec<f64>; 2],
    /// Where its two transition lines truly sat at the measurement, mV on
    /// RFA / RFB from the operating point (drift included,
    /// [`crate::sim::SimulatedDevice::lines_now_mv`]). Off 0 the load
    /// curve reads `t_sr` long and the detuning scan fades. Absent in
    /// traces written before it existed: 0.
    #[serde(default)]
    pub true_lines_mv: [f64; 2],
    /// Where those lines truly sat at the cell's first line scan after the
    /// iteration's move, mV (world side, as [`CellTrace::true_lines_mv`]):
    /// what that scan found, before the correction it led to; the next
    /// point's [`CellTrace::true_lines_mv`] shows what the correction left
    /// at the next measurement. `None`: no line scan of the cell after a
    /// move in this iteration (or a trace written before it existed).
    #[serde(default)]
    pub lines_at_line_scan_mv: Option<[f64; 2]>,
    /// The cell's targets of `t_sr` (ns) and `w` (µV) at the measurement,
    /// as the iteration's record states them. `None` in traces written
    /// before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub targets: Option<[f64; 2]>,
}

impl CellTrace {
    /// One line of text with units, for a terminal.
    ///
    /// ```
    /// use spintune::benchmark::cell_trace::CellTrace;
    /// let t = CellTrace {
    ///     cell: 2,
    ///     voltages_mv: vec![("c2.N".into(), -700.0), ("c2.T".into(), -650.5)],
    ///     measured: [Some((21.0, 1.5)), None],
    ///     truth: [20.0, 180.0],
    ///     learned_rows: [vec![0.01, -0.02], vec![0.0, 0.005]],
    ///     true_rows: [vec![0.011, -0.019], vec![0.002, 0.004]],
    ///     true_lines_mv: [0.3, -1.5],
    ///     lines_at_line_scan_mv: Some([1.6, -2.0]),
    ///     targets: Some([20.0, 200.0]),
    /// };
    /// assert_eq!(
    ///     t.line(),
    ///     "c2.N -700.0 c2.T -650.5 mV | t_sr 21.0 ± 1.5 (true 20.0, target 20.0) ns, \
    ///      rows /mV learned [+0.0100 -0.0200] true [+0.0110 -0.0190] | \
    ///      w failed (true 180.0, target 200.0) µV, rows /mV learned [+0.0000 +0.0050] true [+0.0020 +0.0040] | \
    ///      lines true A +0.3 B -1.5 mV | at its line scan after the move A +1.6 B -2.0 mV"
    /// );
    /// ```
    pub fn line(&self) -> String {
        let volts: Vec<String> = self
            .voltages_mv
            .iter()
            .map(|(g, v)| format!("{g} {v:.1}"))
            .collect();
        let row = |r: &[f64]| {
            r.iter()
                .map(|x| format!("{x:+.4}"))
                .collect::<Vec<_>>()
                .join(" ")
        };
        let params: Vec<String> = UNITS
            .iter()
            .enumerate()
            .map(|(p, (name, unit))| {
                let value = match self.measured[p] {
                    Some((v, s)) => format!("{v:.1} ± {s:.1}"),
                    None => "failed".into(),
                };
                let target = match self.targets {
                    Some(t) => format!(", target {:.1}", t[p]),
                    None => String::new(),
                };
                format!(
                    "{name} {value} (true {:.1}{target}) {unit}, rows /mV learned [{}] true [{}]",
                    self.truth[p],
                    row(&self.learned_rows[p]),
                    row(&self.true_rows[p])
                )
            })
            .collect();
        let [a, b] = self.true_lines_mv;
        let scanned = match self.lines_at_line_scan_mv {
            Some([a, b]) => format!(" | at its line scan after the move A {a:+.1} B {b:+.1} mV"),
            None => String::new(),
        };
        format!(
            "{} mV | {} | lines true A {a:+.1} B {b:+.1} mV{scanned}",
            volts.join(" "),
            params.join(" | ")
        )
    }
}

/// How honest the traced scans' error bars are: per parameter (`t_sr`,
/// `w`), the fraction of the measured values within one reported σ of the
/// truth, and how many were measured (failed fits left out). Gaussian
/// error bars cover 68 %; `None` where nothing was measured.
///
/// ```
/// use spintune::benchmark::cell_trace::{error_bar_coverage, CellTrace};
/// let at = |t_sr: f64, w: f64| CellTrace {
///     cell: 0,
///     voltages_mv: Vec::new(),
///     measured: [Some((t_sr, 1.0)), Some((w, 10.0))],
///     truth: [20.0, 200.0],
///     learned_rows: [Vec::new(), Vec::new()],
///     true_rows: [Vec::new(), Vec::new()],
///     true_lines_mv: [0.0, 0.0],
///     lines_at_line_scan_mv: None,
///     targets: None,
/// };
/// // t_sr 0.5σ, 1σ (covered), 3σ off; w 0.1σ, 2σ, 0σ off
/// let traces = [at(20.5, 201.0), at(21.0, 220.0), at(17.0, 200.0)];
/// let c = error_bar_coverage(traces.iter());
/// assert_eq!(c[0], Some((2.0 / 3.0, 3)));
/// assert_eq!(c[1], Some((2.0 / 3.0, 3)));
/// ```
pub fn error_bar_coverage<'a>(
    traces: impl IntoIterator<Item = &'a CellTrace>,
) -> [Option<(f64, usize)>; 2] {
    let mut within = [0usize; 2];
    let mut n = [0usize; 2];
    for t in traces {
        for p in 0..2 {
            if let Some((v, s)) = t.measured[p] {
                n[p] += 1;
                if (v - t.truth[p]).abs() <= s {
                    within[p] += 1;
                }
            }
        }
    }
    [0, 1].map(|p| (n[p] > 0).then(|| (within[p] as f64 / n[p] as f64, n[p])))
}
