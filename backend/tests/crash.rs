//! Crash test: the real binary as a process, `kill -9` mid-run, restart on the
//! same store, resume. No committed iteration may be lost, and the resumed
//! trajectory must equal an uninterrupted run of the same seed, bit for bit.

mod common;

use std::time::{Duration, Instant};

use common::*;
use serde_json::Value;
use spintune::driver::SimulationRun;
use spintune::protocol::RunStatus;
use spintune_server::config::RunConfig;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_mid_run_then_resume_continues_bit_identically() {
    let dir = TempDir::new("crash");
    let db = dir.0.join("crash.db");
    let n: u64 = 10;
    let config = small_config("crash", n, 40);

    let (proc1, addr) = spawn_server(&db);
    let run = create_run(addr, &config).await;
    wait_status(addr, run.id, |r| r.iterations >= 4).await;
    let seen_before = records(addr, run.id).await;
    assert!(seen_before.len() >= 4);
    // SIGKILL, no chance to clean up.
    proc1.kill_9();

    let (_proc2, addr) = spawn_server(&db);
    let listed = get_run(addr, run.id).await;
    assert_eq!(listed.status, RunStatus::Interrupted, "{listed:?}");
    assert!(listed.iterations >= seen_before.len() as u64);
    assert!(
        listed.iterations < n,
        "the run finished before the kill; make it slower"
    );
    let after_restart = records(addr, run.id).await;
    assert_eq!(
        &after_restart[..seen_before.len()],
        &seen_before[..],
        "a committed iteration was lost or changed"
    );

    let (s, body) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let done = wait_status(addr, run.id, is_finished).await;
    assert_eq!(done.iterations, n);
    let resumed = records(addr, run.id).await;

    // The same config, uninterrupted, in the core's own synchronous driver.
    let (s, cfg) = http(
        addr,
        "GET",
        &format!("/api/runs/{}/config", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200);
    let cfg: RunConfig = serde_json::from_str(&cfg).unwrap();
    let mut sim = SimulationRun::new(cfg.simulation).unwrap();
    let mut reference = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(30);
    while let Some(r) = sim.next_iteration().unwrap() {
        reference.push(serde_json::to_value(&r).unwrap());
        assert!(Instant::now() < deadline);
    }
    assert_eq!(reference.len(), n as usize);
    for (k, (a, b)) in resumed.iter().zip(&reference).enumerate() {
        assert_eq!(a, b, "iteration {k} differs from the uninterrupted run");
    }

    // And an uninterrupted server run of the same config gives the same records.
    let again = create_run(addr, &config).await;
    wait_status(addr, again.id, is_finished).await;
    assert_eq!(records(addr, again.id).await, resumed);

    // Export works on the stored run (CLI, same store while the server runs).
    let out = spintune()
        .args(["export", &run.id.to_string(), "--format", "json", "--db"])
        .arg(&db)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<Value> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(rows.len(), n as usize);
    assert!(rows[0].get("V_SB_mV").is_some(), "{}", rows[0]);
    assert!(rows[0].get("t_sr_ns").is_some(), "{}", rows[0]);
}

/// A keep-mode run (issue 23) killed while keeping resumes keeping after a
/// restart: no committed record lost, check records after the restart, and
/// the whole trajectory equals an uninterrupted run bit for bit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_while_keeping_then_resume_keeps_keeping() {
    let dir = TempDir::new("crash-keep");
    let db = dir.0.join("crash-keep.db");
    let config = serde_json::json!({
        "name": "keep crash",
        "seed": 7,
        "iteration_delay_ms": 60,
        "tuner": { "keep": { "duration_s": 10800.0, "min_check_interval_s": 60.0 } }
    });
    let is_check = |r: &Value| r["keep"]["phase"] == "check";

    let (proc1, addr) = spawn_server(&db);
    let run = create_run(addr, &config).await;
    let deadline = Instant::now() + Duration::from_secs(60);
    let seen_before = loop {
        let recs = records(addr, run.id).await;
        if recs.iter().filter(|r| is_check(r)).count() >= 2 {
            break recs;
        }
        assert!(Instant::now() < deadline, "no keep checks in time");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    proc1.kill_9();

    let (_proc2, addr) = spawn_server(&db);
    let listed = get_run(addr, run.id).await;
    assert_eq!(listed.status, RunStatus::Interrupted, "{listed:?}");
    let after_restart = records(addr, run.id).await;
    assert_eq!(
        &after_restart[..seen_before.len()],
        &seen_before[..],
        "a committed record was lost or changed"
    );
    let (s, body) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    wait_status(addr, run.id, is_finished).await;
    let resumed = records(addr, run.id).await;
    assert!(
        resumed[after_restart.len()..].iter().any(is_check),
        "no check after the restart"
    );
    let last = resumed.last().unwrap();
    assert!(
        last["lab_seconds"].as_f64().unwrap() > 2.0 * 3600.0,
        "{last}"
    );

    let (s, cfg) = http(
        addr,
        "GET",
        &format!("/api/runs/{}/config", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200);
    let cfg: RunConfig = serde_json::from_str(&cfg).unwrap();
    let mut sim = SimulationRun::new(cfg.simulation).unwrap();
    let mut reference = Vec::new();
    while let Some(r) = sim.next_iteration().unwrap() {
        reference.push(serde_json::to_value(&r).unwrap());
    }
    assert_eq!(reference.len(), resumed.len());
    for (k, (a, b)) in resumed.iter().zip(&reference).enumerate() {
        assert_eq!(a, b, "record {k} differs from the uninterrupted run");
    }
}
