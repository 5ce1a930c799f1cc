//! The `spintune` subcommands (argument structs and their implementations).
//! `main.rs` holds only the clap enum and the dispatch.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use spintune::protocol::RunStatus;

use crate::config::RunConfig;
use crate::run::{Manager, ManagerOptions, RunEvent};
use crate::server::auth::{random_token, read_token_file, Auth, TokenSource};
use crate::server::origin::Access;
use crate::server::{router, AppState};
use crate::store::Store;

/// A failed command: message and process exit code.
#[derive(Debug)]
pub struct CliError {
    /// Exit code (1 = runtime failure, 2 = bad input).
    pub code: i32,
    /// What went wrong.
    pub message: String,
}

impl CliError {
    /// Runtime failure (exit 1).
    pub fn runtime(m: impl std::fmt::Display) -> Self {
        Self {
            code: 1,
            message: m.to_string(),
        }
    }
    /// Bad input (exit 2).
    pub fn input(m: impl std::fmt::Display) -> Self {
        Self {
            code: 2,
            message: m.to_string(),
        }
    }
}

/// Iterations of the built-in demo run (about 5 minutes at the default pace).
const DEMO_MAX_ITERATIONS: u64 = 1000;

/// When `serve` creates a demo run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DemoMode {
    /// Only if the store has no runs yet.
    Auto,
    /// Always create one.
    Always,
    /// Never.
    Never,
}

/// `spintune serve`.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to bind (host:port). Port 0 picks a free port.
    #[arg(long, env = "SPINTUNE_BIND", default_value = "127.0.0.1:8080")]
    pub bind: SocketAddr,
    /// SQLite database file.
    #[arg(long, env = "SPINTUNE_DB", default_value = "spintune.db")]
    pub db: PathBuf,
    /// Directory of the built dashboard (Trunk's output).
    #[arg(long, default_value = "dist")]
    pub dist: PathBuf,
    /// Control token. Prefer the SPINTUNE_TOKEN environment variable or
    /// --token-file: a flag is visible to every user in `ps` (default: random,
    /// printed at start).
    #[arg(long, env = "SPINTUNE_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Token file, origin and host options (`crate::server::auth`, `crate::server::origin`).
    #[command(flatten)]
    pub security: SecurityArgs,
    /// Wall-clock pause after each iteration, ms, so a human can watch (runs may
    /// override); at most 3,600,000 (`SessionConfig::MAX_ITERATION_DELAY_MS`).
    #[arg(long, default_value_t = 300)]
    pub iteration_delay_ms: u64,
    /// Live frames buffered per viewer before it is told it lagged.
    #[arg(long, default_value_t = 256)]
    pub viewer_buffer: usize,
    /// Create a demo run on the embedded simulator (paper default config cycling the
    /// paper's set points, then holding the last one; 1000 iterations).
    #[arg(long, value_enum, default_value_t = DemoMode::Auto)]
    pub demo: DemoMode,
    /// Config of the demo run (TOML); default: the paper's default run.
    #[arg(long)]
    pub demo_config: Option<PathBuf>,
    /// POST every alert (a run faulted, finished, failed, or keep mode not
    /// back in band in time) as JSON to this http:// URL (docs/alerts.md):
    /// 5 s per attempt, at most 3 attempts, a queue of 64; never blocks a run.
    #[arg(long, env = "SPINTUNE_ALERT_WEBHOOK", value_name = "URL")]
    pub alert_webhook: Option<String>,
    /// Connection and viewer limits (timeouts, caps).
    #[command(flatten)]
    pub limits: crate::server::listener::LimitArgs,
}

/// `serve` options of the token file and the Origin/Host checks.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct SecurityArgs {
    /// Read the control token from this file (contents trimmed).
    #[arg(long, env = "SPINTUNE_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// Also accept WebSocket connections and state-changing requests from web
    /// pages of this origin (`scheme://host[:port]`); repeatable.
    #[arg(long = "allow-origin", value_name = "ORIGIN")]
    pub allow_origin: Vec<String>,
    /// Also answer requests whose Host header is this name (how the server is
    /// reached, e.g. through a reverse proxy); repeatable.
    #[arg(long = "allow-host", value_name = "NAME")]
    pub allow_host: Vec<String>,
    /// Optional TLS (`crate::server::tls`).
    #[command(flatten)]
    pub tls: crate::server::tls::TlsArgs,
}

