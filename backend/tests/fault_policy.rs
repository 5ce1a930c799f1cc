//! The fault policy against the real server and a scripted lab bridge that
//! lies (ARCHITECTURE.md, invariant 5; issue 20):
//!
//! * a fault that needs a person (an instrument error such as leakage, a
//!   refused read-back) is not cleared by the bridge reconnecting: nothing is
//!   requested until a person resumes;
//! * a read-back that is not finite, 1e308 or outside the gate's limits
//!   faults the run with nothing moved;
//! * a gate that reads 50 mV from where the run left it faults on resume
//!   (`moved`) and waits for `accept_positions`; after it, every physical
//!   step stays within `max_step_mv`;
//! * a bridge that reconnects while the fault's status write waits on a busy
//!   store still resumes the run (no lost wake-up), every time.

mod common;

use std::path::Path;
use std::time::Duration;

use common::bridge_client::*;
use common::*;
use serde_json::{json, Value};
use spintune::driver::SimulationRun;
use spintune::protocol::{BridgeServerMessage, FaultKind, Request, Response, RunStatus};
use spintune::sim::SimulatedDevice;
use spintune_server::config::RunConfig;

fn bridge_config(name: &str, iterations: u64) -> Value {
    json!({
        "name": name,
        "seed": 5,
        "iteration_delay_ms": 0,
        "driver": "bridge",
        "bridge": { "request_timeout_s": 5.0 },
        "tuner": { "max_iterations": iterations, "stop_when_tuned": false }
    })
}

/// The lab's device: the simulated dot of `config`.
fn lab_device(config: &Value) -> SimulatedDevice {
    let parsed = RunConfig::from_json_str(&config.to_string()).unwrap();
    SimulationRun::new(parsed.simulation)
        .unwrap()
        .device()
        .clone()
}

/// Answer the read request `read` (id `id`) from `device`, but with `gate`
/// reported at `lie_mv`.
async fn answer_read_lying(
    ws: &mut Ws,
    device: &mut SimulatedDevice,
    id: u64,
    read: &Request,
    gate: &str,
    lie_mv: f64,
) {
    answer_lying(ws, id, device.execute(read), gate, lie_mv).await;
}

