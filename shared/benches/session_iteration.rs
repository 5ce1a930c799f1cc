//! One whole tuner iteration through the run session (`RunSession::poll` /
//! `feed` until the next `Commit`), at the paper's qubit level: 4 gates (N,
//! SA, SB, T) × 2 parameters (t_sr in ns, w in µV), a Kalman filter per
//! parameter and the limited Newton step, plus everything around them that
//! the paper's Python package calls its "solver stack": the session's guard
//! (limits and step from the read-back), read-back validation, target and
//! tolerance checks, the iteration record. The device answers at once with
//! evaluated values from a linear model (mV in, ns and µV out), so no fit
//! and no lab time is included.
//!
//! ```sh
//! cargo bench -p spintune --bench session_iteration -- --warm-up-time 1 --measurement-time 3
//! ```
//!
//! Group `session_iteration`, id `4x2`.

#[cfg(not(target_arch = "wasm32"))]
criterion::criterion_main!(native::benches);

/// Benchmarks are native only (criterion is not a wasm32 dev-dependency).
#[cfg(target_arch = "wasm32")]
fn main() {}

#[cfg(not(target_arch = "wasm32"))]
mod native {
    use std::collections::BTreeMap;
    use std::hint::black_box;

    use criterion::{criterion_group, Criterion};
    use spintune::driver::SimulationConfig;
    use spintune::protocol::{ParameterValue, Request, Response, ScanKind, ScanOutcome};
    use spintune::session::{Output, RunSession, SessionConfig};
    use spintune::tuner::InitialGradient;

    /// The instrument: gates in mV; t_sr = 40 − 0.8 (N − N₀) + 0.5 (SB − SB₀) ns,
    /// w = 230 + 1.5 (SA − SA₀) − 1.2 (T − T₀) µV.
    struct Linear {
        v: BTreeMap<String, f64>,
        v0: BTreeMap<String, f64>,
    }

    impl Linear {
        fn d(&self, g: &str) -> f64 {
            self.v[g] - self.v0[g]
        }

        fn execute(&mut self, req: &Request) -> Response {
            match req {
                Request::SetVoltages { voltages_mv } => {
                    self.v
                        .extend(voltages_mv.iter().map(|(k, v)| (k.clone(), *v)));
                    Response::VoltagesSet {
                        voltages_mv: voltages_mv.clone(),
                        lab_seconds: 0.0,
                    }
                }
                Request::ReadVoltages { gates } => Response::VoltagesRead {
                    voltages_mv: gates.iter().map(|g| (g.clone(), self.v[g])).collect(),
                    lab_seconds: 0.0,
                },
                Request::Measure { scan } => {
                    let (name, value, variance) = match scan.kind {
                        ScanKind::ReloadTime => {
                            ("t_sr", 40.0 - 0.8 * self.d("N") + 0.5 * self.d("SB"), 0.3)
                        }
                        _ => ("w", 230.0 + 1.5 * self.d("SA") - 1.2 * self.d("T"), 25.0),
                    };
                    Response::Scanned {
                        outcome: ScanOutcome::Evaluated {
                            values: vec![ParameterValue {
                                name: name.into(),
                                value,
                                variance,
                            }],
                        },
                        lab_seconds: 0.0,
                    }
                }
                Request::TrueJacobian { .. } => Response::Error {
                    message: "no oracle".into(),
                },
            }
        }
    }

    fn setup() -> (RunSession, Linear) {
        let mut t = SimulationConfig::paper_default().tuner;
        t.levels.truncate(1);
        t.levels[0].after_move.clear();
        if let spintune::tuner::LevelKind::Newton(n) = &mut t.levels[0].kind {
            n.compensation = None;
            n.initial_gradient = InitialGradient::Given {
                gradient: vec![vec![-0.6, 0.1, 0.4, 0.0], vec![0.1, 1.2, 0.0, -1.0]],
                covariance: vec![
                    (0..4)
                        .map(|i| (0..4).map(|j| if i == j { 0.1 } else { 0.0 }).collect())
                        .collect();
                    2
                ],
            };
        }
        t.max_iterations = None;
        let v0: BTreeMap<String, f64> = t
            .gates
            .iter()
            .map(|g| (g.name.clone(), g.initial_mv))
            .collect();
        let session = RunSession::new(t, SessionConfig::default()).expect("valid config");
        (session, Linear { v: v0.clone(), v0 })
    }

    /// Drive until the next committed iteration; returns the number of requests.
    fn one_iteration(s: &mut RunSession, dev: &mut Linear) -> usize {
        let mut requests = 0;
        loop {
            match s.poll() {
                Output::Execute(r) => {
                    requests += 1;
                    let resp = dev.execute(&r);
                    s.feed(resp).expect("a request was outstanding");
                }
                Output::Commit(rec) => {
                    black_box(rec);
                    return requests;
                }
                Output::Wait | Output::Done(_) => panic!("the session stopped: {:?}", s.status()),
                Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
            }
        }
    }

    fn session_iteration(c: &mut Criterion) {
        let (mut s, mut dev) = setup();
        // warm: the first iteration includes the initial read-back of every gate
        let first = one_iteration(&mut s, &mut dev);
        assert!(first >= 3, "{first} requests");
        let mut g = c.benchmark_group("session_iteration");
        g.bench_function("4x2", |b| b.iter(|| one_iteration(&mut s, &mut dev)));
        g.finish();
    }

    criterion_group!(benches, session_iteration);
}
