//! Browser end-to-end test: the real backend binary serves the Trunk-built
//! dashboard; headless Chromium (through chromedriver and fantoccini) loads it.
//!
//! Checks: a live run's plots update as iterations arrive; the page is
//! read-only without the control token and the server refuses control without
//! it; after a server restart the page reconnects and resumes without
//! duplicate or missing iterations; with the token, pause / step / resume /
//! target change / stop work; the in-browser mode tunes the simulated dot.
//! Screenshots of each mode go to `<target>/e2e-screenshots/`.
//!
//! Inputs (set by `cargo xtask test`; fallbacks in brackets):
//! - `SPINTUNE_BIN`: the backend binary [`<target>/debug/spintune`, built if missing]
//! - `SPINTUNE_DIST`: Trunk's output [`<workspace>/dist`]; must contain index.html
//! - `CHROMEDRIVER`: chromedriver [`chromedriver` on PATH]; `CHROME`: browser binary [chromedriver's default]
//!
//! Missing chromedriver or dist is a test failure with an explanation, never a skip.

use std::time::Duration;

use fantoccini::Locator;

mod support;
use support::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_live_control_reconnect_and_in_browser_mode() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let db = tmp.join("runs.db");
    let port = free_port();
    let mut server = start_server(port, &db);
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    let base = format!("http://127.0.0.1:{port}/");

    // --- Live mode: history, then live updates -------------------------------
    c.goto(&base).await.unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    let first = wait("plots to show ≥ 2 iterations", 60, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n >= 2)
    })
    .await;
    wait("plots to update live", 60, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n > first)
    })
    .await;
    for chart in [
        "parameter-w",
        "gradient-t_sr",
        "gradient-w",
        "gates",
        "scan-0",
        "lab-time",
    ] {
        let n = attr(
            &c,
            &format!("canvas[data-chart={chart}]"),
            "data-iterations",
        )
        .await;
        assert!(
            n.is_some_and(|n| n != "0"),
            "chart {chart} not drawn with data"
        );
    }
    // The run list names each run's driver (the demo run is simulated).
    wait_text(&c, "[data-testid=run-driver]", "simulator", 10).await;
    // Read-only without the token.
    wait_text(&c, "[data-testid=readonly]", "Read-only view", 5).await;
    assert!(
        c.find(Locator::Css("[data-testid=controls]"))
            .await
            .is_err(),
        "controls visible without token"
    );
    let first_chart_ms = c
        .execute("return window.spintuneFirstChartMs ?? null", vec![])
        .await
        .unwrap();
    eprintln!("budget: first chart with data drawn {first_chart_ms} ms after navigation start (live mode)");
    let metrics = c
        .execute("return window.__spintune_metrics ?? null", vec![])
        .await
        .unwrap();
    eprintln!(
        "budget: live updates (demo run, {} iterations): latest {} ms, largest {} ms of chart drawing per animation frame (recent frames, ms: {}); wasm memory {} B",
        iterations_drawn(&c).await,
        metrics["updateMs"],
        metrics["maxUpdateMs"],
        metrics["recentUpdateMs"],
        metrics["wasmMemoryBytes"]
    );
    assert!(
        metrics["updates"].as_f64().is_some_and(|n| n >= 2.0),
        "no live updates measured: {metrics}"
    );
    screenshot(&c, "live").await;

    // --- Control is refused without (or with a wrong) token -------------------
    let (run_id, _, _) = run_iterations(port);
    let control = format!("/api/runs/{run_id}/control");
    let (status, _) = http(port, "POST", &control, None, r#"{"action":"pause"}"#);
    assert_eq!(status, 401, "control without token must be refused");
    let (status, _) = http(
        port,
        "POST",
        &control,
        Some("wrong"),
        r#"{"action":"pause"}"#,
    );
    assert!(
        status == 401 || status == 403,
        "control with a wrong token must be refused, got {status}"
    );
    type_into(&c, "[data-testid=token]", "wrong-token").await;
    click(&c, "[data-testid=unlock]").await;
    wait_text(&c, "[data-testid=auth-error]", "Token refused", 10).await;
    assert!(c
        .find(Locator::Css("[data-testid=controls]"))
        .await
        .is_err());
    assert_eq!(
        run_iterations(port).2,
        "running",
        "a refused control must not change the run"
    );

    // --- Server restart: reconnect and resume without duplicates or gaps -------
    drop(server);
    wait_text(&c, "[data-testid=connection]", "retry", 20).await;
    server = start_server(port, &db);
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    let (_, stored, state) = run_iterations(port);
    eprintln!("after restart: {stored} stored iterations, run {state}");
    let drawn = wait(
        "page to hold exactly the stored iterations",
        20,
        async || {
            let (_, stored, _) = run_iterations(port);
            let n = iterations_drawn(&c).await;
            (n == stored).then_some(n)
        },
    )
    .await;
    wait_text(&c, "[data-testid=iteration]", &format!("{}", drawn - 1), 5).await;

    // --- With the token: resume, pause, step, target, stop ---------------------
    type_into(&c, "[data-testid=token]", TOKEN).await;
    click(&c, "[data-testid=unlock]").await;
    wait("controls after a valid token", 10, async || {
        c.find(Locator::Css("[data-testid=controls]")).await.ok()
    })
    .await;
    if state != "running" {
        click(&c, "[data-testid=resume]").await;
    }
    wait_text(&c, "[data-testid=run-status]", "running", 10).await;
    let n0 = iterations_drawn(&c).await;
    wait("iterations after resume", 30, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n > n0)
    })
    .await;
    click(&c, "[data-testid=pause]").await;
    wait_text(&c, "[data-testid=run-status]", "paused", 15).await;
    // The run list follows the header at once (it polls only every 4 s).
    wait(
        "the sidebar's state of the run after the pause",
        1,
        async || {
            attr(&c, "button.run.selected [data-state]", "data-state")
                .await
                .filter(|s| s == "paused")
        },
    )
    .await;
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let paused_at = iterations_drawn(&c).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        iterations_drawn(&c).await,
        paused_at,
        "iterations continued while paused"
    );
    assert_eq!(
        run_iterations(port).1,
        paused_at,
        "page and server disagree while paused"
    );
    click(&c, "[data-testid=step]").await;
    wait("one more iteration after a single step", 30, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n == paused_at + 1)
    })
    .await;
    wait_text(&c, "[data-testid=run-status]", "paused", 15).await;
    type_into(&c, "[data-testid=target-t_sr]", "70").await;
    click(&c, "form[data-parameter=t_sr] button[type=submit]").await;
    click(&c, "[data-testid=resume]").await;
    wait_text(&c, "[data-testid=param-t_sr]", "target 70", 30).await;
    screenshot(&c, "live-controls").await;
    click(&c, "[data-testid=stop]").await;
    c.accept_alert().await.expect("confirm dialog for Stop");
    wait_text(&c, "[data-testid=run-status]", "stopped", 15).await;

    // --- In-browser mode ---------------------------------------------------------
    click(&c, "[data-testid=tab-local]").await;
    wait_text(&c, ".explain", "What am I looking at?", 10).await;
    // The virtual-gate matrix: an empty cell and an out-of-range one are
    // refused by name, and no run starts with them.
    set_value(&c, "[data-testid=comp-PB-SB]", "").await;
    let e = wait_text(&c, "[data-testid=comp-error]", "PB per SB", 10).await;
    assert!(e.contains("not a finite number"), "{e}");
    assert_eq!(
        attr(&c, "[data-testid=comp-PB-SB]", "class")
            .await
            .as_deref(),
        Some("invalid"),
        "the refused cell is not marked"
    );
    // (The page header is sticky: buttons at the top are clicked from the top.)
    c.execute("window.scrollTo(0, 0); return true;", vec![])
        .await
        .unwrap();
    click(&c, "[data-testid=local-run]").await;
    // Named once, at the cell; the run says where to look.
    wait_text(&c, "[data-testid=local-error]", "fix the marked cell", 10).await;
    wait_text(&c, "[data-testid=local-state]", "ready", 5).await;
    set_value(&c, "[data-testid=comp-PB-SB]", "5e6").await;
    wait_text(&c, "[data-testid=comp-error]", "out of range", 10).await;
    // Reset to the default; a perturbed matrix changes the cells.
    click(&c, "[data-testid=comp-reset]").await;
    wait("the matrix error to clear", 10, async || {
        c.find(Locator::Css("[data-testid=comp-error]"))
            .await
            .is_err()
            .then_some(())
    })
    .await;
    let default_pa_n = attr(&c, "[data-testid=comp-PA-N]", "value").await;
    assert_eq!(
        c.execute(
            "return document.querySelector('[data-testid=comp-PA-N]').value",
            vec![]
        )
        .await
        .unwrap()
        .as_str(),
        Some("-0.36"),
        "default PA per N ({default_pa_n:?})"
    );
    click(&c, "[data-testid=comp-perturb]").await;
    let perturbed = wait("a perturbed matrix", 10, async || {
        let v = c
            .execute(
                "return document.querySelector('[data-testid=comp-PA-N]').value",
                vec![],
            )
            .await
            .ok()?;
        v.as_str().filter(|v| *v != "-0.36").map(str::to_string)
    })
    .await;
    let x: f64 = perturbed.parse().unwrap();
    assert!(x < 0.0 && x.is_finite(), "perturbed PA per N {x}");
    // The run below is timed against the paper's default matrix.
    click(&c, "[data-testid=comp-reset]").await;
    c.execute("window.scrollTo(0, 0); return true;", vec![])
        .await
        .unwrap();
    click(&c, "[data-testid=local-run]").await;
    let tuned = wait_text(&c, "[data-testid=local-tuned]", "tuned at iteration", 120).await;
    eprintln!("in-browser mode: {tuned}");
    let k: u64 = tuned
        .trim_start_matches("tuned at iteration ")
        .trim()
        .parse()
        .unwrap();
    assert!(k <= 60, "in-browser tuning took {k} iterations");
    // Let a few more iterations draw, then pause and take the picture.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    click(&c, "[data-testid=local-pause]").await;
    wait_text(&c, "[data-testid=local-status]", "paused", 10).await;
    screenshot(&c, "local").await;
    // The in-browser mode (settings with the matrix editor) on a narrow screen.
    c.set_window_size(420, 900).await.unwrap();
    tokio::time::sleep(Duration::from_millis(800)).await;
    let overflow = c
        .execute(
            "return document.documentElement.scrollWidth > window.innerWidth + 1",
            vec![],
        )
        .await
        .unwrap();
    let dir = target_dir().join("e2e-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("local-narrow.png"), c.screenshot().await.unwrap()).unwrap();
    assert_eq!(
        overflow.as_bool(),
        Some(false),
        "the in-browser mode scrolls sideways at 420 px"
    );
    c.set_window_size(1400, 900).await.unwrap();

    c.close().await.unwrap();
    drop(server);
    let _ = std::fs::remove_dir_all(&tmp);
}
