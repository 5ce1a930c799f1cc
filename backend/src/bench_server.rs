//! `spintune bench-server`: load bench of the streaming path.
//!
//! Starts a real server on 127.0.0.1 (ephemeral port, temporary store),
//! creates one run, connects N real WebSocket viewers (tokio-tungstenite),
//! then publishes iteration records at a fixed rate through the same
//! commit-then-broadcast path the run tasks use. The records are real
//! simulator records (raw scans and fits included), re-numbered; viewers get
//! summary frames (the default of protocol 2) or, with `--full-frames`, full
//! records (they send `subscribe {scans: true}`).
//!
//! The viewers run either in the bench's own process (`--clients same`) or
//! in a child process (`--clients separate`: the same binary started with
//! the hidden `--clients-of URL`), so that the server's CPU and memory are
//! measured apart from the clients'. `both` (the default) reports both.
//!
//! Reported per N: delivery latency (from just before the SQLite commit to
//! the viewer holding the whole frame, both ends read from the system's
//! real-time clock, so it is comparable across the two processes) p50 / p99 /
//! max over every live frame delivered, frames delivered vs. expected,
//! `Lagged` notices, and the bench process's memory per viewer: (VmRSS after
//! streaming − VmRSS before connecting) / N. With separate clients the bench
//! process is the server (plus the publisher), so that figure is the
//! server's.
//!
//! The client process runs on one thread (the server keeps a core of its
//! own on a 2-core machine); in-process clients share the server's runtime.
//!
//! `--stalled N` measures memory instead: N viewers that connect and never
//! read, records published for `--seconds`, and the server's peak VmRSS
//! sampled every 50 ms, plus how many of those viewers the server dropped
//! (send timeout, `serve --viewer-send-timeout-ms`).

use std::io::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use futures_util::{SinkExt, StreamExt};
use serde::{Deserialize, Serialize};
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::{ClientMessage, IterationRecord};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::Message;

use crate::cli::{start_server, CliError, DemoMode, ServeArgs, Server};
use crate::config::RunConfig;

/// Where the bench's viewers run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ClientsWhere {
    /// In the bench's (and the server's) process.
    Same,
    /// In a child process (the server's cost measured alone).
    Separate,
    /// Both, one after the other.
    Both,
}

/// `spintune bench-server`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchServerArgs {
    /// Numbers of viewers to measure, comma-separated (each ≤ 10,000).
    #[arg(long, value_delimiter = ',', default_values_t = vec![10usize, 100, 1000])]
    pub viewers: Vec<usize>,
    /// Iterations per second published on the run (≤ 10,000).
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Seconds of streaming per measurement (≤ 3,600).
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Live frames buffered per run before a viewer is told it lagged.
    #[arg(long, default_value_t = 256)]
    pub viewer_buffer: usize,
    /// Where the viewers run.
    #[arg(long, value_enum, default_value_t = ClientsWhere::Both)]
    pub clients: ClientsWhere,
    /// Viewers subscribe to full frames (raw scans and fits) instead of summaries.
    #[arg(long)]
    pub full_frames: bool,
    /// Memory mode: this many viewers that never read; reports the server's peak RSS.
    #[arg(long)]
    pub stalled: Option<usize>,
    /// Send timeout of the server's viewers, ms (`serve --viewer-send-timeout-ms`).
    #[arg(long, default_value_t = crate::server::VIEWER_SEND_TIMEOUT.as_millis() as u64)]
    pub viewer_send_timeout_ms: u64,
    /// Internal: run as the client process of a bench, against this WebSocket URL.
    #[arg(long, hide = true)]
    pub clients_of: Option<String>,
    /// Internal (client process): frames each viewer is to receive.
    #[arg(long, hide = true, default_value_t = 0)]
    pub expect: u64,
}

/// Most viewers in one measurement.
pub const MAX_BENCH_VIEWERS: usize = 10_000;

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

/// Nanoseconds since the Unix epoch (the clock both bench processes share).
fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

