//! One iteration's measurement: every cell's `t_sr` and `w` evaluated,
//! the filter rows taught, the in-band decision (which cells count in band,
//! which entries are scanned again before the run stops,
//! [`ArrayRunSettings::confirm_entry_sigma`](super::ArrayRunSettings::confirm_entry_sigma)),
//! the rows that start again (flat, [`ArrayRunSettings::reset_flat_row_fraction`](super::ArrayRunSettings::reset_flat_row_fraction);
//! stalled, [`ArrayRunSettings::reset_stalled_row_after`](super::ArrayRunSettings::reset_stalled_row_after)),
//! and the step that follows.

use std::collections::BTreeMap;

use super::{ArrayRun, ArrayRunError, Scratch, Step, CELL_PARAMETERS};
use crate::fit::evaluate_with;
use crate::protocol::{
    EventKind, IterationRecord, ParameterReport, Response, ScanOutcome, TunerEvent,
};
use crate::sim::array::parameter_name;
use crate::tuner::array::{JointArrayTuner, Measured};
use crate::tuner::in_band::{
    beyond_band, inside_margin, pooled_reading, stays_in_band, to_confirm, within_band, InBandRule,
};
use crate::tuner::shrink::shrunk_residual;
use crate::tuner::stall::StalledRowSource;

impl ArrayRun {
    /// The value `name` of a scan's answer: fitted from raw traces with
    /// the cell's references, or as a lab's own analysis evaluated it.
    pub(super) fn evaluate(&self, cell: usize, answer: &Response, name: &str) -> Option<Measured> {
        let Response::Scanned { outcome, .. } = answer else {
            return None;
        };
        let fitted;
        let values = match outcome {
            ScanOutcome::Raw { scan } => {
                let references = &self.joint.as_ref()?.lower.get(cell)?.references;
                fitted = evaluate_with(scan, references).ok()?.values;
                &fitted
            }
            ScanOutcome::Evaluated { values } => values,
            ScanOutcome::Failed { .. } => return None,
        };
        values
            .iter()
            .find(|v| v.name == name)
            .filter(|v| v.validate().is_ok())
            .map(|v| (v.value, v.variance))
    }

