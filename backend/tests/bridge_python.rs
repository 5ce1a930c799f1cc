//! `examples/bridge_client.py` against a real server: the Python client
//! serves a bridge run to the end; killing it pauses the run, starting it
//! again resumes it, and every iteration is stored once.
//!
//! Needs a Python with `websockets` in `SPINTUNE_PYTHON` (the test command,
//! `cargo xtask test`, sets up that environment first; nothing is installed
//! here). Without it the test fails and says so.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use common::*;
use serde_json::json;
use spintune::protocol::RunStatus;

/// The interpreter prepared by the test command.
fn python() -> PathBuf {
    let p = std::env::var_os("SPINTUNE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            panic!(
            "SPINTUNE_PYTHON is not set: run the tests with `cargo xtask test`, or point it at a \
             Python that has `websockets` installed"
        )
        });
    assert!(
        p.is_file(),
        "SPINTUNE_PYTHON={} does not exist",
        p.display()
    );
    let ok = Command::new(&p)
        .args(["-c", "import websockets"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(ok, "{} cannot import websockets", p.display());
    p
}

/// Kills the client (a process this test started) when dropped.
struct Client(Child);

impl Client {
    fn start(url: &str, python: &Path, extra: &[&str]) -> Self {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/bridge_client.py");
        let mut c = Command::new(python);
        c.arg(script)
            .args(["--url", url, "--token", TOKEN])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null());
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
    let python = python();

    let dir = TempDir::new("pybridge");
    let srv = server(&dir, 256).await;
    // enough iterations that `ANSWERS` answers end mid-run with the
    // recommended tuner's cheaper cold start and skipped scans
    let n = 40;
    const ANSWERS: usize = 90;
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

    // The lab script answers ANSWERS requests (more than one iteration), then
    // goes away with the next one outstanding: the run pauses, saying why.
    // The toy instrument keeps its outputs across the restart, as a DAC does.
    let state = dir.0.join("toy-instrument.json");
    let state = state.to_str().unwrap();
    let answers = ANSWERS.to_string();
    let mut first = Client::start(&url, &python, &["--exit-after", &answers, "--state", state]);
    let paused = wait_status(srv.addr, run.id, |r| {
        // (Before the script connects the run waits, paused for lack of a bridge.)
        matches!(&r.status, RunStatus::Faulted { fault } if fault.message.contains("disconnected"))
            || r.status == RunStatus::Finished
    })
    .await;
    match &paused.status {
        RunStatus::Faulted { fault } => assert!(
            fault.message.contains(&format!(
                "lab bridge disconnected while request {}",
                ANSWERS + 1
            )),
            "{fault}"
        ),
        other => panic!("expected a pause, got {other:?} ({paused:?})"),
    }
    assert!(paused.iterations < n, "{paused:?}");
    first.stop();
    let before = records(srv.addr, run.id).await;
    // It comes back: the run resumes by itself and finishes.
    let _client = Client::start(&url, &python, &["--state", state]);
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

/// The same script serves an array run: a three-cell chain described in the
/// run config (`examples/array-lab.toml`'s cells, with one readout group
/// per cell), every scan naming its cell and every cell's gates prefixed;
/// the run ends with every cell in band, each cell's t_sr and w measured in
/// every record.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_bridge_client_serves_an_array_run_to_every_cell_in_band() {
    let python = python();
    let dir = TempDir::new("pybridge-array");
    let srv = server(&dir, 256).await;
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/array-lab.toml");
    let mut config: serde_json::Value =
        toml::from_str(&std::fs::read_to_string(example).unwrap()).unwrap();
    config["bridge"]["request_timeout_s"] = json!(10.0);
    // The toy's cells do not couple: the lab's calibration says so (with the
    // example's 0.3 the joint prior expects crosstalk that never comes; see
    // docs/array-history.md, "A calibration that is wrong").
    config["array"]["cross_calibration"] = json!([0.0, 0.0]);
    config["array"]["description"]
        .as_object_mut()
        .unwrap()
        .remove("readout_groups");
    let run = create_run(srv.addr, &config).await;
    let url = format!("ws://{}/api/runs/{}/bridge", srv.addr, run.id);
    let _client = Client::start(&url, &python, &[]);
    // (Until the script has connected the run waits, faulted for lack of a
    // bridge; that fault clears by itself. Any other fault ends the wait.)
    let done = wait_status(srv.addr, run.id, |r| {
        is_finished(r)
            || matches!(&r.status, RunStatus::Faulted { fault } if fault.kind != spintune::protocol::FaultKind::Disconnected)
    })
    .await;
    assert_eq!(done.status, RunStatus::Finished, "{done:?}");
    assert!(done.tuned, "{done:?}");
    let stored = records(srv.addr, run.id).await;
    assert!(!stored.is_empty());
    for r in &stored {
        let names: Vec<&str> = r["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            names,
            ["c0.t_sr", "c0.w", "c1.t_sr", "c1.w", "c2.t_sr", "c2.w"],
            "{r}"
        );
    }
    // every cell's last values are within the band of its targets (the toy's truth is its model)
    let last = stored.last().unwrap();
    for p in last["parameters"].as_array().unwrap() {
        let (v, t) = (p["value"].as_f64().unwrap(), p["target"].as_f64().unwrap());
        assert!((v - t).abs() <= 0.1 * t + 1e-9, "{p}");
    }
}
