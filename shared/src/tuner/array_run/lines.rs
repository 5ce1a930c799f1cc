//! The joint loop's line level: each cell's transition lines scanned,
//! corrected with its line Jacobian (alone or coupled across cells), forecast
//! from the neighbourhood's gates, searched for when lost, and verified
//! before a run stops. Methods of [`ArrayRun`] and the free functions they use.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};

use super::{
    who_scans, AfterPark, ArrayRun, ArrayRunError, CellLower, Joint, LineCorrections, LinePlan,
    Step, MIN_LINE_CHECKS,
};
use crate::protocol::{EventKind, Request, Response, ScanKind, ScanRequest, TunerEvent};
use crate::sim::array::parameter_name;
use crate::tuner::array::{lockstep_factor, Measured};
use crate::tuner::line_steps::joint_line_steps;
use crate::tuner::search::SearchMove;
use crate::tuner::{GradientRow, ParameterForecast};

/// One chemical-potential (transition-line) scan of each of `cells`.
pub(super) fn line_scan_requests(cells: &[u32]) -> Vec<Request> {
    cells
        .iter()
        .map(|&c| Request::Measure {
            scan: ScanRequest {
                kind: ScanKind::ChemicalPotential,
                sweep: None,
                cell: Some(c),
            },
        })
        .collect()
}

impl ArrayRun {
    /// The measured cells (not `skip`ped) whose lines are scanned again
    /// before the run stops ([`ArrayRunSettings::verify_lines_above_mv`](super::ArrayRunSettings::verify_lines_above_mv)).
    pub(super) fn lines_to_verify(&self, skip: &[bool]) -> Vec<u32> {
        let (Some(_), Some(joint)) = (self.settings.verify_lines_above_mv, &self.joint) else {
            return Vec::new();
        };
        joint
            .lower
            .iter()
            .enumerate()
            .filter(|(c, l)| {
                l.lines_unverified
                    && l.line_gates.len() == 2
                    && !skip.get(*c).copied().unwrap_or(true)
            })
            .map(|(c, _)| c as u32)
            .collect()
    }

    /// The answers to [`Step::VerifyLines`]'s scans of `cells`: every
    /// cell's lines learned as in a line round; the cells that lost a line
    /// or found one beyond [`ArrayRunSettings::verify_lines_above_mv`](super::ArrayRunSettings::verify_lines_above_mv) are
    /// corrected and their `t_sr` (and `w`, when line A was off or lost)
    /// joins `pending`'s confirming scans, their readings replacing this
    /// iteration's. None found off: `pending` as it was (or the run stops).
    pub(super) fn lines_verified(
        &mut self,
        cells: &[u32],
        pending: Vec<(u32, usize)>,
        answers: &[Response],
    ) -> Result<(), ArrayRunError> {
        let limit = self.settings.verify_lines_above_mv.unwrap_or(f64::INFINITY);
        let (lines, moved) = self.line_corrections(cells, answers)?;
        // the cells that lost a line: those of `cells` with no lines found
        let found: Vec<u32> = lines.iter().map(|&(c, _)| c).collect();
        let joint = self.joint()?;
        let lost: Vec<u32> = cells
            .iter()
            .copied()
            .filter(|&c| !found.contains(&c) && joint.lower[c as usize].lines_unverified)
            .collect();
        let off: Vec<(u32, [f64; 2])> = lines
            .into_iter()
            .filter(|(_, mu)| mu.iter().any(|m| m.abs() > limit))
            .collect();
        let mut confirm = pending;
        let mut verified = Vec::new();
        for &(c, mu) in &off {
            confirm.push((c, 0));
            if mu[0].abs() > limit {
                confirm.push((c, 1));
            }
            verified.push(c);
        }
        for &c in &lost {
            confirm.extend([(c, 0), (c, 1)]);
            verified.push(c);
        }
        confirm.sort_unstable();
        confirm.dedup();
        let moved: Vec<u32> = moved.into_iter().filter(|c| verified.contains(c)).collect();
        self.scratch.lines_verified = verified;
        self.step = if moved.is_empty() && confirm.is_empty() {
            if let Some(r) = self.scratch.record.as_mut() {
                r.tuned = true;
            }
            Step::Boundary
        } else if moved.is_empty() {
            Step::Confirm(confirm)
        } else {
            Step::VerifySet(off, moved, confirm)
        };
        Ok(())
    }

