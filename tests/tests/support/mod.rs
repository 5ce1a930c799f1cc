//! Helpers of the browser end-to-end tests: the backend binary and the
//! built dashboard, chromedriver, a headless Chromium session, HTTP, waiting
//! and screenshots.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder, Locator};

pub const TOKEN: &str = "e2e-secret-token";

pub fn target_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is `<target>/tmp`.
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target dir")
        .to_path_buf()
}

pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

pub fn backend_binary() -> PathBuf {
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

pub fn dist_dir() -> PathBuf {
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

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A child process killed on drop.
pub struct Proc(pub Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub fn start_server(port: u16, db: &Path) -> Proc {
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

pub fn start_chromedriver(port: u16) -> Proc {
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
pub fn http(port: u16, method: &str, path: &str, auth: Option<&str>, body: &str) -> (u16, String) {
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

pub fn run_iterations(port: u16) -> (u64, u64, String) {
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

pub async fn text(c: &Client, css: &str) -> Option<String> {
    c.find(Locator::Css(css)).await.ok()?.text().await.ok()
}

pub async fn attr(c: &Client, css: &str, name: &str) -> Option<String> {
    c.find(Locator::Css(css))
        .await
        .ok()?
        .attr(name)
        .await
        .ok()?
}

pub async fn iterations_drawn(c: &Client) -> u64 {
    attr(c, "canvas[data-chart=parameter-t_sr]", "data-iterations")
        .await
        .and_then(|s| s.parse().ok())
        .unwrap_or(0)
}

/// Poll `check` every 100 ms until it returns `Some`, or fail after `secs`.
pub async fn wait<T>(what: &str, secs: u64, mut check: impl AsyncFnMut() -> Option<T>) -> T {
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

pub async fn wait_text(c: &Client, css: &str, needle: &str, secs: u64) -> String {
    wait(
        &format!("`{css}` to contain {needle:?}"),
        secs,
        async || text(c, css).await.filter(|t| t.contains(needle)),
    )
    .await
}

pub async fn click(c: &Client, css: &str) {
    c.find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css}: {e}"))
        .click()
        .await
        .unwrap_or_else(|e| panic!("click {css}: {e}"));
}

pub async fn type_into(c: &Client, css: &str, value: &str) {
    let el = c
        .find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css}: {e}"));
    el.clear().await.unwrap();
    el.send_keys(value).await.unwrap();
}

/// Set an input's value and fire its `change` event (as after typing and
/// leaving the field).
pub async fn set_value(c: &Client, css: &str, value: &str) {
    let script = format!(
        "const e = document.querySelector('{css}'); if (!e) return false; e.value = '{value}'; e.dispatchEvent(new Event('change', {{bubbles: true}})); return true;"
    );
    let found = c.execute(&script, vec![]).await.unwrap();
    assert_eq!(found.as_bool(), Some(true), "no {css}");
}

pub async fn screenshot(c: &Client, name: &str) {
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

pub async fn browser(driver_port: u16) -> Client {
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
