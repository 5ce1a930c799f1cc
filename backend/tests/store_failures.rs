//! An honest store, against the real binary: a write the store refuses fails
//! the run (durably when the store takes the status), a run is never left
//! `running`, a corrupt run is quarantined while the others are served, and a
//! malformed or foreign checkpoint is an error reply, not a panic.
//!
//! Store failures are real SQLite errors, raised by triggers that the test
//! installs through a second connection to the live database (the same
//! `SQLITE_ABORT`-class error a full disk or an I/O error gives the writer);
//! the server has no test hook.

mod common;

use std::path::Path;
use std::time::Duration;

use common::*;
use spintune::protocol::{RunStatus, RunSummary};

fn sql(db: &Path, statements: &str) {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.busy_timeout(Duration::from_secs(10)).unwrap();
    conn.execute_batch(statements).unwrap();
}

/// Waits until the store itself holds a status of run `id` containing
/// `needle` (read through a second connection): the API shows a failed run
/// at once, before its status is stored (`persist::fail_run`), so a kill
/// right after the API says `failed` may beat the store.
async fn wait_stored_status(db: &Path, id: u64, needle: &str) {
    for _ in 0..200 {
        let conn = rusqlite::Connection::open(db).unwrap();
        conn.busy_timeout(Duration::from_secs(10)).unwrap();
        let status: String = conn
            .query_row("SELECT status FROM runs WHERE id = ?1", [id as i64], |r| {
                r.get(0)
            })
            .unwrap();
        if status.contains(needle) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("run {id}: no stored status containing {needle:?} within 10 s");
}

fn failed_message(r: &RunSummary) -> Option<&str> {
    match &r.status {
        RunStatus::Failed { message } => Some(message),
        _ => None,
    }
}

const FAIL_ITERATIONS: &str = "CREATE TRIGGER test_full BEFORE INSERT ON iterations \
     BEGIN SELECT RAISE(ABORT, 'simulated disk full'); END;";
const FAIL_STATUS: &str = "CREATE TRIGGER test_full_runs BEFORE UPDATE ON runs \
     BEGIN SELECT RAISE(ABORT, 'simulated disk full'); END;";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_iteration_write_fails_the_run_durably_across_a_restart() {
    let dir = TempDir::new("store-fail");
    let db = dir.0.join("s.db");
    let id;
    let committed;
    {
        let (_p, addr) = spawn_server(&db);
        let run = create_run(addr, &small_config("full", 100_000, 20)).await;
        id = run.id;
        wait_status(addr, id, |r| r.iterations >= 2).await;
        sql(&db, FAIL_ITERATIONS);
        let failed = wait_status(addr, id, |r| failed_message(r).is_some()).await;
        let message = failed_message(&failed).unwrap();
        assert!(message.contains("simulated disk full"), "{message}");
        assert!(!message.contains("could not be stored"), "{message}");
        committed = failed.iterations;
        // Nothing more happens to it.
        assert_eq!(records(addr, id).await.len() as u64, committed);
        // the store takes the failed status (the trigger refuses iterations only)
        wait_stored_status(&db, id, "simulated disk full").await;
    } // kill -9
    let (_p, addr) = spawn_server(&db);
    let after = get_run(addr, id).await;
    let message = failed_message(&after)
        .unwrap_or_else(|| panic!("after a restart the run is {:?}", after.status));
    assert!(message.contains("simulated disk full"), "{message}");
    assert_eq!(after.iterations, committed);
    // Once the store takes writes again, the run resumes from its last commit.
    sql(&db, "DROP TRIGGER test_full;");
    let (s, body) = control(addr, id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
    let more = wait_status(addr, id, |r| r.iterations >= committed + 2).await;
    assert_eq!(more.status, RunStatus::Running);
    let stored = records(addr, id).await;
    for (k, r) in stored.iter().enumerate() {
        assert_eq!(
            r["iteration"], k as u64,
            "iterations contiguous across the failure"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn when_the_store_takes_no_write_the_run_is_failed_in_memory_and_never_running_after_restart()
{
    let dir = TempDir::new("store-dead");
    let db = dir.0.join("s.db");
    let id;
    {
        let (_p, addr) = spawn_server(&db);
        let run = create_run(addr, &small_config("dead", 100_000, 20)).await;
        id = run.id;
        wait_status(addr, id, |r| r.iterations >= 1).await;
        sql(&db, &format!("{FAIL_ITERATIONS}{FAIL_STATUS}"));
        let failed = wait_status(addr, id, |r| {
            failed_message(r).is_some_and(|m| m.contains("could not be stored"))
        })
        .await;
        let message = failed_message(&failed).unwrap();
        assert!(message.contains("interrupted"), "{message}");
    }
    sql(&db, "DROP TRIGGER test_full_runs;");
    let (_p, addr) = spawn_server(&db);
    assert_eq!(get_run(addr, id).await.status, RunStatus::Interrupted);
}

/// A full disk during `resume` of a run with no task (here: interrupted by a
/// crash) answers an error and leaves the run truthfully as it was — never a
/// phantom `running` nobody drives — and `stop` still works: stopped at
/// once, stored as soon as the store takes writes again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resume_on_a_full_disk_leaves_a_truthful_run_that_stop_still_stops() {
    let dir = TempDir::new("store-resume");
    let db = dir.0.join("s.db");
    let id;
    {
        let (_p, addr) = spawn_server(&db);
        let run = create_run(addr, &small_config("resume", 100_000, 20)).await;
        id = run.id;
        wait_status(addr, id, |r| r.iterations >= 2).await;
    } // kill -9
    let (_p, addr) = spawn_server(&db);
    assert_eq!(get_run(addr, id).await.status, RunStatus::Interrupted);
    sql(&db, FAIL_STATUS);
    let (s, body) = control(addr, id, r#"{"action":"resume"}"#).await;
    assert!(s >= 500, "{s} {body}");
    assert!(body.contains("simulated disk full"), "{body}");
    let iterations = get_run(addr, id).await.iterations;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let after = get_run(addr, id).await;
    assert_eq!(after.status, RunStatus::Interrupted, "no phantom running");
    assert_eq!(after.iterations, iterations, "nothing ran");
    // The viewers' socket says the same.
    let mut ws = connect(addr, id, None).await;
    match next_msg(&mut ws).await {
        spintune::protocol::ServerMessage::Hello { run, .. } => {
            assert_eq!(run.status, RunStatus::Interrupted)
        }
        other => panic!("{other:?}"),
    }
    // Stop works although the store refuses it ...
    let (s, body) = control(addr, id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200, "{body}");
    assert_eq!(get_run(addr, id).await.status, RunStatus::Stopped);
    let (s, _) = control(addr, id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 409, "a stopped run cannot be resumed");
    // ... and is stored when the disk allows.
    sql(&db, "DROP TRIGGER test_full_runs;");
    tokio::time::sleep(Duration::from_secs(3)).await;
    drop(_p);
    let (_p, addr) = spawn_server(&db);
    assert_eq!(get_run(addr, id).await.status, RunStatus::Stopped);
}

/// A full disk when a person stops a live run: the run is stopped (not
/// failed, nothing more reaches the device) and stored as stopped when the
/// disk allows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_on_a_full_disk_stops_a_live_run_and_is_stored_later() {
    let dir = TempDir::new("store-stop");
    let db = dir.0.join("s.db");
    let (p, addr) = spawn_server(&db);
    let run = create_run(addr, &small_config("stop", 100_000, 20)).await;
    let id = run.id;
    wait_status(addr, id, |r| r.iterations >= 1).await;
    let (s, body) = control(addr, id, r#"{"action":"pause"}"#).await;
    assert_eq!(s, 200, "{body}");
    let paused = wait_status(addr, id, |r| r.status == RunStatus::Paused).await;
    sql(&db, FAIL_STATUS);
    let (s, body) = control(addr, id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200, "{body}");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let after = get_run(addr, id).await;
    assert_eq!(after.status, RunStatus::Stopped, "{:?}", after.status);
    assert_eq!(after.iterations, paused.iterations);
    sql(&db, "DROP TRIGGER test_full_runs;");
    tokio::time::sleep(Duration::from_secs(3)).await;
    drop(p);
    let (_p, addr) = spawn_server(&db);
    assert_eq!(get_run(addr, id).await.status, RunStatus::Stopped);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_run_is_quarantined_and_the_others_are_served() {
    let dir = TempDir::new("quarantine");
    let db = dir.0.join("s.db");
    let (bad, good);
    {
        let (_p, addr) = spawn_server(&db);
        bad = create_run(addr, &small_config("bad", 2, 0)).await.id;
        good = create_run(addr, &small_config("good", 3, 0)).await.id;
        wait_status(addr, bad, is_finished).await;
        wait_status(addr, good, is_finished).await;
    }
    let bad_config = bad + 1_000; // a second corrupt run: unreadable config only
    sql(
        &db,
        &format!(
            "UPDATE runs SET iterations = 'garbage' WHERE id = {bad};
             INSERT INTO runs (id, name, config, status, checkpoint, created_unix_s)
                 VALUES ({bad_config}, 'x', '{{not json', '\"paused\"', '{{}}', 0);"
        ),
    );
    let (_p, addr) = spawn_server(&db);
    let (s, body) = http(addr, "GET", "/api/runs", None, None).await;
    assert_eq!(s, 200, "{body}");
    let listed: Vec<RunSummary> = serde_json::from_str(&body).unwrap();
    for q in [bad, bad_config] {
        let r = listed
            .iter()
            .find(|r| r.id == q)
            .expect("quarantined run listed");
        let m = failed_message(r).unwrap_or_else(|| panic!("{:?}", r.status));
        assert!(m.contains("quarantined") && m.contains("unreadable"), "{m}");
        let (s, body) = control(addr, q, r#"{"action":"resume"}"#).await;
        assert_eq!(s, 409, "{body}");
        assert!(body.contains(&format!("run {q} is quarantined")), "{body}");
        let (s, _) = http(addr, "GET", &format!("/api/runs/{q}/config"), None, None).await;
        assert_eq!(s, 409);
    }
    assert_eq!(get_run(addr, good).await.status, RunStatus::Finished);
    assert_eq!(records(addr, good).await.len(), 3);
    // A quarantined run can be deleted.
    let (s, body) = http(
        addr,
        "DELETE",
        &format!("/api/runs/{bad_config}"),
        Some(TOKEN),
        None,
    )
    .await;
    assert_eq!(s, 204, "{body}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_future_or_foreign_checkpoint_is_an_error_reply_not_a_panic() {
    let dir = TempDir::new("checkpoint");
    let db = dir.0.join("s.db");
    let (id, donor);
    {
        let (_p, addr) = spawn_server(&db);
        id = create_run(addr, &small_config("cp", 1_000, 50)).await.id;
        assert_eq!(control(addr, id, r#"{"action":"pause"}"#).await.0, 200);
        // A run with other gate limits, whose checkpoint is planted below.
        let mut other = small_config("donor", 1_000, 50);
        other["tuner"]["gates"] = serde_json::to_value(
            spintune::sim::default_gates()
                .into_iter()
                .map(|mut g| {
                    g.max_step_mv *= 2.0;
                    g
                })
                .collect::<Vec<_>>(),
        )
        .unwrap();
        donor = create_run(addr, &other).await.id;
        assert_eq!(control(addr, donor, r#"{"action":"pause"}"#).await.0, 200);
    }
    let (_p, addr) = spawn_server(&db);
    let cases = [
        (
            "'{\"version\": 99, \"device\": null}'".to_string(),
            "schema version 99",
        ),
        ("'{not json'".to_string(), "is not JSON"),
        (
            "'{\"version\": 2, \"session\": {\"tuner\": 5}, \"device\": null}'".to_string(),
            "malformed at `session",
        ),
        (
            format!("(SELECT checkpoint FROM runs WHERE id = {donor})"),
            "other gates or gate limits",
        ),
    ];
    for (value, expected) in cases {
        sql(
            &db,
            &format!("UPDATE runs SET checkpoint = {value} WHERE id = {id};"),
        );
        let (s, body) = control(addr, id, r#"{"action":"resume"}"#).await;
        assert_eq!(s, 409, "{expected}: {body}");
        assert!(body.contains(expected), "{expected}: {body}");
        assert!(
            body.contains(&format!("run {id} cannot continue")),
            "{body}"
        );
        // The server is alive and the run did not move.
        assert_eq!(get_run(addr, id).await.status, RunStatus::Interrupted);
    }
    // A checkpoint of this release resumes.
    let (s, body) = control(addr, donor, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{body}");
}
