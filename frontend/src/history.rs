//! The client's history of one run, built for long runs (10⁵ iterations and
//! more): rows keyed by iteration, sorted, gaps allowed, filled from pages
//! arriving in any order, and a compact numeric form of each record.
//!
//! **Memory bound.** A record is not kept as such: each iteration becomes a
//! [`Row`] (iteration, lab time, tuned) and one number in each of the
//! history's columns, laid out by the run's [`Layout`] (per parameter value,
//! σ, target, tolerance; per gradient element value and σ; per gate voltage
//! and step; per parameter the value the tuner rejected, see [`rejects`]) —
//! 5·P + 2·P·G + 2·G `f64`s (P parameters, G gates: 34 numbers,
//! 272 B, plus the 24 B row, for the paper's 2 parameters and 4 gates), and
//! its events (usually none). Columns are contiguous, so a chart reading one
//! series of 100,000 iterations streams through 800 kB of memory. Raw scans (tens of kB per
//! iteration) are kept for two iterations only: the latest live one and the
//! one being inspected. At most [`MAX_ROWS`] rows are held (the oldest are
//! dropped beyond it): ≈ 28 MB for 100,000 iterations, plus the min/max
//! pyramids of the 14 drawn series and the lab time ([`Pyramid`], about
//! n / 7 blocks of 48 B each: ≈ 11 MB for 100,000 iterations) that make a
//! redraw O(pixel columns) instead of O(iterations).

use std::collections::BTreeMap;

use spintune::protocol::{
    EventKind, GradientReport, IterationRecord, ParameterReport, ScanReport, TunerEvent,
};

use crate::decimate::{Decimated, Pyramid};
use crate::model::gradient_sigmas;

/// Most rows held; older rows are dropped (and not fetched again) beyond this.
pub const MAX_ROWS: usize = 1_000_000;

/// Whether `event` says the tuner did not act on this iteration's
/// measurement of `parameter` (too uncertain, refused by the outlier gate,
/// or an update the estimator refused). Such a value is drawn marked and
/// does not set a chart's y range: it is kept in its own column
/// ([`Layout::rejected`]) and left out of the parameter's series.
pub fn rejects(event: &TunerEvent, parameter: &str) -> bool {
    match &event.kind {
        EventKind::TooUncertain { parameter: p, .. }
        | EventKind::OutlierGated { parameter: p, .. }
        | EventKind::UpdateRejected { parameter: p, .. } => p == parameter,
        _ => false,
    }
}

/// Names and units of the numbers in a [`Row`], fixed by the first record.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Layout {
    /// Parameters: (name, unit).
    pub parameters: Vec<(String, String)>,
    /// Gradients: (parameter, unit, e.g. `"ns/mV"`).
    pub gradients: Vec<(String, String)>,
    /// The top level's gates (gradient columns, voltages, steps).
    pub gates: Vec<String>,
}

/// Column indices of the numbers of an iteration.
impl Layout {
    fn from_record(r: &IterationRecord) -> Self {
        Self {
            parameters: r
                .parameters
                .iter()
                .map(|p| (p.name.clone(), p.unit.clone()))
                .collect(),
            gradients: r
                .gradients
                .iter()
                .map(|g| (g.parameter.clone(), g.unit.clone()))
                .collect(),
            gates: r.gates.clone(),
        }
    }

    /// Numbers per row.
    pub fn width(&self) -> usize {
        5 * self.parameters.len()
            + 2 * self.gradients.len() * self.gates.len()
            + 2 * self.gates.len()
    }

    /// Column of parameter `p`'s value; σ, target and tolerance follow.
    pub fn param(&self, p: usize) -> usize {
        4 * p
    }

    /// Column of gradient `g`'s element for gate `gate`; its σ follows.
    pub fn grad(&self, g: usize, gate: usize) -> usize {
        4 * self.parameters.len() + 2 * (g * self.gates.len() + gate)
    }

    /// Column of gate `gate`'s voltage (mV); its step (mV) follows.
    pub fn gate(&self, gate: usize) -> usize {
        4 * self.parameters.len() + 2 * self.gradients.len() * self.gates.len() + 2 * gate
    }

    /// Column of parameter `p`'s value where the tuner rejected it ([`rejects`];
    /// NaN where it did not). The value column holds every measured value.
    pub fn rejected(&self, p: usize) -> usize {
        4 * self.parameters.len()
            + 2 * self.gradients.len() * self.gates.len()
            + 2 * self.gates.len()
            + p
    }

    /// The parameter whose value is in column `c`, if any.
    fn param_of_value(&self, c: usize) -> Option<usize> {
        (c % 4 == 0 && c < 4 * self.parameters.len()).then_some(c / 4)
    }

    /// Position of a parameter by name.
    pub fn param_index(&self, name: &str) -> Option<usize> {
        self.parameters.iter().position(|p| p.0 == name)
    }

