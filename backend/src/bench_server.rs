//! `spintune bench-server`: load bench of the streaming path.
//!
//! Starts a real server on 127.0.0.1 (ephemeral port, temporary store),
//! creates one run, connects N real WebSocket viewers (tokio-tungstenite, in
//! this process), then publishes iteration records at a fixed rate through the
//! same commit-then-broadcast path the run tasks use. The records are real
//! simulator records (raw scans and fits included), re-numbered.
//!
//! Reported per N: delivery latency (from just before the SQLite commit to the
//! viewer having the whole frame) p50 / p99 / max over every delivered frame,
//! frames delivered vs. expected, `Lagged` notices, and memory per viewer:
//! (VmRSS after streaming − VmRSS before connecting) / N, from
//! `/proc/self/status`. Client and server share the process, so the memory
//! figure is an upper bound for the server alone.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::IterationRecord;
use tokio_tungstenite::tungstenite::Message;

use crate::cli::{start_server, CliError, DemoMode, ServeArgs};
use crate::config::RunConfig;

/// `spintune bench-server`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchServerArgs {
    /// Numbers of viewers to measure, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![10usize, 100, 1000])]
    pub viewers: Vec<usize>,
    /// Iterations per second published on the run.
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Seconds of streaming per measurement.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Live frames buffered per viewer.
    #[arg(long, default_value_t = 256)]
    pub viewer_buffer: usize,
    /// Strip raw scans from the records (smaller frames).
    #[arg(long)]
    pub no_scans: bool,
}

/// Resident set size of this process, kB (`VmRSS` in /proc/self/status).
pub fn rss_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// The `iteration` number at the start of an `Iteration` frame, without a full parse.
fn frame_iteration(text: &str) -> Option<u64> {
    let rest = text.strip_prefix("{\"type\":\"iteration\",\"record\":{\"iteration\":")?;
    let end = rest.find(|c: char| !c.is_ascii_digit())?;
    rest[..end].parse().ok()
}

