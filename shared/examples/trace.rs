//! Print one simulated run of the paper's default setup, iteration by iteration:
//! `cargo run -p spintune --example trace --release -- [iterations] [seed]`.
use spintune::driver::{SimulationConfig, SimulationRun};

fn main() {
    let mut args = std::env::args().skip(1);
    let n: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(15);
    let seed: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(1);
    let mut cfg = SimulationConfig::paper_default();
    cfg.seed = seed;
    cfg.tuner.max_iterations = Some(n);
    let mut run = SimulationRun::new(cfg).expect("valid default config");
    let t = run.device().truth();
    println!(
        "start: true t_sr = {:.1} ns, w = {:.1} µV",
        t.t_sr_ns, t.w_uv
    );
    while let Some(r) = run.next_iteration().expect("run") {
        let p: Vec<String> = r
            .parameters
            .iter()
            .map(|p| match (p.value, p.std) {
                (Some(v), Some(s)) => format!("{} = {v:.1} ± {s:.1} {}", p.name, p.unit),
                _ => format!("{} = (failed)", p.name),
            })
            .collect();
        let t = run.device().truth();
        println!(
            "k={:2} {} | truth t_sr={:.1} w={:.1} mu=({:.2},{:.2}) | step {:.1} mV | tuned={} | {:.1} min | {:?}",
            r.iteration,
            p.join(", "),
            t.t_sr_ns,
            t.w_uv,
            t.mu_a_mv,
            t.mu_b_mv,
            r.step_mv.iter().map(|x| x * x).sum::<f64>().sqrt(),
            r.tuned,
            r.lab_seconds / 60.0,
            r.events
        );
    }
}