    /// The numbers of a record in this layout (NaN where absent).
    fn row(&self, r: &IterationRecord) -> (Row, Vec<f64>) {
        let mut data = vec![f64::NAN; self.width()];
        for (i, (name, _)) in self.parameters.iter().enumerate() {
            if let Some(p) = r.parameters.iter().find(|p| &p.name == name) {
                let o = self.param(i);
                let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
                data[o] = f(p.value);
                data[o + 1] = f(p.std);
                data[o + 2] = f(p.target);
                data[o + 3] = f(p.tolerance);
                if r.events.iter().any(|e| rejects(e, name)) {
                    data[self.rejected(i)] = f(p.value);
                }
            }
        }
        for (gi, (name, _)) in self.gradients.iter().enumerate() {
            let Some(g) = r.gradients.iter().find(|g| &g.parameter == name) else {
                continue;
            };
            let sig = gradient_sigmas(g);
            for (k, gate) in self.gates.iter().enumerate() {
                let Some(col) = r.gates.iter().position(|x| x == gate) else {
                    continue;
                };
                let o = self.grad(gi, k);
                data[o] = g.gradient.get(col).copied().unwrap_or(f64::NAN);
                data[o + 1] = sig
                    .as_ref()
                    .and_then(|s| s.get(col).copied())
                    .unwrap_or(f64::NAN);
            }
        }
        for (k, gate) in self.gates.iter().enumerate() {
            let o = self.gate(k);
            data[o] = r.voltages_mv.get(gate).copied().unwrap_or(f64::NAN);
            data[o + 1] = r
                .gates
                .iter()
                .position(|x| x == gate)
                .and_then(|c| r.step_mv.get(c).copied())
                .unwrap_or(f64::NAN);
        }
        (
            Row {
                iteration: r.iteration,
                lab_seconds: r.lab_seconds,
                tuned: r.tuned,
            },
            data,
        )
    }
}

/// `(lab seconds, 0)` of row `i` (NaN for an untuned row with `tuned_only`).
fn lab_of(rows: &[Row], tuned_only: bool, i: usize) -> (f64, f64) {
    let r = &rows[i];
    if tuned_only && !r.tuned {
        (f64::NAN, 0.0)
    } else {
        (r.lab_seconds, 0.0)
    }
}

/// One iteration (its numbers are in the history's columns, same index).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Row {
    /// Iteration number.
    pub iteration: u64,
    /// Cumulative lab time, s.
    pub lab_seconds: f64,
    /// All targeted parameters in band.
    pub tuned: bool,
}

/// How a page or a live record changed the history.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Merge {
    /// Rows added.
    pub added: usize,
    /// Records already known (ignored).
    pub duplicates: usize,
}

/// A change stamp: increasing and unique within the page (all histories
/// share one counter), so equal stamps mean the same content.
pub fn next_stamp() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static STAMP: AtomicU64 = AtomicU64::new(0);
    STAMP.fetch_add(1, Ordering::Relaxed) + 1
}

/// The history of one run (see the module doc for its memory bound).
#[derive(Debug, Clone, Default)]
pub struct RunHistory {
    layout: Layout,
    rows: Vec<Row>,
    /// `columns[c][i]`: number `c` of the [`Layout`] for `rows[i]` (NaN where
    /// the record had none).
    columns: Vec<Vec<f64>>,
    events: BTreeMap<u64, Vec<TunerEvent>>,
    /// The newest record received (summary or full), for the headline numbers.
    latest: Option<IterationRecord>,
    /// Scans of the latest iteration (live frames after `subscribe`).
    latest_scans: Option<(u64, Vec<ScanReport>)>,
    /// Scans of the inspected iteration (answer to `scans`).
    inspected_scans: Option<(u64, Vec<ScanReport>)>,
    /// No stored iteration below this one exists (a page said `more_before: false`).
    floor: u64,
    /// Iterations the server holds, as far as known (`RunSummary::iterations`).
    total: u64,
    /// Stamp of the latest change of any kind ([`next_stamp`]: unique
    /// across histories, so a chart never mistakes a new history for the
    /// one it drew).
    version: u64,
    /// Stamp of the latest change of the rows, columns or pyramids (what
    /// the time-series charts draw); not changed by scans, totals or floors.
    rows_version: u64,
    /// Min/max pyramids of the drawn series, by column (`None` for the
    /// columns that are not drawn as a series: σ, target, tolerance, step).
    pyramids: Vec<Option<Pyramid>>,
    /// Min/max pyramid of the lab time (s) over the rows.
    lab_pyramid: Pyramid,
    /// The same over the tuned rows only (NaN for the others).
    tuned_pyramid: Pyramid,
    /// Per parameter, runs of rows with the same (target, tolerance)
    /// ([`TargetRun`]), so that a chart finds the targets in its window
    /// without reading every row.
    target_runs: Vec<Vec<TargetRun>>,
}

/// Rows `first..=last` (both with a finite target) share one target and
/// tolerance (rows between them without a target do not break the run).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetRun {
    /// First row (index) with this target.
    pub first: usize,
    /// Last row (index) with this target.
    pub last: usize,
    /// Target (parameter units).
    pub target: f64,
    /// Tolerance half-width (parameter units; 0 where none).
    pub tolerance: f64,
}

impl RunHistory {
    /// Empty.
    pub fn new() -> Self {
        Self::default()
    }

    /// The layout of the rows (empty before the first record).
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// All rows, sorted by iteration (gaps possible).
    pub fn rows(&self) -> &[Row] {
        &self.rows
    }

    /// Number of iterations held.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether no iteration is held.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Stamp of the latest change of anything held (0 for a new, empty
    /// history; unique across histories otherwise).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// Stamp of the latest change of the rows (what the time-series charts
    /// draw): unchanged when only scans, the total or the floor change.
    pub fn rows_version(&self) -> u64 {
        self.rows_version
    }

    /// Stamp of the latest scans (iteration and count), for the scan charts.
    pub fn latest_scans_key(&self) -> Option<(u64, usize)> {
        self.latest_scans.as_ref().map(|(k, s)| (*k, s.len()))
    }

    /// The newest record received.
    pub fn latest(&self) -> Option<&IterationRecord> {
        self.latest.as_ref()
    }

    /// First and last iteration held.
    pub fn extent(&self) -> Option<(u64, u64)> {
        Some((self.rows.first()?.iteration, self.rows.last()?.iteration))
    }

