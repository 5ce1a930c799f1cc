//! Re-finding parameters a child level lost (e.g. transition lines that left
//! the line scan's window after a charge rearrangement or a neighbour's move).
//!
//! A scan whose window no longer holds the feature gives no value, and the
//! level's usual answer, a retreat toward its last good gate voltages
//! (qtune's rule), cannot help when the level's own gates never moved: the
//! feature moved by itself. After [`ParameterSearch::after_failures`] such
//! evaluations in a row the level **searches**: it moves its gates so that
//! each lost parameter shifts by `±step`, `±2·step`, … (estimator units,
//! through the level's learned Jacobian, the found parameters held), the
//! first probe against the side the parameter was last seen on, and scans
//! after each probe. The first scan that gives every targeted parameter
//! ends the search (`search_ended`, found) and the level's normal Newton
//! step brings the parameters home; after `max_probes` probes the gates go
//! back by what the search added and the level does not search again until
//! an evaluation works (`search_ended`, not found). Every probe is a move
//! like any other: clipped to the gate limits, split into moves of at most
//! the step limit, checked by the session's guard.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::config_error::ConfigError;

/// Upper bound on [`ParameterSearch::max_probes`].
pub const MAX_SEARCH_PROBES: u32 = 16;

/// How a child level searches for parameters its scans lost.
///
/// ```
/// use spintune::tuner::ParameterSearch;
/// let s = ParameterSearch { step: 4.0, max_probes: 4, after_failures: 2, max_excursion_mv: 40.0 };
/// assert!(s.validate().is_ok());
/// // the probes alternate sides, the first against where the parameter was last seen
/// let offsets: Vec<f64> = (1..=4).map(|k| s.offset(k, -1.0)).collect();
/// assert_eq!(offsets, [-4.0, 4.0, -8.0, 8.0]);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ParameterSearch {
    /// Shift of a lost parameter per probe, estimator units (mV for the
    /// transition lines), 0 < step ≤ 1000. At most the half-width of the
    /// scan's window: consecutive windows then overlap even when the
    /// Jacobian's lever is off by half.
    pub step: f64,
    /// Probes before the search gives up (1..=[`MAX_SEARCH_PROBES`]).
    pub max_probes: u32,
    /// Failed evaluations in a row, with the level's gates where its last
    /// good evaluation left them (nothing to retreat to), before a search
    /// starts (1..=10): one failed fit is usually noise.
    pub after_failures: u32,
    /// Farthest a probe may take the level's gates from where the search
    /// started (norm over the gates, mV; 0 < value ≤ 1000). A probe beyond
    /// it (a Jacobian that says the parameter hardly moves) ends the search.
    pub max_excursion_mv: f64,
}

/// The defaults suit transition lines (mV): step = the half-width of the
/// simulator's ±4 mV line window (consecutive windows touch, and overlap
/// when the plunger lever is underestimated, as a lever borrowed from the
/// other line is); 4 probes reach lines 12 mV off; 2 failures in a row so
/// that a single failed fit (noise) never moves the plungers; 40 mV of
/// plunger covers 12 mV of line down to a lever of 0.3. Set once from the
/// window, not tuned.
impl Default for ParameterSearch {
    fn default() -> Self {
        Self {
            step: 4.0,
            max_probes: 4,
            after_failures: 2,
            max_excursion_mv: 40.0,
        }
    }
}

impl ParameterSearch {
    /// Check the bounds; the error names the field (relative to the level).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.step.is_finite() && self.step > 0.0 && self.step <= 1000.0) {
            return Err(ConfigError::new("search.step", "must be > 0 and ≤ 1000"));
        }
        if !(1..=MAX_SEARCH_PROBES).contains(&self.max_probes) {
            return Err(ConfigError::new(
                "search.max_probes",
                format!("must be 1..={MAX_SEARCH_PROBES}"),
            ));
        }
        if !(self.max_excursion_mv.is_finite()
            && self.max_excursion_mv > 0.0
            && self.max_excursion_mv <= 1000.0)
        {
            return Err(ConfigError::new(
                "search.max_excursion_mv",
                "must be > 0 and ≤ 1000 mV",
            ));
        }
        if !(1..=10).contains(&self.after_failures) {
            return Err(ConfigError::new("search.after_failures", "must be 1..=10"));
        }
        Ok(())
    }

    /// Offset of probe `k` (1-based) from where the search started,
    /// estimator units: `first_sign · step · ⌈k/2⌉`, the sign alternating
    /// with every probe (`first_sign` is ±1).
    pub fn offset(&self, k: u32, first_sign: f64) -> f64 {
        let sign = if k % 2 == 1 { first_sign } else { -first_sign };
        sign * self.step * f64::from(k.div_ceil(2))
    }
}