/// The `iteration` number at the start of an `Iteration` frame, without a full parse.
fn frame_iteration(text: &str) -> Option<u64> {
    let rest = text.strip_prefix("{\"type\":\"iteration\",\"record\":{\"iteration\":")?;
    let end = rest.find(|c: char| !c.is_ascii_digit())?;
    rest[..end].parse().ok()
}

/// What the viewers saw, summarised (also the child process's answer, one
/// JSON line on its stdout).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct ClientReport {
    /// Viewers that connected.
    pub connected: usize,
    /// Live frames plus records re-sent in `History` after a `Lagged`.
    pub delivered: u64,
    /// `Lagged` notices.
    pub lagged: u64,
    /// Latency of live frames, ms: median.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

/// One measurement's result.
#[derive(Debug, Clone)]
pub struct BenchResult {
    /// Viewers.
    pub viewers: usize,
    /// Records published.
    pub published: u64,
    /// What the viewers saw.
    pub clients: ClientReport,
    /// Memory per viewer of the bench process, kB.
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

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn connect(url: &str, full_frames: bool) -> Result<Ws, CliError> {
    let (mut ws, _) = tokio_tungstenite::connect_async_with_config(
        url,
        Some(
            tokio_tungstenite::tungstenite::protocol::WebSocketConfig::default()
                .read_buffer_size(32 * 1024),
        ),
        true,
    )
    .await
    .map_err(|e| CliError::runtime(format!("viewer cannot connect to {url}: {e}")))?;
    if full_frames {
        let msg = serde_json::to_string(&ClientMessage::Subscribe {
            scans: true,
            alerts: false,
        })
        .expect("ClientMessage serializes");
        ws.send(Message::text(msg))
            .await
            .map_err(|e| CliError::runtime(format!("viewer cannot subscribe: {e}")))?;
    }
    Ok(ws)
}

/// N reading viewers: each records `(iteration, arrival ns)` of every live
/// frame until told to stop.
struct Viewers {
    delivered: Arc<AtomicU64>,
    lagged: Arc<AtomicU64>,
    stop: tokio::sync::watch::Sender<bool>,
    tasks: Vec<tokio::task::JoinHandle<Vec<(u64, u64)>>>,
}

impl Viewers {
    async fn connect(url: &str, n: usize, full_frames: bool) -> Result<Self, CliError> {
        let delivered = Arc::new(AtomicU64::new(0));
        let lagged = Arc::new(AtomicU64::new(0));
        let (stop, _) = tokio::sync::watch::channel(false);
        let mut tasks = Vec::with_capacity(n);
        for _ in 0..n {
            let ws = connect(url, full_frames).await?;
            let delivered = delivered.clone();
            let lagged = lagged.clone();
            let mut stop = stop.subscribe();
            tasks.push(tokio::spawn(async move {
                let (_write, mut read) = ws.split();
                let mut arrivals = Vec::new();
                loop {
                    let msg = tokio::select! {
                        m = read.next() => m,
                        _ = stop.changed() => break,
                    };
                    let Some(Ok(msg)) = msg else { break };
                    let Message::Text(t) = msg else { continue };
                    let t = t.as_str();
                    if let Some(k) = frame_iteration(t) {
                        arrivals.push((k, now_ns()));
                        delivered.fetch_add(1, Ordering::Relaxed);
                    } else if t.starts_with("{\"type\":\"lagged\"") {
                        lagged.fetch_add(1, Ordering::Relaxed);
                    } else if t.starts_with("{\"type\":\"history\"") && !arrivals.is_empty() {
                        // A refill after a lag: its records arrived (late).
                        let n = t.matches("{\"iteration\":").count() as u64;
                        delivered.fetch_add(n, Ordering::Relaxed);
                    }
                }
                arrivals
            }));
        }
        Ok(Self {
            delivered,
            lagged,
            stop,
            tasks,
        })
    }

