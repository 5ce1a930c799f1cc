//! Array runs on the server (issue 24): the real binary runs an array of
//! double dots like any run — created over HTTP, its records name every
//! cell, killed with `kill -9` and resumed bit-identically, a cell's target
//! changed by name; bad array configs are refused naming the field.

mod common;

use std::time::{Duration, Instant};

use common::*;
use serde_json::{json, Value};
use spintune::protocol::RunStatus;
use spintune_server::config::RunConfig;

fn array_config(delay_ms: u64) -> Value {
    json!({
        "iteration_delay_ms": delay_ms,
        "array": {
            "name": "three cells",
            "array": { "cells": 3, "device_seed": 5, "seed": 2 },
            "targets": [[20.0, 270.0]]
        }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_array_run_killed_mid_run_resumes_bit_identically_and_names_every_cell() {
    let dir = TempDir::new("array-crash");
    let db = dir.0.join("array.db");
    let (proc1, addr) = spawn_server(&db);
    let run = create_run(addr, &array_config(300)).await;
    assert_eq!(run.name, "three cells");
    wait_status(addr, run.id, |r| r.iterations >= 2).await;
    let seen_before = records(addr, run.id).await;
    proc1.kill_9();

    let (_proc2, addr) = spawn_server(&db);
    let listed = get_run(addr, run.id).await;
    assert_eq!(listed.status, RunStatus::Interrupted, "{listed:?}");
    let after_restart = records(addr, run.id).await;
    assert_eq!(&after_restart[..seen_before.len()], &seen_before[..]);
    let (s, body) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let done = wait_status(addr, run.id, is_finished).await;
    assert!(done.tuned, "finished in band: {done:?}");
    let resumed = records(addr, run.id).await;
    assert!(
        resumed.len() > seen_before.len(),
        "it went on after the restart"
    );

    // every record names every cell's parameters and carries the learned rows
    for r in &resumed {
        let names: Vec<&str> = r["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            names,
            ["c0.t_sr", "c0.w", "c1.t_sr", "c1.w", "c2.t_sr", "c2.w"]
        );
        assert_eq!(r["gradients"].as_array().unwrap().len(), 6);
    }

    // the same config, uninterrupted, in the core's synchronous driver
    let (s, cfg) = http(
        addr,
        "GET",
        &format!("/api/runs/{}/config", run.id),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200, "{cfg}");
    let cfg: RunConfig = serde_json::from_str(&cfg).unwrap();
    let mut sim = cfg.array.expect("an array run").build().unwrap();
    let mut reference = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    while let Some(r) = sim.next_iteration().unwrap() {
        reference.push(serde_json::to_value(&r).unwrap());
        assert!(Instant::now() < deadline);
    }
    assert_eq!(resumed.len(), reference.len());
    for (k, (a, b)) in resumed.iter().zip(&reference).enumerate() {
        assert_eq!(a, b, "iteration {k} differs from the uninterrupted run");
    }

    // a new target for one cell, by name: the finished run is revived
    let (s, body) = control(
        addr,
        run.id,
        r#"{"action":"set_target","parameter":"c1.w","target":240.0}"#,
    )
    .await;
    assert_eq!(s, 200, "{body}");
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Paused);
    let (s, body) = control(
        addr,
        run.id,
        r#"{"action":"set_target","parameter":"c9.w","target":240.0}"#,
    )
    .await;
    assert_eq!(s, 422, "{body}");
    assert!(body.contains("c9.w"), "{body}");
    let (s, body) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let again = wait_status(addr, run.id, is_finished).await;
    assert!(
        again.tuned && again.iterations > done.iterations,
        "{again:?}"
    );
    let last = records(addr, run.id).await.pop().unwrap();
    let c1w = &last["parameters"][3];
    assert_eq!(c1w["target"], 240.0, "{c1w}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_array_configs_are_refused_naming_the_field() {
    let dir = TempDir::new("array-bad");
    let server = server(&dir, 64).await;
    let addr = server.addr;
    for (config, needle) in [
        (
            json!({"array": {"array": {"cells": 17, "device_seed": 0, "seed": 1}}}),
            "array",
        ),
        (
            json!({"array": {"array": {"cells": 3, "device_seed": "five"}}}),
            "array.array.device_seed",
        ),
        (
            json!({"array": {"tuning": {"line_rounds": 9}}}),
            "array.tuning.line_rounds",
        ),
        (json!({"array": {"colour": "red"}}), "array.colour"),
        (
            json!({"array": {"targets": [[20.0, 270.0], [20.0, 270.0]]}}),
            "array.targets",
        ),
        (
            json!({"array": {}, "driver": "bridge"}),
            "array.description",
        ),
        (
            json!({"array": {}, "driver": "scpi", "scpi": {"address": "127.0.0.1:5025", "channels": {"c0.N": 1}}}),
            "driver",
        ),
        (
            json!({"array": {"description": {"cells": 2, "cell": {
                "gates": [{"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}],
                "qubit": {"gates": ["B1"]}}}}}),
            "array.description.cell.gates[0].name",
        ),
        (
            json!({"array": {"description": {"cells": 2, "cell": {"gates": [], "qubit": {"gates": []}}}}, "driver": "bridge"}),
            "array.description.cell",
        ),
        (
            json!({"array": {"description": {"cells": 2, "readout_groups": [[0]], "cell": {
                "gates": [{"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}],
                "qubit": {"gates": ["B1"]}}}}, "driver": "bridge"}),
            "array.description.readout_groups",
        ),
        (
            json!({"array": {"description": {"cells": 2, "cell": {
                "gates": [{"name": "B1", "min_mv": -500, "max_mv": 0, "initial_mv": -250}],
                "qubit": {"gates": ["B1"]}}}, "targets": [[20.0, 270.0], [20.0, 270.0], [20.0, 270.0]]}, "driver": "bridge"}),
            "array.targets",
        ),
        (json!({"array": {}, "targets": {"w": 200.0}}), "targets"),
    ] {
        let (s, body) = http(
            addr,
            "POST",
            "/api/runs",
            Some(TOKEN),
            Some(&config.to_string()),
        )
        .await;
        assert_eq!(s, 422, "{config}: {body}");
        assert!(body.contains(needle), "{config}: {body}");
    }
}

/// The same revival for a single double dot: a run that finished because it
/// was tuned (`stop_when_tuned`) takes a new target while no task runs, and
/// is revived (paused) — the stored checkpoint predates the finish, so the
/// manager asks the plan, not the checkpoint's mode.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_single_cell_run_finished_when_tuned_is_revived_by_a_new_target() {
    let dir = TempDir::new("revive");
    let server = server(&dir, 64).await;
    let addr = server.addr;
    let run = create_run(addr, &json!({"tuner": {"stop_when_tuned": true}})).await;
    let done = wait_status(addr, run.id, is_finished).await;
    assert!(done.tuned, "{done:?}");
    let (s, body) = control(
        addr,
        run.id,
        r#"{"action":"set_target","parameter":"t_sr","target":30.0}"#,
    )
    .await;
    assert_eq!(s, 200, "{body}");
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Paused);
    let (s, body) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let again = wait_status(addr, run.id, is_finished).await;
    assert!(
        again.tuned && again.iterations > done.iterations,
        "{again:?}"
    );
}