/// A search under way.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct ActiveSearch {
    /// Probes made so far.
    pub(super) probes: u32,
    /// Per parameter: `Some(first_sign)` if it is searched for, `None` if held.
    pub(super) signs: Vec<Option<f64>>,
    /// What the probes added to the level's gates so far, mV.
    pub(super) applied_mv: Vec<f64>,
    /// Per parameter, the shift every probe gives a held one (estimator
    /// units): 0, or with `recentre_held` its target minus where the scan
    /// that started the search saw it (at most one `step`).
    #[serde(default)]
    pub(super) held: Vec<f64>,
}

/// What a level remembers for searching (part of its serializable state).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub(super) struct SearchMemory {
    /// Failed evaluations in a row with nothing to retreat to.
    pub(super) lost_in_a_row: u32,
    /// A search gave up: none until an evaluation works again (or, where
    /// the level re-arms it, [`SearchMemory::rearm_after`]).
    pub(super) exhausted: bool,
    /// Failed evaluations since the last search gave up.
    #[serde(default)]
    pub(super) lost_since_give_up: u32,
    /// Per parameter, the last value a scan gave (estimator units).
    pub(super) last_seen: Vec<Option<f64>>,
    pub(super) active: Option<ActiveSearch>,
}

/// What the level does after a failed evaluation.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum SearchMove {
    /// Move the level's gates by this much (mV) and scan again.
    Probe {
        probe: u32,
        offsets: Vec<f64>,
        dv_mv: Vec<f64>,
    },
    /// Give up: move back by this much (mV).
    GiveUp { probes: u32, dv_mv: Vec<f64> },
}

impl SearchMemory {
    /// An evaluation gave every targeted parameter: the search (if any) is
    /// over. Returns the number of probes it took, if one was under way.
    pub(super) fn found(&mut self) -> Option<u32> {
        self.lost_in_a_row = 0;
        self.exhausted = false;
        self.lost_since_give_up = 0;
        self.active.take().map(|a| a.probes)
    }

    /// A scan found every parameter the active search looks for while a
    /// held one went missing (the probe moved it out of its window too):
    /// the search ends there, its probes kept (the gates stay where the
    /// searched parameters were found), and whatever is now missing starts
    /// a search of its own after [`ParameterSearch::after_failures`] failed
    /// scans, counted from this one. `missing`: per parameter, whether the
    /// scan lacks it. Returns the probes the ended search took; `None`
    /// (nothing changed) when no search is under way or a searched
    /// parameter is still missing. Without it the search would go on
    /// probing for what it has just found, and give up back where it was
    /// lost.
    pub(super) fn searched_found(&mut self, missing: &[bool]) -> Option<u32> {
        let active = self.active.as_ref()?;
        let searched_found = active
            .signs
            .iter()
            .enumerate()
            .all(|(i, s)| s.is_none() || missing.get(i) == Some(&false));
        if !searched_found {
            return None;
        }
        let probes = active.probes;
        self.active = None;
        self.exhausted = false;
        self.lost_in_a_row = 0;
        self.lost_since_give_up = 0;
        Some(probes)
    }

    /// Remember the values a scan gave (estimator units, parameter order).
    pub(super) fn seen(&mut self, samples: &[Option<f64>]) {
        self.last_seen.resize(samples.len(), None);
        for (s, v) in self.last_seen.iter_mut().zip(samples) {
            if let Some(v) = v.filter(|v| v.is_finite()) {
                *s = Some(v);
            }
        }
    }