/// Where the token of `args` comes from, and the token.
pub fn resolve_token(args: &ServeArgs) -> Result<(String, TokenSource), CliError> {
    let (token, source) = match (&args.token, &args.security.token_file) {
        (Some(_), Some(_)) => return Err(CliError::input(
            "give the control token one way: SPINTUNE_TOKEN (or --token) or --token-file, not both",
        )),
        (Some(t), None) => {
            let from_env = std::env::var("SPINTUNE_TOKEN").is_ok_and(|e| &e == t);
            let source = if from_env {
                TokenSource::Env
            } else {
                TokenSource::Flag
            };
            (t.trim().to_string(), source)
        }
        (None, Some(path)) => (
            read_token_file(path).map_err(CliError::input)?,
            TokenSource::File(path.clone()),
        ),
        (None, None) => (random_token(), TokenSource::Random),
    };
    if token.is_empty() {
        return Err(CliError::input("the control token must not be empty"));
    }
    Ok((token, source))
}

/// A started server.
pub struct Server {
    /// The bound address.
    pub addr: SocketAddr,
    /// The control token.
    pub token: String,
    /// Where the token came from.
    pub token_source: TokenSource,
    /// The run manager.
    pub manager: Arc<Manager>,
    /// The serving task.
    pub task: tokio::task::JoinHandle<()>,
    /// Whether it serves HTTPS/WSS (`--tls-cert/--tls-key`).
    pub tls: bool,
}

/// Start a server (store, manager, demo run, HTTP) and return once it listens.
pub async fn start_server(args: &ServeArgs) -> Result<Server, CliError> {
    // Bad flags and certificate errors before anything is opened or bound.
    let max_delay = spintune::session::SessionConfig::MAX_ITERATION_DELAY_MS;
    if args.iteration_delay_ms > max_delay {
        return Err(CliError::input(format!(
            "--iteration-delay-ms {} exceeds the largest iteration delay, {max_delay} ms (one hour)",
            args.iteration_delay_ms
        )));
    }
    let webhook = args
        .alert_webhook
        .as_deref()
        .map(crate::alerts::WebhookUrl::parse)
        .transpose()
        .map_err(CliError::input)?;
    let tls = args.security.tls.acceptor().map_err(CliError::input)?;
    let store = Arc::new(
        Store::open(&args.db)
            .map_err(|e| CliError::runtime(format!("cannot open {}: {e}", args.db.display())))?,
    );
    let was_empty = store.list_runs().map(|r| r.is_empty()).unwrap_or(false);
    let manager = Manager::open(
        store,
        ManagerOptions {
            iteration_delay: Duration::from_millis(args.iteration_delay_ms),
            viewer_buffer: args.viewer_buffer,
            recover: true,
            viewers: args.limits.viewer_limits(),
            alerts: webhook.map(crate::alerts::AlertSink::start),
        },
    )
    .map_err(CliError::runtime)?;
    let (token, token_source) = resolve_token(args)?;
    let create_demo = match args.demo {
        DemoMode::Auto => was_empty,
        DemoMode::Always => true,
        DemoMode::Never => false,
    };
    if create_demo {
        let mut config = match &args.demo_config {
            Some(path) => load_config(path)?,
            None => RunConfig::recommended(),
        };
        if args.demo_config.is_none() {
            // The paper's set-point cycle (its Fig. 3), then hold the last set point;
            // bounded, so a demo left running does not grow the store forever.
            config.simulation.name = "demo: paper set-point cycle".into();
            config.simulation.tuner.schedule = spintune::benchmark::paper_schedule(21);
            config.simulation.tuner.max_iterations = Some(DEMO_MAX_ITERATIONS);
        }
        manager
            .create(config, false)
            .await
            .map_err(|e| CliError::runtime(format!("cannot create the demo run: {e}")))?;
    }
    let listener = tokio::net::TcpListener::bind(args.bind)
        .await
        .map_err(|e| CliError::runtime(format!("cannot bind {}: {e}", args.bind)))?;
    let addr = listener.local_addr().map_err(CliError::runtime)?;
    let access = Access::new(
        Some(addr),
        &args.security.allow_host,
        &args.security.allow_origin,
    )
    .map_err(CliError::input)?;
    let app = router(
        AppState {
            manager: manager.clone(),
            auth: Arc::new(Auth::new(&token)),
            access: Arc::new(access),
            client: None,
        },
        args.dist.clone(),
    );
    // Header timeout, connections per IP, TCP_NODELAY: see `server::listener`.
    let task = tokio::spawn(crate::server::listener::serve(
        listener,
        app,
        args.limits.connection_limits(),
        tls.clone(),
    ));
    Ok(Server {
        addr,
        token,
        token_source,
        manager,
        task,
        tls: tls.is_some(),
    })
}

