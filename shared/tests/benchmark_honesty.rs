//! The benchmark's honesty rules (ARCHITECTURE.md invariant 7): no strategy
//! but the oracles reads the simulator's truth, and the lab's virtual-gate
//! matrix is not the simulator's.

use spintune::benchmark::{run_seed, BenchmarkProtocol, Strategy};
use spintune::driver::SimulationConfig;

fn short_protocol() -> BenchmarkProtocol {
    BenchmarkProtocol {
        set_points: vec![(20.0, 270.0), (70.0, 180.0)],
        iterations_per_set_point: 4,
        ..BenchmarkProtocol::default()
    }
}

#[test]
fn non_oracle_strategies_never_query_the_truth() {
    let results = run_seed(
        &SimulationConfig::paper_default(),
        &SimulationConfig::recommended().tuner,
        &short_protocol(),
        &Strategy::ALL,
        3,
        false,
    )
    .unwrap();
    assert_eq!(results.len(), Strategy::ALL.len());
    for r in &results {
        if r.strategy.is_oracle() {
            // the counter does count: the oracles ask whenever they step
            assert!(
                r.truth_queries >= 4,
                "{:?}: {}",
                r.strategy,
                r.truth_queries
            );
        } else {
            assert_eq!(r.truth_queries, 0, "{:?} read the truth", r.strategy);
        }
    }
}

#[test]
fn kalman_strategies_report_filter_consistency_for_t_sr_and_w() {
    let results = run_seed(
        &SimulationConfig::paper_default(),
        &SimulationConfig::recommended().tuner,
        &short_protocol(),
        &[Strategy::Kalman, Strategy::KalmanLog],
        5,
        false,
    )
    .unwrap();
    for r in &results {
        for p in ["t_sr", "w"] {
            let c = r.consistency.get(p).unwrap_or_else(|| panic!("{p}"));
            assert!(c.count >= 4, "{:?} {p}: {c:?}", r.strategy);
            assert!(c.nis_mean().unwrap().is_finite());
        }
    }
}

#[test]
fn the_labs_virtual_gate_matrix_is_not_the_simulators() {
    let cfg = SimulationConfig::paper_default();
    let exact = cfg
        .device
        .nominal_compensation(&["N", "SA", "SB", "T"], &["PA", "PB"]);
    // the default config carries a literal matrix within its stated uncertainty
    let c = cfg.tuner.top().compensation.clone().unwrap();
    for (m, e) in c.matrix.iter().flatten().zip(exact.iter().flatten()) {
        assert!((m - e).abs() <= c.relative_uncertainty * e.abs() + 1e-12);
    }
    // the benchmark's per-seed matrices differ from the truth and from each other
    let a = spintune::benchmark::perturbed_compensation(
        &cfg.device,
        &["N", "SA", "SB", "T"],
        &["PA", "PB"],
        0.2,
        1,
    );
    let b = spintune::benchmark::perturbed_compensation(
        &cfg.device,
        &["N", "SA", "SB", "T"],
        &["PA", "PB"],
        0.2,
        2,
    );
    assert_ne!(a, exact);
    assert_ne!(a, b);
    let rel: Vec<f64> = a
        .iter()
        .flatten()
        .zip(exact.iter().flatten())
        .map(|(m, e)| (m / e - 1.0).abs())
        .collect();
    assert!(rel.iter().all(|r| *r <= 0.2 + 1e-12), "{rel:?}");
    assert!(rel.iter().any(|r| *r > 0.05), "{rel:?}");
}

/// Lab time runs on through a strategy's start: every change costs
/// positive lab time, and a strategy's cold start is at least the lab time
/// of the initial measurement it started from (measured here on its own:
/// the paper's finite differences for the classic strategies, the
/// recommended cold start for `default`).
#[test]
fn cold_start_includes_the_initial_measurement_and_changes_cost_lab_time() {
    use spintune::driver::SimulationRun;
    let init_minutes = |mut cfg: SimulationConfig| {
        cfg.seed = 2;
        cfg.tuner.max_iterations = Some(0);
        let mut run = SimulationRun::new(cfg).unwrap();
        while run.next_iteration().unwrap().is_some() {}
        run.tuner().lab_seconds() / 60.0
    };
    let paper_init = init_minutes(SimulationConfig::paper_default());
    let recommended_init = init_minutes(SimulationConfig::recommended());
    assert!(
        recommended_init < paper_init,
        "{recommended_init} vs {paper_init}"
    );
    let results = run_seed(
        &SimulationConfig::paper_default(),
        &SimulationConfig::recommended().tuner,
        &BenchmarkProtocol {
            // long enough for every first change to converge
            iterations_per_set_point: 12,
            ..short_protocol()
        },
        &[Strategy::Default, Strategy::KalmanLogTrMultiBare],
        2,
        false,
    )
    .unwrap();
    for r in &results {
        for c in &r.changes {
            assert!(
                c.lab_minutes.is_none_or(|m| m > 0.0),
                "{:?}: {c:?}",
                r.strategy
            );
        }
        let init = if r.strategy == Strategy::Default {
            recommended_init
        } else {
            paper_init
        };
        let cold = r
            .cold_start_lab_minutes
            .expect("the first change converged");
        assert!(
            cold > init,
            "{:?}: cold start {cold} ≤ initial measurement {init}",
            r.strategy
        );
        assert!(r.truly_in_band <= r.tuned_records);
        assert!(r.tuned_records > 0);
    }
}
