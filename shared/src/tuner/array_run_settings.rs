//! [`ArrayRunSettings`]: the joint array loop's settings (every key of a
//! run config's `[array.tuning]` table), their defaults and bounds, and
//! [`Retreat`], the rule a cell whose evaluation failed moves back by.
//! Plain data; the loop that reads them is [`super::array_run::ArrayRun`].

use serde::{Deserialize, Serialize};

use super::in_band::InBandRule;
use super::lagging::{MAX_LAGGING_AFTER, MAX_REPEATS};
use super::shrink::MAX_SHRINK;
use super::stall::{StalledRowSource, MAX_STALL_WINDOW};
use crate::config_error::ConfigError;
use crate::tuner::array::JointConfig;
use crate::tuner::{FlankPrediction, ParameterForecast};

/// Settings of the joint loop (bounded; [`ArrayRunSettings::validate`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayRunSettings {
    /// Relative band of `t_sr` and `w` (0 < b ≤ 0.5). Default 0.1.
    pub relative_tolerance: f64,
    /// The joint tuner's settings.
    #[serde(default)]
    pub joint: JointConfig,
    /// Line re-centring rounds after a joint move, 0..=5. Default 1.
    pub line_rounds: u32,
    /// Limited joint moves per measurement (the later ones while a cell's
    /// predicted residual is still beyond half its band), 1..=4. Default 1.
    pub moves_per_iteration: u32,
    /// Band of the lines, mV (0 < b ≤ 1). Default 0.1.
    pub line_tolerance_mv: f64,
    /// Whether the line level treats the cells as coupled: each cell's line
    /// Jacobian, measured while every cell moved its plungers in lockstep,
    /// is divided by its lockstep factor
    /// ([`crate::tuner::array::lockstep_factor`]), and the cells that
    /// correct their lines in one batch take out the crosstalk of each
    /// other's plunger steps ([`joint_line_steps`](super::line_steps::joint_line_steps)), both with the lab's
    /// cross-cell calibration `λ̂`; a cell whose lines are in band within
    /// two cells of one that corrects takes part with its own offsets (a
    /// small step that keeps it in band). `false`: each cell corrects as if
    /// alone with the Jacobian as measured. Default `true`, together with
    /// the 10 mV [`Self::line_max_step_mv`] that lets its steps through
    /// (docs/array-history.md, "Line steps that are not cut"); with the old 4 mV
    /// limit it was no better (docs/array-history.md, "The line level, coupled").
    #[serde(default = "default_joint_line_steps")]
    pub joint_line_steps: bool,
    /// Solve the line corrections of one batch together, as
    /// [`Self::joint_line_steps`] does ([`joint_line_steps`](super::line_steps::joint_line_steps): each step
    /// takes out the crosstalk of the others), with each cell's lone lever
    /// (its line Jacobian as measured divided by its lockstep factor,
    /// [`crate::tuner::array::lockstep_factor`]), but for those steps only:
    /// the lines' forecast, the pre-correction and the line search keep
    /// the Jacobian as measured, and cells in band do not take part. A
    /// cell correcting alone otherwise moves its lines by 1/1.7 of what it
    /// asks in mid-chain, and its neighbours' corrections in the same batch
    /// push it by their crosstalk (docs/array-history.md, "Two fresh failures
    /// traced"). No effect when `joint_line_steps` is on (it does this and
    /// more). Default `false`: measured slower on every set (5–9 lab min
    /// per cold start, 1.5–3 per all-cell change), with more neighbours
    /// out and half as many failed fits again (docs/array-history.md, "Line
    /// corrections solved together").
    #[serde(default)]
    pub couple_line_corrections: bool,
    /// Before a cell's line scan, correct its plungers from the lines'
    /// forecast when it puts a line beyond this, mV (0 < value ≤ 4, the
    /// scan's half-window; `None`: never). Default 1: chosen on random
    /// arrays (docs/array-history.md, "Lines corrected before their scan").
    /// Never while the cell's lines count as lost by its line search's rule
    /// (a lost line's forecast starts from a scan made before the loss).
    #[serde(default)]
    pub precorrect_lines_mv: Option<f64>,
    /// Longest plunger correction of a cell's lines per line round, mV
    /// (norm over its two plungers; 0 < value ≤ 10; each gate's own
    /// `max_step_mv` still applies). `None`: the step limit of the cell
    /// tuner's line level (2 mV in the recommended tuner). Default 10: a
    /// line the scan sees (within its ±4 mV half-window) comes back to its
    /// centre in one correction even where the cell's two lines respond to
    /// its plungers nearly alike, and a line 2–3 mV off asks for 10–18 mV
    /// of plunger (docs/array-history.md, "Line steps that are not cut"; the
    /// earlier 4 mV cut those corrections to a quarter). With 2 mV a line
    /// found 3 mV off was still off at the next measurement, which then
    /// failed or read `t_sr` long, and the cell's retreat undid the
    /// correction (docs/array-history.md, "Lines brought back in one step").
    #[serde(default = "default_line_max_step_mv")]
    pub line_max_step_mv: Option<f64>,
    /// A cell's line search that gave up starts again after this many more
    /// line scans that lost a line (0..=30; 0: never, the single-cell line
    /// level's rule). Default 3: one more than the failures in a row that
    /// start a search (`ParameterSearch::after_failures`, 2); set once,
    /// not tuned. While a line is lost the cell's lines' forecast is not
    /// acted on (it starts from a scan made before the loss), so without a
    /// new search nothing would bring the line back; the moves and drift
    /// since the last search may have brought it within the probes' reach
    /// (docs/array-history.md, "A lost line: no forecast, a new search").
    #[serde(default = "default_rearm_line_search_after")]
    pub rearm_line_search_after: u32,
    /// A cell's line search also brings the line it holds back to its
    /// window's centre from where the scan that started the search saw it
    /// (at most one probe step), instead of holding it where it is. A held
    /// line near its window's edge is otherwise pushed out by the first
    /// probe whose 2×2 line Jacobian is off, and two searches can undo each
    /// other for the rest of the run (docs/array-history.md, "A probe that
    /// finds its line ends the search", on a 2×4 ladder). On by default
    /// since the seventeenth round ("A line search that re-centres the line
    /// it holds"): on 72 ladder runs 7 lab min less per run and 2 phases
    /// unconverged where the oracle converged against 7; on 84 chain runs
    /// lab time unchanged, 11 such phases against 19. `false`: the
    /// single-cell line level's rule (the held line stays where it is).
    #[serde(default = "yes")]
    pub search_recentres_held_line: bool,
    /// Before the run stops with every cell measured in band, each measured
    /// cell whose last line scan found a line farther than this from its
    /// centre, mV, or lost one, scans its lines again where they are
    /// (0 < value ≤ 4, the scan's half-window, and at least
    /// `line_tolerance_mv`; `None`: never). A cell
    /// found off by more than this again is corrected (one line step) and
    /// its `t_sr` (and `w` when line A was off) scanned again: the run
    /// stops only if those readings are in band too. Why: the load curve
    /// reads `t_sr` long by a factor that grows with the square of line
    /// B's offset at it, and a cell correcting alone among neighbours that
    /// also correct keeps part of its offset (docs/array-history.md, "Lines
    /// checked before a run stops"); the in-band verdict that ends a
    /// change is then taken on lines known to be near their centre.
    #[serde(default = "default_verify_lines_above_mv")]
    pub verify_lines_above_mv: Option<f64>,
    /// Correct a cell's lines from their forecast instead of scanning them
    /// (the single-cell line level's rule, [`ParameterForecast`]: both
    /// lines predicted within `skip_std` mV, fewer than `max_skips`
    /// forecasts in a row, no failed evaluation of the cell since its last
    /// line scan, that scan at most `max_age_s` old; the prediction's
    /// `noise` and prior lever stay the array's own). Beyond it, for an
    /// array: the forecast's variance is scaled by the cell's mean NIS at
    /// its line scans when above 1 ([`ArrayRun::line_forecast_checks`](super::array_run::ArrayRun::line_forecast_checks)), at
    /// least [`MIN_LINE_CHECKS`](super::array_run::MIN_LINE_CHECKS) lines were checked, and one plunger step
    /// within the step limit reaches the centre. A confident cell scans
    /// anyway when its readout group scans in the same batch for as long
    /// (the lab time is the same): with one sensor per cell, a line batch
    /// is skipped only when every cell in it is confident. The forecast is
    /// honest only with unbiased line Jacobians (`joint_line_steps`).
    /// `None` (JSON `null`) or `max_skips = 0`: scan every time. Default
    /// on, with the single-cell level's defaults, a trade: on the
    /// eleventh round's loop every fresh set's all-cell and single-cell
    /// changes were shorter (by 0.4–0.8 and 0.2–2.5 lab min), the phases
    /// unconverged where the oracle converged 24 against 19 on 240 fresh
    /// runs and 0 against 4 on 84 development runs, within the sets'
    /// noise (earlier rounds, on older loops, measured 7 against 1 and
    /// left it off; docs/array-history.md, "Lines forecast instead of
    /// scanned, now the default").
    #[serde(default = "default_line_forecast")]
    pub line_forecast: Option<ParameterForecast>,
    /// Iterations after the start or the last target change without every
    /// cell in band after which the run gives up: it finishes, not tuned,
    /// until a target changes (1..=100,000; `None`: never). Default 200
    /// (several lab hours: a run that cannot tune stops instead of measuring
    /// forever).
    #[serde(default = "default_max_iterations")]
    pub max_iterations: Option<u32>,
    /// Skip the t_sr and w scans of a cell that shares its sensor readout
    /// with another cell (a skipped scan then saves lab time), was measured
    /// in band and is predicted by the filter to stay in band with this many
    /// σ of margin (0.5..=10; `None`: measure every cell every iteration).
    /// At most [`MAX_SKIPS_IN_A_ROW`](super::array_run::MAX_SKIPS_IN_A_ROW) iterations in a row. Default 1.5:
    /// the prediction's σ is at least the last reading's as the filter
    /// holds it, and a `t_sr` reading's is at least
    /// [`ArrayRunSettings::t_sr_floor`] (5.5 %) there, so
    /// with 2σ (the single-cell confirming-scan rule, the default before
    /// the floor) no margin fits in a 10 % band and no scan is ever
    /// skipped. Chosen on development arrays with three cells per sensor
    /// among 1, 1.5 and 2, checked on fresh ones (docs/array-history.md,
    /// "Skipping shared-sensor scans under the t_sr floor").
    #[serde(default = "default_skip_sigma")]
    pub skip_confident_sigma: Option<f64>,
    /// Park a cell's sensing dot on its flank as predicted from the gates
    /// of its neighbourhood (a `FlankModel` per cell, learned from every
    /// sweep) instead of sweeping, when the prediction is confident
    /// (`skip_std_mv`), the cell's evaluations have not failed since its
    /// last sweep and fewer than `max_skips` sweeps were skipped in a row
    /// (`max_skips = 0`: sweep every time). A cell sweeps anyway when its
    /// readout group sweeps in the same batch for as long (the lab time is
    /// the same). Default: the single-cell sensing-dot level's defaults.
    #[serde(default)]
    pub flank_prediction: FlankPrediction,
    /// Hold a cell measured in band where it is (residual 0: the joint step
    /// only compensates the crosstalk onto it) instead of aiming it at its
    /// targets like the cells out of band. Default `false`: a held cell sits
    /// wherever it entered the band, often near its edge, where noise and
    /// the crosstalk the estimate misses push it out again; aiming it
    /// measured better for `joint` on random arrays (with the correlated
    /// prior; docs/array-history.md), though worse for the oracle.
    #[serde(default)]
    pub hold_in_band: bool,
    /// Return a cell's parameter row to its prior
    /// ([`JointArrayTuner::reset_row`](crate::tuner::array::JointArrayTuner::reset_row)) when the parameter is measured out of
    /// band and the row's learned gradient would move it by less than this
    /// fraction of its band over a full step (`‖g‖·max_step_mv < f·band`, log
    /// space; 0 ≤ f ≤ 1, 0: never). A parameter that stopped responding
    /// (`w` at its thermal floor `2kT/α`, where `t_c` drifts unseen while
    /// `w`'s target sits on the floor) is then steered by what the lab
    /// measured where it did respond, instead of by a gradient learned to be
    /// zero. Default 0.5, chosen on random arrays (docs/array-history.md). Not
    /// again once the parameter turned away from its target since the
    /// first reset ([`Self::flat_reset_refuted_sigma`]).
    #[serde(default = "default_reset_flat_row_fraction")]
    pub reset_flat_row_fraction: f64,
    /// A flat row is not returned to its prior again once its parameter
    /// has, since the row's first reset, moved away from its target (same
    /// side) by more than this many σ of the two readings, counted from its
    /// nearest reading since that reset: the prior's direction is refuted
    /// where the cell now is ([`FlatResetWatch`](super::flat_reset::FlatResetWatch)), until the parameter
    /// comes into band, crosses its target or gets a new one. 0..=5; 0:
    /// never refuted (the earlier loop). Default 3 (docs/array-history.md, "A flat
    /// row's prior refuted").
    #[serde(default = "default_flat_reset_refuted_sigma")]
    pub flat_reset_refuted_sigma: f64,
    /// How a cell whose evaluation failed retreats (its first move of the
    /// next iteration). Default [`Retreat::EveryGate`]: the two rules that
    /// move only the tuning gates un-stranded the traced runs and the
    /// oracle, but measured no better for `joint` on fresh random arrays
    /// (docs/array-history.md, "A failed cell's retreat"), and neither did
    /// [`Retreat::EveryGateLinesKept`] ("Lines brought back in one step").
    #[serde(default)]
    pub retreat: Retreat,
    /// Whether a cell whose initial finite differences failed for a
    /// parameter (a zero row) starts that row from the mean of the other
    /// cells' measured rows ([`borrow_failed_gradients`](super::borrowed_gradient::borrow_failed_gradients)) instead of from
    /// zero, when the rows are not pooled
    /// ([`Self::pool_initial_gradients`], which does it too). Default
    /// `true`, measured on random arrays (docs/array-history.md, "Stalled cells
    /// traced").
    #[serde(default = "yes")]
    pub borrow_failed_gradients: bool,
    /// Whether every cell's initial row is pooled with the other cells'
    /// rows ([`pool_gradients`](super::pooled_gradient::pool_gradients): each gate's value the precision-weighted
    /// mean of the cell's own measurement and the others' mean, weighted by
    /// the spread between the cells). A failed row then takes the others'
    /// prior, so this replaces [`Self::borrow_failed_gradients`]. Default
    /// `true` (docs/array-history.md, "Initial rows: central and pooled").
    #[serde(default = "yes")]
    pub pool_initial_gradients: bool,
    /// Whether the rows are pooled in units of each cell's lockstep factor
    /// (an end cell measured its row ×1.35, an inner one ×1.6 with the
    /// default crosstalk) instead of as measured. Default `false`: as
    /// measured left fewer phases unconverged (docs/array-history.md).
    #[serde(default)]
    pub pool_in_lockstep_units: bool,
    /// Whether each cell's initial finite differences are central (every
    /// tuning gate offset by `±step_mv`, `InitialGradient::FiniteDifference`
    /// `central`) instead of the single-cell default's one-sided ones. The
    /// cells' lines are not re-centred between offsets, and a line left off
    /// by `μ` reads an apparent `t_sr·(1 + c·μ²)`: even in the offset, so
    /// the central difference cancels it, and it halves the rows' noise,
    /// for one more measurement per gate. Default `true` (docs/array-history.md,
    /// "Initial rows: central and pooled").
    #[serde(default = "yes")]
    pub central_differences: bool,
    /// Each tuning gate's offset in the cells' initial finite differences,
    /// mV, at most the cell tuner's own offset (`step_mv`: 6 mV from a
    /// description, [`crate::description::RECOMMENDED_FD_STEP_MV`], or its
    /// qubit step limit if shorter); 0 < value ≤ 8. `None`: the cell
    /// tuner's own offset. Default 3 mV: a longer offset measures a row
    /// with less of the fits' noise but more of the gradient's curvature
    /// and, all cells moving at once, likely more of the neighbours' line
    /// shifts (chosen on random arrays 13501–13801 over 2 to 6 mV, checked
    /// on fresh 13901–14201: docs/array-history.md, "Initial differences at a 3 mV
    /// offset").
    #[serde(default = "default_finite_difference_step_mv")]
    pub finite_difference_step_mv: Option<f64>,
    /// Whether the cells' initial repetitions are staggered against each
    /// other ([`staggered_mirror`](super::array_run::staggered_mirror)), at least two of them (one more than
    /// the recommended cell tuner's one: a cold start some 4 lab min
    /// longer). In lockstep, every cell moving the same gate the same way
    /// at once, a cell's rows come out `1 + Σλ` times its own gradient
    /// ([`lockstep_factor`](crate::tuner::array::lockstep_factor), 1.7 mid-chain at the default crosstalk).
    /// Mirrored, repetition 1 has the nearest neighbours moving the other
    /// way, so over two repetitions the mean is `1 + 2λ₂` mid-chain (1.1),
    /// over three (repetition 2 mirroring the next-nearest) `1 + 2λ₂/3`,
    /// whatever the lab's calibration; the repetitions' spread, which sets
    /// the rows' initial variance, then holds the neighbours' share.
    /// Needs `central_differences` to leave the lines' even offsets out.
    /// Default `false`.
    #[serde(default)]
    pub staggered_differences: bool,
    /// When a measured cell counts in band ([`InBandRule`]). Default
    /// [`InBandRule::Measured`].
    #[serde(default)]
    pub in_band: InBandRule,
    /// When every cell is measured in band, each parameter of a cell that
    /// has just entered its band within this many of its reported σ of the
    /// band's edge ([`to_confirm`](super::in_band::to_confirm)) is scanned once more where it is, and
    /// the run stops only if every such scan is in band too; otherwise the
    /// iteration moves on, the two readings' mean aimed at. 0..=3; 0:
    /// never. Default 1 (docs/array-history.md, "A cell entering near its band's
    /// edge scanned again").
    #[serde(default = "default_confirm_entry_sigma")]
    pub confirm_entry_sigma: f64,
    /// Whether that second scan also takes the cells already in band at
    /// their previous measurement (the neighbours of a changed cell, whose
    /// true values the change's crosstalk may have pushed just past the
    /// edge while they still read in band). Default `false` (measured no
    /// better: as many neighbours left out, slower; docs/array-history.md, "Initial
    /// differences at a 3 mV offset").
    #[serde(default)]
    pub confirm_in_band_cells: bool,
    /// The second scan's margin for a **bystander**: a cell whose targets
    /// were not set since the run last stopped with every cell in band (the
    /// neighbours of a cell whose targets changed alone). Such a cell read
    /// in band within this many of its reported σ of its band's edge is
    /// scanned once more before the run stops, whether or not it was in band
    /// at its previous measurement: the change's crosstalk, and the joint
    /// step's compensation of it, moved it although nobody asked. 0..=3; 0:
    /// bystanders are confirmed like every other cell
    /// ([`Self::confirm_entry_sigma`], [`Self::confirm_in_band_cells`]).
    /// Default 0 (off).
    #[serde(default)]
    pub confirm_bystander_sigma: f64,
    /// The in-band margin of a **disturbed bystander**: a cell whose targets
    /// were not set since the run last stopped with every cell in band,
    /// next to one (within one step on the grid) whose targets were. Such
    /// a cell counts in band only when each parameter reads at least this
    /// many of its reported σ inside its band's edge, the margin at most
    /// half the band ([`inside_margin`](super::in_band::inside_margin)): the
    /// change's crosstalk pushed it, and a reading just inside the edge
    /// leaves it truly outside about as often as not; the joint step keeps
    /// aiming it at its target until it reads well inside. 0..=3; 0: judged
    /// like every other cell. Default 1: on 156 runs of random development
    /// arrays 1 and 2 each left 2 neighbours of a changed cell truly out
    /// against 6 with 0, 1 for one phase more unconverged (17 against 16),
    /// 2 for two (docs/array-history.md, "A changed cell's neighbours
    /// judged with a margin").
    #[serde(default = "default_disturbed_margin_sigma")]
    pub disturbed_margin_sigma: f64,
    /// Hysteresis of the in-band verdict: a cell that counted in band at
    /// its previous measurement keeps counting while each of its
    /// parameters reads within this many of its reported σ beyond its
    /// band's edge (a cell truly at its target whose `w` scan, σ about
    /// half the band, reads just outside). 0..=3; 0: every measurement
    /// judged on its own ([`Self::in_band`]). Default 0 (off): 1 was the
    /// best of 0, 1, 1.5 and 2 on the default array and random development
    /// arrays, but on 120 fresh runs it left 13 neighbours of a changed
    /// cell truly out of band against 7, for one unconverged phase fewer
    /// (docs/array-history.md, "A cell in band stays in band within 1σ").
    #[serde(default)]
    pub stay_in_band_sigma: f64,
    /// Whether a confirming scan is judged together with the reading it
    /// confirms: the parameter counts in band when the two readings'
    /// inverse-variance mean lies within the band (the cell did not move
    /// between them; after a line correction the second reading alone),
    /// instead of the second reading alone. A truly-in parameter near its
    /// edge then passes more often and a truly-out one less often than on
    /// one reading ([`pooled_reading`](super::in_band::pooled_reading)). It
    /// also confirms, before the run stops, every parameter of a cell that
    /// counts in band only by [`Self::stay_in_band_sigma`] (read beyond its
    /// edge). Default `false`.
    #[serde(default)]
    pub pool_confirmations: bool,
    /// With [`Self::pool_confirmations`]: how many rounds of confirming
    /// scans a stop may take. After each round a parameter whose pooled
    /// reading lies within its band by more than [`Self::confirm_entry_sigma`]
    /// of the pooled σ is confirmed, one outside its band ends the stop
    /// (its cell out, the pooled value aimed at), and the rest are scanned
    /// again while rounds remain (in the last round, inside is enough).
    /// 1..=[`MAX_CONFIRM_ROUNDS`]; default 1 (one confirming scan).
    #[serde(default = "one")]
    pub confirm_rounds: u32,
    /// Start a cell's parameter row again ([`Self::stalled_row_from`]) when
    /// the parameter stalled: measured out of band on one side this many
    /// iterations in a row without coming nearer its target by a band
    /// ([`StallWatch`](super::stall::StallWatch); 2..=[`MAX_STALL_WINDOW`], 0: never). Never for the
    /// oracle. Default 8, chosen among 4 and 8 on random development arrays
    /// and checked on fresh ones (docs/array-history.md, "Stalled parameters").
    #[serde(default = "default_reset_stalled_row_after")]
    pub reset_stalled_row_after: u32,
    /// Where a stalled row starts again ([`StalledRowSource`]). Default
    /// [`StalledRowSource::Widened`]: the rows borrowed from the peers or
    /// returned to their prior left more phases unconverged on random
    /// development arrays (docs/array-history.md).
    #[serde(default = "default_stalled_row_from")]
    pub stalled_row_from: StalledRowSource,
    /// The least relative floor `r` of a `t_sr` reading's σ in the joint
    /// loop (dimensionless, 0..[`MAX_T_SR_FLOOR`]): a cell's references
    /// ([`Reference::relative_floor`](crate::fit::uncertainty::Reference::relative_floor))
    /// with a lower `t_sr` floor are evaluated with this one; 0 keeps the
    /// references' floor. The load curve's fitted σ sees neither the
    /// line's drift during the scan nor a line left off, which reads
    /// `t_sr` long: on traced readings of random development arrays
    /// `t_sr`'s error spread 2.0 of its reported σ (1.6 on its line), so
    /// the filter weighed each reading up to four times too much and the
    /// in-band margins were thin. Default 0.055, chosen among 0 (the
    /// references' 0.9 %), 0.028 (the floor that makes the on-line spread
    /// 1σ), 0.04, 0.055 and 0.07 on 84 runs of development arrays: 3
    /// phases unconverged against 12 with 0, no neighbour of a changed
    /// cell left out against 2. On 192 fresh runs it left more phases
    /// unconverged (31 against 22) but shortened every set's all-cell
    /// change (docs/array-history.md, "A floor under the load curve's σ").
    #[serde(default = "default_t_sr_floor")]
    pub t_sr_floor: f64,
    /// Apply [`Self::t_sr_floor`] only to what the filter learns from
    /// (the variance of a `t_sr` reading handed to the rows), not to the
    /// readings themselves: the in-band margins, the confirming scans, the
    /// skips and the records keep the load curve's own σ. Default on:
    /// against the floor everywhere it left fewer phases unconverged where
    /// the oracle converged on 96 fresh runs (5 against 12), with shorter
    /// single-cell changes but an all-cell change up to 1 lab min longer
    /// on some sets (docs/array-history.md, "The t_sr floor for the filter
    /// alone" and "… now the default"). Off applies the floor everywhere
    /// (the eighth round's rule).
    #[serde(default = "yes")]
    pub t_sr_floor_filter_only: bool,
    /// Extra scans per iteration of a lagging parameter (0..=[`MAX_REPEATS`];
    /// 0: off, the default): a parameter that lags (measured out of band on
    /// the same side [`Self::lagging_after`] iterations in a row:
    /// [`super::lagging::LagCount`]) is scanned this many more times in each
    /// measurement while it lags, and its readings are pooled by their
    /// inverse variances
    /// ([`super::lagging`]): the filter learns its row from each move with a
    /// smaller error bar, at the extra scans' lab time (serial on the cell's
    /// sensor). Never for the oracle, which plans with the true Jacobian.
    #[serde(default)]
    pub repeat_lagging_scans: u32,
    /// With [`Self::repeat_lagging_scans`]: the iterations in a row out of
    /// band on one side after which a parameter lags,
    /// 1..=[`MAX_LAGGING_AFTER`]. Default 4.
    #[serde(default = "default_lagging_after")]
    pub lagging_after: u32,
    /// Aim each step at readings shrunk toward their targets
    /// (0..=[`MAX_SHRINK`]; 0: off, the default): a parameter's residual
    /// `y` (row scale) with variance `σ²` (the filter's, under
    /// [`Self::t_sr_floor_filter_only`] with the `t_sr` floor) enters the
    /// step as `y · y²/(y² + s·σ²)` ([`super::shrink`]): a reading within
    /// the noise of its target moves its cell little, one many σ away as
    /// before. For `joint` and the oracle alike (it is about the readings'
    /// noise, not the Jacobian).
    #[serde(default)]
    pub shrink_residuals: f64,
    /// With [`Self::shrink_residuals`]: shrink only the readings within
    /// their band (a parameter read out of band is aimed at in full).
    #[serde(default)]
    pub shrink_in_band_only: bool,
    /// Scan `t_sr` and `w` of the cells that wait while others scan their
    /// lines, in the same batch where their readout group has the time
    /// (the batch lasts as long as its busiest group: such scans cost no
    /// lab time; the scans' durations are taken from the batches answered
    /// before, [`super::array_run::slack`]), and pool each such reading
    /// with the next measurement's, carried there along the learned row
    /// ([`super::array::JointArrayTuner::carry`]). For `joint` and the
    /// oracle alike. Default off.
    #[serde(default)]
    pub slack_readings: bool,
}