/// `spintune serve`: run until Ctrl-C.
pub async fn serve(args: ServeArgs) -> Result<(), CliError> {
    let server = start_server(&args).await?;
    let host = if server.addr.ip().is_unspecified() {
        "127.0.0.1".to_string()
    } else {
        server.addr.ip().to_string()
    };
    let scheme = if server.tls { "https" } else { "http" };
    println!("Dashboard: {scheme}://{host}:{}/", server.addr.port());
    match &server.token_source {
        TokenSource::Random => println!("Control token: {}", server.token),
        TokenSource::Env => println!("Control token: from SPINTUNE_TOKEN"),
        TokenSource::File(p) => println!("Control token: from {}", p.display()),
        TokenSource::Flag => {
            println!("Control token: from --token");
            eprintln!(
                "warning: --token puts the control token on the command line, where every user of this machine can read it (`ps`); set SPINTUNE_TOKEN or use --token-file instead"
            );
        }
    }
    if let Some(url) = args
        .alert_webhook
        .as_deref()
        .and_then(|u| crate::alerts::WebhookUrl::parse(u).ok())
    {
        println!("Alerts: POSTed to {}", url.shown());
    }
    println!("Store: {}", args.db.display());
    if !args.dist.join("index.html").is_file() {
        println!(
            "Note: no dashboard in {} (build it with `trunk build --release`); the API works.",
            args.dist.display()
        );
    }
    for r in server.manager.list() {
        if r.status == RunStatus::Interrupted {
            println!(
                "Interrupted run {} ({:?}, {} iterations): resume with POST /api/runs/{}/control {{\"action\":\"resume\"}}",
                r.id, r.name, r.iterations, r.id
            );
        }
    }
    use std::io::Write;
    let _ = std::io::stdout().flush();
    let manager = server.manager.clone();
    tokio::select! {
        _ = server.task => Err(CliError::runtime("the server stopped")),
        _ = tokio::signal::ctrl_c() => {
            manager.mark_live_interrupted();
            println!("Shutting down; live runs are marked interrupted and can be resumed.");
            Ok(())
        }
    }
}

/// Read a TOML run config.
pub fn load_config(path: &std::path::Path) -> Result<RunConfig, CliError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| CliError::input(format!("cannot read {}: {e}", path.display())))?;
    RunConfig::from_toml_str(&text).map_err(|e| CliError::input(format!("{}: {e}", path.display())))
}

/// `spintune run`.
#[derive(Debug, Clone, clap::Args)]
pub struct RunArgs {
    /// Run config (TOML); see examples/.
    #[arg(long)]
    pub config: PathBuf,
    /// SQLite database file (results are stored like server runs).
    #[arg(long, env = "SPINTUNE_DB", default_value = "spintune.db")]
    pub db: PathBuf,
    /// No progress display (final summary only).
    #[arg(long)]
    pub quiet: bool,
    /// Keep mode: once tuned, keep the qubit in tune for this many lab hours
    /// (0 < HOURS ≤ 720; the config's `[tuner.keep]` settings, or the defaults).
    #[arg(long, value_name = "HOURS")]
    pub keep: Option<f64>,
}

/// Longest `spintune run --keep`, lab hours (30 days).
pub const MAX_KEEP_HOURS: f64 = 720.0;