    /// Wait until `expected` frames were delivered, at most `within`.
    async fn wait_delivered(&self, expected: u64, within: Duration) {
        let deadline = Instant::now() + within;
        while self.delivered.load(Ordering::Relaxed) < expected && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Stop every viewer and compute latencies against `sent_ns[k]`, the
    /// time record `k` was published.
    async fn finish(self, sent_ns: &[u64]) -> ClientReport {
        let _ = self.stop.send(true);
        let connected = self.tasks.len();
        let mut latencies = Vec::new();
        for task in self.tasks {
            if let Ok(Ok(arrivals)) = tokio::time::timeout(Duration::from_secs(10), task).await {
                for (k, at) in arrivals {
                    if let Some(&sent) = sent_ns.get(k as usize) {
                        latencies.push(at.saturating_sub(sent) as f64 / 1e6);
                    }
                }
            }
        }
        latencies.sort_by(|a, b| a.total_cmp(b));
        ClientReport {
            connected,
            delivered: self.delivered.load(Ordering::Relaxed),
            lagged: self.lagged.load(Ordering::Relaxed),
            p50_ms: percentile(&latencies, 0.5),
            p99_ms: percentile(&latencies, 0.99),
            max_ms: latencies.last().copied().unwrap_or(f64::NAN),
        }
    }
}

/// The client process (`--clients-of URL`): connect `--viewers` viewers
/// (stalled ones with `--stalled`), print `ready`, then read one line from
/// stdin — the publish times, ns, as a JSON array — wait for the frames
/// (at most 30 s) and print `result {ClientReport}`. Stalled viewers are
/// held until stdin closes.
async fn client_process(args: &BenchServerArgs, url: &str) -> Result<(), CliError> {
    let mut stdin = tokio::io::BufReader::new(tokio::io::stdin());
    let mut line = String::new();
    if let Some(n) = args.stalled {
        let mut held = Vec::with_capacity(n);
        for _ in 0..n {
            held.push(connect(url, args.full_frames).await?);
        }
        println!("ready");
        std::io::stdout().flush().map_err(CliError::runtime)?;
        let _ = stdin.read_line(&mut line).await;
        return Ok(());
    }
    let n = *args.viewers.first().unwrap_or(&0);
    let viewers = Viewers::connect(url, n, args.full_frames).await?;
    println!("ready");
    std::io::stdout().flush().map_err(CliError::runtime)?;
    stdin
        .read_line(&mut line)
        .await
        .map_err(CliError::runtime)?;
    let sent: Vec<u64> = serde_json::from_str(line.trim())
        .map_err(|e| CliError::input(format!("publish times: {e}")))?;
    viewers
        .wait_delivered(args.expect * n as u64, Duration::from_secs(30))
        .await;
    let report = viewers.finish(&sent).await;
    println!(
        "result {}",
        serde_json::to_string(&report).map_err(CliError::runtime)?
    );
    std::io::stdout().flush().map_err(CliError::runtime)?;
    Ok(())
}

/// A started client process and its stdin/stdout.
struct ClientProcess {
    child: tokio::process::Child,
    stdin: tokio::process::ChildStdin,
    stdout: tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
}

impl ClientProcess {
    async fn start(
        url: &str,
        viewers: usize,
        expect: u64,
        args: &BenchServerArgs,
        stalled: bool,
    ) -> Result<Self, CliError> {
        let exe = std::env::current_exe().map_err(CliError::runtime)?;
        let mut cmd = tokio::process::Command::new(exe);
        cmd.arg("bench-server")
            .arg("--clients-of")
            .arg(url)
            .arg("--viewers")
            .arg(viewers.to_string())
            .arg("--expect")
            .arg(expect.to_string());
        if stalled {
            cmd.arg("--stalled").arg(viewers.to_string());
        }
        if args.full_frames {
            cmd.arg("--full-frames");
        }
        let mut child = cmd
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .map_err(|e| CliError::runtime(format!("cannot start the client process: {e}")))?;
        let stdin = child.stdin.take().expect("piped stdin");
        let stdout = tokio::io::BufReader::new(child.stdout.take().expect("piped stdout")).lines();
        let mut p = Self {
            child,
            stdin,
            stdout,
        };
        let first = p.line(Duration::from_secs(120)).await?;
        if first != "ready" {
            return Err(CliError::runtime(format!(
                "client process: expected `ready`, got {first:?}"
            )));
        }
        Ok(p)
    }