    /// Iterations on the server (at least those held).
    pub fn total(&self) -> u64 {
        self.total
            .max(self.rows.last().map_or(0, |r| r.iteration + 1))
    }

    /// Tell the history how many iterations the server holds.
    pub fn set_total(&mut self, total: u64) {
        if total != self.total {
            self.total = total;
            self.version = next_stamp();
        }
    }

    /// Column `c` of the [`Layout`], one number per row.
    pub fn column(&self, c: usize) -> &[f64] {
        self.columns.get(c).map_or(&[], Vec::as_slice)
    }

    /// The σ column of a drawn series column `c` (parameter values and
    /// gradient elements have one; gate voltages and rejected values have none).
    fn sigma_of(&self, c: usize) -> Option<usize> {
        let l = &self.layout;
        let params = (0..l.parameters.len()).map(|p| l.param(p));
        let grads = (0..l.gradients.len())
            .flat_map(|g| (0..l.gates.len()).map(move |gi| (g, gi)))
            .map(|(g, gi)| l.grad(g, gi));
        params.chain(grads).any(|v| v == c).then_some(c + 1)
    }

    /// Whether column `c` is drawn as a series (has a pyramid).
    fn is_series(&self, c: usize) -> bool {
        let l = &self.layout;
        self.sigma_of(c).is_some()
            || (0..l.gates.len()).any(|g| l.gate(g) == c)
            || (0..l.parameters.len()).any(|p| l.rejected(p) == c)
    }

    /// Whether row `i`'s value in column `c` is one the tuner rejected
    /// (only parameter values can be).
    #[inline]
    pub fn is_rejected(&self, c: usize, i: usize) -> bool {
        self.layout
            .param_of_value(c)
            .is_some_and(|p| self.columns[self.layout.rejected(p)][i].is_finite())
    }

    /// `(value, σ)` of row `i` in series column `c` as drawn: NaN where the
    /// tuner rejected the value (it is drawn from [`Layout::rejected`]).
    #[inline]
    fn point(&self, c: usize, sigma: Option<usize>, i: usize) -> (f64, f64) {
        if self.is_rejected(c, i) {
            return (f64::NAN, 0.0);
        }
        let s = sigma.map_or(0.0, |s| self.columns[s][i]);
        (self.columns[c][i], s)
    }

    /// Bring the pyramids up to date: rows `from..` are new or changed.
    fn update_pyramids(&mut self, from: usize) {
        let n = self.rows.len();
        if self.pyramids.len() != self.columns.len() {
            self.pyramids = (0..self.columns.len())
                .map(|c| self.is_series(c).then(Pyramid::default))
                .collect();
        }
        let mut pyramids = std::mem::take(&mut self.pyramids);
        for (c, p) in pyramids.iter_mut().enumerate() {
            if let Some(p) = p {
                let sigma = self.sigma_of(c);
                p.update(n, from, |i| self.point(c, sigma, i));
            }
        }
        self.pyramids = pyramids;
        let rows = &self.rows;
        self.lab_pyramid.update(n, from, |i| lab_of(rows, false, i));
        self.tuned_pyramid
            .update(n, from, |i| lab_of(rows, true, i));
        let params = self.layout.parameters.len();
        self.target_runs.resize(params, Vec::new());
        for p in 0..params {
            let o = self.layout.param(p);
            let (t, tol) = (&self.columns[o + 2], &self.columns[o + 3]);
            let runs = &mut self.target_runs[p];
            // Runs reaching `from` are rescanned (the one before may grow).
            let keep = runs.partition_point(|r| r.last < from);
            let restart = runs.get(keep).map_or(from, |r| r.first.min(from));
            runs.truncate(keep);
            for i in restart..n {
                if !t[i].is_finite() {
                    continue;
                }
                let tl = if tol[i].is_finite() { tol[i] } else { 0.0 };
                match runs.last_mut() {
                    Some(r) if r.target == t[i] && r.tolerance == tl => r.last = i,
                    _ => runs.push(TargetRun {
                        first: i,
                        last: i,
                        target: t[i],
                        tolerance: tl,
                    }),
                }
            }
        }
    }

    /// Parameter `p`'s runs of one target within the rows `rows` (clipped
    /// to the rows with a target inside it), in row order.
    pub fn target_runs(&self, p: usize, rows: std::ops::Range<usize>) -> Vec<TargetRun> {
        let Some(runs) = self.target_runs.get(p) else {
            return Vec::new();
        };
        let t = &self.columns[self.layout.param(p) + 2];
        let start = runs.partition_point(|r| r.last < rows.start);
        let mut out = Vec::new();
        for r in &runs[start..] {
            if r.first >= rows.end {
                break;
            }
            let a = (r.first.max(rows.start)..=r.last).find(|&i| t[i].is_finite());
            let b = (r.first..=r.last.min(rows.end - 1))
                .rev()
                .find(|&i| t[i].is_finite());
            if let (Some(a), Some(b)) = (a, b) {
                if a <= b {
                    out.push(TargetRun {
                        first: a,
                        last: b,
                        ..*r
                    });
                }
            }
        }
        out
    }

    /// Decimate series column `c` over the rows with index in `rows` (x from
    /// `x(row)`, non-decreasing) into `columns` pixel columns over
    /// `[x0, x1]`: the M4 line and the ±σ band envelope
    /// ([`Pyramid::decimate`], O(columns × log n)). `None` if `c` is not a
    /// series column.
    pub fn decimate(
        &self,
        c: usize,
        rows: std::ops::Range<usize>,
        x: impl Fn(&Row) -> f64,
        (x0, x1): (f64, f64),
        columns: usize,
    ) -> Option<Decimated> {
        let p = self.pyramids.get(c)?.as_ref()?;
        let sigma = self.sigma_of(c);
        let r = self.rows.as_slice();
        Some(p.decimate(
            rows,
            |i| x(&r[i]),
            |i| self.point(c, sigma, i),
            x0,
            x1,
            columns,
        ))
    }