/// One measurement's result.
#[derive(Debug, Clone)]
pub struct BenchResult {
    /// Viewers.
    pub viewers: usize,
    /// Records published.
    pub published: u64,
    /// Frames delivered (over all viewers).
    pub delivered: u64,
    /// `Lagged` notices received.
    pub lagged: u64,
    /// Latency percentiles, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
    /// Memory per viewer, kB.
    pub kb_per_viewer: f64,
    /// Achieved publish rate, Hz.
    pub achieved_hz: f64,
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

async fn measure(
    args: &BenchServerArgs,
    viewers: usize,
    template: &IterationRecord,
) -> Result<BenchResult, CliError> {
    let dir = std::env::temp_dir().join(format!(
        "spintune-bench-{}-{viewers}-{}",
        std::process::id(),
        Instant::now().elapsed().as_nanos()
    ));
    std::fs::create_dir_all(&dir).map_err(CliError::runtime)?;
    let serve = ServeArgs {
        bind: "127.0.0.1:0".parse().expect("literal address"),
        db: dir.join("bench.db"),
        dist: dir.join("no-dist"),
        token: Some("bench".into()),
        iteration_delay_ms: 0,
        viewer_buffer: args.viewer_buffer,
        demo: DemoMode::Never,
        demo_config: None,
        limits: Default::default(),
        security: Default::default(),
    };
    let server = start_server(&serve).await?;
    let mut cfg = RunConfig::paper_default();
    cfg.simulation.name = "bench".into();
    let summary = server
        .manager
        .create(cfg, true)
        .await
        .map_err(CliError::runtime)?;
    let id = summary.id;
    server
        .manager
        .control(id, spintune::protocol::ControlCommand::Stop)
        .await
        .map_err(CliError::runtime)?;
    server
        .manager
        .wait_idle(id)
        .await
        .map_err(CliError::runtime)?;
    let checkpoint = server
        .manager
        .store()
        .checkpoint(id)
        .map_err(CliError::runtime)?;

    let published = args.rate * args.seconds;
    let n_records = published.ceil() as u64;
    let send_times: Arc<Mutex<Vec<Option<Instant>>>> =
        Arc::new(Mutex::new(vec![None; n_records as usize]));
    let delivered = Arc::new(AtomicU64::new(0));
    let lagged = Arc::new(AtomicU64::new(0));
    let rss_before = rss_kb().unwrap_or(0);

    let url = format!("ws://{}/api/runs/{id}/ws", server.addr);
    let mut clients = Vec::with_capacity(viewers);
    for _ in 0..viewers {
        let (ws, _) = tokio_tungstenite::connect_async_with_config(
            url.as_str(),
            Some(
                tokio_tungstenite::tungstenite::protocol::WebSocketConfig::default()
                    .read_buffer_size(32 * 1024),
            ),
            true,
        )
        .await
        .map_err(|e| CliError::runtime(format!("viewer cannot connect: {e}")))?;
        let send_times = send_times.clone();
        let delivered = delivered.clone();
        let lagged = lagged.clone();
        clients.push(tokio::spawn(async move {
            let (_, mut read) = ws.split();
            let mut latencies = Vec::new();
            while let Some(Ok(msg)) = read.next().await {
                let now = Instant::now();
                if let Message::Text(t) = msg {
                    let t = t.as_str();
                    if let Some(k) = frame_iteration(t) {
                        let sent = send_times
                            .lock()
                            .ok()
                            .and_then(|v| v.get(k as usize).copied().flatten());
                        if let Some(sent) = sent {
                            latencies.push(now.duration_since(sent).as_secs_f64() * 1e3);
                        }
                        delivered.fetch_add(1, Ordering::Relaxed);
                    } else if t.starts_with("{\"type\":\"lagged\"") {
                        lagged.fetch_add(1, Ordering::Relaxed);
                    } else if t.starts_with("{\"type\":\"history\"") {
                        // refill after lag: count the records as delivered (late)
                        let n = t.matches("{\"iteration\":").count() as u64;
                        delivered.fetch_add(n, Ordering::Relaxed);
                    }
                }
            }
            latencies
        }));
    }
    // Wait for every viewer's Hello + History.
    tokio::time::sleep(Duration::from_millis(200 + viewers as u64)).await;

    let period = Duration::from_secs_f64(1.0 / args.rate);
    let start = Instant::now();
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
    for k in 0..n_records {
        ticker.tick().await;
        let mut rec = template.clone();
        rec.iteration = k;
        if let Ok(mut v) = send_times.lock() {
            v[k as usize] = Some(Instant::now());
        }
        server
            .manager
            .publish_external(id, &rec, checkpoint.clone())
            .await
            .map_err(CliError::runtime)?;
    }
    let elapsed = start.elapsed().as_secs_f64();
    // Let the viewers drain (bounded).
    let expected = n_records * viewers as u64;
    let drain_deadline = Instant::now() + Duration::from_secs(30);
    while delivered.load(Ordering::Relaxed) < expected && Instant::now() < drain_deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let rss_after = rss_kb().unwrap_or(0);
    // Deleting the run closes its channel: every viewer gets a Close and returns.
    let _ = server.manager.delete(id).await;
    server.task.abort();
    let mut all = Vec::new();
    for c in clients {
        if let Ok(Ok(l)) = tokio::time::timeout(Duration::from_secs(10), c).await {
            all.extend(l);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    all.sort_by(|a, b| a.total_cmp(b));
    Ok(BenchResult {
        viewers,
        published: n_records,
        delivered: delivered.load(Ordering::Relaxed),
        lagged: lagged.load(Ordering::Relaxed),
        p50_ms: percentile(&all, 0.5),
        p99_ms: percentile(&all, 0.99),
        max_ms: all.last().copied().unwrap_or(f64::NAN),
        kb_per_viewer: (rss_after.saturating_sub(rss_before)) as f64 / viewers.max(1) as f64,
        achieved_hz: n_records as f64 / elapsed,
    })
}

/// Run the bench and print a markdown table.
pub async fn run(args: BenchServerArgs) -> Result<(), CliError> {
    let positive = |x: f64| x.is_finite() && x > 0.0;
    if !(positive(args.rate) && positive(args.seconds)) {
        return Err(CliError::input(
            "--rate and --seconds must be positive numbers",
        ));
    }
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(3);
    let mut sim = SimulationRun::new(cfg).map_err(CliError::runtime)?;
    let mut template = None;
    while let Some(r) = sim.next_iteration().map_err(CliError::runtime)? {
        template = Some(r);
    }
    let mut template =
        template.ok_or_else(|| CliError::runtime("the simulator produced no record"))?;
    if args.no_scans {
        template.scans.clear();
    }
    let frame_bytes = serde_json::to_string(&template)
        .map(|s| s.len())
        .unwrap_or(0)
        + 30;
    println!(
        "spintune bench-server: rate {} Hz, {} s per point, frame {} bytes, viewer buffer {}, {} cores",
        args.rate,
        args.seconds,
        frame_bytes,
        args.viewer_buffer,
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
    );
    println!();
    println!("| viewers | published | achieved Hz | delivered / expected | lagged | p50 ms | p99 ms | max ms | RSS kB / viewer |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for &n in &args.viewers {
        let r = measure(&args, n, &template).await?;
        println!(
            "| {} | {} | {:.1} | {} / {} | {} | {:.2} | {:.2} | {:.2} | {:.1} |",
            r.viewers,
            r.published,
            r.achieved_hz,
            r.delivered,
            r.published * r.viewers as u64,
            r.lagged,
            r.p50_ms,
            r.p99_ms,
            r.max_ms,
            r.kb_per_viewer
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_iteration_parses_prefix() {
        assert_eq!(
            frame_iteration("{\"type\":\"iteration\",\"record\":{\"iteration\":42,\"x\":1}}"),
            Some(42)
        );
        assert_eq!(frame_iteration("{\"type\":\"lagged\",\"skipped\":3}"), None);
    }
}
