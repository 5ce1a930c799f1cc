//! One whole tuner iteration through the run session (`RunSession::poll` /
//! `feed` until the next `Commit`), at the paper's qubit level: 4 gates (N,
//! SA, SB, T) × 2 parameters (t_sr in ns, w in µV), a Kalman filter per
//! parameter and the limited Newton step, plus everything around them that
//! the paper's Python package calls its "solver stack": the session's guard
//! (limits and step from the read-back), read-back validation, target and
//! tolerance checks, the iteration record. The device answers at once with
//! evaluated values from a linear model (mV in, ns and µV out), so no fit
//! and no lab time is included. The t_sr target alternates every iteration,
//! so each timed iteration is a full one (measure, update, step, move).
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
    use spintune::protocol::{
        ControlCommand, ParameterValue, Request, Response, ScanKind, ScanOutcome,
    };
    use spintune::session::{Output, RunSession, SessionConfig};
    use spintune::tuner::InitialGradient;

    /// The instrument: gates in mV; t_sr = 40 − 0.8 (N − N₀) + 0.5 (SB − SB₀) ns,
    /// w = 230 + 1.5 (SA − SA₀) − 1.2 (T − T₀) µV.
    struct Linear {
        v: BTreeMap<String, f64>,
        v0: BTreeMap<String, f64>,
        /// LCG state for the measurement noise (keeps every iteration a real
        /// filter update and a real step, also once tuned).
        noise: u64,
    }

    impl Linear {
        /// Deterministic noise, uniform in [−0.5, 0.5).
        fn jitter(&mut self) -> f64 {
            self.noise = self
                .noise
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.noise >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        }

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
                        ScanKind::ReloadTime => (
                            "t_sr",
                            40.0 - 0.8 * self.d("N") + 0.5 * self.d("SB") + 2.0 * self.jitter(),
                            0.3,
                        ),
                        _ => (
                            "w",
                            230.0 + 1.5 * self.d("SA") - 1.2 * self.d("T") + 20.0 * self.jitter(),
                            25.0,
                        ),
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
                Request::TrueJacobian { .. } | Request::Batch { .. } => {
                    Response::error("no oracle, no batch")
                }
                Request::Wait { seconds } => Response::Waited {
                    lab_seconds: *seconds,
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
        (
            session,
            Linear {
                v: v0.clone(),
                v0,
                noise: 1,
            },
        )
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
        // The t_sr target alternates between 25 and 45 ns, so that every
        // iteration is a full one (two measurements, two filter updates, a
        // limited Newton step, one move), not the cheap "tuned, nothing to
        // do" iteration.
        let mut k = 0u64;
        let mut full = |s: &mut RunSession, dev: &mut Linear| {
            k += 1;
            s.control(&ControlCommand::SetTarget {
                parameter: "t_sr".into(),
                target: Some(if k % 2 == 0 { 25.0 } else { 45.0 }),
                tolerance: None,
            })
            .expect("valid target");
            one_iteration(s, dev)
        };
        let typical: usize = (0..50).map(|_| full(&mut s, &mut dev)).sum();
        assert!(typical >= 150, "{typical} requests in 50 iterations");
        let mut g = c.benchmark_group("session_iteration");
        g.bench_function("4x2", |b| b.iter(|| full(&mut s, &mut dev)));
        g.finish();
    }

    criterion_group!(benches, session_iteration);
}