    /// Decimated lab time (s) against `x(row)`, like [`RunHistory::decimate`];
    /// with `tuned_only`, of the tuned rows only.
    pub fn decimate_lab_time(
        &self,
        rows: std::ops::Range<usize>,
        x: impl Fn(&Row) -> f64,
        (x0, x1): (f64, f64),
        columns: usize,
        tuned_only: bool,
    ) -> Vec<(f64, f64)> {
        let r = &self.rows;
        let p = if tuned_only {
            &self.tuned_pyramid
        } else {
            &self.lab_pyramid
        };
        p.decimate(
            rows,
            |i| x(&r[i]),
            |i| lab_of(r, tuned_only, i),
            x0,
            x1,
            columns,
        )
        .0
    }

    /// All numbers of iteration `k` (indexed by the [`Layout`]).
    pub fn values(&self, k: u64) -> Option<Vec<f64>> {
        let i = self.rows.binary_search_by_key(&k, |r| r.iteration).ok()?;
        Some(self.columns.iter().map(|c| c[i]).collect())
    }

    /// Iteration `k` as a record again, without scans: the newest record
    /// as received, any other rebuilt from the numbers held — values, σ,
    /// targets and tolerances, gradients (their σ as a diagonal covariance
    /// where known), the layout's gates' voltages and steps, tuned, lab
    /// time and events (not kept for an older row: scan counts, failed
    /// evaluations, keep mode, other gates' voltages). For views of a part
    /// of a run ([`crate::cell_history`]).
    pub fn record(&self, k: u64) -> Option<IterationRecord> {
        if let Some(l) = self.latest.as_ref().filter(|l| l.iteration == k) {
            let mut r = l.clone();
            r.events = self.events(k).to_vec();
            return Some(r);
        }
        let row = *self.row(k)?;
        let d = self.values(k)?;
        let l = &self.layout;
        let opt = |v: f64| v.is_finite().then_some(v);
        let parameters = l
            .parameters
            .iter()
            .enumerate()
            .map(|(i, (name, unit))| {
                let o = l.param(i);
                ParameterReport {
                    name: name.clone(),
                    unit: unit.clone(),
                    value: opt(d[o]),
                    std: opt(d[o + 1]),
                    target: opt(d[o + 2]),
                    tolerance: opt(d[o + 3]),
                }
            })
            .collect();
        let gradients = l
            .gradients
            .iter()
            .enumerate()
            .map(|(g, (parameter, unit))| {
                let n = l.gates.len();
                let sigma: Vec<f64> = (0..n).map(|gi| d[l.grad(g, gi) + 1]).collect();
                let covariance = sigma.iter().any(|s| s.is_finite()).then(|| {
                    (0..n)
                        .map(|i| {
                            (0..n)
                                .map(|j| if i == j { sigma[i] * sigma[i] } else { 0.0 })
                                .collect()
                        })
                        .collect()
                });
                GradientReport {
                    parameter: parameter.clone(),
                    unit: unit.clone(),
                    gradient: (0..n).map(|gi| d[l.grad(g, gi)]).collect(),
                    covariance,
                }
            })
            .collect();
        let voltages_mv = l
            .gates
            .iter()
            .enumerate()
            .filter(|(i, _)| d[l.gate(*i)].is_finite())
            .map(|(i, g)| (g.clone(), d[l.gate(i)]))
            .collect();
        Some(IterationRecord {
            iteration: k,
            voltages_mv,
            gates: l.gates.clone(),
            parameters,
            gradients,
            step_mv: (0..l.gates.len()).map(|i| d[l.gate(i) + 1]).collect(),
            tuned: row.tuned,
            lab_seconds: row.lab_seconds,
            scan_counts: Default::default(),
            failed_evaluations: 0,
            scans: Vec::new(),
            events: self.events(k).to_vec(),
            keep: None,
        })
    }

    /// The first iteration whose target of some parameter differs from the
    /// row before (both set): where a run's first set-point change took
    /// effect, for aligning a compared run on it.
    pub fn first_target_change(&self) -> Option<u64> {
        let cols: Vec<&[f64]> = (0..self.layout.parameters.len())
            .map(|p| self.column(self.layout.param(p) + 2))
            .collect();
        (1..self.rows.len())
            .find(|&i| {
                cols.iter().any(|c| {
                    let (a, b) = (c[i - 1], c[i]);
                    a.is_finite() && b.is_finite() && a != b
                })
            })
            .map(|i| self.rows[i].iteration)
    }

    /// The row of iteration `k`.
    pub fn row(&self, k: u64) -> Option<&Row> {
        self.rows
            .binary_search_by_key(&k, |r| r.iteration)
            .ok()
            .map(|i| &self.rows[i])
    }

    /// Index range of rows with iteration in `[lo, hi]`.
    pub fn range(&self, lo: f64, hi: f64) -> std::ops::Range<usize> {
        let a = self.rows.partition_point(|r| (r.iteration as f64) < lo);
        let b = self.rows.partition_point(|r| (r.iteration as f64) <= hi);
        a..b.max(a)
    }

