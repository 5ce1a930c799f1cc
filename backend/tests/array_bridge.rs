//! An array of double dots on a lab's instruments (issue 24): the real
//! binary runs an array described in its config (`array.description`)
//! through the lab bridge, and a scripted bridge answers it — batches
//! included — from a simulated array standing in for the lab's:
//!
//! * honest, the run's records equal the same array run on the simulator
//!   bit for bit, and every request stays within each gate's limits and
//!   step of where the gate physically is;
//! * lying, dropping, stalling and answering short, the run faults; a fault
//!   that needs a person survives the bridge reconnecting; after `stop`
//!   nothing reaches the instrument.

mod common;

use std::time::Duration;

use common::bridge_client::*;
use common::*;
use serde_json::{json, Value};
use spintune::description::array::ArrayDescription;
use spintune::protocol::{BridgeServerMessage, FaultKind, Request, Response, RunStatus};
use spintune::safety::GateSpec;
use spintune::sim::array::ArrayDevice;
use spintune_server::config::RunConfig;

/// The simulated array's own description, as a lab would write it, with
/// cell 1's plunger PA given narrower limits of its own.
fn description() -> Value {
    let mut d = serde_json::to_value(ArrayDescription::simulated(3, None)).unwrap();
    d["cell_gates"] = json!([{ "cell": 1, "gates": [
        { "name": "PA", "min_mv": -500, "max_mv": -100, "initial_mv": -300, "max_step_mv": 30 }
    ]}]);
    d
}

fn config(driver: &str, timeout_s: f64) -> Value {
    json!({
        "iteration_delay_ms": 0,
        "driver": driver,
        "bridge": { "request_timeout_s": timeout_s },
        "array": {
            "name": "three cells on the bridge",
            "array": { "device_seed": 5, "seed": 2 },
            "targets": [[20.0, 270.0]],
            "description": description(),
        }
    })
}

/// The faults test's run: the same array and bridge with a band no
/// measurement meets (relative tolerance 10⁻⁶) and no iteration cap, so it
/// never finishes while faults are scripted. (The honest run is tuned in 5
/// iterations, and `serve_until` may serve more iterations than asked for
/// while it polls the run's progress: on a loaded machine it served this
/// run to the end before the faults were scripted, and the test failed.)
fn endless_config(timeout_s: f64) -> Value {
    let mut c = config("bridge", timeout_s);
    c["array"]["tuning"] = json!({ "relative_tolerance": 1e-6, "max_iterations": null });
    c
}

/// The lab's array: the world the simulator config draws.
fn lab(timeout_s: f64) -> (ArrayDevice, Vec<GateSpec>) {
    let parsed = RunConfig::from_json_str(&config("simulator", timeout_s).to_string()).unwrap();
    let array = parsed.array.unwrap();
    (array.build_world().unwrap(), array.gates().unwrap())
}

/// Checks one request against the lab's physical state: every gate it sets
/// or sweeps within its limits and within its step of where it is.
fn violations(device: &ArrayDevice, gates: &[GateSpec], req: &Request, out: &mut Vec<String>) {
    let now = device.voltages_mv();
    let mut check = |g: &str, v: f64| {
        let Some(s) = gates.iter().find(|s| s.name == g) else {
            out.push(format!("{g}: not a described gate"));
            return;
        };
        if !(s.min_mv..=s.max_mv).contains(&v) {
            out.push(format!("{g}: {v} mV outside [{}, {}]", s.min_mv, s.max_mv));
        }
        if (v - now[g]).abs() > s.max_step_mv + 1e-9 {
            out.push(format!(
                "{g}: step {} mV from {} mV",
                (v - now[g]).abs(),
                now[g]
            ));
        }
    };
    match req {
        Request::SetVoltages { voltages_mv } => {
            voltages_mv.iter().for_each(|(g, &v)| check(g, v));
        }
        Request::Measure { scan } => {
            if let Some(s) = &scan.sweep {
                check(&s.gate, s.from_mv);
                check(&s.gate, s.to_mv);
            }
        }
        Request::Batch { requests } => {
            for r in requests {
                violations(device, gates, r, out);
            }
        }
        _ => {}
    }
}

