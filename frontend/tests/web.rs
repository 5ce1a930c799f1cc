//! Browser tests (wasm-bindgen-test, headless Chromium): components mount and
//! show what they should, protocol frames decode in wasm, and the in-browser
//! mode tunes the simulated dot.
#![cfg(target_arch = "wasm32")]

use std::time::Duration;

use leptos::prelude::*;
use spintune::protocol::{ClientMessage, ControlCommand, ServerMessage, PROTOCOL_VERSION};
use spintune_web::api::ApiBase;
use spintune_web::local::{LocalRunner, LocalSettings};
use spintune_web::model::{fake_records, History};
use spintune_web::ui::Dashboard;
use spintune_web::{App, Mode};
use wasm_bindgen::JsCast;
use wasm_bindgen_test::*;

wasm_bindgen_test_configure!(run_in_browser);

fn host() -> web_sys::HtmlElement {
    let doc = document();
    let el = doc.create_element("div").unwrap();
    doc.body().unwrap().append_child(&el).unwrap();
    el.unchecked_into()
}

async fn sleep(ms: u32) {
    gloo_timers::future::TimeoutFuture::new(ms).await;
}

/// Wait (up to `timeout`) until `cond` holds, yielding to the browser in between.
async fn wait_for(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let start = js_sys::Date::now();
    while !cond() {
        assert!(
            js_sys::Date::now() - start < timeout.as_millis() as f64,
            "timed out waiting for {what}"
        );
        sleep(20).await;
    }
}

fn text(el: &web_sys::HtmlElement) -> String {
    el.inner_text()
}

