//! Browser end-to-end test: the real backend binary serves the Trunk-built
//! dashboard; headless Chromium (through chromedriver and fantoccini) loads it.
//!
//! Checks: a live run's plots update as iterations arrive; the page is
//! read-only without the control token and the server refuses control without
//! it; after a server restart the page reconnects and resumes without
//! duplicate or missing iterations; with the token, pause / step / resume /
//! target change / stop work; the in-browser mode tunes the simulated dot.
//! Screenshots of each mode go to `<target>/e2e-screenshots/`.
//!
//! Inputs (set by `cargo xtask test`; fallbacks in brackets):
//! - `SPINTUNE_BIN`: the backend binary [`<target>/debug/spintune`, built if missing]
//! - `SPINTUNE_DIST`: Trunk's output [`<workspace>/dist`]; must contain index.html
//! - `CHROMEDRIVER`: chromedriver [`chromedriver` on PATH]; `CHROME`: browser binary [chromedriver's default]
//!
//! Missing chromedriver or dist is a test failure with an explanation, never a skip.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder, Locator};

const TOKEN: &str = "e2e-secret-token";

fn target_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is `<target>/tmp`.
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target dir")
        .to_path_buf()
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn backend_binary() -> PathBuf {
    if let Some(p) = std::env::var_os("SPINTUNE_BIN") {
        let p = PathBuf::from(p);
        assert!(p.is_file(), "SPINTUNE_BIN={} does not exist", p.display());
        return p;
    }
    let p = target_dir().join("debug").join("spintune");
    if !p.is_file() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .args(["build", "-p", "spintune-server", "--bin", "spintune"])
            .current_dir(workspace_root())
            .env("CARGO_TARGET_DIR", target_dir())
            .status()
            .expect("run cargo build for the backend");
        assert!(status.success(), "building the backend failed");
    }
    assert!(p.is_file(), "backend binary not found at {}", p.display());
    p
}

fn dist_dir() -> PathBuf {
    let p = std::env::var_os("SPINTUNE_DIST")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("dist"));
    assert!(
        p.join("index.html").is_file(),
        "no built dashboard at {} (set SPINTUNE_DIST, or run `TRUNK_SKIP_VERSION_CHECK=true trunk build --release --offline` at the workspace root)",
        p.display()
    );
    p
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A child process killed on drop.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_server(port: u16, db: &Path) -> Proc {
    let mut child = Command::new(backend_binary())
        .args([
            "serve",
            "--bind",
            &format!("127.0.0.1:{port}"),
            "--token",
            TOKEN,
            "--iteration-delay-ms",
            "250",
        ])
        .arg("--dist")
        .arg(dist_dir())
        .arg("--db")
        .arg(db)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start the backend");
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            eprintln!("[server] {line}");
            if line.contains("Dashboard:") {
                let _ = tx.send(());
            }
        }
    });
    rx.recv_timeout(Duration::from_secs(60))
        .expect("backend did not print its Dashboard address within 60 s");
    Proc(child)
}

fn start_chromedriver(port: u16) -> Proc {
    let bin = std::env::var("CHROMEDRIVER").unwrap_or_else(|_| "chromedriver".into());
    let child = Command::new(&bin)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| {
            panic!("cannot start `{bin}` ({e}): install chromium and chromium-driver (apt-get install chromium chromium-driver) or set CHROMEDRIVER")
        });
    let start = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "chromedriver did not listen on {port}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    Proc(child)
}

/// Minimal HTTP/1.1 request; returns (status, body).
fn http(port: u16, method: &str, path: &str, auth: Option<&str>, body: &str) -> (u16, String) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).expect("connect to backend");
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let auth = auth
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut resp = String::new();
    s.read_to_string(&mut resp).unwrap();
    let status = resp
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = resp
        .split_once("\r\n\r\n")
        .map(|x| x.1.to_string())
        .unwrap_or_default();
    (status, body)
}

fn run_iterations(port: u16) -> (u64, u64, String) {
    let (status, body) = http(port, "GET", "/api/runs", None, "");
    assert_eq!(status, 200, "GET /api/runs: {body}");
    // The body may be chunked; take the JSON array.
    let json = &body[body.find('[').unwrap()..=body.rfind(']').unwrap()];
    let runs: serde_json::Value = serde_json::from_str(json).unwrap();
    let run = &runs[0];
    (
        run["id"].as_u64().unwrap(),
        run["iterations"].as_u64().unwrap(),
        run["status"]["state"].as_str().unwrap().to_string(),
    )
}