    /// [`super::Retreat::EveryGateLinesKept`]: the line corrections just answered
    /// (`lines`: the cells corrected from scans that found both lines) shift
    /// those cells' retreat targets by what their plungers moved.
    pub(super) fn keep_line_corrections(&mut self, lines: &[(u32, [f64; 2])]) {
        let before = &self.scratch.before_lines;
        let now = &self.voltages_mv;
        let Some(joint) = self.joint.as_mut() else {
            return;
        };
        for &(c, _) in lines {
            let (Some(l), Some(good)) = (
                joint.lower.get(c as usize),
                joint.last_good.get_mut(c as usize),
            ) else {
                continue;
            };
            for g in &l.line_gates {
                if let (Some(b), Some(n), Some(to)) = (before.get(g), now.get(g), good.get_mut(g)) {
                    *to += n - b;
                }
            }
        }
    }

    /// Before the first line scan: which of `cells` act on their lines'
    /// forecast instead of scanning ([`ArrayRunSettings::line_forecast`](super::ArrayRunSettings::line_forecast);
    /// corrected when it puts a line outside `line_tolerance_mv`), and the
    /// scanning cells whose forecast puts a line beyond
    /// [`ArrayRunSettings::precorrect_lines_mv`](super::ArrayRunSettings::precorrect_lines_mv), corrected from it first.
    pub(super) fn plan_lines(
        &self,
        cells: &[u32],
    ) -> Result<(Vec<Request>, LinePlan), ArrayRunError> {
        let joint = self.joint()?;
        let v = &self.voltages_mv;
        let forecasts: Vec<Option<[Measured; 2]>> = cells
            .iter()
            .map(|&c| {
                if joint.lower[c as usize].lines_missing() {
                    return None;
                }
                let mut f = line_forecast(joint, c as usize, v)?;
                let checks = &joint.lower[c as usize].line_checks;
                let scale = checks.nis_mean().unwrap_or(1.0).max(1.0);
                f.iter_mut().for_each(|m| m.1 *= scale);
                Some(f)
            })
            .collect();
        let confident: Vec<bool> = cells
            .iter()
            .zip(&forecasts)
            .map(|(&c, f)| {
                let l = &joint.lower[c as usize];
                let (Some(skip), Some(f)) = (&self.settings.line_forecast, f) else {
                    return false;
                };
                l.line_gates.len() == 2
                    && l.line_checks.count >= MIN_LINE_CHECKS
                    && l.search.active.is_none()
                    && l.probe_mv.is_none()
                    && l.lines
                        .may_forecast(skip, l.failed_evaluations, self.lab_seconds)
                    && f.iter().all(|&m| skip.confident(Some(m)))
                    // one correction within the step limit reaches the centre
                    && single_line_step(l, f.map(|m| m.0))
                        .is_some_and(|q| q[0].hypot(q[1]) <= self.line_step_limit(l))
            })
            .collect();
        let scan = who_scans(cells, &confident, &self.readout_group);
        let mut plan = LinePlan {
            scan,
            forecast: Vec::new(),
        };
        let mut lines = Vec::new();
        for (&c, f) in cells.iter().zip(forecasts) {
            let Some(f) = f else { continue };
            let mu = f.map(|m| m.0);
            let limit = if plan.scan.contains(&c) {
                match self.settings.precorrect_lines_mv {
                    Some(limit) => limit,
                    None => continue,
                }
            } else {
                plan.forecast.push((c, f));
                self.settings.line_tolerance_mv
            };
            if mu.iter().any(|m| m.abs() > limit) {
                lines.push((c, mu));
            }
        }
        Ok((self.line_steps(joint, &lines), plan))
    }