fn default_lagging_after() -> u32 {
    4
}

fn yes() -> bool {
    true
}

fn one() -> u32 {
    1
}

/// Most rounds of confirming scans before a stop
/// ([`ArrayRunSettings::confirm_rounds`]).
pub const MAX_CONFIRM_ROUNDS: u32 = 5;

fn default_joint_line_steps() -> bool {
    true
}

fn default_finite_difference_step_mv() -> Option<f64> {
    Some(3.0)
}
fn default_confirm_entry_sigma() -> f64 {
    1.0
}

/// Bound (exclusive) of [`ArrayRunSettings::t_sr_floor`]: a floor of a
/// fifth of the value would outweigh a band of a tenth.
pub const MAX_T_SR_FLOOR: f64 = 0.2;

fn default_t_sr_floor() -> f64 {
    0.055
}

fn default_disturbed_margin_sigma() -> f64 {
    1.0
}

fn default_reset_stalled_row_after() -> u32 {
    8
}

fn default_stalled_row_from() -> StalledRowSource {
    StalledRowSource::Widened
}

fn default_reset_flat_row_fraction() -> f64 {
    0.5
}

fn default_flat_reset_refuted_sigma() -> f64 {
    3.0
}

impl Default for ArrayRunSettings {
    fn default() -> Self {
        Self {
            relative_tolerance: 0.1,
            joint: JointConfig::default(),
            line_rounds: 1,
            moves_per_iteration: 1,
            line_tolerance_mv: 0.1,
            joint_line_steps: default_joint_line_steps(),
            couple_line_corrections: false,
            precorrect_lines_mv: Some(1.0),
            line_max_step_mv: default_line_max_step_mv(),
            rearm_line_search_after: default_rearm_line_search_after(),
            search_recentres_held_line: true,
            verify_lines_above_mv: default_verify_lines_above_mv(),
            line_forecast: default_line_forecast(),
            max_iterations: default_max_iterations(),
            skip_confident_sigma: default_skip_sigma(),
            flank_prediction: FlankPrediction::default(),
            hold_in_band: false,
            reset_flat_row_fraction: default_reset_flat_row_fraction(),
            flat_reset_refuted_sigma: default_flat_reset_refuted_sigma(),
            retreat: Retreat::default(),
            borrow_failed_gradients: true,
            pool_initial_gradients: true,
            pool_in_lockstep_units: false,
            central_differences: true,
            finite_difference_step_mv: default_finite_difference_step_mv(),
            staggered_differences: false,
            in_band: InBandRule::Measured,
            confirm_entry_sigma: default_confirm_entry_sigma(),
            confirm_in_band_cells: false,
            confirm_bystander_sigma: 0.0,
            disturbed_margin_sigma: default_disturbed_margin_sigma(),
            stay_in_band_sigma: 0.0,
            pool_confirmations: false,
            confirm_rounds: 1,
            reset_stalled_row_after: default_reset_stalled_row_after(),
            repeat_lagging_scans: 0,
            lagging_after: default_lagging_after(),
            shrink_residuals: 0.0,
            shrink_in_band_only: false,
            slack_readings: false,
            stalled_row_from: default_stalled_row_from(),
            t_sr_floor: default_t_sr_floor(),
            t_sr_floor_filter_only: true,
        }
    }
}

