//! The default gate set of the simulated double dot.

use crate::safety::GateSpec;

/// The default gates with limits (mV), step limits (mV per set command) and
/// the documented start point (`initial_mv`).
///
/// | gates | role | start (mV) | limits | max step |
/// |---|---|---|---|---|
/// | N, T, SA, SB | tuning | −700, −650, −820, −780 | start ± 200 | 10 mV |
/// | PA, PB | plungers | −300, −320 | start ± 250 | 30 mV |
/// | SD1, SP, SD2 | sensing dot | −600, −500, −620 | start ± 150 | 30 mV |
/// | RFA, RFB | fast scan gates | 0, 0 | ± 50 | 5 mV |
///
/// At this start point the default [`crate::sim::DeviceConfig`] gives
/// t_sr = 45 ns and w ≈ 210 µV (not yet at the paper's first target
/// t_sr = 20 ns, w = 270 µV, which lies well inside the limits), the sensing
/// dot sits on the steepest flank of its highest peak and both transition
/// lines are at 0 mV.
///
/// ```
/// let gates = spintune::sim::default_gates();
/// assert_eq!(gates.len(), 11);
/// let n = gates.iter().find(|g| g.name == "N").unwrap();
/// assert_eq!((n.initial_mv, n.max_step_mv), (-700.0, 10.0));
/// assert!(gates.iter().all(|g| g.min_mv < g.initial_mv && g.initial_mv < g.max_mv));
/// ```
pub fn default_gates() -> Vec<GateSpec> {
    let gate = |name: &str, initial_mv: f64, half_range_mv: f64, max_step_mv: f64| GateSpec {
        name: name.into(),
        min_mv: initial_mv - half_range_mv,
        max_mv: (initial_mv + half_range_mv).min(if initial_mv < 0.0 { 0.0 } else { f64::MAX }),
        max_step_mv,
        initial_mv,
    };
    vec![
        gate("N", -700.0, 200.0, 10.0),
        gate("T", -650.0, 200.0, 10.0),
        gate("SA", -820.0, 200.0, 10.0),
        gate("SB", -780.0, 200.0, 10.0),
        gate("PA", -300.0, 250.0, 30.0),
        gate("PB", -320.0, 250.0, 30.0),
        gate("SD1", -600.0, 150.0, 30.0),
        gate("SP", -500.0, 150.0, 30.0),
        gate("SD2", -620.0, 150.0, 30.0),
        gate("RFA", 0.0, 50.0, 5.0),
        gate("RFB", 0.0, 50.0, 5.0),
    ]
}