    /// The line corrections of `plan` are answered: the cells that acted
    /// on their forecast count it (event `measurement_skipped` per line)
    /// and have their sensors parked again when they moved; the others
    /// scan (round 0). Without a cell to scan, the iteration's line
    /// rounds are over.
    pub(super) fn lines_planned(&mut self, plan: LinePlan) {
        let tolerance = self.settings.line_tolerance_mv;
        let mut moved = Vec::new();
        let mut events = Vec::new();
        if let Some(joint) = self.joint.as_mut() {
            for (c, f) in &plan.forecast {
                let l = &mut joint.lower[*c as usize];
                l.lines.skips += 1;
                if f.iter().any(|m| m.0.abs() > tolerance) {
                    moved.push(*c);
                }
                for (name, m) in ["mu_a_mv", "mu_b_mv"].iter().zip(f) {
                    events.push((
                        *c,
                        EventKind::MeasurementSkipped {
                            parameter: parameter_name(*c, name),
                            predicted: m.0,
                            std: m.1.max(0.0).sqrt(),
                            unit: "mV".into(),
                        },
                    ));
                }
            }
        }
        for (c, kind) in events {
            self.note_line_event(c, kind);
        }
        if plan.scan.is_empty() {
            let done = AfterPark::LineRound(Vec::new(), self.settings.line_rounds);
            self.step = Step::ParkSweep(moved, done);
        } else {
            self.scratch.forecast_moved = moved;
            self.step = Step::LineScan(plan.scan, 0);
        }
    }

    /// A line round's answers: every cell's lines learned; the cells whose
    /// lines are outside their band get a limited plunger correction.
    pub(super) fn line_corrections(
        &mut self,
        cells: &[u32],
        answers: &[Response],
    ) -> Result<LineCorrections, ArrayRunError> {
        let mut lines = Vec::new();
        let mut moved = Vec::new();
        let mut quiet = Vec::new();
        let v = self.voltages_mv.clone();
        for (&c, a) in cells.iter().zip(answers) {
            let found = [
                self.evaluate(c as usize, a, "mu_a_mv"),
                self.evaluate(c as usize, a, "mu_b_mv"),
            ];
            let verify = self.settings.verify_lines_above_mv;
            if let Some(l) = self
                .joint
                .as_mut()
                .and_then(|j| j.lower.get_mut(c as usize))
            {
                l.lines_unverified = verify.is_some_and(|limit| {
                    found
                        .iter()
                        .any(|m| m.is_none_or(|(mu, _)| mu.abs() > limit))
                });
            }
            let [Some(a_mv), Some(b_mv)] = found else {
                self.evaluation_failed(c as usize);
                if self.lines_lost(c as usize, found) {
                    moved.push(c);
                }
                continue;
            };
            if let Some(joint) = self.joint.as_mut() {
                observe_lines(joint, c as usize, [a_mv, b_mv], &v, self.lab_seconds);
                let search = &mut joint.lower[c as usize].search;
                search.seen(&[Some(a_mv.0), Some(b_mv.0)]);
                if let Some(probes) = search.found() {
                    self.note_line_event(
                        c,
                        EventKind::SearchEnded {
                            probes,
                            found: true,
                        },
                    );
                }
            }
            let mu = [a_mv.0, b_mv.0];
            if mu
                .iter()
                .all(|m| m.abs() <= self.settings.line_tolerance_mv)
            {
                if self.settings.joint_line_steps
                    && single_line_step(&self.joint()?.lower[c as usize], mu).is_some()
                {
                    quiet.push((c, mu));
                }
                continue;
            }
            if single_line_step(&self.joint()?.lower[c as usize], mu).is_some() {
                lines.push((c, mu));
                moved.push(c);
            }
        }
        // coupled (`quiet` is empty otherwise): a cell in band near one that
        // corrects takes part with its own small offsets, so that the
        // others' steps do not push it out (the cells within two of a
        // correcting one, as the crosstalk reaches)
        let correcting: Vec<u32> = lines.iter().map(|&(c, _)| c).collect();
        let grid = self.grid();
        for (c, mu) in quiet {
            if correcting
                .iter()
                .any(|&k| grid.distance(k as usize, c as usize) <= 2)
            {
                lines.push((c, mu));
                moved.push(c);
            }
        }
        Ok((lines, moved))
    }

