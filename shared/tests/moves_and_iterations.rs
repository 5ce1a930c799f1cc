//! Issue 11 item 6: moves are counted apart from measure-and-decide
//! iterations, every move is checked against the step limit by the
//! benchmark's own driver loop, and the multi-move strategies really make
//! more than one move per iteration.

use spintune::benchmark::{run_seed, BenchmarkProtocol, Strategy};
use spintune::driver::SimulationConfig;

#[test]
fn multi_move_strategies_make_more_moves_than_iterations_within_the_limit() {
    let protocol = BenchmarkProtocol {
        set_points: vec![(20.0, 270.0), (70.0, 270.0), (70.0, 180.0)],
        iterations_per_set_point: 8,
        ..BenchmarkProtocol::default()
    };
    let strategies = [
        Strategy::KalmanLog,
        Strategy::KalmanLogTr,
        Strategy::KalmanLogTrMulti,
        Strategy::KalmanLogTrMultiBare,
    ];
    let results = run_seed(
        &SimulationConfig::paper_default(),
        &SimulationConfig::recommended().tuner,
        &protocol,
        &strategies,
        2,
        false,
    )
    .unwrap();
    let mut multi_extra_moves = 0;
    for r in &results {
        assert_eq!(r.limit_violations, 0, "{:?}", r.strategy);
        for c in &r.changes {
            let (Some(it), Some(mv)) = (c.iterations, c.moves) else {
                assert!(c.moves.is_none() && c.lab_minutes.is_none());
                continue;
            };
            let max_moves = r.strategy.max_moves_per_iteration();
            // each iteration before the converged measurement moves at most
            // max_moves times (retreats included)
            assert!(mv <= it * max_moves, "{:?}: {mv} moves in {it}", r.strategy);
            if max_moves == 1 {
                assert!(mv <= it);
            } else {
                multi_extra_moves += mv.saturating_sub(it);
            }
        }
    }
    assert!(
        multi_extra_moves > 0,
        "the multi-move strategies never made a second move"
    );
}