/// How a cell whose evaluation failed retreats ([`ArrayRunSettings::retreat`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Retreat {
    /// Every gate of the cell (tuning gates, plungers, sensing gate)
    /// half-way back to its voltage at the cell's last good evaluation,
    /// when a value is missing.
    #[default]
    EveryGate,
    /// The tuning gates half-way back, their compensation gates following
    /// ([`JointArrayTuner::retreat_move`](crate::tuner::array::JointArrayTuner::retreat_move), the single-cell tuner's rule),
    /// when a value is missing.
    TuningGates,
    /// As [`Retreat::TuningGates`], also when a value came back with an
    /// error bar wider than its band (the single-cell tuner's trigger).
    TuningGatesWhenUncertain,
    /// As [`Retreat::EveryGate`], but the plunger corrections made since the
    /// cell's last good evaluation from line scans that found both lines
    /// are kept: each such correction shifts the plungers' retreat target
    /// with it. A line scan is newer knowledge than the last good
    /// evaluation: the neighbours' moves and drift have shifted the lines
    /// since, and retreating the plungers toward their old voltages would
    /// undo the correction and take the lines off again.
    EveryGateLinesKept,
}

fn default_line_max_step_mv() -> Option<f64> {
    Some(10.0)
}

fn default_rearm_line_search_after() -> u32 {
    3
}