/// `spintune run --config FILE`: a full headless run with a progress display.
pub async fn run(args: RunArgs) -> Result<(), CliError> {
    let mut config = load_config(&args.config)?;
    if let Some(hours) = args.keep {
        if !(hours.is_finite() && hours > 0.0 && hours <= MAX_KEEP_HOURS) {
            return Err(CliError::input(format!(
                "--keep must be a number of lab hours in (0, {MAX_KEEP_HOURS}], got {hours}"
            )));
        }
        let tuner = &mut config.simulation.tuner;
        let keep = tuner.keep.get_or_insert_with(Default::default);
        keep.duration_s = Some(hours * 3600.0);
        // the keep duration ends the run, not an iteration count
        tuner.stop_when_tuned = false;
        tuner.max_iterations = None;
        tuner
            .validate()
            .map_err(|e| CliError::input(format!("--keep: {}", e.within("tuner"))))?;
    }
    let keeping = config.simulation.tuner.keep.is_some();
    if config.backend.uses_bridge() {
        // The bridge client connects over the server's WebSocket, which `run` does not start.
        return Err(CliError::input(format!(
            "{}: a run that uses the lab bridge needs the server: start `spintune serve` and create the run there (see docs/instruments.md)",
            args.config.display()
        )));
    }
    let store = Arc::new(
        Store::open(&args.db)
            .map_err(|e| CliError::runtime(format!("cannot open {}: {e}", args.db.display())))?,
    );
    // Do not recover: a server may be using the same store.
    let manager = Manager::open(
        store,
        ManagerOptions {
            iteration_delay: Duration::ZERO,
            viewer_buffer: 1 << 16,
            recover: false,
            ..ManagerOptions::default()
        },
    )
    .map_err(CliError::runtime)?;
    let max = config.simulation.tuner.max_iterations;
    let summary = manager
        .create(config, true)
        .await
        .map_err(|e| CliError::input(format!("{}: {e}", args.config.display())))?;
    let id = summary.id;
    let handle = manager.get(id).map_err(CliError::runtime)?;
    let mut rx = handle.subscribe();
    manager
        .control(id, spintune::protocol::ControlCommand::Resume)
        .await
        .map_err(CliError::runtime)?;

    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        match max {
            Some(n) if !keeping => indicatif::ProgressBar::new(n),
            _ => indicatif::ProgressBar::new_spinner(),
        }
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(if max.is_some() && !keeping {
            "{spinner} [{bar:30}] {pos}/{len} {msg}"
        } else {
            "{spinner} {pos} iterations {msg}"
        })
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_message(format!("run {id} ({})", summary.name));
    let mut last: Option<spintune::protocol::IterationRecord> = None;
    let mut tally = spintune::tuner::KeepTally::default();
    let mut fault: Option<spintune::protocol::Fault> = None;
    let interrupted = loop {
        tokio::select! {
            frame = rx.recv() => match frame {
                Ok(frame) => {
                    match frame.event {
                        RunEvent::Iteration(record) => {
                            bar.set_position(record.iteration + 1);
                            tally.add(&record);
                            let mut line = progress_line(&record);
                            if keeping {
                                line.push_str(&tally.describe(&record));
                            }
                            bar.set_message(line);
                            last = Some((*record).clone());
                        }
                        RunEvent::Status(run) => match run.status {
                            // Nobody can resume a headless run: leave it
                            // resumable in the store and say so.
                            RunStatus::Faulted { fault: f } => {
                                fault = Some(f);
                                manager.detach(id).await.map_err(CliError::runtime)?;
                                break false;
                            }
                            s if s.is_terminal() || matches!(s, RunStatus::Failed { .. }) => {
                                break false
                            }
                            _ => {}
                        },
                        _ => {}
                    }
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                Err(tokio::sync::broadcast::error::RecvError::Closed) => break false,
            },
            _ = tokio::signal::ctrl_c() => break true,
        }
    };
    if let Some(f) = fault {
        manager.wait_idle(id).await.map_err(CliError::runtime)?;
        bar.abandon_with_message("faulted");
        return Err(CliError {
            code: 3,
            message: format!(
                "run {id} paused by a {f}\nNothing further was sent to the device. The run is stored in {} and stays resumable: fix the cause, then `spintune serve --db {}` and resume run {id}.",
                args.db.display(),
                args.db.display()
            ),
        });
    }
    if interrupted {
        manager.mark_live_interrupted();
        bar.abandon_with_message("interrupted");
        eprintln!(
            "Interrupted: run {id} is stored in {} and can be resumed from `spintune serve --db {}`.",
            args.db.display(),
            args.db.display()
        );
        return Err(CliError {
            code: 130,
            message: "interrupted".into(),
        });
    }
    let final_summary = manager.wait_idle(id).await.map_err(CliError::runtime)?;
    bar.finish_and_clear();
    println!(
        "Run {id} ({}): {}",
        final_summary.name,
        describe_status(&final_summary.status)
    );
    println!(
        "  iterations: {}   lab time: {:.1} min   tuned: {}",
        final_summary.iterations,
        final_summary.lab_seconds / 60.0,
        if final_summary.tuned { "yes" } else { "no" }
    );
    if keeping {
        if let Some(r) = &last {
            println!("  keep:{}", tally.describe(r).trim_start_matches(" |"));
        }
    }
    if let Some(r) = &last {
        for p in &r.parameters {
            println!(
                "  {:<6} {:>10} ± {:<8} {:<3} target {}",
                p.name,
                fmt_opt(p.value),
                fmt_opt(p.std),
                p.unit,
                match (p.target, p.tolerance) {
                    (Some(t), Some(tol)) => format!("{t} ± {tol:.3}"),
                    (Some(t), None) => format!("{t}"),
                    _ => "none".into(),
                }
            );
        }
    }
    println!(
        "  stored in {} — export with `spintune export {id} --format csv --db {}`",
        args.db.display(),
        args.db.display()
    );
    match final_summary.status {
        RunStatus::Failed { message } => {
            Err(CliError::runtime(format!("run {id} failed: {message}")))
        }
        _ => Ok(()),
    }
}

fn describe_status(s: &RunStatus) -> String {
    match s {
        RunStatus::Failed { message } => format!("failed: {message}"),
        RunStatus::Faulted { fault } => format!("faulted ({fault})"),
        other => other.name().to_string(),
    }
}

fn fmt_opt(x: Option<f64>) -> String {
    x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "—".into())
}