    /// The row nearest to iteration `k` (for hover).
    pub fn nearest(&self, k: f64) -> Option<&Row> {
        let i = self.rows.partition_point(|r| (r.iteration as f64) < k);
        let after = self.rows.get(i);
        let before = i.checked_sub(1).and_then(|j| self.rows.get(j));
        match (before, after) {
            (Some(b), Some(a)) => Some(if k - b.iteration as f64 <= a.iteration as f64 - k {
                b
            } else {
                a
            }),
            (b, a) => b.or(a),
        }
    }

    /// The iteration whose lab time is nearest to `seconds`.
    pub fn at_lab_seconds(&self, seconds: f64) -> Option<u64> {
        let i = self.rows.partition_point(|r| r.lab_seconds < seconds);
        let cand = [i.checked_sub(1), Some(i)];
        cand.into_iter()
            .flatten()
            .filter_map(|j| self.rows.get(j))
            .min_by(|a, b| {
                (a.lab_seconds - seconds)
                    .abs()
                    .total_cmp(&(b.lab_seconds - seconds).abs())
            })
            .map(|r| r.iteration)
    }

    /// Events of iteration `k`.
    pub fn events(&self, k: u64) -> &[TunerEvent] {
        self.events.get(&k).map_or(&[], Vec::as_slice)
    }

    /// The newest `n` events with their iterations, newest first.
    pub fn recent_events(&self, n: usize) -> Vec<(u64, TunerEvent)> {
        self.events
            .iter()
            .rev()
            .flat_map(|(k, es)| es.iter().map(move |e| (*k, e.clone())))
            .take(n)
            .collect()
    }

    /// Scans of iteration `k` if held (latest or inspected).
    pub fn scans(&self, k: u64) -> Option<&[ScanReport]> {
        [&self.inspected_scans, &self.latest_scans]
            .into_iter()
            .flatten()
            .find(|(i, _)| *i == k)
            .map(|(_, s)| s.as_slice())
    }

    /// The latest iteration's scans, if held.
    pub fn latest_scans(&self) -> Option<(u64, &[ScanReport])> {
        self.latest_scans.as_ref().map(|(k, s)| (*k, s.as_slice()))
    }

    /// Scans of iteration `k` asked for by the page: kept as the inspected
    /// iteration's, and as the latest scans too when `k` is the newest
    /// iteration held and no newer scans are (a finished, stopped or
    /// reopened run gets its last scans this way, not from live frames).
    pub fn offer_scans(&mut self, k: u64, scans: Vec<ScanReport>) {
        let newest = self.rows.last().is_some_and(|r| r.iteration == k);
        let newer_held = self.latest_scans.as_ref().is_some_and(|(i, _)| *i >= k);
        if newest && !newer_held && !scans.is_empty() {
            self.latest_scans = Some((k, scans.clone()));
        }
        self.set_inspected_scans(k, scans);
    }

    /// The iteration whose scans the page should ask for to show the latest
    /// scans: the newest one held, when its scans are not held.
    pub fn missing_latest_scans(&self) -> Option<u64> {
        let k = self.rows.last()?.iteration;
        let held = self.latest_scans.as_ref().is_some_and(|(i, _)| *i >= k)
            || self.inspected_scans.as_ref().is_some_and(|(i, _)| *i == k);
        (!held).then_some(k)
    }

    /// Keep the scans of the inspected iteration `k` (replacing the previous).
    pub fn set_inspected_scans(&mut self, k: u64, scans: Vec<ScanReport>) {
        self.inspected_scans = Some((k, scans));
        self.version = next_stamp();
    }

    /// Insert records (a page in any order, or one live record). Known
    /// iterations are ignored; a record carrying scans that is the newest
    /// becomes the latest scans. Returns what changed.
    pub fn insert(&mut self, records: impl IntoIterator<Item = IterationRecord>) -> Merge {
        let mut new_rows: Vec<(Row, Vec<f64>)> = Vec::new();
        let mut merge = Merge::default();
        for mut r in records {
            if self.layout.gates.is_empty() && self.layout.parameters.is_empty() {
                self.layout = Layout::from_record(&r);
                self.columns = vec![Vec::new(); self.layout.width()];
            }
            if self.row(r.iteration).is_some() {
                merge.duplicates += 1;
                continue;
            }
            let newest = self
                .latest
                .as_ref()
                .is_none_or(|l| r.iteration >= l.iteration);
            let scans = std::mem::take(&mut r.scans);
            if newest && !scans.is_empty() {
                self.latest_scans = Some((r.iteration, scans));
            }
            if !r.events.is_empty() {
                self.events.insert(r.iteration, r.events.clone());
            }
            new_rows.push(self.layout.row(&r));
            if newest {
                r.events.clear();
                self.latest = Some(r);
            }
        }
        if new_rows.is_empty() {
            return merge;
        }
        new_rows.sort_by_key(|r| r.0.iteration);
        new_rows.dedup_by_key(|r| r.0.iteration);
        merge.added = new_rows.len();
        let appending = self
            .rows
            .last()
            .is_none_or(|l| l.iteration < new_rows[0].0.iteration);
        // Rows before this index keep their place (the pyramids above them stay).
        let mut changed_from = self.rows.len();
        if appending {
            for (row, values) in new_rows {
                self.rows.push(row);
                for (c, v) in self.columns.iter_mut().zip(values) {
                    c.push(v);
                }
            }
        } else {
            // Merge two sorted lists in O(n + m): the order once, then every column.
            let (n, m) = (self.rows.len(), new_rows.len());
            let mut order: Vec<(bool, usize)> = Vec::with_capacity(n + m);
            let (mut i, mut j) = (0, 0);
            while i < n || j < m {
                let take_old =
                    j == m || (i < n && self.rows[i].iteration <= new_rows[j].0.iteration);
                if take_old {
                    order.push((false, i));
                    i += 1;
                } else {
                    order.push((true, j));
                    j += 1;
                }
            }
            let pick_row = |&(new, k): &(bool, usize)| {
                if new {
                    new_rows[k].0
                } else {
                    self.rows[k]
                }
            };
            changed_from = order.iter().position(|o| o.0).unwrap_or(n);
            let rows: Vec<Row> = order.iter().map(pick_row).collect();
            for (ci, col) in self.columns.iter_mut().enumerate() {
                let merged: Vec<f64> = order
                    .iter()
                    .map(|&(new, k)| if new { new_rows[k].1[ci] } else { col[k] })
                    .collect();
                *col = merged;
            }
            self.rows = rows;
        }
        if self.rows.len() > MAX_ROWS {
            let drop = self.rows.len() - MAX_ROWS;
            let cut = self.rows[drop].iteration;
            self.rows.drain(..drop);
            for c in &mut self.columns {
                c.drain(..drop);
            }
            self.events = self.events.split_off(&cut);
            self.floor = self.floor.max(cut);
            changed_from = 0;
        }
        self.update_pyramids(changed_from);
        self.version = next_stamp();
        self.rows_version = self.version;
        merge
    }

