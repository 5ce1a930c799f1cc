//! Browser end-to-end test of the array overview (issue 24, item 5): the
//! real server runs an array of three double-dot cells created over HTTP;
//! its page shows a tile per cell and the heat map of the learned
//! |Jacobian| (6 parameters × 12 gates, the prior's blocks outlined, the
//! numbers of the server's last record); when the run has finished every
//! tile says "in band"; a click on a tile shows that cell's charts (its two
//! parameters, its four gates), and "all cells" goes back. A 2×2 ladder's
//! tiles then sit in its two rows.
//!
//! Screenshots go to `<target>/e2e-screenshots/array-*.png`.

use std::time::Duration;

use fantoccini::Client;

mod support;
use support::*;

async fn js(c: &Client, script: &str) -> serde_json::Value {
    c.execute(script, vec![]).await.unwrap()
}

/// An HTTP body without its chunked transfer encoding (as is, if it has none).
fn dechunk(body: &str) -> String {
    let b = body.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    loop {
        let Some(eol) = b[i..].windows(2).position(|w| w == b"\r\n") else {
            return body.to_string();
        };
        let Some(size) = std::str::from_utf8(&b[i..i + eol])
            .ok()
            .and_then(|s| usize::from_str_radix(s.trim(), 16).ok())
        else {
            return body.to_string();
        };
        i += eol + 2;
        if size == 0 {
            return String::from_utf8(out).expect("UTF-8 body");
        }
        if i + size > b.len() {
            return body.to_string();
        }
        out.extend_from_slice(&b[i..i + size]);
        i += size + 2;
    }
}

fn get_json(port: u16, path: &str) -> serde_json::Value {
    let (status, body) = http(port, "GET", path, None, "");
    assert_eq!(status, 200, "GET {path}: {body}");
    let body = dechunk(&body);
    serde_json::from_str(body.trim()).unwrap_or_else(|e| panic!("{e}: {body}"))
}