    /// A line scan of `cell` lost a line (`found`: what it gave): the line
    /// level's search ([`ParameterSearch`](crate::tuner::ParameterSearch), as a single cell's line level
    /// searches) plans its next probe or its way back. Whether the cell's
    /// plungers move.
    fn lines_lost(&mut self, cell: usize, found: [Option<Measured>; 2]) -> bool {
        let rearm = self.settings.rearm_line_search_after;
        let recentre = self.settings.search_recentres_held_line;
        let Some(l) = self.joint.as_mut().and_then(|j| j.lower.get_mut(cell)) else {
            return false;
        };
        let Some(cfg) = l.line_search.clone() else {
            return false;
        };
        if l.line_gates.len() != 2 || !invertible(&l.line_jacobian) {
            return false;
        }
        l.search.seen(&found.map(|m| m.map(|m| m.0)));
        let missing = found.map(|m| m.is_none());
        if let Some(probes) = l.search.searched_found(&missing) {
            // the probe found the line it looked for and lost the other:
            // the plungers stay, and this scan counts toward the other
            // line's own search (below)
            self.note_line_event(
                cell as u32,
                EventKind::SearchEnded {
                    probes,
                    found: true,
                },
            );
        }
        let Some(l) = self.joint.as_mut().and_then(|j| j.lower.get_mut(cell)) else {
            return false;
        };
        if rearm > 0 {
            l.search.rearm_after(&cfg, rearm);
        }
        let j = l.line_jacobian;
        let jacobian = DMatrix::from_fn(2, 2, |r, s| j[r][s]);
        let Some(next) = l
            .search
            .lost(&cfg, &missing, &[Some(0.0); 2], &jacobian, recentre)
        else {
            return false;
        };
        let (dv, event) = match next {
            SearchMove::Probe {
                probe,
                offsets,
                dv_mv,
            } => (
                dv_mv,
                EventKind::SearchProbe {
                    probe,
                    parameters: ["mu_a_mv", "mu_b_mv"]
                        .iter()
                        .zip(&missing)
                        .filter(|(_, &m)| m)
                        .map(|(p, _)| parameter_name(cell as u32, p))
                        .collect(),
                    offsets: offsets
                        .iter()
                        .zip(&missing)
                        .filter(|(_, &m)| m)
                        .map(|(o, _)| *o)
                        .collect(),
                },
            ),
            SearchMove::GiveUp { probes, dv_mv } => (
                dv_mv,
                EventKind::SearchEnded {
                    probes,
                    found: false,
                },
            ),
        };
        let moves = dv.iter().any(|d| d.abs() > 1e-9);
        l.probe_mv = moves.then_some(dv);
        self.note_line_event(cell as u32, event);
        moves
    }

    /// An event of cell `cell`'s line level in this iteration's record.
    fn note_line_event(&mut self, cell: u32, kind: EventKind) {
        if let Some(record) = self.scratch.record.as_mut() {
            record.events.push(TunerEvent {
                level: format!("c{cell}.lines"),
                kind,
            });
        }
    }

    /// The set that makes cell `cell`'s pending search move (`None`: none).
    /// The line corrections `lines` ((cell, measured line centres in mV))
    /// and then the search probe of every cell in `moved` that has one.
    pub(super) fn line_set_requests(
        &self,
        joint: &Joint,
        lines: &[(u32, [f64; 2])],
        moved: &[u32],
    ) -> Vec<Request> {
        let mut sets = self.line_steps(joint, lines);
        sets.extend(
            moved
                .iter()
                .filter_map(|&c| self.probe_set(joint, c as usize)),
        );
        sets
    }