    async fn line(&mut self, within: Duration) -> Result<String, CliError> {
        match tokio::time::timeout(within, self.stdout.next_line()).await {
            Ok(Ok(Some(l))) => Ok(l),
            Ok(Ok(None)) => Err(CliError::runtime(
                "the client process ended early (see its errors above)",
            )),
            Ok(Err(e)) => Err(CliError::runtime(format!("client process: {e}"))),
            Err(_) => Err(CliError::runtime("the client process did not answer")),
        }
    }

    async fn report(mut self, sent_ns: &[u64]) -> Result<ClientReport, CliError> {
        let mut line = serde_json::to_string(sent_ns).map_err(CliError::runtime)?;
        line.push('\n');
        self.stdin
            .write_all(line.as_bytes())
            .await
            .map_err(|e| CliError::runtime(format!("client process: {e}")))?;
        let answer = self.line(Duration::from_secs(90)).await?;
        let json = answer.strip_prefix("result ").ok_or_else(|| {
            CliError::runtime(format!("client process: expected a result, got {answer:?}"))
        })?;
        let report = serde_json::from_str(json).map_err(CliError::runtime)?;
        let _ = tokio::time::timeout(Duration::from_secs(10), self.child.wait()).await;
        Ok(report)
    }
}

/// A bench server with one run, ready to publish.
struct Bench {
    server: Server,
    id: u64,
    checkpoint: String,
    dir: std::path::PathBuf,
}

impl Bench {
    async fn start(args: &BenchServerArgs, viewers: usize) -> Result<Self, CliError> {
        let dir = std::env::temp_dir().join(format!(
            "spintune-bench-{}-{viewers}-{}",
            std::process::id(),
            now_ns()
        ));
        std::fs::create_dir_all(&dir).map_err(CliError::runtime)?;
        let mut serve = ServeArgs {
            bind: "127.0.0.1:0".parse().expect("literal address"),
            db: dir.join("bench.db"),
            dist: dir.join("no-dist"),
            token: Some("bench".into()),
            iteration_delay_ms: 0,
            viewer_buffer: args.viewer_buffer,
            demo: DemoMode::Never,
            demo_config: None,
            alert_webhook: None,
            limits: Default::default(),
            security: Default::default(),
        };
        // Every viewer comes from 127.0.0.1.
        serve.limits.max_connections_per_ip = viewers + 16;
        serve.limits.max_viewers_per_run = viewers.max(serve.limits.max_viewers_per_run);
        serve.limits.viewer_send_timeout_ms = args.viewer_send_timeout_ms;
        let server = start_server(&serve).await?;
        let mut cfg = RunConfig::recommended();
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
        Ok(Self {
            server,
            id,
            checkpoint,
            dir,
        })
    }

    fn url(&self) -> String {
        format!(
            "ws://{}/api/runs/{}/ws?protocol={}",
            self.server.addr,
            self.id,
            spintune::protocol::PROTOCOL_VERSION
        )
    }

    /// Publish `n` copies of `template` (numbered 0..n) at `rate` Hz, calling
    /// `each` after every publish; returns the publish times (ns) and the
    /// achieved rate, Hz.
    async fn publish(
        &self,
        template: &IterationRecord,
        n: u64,
        rate: f64,
        mut each: impl FnMut(),
    ) -> Result<(Vec<u64>, f64), CliError> {
        let mut sent = Vec::with_capacity(n as usize);
        let start = Instant::now();
        let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / rate));
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
        for k in 0..n {
            ticker.tick().await;
            let mut rec = template.clone();
            rec.iteration = k;
            sent.push(now_ns());
            self.server
                .manager
                .publish_external(self.id, &rec, self.checkpoint.clone())
                .await
                .map_err(CliError::runtime)?;
            each();
        }
        Ok((sent, n as f64 / start.elapsed().as_secs_f64()))
    }