    pub(super) fn evaluate_measurement(
        &mut self,
        answers: &[Response],
    ) -> Result<(), ArrayRunError> {
        let k = self.sessions.len();
        let band = self.settings.relative_tolerance;
        let skip = match &self.joint {
            Some(j) if j.skip.len() == k => j.skip.clone(),
            _ => vec![false; k],
        };
        let measured: Vec<usize> = (0..k).filter(|&c| !skip[c]).collect();
        let repeats = self
            .joint
            .as_ref()
            .map(|j| j.repeats.clone())
            .unwrap_or_default();
        if answers.len() != 2 * measured.len() + repeats.len() {
            return Err(ArrayRunError::Protocol(format!(
                "{} answers to the measurement of {} cells and {} repeated scans",
                answers.len(),
                measured.len(),
                repeats.len()
            )));
        }
        let (first, again) = answers.split_at(2 * measured.len());
        let mut raw: Vec<Vec<Option<Measured>>> = vec![vec![None; 2]; k];
        for (i, a) in first.iter().enumerate() {
            let (c, p) = (measured[i / 2], i % 2);
            match self.evaluate(c, a, CELL_PARAMETERS[p]) {
                Some(v) => raw[c][p] = Some(v),
                None => self.evaluation_failed(c),
            }
        }
        // a lagging parameter's extra readings, pooled with its first
        for (&(c, p), a) in repeats.iter().zip(again) {
            let (c, p) = (c as usize, p);
            match (self.evaluate(c, a, CELL_PARAMETERS[p]), raw[c][p]) {
                (Some(v), Some(r)) => raw[c][p] = Some(pooled_reading(r, v)),
                (Some(v), None) => raw[c][p] = Some(v),
                (None, _) => self.failed_fits += 1,
            }
        }
        self.pool_early(&mut raw, &skip);
        let events = self.skipped_predictions(&skip);
        // values with error bars wider than the band are not acted on
        let values: Vec<Vec<Option<Measured>>> = raw
            .iter()
            .map(|m| {
                m.iter()
                    .map(|x| x.filter(|(p, var)| *p > 0.0 && var.sqrt() <= band * p))
                    .collect()
            })
            .collect();
        let failed: Vec<bool> = raw
            .iter()
            .zip(&skip)
            .map(|(m, &s)| !s && m.iter().any(Option::is_none))
            .collect();
        let unsure: Vec<bool> = values
            .iter()
            .zip(&skip)
            .map(|(m, &s)| !s && m.iter().any(Option::is_none))
            .collect();
        // too uncertain: the sensor may be off its flank too
        if let Some(j) = self.joint.as_mut() {
            for (l, _) in j.lower.iter_mut().zip(&unsure).filter(|(_, &u)| u) {
                l.failed_since_sweep = true;
            }
        }
        let v = self.voltages_mv.clone();
        let estimates = self.filter_estimates(&values);
        for (c, vals) in values.iter().enumerate() {
            if vals.iter().all(Option::is_some) {
                let good = self.cell_voltages(c);
                if let Some(j) = self.joint.as_mut() {
                    j.last_good[c] = good;
                }
            }
            let taught = self.taught(c, vals);
            if let Some(j) = self.joint.as_mut() {
                j.tuner.observe(c, &taught, &v);
            }
        }
        let disturbed = self.disturbed_bystanders();
        let mut residual = vec![vec![None; 2]; k];
        let mut all_in = true;
        let mut confirm = Vec::new();
        let mut reports = Vec::with_capacity(2 * k);
        for c in 0..k {
            let (t_sr, w) = self.targets[c];
            let tv = [t_sr, w];
            if skip[c] {
                // predicted in band with margin (plan_skips): held
                residual[c] = vec![Some(0.0); 2];
            } else {
                // a measured parameter within its band
                let within =
                    |p: usize| values[c][p].is_some_and(|(x, _)| within_band(x, tv[p], band));
                let by_rule = self
                    .settings
                    .in_band
                    .in_band(&values[c], &estimates[c], &tv, band)
                    && (!disturbed[c]
                        || inside_margin(
                            &values[c],
                            &tv,
                            band,
                            self.settings.disturbed_margin_sigma,
                        ));
                let held = !by_rule && self.stays_in_band(c, &values[c], tv);
                let in_band = by_rule || held;
                all_in &= in_band;
                confirm.extend(self.note_in_band(c, &values[c], tv, in_band));
                if held && self.settings.pool_confirmations {
                    // held by the hysteresis alone: confirmed before a stop
                    for p in beyond_band(&values[c], &tv, band) {
                        if !confirm.contains(&(c as u32, p)) {
                            confirm.push((c as u32, p));
                        }
                    }
                }
                let out: Vec<bool> = (0..tv.len())
                    .map(|p| values[c][p].is_some() && !within(p))
                    .collect();
                for (p, m) in values[c].iter().enumerate() {
                    self.note_flat_reset(c, p, *m, tv[p]);
                    if out[p] {
                        self.reset_if_flat(c, p, *m, tv[p]);
                    }
                    if let Some((x, _)) = m {
                        self.reset_if_stalled(c, p, x / tv[p]);
                        self.note_lag(c, p, x / tv[p]);
                    }
                    let hold = in_band && self.settings.hold_in_band;
                    let tuner = self.joint.as_ref().map(|j| &j.tuner);
                    residual[c][p] = m.filter(|(x, _)| *x > 0.0).and_then(|m| {
                        if hold {
                            Some(0.0)
                        } else {
                            self.step_residual(tuner?, c, p, m, tv[p], !out[p])
                        }
                    });
                }
            }
            if let Some(j) = self.joint.as_mut() {
                if j.skips_in_a_row.len() != k {
                    j.skips_in_a_row = vec![0; k];
                }
                j.skips_in_a_row[c] = if skip[c] { j.skips_in_a_row[c] + 1 } else { 0 };
            }
            for (p, name) in CELL_PARAMETERS.iter().enumerate() {
                reports.push(ParameterReport {
                    name: parameter_name(c as u32, name),
                    unit: ["ns", "µV"][p].into(),
                    value: raw[c][p].map(|m| m.0),
                    std: raw[c][p].map(|m| m.1.sqrt()),
                    target: Some(tv[p]),
                    tolerance: Some(band * tv[p]),
                });
            }
        }
        let joint = self.joint()?;
        let record = IterationRecord {
            iteration: self.iteration,
            voltages_mv: v,
            gates: joint.tuner.gates().to_vec(),
            parameters: reports,
            gradients: Vec::new(),
            step_mv: vec![0.0; joint.tuner.gates().len()],
            tuned: all_in,
            lab_seconds: self.lab_seconds,
            scan_counts: BTreeMap::new(),
            failed_evaluations: self.failed_evaluations(),
            scans: Vec::new(),
            events,
            keep: None,
        };
        self.scratch = Scratch {
            residual,
            failed,
            unsure,
            jacobian: None,
            moved_cells: Vec::new(),
            forecast_moved: Vec::new(),
            before_move: BTreeMap::new(),
            before_lines: BTreeMap::new(),
            lines_verified: Vec::new(),
            confirm_round: 0,
            pooled: Vec::new(),
            record: Some(Box::new(record)),
        };
        self.step = self.step_after_measurement(all_in, confirm, &skip)?;
        Ok(())
    }

