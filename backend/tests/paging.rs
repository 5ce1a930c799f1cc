//! Paged history, scans on request and the scans subscription on a viewer
//! WebSocket, against a real server (in this process) and real clients. Runs
//! longer than a page are filled through the same commit-then-broadcast path
//! a run task uses (`Manager::publish_external`) with a real simulator record
//! (raw scans and fits included), renumbered.

mod common;

use common::*;
use serde_json::Value;
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::{
    ControlCommand, IterationRecord, ServerMessage, DEFAULT_HISTORY_PAGE, MAX_HISTORY_PAGE,
};
use spintune_server::cli::Server;

/// A real simulator record with its scans.
fn template() -> IterationRecord {
    let mut cfg = SimulationConfig::paper_default();
    cfg.tuner.max_iterations = Some(1);
    let mut sim = SimulationRun::new(cfg).unwrap();
    let r = sim.next_iteration().unwrap().expect("one record");
    assert!(!r.scans.is_empty());
    r
}

/// A run without a task (created paused, then stopped) to publish into.
async fn idle_run(srv: &Server) -> u64 {
    let mut cfg = spintune_server::config::RunConfig::recommended();
    cfg.simulation.name = "paging".into();
    let id = srv.manager.create(cfg, true).await.unwrap().id;
    srv.manager.control(id, ControlCommand::Stop).await.unwrap();
    srv.manager.wait_idle(id).await.unwrap();
    id
}

/// Publish records `from..to` (the template renumbered, `lab_seconds` = k so
/// that records differ).
async fn publish(srv: &Server, id: u64, t: &IterationRecord, range: std::ops::Range<u64>) {
    let checkpoint = srv.manager.store().checkpoint(id).unwrap();
    for k in range {
        let mut r = t.clone();
        r.iteration = k;
        r.lab_seconds = k as f64;
        srv.manager
            .publish_external(id, &r, checkpoint.clone())
            .await
            .unwrap();
    }
}