    /// Another failed evaluation after a search gave up: at the `after`-th
    /// the give-up ends, and the next [`SearchMemory::lost`] starts a new
    /// search at once (the moves and the drift since may have brought the
    /// parameter within the probes' reach). Call before `lost`. The
    /// single-cell level never re-arms; the array's line level does.
    pub(super) fn rearm_after(&mut self, cfg: &ParameterSearch, after: u32) {
        if !self.exhausted || self.active.is_some() {
            return;
        }
        self.lost_since_give_up += 1;
        if self.lost_since_give_up >= after {
            self.exhausted = false;
            self.lost_since_give_up = 0;
            self.lost_in_a_row = cfg.after_failures.saturating_sub(1);
        }
    }

    /// A targeted parameter is missing and the level has nothing to retreat
    /// to. `missing`: per parameter, whether it is targeted and missing;
    /// `targets`: estimator-space targets; `jacobian`: the level's m×n
    /// Jacobian (estimator units per mV). `recentre_held`: the probes also
    /// bring each held parameter to its target from where the scan that
    /// started the search saw it (at most one `step`), instead of holding
    /// it where it is: a held line near its window's edge is otherwise
    /// pushed out by the first probe whose Jacobian is off. `None`: no
    /// search (yet): the level goes on as without one.
    pub(super) fn lost(
        &mut self,
        cfg: &ParameterSearch,
        missing: &[bool],
        targets: &[Option<f64>],
        jacobian: &DMatrix<f64>,
        recentre_held: bool,
    ) -> Option<SearchMove> {
        let n = jacobian.ncols();
        if self.active.is_none() {
            if self.exhausted {
                return None;
            }
            self.lost_in_a_row += 1;
            if self.lost_in_a_row < cfg.after_failures || !missing.iter().any(|&m| m) {
                return None;
            }
            let signs = missing
                .iter()
                .enumerate()
                .map(|(i, &m)| {
                    m.then(|| {
                        // last seen above its target: it has probably gone further up,
                        // so the first probe shifts it down (and vice versa)
                        let seen = self.last_seen.get(i).copied().flatten();
                        let target = targets.get(i).copied().flatten();
                        match (seen, target) {
                            (Some(s), Some(t)) if s > t => -1.0,
                            _ => 1.0,
                        }
                    })
                })
                .collect();
            let held = (0..missing.len())
                .map(|i| {
                    let seen = self.last_seen.get(i).copied().flatten();
                    let target = targets.get(i).copied().flatten();
                    match (recentre_held && !missing[i], seen, target) {
                        (true, Some(s), Some(t)) => (t - s).clamp(-cfg.step, cfg.step),
                        _ => 0.0,
                    }
                })
                .collect();
            self.active = Some(ActiveSearch {
                probes: 0,
                signs,
                applied_mv: vec![0.0; n],
                held,
            });
        }
        let active = self.active.as_mut()?;
        if active.probes >= cfg.max_probes || active.applied_mv.len() != n {
            return Some(self.give_up());
        }
        let k = active.probes + 1;
        let offsets: Vec<f64> = active
            .signs
            .iter()
            .enumerate()
            .map(|(i, s)| match s {
                Some(sign) => cfg.offset(k, *sign),
                None => active.held.get(i).copied().unwrap_or(0.0),
            })
            .collect();
        let assumed = with_assumed_rows(jacobian, &active.signs);
        let Some(total) = probe_voltages(&assumed, &offsets) else {
            // no usable Jacobian: nothing to search with (the level goes on without)
            if active.probes == 0 {
                self.active = None;
            }
            return None;
        };
        if total.iter().map(|x| x * x).sum::<f64>().sqrt() > cfg.max_excursion_mv {
            if active.probes == 0 {
                // the Jacobian puts even the first probe out of reach: no search
                self.active = None;
                return None;
            }
            return Some(self.give_up());
        }
        let dv_mv: Vec<f64> = total
            .iter()
            .zip(&active.applied_mv)
            .map(|(t, a)| t - a)
            .collect();
        active.probes = k;
        active.applied_mv = total;
        Some(SearchMove::Probe {
            probe: k,
            offsets,
            dv_mv,
        })
    }
}