    async fn close(self) {
        // Deleting the run closes its channel: every viewer gets a Close.
        let _ = self.server.manager.delete(self.id).await;
        self.server.task.abort();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

async fn measure(
    args: &BenchServerArgs,
    viewers: usize,
    separate: bool,
    template: &IterationRecord,
) -> Result<BenchResult, CliError> {
    let bench = Bench::start(args, viewers).await?;
    let n_records = (args.rate * args.seconds).ceil() as u64;
    let url = bench.url();
    let rss_before = rss_kb().unwrap_or(0);
    enum Clients {
        Same(Viewers),
        Separate(Box<ClientProcess>),
    }
    let clients = if separate {
        Clients::Separate(Box::new(
            ClientProcess::start(&url, viewers, n_records, args, false).await?,
        ))
    } else {
        Clients::Same(Viewers::connect(&url, viewers, args.full_frames).await?)
    };
    // Let every viewer receive its Hello + History before publishing.
    tokio::time::sleep(Duration::from_millis(200 + viewers as u64)).await;
    let (sent, achieved_hz) = bench.publish(template, n_records, args.rate, || {}).await?;
    let report = match clients {
        Clients::Same(v) => {
            v.wait_delivered(n_records * viewers as u64, Duration::from_secs(30))
                .await;
            v.finish(&sent).await
        }
        Clients::Separate(p) => p.report(&sent).await?,
    };
    let rss_after = rss_kb().unwrap_or(0);
    bench.close().await;
    Ok(BenchResult {
        viewers,
        published: n_records,
        clients: report,
        kb_per_viewer: rss_after.saturating_sub(rss_before) as f64 / viewers.max(1) as f64,
        achieved_hz,
    })
}

/// Result of the memory mode.
#[derive(Debug, Clone)]
pub struct StalledResult {
    /// Bench process RSS before the viewers connected, MiB.
    pub before_mib: f64,
    /// Peak RSS while publishing, MiB.
    pub peak_mib: f64,
    /// Stalled viewers dropped by the server (send timeout) by the end.
    pub dropped: usize,
    /// Achieved publish rate, Hz.
    pub achieved_hz: f64,
}

async fn measure_stalled(
    args: &BenchServerArgs,
    stalled: usize,
    separate: bool,
    template: &IterationRecord,
) -> Result<StalledResult, CliError> {
    let bench = Bench::start(args, stalled).await?;
    let n_records = (args.rate * args.seconds).ceil() as u64;
    let url = bench.url();
    let before = rss_kb().unwrap_or(0);
    let mut held = Vec::new();
    let process = if separate {
        Some(ClientProcess::start(&url, stalled, n_records, args, true).await?)
    } else {
        for _ in 0..stalled {
            held.push(connect(&url, args.full_frames).await?);
        }
        None
    };
    let mut peak = rss_kb().unwrap_or(0);
    let mut last_sample = Instant::now();
    let (_, achieved_hz) = bench
        .publish(template, n_records, args.rate, || {
            if last_sample.elapsed() >= Duration::from_millis(50) {
                peak = peak.max(rss_kb().unwrap_or(0));
                last_sample = Instant::now();
            }
        })
        .await?;
    peak = peak.max(rss_kb().unwrap_or(0));
    // Give the server one send timeout to drop the last stalled viewers.
    tokio::time::sleep(Duration::from_millis(args.viewer_send_timeout_ms + 500)).await;
    let connected = bench
        .server
        .manager
        .get(bench.id)
        .map_err(CliError::runtime)?
        .viewer_sockets();
    drop(held);
    drop(process);
    bench.close().await;
    Ok(StalledResult {
        before_mib: before as f64 / 1024.0,
        peak_mib: peak as f64 / 1024.0,
        dropped: stalled.saturating_sub(connected),
        achieved_hz,
    })
}

/// The record every measurement publishes: the last of a 3-iteration
/// simulator run (raw scans and fits included).
fn template_record() -> Result<IterationRecord, CliError> {
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(3);
    let mut sim = SimulationRun::new(cfg).map_err(CliError::runtime)?;
    let mut template = None;
    while let Some(r) = sim.next_iteration().map_err(CliError::runtime)? {
        template = Some(r);
    }
    template.ok_or_else(|| CliError::runtime("the simulator produced no record"))
}

fn check_args(args: &BenchServerArgs) -> Result<(), CliError> {
    let in_range = |x: f64, max: f64| x.is_finite() && x > 0.0 && x <= max;
    if !in_range(args.rate, 10_000.0) {
        return Err(CliError::input("--rate must be in (0, 10000] Hz"));
    }
    if !in_range(args.seconds, 3600.0) {
        return Err(CliError::input("--seconds must be in (0, 3600]"));
    }
    let counts = args.viewers.iter().chain(args.stalled.iter());
    if counts.clone().any(|&n| n == 0 || n > MAX_BENCH_VIEWERS) {
        return Err(CliError::input(format!(
            "--viewers and --stalled must be in 1..={MAX_BENCH_VIEWERS}"
        )));
    }
    if args.viewer_buffer == 0 || args.viewer_buffer > 65_536 {
        return Err(CliError::input("--viewer-buffer must be in 1..=65536"));
    }
    Ok(())
}

/// `spintune bench-server`: the bench on a multi-threaded runtime (one
/// worker per core, as `serve`); the client process (`--clients-of`) on a
/// single thread, so that on a small machine it cannot take every core
/// from the server it measures.
pub fn main(args: BenchServerArgs) -> Result<(), CliError> {
    let mut builder = if args.clients_of.is_some() {
        tokio::runtime::Builder::new_current_thread()
    } else {
        tokio::runtime::Builder::new_multi_thread()
    };
    let runtime = builder
        .enable_all()
        .build()
        .map_err(|e| CliError::runtime(format!("cannot start the async runtime: {e}")))?;
    runtime.block_on(run(args))
}

/// Run the bench and print markdown tables (or, with `--clients-of`, serve
/// as the client process of another bench).
pub async fn run(args: BenchServerArgs) -> Result<(), CliError> {
    check_args(&args)?;
    if let Some(url) = args.clients_of.clone() {
        return client_process(&args, &url).await;
    }
    let mut template = template_record()?;
    let full_bytes = serde_json::to_string(&template).map_or(0, |s| s.len()) + 30;
    template.scans.shrink_to_fit();
    let summary_bytes = {
        let mut s = template.clone();
        s.scans.clear();
        serde_json::to_string(&s).map_or(0, |s| s.len()) + 30
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let places: &[bool] = match args.clients {
        ClientsWhere::Same => &[false],
        ClientsWhere::Separate => &[true],
        ClientsWhere::Both => &[true, false],
    };
    let frame = if args.full_frames {
        format!("full frames, {full_bytes} B")
    } else {
        format!("summary frames, {summary_bytes} B (full: {full_bytes} B)")
    };
    println!(
        "spintune bench-server: {} Hz for {} s, {frame}, run buffer {} frames, viewer send timeout {} ms, {cores} cores",
        args.rate, args.seconds, args.viewer_buffer, args.viewer_send_timeout_ms
    );
    if let Some(n) = args.stalled {
        println!();
        println!("| clients | stalled viewers | before MiB | peak MiB | dropped by the server | achieved Hz |");
        println!("|---|---:|---:|---:|---:|---:|");
        for &separate in places {
            let r = measure_stalled(&args, n, separate, &template).await?;
            println!(
                "| {} | {n} | {:.1} | {:.1} | {} / {n} | {:.1} |",
                if separate { "separate" } else { "same" },
                r.before_mib,
                r.peak_mib,
                r.dropped,
                r.achieved_hz
            );
        }
        return Ok(());
    }
    println!();
    println!("| clients | viewers | published | achieved Hz | delivered / expected | lagged | p50 ms | p99 ms | max ms | RSS kB / viewer |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for &separate in places {
        for &n in &args.viewers {
            let r = measure(&args, n, separate, &template).await?;
            let c = &r.clients;
            println!(
                "| {} | {} | {} | {:.1} | {} / {} | {} | {:.2} | {:.2} | {:.2} | {:.1} |",
                if separate { "separate" } else { "same" },
                r.viewers,
                r.published,
                r.achieved_hz,
                c.delivered,
                r.published * r.viewers as u64,
                c.lagged,
                c.p50_ms,
                c.p99_ms,
                c.max_ms,
                r.kb_per_viewer
            );
        }
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

    #[test]
    fn percentile_picks_the_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 51.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert!(percentile(&[], 0.5).is_nan());
    }
}