    /// The step's residual of cell `c`'s parameter `p` read `m` (value and
    /// variance) against `target`: [`JointArrayTuner::residual`], shrunk
    /// toward 0 by [`ArrayRunSettings::shrink_residuals`](super::ArrayRunSettings::shrink_residuals)
    /// with the variance the filter learns from ([`Self::taught`]); under
    /// [`ArrayRunSettings::shrink_in_band_only`](super::ArrayRunSettings::shrink_in_band_only)
    /// only a reading `within` its band.
    fn step_residual(
        &self,
        tuner: &JointArrayTuner,
        c: usize,
        p: usize,
        m: Measured,
        target: f64,
        within: bool,
    ) -> Option<f64> {
        let y = tuner.residual(c, p, m.0, target)?;
        let factor = self.settings.shrink_residuals;
        if factor <= 0.0 || (self.settings.shrink_in_band_only && !within) {
            return Some(y);
        }
        let mut one = vec![None; CELL_PARAMETERS.len()];
        *one.get_mut(p)? = Some(m);
        let (x, var) = self.taught(c, &one)[p]?;
        let var_y = tuner.scale(c, p)?.variance(x, var);
        Some(shrunk_residual(y, var_y, factor))
    }

    /// Cell `cell`'s values as the filter learns from them: under
    /// [`ArrayRunSettings::t_sr_floor_filter_only`](super::ArrayRunSettings::t_sr_floor_filter_only)
    /// the `t_sr` variance as if evaluated with the run's floor
    /// ([`Reference::variance_with_floor`](crate::fit::uncertainty::Reference::variance_with_floor));
    /// else as measured (the floor is in the readings then).
    fn taught(&self, cell: usize, values: &[Option<Measured>]) -> Vec<Option<Measured>> {
        let references = self
            .joint
            .as_ref()
            .and_then(|j| j.lower.get(cell))
            .map(|l| &l.references)
            .filter(|_| self.settings.t_sr_floor_filter_only);
        let floor = self.settings.t_sr_floor;
        values
            .iter()
            .enumerate()
            .map(|(p, m)| {
                m.map(|(x, var)| match references {
                    Some(r) if p == 0 => (x, r.t_sr.variance_with_floor(r.rule, x, var, floor)),
                    _ => (x, var),
                })
            })
            .collect()
    }

    /// A skipped cell's parameters: its predictions, reported as events,
    /// not values ([`ArrayRunSettings::skip_confident_sigma`](super::ArrayRunSettings::skip_confident_sigma)).
    fn skipped_predictions(&self, skip: &[bool]) -> Vec<TunerEvent> {
        let mut events = Vec::new();
        let Some(joint) = &self.joint else {
            return events;
        };
        for c in (0..skip.len()).filter(|&c| skip[c]) {
            for (p, name) in CELL_PARAMETERS.iter().enumerate() {
                if let Some((y, var)) = joint.tuner.predict(c, p, &self.voltages_mv) {
                    let scale = joint.tuner.scale(c, p).unwrap_or_default();
                    let (value, std) = scale.value_and_std(y, var);
                    events.push(TunerEvent {
                        level: "array".into(),
                        kind: EventKind::ConfirmationSkipped {
                            parameter: parameter_name(c as u32, name),
                            predicted: value,
                            std,
                            unit: ["ns", "µV"][p].into(),
                        },
                    });
                }
            }
        }
        events
    }

