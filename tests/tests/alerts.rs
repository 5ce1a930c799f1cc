//! Browser end-to-end test of alerts (issue 23): a run the page follows
//! finishes; the page lists the alert in its banner, prefixes the document
//! title with the number of unseen alerts and badges the favicon (a PNG
//! data URL); the banner's dismiss button clears all three. A run the page
//! only lists (not the one it shows) raises its alert from the list's
//! statuses.

use fantoccini::Client;

mod support;
use support::*;

async fn js(c: &Client, script: &str) -> serde_json::Value {
    c.execute(script, vec![]).await.unwrap()
}

async fn title_and_icon(c: &Client) -> (String, String) {
    let v = js(
        c,
        "const l = document.querySelector(\"link[rel~='icon']\"); return [document.title, l ? l.getAttribute('href') : ''];",
    )
    .await;
    (
        v[0].as_str().unwrap().to_string(),
        v[1].as_str().unwrap().to_string(),
    )
}

/// POST a run config; its id.
fn create_run(port: u16, config: &str) -> u64 {
    let (s, body) = http(port, "POST", "/api/runs", Some(TOKEN), config);
    assert_eq!(s, 201, "{body}");
    let json = &body[body.find('{').unwrap()..=body.rfind('}').unwrap()];
    serde_json::from_str::<serde_json::Value>(json).unwrap()["id"]
        .as_u64()
        .unwrap()
}

/// A control action on run `id`, required to succeed.
fn control(port: u16, id: u64, action: &str) {
    let (s, body) = http(
        port,
        "POST",
        &format!("/api/runs/{id}/control"),
        Some(TOKEN),
        &format!(r#"{{"action":"{action}"}}"#),
    );
    assert_eq!(s, 200, "{action}: {body}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_run_raises_an_alert_in_the_title_favicon_and_banner_until_dismissed() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-alerts-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let _server = start_server(port, &tmp.join("runs.db"));
    // A short run, paused at once so that the page follows it before it
    // finishes (it paces 300 ms per iteration: the pause lands first).
    let id = create_run(
        port,
        r#"{"name":"alert e2e","seed":7,"iteration_delay_ms":300,"tuner":{"max_iterations":3}}"#,
    );
    control(port, id, "pause");

    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    c.goto(&format!("http://127.0.0.1:{port}/#live/{id}"))
        .await
        .unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 60).await;
    wait("the paused run", 30, async || {
        attr(&c, "[data-testid=run-status]", "data-state")
            .await
            .filter(|s| s == "paused")
    })
    .await;
    let (title, icon) = title_and_icon(&c).await;
    assert!(!title.starts_with('('), "{title}");
    assert!(!icon.starts_with("data:"), "{icon}");
    assert!(
        c.find(fantoccini::Locator::Css("[data-testid=alert-banner]"))
            .await
            .is_err(),
        "a banner before any alert"
    );

    // The run goes on and finishes: the alert arrives over the run's socket.
    control(port, id, "resume");
    let item = wait_text(&c, "[data-testid=alert-item]", "finished", 60).await;
    assert!(item.contains(&format!("Run #{id}")), "{item}");
    assert!(item.contains("alert e2e"), "{item}");
    assert!(item.contains("finished after 3 iterations"), "{item}");
    assert!(item.contains("lab time"), "{item}");
    assert_eq!(
        attr(&c, "[data-testid=alert-item]", "data-kind")
            .await
            .as_deref(),
        Some("finished")
    );
    let (alerted_title, alerted_icon) = title_and_icon(&c).await;
    assert_eq!(alerted_title, format!("(1) ⚠ {title}"));
    assert!(
        alerted_icon.starts_with("data:image/png;base64,"),
        "{alerted_icon}"
    );
    screenshot(&c, "alerts-finished").await;

    // Dismiss: banner, title prefix and badge go.
    click(&c, "[data-testid=alert-dismiss]").await;
    wait("the banner to go", 10, async || {
        c.find(fantoccini::Locator::Css("[data-testid=alert-banner]"))
            .await
            .is_err()
            .then_some(())
    })
    .await;
    assert_eq!(title_and_icon(&c).await, (title.clone(), icon));

    // Another run, only listed: its alert comes from the run list's statuses.
    let other = create_run(
        port,
        r#"{"name":"listed only","seed":8,"iteration_delay_ms":300,"tuner":{"max_iterations":2}}"#,
    );
    control(port, other, "pause");
    let listed = format!("button.run[data-run='{other}'] [data-state=paused]");
    wait("the paused run in the list", 30, async || {
        c.find(fantoccini::Locator::Css(&listed)).await.ok()
    })
    .await;
    control(port, other, "resume");
    let item = wait_text(&c, "[data-testid=alert-item]", "listed only", 30).await;
    assert!(item.contains("finished after 2 iterations"), "{item}");
    assert_eq!(title_and_icon(&c).await.0, format!("(1) ⚠ {title}"));
    let _ = c.close().await;
    let _ = std::fs::remove_dir_all(&tmp);
}

/// A keep run (issue 23) in the dashboard: the stats line says what keep
/// mode is doing and when it checks next; checks and re-tunes show as its
/// phase; a re-tune that takes longer than `alert_after_s` raises a
/// `not_back_in_band` alert in the banner.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_keep_run_shows_its_phase_next_check_and_not_back_in_band_alert() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-keep-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let _server = start_server(port, &tmp.join("runs.db"));
    // Paused at once: an alert reaches the pages that are open when it is
    // raised, and this run's first comes within its first 20 records.
    let id = create_run(
        port,
        r#"{"name":"keep e2e","seed":2,"iteration_delay_ms":40,"tuner":{"keep":{"duration_s":43200,"alert_after_s":60}}}"#,
    );
    control(port, id, "pause");
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    c.goto(&format!("http://127.0.0.1:{port}/#live/{id}"))
        .await
        .unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 60).await;
    wait("the paused run", 30, async || {
        attr(&c, "[data-testid=run-status]", "data-state")
            .await
            .filter(|s| s == "paused")
    })
    .await;
    control(port, id, "resume");
    // keeping: the next planned check, in lab time
    let keep = wait_text(&c, "[data-testid=keep]", "next check of", 90).await;
    assert!(keep.contains("lab time"), "{keep}");
    let mut phases = std::collections::BTreeSet::new();
    let item = wait("a not_back_in_band alert", 120, async || {
        if let Some(p) = attr(&c, "[data-testid=keep]", "data-phase").await {
            phases.insert(p);
        }
        let el = c
            .find(fantoccini::Locator::Css(
                "[data-testid=alert-item][data-kind=not_back_in_band]",
            ))
            .await
            .ok()?;
        el.text().await.ok()
    })
    .await;
    assert!(item.contains("not back in band"), "{item}");
    assert!(item.contains("keep e2e"), "{item}");
    assert!(
        phases.contains("check") || phases.contains("retune"),
        "{phases:?}"
    );
    screenshot(&c, "keep-alert").await;
    let _ = c.close().await;
    let _ = std::fs::remove_dir_all(&tmp);
}