/// One-line progress: iteration, parameters vs targets, lab time.
pub fn progress_line(r: &spintune::protocol::IterationRecord) -> String {
    let mut s = format!("k={}", r.iteration);
    for p in &r.parameters {
        s.push_str(&format!(" {}={}", p.name, fmt_opt(p.value)));
        if let Some(t) = p.target {
            s.push_str(&format!("→{t}"));
        }
        s.push_str(&format!(" {}", p.unit));
    }
    s.push_str(&format!(
        " | lab {:.1} min{}",
        r.lab_seconds / 60.0,
        if r.tuned { " | tuned" } else { "" }
    ));
    s
}

/// `spintune export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// Run id.
    pub run: u64,
    /// Output format.
    #[arg(long, value_enum, default_value_t = crate::export::Format::Csv)]
    pub format: crate::export::Format,
    /// SQLite database file.
    #[arg(long, env = "SPINTUNE_DB", default_value = "spintune.db")]
    pub db: PathBuf,
    /// Write to this file instead of stdout.
    #[arg(long, short)]
    pub output: Option<PathBuf>,
}

/// `spintune export RUN`.
pub fn export(args: ExportArgs) -> Result<(), CliError> {
    if !args.db.exists() {
        return Err(CliError::input(format!(
            "no database at {}",
            args.db.display()
        )));
    }
    let store = Store::open(&args.db)
        .map_err(|e| CliError::runtime(format!("cannot open {}: {e}", args.db.display())))?;
    let out = crate::export::export(&store, args.run, args.format).map_err(CliError::input)?;
    match args.output {
        Some(path) => std::fs::write(&path, out)
            .map_err(|e| CliError::runtime(format!("cannot write {}: {e}", path.display()))),
        None => {
            use std::io::Write;
            std::io::stdout()
                .write_all(out.as_bytes())
                .map_err(CliError::runtime)
        }
    }
}

/// `spintune replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    /// Recorded sequence (JSON, see `spintune_server::replay`).
    pub file: PathBuf,
}

/// `spintune replay FILE.json`.
pub fn replay(args: ReplayArgs) -> Result<(), CliError> {
    let stdout = std::io::stdout();
    let mut lock = stdout.lock();
    crate::replay::run_file(&args.file, &mut lock).map_err(CliError::input)
}

/// `spintune config …`.
#[derive(Debug, Clone, clap::Args)]
pub struct ConfigArgs {
    /// What to do with a config.
    #[command(subcommand)]
    pub action: ConfigAction,
}

/// Subcommands of `spintune config`.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum ConfigAction {
    /// Print the fully resolved run config of FILE (every default, the
    /// levels a `description` derives, targets applied) as TOML that
    /// `spintune run --config` reads back unchanged.
    Resolve {
        /// Run config (TOML).
        file: PathBuf,
        /// Print JSON (the body of `POST /api/runs`) instead of TOML.
        #[arg(long)]
        json: bool,
    },
}

/// `spintune config resolve FILE`.
pub fn config(args: ConfigArgs) -> Result<(), CliError> {
    let ConfigAction::Resolve { file, json } = args.action;
    let config = load_config(&file)?;
    let text = if json {
        serde_json::to_string_pretty(&config.to_document()).map_err(CliError::runtime)? + "\n"
    } else {
        config.to_toml().map_err(CliError::runtime)?
    };
    use std::io::Write;
    std::io::stdout()
        .write_all(text.as_bytes())
        .map_err(CliError::runtime)
}