    /// The filter's estimate of each measured value (per cell and
    /// parameter, in the values' units), from its prediction before this
    /// measurement; `None` throughout under [`InBandRule::Measured`], which
    /// does not use them ([`ArrayRunSettings::in_band`](super::ArrayRunSettings::in_band)).
    fn filter_estimates(&self, values: &[Vec<Option<Measured>>]) -> Vec<Vec<Option<f64>>> {
        values
            .iter()
            .enumerate()
            .map(|(c, cell)| {
                cell.iter()
                    .enumerate()
                    .map(|(p, m)| {
                        let j = self
                            .joint
                            .as_ref()
                            .filter(|_| self.settings.in_band != InBandRule::Measured)?;
                        let measured = (*m)?;
                        let prediction = j.tuner.predict(c, p, &self.voltages_mv)?;
                        j.tuner.estimate(c, p, prediction, measured)
                    })
                    .collect()
            })
            .collect()
    }

    /// Per cell: whether it is a disturbed bystander, judged with
    /// [`ArrayRunSettings::disturbed_margin_sigma`](super::ArrayRunSettings::disturbed_margin_sigma):
    /// its targets not set since the run last stopped tuned, a cell within
    /// one step on the grid whose targets were. All `false` when the
    /// margin is off.
    fn disturbed_bystanders(&self) -> Vec<bool> {
        let k = self.sessions.len();
        if self.settings.disturbed_margin_sigma <= 0.0 {
            return vec![false; k];
        }
        let grid = self.grid();
        (0..k)
            .map(|c| self.is_bystander(c) && grid.within(c, 1).any(|n| !self.is_bystander(n)))
            .collect()
    }

    /// Whether cell `c` is a bystander of the present change: its targets
    /// not set since the run last stopped with every cell in band (a
    /// checkpoint without the flags: every cell counts as changed).
    fn is_bystander(&self, c: usize) -> bool {
        !self.changed_since_stop.get(c).copied().unwrap_or(true)
    }

    /// Whether cell `c` still counts in band on `values` (targets `tv`)
    /// by the verdict's hysteresis ([`stays_in_band`],
    /// [`ArrayRunSettings::stay_in_band_sigma`](super::ArrayRunSettings::stay_in_band_sigma)).
    fn stays_in_band(&self, c: usize, values: &[Option<Measured>], tv: [f64; 2]) -> bool {
        let was_in = self
            .joint
            .as_ref()
            .is_some_and(|j| j.in_band.get(c).copied().unwrap_or(false));
        stays_in_band(
            values,
            &tv,
            self.settings.relative_tolerance,
            was_in,
            self.settings.stay_in_band_sigma,
        )
    }

    /// Cell `c` was measured (`values` against the targets `tv`) and counts
    /// `in_band` or not: remembered, and the parameters to scan again
    /// before the run stops returned as (cell, parameter index): those
    /// near the band's edge of a cell that just entered it
    /// ([`ArrayRunSettings::confirm_entry_sigma`](super::ArrayRunSettings::confirm_entry_sigma)), or of a changed
    /// cell's bystander whether it was in band before or not
    /// ([`ArrayRunSettings::confirm_bystander_sigma`](super::ArrayRunSettings::confirm_bystander_sigma)).
    fn note_in_band(
        &mut self,
        c: usize,
        values: &[Option<Measured>],
        tv: [f64; 2],
        in_band: bool,
    ) -> Vec<(u32, usize)> {
        let k = self.sessions.len();
        let band = self.settings.relative_tolerance;
        let bystander = self.is_bystander(c);
        let Some(j) = self.joint.as_mut() else {
            return Vec::new();
        };
        if j.in_band.len() != k {
            j.in_band = vec![false; k];
        }
        let mut confirm = Vec::new();
        if in_band {
            let by_sigma = self.settings.confirm_bystander_sigma;
            // a bystander near its edge is scanned again whether or
            // not it was in band before: the change's crosstalk and
            // the compensation of it moved it unasked
            let (sigma, was_in) = if bystander && by_sigma > 0.0 {
                (by_sigma, false)
            } else {
                (
                    self.settings.confirm_entry_sigma,
                    j.in_band[c] && !self.settings.confirm_in_band_cells,
                )
            };
            confirm.extend(
                to_confirm(values, &tv, band, was_in, sigma)
                    .into_iter()
                    .map(|p| (c as u32, p)),
            );
        }
        j.in_band[c] = in_band;
        confirm
    }

