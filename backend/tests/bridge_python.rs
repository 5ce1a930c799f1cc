//! `examples/bridge_client.py` against a real server: the Python client
//! serves a bridge run to the end; killing it pauses the run, starting it
//! again resumes it, and every iteration is stored once.
//!
//! Needs `python3`. The client's one dependency (`websockets`) is
//! pip-installed into a cache directory under the system temp dir if it is
//! not importable. Without python3 (or when the install fails) this test
//! FAILS with an explanation; set `SPINTUNE_SKIP_PYTHON=1` to skip it
//! explicitly (it then says so on stderr).

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use common::*;
use serde_json::json;
use spintune::protocol::RunStatus;

fn skip_or_fail(why: &str) {
    if std::env::var("SPINTUNE_SKIP_PYTHON").is_ok_and(|v| v == "1") {
        eprintln!("\n*** SKIPPED bridge_client.py test: {why} (SPINTUNE_SKIP_PYTHON=1) ***\n");
        return;
    }
    panic!(
        "the bridge_client.py test cannot run: {why}.\n\
         Install python3 (and let pip reach PyPI), or set SPINTUNE_SKIP_PYTHON=1 to skip this test explicitly."
    );
}

/// `PYTHONPATH` under which `import websockets` works, or why not.
fn websockets_path() -> Result<Option<PathBuf>, String> {
    let can_import = |path: Option<&Path>| {
        let mut c = Command::new("python3");
        c.args(["-c", "import websockets"]);
        if let Some(p) = path {
            c.env("PYTHONPATH", p);
        }
        c.stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    };
    if can_import(None) {
        return Ok(None);
    }
    let dir = std::env::temp_dir().join("spintune-pydeps-websockets");
    if can_import(Some(&dir)) {
        return Ok(Some(dir));
    }
    eprintln!("installing `websockets` from PyPI into {}", dir.display());
    let out = Command::new("python3")
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--target",
        ])
        .arg(&dir)
        .arg("websockets")
        .output()
        .map_err(|e| format!("cannot run pip: {e}"))?;
    if !out.status.success() || !can_import(Some(&dir)) {
        return Err(format!(
            "pip install websockets failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    Ok(Some(dir))
}

/// Kills the client (a process this test started) when dropped.
struct Client(Child);

impl Client {
    fn start(url: &str, pythonpath: Option<&Path>, extra: &[&str]) -> Self {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/bridge_client.py");
        let mut c = Command::new("python3");
        c.arg(script)
            .args(["--url", url, "--token", TOKEN])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        if let Some(p) = pythonpath {
            c.env("PYTHONPATH", p);
        }
        Self(c.spawn().expect("start bridge_client.py"))
    }

    fn stop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        self.stop();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_bridge_client_serves_a_run_and_reconnects() {
    let python = Command::new("python3")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !python {
        return skip_or_fail("python3 was not found on PATH");
    }
    let pythonpath = match websockets_path() {
        Ok(p) => p,
        Err(why) => return skip_or_fail(&why),
    };

    let dir = TempDir::new("pybridge");
    let srv = server(&dir, 256).await;
    let n = 4;
    let run = create_run(
        srv.addr,
        &json!({
            "name": "python bridge",
            "seed": 5,
            "iteration_delay_ms": 0,
            "driver": "bridge",
            "bridge": { "request_timeout_s": 10.0 },
            "tuner": { "max_iterations": n, "stop_when_tuned": false }
        }),
    )
    .await;
    let url = format!("ws://{}/api/runs/{}/bridge", srv.addr, run.id);

    // The lab script answers 180 requests (more than one iteration), then
    // goes away with the next one outstanding: the run pauses, saying why.
    let mut first = Client::start(&url, pythonpath.as_deref(), &["--exit-after", "180"]);
    let paused = wait_status(srv.addr, run.id, |r| {
        // (Before the script connects the run waits, paused for lack of a bridge.)
        matches!(&r.status, RunStatus::Faulted { fault } if fault.message.contains("disconnected"))
            || r.status == RunStatus::Finished
    })
    .await;
    match &paused.status {
        RunStatus::Faulted { fault } => assert!(
            fault
                .message
                .contains("lab bridge disconnected while request 181"),
            "{fault}"
        ),
        other => panic!("expected a pause, got {other:?}"),
    }
    assert!(paused.iterations < n, "{paused:?}");
    first.stop();
    let before = records(srv.addr, run.id).await;
    // It comes back: the run resumes by itself and finishes.
    let _client = Client::start(&url, pythonpath.as_deref(), &[]);
    let done = wait_status(srv.addr, run.id, is_finished).await;
    assert_eq!(done.iterations, n);
    let stored = records(srv.addr, run.id).await;
    assert_eq!(stored.len() as u64, n);
    assert_eq!(stored[..before.len()], before[..]);
    for (k, r) in stored.iter().enumerate() {
        assert_eq!(r["iteration"], k as u64);
        // Evaluated values from the toy model: t_sr and w are measured.
        let params = r["parameters"].as_array().unwrap();
        for name in ["t_sr", "w"] {
            let p = params.iter().find(|p| p["name"] == name).unwrap();
            assert!(p["value"].is_f64(), "iteration {k}: {name} missing: {p}");
            assert!(p["std"].as_f64().unwrap() > 0.0);
        }
    }
}