/// POST a run config; its id.
fn create_run(port: u16, config: &str) -> u64 {
    let (s, body) = http(port, "POST", "/api/runs", Some(TOKEN), config);
    assert_eq!(s, 201, "{body}");
    let v: serde_json::Value = serde_json::from_str(dechunk(&body).trim()).unwrap();
    v["id"].as_u64().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_three_cell_array_shows_tiles_in_band_the_jacobian_heat_map_and_a_cell_s_charts() {
    let tmp = std::env::temp_dir().join(format!("spintune-e2e-array-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let _server = start_server(port, &tmp.join("runs.db"));
    // The demo run the server starts on an empty store only competes for
    // the CPU here: pause it.
    for run in get_json(port, "/api/runs").as_array().unwrap() {
        let id = run["id"].as_u64().unwrap();
        let (s, body) = http(
            port,
            "POST",
            &format!("/api/runs/{id}/control"),
            Some(TOKEN),
            r#"{"action":"pause"}"#,
        );
        assert_eq!(s, 200, "pause the demo run: {body}");
    }
    let id = create_run(
        port,
        r#"{"iteration_delay_ms": 600, "array": {"name": "three cells", "array": {"cells": 3, "device_seed": 5, "seed": 2}, "targets": [[20.0, 270.0]]}}"#,
    );

    let driver_port = free_port();
    let _driver = start_chromedriver(driver_port);
    let c = browser(driver_port).await;
    c.set_window_size(1400, 900).await.unwrap();
    c.goto(&format!("http://127.0.0.1:{port}/#live/{id}"))
        .await
        .unwrap();
    wait_text(&c, "[data-testid=connection]", "live", 60).await;
    // The page tells an array run from its records: the overview, not the
    // single-cell charts.
    let state = wait("the overview of three cells", 120, async || {
        let v = js(
            &c,
            "const o = document.querySelector('[data-testid=array-overview]');
             const s = document.querySelector('[data-testid=run-status]');
             return o && o.getAttribute('data-cells') === '3' ? s.getAttribute('data-state') : null;",
        )
        .await;
        v.as_str().map(str::to_string)
    })
    .await;
    eprintln!("overview of three cells shown while the run is {state}");
    wait("the run to finish", 300, async || {
        attr(&c, "[data-testid=run-status]", "data-state")
            .await
            .filter(|s| s == "finished")
    })
    .await;
    let summary = get_json(port, &format!("/api/runs/{id}"));
    let n = summary["iterations"].as_u64().unwrap();
    assert!(summary["tuned"].as_bool().unwrap(), "{summary}");
    let last = &get_json(
        port,
        &format!("/api/runs/{id}/iterations?from={}&limit=1", n - 1),
    )[0];
    assert_eq!(last["iteration"].as_u64(), Some(n - 1));

    // Tiles and heat map of the last record, read in one script (the page
    // re-renders as records arrive).
    let v = wait("the overview of the last record", 30, async || {
        let v = js(
            &c,
            "const tiles = [...document.querySelectorAll('[data-testid=cell-tile]')];
             const hm = document.querySelector('[data-testid=jacobian-heatmap]');
             if (!hm) return null;
             const cells = [...hm.querySelectorAll('.hm-cell')];
             return {
               tiles: tiles.map(t => [t.getAttribute('data-cell'), t.getAttribute('data-band'), t.innerText]),
               rows: Number(hm.getAttribute('data-rows')), cols: Number(hm.getAttribute('data-cols')),
               iteration: Number(hm.getAttribute('data-iteration')), unit: hm.getAttribute('data-unit'),
               elements: cells.map(e => [Number(e.getAttribute('data-row')), Number(e.getAttribute('data-col')),
                                         e.getAttribute('data-prior'), Number(e.getAttribute('data-value')),
                                         e.getAttribute('data-col-name')]),
               own: hm.querySelectorAll('.hm-block[data-prior=own]').length,
               neighbour: hm.querySelectorAll('.hm-block[data-prior=neighbour]').length,
               summary: document.querySelector('[data-testid=heatmap-summary]').innerText,
               text: hm.textContent,
             };",
        )
        .await;
        (v["iteration"].as_u64() == Some(n - 1)).then_some(v)
    })
    .await;
    let tiles = v["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), 3, "{v}");
    for (k, t) in tiles.iter().enumerate() {
        let text = t[2].as_str().unwrap();
        eprintln!("tile: {}", text.replace('\n', " | "));
        assert_eq!(t[0].as_str(), Some(k.to_string().as_str()), "{t}");
        assert_eq!(t[1].as_str(), Some("in"), "{t}");
        assert!(text.contains(&format!("cell {k}")), "{text}");
        assert!(
            text.contains("in band") && !text.contains("out of band"),
            "{text}"
        );
        for needle in [
            "t_sr",
            " ns",
            "w ",
            " µV",
            "target 20",
            "target 270",
            " min",
        ] {
            assert!(text.contains(needle), "{needle:?} in {text}");
        }
    }
    assert_eq!(
        (v["rows"].as_u64(), v["cols"].as_u64()),
        (Some(6), Some(12)),
        "{v}"
    );
    assert_eq!(v["unit"].as_str(), Some("1/mV"));
    let elements = v["elements"].as_array().unwrap();
    assert_eq!(elements.len(), 72);
    // 3 own-cell blocks; nearest neighbours 0↔1, 1↔0, 1↔2, 2↔1
    assert_eq!(
        (v["own"].as_u64(), v["neighbour"].as_u64()),
        (Some(3), Some(4))
    );
    // The colours are the server's last record: |gradient| per element.
    let gates = last["gates"].as_array().unwrap();
    let gradients = last["gradients"].as_array().unwrap();
    let mut beyond_the_prior = 0.0f64;
    for e in elements {
        let (r, col) = (
            e[0].as_u64().unwrap() as usize,
            e[1].as_u64().unwrap() as usize,
        );
        let want = gradients[r]["gradient"][col].as_f64().unwrap().abs();
        let shown = e[3].as_f64().unwrap();
        assert!(
            (shown - want).abs() <= 1e-12 * want.max(1e-300),
            "element ({r}, {col}): {shown} shown, {want} in the record"
        );
        assert_eq!(e[4], gates[col]);
        let (row_cell, col_cell) = (r / 2, col / 4);
        let prior = match row_cell.abs_diff(col_cell) {
            0 => "own",
            1 => "neighbour",
            _ => "outside",
        };
        assert_eq!(e[2].as_str(), Some(prior), "{e}");
        if prior == "outside" {
            beyond_the_prior = beyond_the_prior.max(want);
        }
    }
    // the learned rows keep the prior's pattern (zero beyond the neighbours)
    assert_eq!(beyond_the_prior, 0.0);
    let summary_text = v["summary"].as_str().unwrap();
    eprintln!("heat map: {summary_text}");
    assert!(summary_text.contains("/mV"), "{summary_text}");
    let labels = v["text"].as_str().unwrap();
    for needle in [
        "cell 0",
        "cell 2",
        "c1.w",
        "SB",
        "1/mV",
        "gate (∂/∂V, V in mV)",
    ] {
        assert!(
            labels.contains(needle),
            "{needle:?} in the heat map's labels"
        );
    }
    screenshot(&c, "array-overview").await;

    // Drill into cell 1: its charts, as a single double dot.
    js(
        &c,
        "document.querySelector('[data-testid=cell-tile][data-cell=\"1\"]').scrollIntoView({block: 'center'}); return true;",
    )
    .await;
    click(&c, "[data-testid=cell-tile][data-cell='1']").await;
    let cell = wait("cell 1's charts of every iteration", 30, async || {
        let v = js(
            &c,
            "const view = document.querySelector('[data-testid=cell-view]');
             if (!view) return null;
             const ch = (name) => view.querySelector(`canvas[data-chart=${name}]`);
             const it = (name) => ch(name) ? Number(ch(name).getAttribute('data-iterations')) : -1;
             const head = view.querySelector('[data-testid=belief-gradients] thead');
             return {
               cell: view.getAttribute('data-cell'),
               overview: !!document.querySelector('[data-testid=array-overview]'),
               t_sr: it('parameter-t_sr'), w: it('parameter-w'),
               gradient: it('gradient-t_sr'), gates: it('gates'),
               any_prefixed: !!view.querySelector('canvas[data-chart^=\"parameter-c\"]'),
               belief: head ? [...head.querySelectorAll('th')].map(e => e.innerText) : [],
               stat_t_sr: (view.querySelector('[data-testid=param-t_sr]') || {}).innerText || '',
               stat_w: (view.querySelector('[data-testid=param-w]') || {}).innerText || '',
               band: (view.querySelector('[data-testid=cell-view-band]') || {}).innerText || '',
             };",
        )
        .await;
        let all = |k: &str| v[k].as_u64() == Some(n);
        (all("t_sr") && all("w") && all("gradient") && all("gates")).then_some(v)
    })
    .await;
    eprintln!("cell view: {cell}");
    assert_eq!(cell["cell"].as_str(), Some("1"));
    assert_eq!(cell["overview"].as_bool(), Some(false));
    assert_eq!(cell["any_prefixed"].as_bool(), Some(false));
    let belief: Vec<&str> = cell["belief"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    assert_eq!(
        belief,
        ["∂p/∂V", "N", "SA", "SB", "T", "unit"],
        "the cell's own gates"
    );
    let (st, sw) = (
        cell["stat_t_sr"].as_str().unwrap(),
        cell["stat_w"].as_str().unwrap(),
    );
    assert!(st.contains("ns") && st.contains("target 20"), "{st}");
    assert!(sw.contains("µV") && sw.contains("target 270"), "{sw}");
    assert_eq!(cell["band"].as_str(), Some("in band"));
    screenshot(&c, "array-cell-1").await;

    // Back to the overview.
    click(&c, "[data-testid=cell-back]").await;
    wait("the overview again", 10, async || {
        attr(&c, "[data-testid=array-overview]", "data-cells")
            .await
            .filter(|n| n == "3")
    })
    .await;
    assert!(c
        .find(fantoccini::Locator::Css("[data-testid=cell-view]"))
        .await
        .is_err());
    // A chain's tiles: one row, no ladder note.
    assert_eq!(
        attr(&c, ".cell-tiles", "data-rows").await.as_deref(),
        Some("1")
    );
    assert!(c
        .find(fantoccini::Locator::Css("[data-testid=cell-layout]"))
        .await
        .is_err());

    // A 2×2 ladder (cells 0 1 over 2 3): its tiles in its two rows, cell 2
    // under cell 0 and cell 1 beside it, as the run's config says.
    let ladder = create_run(
        port,
        r#"{"iteration_delay_ms": 2000, "array": {"name": "ladder", "array": {"cells": 4, "layout": "ladder", "device_seed": 5, "seed": 2}, "targets": [[20.0, 270.0]]}}"#,
    );
    // (a new page load: the dashboard reads the run from the address once)
    c.goto("about:blank").await.unwrap();
    c.goto(&format!("http://127.0.0.1:{port}/#live/{ladder}"))
        .await
        .unwrap();
    let v = wait("the ladder's tiles in two rows", 120, async || {
        let v = js(
            &c,
            "const o = document.querySelector('[data-testid=array-overview]');
             const g = document.querySelector('.cell-tiles');
             const note = document.querySelector('[data-testid=cell-layout]');
             if (!o || o.getAttribute('data-cells') !== '4' || !g || g.getAttribute('data-rows') !== '2' || !note) return null;
             const box = (k) => document.querySelector(`[data-testid=cell-tile][data-cell=\"${k}\"]`).getBoundingClientRect();
             return { note: note.innerText, boxes: [0, 1, 2, 3].map(k => [box(k).left, box(k).top]) };",
        )
        .await;
        (!v.is_null()).then_some(v)
    })
    .await;
    eprintln!("ladder overview: {v}");
    let note = v["note"].as_str().unwrap();
    assert!(note.contains("2 rows of 2"), "{note}");
    let b: Vec<(f64, f64)> = v["boxes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p[0].as_f64().unwrap(), p[1].as_f64().unwrap()))
        .collect();
    assert_eq!(b[0].1, b[1].1, "cells 0 and 1 on one row: {b:?}");
    assert!(b[1].0 > b[0].0, "cell 1 right of cell 0: {b:?}");
    assert_eq!((b[2].0, b[3].1), (b[0].0, b[2].1), "{b:?}");
    assert!(b[2].1 > b[0].1, "cell 2 under cell 0: {b:?}");
    screenshot(&c, "array-ladder").await;
    tokio::time::sleep(Duration::from_millis(200)).await;

    c.close().await.unwrap();
    let _ = std::fs::remove_dir_all(&tmp);
}