    /// After the measurement: lines to verify or entries to confirm when
    /// every cell counts in band (the record not tuned until they are
    /// done), the iteration's end when none, a move otherwise.
    fn step_after_measurement(
        &mut self,
        all_in: bool,
        confirm: Vec<(u32, usize)>,
        skip: &[bool],
    ) -> Result<Step, ArrayRunError> {
        let verify = if all_in {
            self.lines_to_verify(skip)
        } else {
            Vec::new()
        };
        if all_in && (!verify.is_empty() || !confirm.is_empty()) {
            if let Some(r) = self.scratch.record.as_mut() {
                r.tuned = false;
            }
        }
        Ok(if all_in && !verify.is_empty() {
            Step::VerifyLines(verify, confirm)
        } else if all_in && !confirm.is_empty() {
            Step::Confirm(confirm)
        } else if all_in {
            Step::Boundary
        } else {
            self.step_to_move()?
        })
    }

    /// The step after a measurement that left cells out of band: the
    /// oracle's Jacobian, or the first move planned with the learned one.
    fn step_to_move(&mut self) -> Result<Step, ArrayRunError> {
        Ok(if self.oracle {
            Step::Oracle
        } else {
            self.scratch.jacobian = Some(self.joint()?.tuner.jacobian());
            Step::Move(0)
        })
    }

