//! Why an in-browser run is not tuning, in words a student can act on
//! ([`why_not_tuned`]): read from the settings and what the run recorded
//! (steps, rejected measurements), never from the simulator's truth.

use super::settings::LocalSettings;
use crate::history::RunHistory;

/// Iterations without tuning before the page explains.
pub const PATIENCE: usize = 15;
/// The recent iterations the explanation looks at.
const RECENT: usize = 10;

/// The recent iterations whose steps say whether the gates froze.
const RECENT_STEPS: usize = 5;

/// Largest |entry| of the virtual-gate matrix (mV/mV) that still counts as plausible.
const LARGE_COMPENSATION: f64 = 10.0;

/// `None` while the run is tuned or young (< [`PATIENCE`] iterations since
/// the targets were last set); else a sentence saying that it does not
/// converge and the likely reasons: the steps are limited to (almost)
/// zero (e.g. a huge virtual-gate matrix entry), most measurements are too
/// uncertain to act on (noise against the tolerance band), Q = 0 (the filter
/// stops learning).
pub fn why_not_tuned(
    settings: &LocalSettings,
    history: &RunHistory,
    tuned_at: Option<u64>,
    since: u64,
) -> Option<String> {
    if tuned_at.is_some() {
        return None;
    }
    let rows = history.rows();
    let young = rows.iter().filter(|r| r.iteration >= since).count();
    if young < PATIENCE {
        return None;
    }
    let l = history.layout();
    let recent = rows.len().saturating_sub(RECENT)..rows.len();
    let mut reasons = Vec::new();
    // Steps: the largest gate step of the last few iterations.
    let last_steps = rows.len().saturating_sub(RECENT_STEPS)..rows.len();
    let largest_step = (0..l.gates.len())
        .flat_map(|g| history.column(l.gate(g) + 1)[last_steps.clone()].iter())
        .filter(|x| x.is_finite())
        .fold(0.0f64, |m, x| m.max(x.abs()));
    let biggest_cell = settings
        .compensation
        .iter()
        .flatten()
        .fold(0.0f64, |m, x| m.max(x.abs()));
    let rejected = (0..l.parameters.len())
        .map(|p| {
            history.column(l.rejected(p))[recent.clone()]
                .iter()
                .filter(|x| x.is_finite())
                .count()
        })
        .max()
        .unwrap_or(0);
    let mostly_rejected = rejected * 2 >= recent.len();
    if mostly_rejected {
        reasons.push(format!(
            "{rejected} of the last {} measurements were too uncertain to act on (their error bars are wider than the ±{:.0} % tolerance band): the measurement noise (× {}) is too large for this tolerance",
            recent.len(),
            100.0 * settings.tolerance,
            settings.noise_scale
        ));
    }
    // Frozen because nothing is acted on: the sentence above says why.
    if largest_step < 0.05 * settings.max_step_mv
        && (biggest_cell > LARGE_COMPENSATION || !mostly_rejected)
    {
        let why = if biggest_cell > LARGE_COMPENSATION {
            format!(
                "a virtual-gate matrix entry of {biggest_cell} mV/mV makes every gate step move a plunger {biggest_cell} times as far, so the step limit cuts each step to almost nothing (the paper's entries are below 1)"
            )
        } else {
            "the Newton step is (almost) zero: the filter's gradient says no move helps, or the step limit is tiny".to_string()
        };
        reasons.push(format!(
            "the gates have nearly stopped (no step above {:.2} mV in the last {RECENT_STEPS} iterations): {why}",
            largest_step
        ));
    }
    if settings.q_tsr == 0.0 || settings.q_w == 0.0 {
        reasons.push(
            "Q σ = 0: the filter never forgets, so once its error bars are small it stops correcting a wrong gradient and the steps keep missing"
                .to_string(),
        );
    }
    if reasons.is_empty() {
        reasons.push(
            "the tuner is not converging: try a smaller step limit, a larger Q σ or less noise"
                .to_string(),
        );
    }
    Some(format!(
        "Not tuned after {young} iterations. Likely why: {}.",
        reasons.join("; ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::local::LocalRunner;

    fn run(settings: &LocalSettings, n: usize) -> (RunHistory, Option<u64>) {
        let mut r = LocalRunner::new(settings).unwrap();
        let mut h = RunHistory::new();
        for _ in 0..n {
            if r.advance(&mut h).ok().flatten().is_none() {
                break;
            }
        }
        (h, r.tuned_at)
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn noise_and_q_zero_are_named_when_the_run_does_not_tune() {
        // the paper's rule, as in the report: the recommended rule's trust
        // region gets there (slowly) even so
        let s = LocalSettings {
            rule: crate::local::settings::Rule::Paper,
            q_tsr: 0.0,
            q_w: 0.0,
            noise_scale: 10.0,
            max_iterations: 25,
            ..LocalSettings::default()
        };
        let (h, tuned) = run(&s, 25);
        let why = why_not_tuned(&s, &h, tuned, 0);
        assert_eq!(tuned, None, "tuned with noise × 10 and Q = 0?");
        let why = why.expect("an explanation after 25 iterations");
        assert!(why.starts_with("Not tuned after 25 iterations"), "{why}");
        assert!(why.contains("too uncertain to act on"), "{why}");
        assert!(why.contains("noise (× 10)"), "{why}");
        assert!(why.contains("Q σ = 0"), "{why}");
        assert!(!why.contains("nearly stopped"), "{why}");
        // Young runs and tuned runs get no explanation.
        assert_eq!(why_not_tuned(&s, &h, Some(3), 0), None);
        assert_eq!(why_not_tuned(&s, &h, None, 20), None);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_huge_matrix_entry_that_freezes_the_gates_is_named() {
        let mut s = LocalSettings {
            max_iterations: 20,
            ..LocalSettings::default()
        };
        s.compensation[0][0] = 1000.0;
        let (h, tuned) = run(&s, 20);
        assert_eq!(tuned, None, "tuned with a frozen tuner?");
        let why = why_not_tuned(&s, &h, tuned, 0).expect("an explanation");
        assert!(why.contains("nearly stopped"), "{why}");
        assert!(why.contains("1000 mV/mV"), "{why}");
    }
}
