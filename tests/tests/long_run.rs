//! Browser end-to-end test of the dashboard on a long run: a finished run of
//! 100,000 iterations in a SQLite store that `spintune serve` serves.
//!
//! The store is written by this test through the backend's store API
//! ([`spintune_server::store::Store`]) instead of running the tuner 100,000
//! times: the records are real simulator records (40 iterations of the
//! paper's run, cycled from iteration 10 on) renumbered, with lab time
//! accumulating, summaries (no scans) except for the newest 20 iterations,
//! and one deliberate spike: t_sr at iteration [`SPIKE_AT`] is
//! [`SPIKE_NS`].
//!
//! Checks: the newest page is drawn first and older pages load in the
//! background until the page holds all 100,000 iterations ("loaded 100,000 /
//! 100,000"); with the whole run in view the t_sr chart still reaches the
//! spike (decimation keeps extremes) with at most 4 points per pixel
//! column; zoom (buttons, keys, drag, double-click, "last N") changes the
//! iterations in view of every chart; a click inspects an iteration and
//! shows its scans; the lab-time axis; the in-browser estimator race.
//! Budget numbers are printed (`budget: …`) and screenshots of each view go
//! to `<target>/e2e-screenshots/long-*.png`.

use std::path::Path;
use std::time::{Duration, Instant};

use fantoccini::{Client, Locator};
use spintune::driver::{SimulationConfig, SimulationRun};
use spintune::protocol::{IterationRecord, RunStatus};
use spintune_server::config::RunConfig;
use spintune_server::store::Store;

mod support;
use support::*;

/// Iterations of the long run.
const N: u64 = 100_000;
/// The iteration whose t_sr is a one-point spike.
const SPIKE_AT: u64 = 73_219;
/// The spike's t_sr, ns (the run's values are 10–80 ns).
const SPIKE_NS: f64 = 900.0;

/// Real records of the paper's run on the simulator.
fn real_records(n: usize) -> Vec<IterationRecord> {
    let mut run = SimulationRun::new(SimulationConfig::paper_default()).expect("paper config");
    (0..n)
        .map(|_| {
            run.next_iteration()
                .expect("simulated iteration")
                .expect("run not over")
        })
        .collect()
}

/// Iterations of the second (compared) run.
const N2: u64 = 3_000;