    /// The answers to [`Step::Confirm`]'s scans: the iteration is tuned when
    /// each confirms its parameter in band (a value whose error bar fits
    /// the band, within it; under
    /// [`ArrayRunSettings::pool_confirmations`](super::ArrayRunSettings::pool_confirmations)
    /// the readings since the measurement pooled, and one within the band
    /// but near its edge scanned again while
    /// [`ArrayRunSettings::confirm_rounds`](super::ArrayRunSettings::confirm_rounds)
    /// remain). Otherwise a parameter that read out aims at its readings'
    /// mean, its cell counts out of band, and the iteration moves on. Each
    /// scan is reported as an event.
    pub(super) fn confirm_entries(
        &mut self,
        pending: &[(u32, usize)],
        answers: &[Response],
    ) -> Result<(), ArrayRunError> {
        if answers.len() != pending.len() {
            return Err(ArrayRunError::Protocol(format!(
                "{} answers to {} confirming scans",
                answers.len(),
                pending.len()
            )));
        }
        let band = self.settings.relative_tolerance;
        let pool = self.settings.pool_confirmations;
        let last_round = !pool || self.scratch.confirm_round + 1 >= self.settings.confirm_rounds;
        let margin = self.settings.confirm_entry_sigma;
        let mut confirmed = true;
        let mut again = Vec::new();
        let mut events = Vec::with_capacity(pending.len());
        for (&(c, p), a) in pending.iter().zip(answers) {
            let cell = c as usize;
            let (t_sr, w) = self.targets[cell];
            let target = [t_sr, w][p];
            let name = CELL_PARAMETERS[p];
            let m = self.evaluate(cell, a, name);
            if m.is_none() {
                self.evaluation_failed(cell);
            }
            let usable = |(x, var): Measured| x > 0.0 && var.sqrt() <= band * x;
            let verified = self.scratch.lines_verified.contains(&c);
            let first = self
                .scratch
                .record
                .as_ref()
                .and_then(|r| r.parameters.get(2 * cell + p))
                .and_then(|r| Some((r.value?, r.std?.powi(2))));
            // the readings so far at these voltages: pooled in earlier
            // rounds, else the measurement's (not after a line correction)
            let before = self
                .scratch
                .pooled
                .iter()
                .find(|(k, _)| *k == (c, p))
                .map(|&(_, r)| r)
                .or(first.filter(|&r| usable(r) && !verified));
            let judged = match (m.filter(|&r| usable(r)), before) {
                (Some(b), Some(a)) if pool => Some(pooled_reading(a, b)),
                (b, _) => b,
            };
            let inside = judged.is_some_and(|(x, _)| within_band(x, target, band));
            events.push(TunerEvent {
                level: "array".into(),
                kind: EventKind::BandEntryRechecked {
                    parameter: parameter_name(c, name),
                    value: m.map(|(x, _)| x),
                    std: m.map(|(_, var)| var.max(0.0).sqrt()),
                    in_band: inside,
                    unit: ["ns", "µV"][p].into(),
                },
            });
            if inside {
                if let Some((x, var)) = judged.filter(|_| pool) {
                    let near_edge =
                        (x - target).abs() + margin * var.max(0.0).sqrt() > band * target;
                    if near_edge && !last_round {
                        again.push((c, p));
                    }
                    match self.scratch.pooled.iter_mut().find(|(k, _)| *k == (c, p)) {
                        Some(slot) => slot.1 = (x, var),
                        None => self.scratch.pooled.push(((c, p), (x, var))),
                    }
                }
                continue;
            }
            confirmed = false;
            let mean = match (judged, first, m) {
                (Some((x, _)), _, _) if pool && x > 0.0 => Some(x),
                (_, _, Some((b, _))) if b > 0.0 && verified => Some(b),
                (_, Some((a, _)), Some((b, _))) if b > 0.0 => Some(0.5 * (a + b)),
                _ => None,
            };
            // the slot's new value when there is a mean (shrunk with the
            // latest reading's variance: the mean's is smaller)
            let residual = match (mean, m, self.joint.as_ref()) {
                (Some(x), Some((_, var)), Some(j)) => {
                    Some(self.step_residual(&j.tuner, cell, p, (x, var), target, false))
                }
                _ => None,
            };
            if let Some(j) = self.joint.as_mut() {
                if let Some(b) = j.in_band.get_mut(cell) {
                    *b = false;
                }
                if let (Some(r), Some(slot)) = (
                    residual,
                    self.scratch
                        .residual
                        .get_mut(cell)
                        .and_then(|r| r.get_mut(p)),
                ) {
                    *slot = r;
                }
            }
        }
        let more = confirmed && !again.is_empty();
        if let Some(r) = self.scratch.record.as_mut() {
            r.events.extend(events);
            r.tuned = confirmed && !more;
        }
        self.step = if more {
            self.scratch.confirm_round += 1;
            Step::Confirm(again)
        } else if confirmed {
            Step::Boundary
        } else {
            self.step_to_move()?
        };
        Ok(())
    }

    /// Cell `c`'s parameter `p` measured (`m`: value and variance, against
    /// `target`): its flat-row watch notes it
    /// ([`ArrayRunSettings::flat_reset_refuted_sigma`](super::ArrayRunSettings::flat_reset_refuted_sigma)).
    fn note_flat_reset(&mut self, c: usize, p: usize, m: Option<Measured>, target: f64) {
        let band = self.settings.relative_tolerance;
        let sigmas = self.settings.flat_reset_refuted_sigma;
        let k = self.sessions.len();
        let (Some(j), Some((x, var))) = (self.joint.as_mut(), m) else {
            return;
        };
        if j.flat_resets.len() != k {
            j.flat_resets = vec![Default::default(); k];
        }
        j.flat_resets[c][p].note(x / target, var.max(0.0).sqrt() / x, band, sigmas);
    }

    /// Cell `c`'s parameter `p`, measured out of band (`m`: value and
    /// variance, against `target`): its row returns to its prior if its
    /// gradient is flat ([`ArrayRunSettings::reset_flat_row_fraction`](super::ArrayRunSettings::reset_flat_row_fraction)) and
    /// no reset since it was last in band was refuted
    /// ([`ArrayRunSettings::flat_reset_refuted_sigma`](super::ArrayRunSettings::flat_reset_refuted_sigma)).
    fn reset_if_flat(&mut self, c: usize, p: usize, m: Option<Measured>, target: f64) {
        let band = self.settings.relative_tolerance;
        let f = self.settings.reset_flat_row_fraction;
        let k = self.sessions.len();
        let Some(j) = self.joint.as_mut() else { return };
        let Some(step) = j.tuner.cells().get(c).map(|k| k.max_step_mv) else {
            return;
        };
        if j.flat_resets.len() != k {
            j.flat_resets = vec![Default::default(); k];
        }
        let watch = &mut j.flat_resets[c][p];
        if watch.may_reset()
            && j.tuner.row_norm(c, p).is_some_and(|g| g * step < f * band)
            && j.tuner.reset_row(c, p)
        {
            if let Some((x, var)) = m {
                watch.reset_at(x / target, var.max(0.0).sqrt() / x);
            }
        }
    }

