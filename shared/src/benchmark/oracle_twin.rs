//! The oracle against itself: the noise floor of the array benchmark's
//! paired goals (`spintune bench-array --oracle-twin`).
//!
//! "Not converged where the oracle converged" pairs each `joint` run with
//! the oracle's run on the same array and noise seed. The two take
//! different paths through the same world, so even a strategy as good as
//! the oracle fails the pairing wherever noise alone decides a phase. The
//! twin measures how often: the oracle again on noise seeds `N + 1..=2N`
//! (`N` = `--seeds`), each paired with the oracle's run on seed `s − N` of
//! the same array exactly as `joint` is.

use serde::{Deserialize, Serialize};

use super::array::{all_changes, ArrayRunResult, ArrayStrategy};

/// The twin's counts over its pairs (keys as in the JSON report).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OracleTwin {
    /// Pairs compared (array × seed).
    pub runs: u64,
    /// Phases (cold starts included) the twin left unconverged.
    pub not_converged: u64,
    /// Of those, where the oracle on the paired seed converged: the count
    /// `joint`'s `not_converged_where_oracle_converged` is compared with.
    pub not_converged_where_oracle_converged: u64,
    /// Neighbours of a changed cell the twin left truly out of band.
    pub neighbours_left_out_of_band: u64,
}

/// The twin's counts: every oracle run of `results` with a seed above
/// `seeds` paired with the oracle's run on the same array and seed
/// `seed − seeds` (a twin without its pair is left out). `None` when no
/// pair exists.
///
/// ```
/// use spintune::benchmark::array::{ArrayRunResult, ArrayStrategy};
/// use spintune::benchmark::oracle_twin::oracle_twin;
/// let run = |seed, phases: [Option<f64>; 2], out| ArrayRunResult {
///     strategy: ArrayStrategy::Oracle,
///     seed,
///     device: 7,
///     cold_start_lab_minutes: Some(20.0),
///     changes: phases.to_vec(),
///     single_cell_changes: Vec::new(),
///     neighbours_left_out_of_band: out,
///     limit_violations: 0,
///     truth_queries: 0,
///     failed_fits: 0,
///     measurements: 0,
///     lab_minutes_by_kind: Default::default(),
///     timeline: Vec::new(),
/// };
/// // seed 1 missed its second change, its twin (seed 2) its first
/// let results = [run(1, [Some(9.0), None], 0), run(2, [None, None], 1)];
/// let t = oracle_twin(&results, 1).unwrap();
/// assert_eq!((t.runs, t.not_converged, t.not_converged_where_oracle_converged), (1, 2, 1));
/// assert_eq!(t.neighbours_left_out_of_band, 1);
/// assert!(oracle_twin(&results[..1], 1).is_none());
/// ```
pub fn oracle_twin(results: &[ArrayRunResult], seeds: u64) -> Option<OracleTwin> {
    let oracle = |r: &&ArrayRunResult| r.strategy == ArrayStrategy::Oracle;
    let mut twin = OracleTwin {
        runs: 0,
        not_converged: 0,
        not_converged_where_oracle_converged: 0,
        neighbours_left_out_of_band: 0,
    };
    for t in results.iter().filter(oracle).filter(|r| r.seed > seeds) {
        let Some(o) = results
            .iter()
            .filter(oracle)
            .find(|o| o.device == t.device && o.seed + seeds == t.seed)
        else {
            continue;
        };
        let (mine, theirs) = (all_changes(t), all_changes(o));
        twin.runs += 1;
        twin.not_converged += mine.iter().filter(|p| p.is_none()).count() as u64;
        twin.not_converged_where_oracle_converged += mine
            .iter()
            .zip(&theirs)
            .filter(|(a, b)| a.is_none() && b.is_some())
            .count() as u64;
        twin.neighbours_left_out_of_band += t.neighbours_left_out_of_band;
    }
    (twin.runs > 0).then_some(twin)
}