    fn probe_set(&self, joint: &Joint, cell: usize) -> Option<Request> {
        let l = joint.lower.get(cell)?;
        Some(self.plunger_set(l, l.probe_mv.as_ref()?))
    }

    /// The limited plunger corrections that cancel each cell's `mu` (mV)
    /// with the cell's line Jacobian, as set requests (a cell whose
    /// Jacobian is singular is left out). All cells correct in one batch, so
    /// with [`ArrayRunSettings::joint_line_steps`](super::ArrayRunSettings::joint_line_steps) the steps take out each
    /// other's crosstalk ([`joint_line_steps`]; if that system is singular,
    /// a calibration far beyond physical crosstalk, each cell steps as if
    /// alone); each is then limited to the cell's line step.
    fn line_steps(&self, joint: &Joint, lines: &[(u32, [f64; 2])]) -> Vec<Request> {
        let single: Vec<(usize, Vec<f64>)> = lines
            .iter()
            .filter_map(|&(c, mu)| {
                let q = single_line_step(&joint.lower[c as usize], mu)?;
                Some((c as usize, q.to_vec()))
            })
            .collect();
        let steps = if self.settings.joint_line_steps {
            joint_line_steps(&self.grid(), &single, self.cross_calibration)
        } else if self.settings.couple_line_corrections {
            // the lone lever: the measured Jacobian ÷ the lockstep factor,
            // so each single step × that factor
            let grid = self.grid();
            let lone: Vec<(usize, Vec<f64>)> = single
                .iter()
                .map(|(c, q)| {
                    let f = lockstep_factor(&grid, *c, self.cross_calibration);
                    (*c, q.iter().map(|x| x * f).collect())
                })
                .collect();
            joint_line_steps(&self.grid(), &lone, self.cross_calibration)
        } else {
            None
        }
        .unwrap_or_else(|| single.iter().map(|(_, q)| q.clone()).collect());
        single
            .iter()
            .zip(steps)
            .map(|(&(c, _), mut dp)| {
                let l = &joint.lower[c];
                let norm = dp[0].hypot(dp[1]);
                let limit = self.line_step_limit(l);
                if norm > limit {
                    dp.iter_mut().for_each(|x| *x *= limit / norm);
                }
                self.plunger_set(l, &dp)
            })
            .collect()
    }

    /// Longest line correction of cell `l` per round, mV
    /// ([`ArrayRunSettings::line_max_step_mv`](super::ArrayRunSettings::line_max_step_mv)).
    fn line_step_limit(&self, l: &CellLower) -> f64 {
        self.settings.line_max_step_mv.unwrap_or(l.line_max_step_mv)
    }

    /// The set that moves cell `l`'s line gates by `dv` (mV, in their
    /// order) from where they are, each clipped to its limits and step.
    fn plunger_set(&self, l: &CellLower, dv: &[f64]) -> Request {
        let mut set = BTreeMap::new();
        for (g, d) in l.line_gates.iter().zip(dv) {
            if let Some(&now) = self.voltages_mv.get(g) {
                set.insert(g.clone(), self.limits.clip(g, now, now + d));
            }
        }
        Request::SetVoltages { voltages_mv: set }
    }
}

/// The plunger step (mV per line gate) that cancels the lines' offsets
/// `mu` (mV) with the cell's line Jacobian, `−J⁻¹·μ`, before any limit
/// (`None` if `J` is singular or the cell has no two line gates).
fn single_line_step(l: &CellLower, mu: [f64; 2]) -> Option<[f64; 2]> {
    if !invertible(&l.line_jacobian) || l.line_gates.len() != 2 {
        return None;
    }
    let [[a, b], [c, d]] = l.line_jacobian;
    let det = a * d - b * c;
    Some([
        -(d * mu[0] - b * mu[1]) / det,
        -(-c * mu[0] + a * mu[1]) / det,
    ])
}

