//! Readings taken in a line round's slack
//! ([`ArrayRunSettings::slack_readings`](super::ArrayRunSettings::slack_readings)).
//!
//! A batch lasts as long as its busiest readout group. In a line round
//! only the cells whose lines are not forecast with confidence scan (a
//! chemical-potential scan, 38 s on the simulator and in the paper), and
//! every other cell's sensor waits that long. A cell that waits has
//! finished its move, its sensor park and its line correction: its `t_sr`
//! and `w` scans (5 + 28 s) can run in that wait at no lab time, and the
//! next measurement's readings of the same cell pool with them (carried
//! along the learned rows across the neighbours' line corrections in
//! between). A `w` scan's σ is about half the ±10 % band; two readings
//! pooled cut it by √2, for the stop rule and for what the rows learn.
//!
//! The run knows no instrument's durations: [`ScanClock`] takes them from
//! the batches it was answered (the shortest time per scan seen), and a
//! cell scans in the slack only where its group's wait holds its two
//! scans by those durations.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::{ArrayRun, CELL_PARAMETERS, CELL_SCANS};
use crate::protocol::Response;
use crate::tuner::array::Measured;
use crate::tuner::in_band::pooled_reading;

/// The shortest lab time seen per scan of each kind, s (the run's only
/// knowledge of its instrument's durations).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct ScanClock {
    /// One cell's `t_sr` and `w` scans together, s.
    pub pair_s: Option<f64>,
    /// One cell's line scan, s.
    pub line_s: Option<f64>,
}

impl ScanClock {
    /// A measurement batch of `busiest` cells' scan pairs in its busiest
    /// group took `seconds`.
    pub fn note_pairs(&mut self, seconds: f64, busiest: usize) {
        note(&mut self.pair_s, seconds, busiest);
    }

    /// A line batch of `busiest` cells' line scans (and nothing else) in
    /// its busiest group took `seconds`.
    pub fn note_lines(&mut self, seconds: f64, busiest: usize) {
        note(&mut self.line_s, seconds, busiest);
    }

    /// How many scan pairs fit beside `own` line scans in a group of a
    /// batch whose busiest group holds `busiest` line scans (0 until both
    /// durations were seen).
    ///
    /// ```
    /// use spintune::tuner::array_run::slack::ScanClock;
    /// let mut clock = ScanClock::default();
    /// assert_eq!(clock.pairs_that_fit(1, 0), 0);
    /// clock.note_pairs(33.0, 1); // w 28 s + t_sr 5 s
    /// clock.note_lines(38.0, 1);
    /// assert_eq!(clock.pairs_that_fit(1, 0), 1); // 33 s within 38 s
    /// assert_eq!(clock.pairs_that_fit(1, 1), 0); // its sensor scans lines
    /// assert_eq!(clock.pairs_that_fit(2, 0), 2); // 66 s within 76 s
    /// ```
    pub fn pairs_that_fit(&self, busiest: usize, own: usize) -> usize {
        match (self.pair_s, self.line_s) {
            (Some(pair), Some(line)) if pair > 0.0 && busiest > own => {
                let wait = (busiest - own) as f64 * line;
                // (a relative allowance for the clock's rounding)
                (wait * (1.0 + 1e-9) / pair).floor() as usize
            }
            _ => 0,
        }
    }
}

fn note(slot: &mut Option<f64>, seconds: f64, count: usize) {
    if count == 0 || !(seconds.is_finite() && seconds > 0.0) {
        return;
    }
    let each = seconds / count as f64;
    *slot = Some(slot.map_or(each, |s| s.min(each)));
}

/// The cells that scan `t_sr` and `w` in a line round's slack: of
/// `waiting` (in order: cells that do not scan their lines and are
/// parked), as many per readout group as its wait holds beside the round's
/// `line_cells`. `group(c)` is cell `c`'s readout group.
///
/// ```
/// use spintune::tuner::array_run::slack::{slack_cells, ScanClock};
/// let clock = ScanClock { pair_s: Some(33.0), line_s: Some(38.0) };
/// // one sensor per cell: every waiting cell fits
/// assert_eq!(slack_cells(&[1], &[0, 2, 3], |c| c as usize, &clock), vec![0, 2, 3]);
/// // cells 0-1 and 2-3 share a sensor: cell 1 scans lines, cell 0 waits
/// // beside it in vain (its sensor is busy); group 1 holds one pair
/// let group = |c: u32| (c / 2) as usize;
/// assert_eq!(slack_cells(&[1], &[0, 2, 3], group, &clock), vec![2]);
/// ```
pub fn slack_cells(
    line_cells: &[u32],
    waiting: &[u32],
    group: impl Fn(u32) -> usize,
    clock: &ScanClock,
) -> Vec<u32> {
    let mut lines: BTreeMap<usize, usize> = BTreeMap::new();
    for &c in line_cells {
        *lines.entry(group(c)).or_default() += 1;
    }
    let busiest = lines.values().copied().max().unwrap_or(0);
    let mut used: BTreeMap<usize, usize> = BTreeMap::new();
    let mut out = Vec::new();
    for &c in waiting {
        let g = group(c);
        let room = clock.pairs_that_fit(busiest, lines.get(&g).copied().unwrap_or(0));
        let n = used.entry(g).or_default();
        if *n < room {
            *n += 1;
            out.push(c);
        }
    }
    out
}