    /// A page arrived: insert it; with `more_before == false` nothing older
    /// than its first record (or than `before` for an empty page) exists.
    pub fn insert_page(
        &mut self,
        records: Vec<IterationRecord>,
        more_before: bool,
        before: Option<u64>,
    ) -> Merge {
        let first = records.iter().map(|r| r.iteration).min().or(before);
        let m = self.insert(records);
        if !more_before {
            if let Some(f) = first {
                if f > self.floor {
                    self.floor = f;
                    self.version = next_stamp();
                }
            }
        }
        m
    }

    /// Iterations known missing, as half-open ranges `[a, b)`, newest first:
    /// below the first row (down to the floor) and between rows.
    pub fn gaps(&self) -> Vec<(u64, u64)> {
        let mut out = Vec::new();
        for w in self.rows.windows(2).rev() {
            if w[1].iteration > w[0].iteration + 1 {
                out.push((w[0].iteration + 1, w[1].iteration));
            }
        }
        if let Some(first) = self.rows.first() {
            if first.iteration > self.floor {
                out.push((self.floor, first.iteration));
            }
        }
        out
    }

    /// The next older page to ask for: `(before, limit)` covering the top of
    /// the newest gap, with `limit ≤ max_limit`; `None` when complete.
    pub fn next_page(&self, max_limit: u32) -> Option<(u64, u32)> {
        let (a, b) = *self.gaps().first()?;
        let limit = (b - a).min(max_limit as u64) as u32;
        Some((b, limit))
    }