#[wasm_bindgen_test]
fn protocol_frames_decode_in_wasm() {
    let hello = format!(
        r#"{{"type":"hello","version":{PROTOCOL_VERSION},"run":{{"id":7,"name":"demo","status":{{"state":"running"}},"iterations":3,"lab_seconds":12.5,"tuned":false}}}}"#
    );
    match serde_json::from_str::<ServerMessage>(&hello).unwrap() {
        ServerMessage::Hello { version, run } => {
            assert_eq!(version, PROTOCOL_VERSION);
            assert_eq!(run.id, 7);
        }
        other => panic!("decoded as {other:?}"),
    }
    let failed = r#"{"type":"status","run":{"id":1,"name":"x","status":{"state":"failed","message":"device fault"},"iterations":0,"lab_seconds":0.0,"tuned":false}}"#;
    assert!(matches!(
        serde_json::from_str::<ServerMessage>(failed).unwrap(),
        ServerMessage::Status { .. }
    ));
    let history = ServerMessage::History {
        records: fake_records(3),
    };
    let json = serde_json::to_string(&history).unwrap();
    assert_eq!(
        serde_json::from_str::<ServerMessage>(&json).unwrap(),
        history
    );
    for (json, msg) in [
        (
            r#"{"type":"lagged","skipped":4}"#,
            ServerMessage::Lagged { skipped: 4 },
        ),
        (r#"{"type":"auth_ok"}"#, ServerMessage::AuthOk),
    ] {
        assert_eq!(serde_json::from_str::<ServerMessage>(json).unwrap(), msg);
    }
    let ctl = serde_json::to_string(&ClientMessage::Control {
        command: ControlCommand::Pause,
    })
    .unwrap();
    assert_eq!(ctl, r#"{"type":"control","command":{"action":"pause"}}"#);
}

#[wasm_bindgen_test]
async fn dashboard_draws_every_chart_from_records() {
    let el = host();
    let history = RwSignal::new(History::new());
    let _h = leptos::mount::mount_to(el.clone(), move || view! { <Dashboard history=history /> });
    leptos::task::tick().await;
    assert!(text(&el).contains("Waiting for the first iteration"));
    history.update(|h| {
        h.extend(fake_records(12)).unwrap();
    });
    let charts = || el.query_selector_all("canvas.chart").unwrap();
    wait_for(
        "charts to draw 12 iterations",
        Duration::from_secs(10),
        || {
            let list = charts();
            list.length() >= 6
                && (0..list.length()).all(|i| {
                    let c: web_sys::Element = list.get(i).unwrap().unchecked_into();
                    c.get_attribute("data-iterations").as_deref() == Some("12")
                })
        },
    )
    .await;
    let names: Vec<String> = (0..charts().length())
        .map(|i| {
            let c: web_sys::Element = charts().get(i).unwrap().unchecked_into();
            c.get_attribute("data-chart").unwrap()
        })
        .collect();
    for expected in [
        "parameter-t_sr",
        "parameter-w",
        "gradient-t_sr",
        "gradient-w",
        "gates",
        "scan-0",
        "lab-time",
    ] {
        assert!(
            names.iter().any(|n| n == expected),
            "missing chart {expected} in {names:?}"
        );
    }
    let t = text(&el);
    assert!(t.contains("iteration 11"), "{t}");
    assert!(t.contains("√diag C"), "{t}");
    assert!(t.contains("step clipped"), "events listed: {t}");
    // Canvas got non-white pixels.
    let c: web_sys::HtmlCanvasElement = charts().get(0).unwrap().unchecked_into();
    let ctx: web_sys::CanvasRenderingContext2d =
        c.get_context("2d").unwrap().unwrap().unchecked_into();
    let data = ctx
        .get_image_data(0.0, 0.0, c.width() as f64, c.height() as f64)
        .unwrap()
        .data();
    assert!(data.chunks(4).any(|p| p[0] < 200), "chart is blank");
}

#[wasm_bindgen_test]
async fn live_mode_without_server_is_read_only_and_retries() {
    let el = host();
    // Port 9 (discard) is closed: every fetch and socket fails.
    let base = ApiBase::new("http://127.0.0.1:9");
    let b2 = base.clone();
    let _h = leptos::mount::mount_to(
        el.clone(),
        move || view! { <App base=b2.clone() mode=Mode::Live /> },
    );
    leptos::task::tick().await;
    assert!(text(&el).contains("Live runs"));
    assert!(text(&el).contains("In-browser simulation"));
    wait_for("runs error", Duration::from_secs(10), || {
        text(&el).contains("cannot reach the server")
    })
    .await;
    assert!(
        text(&el).contains("No spintune server answers"),
        "{}",
        text(&el)
    );
    // The way out when the page is served statically: the in-browser mode.
    let open: web_sys::HtmlElement = el
        .query_selector("[data-testid=open-local]")
        .unwrap()
        .unwrap()
        .unchecked_into();
    open.click();
    wait_for("in-browser mode", Duration::from_secs(5), || {
        text(&el).contains("What am I looking at?")
    })
    .await;

    // A run view (opened directly) shows the read-only banner and retries with backoff.
    let el2 = host();
    let _h2 = leptos::mount::mount_to(el2.clone(), move || {
        view! { <spintune_web::live::RunView run=1 base=base.clone() /> }
    });
    leptos::task::tick().await;
    let t = text(&el2);
    assert!(t.contains("Read-only view"), "{t}");
    assert!(el2
        .query_selector("[data-testid=controls]")
        .unwrap()
        .is_none());
    wait_for("reconnect backoff", Duration::from_secs(10), || {
        text(&el2).contains("retry")
    })
    .await;
}

#[wasm_bindgen_test]
async fn local_runner_reaches_a_new_target() {
    let settings = LocalSettings {
        max_iterations: 200,
        ..LocalSettings::default()
    };
    let mut r = LocalRunner::new(&settings).unwrap();
    // Paper set point I first, then move t_sr to 70 ns (paper set point II).
    for _ in 0..60 {
        assert!(r.step().unwrap());
        if r.tuned_at.is_some() {
            break;
        }
        sleep(0).await;
    }
    let first = r
        .tuned_at
        .expect("tuned to (20 ns, 270 µV) within 60 iterations");
    r.set_targets(70.0, 270.0, 0.1).unwrap();
    for _ in 0..60 {
        assert!(r.step().unwrap());
        if r.tuned_at.is_some() {
            break;
        }
        sleep(0).await;
    }
    let second = r
        .tuned_at
        .expect("tuned to (70 ns, 270 µV) within 60 iterations");
    assert!(second > first);
    // The ground-truth heat map has an in-band region.
    let land = r.landscape("SB", "T", 30.0, 21).unwrap();
    assert_eq!(land.error.len(), 21 * 21);
    assert!(land.error.iter().any(|e| *e <= 1.0), "no in-band cell");
    assert!(land.error.iter().all(|e| e.is_finite()));
    let last = r.history.last().unwrap();
    let t_sr = last.parameters.iter().find(|p| p.name == "t_sr").unwrap();
    assert!((t_sr.value.unwrap() - 70.0).abs() <= 7.0 + 3.0 * t_sr.std.unwrap_or(0.0));
}

#[wasm_bindgen_test]
async fn local_mode_runs_in_the_page_and_tunes() {
    let el = host();
    let _h = leptos::mount::mount_to(el.clone(), move || view! { <App mode=Mode::Local /> });
    leptos::task::tick().await;
    let t = text(&el);
    assert!(t.contains("What am I looking at?"), "{t}");
    assert!(
        t.contains("kalman-adaptive-q"),
        "estimator choices listed: {t}"
    );
    let q = |sel: &str| -> web_sys::HtmlElement {
        el.query_selector(&format!("[data-testid={sel}]"))
            .unwrap()
            .unwrap_or_else(|| panic!("no {sel}"))
            .unchecked_into()
    };
    // No pause between iterations: the loop still yields to the browser.
    let delay: web_sys::HtmlInputElement = q("local-delay").unchecked_into();
    delay.set_value("0");
    delay
        .dispatch_event(&web_sys::Event::new("change").unwrap())
        .unwrap();
    q("local-run").click();
    let start = js_sys::Date::now();
    let mut ticks = 0u32;
    wait_for("tuned", Duration::from_secs(120), || {
        ticks += 1;
        q("local-tuned")
            .inner_text()
            .starts_with("tuned at iteration")
    })
    .await;
    // The page was responsive: our own 20 ms polling timer ran many times meanwhile.
    assert!(
        ticks > 3,
        "page froze: only {ticks} timer ticks in {} ms",
        js_sys::Date::now() - start
    );
    wait_for("heat map", Duration::from_secs(20), || {
        el.query_selector("canvas[data-chart=landscape]")
            .unwrap()
            .and_then(|c| c.get_attribute("data-iterations"))
            .is_some_and(|n| n != "0")
    })
    .await;
    q("local-pause").click();
    leptos::task::tick().await;
    assert!(q("local-status").inner_text().contains("paused"));
    let k: u64 = q("local-tuned")
        .inner_text()
        .trim_start_matches("tuned at iteration ")
        .parse()
        .unwrap();
    assert!(k < 60, "took {k} iterations");
    q("local-reset").click();
    leptos::task::tick().await;
    assert!(q("local-tuned").inner_text().contains("not tuned yet"));
}