/// Whether a line Jacobian (mV/mV) can be inverted.
fn invertible(j: &[[f64; 2]; 2]) -> bool {
    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
    det.is_finite() && det.abs() > 1e-12
}

/// Whether a learned line Jacobian (mV/mV) can be a double dot's: invertible,
/// and each line moving most with its own plunger (`|J_ii| > |J_ij|`; the
/// line level lists its plungers in the lines' order). A finite difference
/// taken while a line was lost gives a near-singular matrix that fails this
/// (seen on random arrays: a row of (−3.2, −18.0) beside (0.34, 1.9), or
/// (15.3, 4.3)); the plausible ones measured there had `|J_ii|` ≥ 2 `|J_ij|`.
fn plausible(j: &[[f64; 2]; 2]) -> bool {
    invertible(j) && j[0][0].abs() > j[0][1].abs() && j[1][1].abs() > j[1][0].abs()
}

/// A cell whose initial measurement never had to move its lines learned no
/// line Jacobian (its line level measures one only when it first corrects),
/// and without one its lines are never corrected again; a cell whose
/// measurement gave an implausible one ([`plausible`]) would correct and
/// search its lines the wrong way for the whole run. Either borrows the
/// mean of the cells whose Jacobian is plausible (cells of one design share
/// their lever arms). Nothing changes when no cell's is plausible (e.g. a
/// description that lists the plungers in the other order).
pub(super) fn borrow_line_jacobians(lower: &mut [CellLower]) {
    let learned: Vec<[[f64; 2]; 2]> = lower
        .iter()
        .filter(|l| l.line_gates.len() == 2 && plausible(&l.line_jacobian))
        .map(|l| l.line_jacobian)
        .collect();
    if learned.is_empty() {
        return;
    }
    let n = learned.len() as f64;
    let mut mean = [[0.0; 2]; 2];
    for j in &learned {
        for (r, row) in j.iter().enumerate() {
            for (s, x) in row.iter().enumerate() {
                mean[r][s] += x / n;
            }
        }
    }
    if !invertible(&mean) {
        return;
    }
    for l in lower
        .iter_mut()
        .filter(|l| l.line_gates.len() == 2 && !plausible(&l.line_jacobian))
    {
        l.line_jacobian = mean;
    }
}

/// The cell's lines `[mu_a, mu_b]` forecast at `v`, each as (mV, variance
/// mV²) (`None` before its first line scan).
fn line_forecast(joint: &Joint, cell: usize, v: &BTreeMap<String, f64>) -> Option<[Measured; 2]> {
    let l = &joint.lower[cell];
    let own = l.line_mv(v);
    let noise = ParameterForecast::default().noise;
    let p = l.lines.predict(&own, v, &line_rows(l), noise)?;
    Some([p.first().copied().flatten()?, p.get(1).copied().flatten()?])
}

/// The cell's line Jacobian as the forecast's own-gate rows.
fn line_rows(l: &CellLower) -> Vec<GradientRow> {
    l.line_jacobian
        .iter()
        .map(|r| (DVector::from_row_slice(r), None))
        .collect()
}

/// A line scan of `cell` at `v`: the forecast learns from it.
fn observe_lines(
    joint: &mut Joint,
    cell: usize,
    mu: [Measured; 2],
    v: &BTreeMap<String, f64>,
    lab_seconds: f64,
) {
    if let Some(predicted) = line_forecast(joint, cell, v) {
        let checks = &mut joint.lower[cell].line_checks;
        for (m, p) in mu.iter().zip(predicted) {
            checks.add(m.0 - p.0, (m.1 + p.1).sqrt());
        }
    }
    let l = &mut joint.lower[cell];
    let rows = line_rows(l);
    let own = l.line_mv(v);
    let noise = ParameterForecast::default().noise;
    l.lines
        .observe(&own, v, &[Some(mu[0]), Some(mu[1])], &rows, noise);
    l.lines.scanned(l.failed_evaluations, lab_seconds);
}
