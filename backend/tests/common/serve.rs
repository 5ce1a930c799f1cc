//! The one serve-process spawner of the process-level tests: the real
//! `spintune serve` binary on an ephemeral loopback port, waited for (its
//! printed address, with a timeout) and killed on drop.

use std::ffi::{OsStr, OsString};
use std::io::{BufRead, BufReader, Read};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use tokio::sync::mpsc;

use super::TOKEN;

/// How long `serve` may take to print its address, or to exit when it must refuse.
pub const SERVE_START: Duration = Duration::from_secs(20);

/// The `spintune` binary under test, as a command (add the subcommand).
pub fn spintune() -> Command {
    Command::new(env!("CARGO_BIN_EXE_spintune"))
}

/// A child process killed (SIGKILL) and reaped on drop.
pub struct Proc(pub Child);

impl Proc {
    /// `kill -9` now and reap it (a crash, no chance to clean up).
    pub fn kill_9(mut self) {
        self.0.kill().unwrap();
        self.0.wait().unwrap();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A `spintune serve` command line: loopback, ephemeral port, the store `db`,
/// no demo, the token [`TOKEN`] as `--token`, no dashboard (`no-dist` beside
/// `db`), nothing from `SPINTUNE_TOKEN`/`SPINTUNE_TOKEN_FILE` of the
/// environment; change any of it with the methods.
#[derive(Debug, Clone)]
pub struct Serve {
    db: PathBuf,
    demo: &'static str,
    token_flag: bool,
    args: Vec<OsString>,
    env: Vec<(OsString, OsString)>,
    scheme: &'static str,
}

impl Serve {
    pub fn new(db: &Path) -> Self {
        Self {
            db: db.to_path_buf(),
            demo: "never",
            token_flag: true,
            args: Vec::new(),
            env: Vec::new(),
            scheme: "http",
        }
    }

    /// `--demo MODE` (`never`, `auto`, `always`).
    pub fn demo(mut self, mode: &'static str) -> Self {
        self.demo = mode;
        self
    }

    /// No `--token` (the token then comes from [`Serve::env`] or flags).
    pub fn without_token_flag(mut self) -> Self {
        self.token_flag = false;
        self
    }

    /// More flags.
    pub fn args<I, S>(mut self, args: I) -> Self
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        self.args
            .extend(args.into_iter().map(|a| a.as_ref().to_owned()));
        self
    }

    /// An environment variable of the process.
    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.into(), value.into()));
        self
    }

    /// It serves HTTPS (expect `Dashboard: https://…`).
    pub fn https(mut self) -> Self {
        self.scheme = "https";
        self
    }

    /// The command (no stdio set).
    pub fn command(&self) -> Command {
        let mut cmd = spintune();
        cmd.args(["serve", "--bind", "127.0.0.1:0", "--demo", self.demo]);
        if self.token_flag {
            cmd.args(["--token", TOKEN]);
        }
        cmd.arg("--db")
            .arg(&self.db)
            .arg("--dist")
            .arg(self.db.with_file_name("no-dist"))
            .args(&self.args)
            .env_remove("SPINTUNE_TOKEN")
            .env_remove("SPINTUNE_TOKEN_FILE");
        for (k, v) in &self.env {
            cmd.env(k, v);
        }
        cmd
    }

    /// Start it, stdout and stderr piped.
    fn start(&self) -> Child {
        self.command()
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn spintune serve")
    }

    /// Start it and wait (at most [`SERVE_START`]) until it printed its
    /// address and its store; its stderr lines are echoed (`server: …`) and
    /// kept in [`Served::stderr`].
    pub fn spawn(&self) -> Served {
        let mut child = self.start();
        let stdout = child.stdout.take().unwrap();
        let stderr = child.stderr.take().unwrap();
        let proc = Proc(child);
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            // Everything up to the `Store:` line, which follows the address
            // and the token's source; then keep draining the pipe.
            let (mut printed, mut url) = (String::new(), None);
            let mut started = Some(tx);
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let Some(tx) = &started else { continue };
                printed.push_str(&line);
                printed.push('\n');
                if let Some(rest) = line.strip_prefix("Dashboard: ") {
                    url = Some(rest.trim_end_matches('/').to_string());
                }
                if line.starts_with("Store:") {
                    let _ = tx.send((url.take(), std::mem::take(&mut printed)));
                    started = None;
                }
            }
        });
        let (etx, erx) = mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                eprintln!("server: {line}");
                let _ = etx.send(line);
            }
        });
        let (url, printed) = rx
            .recv_timeout(SERVE_START)
            .expect("spintune serve did not print its address");
        let url = url.expect("spintune serve printed no `Dashboard:` line");
        let addr = url
            .strip_prefix(&format!("{}://", self.scheme))
            .unwrap_or_else(|| panic!("expected a {}:// URL, got {url:?}", self.scheme));
        Served {
            proc,
            addr: addr.parse().unwrap(),
            printed,
            stderr: erx,
        }
    }

    /// Run it expecting it to exit (a refused start), at most
    /// [`SERVE_START`]; its output.
    pub fn exit(&self) -> Output {
        let mut child = self.start();
        let read = |mut pipe: Box<dyn Read + Send>| {
            std::thread::spawn(move || {
                let mut buf = Vec::new();
                let _ = pipe.read_to_end(&mut buf);
                buf
            })
        };
        let stdout = read(Box::new(child.stdout.take().unwrap()));
        let stderr = read(Box::new(child.stderr.take().unwrap()));
        let mut proc = Proc(child);
        let deadline = Instant::now() + SERVE_START;
        let status = loop {
            if let Some(status) = proc.0.try_wait().unwrap() {
                break status;
            }
            assert!(
                Instant::now() < deadline,
                "spintune serve kept running; expected it to refuse to start"
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        Output {
            status,
            stdout: stdout.join().unwrap(),
            stderr: stderr.join().unwrap(),
        }
    }
}

/// A running `spintune serve` (killed on drop, through [`Proc`]).
pub struct Served {
    pub proc: Proc,
    pub addr: SocketAddr,
    /// Its stdout up to its `Store:` line (address, token source, store).
    pub printed: String,
    /// Its stderr, a line at a time.
    pub stderr: mpsc::UnboundedReceiver<String>,
}

impl Served {
    /// Wait (at most `within`) for a stderr line containing `needle`.
    pub async fn stderr_line(&mut self, needle: &str, within: Duration) -> String {
        tokio::time::timeout(within, async {
            loop {
                let line = self.stderr.recv().await.expect("server stderr closed");
                if line.contains(needle) {
                    return line;
                }
            }
        })
        .await
        .unwrap_or_else(|_| panic!("no server log line with {needle:?} within {within:?}"))
    }
}

/// `spintune serve` with the store `db` ([`Serve::new`]); the process and its address.
pub fn spawn_server(db: &Path) -> (Proc, SocketAddr) {
    let served = Serve::new(db).spawn();
    (served.proc, served.addr)
}