async fn stored(srv: &Server, id: u64) -> Vec<IterationRecord> {
    let (s, body) = http(
        srv.addr,
        "GET",
        &format!("/api/runs/{id}/iterations?limit=10000"),
        None,
        None,
    )
    .await;
    assert_eq!(s, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// The next frame that is not a `Status`.
async fn next_non_status(ws: &mut Ws) -> ServerMessage {
    loop {
        match next_msg(ws).await {
            ServerMessage::Status { .. } => continue,
            m => return m,
        }
    }
}

async fn page(ws: &mut Ws) -> (Vec<IterationRecord>, bool) {
    match next_non_status(ws).await {
        ServerMessage::History {
            records,
            more_before,
        } => (records, more_before),
        other => panic!("expected a history page, got {other:?}"),
    }
}

fn iterations(records: &[IterationRecord]) -> Vec<u64> {
    records.iter().map(|r| r.iteration).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn newest_page_after_hello_then_older_pages_reach_iteration_zero_and_oversized_limits_are_refused(
) {
    let dir = TempDir::new("paging");
    let srv = server(&dir, 256).await;
    let id = idle_run(&srv).await;
    let t = template();
    let n = 450u64;
    publish(&srv, id, &t, 0..n).await;
    let summaries: Vec<IterationRecord> = stored(&srv, id)
        .await
        .iter()
        .map(IterationRecord::summary)
        .collect();
    assert_eq!(summaries.len(), n as usize);

    let mut ws = connect(srv.addr, id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    // Unasked: the newest page, summaries only, with older ones announced.
    let (newest, more) = page(&mut ws).await;
    let p = DEFAULT_HISTORY_PAGE as u64;
    assert_eq!(iterations(&newest), (n - p..n).collect::<Vec<_>>());
    assert!(more, "older iterations exist");
    assert!(newest.iter().all(|r| r.scans.is_empty()));
    assert_eq!(newest[..], summaries[(n - p) as usize..]);

    // Page back, contiguous, down to iteration 0.
    let mut all = newest;
    let mut more_before = more;
    while more_before {
        let before = all[0].iteration;
        send(
            &mut ws,
            &format!(r#"{{"type":"history","before":{before}}}"#),
        )
        .await;
        let (older, more) = page(&mut ws).await;
        assert!(!older.is_empty() && older.len() as u64 <= p);
        assert_eq!(
            older.last().unwrap().iteration + 1,
            before,
            "not contiguous"
        );
        more_before = more;
        all.splice(0..0, older);
    }
    assert_eq!(all, summaries, "the pages are not the stored summaries");

    // A limit above the largest page is refused; the socket still answers.
    send(
        &mut ws,
        &format!(r#"{{"type":"history","limit":{}}}"#, MAX_HISTORY_PAGE + 1),
    )
    .await;
    match next_non_status(&mut ws).await {
        ServerMessage::Error { message } => {
            assert!(message.contains(&MAX_HISTORY_PAGE.to_string()), "{message}")
        }
        other => panic!("expected an error, got {other:?}"),
    }
    send(&mut ws, r#"{"type":"history","before":10,"limit":5}"#).await;
    let (few, more) = page(&mut ws).await;
    assert_eq!(iterations(&few), vec![5, 6, 7, 8, 9]);
    assert!(more);
    send(
        &mut ws,
        &format!(r#"{{"type":"history","limit":{MAX_HISTORY_PAGE}}}"#),
    )
    .await;
    let (everything, more) = page(&mut ws).await;
    assert_eq!(everything, summaries);
    assert!(!more);
    send(&mut ws, r#"{"type":"history","before":0}"#).await;
    let (none, more) = page(&mut ws).await;
    assert!(none.is_empty() && !more);

    // A viewer with `from` gets the newest page, not older than `from`; one
    // whose `from` is within the page gets exactly what it lacks.
    for (from, first) in [(10, n - p), (400, 400)] {
        let mut ws = connect(srv.addr, id, Some(from)).await;
        assert!(matches!(
            next_msg(&mut ws).await,
            ServerMessage::Hello { .. }
        ));
        let (recs, more) = page(&mut ws).await;
        assert_eq!(iterations(&recs), (first..n).collect::<Vec<_>>());
        assert!(more);
    }

    // A restarted server (empty memory) serves the same pages from the store.
    let db = dir.0.join("test.db");
    drop(ws);
    srv.task.abort();
    let (_proc, addr) = spawn_server(&db);
    let mut ws = connect(addr, id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    let (newest, more) = page(&mut ws).await;
    assert!(more);
    assert_eq!(newest[..], summaries[(n - p) as usize..]);
    send(&mut ws, r#"{"type":"history","before":50,"limit":2000}"#).await;
    let (oldest, more) = page(&mut ws).await;
    assert!(!more);
    assert_eq!(oldest[..], summaries[..50]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scans_on_request_equal_the_stored_records_scans() {
    let dir = TempDir::new("scans");
    let srv = server(&dir, 256).await;
    let id = idle_run(&srv).await;
    let t = template();
    publish(&srv, id, &t, 0..5).await;
    let full = stored(&srv, id).await;
    let mut ws = connect(srv.addr, id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    let (recs, _) = page(&mut ws).await;
    assert_eq!(recs.len(), 5);
    for k in [0u64, 3] {
        send(&mut ws, &format!(r#"{{"type":"scans","iteration":{k}}}"#)).await;
        match next_non_status(&mut ws).await {
            ServerMessage::Scans { iteration, scans } => {
                assert_eq!(iteration, k);
                assert!(!scans.is_empty());
                assert_eq!(scans, full[k as usize].scans);
            }
            other => panic!("expected scans, got {other:?}"),
        }
    }
    send(&mut ws, r#"{"type":"scans","iteration":99}"#).await;
    match next_non_status(&mut ws).await {
        ServerMessage::Error { message } => assert!(message.contains("99"), "{message}"),
        other => panic!("expected an error, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn subscribing_to_scans_makes_live_frames_full_records_and_unsubscribing_summaries() {
    let dir = TempDir::new("subscribe");
    let srv = server(&dir, 256).await;
    let id = idle_run(&srv).await;
    let t = template();
    let mut ws = connect(srv.addr, id, None).await;
    assert!(matches!(
        next_msg(&mut ws).await,
        ServerMessage::Hello { .. }
    ));
    page(&mut ws).await;
    let live = |m: ServerMessage| match m {
        ServerMessage::Iteration { record } => record,
        other => panic!("expected a live iteration, got {other:?}"),
    };
    // Default: summaries.
    publish(&srv, id, &t, 0..1).await;
    let r = live(next_non_status(&mut ws).await);
    assert_eq!(r.iteration, 0);
    assert!(r.scans.is_empty());
    // Subscribed: full records (a history answer shows the subscription applied).
    send(&mut ws, r#"{"type":"subscribe","scans":true}"#).await;
    send(&mut ws, r#"{"type":"history","limit":1}"#).await;
    page(&mut ws).await;
    publish(&srv, id, &t, 1..2).await;
    let r = live(next_non_status(&mut ws).await);
    assert_eq!(r.iteration, 1);
    let full = stored(&srv, id).await;
    assert_eq!(r, full[1]);
    assert!(!r.scans.is_empty());
    // Another viewer still gets summaries of the same iteration.
    send(&mut ws, r#"{"type":"subscribe","scans":false}"#).await;
    send(&mut ws, r#"{"type":"history","limit":1}"#).await;
    page(&mut ws).await;
    publish(&srv, id, &t, 2..3).await;
    let r = live(next_non_status(&mut ws).await);
    assert_eq!(r.iteration, 2);
    assert_eq!(r, full_summary(&srv, id, 2).await);
}

async fn full_summary(srv: &Server, id: u64, k: usize) -> IterationRecord {
    stored(srv, id).await[k].summary()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_beyond_the_per_run_cap_get_503_with_a_clear_reason() {
    let dir = TempDir::new("viewer-cap");
    let mut args = serve_args(&dir, 256);
    args.limits.max_viewers_per_run = 2;
    let srv = spintune_server::cli::start_server(&args).await.unwrap();
    let id = idle_run(&srv).await;
    let mut a = connect(srv.addr, id, None).await;
    let _b = connect(srv.addr, id, None).await;
    let url = format!(
        "ws://{}/api/runs/{id}/ws?protocol={}",
        srv.addr,
        spintune::protocol::PROTOCOL_VERSION
    );
    match tokio_tungstenite::connect_async(url.as_str()).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(resp)) => {
            assert_eq!(resp.status().as_u16(), 503);
            let body = String::from_utf8_lossy(resp.body().as_deref().unwrap_or(&[])).to_string();
            let v: Value = serde_json::from_str(&body).unwrap();
            assert!(
                v["error"]
                    .as_str()
                    .unwrap()
                    .contains("open viewer WebSockets"),
                "{body}"
            );
        }
        other => panic!("the third viewer was not refused: {other:?}"),
    }
    // A viewer that leaves frees its place.
    assert!(matches!(
        next_msg(&mut a).await,
        ServerMessage::Hello { .. }
    ));
    a.close(None).await.unwrap();
    drop(a);
    let freed = tokio::time::timeout(STEP, async {
        loop {
            if tokio_tungstenite::connect_async(url.as_str()).await.is_ok() {
                return;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await;
    assert!(freed.is_ok(), "a closed viewer's place was not freed");
}