    /// Cell `c`'s parameter `p`, measured at `ratio` = value/target: its
    /// row starts again if it stalled
    /// ([`ArrayRunSettings::reset_stalled_row_after`](super::ArrayRunSettings::reset_stalled_row_after),
    /// [`ArrayRunSettings::stalled_row_from`](super::ArrayRunSettings::stalled_row_from)).
    fn reset_if_stalled(&mut self, c: usize, p: usize, ratio: f64) {
        let window = self.settings.reset_stalled_row_after;
        if window == 0 {
            return;
        }
        let band = self.settings.relative_tolerance;
        let k = self.sessions.len();
        let Some(j) = self.joint.as_mut().filter(|_| !self.oracle) else {
            return;
        };
        if j.stalls.len() != k {
            j.stalls = vec![Default::default(); k];
        }
        if !j.stalls[c][p].note(ratio, band, window as usize) {
            return;
        }
        match self.settings.stalled_row_from {
            StalledRowSource::Prior => {
                j.tuner.reset_row(c, p);
            }
            StalledRowSource::Widened => {
                j.tuner.widen_row(c, p);
            }
            StalledRowSource::Peers => {
                let in_band: Vec<usize> = (0..k)
                    .filter(|&o| o != c && j.in_band.get(o).copied().unwrap_or(false))
                    .collect();
                let peers = if in_band.is_empty() {
                    (0..k).filter(|&o| o != c).collect()
                } else {
                    in_band
                };
                j.tuner.borrow_row(c, p, &peers);
            }
        }
    }

    /// Cell `c`'s parameter `p` measured at `ratio` = value/target: its
    /// count of measurements in a row out of band on one side
    /// ([`ArrayRunSettings::repeat_lagging_scans`](super::ArrayRunSettings::repeat_lagging_scans)).
    fn note_lag(&mut self, c: usize, p: usize, ratio: f64) {
        let band = self.settings.relative_tolerance;
        let k = self.sessions.len();
        let Some(j) = self.joint.as_mut() else {
            return;
        };
        if j.lags.len() != k {
            j.lags = vec![Default::default(); k];
        }
        j.lags[c][p].note(ratio, band);
    }

    /// The extra scans of the next measurement: each lagging parameter of
    /// a cell that scans ([`ArrayRunSettings::lagging_after`](super::ArrayRunSettings::lagging_after)),
    /// [`ArrayRunSettings::repeat_lagging_scans`](super::ArrayRunSettings::repeat_lagging_scans)
    /// times, cell by cell. Never for the oracle.
    pub(super) fn lagging_repeats(&self, skip: &[bool]) -> Vec<(u32, usize)> {
        let (r, after) = (
            self.settings.repeat_lagging_scans,
            self.settings.lagging_after,
        );
        // the oracle plans with the truth: more readings would not teach it
        let Some(j) = self.joint.as_ref().filter(|_| r > 0 && !self.oracle) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for (c, lags) in j.lags.iter().enumerate() {
            if skip.get(c).copied().unwrap_or(true) {
                continue;
            }
            for (p, lag) in lags.iter().enumerate() {
                if lag.lags(after) {
                    out.extend(std::iter::repeat_n((c as u32, p), r as usize));
                }
            }
        }
        out
    }

    /// An evaluation of cell `c` failed: counted, and its sensor sweeps at
    /// its next park (it may have left its flank).
    pub(super) fn evaluation_failed(&mut self, c: usize) {
        self.failed_fits += 1;
        if let Some(l) = self.joint.as_mut().and_then(|j| j.lower.get_mut(c)) {
            l.failed_since_sweep = true;
            l.failed_evaluations += 1;
        }
    }
}