/// Serve honestly, checking every request, until the run has at least
/// `iterations` committed (possibly more: progress is polled) or is over.
async fn serve_until(
    ws: &mut Ws,
    lab: &mut (ArrayDevice, Vec<GateSpec>),
    addr: std::net::SocketAddr,
    id: u64,
    iterations: u64,
) -> Vec<String> {
    let mut found = Vec::new();
    serve_until_with(ws, addr, id, iterations, |request| {
        violations(&lab.0, &lab.1, request, &mut found);
        lab.0.execute(request)
    })
    .await;
    found
}

/// The run is still running (the faults test's run never finishes by
/// itself: `endless_config`).
async fn assert_going(addr: std::net::SocketAddr, id: u64) {
    let run = get_run(addr, id).await;
    assert_eq!(run.status, RunStatus::Running, "{run:?}");
}

async fn act(addr: std::net::SocketAddr, id: u64, action: &str) -> Value {
    let (s, b) = control(addr, id, &format!(r#"{{"action":"{action}"}}"#)).await;
    assert_eq!(s, 200, "{action}: {b}");
    serde_json::from_str(&b).unwrap()
}

/// Answer the next request, which must be a read of every gate, from the
/// lab with `gate` reported at `lie_mv`.
async fn answer_read_lying(ws: &mut Ws, device: &mut ArrayDevice, gate: &str, lie_mv: f64) {
    let (id, read) = next_any_request(ws).await;
    assert!(matches!(read, Request::ReadVoltages { .. }), "{read:?}");
    answer_lying(ws, id, device.execute(&read), gate, lie_mv).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_array_on_the_lab_bridge_runs_as_the_simulated_one_within_every_limit() {
    let dir = TempDir::new("array-bridge");
    let (_p, addr) = spawn_server(&dir.0.join("s.db"));
    // The reference: the same described array run on the simulator, in process.
    let parsed = RunConfig::from_json_str(&config("simulator", 5.0).to_string()).unwrap();
    let mut reference_run = parsed.array.unwrap().build().unwrap();
    let mut reference = Vec::new();
    while let Some(r) = reference_run.next_iteration().unwrap() {
        reference.push(serde_json::to_value(r).unwrap());
        assert!(reference.len() <= 200, "the reference run does not finish");
    }
    assert!(reference.last().unwrap()["tuned"].as_bool().unwrap());

    let mut lab = lab(5.0);
    let run = create_run(addr, &config("bridge", 5.0)).await;
    assert_eq!(run.driver.as_deref(), Some("bridge"));
    let mut ws = bridge(addr, run.id).await;
    let found = serve_until(&mut ws, &mut lab, addr, run.id, u64::MAX).await;
    assert!(found.is_empty(), "{found:?}");
    let done = get_run(addr, run.id).await;
    assert_eq!(done.status, RunStatus::Finished, "{done:?}");
    assert!(done.tuned, "{done:?}");
    assert_eq!(records(addr, run.id).await, reference);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_array_bridge_that_lies_drops_stalls_and_answers_short_faults_the_run() {
    let dir = TempDir::new("array-bridge-faults");
    let (_p, addr) = spawn_server(&dir.0.join("s.db"));
    let mut lab = lab(1.0);
    let run = create_run(addr, &endless_config(1.0)).await;
    let id = run.id;
    let mut ws = bridge(addr, id).await;

    // 1. The first read reports c2.PA at 1e308: a fault, nothing moved, and
    //    a reconnect does not clear it.
    answer_read_lying(&mut ws, &mut lab.0, "c2.PA", 1e308).await;
    let fault = faulted(addr, id).await;
    assert_eq!(fault.kind, FaultKind::Readback, "{fault}");
    assert!(fault.message.contains("c2.PA"), "{fault}");
    drop(ws);
    let mut ws = bridge(addr, id).await;
    assert!(silent_for(&mut ws, 1000).await, "a request after reconnect");
    assert!(records(addr, id).await.is_empty());

    // 2. A person resumes; the instrument is honest for two iterations.
    act(addr, id, "resume").await;
    let found = serve_until(&mut ws, &mut lab, addr, id, 2).await;
    assert!(found.is_empty(), "{found:?}");
    assert_going(addr, id).await;

    // 3. Paused, someone moves c1.SB by 50 mV by hand: the resumed run reads
    //    every gate, moves nothing and waits for a person's accept_positions,
    //    across a bridge reconnect.
    act(addr, id, "pause").await;
    while let Ok(frame) =
        tokio::time::timeout(Duration::from_millis(300), next_bridge(&mut ws)).await
    {
        if let BridgeServerMessage::Request { id, request, .. } = frame {
            let resp = lab.0.execute(&request);
            answer(&mut ws, id, resp).await;
        }
    }
    assert_eq!(get_run(addr, id).await.status, RunStatus::Paused);
    let sb = lab.0.voltages_mv()["c1.SB"];
    lab.0.execute(&Request::SetVoltages {
        voltages_mv: [("c1.SB".to_string(), sb - 50.0)].into(),
    });
    act(addr, id, "resume").await;
    let (rid, read) = next_any_request(&mut ws).await;
    assert!(
        matches!(read, Request::ReadVoltages { .. }),
        "moved before reading: {read:?}"
    );
    let resp = lab.0.execute(&read);
    answer(&mut ws, rid, resp).await;
    let fault = faulted(addr, id).await;
    assert_eq!(fault.kind, FaultKind::Moved, "{fault}");
    assert_eq!(fault.moved.len(), 1, "{fault:?}");
    assert_eq!(fault.moved[0].gate, "c1.SB");
    drop(ws);
    let mut ws = bridge(addr, id).await;
    assert!(silent_for(&mut ws, 1000).await, "a request after reconnect");
    let v = act(addr, id, "accept_positions").await;
    assert_eq!(v["status"]["state"], "paused", "{v}");
    act(addr, id, "resume").await;
    let committed = get_run(addr, id).await.iterations;
    let found = serve_until(&mut ws, &mut lab, addr, id, committed + 2).await;
    assert!(found.is_empty(), "{found:?}");
    assert_going(addr, id).await;

    // 4. A batch answered with one response short: a fault; nothing more.
    let (bid, batch) = loop {
        let (bid, req) = next_any_request(&mut ws).await;
        if let Request::Batch { requests } = &req {
            if requests.len() > 1 {
                break (bid, req);
            }
        }
        let resp = lab.0.execute(&req);
        answer(&mut ws, bid, resp).await;
    };
    let Response::Batch {
        mut responses,
        lab_seconds,
    } = lab.0.execute(&batch)
    else {
        panic!("a batch answers a batch")
    };
    responses.pop();
    answer(
        &mut ws,
        bid,
        Response::Batch {
            responses,
            lab_seconds,
        },
    )
    .await;
    let fault = faulted(addr, id).await;
    assert!(fault.message.contains("batch"), "{fault}");
    assert!(
        silent_for(&mut ws, 1000).await,
        "a request after a short answer"
    );

    // 5. A person resumes; the bridge stalls on a request: after the
    //    request timeout the run faults as unreachable, and the bridge
    //    coming back resumes it.
    act(addr, id, "resume").await;
    let (_, stalled) = next_any_request(&mut ws).await;
    let fault = faulted(addr, id).await;
    assert_eq!(fault.kind, FaultKind::Disconnected, "{stalled:?}: {fault}");
    drop(ws);
    let mut ws = bridge(addr, id).await;
    let committed = get_run(addr, id).await.iterations;
    let found = serve_until(&mut ws, &mut lab, addr, id, committed + 1).await;
    assert!(found.is_empty(), "{found:?}");
    assert_going(addr, id).await;

    // 6. Stop: nothing reaches the instrument afterwards, reconnect or not.
    act(addr, id, "stop").await;
    while let Ok(frame) =
        tokio::time::timeout(Duration::from_millis(300), next_bridge(&mut ws)).await
    {
        if let BridgeServerMessage::Request { id, request, .. } = frame {
            let resp = lab.0.execute(&request);
            answer(&mut ws, id, resp).await;
        }
    }
    let before = lab.0.voltages_mv();
    drop(ws);
    let mut ws = bridge(addr, id).await;
    assert!(silent_for(&mut ws, 1000).await, "a request after stop");
    assert_eq!(lab.0.voltages_mv(), before);
    assert!(get_run(addr, id).await.status.is_terminal());
}