async fn text(c: &Client, css: &str) -> Option<String> {
    c.find(Locator::Css(css)).await.ok()?.text().await.ok()
}

async fn attr(c: &Client, css: &str, name: &str) -> Option<String> {
    c.find(Locator::Css(css))
        .await
        .ok()?
        .attr(name)
        .await
        .ok()?
}

async fn iterations_drawn(c: &Client) -> u64 {
    attr(c, "canvas[data-chart=parameter-t_sr]", "data-iterations")
        .await
        .and_then(|s| s.parse().ok())
        .unwrap_or(0)
}

/// Poll `check` every 100 ms until it returns `Some`, or fail after `secs`.
async fn wait<T>(what: &str, secs: u64, mut check: impl AsyncFnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(v) = check().await {
            return v;
        }
        assert!(
            start.elapsed() < Duration::from_secs(secs),
            "timed out after {secs} s waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn wait_text(c: &Client, css: &str, needle: &str, secs: u64) -> String {
    wait(
        &format!("`{css}` to contain {needle:?}"),
        secs,
        async || text(c, css).await.filter(|t| t.contains(needle)),
    )
    .await
}

async fn click(c: &Client, css: &str) {
    c.find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css}: {e}"))
        .click()
        .await
        .unwrap_or_else(|e| panic!("click {css}: {e}"));
}

async fn type_into(c: &Client, css: &str, value: &str) {
    let el = c
        .find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css}: {e}"));
    el.clear().await.unwrap();
    el.send_keys(value).await.unwrap();
}