impl SearchMemory {
    /// End the active search: back by what its probes added; no new search
    /// until an evaluation works.
    fn give_up(&mut self) -> SearchMove {
        let active = self.active.take();
        self.exhausted = true;
        self.lost_in_a_row = 0;
        self.lost_since_give_up = 0;
        SearchMove::GiveUp {
            probes: active.as_ref().map_or(0, |a| a.probes),
            dv_mv: active.map_or_else(Vec::new, |a| a.applied_mv.iter().map(|d| -d).collect()),
        }
    }
}

/// `jacobian` with every searched parameter's unknown row (all zeros: its
/// scans failed from the start, so its gradient was never measured)
/// assumed: parameter `i` responds to the level's gate `i` alone, with the
/// largest lever any known row has (the lines' convention: `lines.gates`
/// lists the plungers in the lines' order). Rows beyond the gates, or with
/// no known row to borrow from, stay zero.
fn with_assumed_rows(jacobian: &DMatrix<f64>, searched: &[Option<f64>]) -> DMatrix<f64> {
    let mut j = jacobian.clone();
    let known = |r: usize| jacobian.row(r).iter().any(|x| *x != 0.0);
    let lever = (0..jacobian.nrows())
        .filter(|&r| known(r))
        .flat_map(|r| jacobian.row(r).iter().map(|x| x.abs()).collect::<Vec<_>>())
        .filter(|x| x.is_finite())
        .fold(0.0, f64::max);
    for (i, s) in searched.iter().enumerate() {
        if s.is_some() && i < j.nrows() && i < j.ncols() && !known(i) && lever > 0.0 {
            j[(i, i)] = lever;
        }
    }
    j
}