fn default_verify_lines_above_mv() -> Option<f64> {
    None
}

fn default_line_forecast() -> Option<ParameterForecast> {
    Some(ParameterForecast::default())
}

fn default_max_iterations() -> Option<u32> {
    Some(200)
}

fn default_skip_sigma() -> Option<f64> {
    Some(1.5)
}

impl ArrayRunSettings {
    /// `Err` naming the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let check = ConfigError::check;
        let b = self.relative_tolerance;
        check(
            b.is_finite() && b > 0.0 && b <= 0.5,
            "relative_tolerance",
            b.to_string(),
        )?;
        check(
            self.line_rounds <= 5,
            "line_rounds",
            self.line_rounds.to_string(),
        )?;
        check(
            (1..=4).contains(&self.moves_per_iteration),
            "moves_per_iteration",
            self.moves_per_iteration.to_string(),
        )?;
        if let Some(p) = self.precorrect_lines_mv {
            check(
                p.is_finite() && p > 0.0 && p <= 4.0,
                "precorrect_lines_mv",
                p.to_string(),
            )?;
        }
        if let Some(m) = self.line_max_step_mv {
            check(
                m.is_finite() && m > 0.0 && m <= 10.0,
                "line_max_step_mv",
                m.to_string(),
            )?;
        }
        if let Some(h) = self.finite_difference_step_mv {
            check(
                h.is_finite() && h > 0.0 && h <= 8.0,
                "finite_difference_step_mv",
                h.to_string(),
            )?;
        }
        let n = self.rearm_line_search_after;
        check(n <= 30, "rearm_line_search_after", n.to_string())?;
        let n = self.repeat_lagging_scans;
        check(n <= MAX_REPEATS, "repeat_lagging_scans", n.to_string())?;
        let n = self.lagging_after;
        check(
            (1..=MAX_LAGGING_AFTER).contains(&n),
            "lagging_after",
            n.to_string(),
        )?;
        let f = self.shrink_residuals;
        check(
            f.is_finite() && (0.0..=MAX_SHRINK).contains(&f),
            "shrink_residuals",
            f.to_string(),
        )?;
        if let Some(m) = self.verify_lines_above_mv {
            check(
                m.is_finite() && m > 0.0 && m <= 4.0,
                "verify_lines_above_mv",
                m.to_string(),
            )?;
        }
        let f = self.reset_flat_row_fraction;
        check(
            f.is_finite() && (0.0..=1.0).contains(&f),
            "reset_flat_row_fraction",
            f.to_string(),
        )?;
        for (name, s, max) in [
            (
                "flat_reset_refuted_sigma",
                self.flat_reset_refuted_sigma,
                5.0,
            ),
            ("confirm_entry_sigma", self.confirm_entry_sigma, 3.0),
            ("confirm_bystander_sigma", self.confirm_bystander_sigma, 3.0),
            ("disturbed_margin_sigma", self.disturbed_margin_sigma, 3.0),
            ("stay_in_band_sigma", self.stay_in_band_sigma, 3.0),
        ] {
            check(
                s.is_finite() && (0.0..=max).contains(&s),
                name,
                s.to_string(),
            )?;
        }
        let f = self.t_sr_floor;
        check(
            f.is_finite() && (0.0..MAX_T_SR_FLOOR).contains(&f),
            "t_sr_floor",
            f.to_string(),
        )?;
        let r = self.confirm_rounds;
        check(
            (1..=MAX_CONFIRM_ROUNDS).contains(&r),
            "confirm_rounds",
            r.to_string(),
        )?;
        let n = self.reset_stalled_row_after;
        check(
            n == 0 || (2..=MAX_STALL_WINDOW as u32).contains(&n),
            "reset_stalled_row_after",
            n.to_string(),
        )?;
        if let Some(m) = self.max_iterations {
            check((1..=100_000).contains(&m), "max_iterations", m.to_string())?;
        }
        if let Some(k) = self.skip_confident_sigma {
            check(
                k.is_finite() && (0.5..=10.0).contains(&k),
                "skip_confident_sigma",
                k.to_string(),
            )?;
        }
        self.flank_prediction
            .validate()
            .map_err(|(field, message)| {
                let field = field.trim_start_matches("prediction.");
                ConfigError::new(format!("flank_prediction.{field}"), message)
            })?;
        if let Some(f) = &self.line_forecast {
            f.validate().map_err(|e| {
                let field = e.field.trim_start_matches("forecast.");
                ConfigError::new(format!("line_forecast.{field}"), e.message)
            })?;
        }
        let l = self.line_tolerance_mv;
        check(
            l.is_finite() && l > 0.0 && l <= 1.0,
            "line_tolerance_mv",
            l.to_string(),
        )?;
        // (a line off by more than the verification's threshold is taken as
        // lost, which is only sound above the tolerance a correction aims at)
        if let Some(m) = self.verify_lines_above_mv.filter(|&m| m < l) {
            return Err(ConfigError::new(
                "verify_lines_above_mv",
                format!("{m} mV is below line_tolerance_mv ({l} mV); it must be at least that"),
            ));
        }
        self.joint.validate()
    }
}