async fn screenshot(c: &Client, name: &str) {
    let dir = target_dir().join("e2e-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(dir.join(format!("{name}.png")), png).unwrap();
    // And the whole page.
    c.set_window_size(1400, 2600).await.unwrap();
    tokio::time::sleep(Duration::from_millis(800)).await;
    let png = c.screenshot().await.expect("screenshot");
    std::fs::write(dir.join(format!("{name}-full.png")), png).unwrap();
    c.set_window_size(1400, 900).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    eprintln!("screenshots: {}", dir.join(format!("{name}.png")).display());
}

async fn browser(driver_port: u16) -> Client {
    let mut opts = serde_json::json!({
        "args": [
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--no-first-run", "--disable-quic", "--window-size=1400,900",
        ]
    });
    if let Ok(bin) = std::env::var("CHROME") {
        opts["binary"] = bin.into();
    }
    let mut caps = serde_json::Map::new();
    caps.insert("goog:chromeOptions".into(), opts);
    ClientBuilder::native()
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{driver_port}"))
        .await
        .expect("connect to chromedriver")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_live_control_reconnect_and_in_browser_mode() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let db = tmp.join("runs.db");
    let port = free_port();
    let mut server = start_server(port, &db);
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    let base = format!("http://127.0.0.1:{port}/");

    // --- Live mode: history, then live updates -------------------------------
    c.goto(&base).await.unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    let first = wait("plots to show ≥ 2 iterations", 60, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n >= 2)
    })
    .await;
    wait("plots to update live", 60, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n > first)
    })
    .await;
    for chart in [
        "parameter-w",
        "gradient-t_sr",
        "gradient-w",
        "gates",
        "scan-0",
        "lab-time",
    ] {
        let n = attr(
            &c,
            &format!("canvas[data-chart={chart}]"),
            "data-iterations",
        )
        .await;
        assert!(
            n.is_some_and(|n| n != "0"),
            "chart {chart} not drawn with data"
        );
    }
    // Read-only without the token.
    wait_text(&c, "[data-testid=readonly]", "Read-only view", 5).await;
    assert!(
        c.find(Locator::Css("[data-testid=controls]"))
            .await
            .is_err(),
        "controls visible without token"
    );
    let first_chart_ms = c
        .execute("return window.spintuneFirstChartMs ?? null", vec![])
        .await
        .unwrap();
    eprintln!("budget: first chart with data drawn {first_chart_ms} ms after navigation start (live mode)");
    screenshot(&c, "live").await;

    // --- Control is refused without (or with a wrong) token -------------------
    let (run_id, _, _) = run_iterations(port);
    let control = format!("/api/runs/{run_id}/control");
    let (status, _) = http(port, "POST", &control, None, r#"{"action":"pause"}"#);
    assert_eq!(status, 401, "control without token must be refused");
    let (status, _) = http(
        port,
        "POST",
        &control,
        Some("wrong"),
        r#"{"action":"pause"}"#,
    );
    assert!(
        status == 401 || status == 403,
        "control with a wrong token must be refused, got {status}"
    );
    type_into(&c, "[data-testid=token]", "wrong-token").await;
    click(&c, "[data-testid=unlock]").await;
    wait_text(&c, "[data-testid=auth-error]", "Token refused", 10).await;
    assert!(c
        .find(Locator::Css("[data-testid=controls]"))
        .await
        .is_err());
    assert_eq!(
        run_iterations(port).2,
        "running",
        "a refused control must not change the run"
    );

    // --- Server restart: reconnect and resume without duplicates or gaps -------
    drop(server);
    wait_text(&c, "[data-testid=connection]", "retry", 20).await;
    server = start_server(port, &db);
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    let (_, stored, state) = run_iterations(port);
    eprintln!("after restart: {stored} stored iterations, run {state}");
    let drawn = wait(
        "page to hold exactly the stored iterations",
        20,
        async || {
            let (_, stored, _) = run_iterations(port);
            let n = iterations_drawn(&c).await;
            (n == stored).then_some(n)
        },
    )
    .await;
    wait_text(&c, "[data-testid=iteration]", &format!("{}", drawn - 1), 5).await;

    // --- With the token: resume, pause, step, target, stop ---------------------
    type_into(&c, "[data-testid=token]", TOKEN).await;
    click(&c, "[data-testid=unlock]").await;
    wait("controls after a valid token", 10, async || {
        c.find(Locator::Css("[data-testid=controls]")).await.ok()
    })
    .await;
    if state != "running" {
        click(&c, "[data-testid=resume]").await;
    }
    wait_text(&c, "[data-testid=run-status]", "running", 10).await;
    let n0 = iterations_drawn(&c).await;
    wait("iterations after resume", 30, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n > n0)
    })
    .await;
    click(&c, "[data-testid=pause]").await;
    wait_text(&c, "[data-testid=run-status]", "paused", 15).await;
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let paused_at = iterations_drawn(&c).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        iterations_drawn(&c).await,
        paused_at,
        "iterations continued while paused"
    );
    assert_eq!(
        run_iterations(port).1,
        paused_at,
        "page and server disagree while paused"
    );
    click(&c, "[data-testid=step]").await;
    wait("one more iteration after a single step", 30, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n == paused_at + 1)
    })
    .await;
    wait_text(&c, "[data-testid=run-status]", "paused", 15).await;
    type_into(&c, "[data-testid=target-t_sr]", "70").await;
    click(&c, "form[data-parameter=t_sr] button[type=submit]").await;
    click(&c, "[data-testid=resume]").await;
    wait_text(&c, "[data-testid=param-t_sr]", "target 70", 30).await;
    screenshot(&c, "live-controls").await;
    click(&c, "[data-testid=stop]").await;
    c.accept_alert().await.expect("confirm dialog for Stop");
    wait_text(&c, "[data-testid=run-status]", "stopped", 15).await;

    // --- In-browser mode ---------------------------------------------------------
    click(&c, "[data-testid=tab-local]").await;
    wait_text(&c, ".explain", "What am I looking at?", 10).await;
    click(&c, "[data-testid=local-run]").await;
    let tuned = wait_text(&c, "[data-testid=local-tuned]", "tuned at iteration", 120).await;
    eprintln!("in-browser mode: {tuned}");
    let k: u64 = tuned
        .trim_start_matches("tuned at iteration ")
        .trim()
        .parse()
        .unwrap();
    assert!(k <= 60, "in-browser tuning took {k} iterations");
    // Let a few more iterations draw, then pause and take the picture.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    click(&c, "[data-testid=local-pause]").await;
    wait_text(&c, "[data-testid=local-status]", "paused", 10).await;
    screenshot(&c, "local").await;

    c.close().await.unwrap();
    drop(server);
    let _ = std::fs::remove_dir_all(&tmp);
}