/// The minimum-norm gate offset (mV) that shifts the parameters by
/// `offsets` (estimator units) through `jacobian` (m×n): `J⁺·offsets`.
/// `None` if the Jacobian gives no finite, non-zero move.
fn probe_voltages(jacobian: &DMatrix<f64>, offsets: &[f64]) -> Option<Vec<f64>> {
    if jacobian.nrows() != offsets.len() {
        return None;
    }
    let delta = -DVector::from_column_slice(offsets);
    let step = crate::solver::newton_step(
        jacobian,
        &delta,
        &crate::solver::SolverConfig {
            max_step_mv: f64::INFINITY,
            ..crate::solver::SolverConfig::default()
        },
    );
    let dv: Vec<f64> = step.dv_mv.iter().copied().collect();
    // the move must give the intended shifts (a rank-deficient Jacobian may
    // not reach a searched parameter at all)
    let achieved = jacobian * &step.dv_mv;
    let reaches = achieved
        .iter()
        .zip(offsets)
        .all(|(a, o)| (a - o).abs() <= 1e-6 * (1.0 + o.abs()));
    (step.rank > 0 && reaches && dv.iter().all(|x| x.is_finite())).then_some(dv)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> ParameterSearch {
        ParameterSearch {
            step: 6.0,
            max_probes: 4,
            after_failures: 2,
            max_excursion_mv: 100.0,
        }
    }

    #[test]
    fn bounds_name_their_field() {
        for (bad, field) in [
            (ParameterSearch { step: 0.0, ..cfg() }, "search.step"),
            (
                ParameterSearch {
                    step: f64::NAN,
                    ..cfg()
                },
                "search.step",
            ),
            (
                ParameterSearch {
                    max_probes: 0,
                    ..cfg()
                },
                "search.max_probes",
            ),
            (
                ParameterSearch {
                    max_probes: MAX_SEARCH_PROBES + 1,
                    ..cfg()
                },
                "search.max_probes",
            ),
            (
                ParameterSearch {
                    after_failures: 11,
                    ..cfg()
                },
                "search.after_failures",
            ),
            (
                ParameterSearch {
                    max_excursion_mv: 0.0,
                    ..cfg()
                },
                "search.max_excursion_mv",
            ),
        ] {
            assert_eq!(bad.validate().unwrap_err().field, field);
        }
    }

    /// Line A responds 0.5 mV per mV of PA plus 0.1 of PB, line B 0.1 of PA
    /// and 0.4 of PB. Line A was last seen at +3 mV and is lost, line B is
    /// found: the probes shift A by −6, +6, −12, +12 mV and hold B, which by
    /// hand is ΔPA = −6·0.4/0.19, ΔPB = +6·0.1/0.19 for the first (the
    /// inverse of [[0.5, 0.1], [0.1, 0.4]] is [[0.4, −0.1], [−0.1, 0.5]]/0.19).
    #[test]
    fn probes_shift_the_lost_parameter_alternately_and_hold_the_found_one() {
        let j = DMatrix::from_row_slice(2, 2, &[0.5, 0.1, 0.1, 0.4]);
        let mut m = SearchMemory::default();
        m.seen(&[Some(3.0), Some(0.2)]);
        let missing = [true, false];
        let targets = [Some(0.0), Some(0.0)];
        // the first failure is not enough
        assert_eq!(m.lost(&cfg(), &missing, &targets, &j, false), None);
        let mut position = [0.0, 0.0];
        for (k, expected) in [(1, -6.0), (2, 6.0), (3, -12.0), (4, 12.0)] {
            let Some(SearchMove::Probe {
                probe,
                offsets,
                dv_mv,
            }) = m.lost(&cfg(), &missing, &targets, &j, false)
            else {
                panic!("probe {k} expected");
            };
            assert_eq!((probe, offsets.clone()), (k, vec![expected, 0.0]));
            position[0] += dv_mv[0];
            position[1] += dv_mv[1];
            let by_hand = [expected * 0.4 / 0.19, -expected * 0.1 / 0.19];
            for (p, h) in position.iter().zip(by_hand) {
                assert!((p - h).abs() < 1e-9, "{position:?} vs {by_hand:?}");
            }
        }
        // the fifth call gives up and goes back where it started
        let Some(SearchMove::GiveUp { probes, dv_mv }) =
            m.lost(&cfg(), &missing, &targets, &j, false)
        else {
            panic!("give up expected");
        };
        assert_eq!(probes, 4);
        assert!((position[0] + dv_mv[0]).abs() < 1e-9 && (position[1] + dv_mv[1]).abs() < 1e-9);
        // and does not search again until something is found
        for _ in 0..5 {
            assert_eq!(m.lost(&cfg(), &missing, &targets, &j, false), None);
        }
        assert_eq!(m.found(), None);
        assert_eq!(m.lost(&cfg(), &missing, &targets, &j, false), None);
        assert!(matches!(
            m.lost(&cfg(), &missing, &targets, &j, false),
            Some(SearchMove::Probe { probe: 1, .. })
        ));
        assert_eq!(m.found(), Some(1));
    }

    /// Line B is searched for (A held); the third probe finds B but moves A
    /// out of its window. The search ends there with B's probes kept (no
    /// fourth probe away from where B was found, no give-up back to where
    /// it was lost), and A's own search starts after `after_failures`
    /// failed scans counted from that one, shifting A first toward where
    /// it was last seen (above its target: down).
    #[test]
    fn a_probe_that_finds_the_searched_line_and_loses_the_held_one_ends_the_search() {
        let j = DMatrix::from_row_slice(2, 2, &[0.5, 0.1, 0.1, 0.4]);
        let targets = [Some(0.0), Some(0.0)];
        let mut m = SearchMemory::default();
        m.seen(&[Some(1.0), Some(-3.0)]);
        let b_lost = [false, true];
        assert_eq!(m.lost(&cfg(), &b_lost, &targets, &j, false), None);
        for k in 1..=3 {
            assert!(matches!(
                m.lost(&cfg(), &b_lost, &targets, &j, false),
                Some(SearchMove::Probe { probe, .. }) if probe == k
            ));
        }
        // the third probe's scan: B found, A missing
        let a_lost = [true, false];
        m.seen(&[None, Some(-0.5)]);
        assert_eq!(
            m.searched_found(&b_lost),
            None,
            "B still missing: nothing ends"
        );
        assert_eq!(m.searched_found(&a_lost), Some(3));
        assert_eq!(m.searched_found(&a_lost), None, "ended once");
        // this scan counts as A's first failure; the next starts A's search
        assert_eq!(m.lost(&cfg(), &a_lost, &targets, &j, false), None);
        let Some(SearchMove::Probe { probe, offsets, .. }) =
            m.lost(&cfg(), &a_lost, &targets, &j, false)
        else {
            panic!("A's search expected");
        };
        assert_eq!(probe, 1);
        assert_eq!(offsets, vec![-cfg().step, 0.0]);
    }

    /// With `recentre_held`, the probes also bring the held line B from
    /// where the search's first scan saw it (+2.5 mV) to its target (0):
    /// every probe's total shift is (±6·⌈k/2⌉, −2.5), so by hand (the
    /// inverse above) the first probe's move is ΔPA = (0.4·−6 − 0.1·−2.5)/0.19,
    /// ΔPB = (−0.1·−6 + 0.5·−2.5)/0.19, and the second's total (+6, −2.5)
    /// moves B by nothing more. A held shift is at most one step.
    #[test]
    fn recentring_probes_bring_the_held_line_to_its_target() {
        let j = DMatrix::from_row_slice(2, 2, &[0.5, 0.1, 0.1, 0.4]);
        let targets = [Some(0.0), Some(0.0)];
        let missing = [true, false];
        let mut m = SearchMemory::default();
        m.seen(&[Some(3.0), Some(2.5)]);
        assert_eq!(m.lost(&cfg(), &missing, &targets, &j, true), None);
        let mut position = [0.0, 0.0];
        for (k, a) in [(1, -6.0), (2, 6.0)] {
            let Some(SearchMove::Probe {
                probe,
                offsets,
                dv_mv,
            }) = m.lost(&cfg(), &missing, &targets, &j, true)
            else {
                panic!("probe {k} expected");
            };
            assert_eq!((probe, offsets), (k, vec![a, -2.5]));
            position[0] += dv_mv[0];
            position[1] += dv_mv[1];
            let by_hand = [
                (0.4 * a - 0.1 * -2.5) / 0.19,
                (-0.1 * a + 0.5 * -2.5) / 0.19,
            ];
            for (p, h) in position.iter().zip(by_hand) {
                assert!((p - h).abs() < 1e-9, "{position:?} vs {by_hand:?}");
            }
            // what the probes did to B in total: its target minus where it was seen
            let shift_b = 0.1 * position[0] + 0.4 * position[1];
            assert!((shift_b + 2.5).abs() < 1e-9, "{shift_b}");
        }
        let mut far = SearchMemory::default();
        far.seen(&[Some(3.0), Some(9.0)]);
        let _ = far.lost(&cfg(), &missing, &targets, &j, true);
        let Some(SearchMove::Probe { offsets, .. }) =
            far.lost(&cfg(), &missing, &targets, &j, true)
        else {
            panic!("a probe expected");
        };
        assert_eq!(offsets, vec![-6.0, -cfg().step]);
    }

    /// Line A's row was never measured (its scans failed from the start);
    /// line B's is [0.18, 0.67]: line A is assumed to move 0.67 mV per mV
    /// of PA alone, so a +6 mV probe moves PA by 6/0.67 mV and PB not at all
    /// (line B held: 0.18·ΔPA + 0.67·ΔPB = 0 → ΔPB = −0.18/0.67·ΔPA; by hand
    /// with the assumed row [0.67, 0]: ΔPA = 6/0.67 · 1, ΔPB = −0.18·ΔPA/0.67).
    #[test]
    fn an_unmeasured_row_is_assumed_on_its_own_gate() {
        let j = DMatrix::from_row_slice(2, 2, &[0.0, 0.0, 0.18, 0.67]);
        let mut m = SearchMemory::default();
        m.seen(&[None, Some(0.0)]);
        let search = ParameterSearch {
            after_failures: 1,
            ..cfg()
        };
        let Some(SearchMove::Probe { dv_mv, .. }) =
            m.lost(&search, &[true, false], &[Some(0.0); 2], &j, false)
        else {
            panic!("a probe expected");
        };
        let pa = 6.0 / 0.67;
        let pb = -0.18 * pa / 0.67;
        assert!(
            (dv_mv[0] - pa).abs() < 1e-9 && (dv_mv[1] - pb).abs() < 1e-9,
            "{dv_mv:?}"
        );
    }

    /// A lever of 0.01 mV/mV would take the plungers 600 mV for the first
    /// probe: no search. With 0.5 the third probe (12 mV → 24 mV of gate)
    /// is beyond an excursion of 20 mV: the search gives up after two.
    #[test]
    fn probes_never_go_beyond_the_excursion_limit() {
        let search = ParameterSearch {
            after_failures: 1,
            max_excursion_mv: 20.0,
            ..cfg()
        };
        let weak = DMatrix::from_row_slice(1, 1, &[0.01]);
        let mut m = SearchMemory::default();
        assert_eq!(m.lost(&search, &[true], &[Some(0.0)], &weak, false), None);
        assert!(m.active.is_none());
        let j = DMatrix::from_row_slice(1, 1, &[0.5]);
        let mut m = SearchMemory::default();
        let mut at = 0.0;
        for _ in 0..2 {
            let Some(SearchMove::Probe { dv_mv, .. }) =
                m.lost(&search, &[true], &[Some(0.0)], &j, false)
            else {
                panic!("probe expected");
            };
            at += dv_mv[0];
            assert!(at.abs() <= 20.0);
        }
        let Some(SearchMove::GiveUp { probes, dv_mv }) =
            m.lost(&search, &[true], &[Some(0.0)], &j, false)
        else {
            panic!("give up expected");
        };
        assert_eq!(probes, 2);
        assert!((at + dv_mv[0]).abs() < 1e-9);
    }

    #[test]
    fn no_search_without_a_usable_jacobian() {
        let mut m = SearchMemory::default();
        let zero = DMatrix::zeros(2, 2);
        assert_eq!(
            m.lost(&cfg(), &[true, true], &[Some(0.0); 2], &zero, false),
            None
        );
        assert_eq!(
            m.lost(&cfg(), &[true, true], &[Some(0.0); 2], &zero, false),
            None
        );
    }

    /// A search that gave up stays given up (the single-cell rule) until
    /// `rearm_after` has counted `after` more failures: then the very next
    /// failure starts a new search (its first probe), as the first search
    /// started after `after_failures` (2) failures in a row.
    #[test]
    fn a_given_up_search_is_rearmed_after_that_many_failures() {
        let j = DMatrix::from_row_slice(2, 2, &[0.5, 0.1, 0.1, 0.4]);
        let lost =
            |m: &mut SearchMemory| m.lost(&cfg(), &[true, false], &[Some(0.0); 2], &j, false);
        let mut m = SearchMemory::default();
        assert_eq!(lost(&mut m), None);
        for _ in 0..4 {
            assert!(matches!(lost(&mut m), Some(SearchMove::Probe { .. })));
        }
        assert!(matches!(
            lost(&mut m),
            Some(SearchMove::GiveUp { probes: 4, .. })
        ));
        assert!(m.exhausted);
        // given up: without a re-arm, no search however long it stays lost
        let mut never = m.clone();
        for _ in 0..10 {
            assert_eq!(lost(&mut never), None);
        }
        for _ in 0..2 {
            m.rearm_after(&cfg(), 3);
            assert_eq!(lost(&mut m), None);
        }
        m.rearm_after(&cfg(), 3);
        assert!(!m.exhausted);
        assert!(matches!(
            lost(&mut m),
            Some(SearchMove::Probe { probe: 1, .. })
        ));
        // a scan that works ends it all, the count since giving up too
        m.found();
        assert_eq!(
            (m.lost_in_a_row, m.lost_since_give_up, m.exhausted),
            (0, 0, false)
        );
    }
}