/// Serve requests honestly from `device`, checking each against the
/// physical state, until the run has `iterations` committed (or is over).
async fn serve_until(
    ws: &mut Ws,
    device: &mut SimulatedDevice,
    addr: std::net::SocketAddr,
    id: u64,
    iterations: u64,
) -> Vec<String> {
    let mut violations = Vec::new();
    serve_until_with(ws, addr, id, iterations, |request| {
        violations.extend(physical_violation(device, request));
        device.execute(request)
    })
    .await;
    violations
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn faults_that_need_a_person_survive_a_bridge_reconnect() {
    let dir = TempDir::new("policy-person");
    let (_p, addr) = spawn_server(&dir.0.join("s.db"));
    let cfg = bridge_config("leakage", 4);
    let mut device = lab_device(&cfg);
    let run = create_run(addr, &cfg).await;
    let mut ws = bridge(addr, run.id).await;
    serve(&mut ws, &mut device, 12).await;

    // 1. The lab's script reports leakage on a move.
    let (id, _) = next_request_reading(&mut ws, &mut device).await;
    answer(
        &mut ws,
        id,
        Response::error("leakage on SB: 500 nA exceeds 100 nA"),
    )
    .await;
    let fault = faulted(addr, run.id).await;
    assert_eq!(fault.kind, FaultKind::Device, "{fault}");
    assert_eq!(fault.cleared_by.name(), "resume");
    // The bridge drops and reconnects: the run stays faulted, nothing is sent.
    drop(ws);
    let mut ws = bridge(addr, run.id).await;
    assert!(silent_for(&mut ws, 1500).await, "a request after reconnect");
    let after = get_run(addr, run.id).await;
    assert!(
        matches!(&after.status, RunStatus::Faulted { fault } if fault.kind == FaultKind::Device),
        "{:?}",
        after.status
    );

    // 2. A person resumes; the read-back of every gate is refused (a gate
    //    reported 150 mV outside its limits); a reconnect does not clear that either.
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let (id, read) = next_any_request(&mut ws).await;
    let Request::ReadVoltages { .. } = &read else {
        panic!("resume must read every gate first: {read:?}")
    };
    answer_read_lying(&mut ws, &mut device, id, &read, "N", 1e308).await;
    let fault = faulted(addr, run.id).await;
    assert_eq!(fault.kind, FaultKind::Readback, "{fault}");
    assert!(fault.message.contains("outside its limits"), "{fault}");
    drop(ws);
    let mut ws = bridge(addr, run.id).await;
    assert!(silent_for(&mut ws, 1500).await, "a request after reconnect");

    // 3. A person resumes with an honest instrument: the run finishes
    //    (served until its status is terminal: its 4th iteration is
    //    committed before the run is marked finished, so a count of 4
    //    alone would race that write).
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let violations = serve_until(&mut ws, &mut device, addr, run.id, u64::MAX).await;
    assert!(violations.is_empty(), "{violations:?}");
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Finished);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn impossible_read_backs_fault_with_nothing_moved() {
    let dir = TempDir::new("policy-impossible");
    let (_p, addr) = spawn_server(&dir.0.join("s.db"));
    let cfg = bridge_config("impossible", 2);
    let mut device = lab_device(&cfg);
    let spec = spintune::sim::default_gates()
        .into_iter()
        .find(|g| g.name == "N")
        .unwrap();
    let run = create_run(addr, &cfg).await;
    let mut ws = bridge(addr, run.id).await;
    // The very first read of a new run: N reported as each impossible value in turn.
    for (k, lie) in [1e308, spec.min_mv - 50.0, spec.max_mv + 5.0]
        .into_iter()
        .enumerate()
    {
        if k > 0 {
            let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
            assert_eq!(s, 200, "{b}");
        }
        let (id, read) = next_any_request(&mut ws).await;
        assert!(matches!(read, Request::ReadVoltages { .. }), "{read:?}");
        answer_read_lying(&mut ws, &mut device, id, &read, "N", lie).await;
        let fault = faulted(addr, run.id).await;
        assert_eq!(fault.kind, FaultKind::Readback, "{lie}: {fault}");
        assert!(silent_for(&mut ws, 500).await, "{lie}: something moved");
    }
    // Nothing was recorded, nothing finished: the run waits, faulted.
    assert!(records(addr, run.id).await.is_empty());
    // The bridge's NaN cannot even be written in JSON: a `null` read-back is malformed.
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let (id, _) = next_any_request(&mut ws).await;
    send(
        &mut ws,
        &format!(
            r#"{{"type":"response","id":{id},"response":{{"response":"voltages_read","voltages_mv":{{"N":null}}}}}}"#
        ),
    )
    .await;
    assert!(matches!(
        next_bridge(&mut ws).await,
        BridgeServerMessage::Error { message } if message.contains("malformed")
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gate_50_mv_from_where_it_was_left_waits_for_accept_positions() {
    let dir = TempDir::new("policy-moved");
    let (_p, addr) = spawn_server(&dir.0.join("s.db"));
    let cfg = bridge_config("moved", 10_000);
    let mut device = lab_device(&cfg);
    let run = create_run(addr, &cfg).await;
    let mut ws = bridge(addr, run.id).await;
    let violations = serve_until(&mut ws, &mut device, addr, run.id, 1).await;
    assert!(violations.is_empty(), "{violations:?}");
    // Pause; serve the request that was at the device when the pause came.
    let (s, b) = control(addr, run.id, r#"{"action":"pause"}"#).await;
    assert_eq!(s, 200, "{b}");
    while let Ok(frame) =
        tokio::time::timeout(Duration::from_millis(300), next_bridge(&mut ws)).await
    {
        if let BridgeServerMessage::Request { id, request, .. } = frame {
            let resp = device.execute(&request);
            answer(&mut ws, id, resp).await;
        }
    }
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Paused);
    // Someone moves N by 50 mV (5× its step limit) by hand.
    let n = device.voltages_mv()["N"];
    device.execute(&Request::SetVoltages {
        voltages_mv: [("N".to_string(), n - 50.0)].into(),
    });
    // accept_positions is refused while the run is merely paused.
    let (s, _) = control(addr, run.id, r#"{"action":"accept_positions"}"#).await;
    assert_eq!(s, 409);
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    // The resumed run reads every gate, finds N 50 mV away and moves nothing.
    let fault = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            tokio::select! {
                frame = next_bridge(&mut ws) => {
                    if let BridgeServerMessage::Request { id, request, .. } = frame {
                        assert!(
                            matches!(request, Request::ReadVoltages { .. }),
                            "moved before the positions were confirmed: {request:?}"
                        );
                        let resp = device.execute(&request);
                        answer(&mut ws, id, resp).await;
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(50)) => {
                    if let RunStatus::Faulted { fault } = get_run(addr, run.id).await.status {
                        return fault;
                    }
                }
            }
        }
    })
    .await
    .expect("no moved fault");
    assert_eq!(fault.kind, FaultKind::Moved, "{fault}");
    assert_eq!(fault.moved.len(), 1, "{fault:?}");
    assert_eq!(fault.moved[0].gate, "N");
    assert_eq!(fault.moved[0].read_mv, n - 50.0);
    assert!((fault.moved[0].left_from_mv - n).abs() < 1e-9, "{fault:?}");
    assert!(silent_for(&mut ws, 500).await);
    // Resume alone re-reads and faults again (N is still there).
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let (id, read) = next_any_request(&mut ws).await;
    assert!(matches!(read, Request::ReadVoltages { .. }), "{read:?}");
    let resp = device.execute(&read);
    answer(&mut ws, id, resp).await;
    assert_eq!(faulted(addr, run.id).await.kind, FaultKind::Moved);
    // A person confirms: paused; resume continues from N's new position,
    // every physical step within the limit.
    let (s, b) = control(addr, run.id, r#"{"action":"accept_positions"}"#).await;
    assert_eq!(s, 200, "{b}");
    let v: Value = serde_json::from_str(&b).unwrap();
    assert_eq!(v["status"]["state"], "paused", "{b}");
    let (s, b) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let committed = get_run(addr, run.id).await.iterations;
    let violations = serve_until(&mut ws, &mut device, addr, run.id, committed + 5).await;
    assert!(violations.is_empty(), "{violations:?}");
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Running);
    let recs = records(addr, run.id).await;
    assert!(
        recs.iter().any(|r| r["events"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["event"] == "instrument_moved" && e["gate"] == "N")),
        "the accepted move of N is not in the record"
    );
}

fn lock_store(db: &Path) -> rusqlite::Connection {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.execute_batch("BEGIN IMMEDIATE;").unwrap();
    conn
}

/// The lost wake-up of issue 20: the bridge drops and reconnects while the
/// fault's status write waits on a store held busy by another writer. When
/// the store frees up, the run must resume on the new bridge. Repeated.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bridge_reconnecting_during_the_fault_write_resumes_the_run_every_time() {
    let dir = TempDir::new("policy-race");
    let db = dir.0.join("s.db");
    let (_p, addr) = spawn_server(&db);
    let cfg = bridge_config("race", 1_000);
    let mut device = lab_device(&cfg);
    let run = create_run(addr, &cfg).await;
    let mut ws = bridge(addr, run.id).await;
    serve(&mut ws, &mut device, 5).await;
    for round in 0..5 {
        // A request is at the bridge; the store is held busy; the bridge drops.
        let (_id, _req) = next_request_reading(&mut ws, &mut device).await;
        let lock = lock_store(&db);
        drop(ws);
        // Let the task see the disconnect and block on the status write.
        tokio::time::sleep(Duration::from_millis(300)).await;
        // The bridge reconnects while the write still waits.
        let mut next = bridge(addr, run.id).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
        drop(lock);
        // The run resumes on the new bridge: every gate is read first.
        let (id, read) = tokio::time::timeout(Duration::from_secs(15), next_any_request(&mut next))
            .await
            .unwrap_or_else(|_| {
                panic!("round {round}: the run stayed faulted with a bridge connected")
            });
        assert!(
            matches!(&read, Request::ReadVoltages { gates } if gates.len() == 11),
            "round {round}: {read:?}"
        );
        let resp = device.execute(&read);
        answer(&mut next, id, resp).await;
        serve(&mut next, &mut device, 3).await;
        ws = next;
    }
}