    /// Forget everything.
    pub fn clear(&mut self) {
        *self = Self::default();
        self.version = next_stamp();
        self.rows_version = self.version;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::fake_records;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn rows_version_changes_with_rows_only_and_stamps_are_unique() {
        let mut h = RunHistory::new();
        let mut other = RunHistory::new();
        assert_eq!((h.version(), h.rows_version()), (0, 0));
        let recs = fake_records(3);
        h.insert(recs[..2].to_vec());
        let rows = h.rows_version();
        assert!(rows > 0);
        // Scans of an inspected iteration, the total: not the rows.
        h.set_inspected_scans(0, Vec::new());
        h.set_total(50);
        assert_eq!(h.rows_version(), rows);
        assert!(h.version() > rows);
        // A known iteration adds nothing; a new one changes the rows.
        h.insert(recs[..1].to_vec());
        assert_eq!(h.rows_version(), rows);
        h.insert(recs[2..].to_vec());
        assert!(h.rows_version() > rows);
        // Another history with the same records has other stamps.
        other.insert(recs.clone());
        assert_ne!(other.rows_version(), h.rows_version());
        let before = h.rows_version();
        h.clear();
        assert_ne!(h.rows_version(), before);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn the_first_set_point_change_is_found() {
        let mut recs = fake_records(12);
        let mut h = RunHistory::new();
        h.insert(recs.clone());
        assert_eq!(h.first_target_change(), None);
        // w's target changes at 7 (and again at 9); a missing target is no change.
        recs[3].parameters[1].target = None;
        for r in &mut recs[7..] {
            r.parameters[1].target = Some(300.0);
        }
        for r in &mut recs[9..] {
            r.parameters[0].target = Some(30.0);
        }
        let mut h = RunHistory::new();
        h.insert(recs);
        assert_eq!(h.first_target_change(), Some(7));
    }

    fn its(h: &RunHistory) -> Vec<u64> {
        h.rows().iter().map(|r| r.iteration).collect()
    }

    fn recs(range: std::ops::Range<u64>) -> Vec<IterationRecord> {
        let all = fake_records(range.end);
        all[range.start as usize..].to_vec()
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pages_out_of_order_with_gaps_and_duplicates() {
        let mut h = RunHistory::new();
        // The newest page first (as after hello), then older pages out of order.
        assert_eq!(h.insert_page(recs(80..100), true, None).added, 20);
        assert_eq!(h.next_page(15), Some((80, 15)));
        assert_eq!(h.insert_page(recs(20..40), true, Some(40)).added, 20);
        assert_eq!(h.gaps(), vec![(40, 80), (0, 20)]);
        // Overlapping page: duplicates ignored.
        let m = h.insert_page(recs(30..60), true, Some(60));
        assert_eq!(
            m,
            Merge {
                added: 20,
                duplicates: 10
            }
        );
        assert_eq!(h.gaps(), vec![(60, 80), (0, 20)]);
        assert_eq!(h.next_page(2000), Some((80, 20)));
        // A live record beyond the end, then a page reversed.
        let mut page: Vec<_> = recs(60..80);
        page.reverse();
        h.insert_page(page, true, Some(80));
        h.insert(recs(100..101));
        assert_eq!(h.gaps(), vec![(0, 20)]);
        // The oldest page says nothing is older.
        h.insert_page(recs(0..20), false, Some(20));
        assert_eq!(h.gaps(), vec![]);
        assert_eq!(h.next_page(2000), None);
        assert_eq!(its(&h), (0..101).collect::<Vec<_>>());
        assert_eq!(h.latest().unwrap().iteration, 100);
        // Every column was merged in the same order as the rows.
        let src = fake_records(101);
        let (p, g) = (h.layout().param(1), h.layout().gate(2));
        for (i, r) in src.iter().enumerate() {
            assert_eq!(h.column(p)[i], r.parameters[1].value.unwrap(), "w at {i}");
            assert_eq!(h.column(g)[i], r.voltages_mv["SB"], "V_SB at {i}");
        }
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pyramids_follow_pages_from_the_newest_backwards_and_live_appends() {
        use crate::decimate::{Band, Columns};
        let mut src = fake_records(700);
        src[345].parameters[0].value = Some(900.0);
        let mut h = RunHistory::new();
        // Newest page first, older pages prepended, then live records.
        h.insert_page(src[500..650].to_vec(), true, None);
        h.insert_page(src[200..500].to_vec(), true, Some(500));
        h.insert_page(src[0..200].to_vec(), false, Some(200));
        for r in &src[650..700] {
            h.insert([r.clone()]);
        }
        assert_eq!(h.len(), 700);
        let l = h.layout().clone();
        for (c, sigma) in [
            (l.param(0), true),
            (l.param(1), true),
            (l.grad(1, 2), true),
            (l.gate(3), false),
        ] {
            let (x0, x1, cols) = (-0.5, 699.5, 60);
            let got = h
                .decimate(c, 0..700, |r| r.iteration as f64, (x0, x1), cols)
                .expect("a series column has a pyramid");
            let mut full = Columns::new(x0, x1, cols);
            for (i, r) in h.rows().iter().enumerate() {
                let v = h.column(c)[i];
                let s = if sigma { h.column(c + 1)[i] } else { 0.0 };
                let s = if s.is_finite() { s } else { 0.0 };
                full.push(r.iteration as f64, v, v - s, v + s);
            }
            let (line, bands) = full.finish();
            assert_eq!(got.0, line, "column {c}");
            let ext = |b: &[Band]| b.iter().map(|b| (b.1, b.2)).collect::<Vec<_>>();
            assert_eq!(ext(&got.1), ext(&bands), "column {c}");
        }
        let (line, _) = h
            .decimate(
                l.param(0),
                0..700,
                |r| r.iteration as f64,
                (-0.5, 699.5),
                60,
            )
            .unwrap();
        assert!(line.contains(&(345.0, 900.0)), "spike lost");
        // Not a series: no pyramid.
        assert!(h
            .decimate(
                l.param(0) + 2,
                0..700,
                |r| r.iteration as f64,
                (0.0, 1.0),
                5
            )
            .is_none());
        // Lab time is non-decreasing: its decimated maximum is the last row's.
        let lab = h.decimate_lab_time(0..700, |r| r.iteration as f64, (-0.5, 699.5), 60, false);
        assert_eq!(lab.last().unwrap().1, h.rows()[699].lab_seconds);
        // Tuned markers: only tuned rows.
        let tuned = h.decimate_lab_time(0..700, |r| r.iteration as f64, (-0.5, 699.5), 15, true);
        for (k, _) in &tuned {
            assert!(
                h.row(*k as u64).unwrap().tuned,
                "untuned iteration {k} marked"
            );
        }
        assert_eq!(tuned.is_empty(), !h.rows().iter().any(|r| r.tuned));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_store_that_starts_late_has_a_floor() {
        let mut h = RunHistory::new();
        h.insert_page(recs(50..60), true, None);
        assert_eq!(h.gaps(), vec![(0, 50)]);
        // The server has nothing below 45 (e.g. pruned): no gap below it.
        h.insert_page(recs(45..50), false, Some(50));
        assert_eq!(h.gaps(), vec![]);
        // An empty page for `before = 45` with more_before = false also ends paging.
        let mut h2 = RunHistory::new();
        h2.insert_page(recs(45..50), true, None);
        h2.insert_page(vec![], false, Some(45));
        assert_eq!(h2.next_page(100), None);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn rows_hold_numbers_and_scans_are_kept_for_two_iterations_only() {
        let mut h = RunHistory::new();
        h.insert(fake_records(8));
        let l = h.layout().clone();
        assert_eq!(l.parameters[0], ("t_sr".to_string(), "ns".to_string()));
        assert_eq!(l.gates, vec!["N", "SA", "SB", "T"]);
        let r = h.values(5).unwrap();
        let src = &fake_records(6)[5];
        assert_eq!(h.column(l.param(0)).len(), 8);
        assert_eq!(r[l.param(0)], src.parameters[0].value.unwrap());
        assert_eq!(r[l.param(1) + 2], 270.0); // w target
        assert_eq!(r[l.grad(1, 2)], src.gradients[1].gradient[2]);
        assert!(
            (r[l.grad(0, 0) + 1] - 0.075 * (1.0 + 3.0 * (-5.0f64 / 6.0).exp()).sqrt()).abs()
                < 1e-12
        );
        assert_eq!(r[l.gate(3)], src.voltages_mv["T"]);
        assert_eq!(r[l.gate(1) + 1], -1.0); // step on SA
                                            // Only the newest record's scans are held; the others were dropped.
        assert_eq!(h.latest_scans().map(|s| s.0), Some(7));
        assert!(h.scans(5).is_none());
        h.set_inspected_scans(5, src.scans.clone());
        assert_eq!(h.scans(5).unwrap().len(), 1);
        assert!(h.scans(7).is_some());
        // Events are kept per iteration.
        assert_eq!(h.events(5).len(), 1);
        assert_eq!(h.recent_events(10).len(), 2);
        assert_eq!(h.recent_events(10)[0].0, 5);
        // Lookup helpers.
        assert_eq!(h.nearest(5.4).unwrap().iteration, 5);
        assert_eq!(h.range(2.0, 4.5), 2..5);
        assert_eq!(h.at_lab_seconds(60.0 * 3.0 + 31.0), Some(3));
    }

    /// A held row comes back as a record: the newest as received, an older
    /// one rebuilt from its numbers (σ of the gradients as a diagonal
    /// covariance), events included, scans not.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_held_row_comes_back_as_a_record() {
        let recs = fake_records(8);
        let mut h = RunHistory::new();
        h.insert(recs.clone());
        assert!(h.record(8).is_none());
        let newest = h.record(7).unwrap();
        assert_eq!(newest, recs[7].summary());
        let r = h.record(5).unwrap();
        let src = &recs[5];
        assert_eq!(r.iteration, 5);
        assert_eq!(r.parameters, src.parameters);
        assert_eq!(r.gates, src.gates);
        assert_eq!(r.voltages_mv, src.voltages_mv);
        assert_eq!(r.step_mv, src.step_mv);
        assert_eq!((r.tuned, r.lab_seconds), (src.tuned, src.lab_seconds));
        assert_eq!(r.events, src.events);
        assert!(r.scans.is_empty());
        for (a, b) in r.gradients.iter().zip(&src.gradients) {
            assert_eq!(
                (&a.parameter, &a.unit, &a.gradient),
                (&b.parameter, &b.unit, &b.gradient)
            );
            let (ca, cb) = (
                a.covariance.as_ref().unwrap(),
                b.covariance.as_ref().unwrap(),
            );
            for (ra, rb) in ca.iter().zip(cb) {
                for (x, y) in ra.iter().zip(rb) {
                    assert!((x - y).abs() <= 1e-12 * y.abs().max(1.0), "{x} vs {y}");
                }
            }
        }
        // A record that arrives again as rebuilt is a duplicate.
        assert_eq!(h.insert([r]).duplicates, 1);
    }

    /// Issue 25: a value the tuner rejected keeps its number (hover,
    /// inspector) but is left out of the drawn series and its pyramid, and
    /// is kept in the parameter's rejected column instead.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn rejected_values_are_kept_apart_from_the_series() {
        use spintune::protocol::EventKind;
        let mut recs = fake_records(400);
        recs[200].parameters[0].value = Some(238.0);
        recs[200].events.push(TunerEvent {
            level: "qubit".into(),
            kind: EventKind::TooUncertain {
                parameter: "t_sr".into(),
                value: 238.0,
                std: 288.0,
                unit: "ns".into(),
            },
        });
        let mut h = RunHistory::new();
        h.insert(recs);
        let l = h.layout().clone();
        let (v, rej) = (l.param(0), l.rejected(0));
        assert_eq!(h.values(200).unwrap()[v], 238.0);
        assert_eq!(h.values(200).unwrap()[rej], 238.0);
        assert!(h.values(201).unwrap()[rej].is_nan());
        // The fake records' outlier-gated t_sr at iteration 5 is rejected too; w is not.
        assert!(h.is_rejected(v, 5) && h.is_rejected(v, 200) && !h.is_rejected(v, 6));
        assert!(!h.is_rejected(l.param(1), 200));
        let x = |r: &Row| r.iteration as f64;
        let (line, bands) = h.decimate(v, 0..400, x, (0.0, 399.0), 50).unwrap();
        let top = line.iter().map(|p| p.1).fold(f64::MIN, f64::max);
        assert!(top < 100.0, "{top}");
        assert!(bands.iter().all(|b| b.2 < 100.0));
        let (marks, _) = h.decimate(rej, 0..400, x, (0.0, 399.0), 50).unwrap();
        let marked: Vec<f64> = marks.iter().map(|p| p.0).collect();
        assert_eq!(marked, vec![5.0, 200.0]);
    }

    /// Issue 25: a run opened after its end has no live scans; the page asks
    /// for the newest iteration's and they become the latest scans.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn scans_asked_for_the_newest_iteration_become_the_latest() {
        let recs = fake_records(6);
        let scans = recs[5].scans.clone();
        let mut h = RunHistory::new();
        assert_eq!(h.missing_latest_scans(), None);
        h.insert(recs.iter().map(|r| r.summary()));
        assert_eq!(h.missing_latest_scans(), Some(5));
        assert!(h.latest_scans().is_none());
        // An older iteration's scans are only inspected.
        h.offer_scans(3, recs[3].scans.clone());
        assert!(h.latest_scans().is_none());
        assert_eq!(h.missing_latest_scans(), Some(5));
        h.offer_scans(5, scans.clone());
        assert_eq!(h.latest_scans().map(|s| s.0), Some(5));
        assert_eq!(h.missing_latest_scans(), None);
        // A live record with scans replaces them as usual.
        let mut next = fake_records(7).pop().unwrap();
        next.iteration = 6;
        h.insert([next]);
        assert_eq!(h.latest_scans().map(|s| s.0), Some(6));
        assert_eq!(h.missing_latest_scans(), None);
    }
}