/// A cell's `t_sr` and `w` read in a line round's slack, and the voltages
/// they were read at (every gate, mV).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EarlyReading {
    /// The cell.
    pub cell: u32,
    /// Its readings, in the order of the cell's parameters (`None`: the
    /// fit failed).
    pub values: [Option<Measured>; 2],
    /// Every gate's voltage when they were read, mV.
    pub voltages_mv: BTreeMap<String, f64>,
}

impl ArrayRun {
    /// Cell `c`'s readout group (a group of its own without one).
    fn readout_group_of(&self, c: u32) -> usize {
        match self.readout_group.get(c as usize) {
            Some(&g) if g != usize::MAX => g,
            _ => usize::MAX - 1 - c as usize,
        }
    }

    /// The cells that scan `t_sr` and `w` beside line round `round`'s
    /// line scans of `line_cells`: parked cells that wait (not scanning,
    /// not corrected from their forecast since their park, measured
    /// without doubt this iteration, with a sensing dot), where their
    /// group has the time.
    pub(super) fn plan_slack(&self, line_cells: &[u32], round: u32) -> Vec<u32> {
        let Some(joint) = self.joint.as_ref().filter(|_| self.settings.slack_readings) else {
            return Vec::new();
        };
        let forecast_moved = if round == 0 {
            &self.scratch.forecast_moved[..]
        } else {
            &[]
        };
        let waiting: Vec<u32> = (0..self.sessions.len() as u32)
            .filter(|c| !line_cells.contains(c) && !forecast_moved.contains(c))
            .filter(|&c| !self.scratch.unsure.get(c as usize).copied().unwrap_or(true))
            .filter(|&c| !joint.lower[c as usize].sd_gate.is_empty())
            .collect();
        slack_cells(
            line_cells,
            &waiting,
            |c| self.readout_group_of(c),
            &joint.clock,
        )
    }

    /// A line round's batch is answered: `extra` are the slack cells'
    /// scans (two per cell, after the line scans of `line_cells`), kept
    /// with the voltages now; a round without them times the line scans.
    pub(super) fn slack_answered(&mut self, line_cells: &[u32], extra: &[Response], seconds: f64) {
        let Some(slack) = self.joint.as_mut().map(|j| std::mem::take(&mut j.slack)) else {
            return;
        };
        if slack.is_empty() {
            let busiest = self.busiest(line_cells);
            if let Some(j) = self.joint.as_mut() {
                j.clock.note_lines(seconds, busiest);
            }
            return;
        }
        let mut early = Vec::new();
        for (&c, pair) in slack.iter().zip(extra.chunks(CELL_SCANS.len())) {
            let mut values = [None; 2];
            for (p, a) in pair.iter().enumerate() {
                values[p] = self.evaluate(c as usize, a, CELL_PARAMETERS[p]);
                if values[p].is_none() {
                    self.failed_fits += 1;
                }
            }
            early.push(EarlyReading {
                cell: c,
                values,
                voltages_mv: self.voltages_mv.clone(),
            });
        }
        if let Some(j) = self.joint.as_mut() {
            j.early.extend(early);
        }
    }

    /// The measurement's batch took `seconds`: timed per scan pair when it
    /// held nothing but one pair per measured cell.
    pub(super) fn measure_timed(&mut self, seconds: f64) {
        let Some(j) = self.joint.as_ref() else {
            return;
        };
        if !j.repeats.is_empty() {
            return;
        }
        let measured: Vec<u32> = (0..self.sessions.len() as u32)
            .filter(|&c| !j.skip.get(c as usize).copied().unwrap_or(false))
            .collect();
        let busiest = self.busiest(&measured);
        if let Some(j) = self.joint.as_mut() {
            j.clock.note_pairs(seconds, busiest);
        }
    }

    /// The most of `cells` in one readout group.
    fn busiest(&self, cells: &[u32]) -> usize {
        let mut count: BTreeMap<usize, usize> = BTreeMap::new();
        for &c in cells {
            *count.entry(self.readout_group_of(c)).or_default() += 1;
        }
        count.values().copied().max().unwrap_or(0)
    }

    /// `raw` (per cell and parameter, this measurement's readings) pooled
    /// with the readings of this iteration's slack, each carried to the
    /// voltages now along its learned row; the slack's readings are used
    /// up. A reading this measurement lacks stays lacking (its fit failed:
    /// the sensor may be off its flank).
    pub(super) fn pool_early(&mut self, raw: &mut [Vec<Option<Measured>>], skip: &[bool]) {
        let early = match self.joint.as_mut() {
            Some(j) => std::mem::take(&mut j.early),
            None => return,
        };
        let Some(j) = self.joint.as_ref() else {
            return;
        };
        for e in early {
            let c = e.cell as usize;
            if skip.get(c).copied().unwrap_or(true) {
                continue;
            }
            for (p, v) in e.values.iter().enumerate() {
                let (Some(now), Some(then)) = (raw[c][p], *v) else {
                    continue;
                };
                if let Some(carried) = j.tuner.carry(c, p, then, &e.voltages_mv, &self.voltages_mv)
                {
                    raw[c][p] = Some(pooled_reading(now, carried));
                }
            }
        }
    }
}
