//! Browser end-to-end test of the dashboard's layout (issue 25): at 420 px
//! the page does not scroll sideways and the four-panel charts stack their
//! panels; a click on a chart opens the inspector in view; a parameter
//! chart's y range can be typed, full or auto; light and dark.
//!
//! Screenshots at 1400 px and 420 px, light and dark, of the live and the
//! in-browser mode go to `<target>/e2e-screenshots/dashboard-*.png`; with
//! `SPINTUNE_DOC_SCREENSHOTS=1` also to `docs/dashboard/` (how the pictures
//! in the docs are made:
//! `SPINTUNE_DOC_SCREENSHOTS=1 cargo test -p spintune-e2e --test dashboard_views`
//! with `SPINTUNE_BIN` and `SPINTUNE_DIST` as for the other browser tests).

use std::time::Duration;

use fantoccini::Client;

mod support;
use support::*;

async fn js(c: &Client, script: &str) -> serde_json::Value {
    c.execute(script, vec![]).await.unwrap()
}

async fn no_sideways_scroll(c: &Client) -> (f64, f64) {
    let v = js(
        c,
        "return [document.documentElement.scrollWidth, window.innerWidth]",
    )
    .await;
    (v[0].as_f64().unwrap(), v[1].as_f64().unwrap())
}