/// Write the long run (and a shorter second run to compare with) into a
/// fresh store at `db`; returns the long run's id.
fn write_long_run(db: &Path) -> u64 {
    let started = Instant::now();
    let real = real_records(40);
    let store = Store::open(db).expect("open store");
    let id = write_run(&store, &real, "long run (100,000 iterations)", N, true);
    write_run(&store, &real, "night run (3,000 iterations)", N2, false);
    eprintln!(
        "fixture: {N} + {N2} iterations written in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    id
}

/// One finished run of `n` iterations cycling `real[10..40]`; the newest 20
/// keep their scans; with `spike`, t_sr at [`SPIKE_AT`] is [`SPIKE_NS`].
fn write_run(store: &Store, real: &[IterationRecord], name: &str, n: u64, spike: bool) -> u64 {
    let per_iteration_s = real[39].lab_seconds / 40.0;
    let config = serde_json::to_string(&RunConfig::recommended()).unwrap();
    let id = store
        .create_run(name, &config, &RunStatus::Finished, "{}")
        .expect("create run");
    for k in 0..n {
        let src = &real[10 + (k as usize % 30)];
        let mut r = if k + 20 >= n {
            src.clone()
        } else {
            src.summary()
        };
        r.iteration = k;
        r.lab_seconds = per_iteration_s * (k + 1) as f64;
        if spike && k == SPIKE_AT {
            let p = r.parameters.iter_mut().find(|p| p.name == "t_sr").unwrap();
            p.value = Some(SPIKE_NS);
        }
        let json = serde_json::to_string(&r).unwrap();
        store
            .commit_iteration(id, None, k, &json, "{}", r.lab_seconds, r.tuned)
            .expect("commit");
    }
    id
}

async fn num_attr(c: &Client, css: &str, name: &str) -> Option<f64> {
    attr(c, css, name).await?.parse().ok()
}

async fn metric(c: &Client, name: &str) -> f64 {
    c.execute(
        &format!("return (window.__spintune_metrics || {{}})['{name}'] ?? null"),
        vec![],
    )
    .await
    .unwrap()
    .as_f64()
    .unwrap_or(f64::NAN)
}

const TSR: &str = "canvas[data-chart=parameter-t_sr]";

async fn in_view(c: &Client) -> u64 {
    num_attr(c, TSR, "data-iterations").await.unwrap_or(0.0) as u64
}

/// Dispatch a mouse drag from `a` to `b` (fractions of the canvas width).
async fn drag(c: &Client, css: &str, a: f64, b: f64) {
    let script = format!(
        "const c = document.querySelector('{css}'); const r = c.getBoundingClientRect();
         const ev = (t, f) => c.dispatchEvent(new MouseEvent(t, {{bubbles: true, clientX: r.left + f * r.width, clientY: r.top + r.height / 2}}));
         ev('mousedown', {a}); ev('mousemove', {b}); ev('mouseup', {b}); return true;"
    );
    c.execute(&script, vec![]).await.unwrap();
}

async fn select(c: &Client, css: &str, value: &str) {
    let script = format!(
        "const s = document.querySelector('{css}'); s.value = '{value}'; s.dispatchEvent(new Event('change', {{bubbles: true}})); return true;"
    );
    c.execute(&script, vec![]).await.unwrap();
}

/// `window.__spintune_metrics[name]` as a list of numbers.
async fn metric_list(c: &Client, name: &str) -> Vec<f64> {
    c.execute(
        &format!("return (window.__spintune_metrics || {{}})['{name}'] ?? []"),
        vec![],
    )
    .await
    .unwrap()
    .as_array()
    .map(|a| a.iter().filter_map(|v| v.as_f64()).collect())
    .unwrap_or_default()
}

/// Main-thread chart drawing caused by `action`, ms: the sum over the
/// animation frames it took (the dashboard draws at most ~10 ms of charts
/// per frame and leaves the rest to the next), printed with the largest
/// single frame.
async fn update_ms_after(c: &Client, action: impl AsyncFnOnce()) -> f64 {
    let before = metric(c, "updates").await;
    action().await;
    wait("the charts to redraw", 20, async || {
        (metric(c, "updates").await > before).then_some(())
    })
    .await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let n = (metric(c, "updates").await - before) as usize;
    let frames = metric_list(c, "recentUpdateMs").await;
    let axes = metric_list(c, "recentAxesMs").await;
    assert!(
        n >= 1 && n <= frames.len(),
        "{n} updates, {} recorded",
        frames.len()
    );
    let frames = &frames[frames.len() - n..];
    let total: f64 = frames.iter().sum();
    eprintln!(
        "update: {total:.1} ms in {n} frame(s) (largest frame {:.1} ms), of which frames (axes, labels, grid) {:.1} ms",
        frames.iter().copied().fold(0.0, f64::max),
        axes[axes.len() - n..].iter().sum::<f64>()
    );
    total
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_run_pages_decimates_zooms_inspects_and_races() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-long-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let db = tmp.join("runs.db");
    let run = write_long_run(&db);
    let port = free_port();
    let _server = start_server(port, &db);
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    let base = format!("http://127.0.0.1:{port}/#live/{run}");

    // --- First chart: the newest page -------------------------------------------
    c.goto(&base).await.unwrap();
    wait("the first chart with data", 30, async || {
        Some(in_view(&c).await).filter(|n| *n > 0)
    })
    .await;
    let first_chart_ms = metric(&c, "firstChartMs").await;
    eprintln!("budget: long run ({N} iterations): first chart with data drawn {first_chart_ms:.0} ms after navigation start");
    assert!(first_chart_ms.is_finite(), "no first-chart time published");
    wait_text(&c, "[data-testid=iteration]", &format!("{}", N - 1), 20).await;
    screenshot(&c, "long-first-page").await;

    // --- Older pages in the background, progress shown ---------------------------
    let loaded_from = Instant::now();
    wait_text(
        &c,
        "[data-testid=loaded]",
        "loaded 100,000 / 100,000 iterations",
        240,
    )
    .await;
    let paging = attr(&c, "[data-testid=paging]", "data-mode").await;
    eprintln!(
        "budget: long run: all {N} iterations loaded {:.1} s after the first chart (pages over {})",
        loaded_from.elapsed().as_secs_f64(),
        paging.as_deref().unwrap_or("?")
    );
    assert_eq!(
        paging.as_deref(),
        Some("socket"),
        "history was not paged over the WebSocket (this server pages over it)"
    );
    // The run list names the driver of the stored runs (both simulated).
    let driver = text(
        &c,
        &format!("button[data-run='{run}'] [data-testid=run-driver]"),
    )
    .await
    .unwrap_or_default();
    assert_eq!(
        driver.trim(),
        "simulator",
        "driver of run {run} in the list"
    );
    wait("all iterations in view", 20, async || {
        (in_view(&c).await == N).then_some(())
    })
    .await;

    // --- Decimation keeps the one-point spike -------------------------------------
    let y_max = num_attr(&c, TSR, "data-ymax").await.unwrap();
    let points = num_attr(&c, TSR, "data-points").await.unwrap();
    let (px0, px1) = (
        num_attr(&c, TSR, "data-px0").await.unwrap(),
        num_attr(&c, TSR, "data-px1").await.unwrap(),
    );
    eprintln!(
        "t_sr chart: {points} points drawn for {N} iterations over {:.0} px; max {y_max} ns",
        px1 - px0
    );
    assert_eq!(
        y_max, SPIKE_NS,
        "the spike at iteration {SPIKE_AT} was decimated away"
    );
    assert!(
        points <= 4.0 * (px1 - px0 + 40.0),
        "{points} points: not decimated"
    );
    assert!(
        points >= px1 - px0,
        "{points} points: fewer than pixel columns"
    );
    let memory = metric(&c, "wasmMemoryBytes").await;
    eprintln!(
        "budget: long run: wasm memory {:.1} MiB with {N} iterations held",
        memory / 1048576.0
    );
    screenshot(&c, "long-whole-run").await;

    // --- Main-thread time of a full redraw (what a live update costs) -------------
    // Five times each, alternating the window; the median is reported.
    let mut all_ms = Vec::new();
    let mut last_ms = Vec::new();
    for _ in 0..5 {
        last_ms.push(
            update_ms_after(&c, async || {
                select(&c, "[data-testid=window-last]", "10000").await;
            })
            .await,
        );
        all_ms.push(
            update_ms_after(&c, async || {
                click(&c, "[data-testid=zoom-reset]").await;
            })
            .await,
        );
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    };
    eprintln!(
        "budget: long run: redraw of every chart, median of 5: {:.1} ms with all {N} iterations in view ({all_ms:.1?}), {:.1} ms with the last 10,000 ({last_ms:.1?})",
        median(&mut all_ms.clone()),
        median(&mut last_ms.clone())
    );
    assert!(
        all_ms.iter().all(|ms| ms.is_finite() && *ms > 0.0),
        "{all_ms:?}"
    );
    assert_eq!(in_view(&c).await, N);

    // --- Zoom: buttons, keys, last N, drag, double-click ---------------------------
    click(&c, "[data-testid=zoom-in]").await;
    let half = wait("zoom in", 10, async || {
        Some(in_view(&c).await).filter(|n| *n < N)
    })
    .await;
    assert!(
        (N / 2 - 10..=N / 2 + 10).contains(&half),
        "zoom in showed {half}"
    );
    // The gradient and gate charts follow the same window.
    let gates = num_attr(&c, "canvas[data-chart=gates]", "data-iterations").await;
    assert_eq!(gates, Some(half as f64));
    c.find(Locator::Css("[data-testid=charts]"))
        .await
        .unwrap()
        .send_keys("+")
        .await
        .unwrap();
    let quarter = wait("zoom in with +", 10, async || {
        Some(in_view(&c).await).filter(|n| *n < half)
    })
    .await;
    assert!(quarter < half * 6 / 10, "{quarter}");
    c.find(Locator::Css("[data-testid=charts]"))
        .await
        .unwrap()
        .send_keys("0")
        .await
        .unwrap();
    wait("reset with 0", 10, async || {
        (in_view(&c).await == N).then_some(())
    })
    .await;
    select(&c, "[data-testid=window-last]", "100").await;
    wait("last 100 iterations", 10, async || {
        (in_view(&c).await == 100).then_some(())
    })
    .await;
    wait_text(&c, "[data-testid=showing]", "iterations 99,900–99,999", 5).await;
    select(&c, "[data-testid=window-last]", "all").await;
    wait("whole run again", 10, async || {
        (in_view(&c).await == N).then_some(())
    })
    .await;
    // Drag over the middle fifth of the plot area: about 20 % of the run.
    let w = {
        let cw: f64 = c
            .execute(
                &format!("return document.querySelector('{TSR}').getBoundingClientRect().width"),
                vec![],
            )
            .await
            .unwrap()
            .as_f64()
            .unwrap();
        (px0 / cw, px1 / cw)
    };
    let span = w.1 - w.0;
    drag(&c, TSR, w.0 + 0.4 * span, w.0 + 0.6 * span).await;
    let dragged = wait("drag to zoom", 10, async || {
        Some(in_view(&c).await).filter(|n| *n < N)
    })
    .await;
    assert!((N / 6..N / 4).contains(&dragged), "drag selected {dragged}");
    screenshot(&c, "long-zoomed").await;
    c.execute(
        &format!("document.querySelector('{TSR}').dispatchEvent(new MouseEvent('dblclick', {{bubbles: true}})); return true;"),
        vec![],
    )
    .await
    .unwrap();
    wait("double-click resets", 10, async || {
        (in_view(&c).await == N).then_some(())
    })
    .await;

    // --- Compare with another run; export ------------------------------------------
    select(&c, "[data-testid=overlay]", "2").await;
    let overlay = wait("the compared run on the t_sr chart", 30, async || {
        num_attr(&c, TSR, "data-overlay-points")
            .await
            .filter(|n| *n > 0.0)
    })
    .await;
    eprintln!("compared run: {overlay} points on the t_sr chart");
    screenshot(&c, "long-compare").await;
    select(&c, "[data-testid=overlay]", "").await;
    wait("the comparison removed", 10, async || {
        (num_attr(&c, TSR, "data-overlay-points").await == Some(0.0)).then_some(())
    })
    .await;
    // The links name this run's export; the route is fetched for the short
    // run (exporting 100,000 iterations from a debug server takes long).
    for (format, needle) in [("csv", "iteration"), ("json", "[")] {
        let href = attr(&c, &format!("[data-testid=export-{format}]"), "href")
            .await
            .unwrap();
        assert!(
            href.ends_with(&format!("/api/runs/{run}/export?format={format}")),
            "{href}"
        );
        let path = format!("/api/runs/2/export?format={format}");
        let (status, body) = http(port, "GET", &path, None, "");
        assert_eq!(status, 200, "{path}");
        assert!(
            body.contains(needle),
            "{path}: {}",
            &body[..body.len().min(200)]
        );
    }

    // --- Inspect an iteration: its numbers, step and scans ---------------------------
    select(&c, "[data-testid=window-last]", "100").await;
    wait("last 100 again", 10, async || {
        (in_view(&c).await == 100).then_some(())
    })
    .await;
    // Click at the right end of the plot area: one of the newest iterations.
    drag(&c, TSR, w.1 - 0.002, w.1 - 0.002).await;
    let inspected = wait("the inspector", 10, async || {
        attr(&c, "[data-testid=inspector]", "data-iteration").await
    })
    .await;
    let k: u64 = inspected.parse().unwrap();
    assert!(k >= N - 3, "clicked near the end but inspected {k}");
    wait_text(&c, "[data-testid=inspect-step]", "mV", 5).await;
    wait("the inspected iteration's scans", 20, async || {
        c.find(Locator::Css("[data-testid=inspect-scans] canvas"))
            .await
            .ok()
    })
    .await;
    let hover = text(&c, "[data-testid=readout]").await.unwrap_or_default();
    assert!(
        hover.contains(" ns") && hover.contains(" mV"),
        "read-out without units: {hover}"
    );
    screenshot(&c, "long-inspect").await;

    // --- Lab-time axis ---------------------------------------------------------------
    select(&c, "[data-testid=window-last]", "all").await;
    select(&c, "[data-testid=x-axis]", "lab").await;
    wait_text(&c, "[data-testid=showing]", "lab time", 10).await;
    let x1_h = wait("the lab-time axis", 10, async || {
        num_attr(&c, TSR, "data-x1")
            .await
            .filter(|x| *x > 100.0 && *x < 100_000.0)
    })
    .await;
    eprintln!("lab-time axis ends at {x1_h:.1} h");
    screenshot(&c, "long-lab-time").await;

    // --- Narrow screen ----------------------------------------------------------------
    c.set_window_size(420, 900).await.unwrap();
    tokio::time::sleep(Duration::from_millis(800)).await;
    let overflow: bool = c
        .execute(
            "return document.documentElement.scrollWidth > window.innerWidth + 1",
            vec![],
        )
        .await
        .unwrap()
        .as_bool()
        .unwrap();
    let dir = target_dir().join("e2e-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("long-narrow.png"), c.screenshot().await.unwrap()).unwrap();
    assert!(!overflow, "the page scrolls sideways at 420 px");
    c.set_window_size(1400, 900).await.unwrap();

    // --- Teaching: two estimators race on the same seeded devices ---------------------
    // (3 seeds each, through the paper's first 3 set points.)
    click(&c, "[data-testid=tab-local]").await;
    click(&c, "[data-testid=race-start]").await;
    let done = async |id: &str| {
        wait(&format!("{id} to finish"), 240, async || {
            text(&c, &format!("[data-testid={id}]"))
                .await
                .filter(|t| t.contains("seeds reached") || t.contains("no seed reached"))
        })
        .await
    };
    let a = done("race-a").await;
    let b = done("race-b").await;
    eprintln!("race: A {a:?}; B {b:?}");
    assert!(a.contains("3 of 3 seeds reached all 3 set points"), "{a}");
    assert!(a.contains("lab min (mean ± sd; "), "{a}");
    wait("the race heat map with both paths", 20, async || {
        num_attr(&c, "canvas[data-chart=race-landscape]", "data-iterations")
            .await
            .filter(|n| *n > 0.0)
    })
    .await;
    screenshot(&c, "local-race").await;

    c.close().await.unwrap();
    let _ = std::fs::remove_dir_all(&tmp);
}