async fn set_theme(c: &Client, theme: &str) {
    for _ in 0..3 {
        if attr(c, "html", "data-theme").await.as_deref() == Some(theme) {
            return;
        }
        click(c, "[data-testid=theme]").await;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(attr(c, "html", "data-theme").await.as_deref(), Some(theme));
}

/// The viewport as PNG into the screenshot folder (and the docs, when asked).
async fn picture(c: &Client, name: &str) {
    tokio::time::sleep(Duration::from_millis(600)).await;
    let png = c.screenshot().await.unwrap();
    let dir = target_dir().join("e2e-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(format!("dashboard-{name}.png")), &png).unwrap();
    if std::env::var_os("SPINTUNE_DOC_SCREENSHOTS").is_some() {
        let docs = workspace_root().join("docs/dashboard");
        std::fs::create_dir_all(&docs).unwrap();
        std::fs::write(docs.join(format!("{name}.png")), &png).unwrap();
    }
}

async fn num(c: &Client, css: &str, name: &str) -> f64 {
    attr(c, css, name)
        .await
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

/// "What the filter believes" follows the inspected iteration: the
/// gradient table (a row per parameter, ±σ, unit) and, per parameter, the
/// change predicted for the last move next to the one measured.
async fn the_filter_s_belief_at_the_inspected_iteration(c: &Client) {
    let k = attr(c, "[data-testid=inspector]", "data-iteration")
        .await
        .unwrap();
    let shown = wait("the belief at the inspected iteration", 10, async || {
        attr(c, "[data-testid=belief]", "data-iteration")
            .await
            .filter(|b| *b == k)
    })
    .await;
    assert_eq!(shown, k);
    let v = js(
        c,
        "const t = document.querySelector('[data-testid=belief-gradients]');
         return [t.tBodies[0].rows.length, t.tBodies[0].rows[0].cells.length, t.tBodies[0].rows[0].innerText,
                 document.querySelectorAll('[data-testid=belief-prediction]').length,
                 document.querySelector('[data-testid=belief-moves]').innerText,
                 [...document.querySelectorAll('[data-testid=belief-prediction]')].map(e => e.innerText).join(' | ')];",
    )
    .await;
    eprintln!("belief at iteration {k}: {} / {} / {}", v[2], v[4], v[5]);
    assert_eq!(v[0].as_u64(), Some(2), "a row per parameter: {v}");
    assert_eq!(v[1].as_u64(), Some(6), "name, 4 gates, unit: {v}");
    let row = v[2].as_str().unwrap();
    assert!(row.contains('±') && row.contains("/mV"), "{row}");
    let moves = v[4].as_str().unwrap();
    if k != "0" && moves.starts_with("Between") {
        assert_eq!(v[3].as_u64(), Some(2), "{v}");
        let said = v[5].as_str().unwrap();
        assert!(
            said.contains("the filter expected") && said.contains("it measured"),
            "{said}"
        );
    }
}

/// The t_sr chart's y range: manual (a typed range above every value pins
/// them all to the top edge; a min above the max is refused with the
/// reason), full, and back to auto.
async fn y_range_of_a_parameter_chart(c: &Client) {
    const TSR: &str = "canvas[data-chart=parameter-t_sr]";
    let (a0, a1) = (num(c, TSR, "data-y0").await, num(c, TSR, "data-y1").await);
    assert!(a0 < a1, "auto y range {a0}..{a1}");
    assert_eq!(num(c, TSR, "data-pinned").await, 0.0);
    set_value(c, "[data-testid=yrange-t_sr]", "manual").await;
    wait("the min and max fields", 10, async || {
        text(c, "[data-testid=yrange-t_sr-max]").await
    })
    .await;
    let span = a1 - a0;
    let (lo, hi) = (
        format!("{:.3}", a1 + 10.0 * span),
        format!("{:.3}", a1 + 20.0 * span),
    );
    set_value(c, "[data-testid=yrange-t_sr-max]", &hi).await;
    set_value(c, "[data-testid=yrange-t_sr-min]", &lo).await;
    let (lo, hi): (f64, f64) = (lo.parse().unwrap(), hi.parse().unwrap());
    wait("the typed y range drawn", 10, async || {
        (num(c, TSR, "data-y0").await == lo && num(c, TSR, "data-y1").await == hi).then_some(())
    })
    .await;
    // one read of both: the run is live, and a frame drawn between two
    // reads would pair one render's count with the next one's
    let v = js(
        c,
        "const ch = document.querySelector('canvas[data-chart=parameter-t_sr]');
         return [Number(ch.getAttribute('data-pinned')), Number(ch.getAttribute('data-points'))];",
    )
    .await;
    let (pinned, points) = (
        v[0].as_f64().unwrap_or(f64::NAN),
        v[1].as_f64().unwrap_or(f64::NAN),
    );
    assert!(
        points >= 1.0 && pinned == points,
        "every value below the typed range is pinned: {pinned} of {points}"
    );
    // A min above the max is refused, with the reason; the range stays.
    set_value(c, "[data-testid=yrange-t_sr-min]", &format!("{}", hi + 1.0)).await;
    let why = wait_text(
        c,
        "[data-testid=yrange-t_sr-min-error]",
        "below the max",
        10,
    )
    .await;
    eprintln!("y range: refused min: {why}");
    assert_eq!(num(c, TSR, "data-y0").await, lo);
    // Full: the range holds every value again, nothing pinned.
    set_value(c, "[data-testid=yrange-t_sr]", "full").await;
    wait("the full y range", 10, async || {
        let (y0, y1, ymax) = (
            num(c, TSR, "data-y0").await,
            num(c, TSR, "data-y1").await,
            num(c, TSR, "data-ymax").await,
        );
        (y0 < ymax && ymax <= y1 && num(c, TSR, "data-pinned").await == 0.0).then_some(())
    })
    .await;
    assert!(text(c, "[data-testid=yrange-t_sr-min]").await.is_none());
    set_value(c, "[data-testid=yrange-t_sr]", "auto").await;
    wait("back to auto", 10, async || {
        let (y0, y1, ymax) = (
            num(c, TSR, "data-y0").await,
            num(c, TSR, "data-y1").await,
            num(c, TSR, "data-ymax").await,
        );
        (y0 < ymax && ymax <= y1 && y1 < lo).then_some(())
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn narrow_and_wide_light_and_dark_and_the_inspector_in_view() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-views-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let server = start_server(port, &tmp.join("runs.db"));
    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    let base = format!("http://127.0.0.1:{port}/");

    // --- Live mode, 1400 px ----------------------------------------------------------
    c.set_window_size(1400, 900).await.unwrap();
    c.goto(&base).await.unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 30).await;
    wait("plots with ≥ 3 iterations", 60, async || {
        Some(iterations_drawn(&c).await).filter(|n| *n >= 3)
    })
    .await;
    assert_eq!(
        attr(&c, "canvas[data-chart=gradient-t_sr]", "data-cols")
            .await
            .as_deref(),
        Some("4")
    );
    // A click on the t_sr chart (top of the page): the inspector opens in view.
    js(
        &c,
        "const ch = document.querySelector('canvas[data-chart=parameter-t_sr]');
         ch.scrollIntoView({block: 'center'});
         const r = ch.getBoundingClientRect();
         const ev = (t) => ch.dispatchEvent(new MouseEvent(t, {bubbles: true, clientX: r.left + 0.7 * r.width, clientY: r.top + r.height / 2}));
         ev('mousedown'); ev('mouseup'); return true;",
    )
    .await;
    let in_view = wait("the inspector in view", 10, async || {
        let v = js(
            &c,
            "const i = document.querySelector('[data-testid=inspector]');
             if (!i) return null;
             const r = i.getBoundingClientRect();
             return r.top >= -1 && r.top < window.innerHeight ? r.top : null;",
        )
        .await;
        v.as_f64()
    })
    .await;
    eprintln!("inspector top at {in_view:.0} px of 900");
    the_filter_s_belief_at_the_inspected_iteration(&c).await;
    y_range_of_a_parameter_chart(&c).await;
    js(&c, "window.scrollTo(0, 0); return true;").await;
    set_theme(&c, "light").await;
    picture(&c, "live-1400-light").await;
    set_theme(&c, "dark").await;
    picture(&c, "live-1400-dark").await;

    // --- Live mode, 420 px -----------------------------------------------------------
    c.set_window_size(420, 900).await.unwrap();
    tokio::time::sleep(Duration::from_millis(800)).await;
    let cols = wait("the gradient panels re-flowed", 10, async || {
        attr(&c, "canvas[data-chart=gradient-t_sr]", "data-cols")
            .await
            .filter(|c| c != "4")
    })
    .await;
    assert!(cols == "1" || cols == "2", "{cols} columns at 420 px");
    let (scroll, inner) = no_sideways_scroll(&c).await;
    assert!(
        scroll <= inner,
        "live mode scrolls sideways at 420 px: {scroll} > {inner}"
    );
    picture(&c, "live-420-dark").await;
    set_theme(&c, "light").await;
    picture(&c, "live-420-light").await;

    // --- In-browser mode, 420 px then 1400 px ----------------------------------------
    click(&c, "[data-testid=tab-local]").await;
    wait_text(&c, "[data-testid=local-state]", "ready", 10).await;
    set_value(&c, "[data-testid=local-delay]", "0").await;
    click(&c, "[data-testid=local-run]").await;
    wait("a few in-browser iterations", 120, async || {
        text(&c, "[data-testid=iteration]")
            .await
            .and_then(|t| t.trim().parse::<u64>().ok())
            .filter(|k| *k >= 3)
    })
    .await;
    let (scroll, inner) = no_sideways_scroll(&c).await;
    assert!(
        scroll <= inner,
        "in-browser mode scrolls sideways at 420 px: {scroll} > {inner}"
    );
    js(&c, "window.scrollTo(0, 0); return true;").await;
    picture(&c, "local-420-light").await;
    set_theme(&c, "dark").await;
    picture(&c, "local-420-dark").await;
    c.set_window_size(1400, 900).await.unwrap();
    tokio::time::sleep(Duration::from_millis(800)).await;
    picture(&c, "local-1400-dark").await;
    set_theme(&c, "light").await;
    picture(&c, "local-1400-light").await;
    // The simulation yields to the browser: the longest main-thread slice.
    let slice = js(
        &c,
        "return (window.__spintune_metrics || {}).maxLocalSliceMs ?? null",
    )
    .await;
    eprintln!(
        "budget: in-browser simulation, longest slice between yields {slice} ms (release wasm)"
    );
    click(&c, "[data-testid=local-pause]").await;
    set_theme(&c, "auto").await;

    c.close().await.unwrap();
    drop(server);
    let _ = std::fs::remove_dir_all(&tmp);
}
