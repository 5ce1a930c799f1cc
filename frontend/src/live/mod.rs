//! Live mode: list the server's runs, stream one over its WebSocket (the
//! newest page of history, then live iterations, then older pages fetched in
//! the background from the newest backwards), reconnect with backoff
//! resuming at the next missing iteration, and — after the control token is
//! accepted — control it.
//!
//! Paging (protocol v2): the server sends the newest page of iteration
//! summaries after `hello`; the page asks for older pages with
//! `history {before, limit}` until every gap in [`RunHistory::gaps`] is
//! filled, asks for one iteration's scans with `scans {iteration}` and, once
//! the server has answered a page, subscribes to live frames with scans. A
//! server that answers these requests with an `error` (one without paged
//! history) gets a notice and the same pages are fetched over HTTP instead
//! (`GET /api/runs/{id}/iterations?from=&limit=`; scans are dropped on
//! arrival, see [`crate::history`] for the memory bound).
//!
//! The socket URL states the protocol version this page speaks
//! (`?protocol=3`); a server that refuses it answers with an error frame
//! before its `hello` and closes the socket: the page then stops retrying and
//! says why.

pub mod client;

use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;
use std::time::Duration;

use leptos::prelude::*;
use send_wrapper::SendWrapper;
use spintune::parameter::Tolerance;
use spintune::protocol::{
    ClientMessage, ControlCommand, IterationRecord, RunStatus, RunSummary, ServerMessage,
    DEFAULT_HISTORY_PAGE, MAX_HISTORY_PAGE, PROTOCOL_VERSION,
};
use wasm_bindgen::prelude::*;
use web_sys::{CloseEvent, MessageEvent, WebSocket};

use crate::api::{get_json, ApiBase};
use crate::history::RunHistory;

use crate::model::{
    format_lab_time, list_state, status_class, status_is_final, status_label, ControlsEnabled,
};
use crate::ui::{Dashboard, DashboardHooks, StatusBadge, StatusNote};

/// State of a run's WebSocket.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnState {
    /// Opening a socket.
    Connecting {
        /// Reconnection attempt (0 = first connection).
        attempt: u32,
    },
    /// Open and streaming.
    Open,
    /// Waiting before the next attempt.
    Reconnecting {
        /// Attempt that will be made.
        attempt: u32,
        /// Delay before it, ms.
        delay_ms: u32,
    },
    /// Not streaming and not retrying.
    Closed {
        /// Why.
        reason: String,
    },
}

impl ConnState {
    /// Text shown in the connection badge.
    pub fn label(&self) -> String {
        match self {
            ConnState::Connecting { attempt: 0 } => "connecting…".into(),
            ConnState::Connecting { attempt } => format!("reconnecting (attempt {attempt})…"),
            ConnState::Open => "live".into(),
            ConnState::Reconnecting { attempt, delay_ms } => {
                format!(
                    "disconnected — retry {attempt} in {:.1} s",
                    *delay_ms as f64 / 1000.0
                )
            }
            ConnState::Closed { reason } => format!("closed: {reason}"),
        }
    }

    /// CSS class of the badge.
    pub fn class(&self) -> &'static str {
        match self {
            ConnState::Open => "conn live",
            ConnState::Connecting { .. } => "conn connecting",
            ConnState::Reconnecting { .. } => "conn down",
            ConnState::Closed { .. } => "conn closed",
        }
    }
}

/// Backoff before reconnection attempt `attempt` (1-based): 0.5 s doubling to 10 s.
pub fn backoff_ms(attempt: u32) -> u32 {
    let exp = attempt.saturating_sub(1).min(5);
    (500u32 << exp).min(10_000)
}

/// Whether the control token was accepted on the current socket.
#[derive(Debug, Clone, PartialEq)]
pub enum AuthState {
    /// No token entered: read-only.
    None,
    /// Token sent, waiting for the answer.
    Pending,
    /// Controls enabled.
    Ok,
    /// The server refused the token.
    Refused(String),
}

/// Reactive outputs of a run session.
#[derive(Clone, Copy)]
struct Signals {
    history: RwSignal<RunHistory>,
    /// How older pages are fetched (shown next to the progress).
    paging: RwSignal<PagingMode>,
    summary: RwSignal<Option<RunSummary>>,
    conn: RwSignal<ConnState>,
    auth: RwSignal<AuthState>,
    notice: RwSignal<Option<String>>,
}

type Handler<T> = Closure<dyn FnMut(T)>;

/// How history pages and scans are fetched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PagingMode {
    /// Over the run's WebSocket (`history`, `scans`), the protocol's way.
    Socket,
    /// Over HTTP (`/api/runs/{id}/iterations`), after the server refused a
    /// socket request (a server without paged history).
    Http,
}

/// A request on the socket whose answer (or `error`) is still due; the
/// server answers in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pending {
    Control,
    History,
    Scans(u64),
    /// `subscribe` has no answer when accepted; an `error` while it is first
    /// in the queue is its refusal (a server without it sends full records).
    Subscribe,
}

struct Session {
    run: u64,
    base: ApiBase,
    sig: Signals,
    ws: Option<WebSocket>,
    handlers: Option<(
        Handler<web_sys::Event>,
        Handler<MessageEvent>,
        Handler<CloseEvent>,
    )>,
    generation: u32,
    attempt: u32,
    retry: Option<gloo_timers::callback::Timeout>,
    shut_down: bool,
    token: Option<String>,
    /// The server's `hello` arrived on the current socket.
    hello_seen: bool,
    /// Requests on the current socket awaiting their answer.
    pending: VecDeque<Pending>,
    /// The older page being fetched: (before, limit).
    page_in_flight: Option<(u64, u32)>,
    /// The last page asked for and how many rows it added (stops a loop on
    /// a server that keeps answering nothing for a gap).
    last_page: Option<((u64, u32), usize)>,
    /// Iterations the server holds, from the run list (for the first `from`).
    total_hint: u64,
}

type SessionRef = Rc<RefCell<Session>>;

fn drop_socket(s: &mut Session) {
    s.generation = s.generation.wrapping_add(1);
    if let Some(ws) = s.ws.take() {
        ws.set_onopen(None);
        ws.set_onmessage(None);
        ws.set_onclose(None);
        let _ = ws.close();
    }
    s.handlers = None;
    s.pending.clear();
    s.page_in_flight = None;
}

fn connect(sess: &SessionRef) {
    let mut s = sess.borrow_mut();
    if s.shut_down {
        return;
    }
    drop_socket(&mut s);
    s.retry = None;
    s.hello_seen = false;
    // Resume after the newest held iteration; on the first connection ask
    // for the newest page only (a server that ignores paging sends
    // everything from `from`, so `from` keeps that to one page too).
    let from = s.sig.history.with_untracked(|h| {
        h.extent()
            .map(|(_, last)| last + 1)
            .unwrap_or_else(|| s.total_hint.saturating_sub(DEFAULT_HISTORY_PAGE as u64))
    });
    let url = s.base.run_ws_url(s.run, from);
    s.sig.conn.set(ConnState::Connecting { attempt: s.attempt });
    let ws = match WebSocket::new(&url) {
        Ok(ws) => ws,
        Err(e) => {
            s.sig.notice.set(Some(format!("cannot open {url}: {e:?}")));
            drop(s);
            schedule_reconnect(sess);
            return;
        }
    };
    let gen = s.generation;

    let weak = Rc::downgrade(sess);
    let on_open = Closure::<dyn FnMut(web_sys::Event)>::new(move |_| {
        let Some(sess) = weak.upgrade() else { return };
        let s = sess.borrow();
        if s.generation != gen {
            return;
        }
        s.sig.conn.set(ConnState::Open);
        if let Some(token) = s.token.clone() {
            send_on(&s, &ClientMessage::Auth { token });
        }
    });

    let weak = Rc::downgrade(sess);
    let on_message = Closure::<dyn FnMut(MessageEvent)>::new(move |ev: MessageEvent| {
        let Some(sess) = weak.upgrade() else { return };
        if sess.borrow().generation != gen {
            return;
        }
        let Some(text) = ev.data().as_string() else {
            return;
        };
        match handle_message(&sess, &text) {
            After::Continue => request_more(&sess),
            After::Refused(message) => {
                // Retrying cannot help (e.g. the server speaks another protocol
                // version): stay closed and say why.
                let mut s = sess.borrow_mut();
                drop_socket(&mut s);
                s.sig.conn.set(ConnState::Closed {
                    reason: format!("refused by the server: {message}"),
                });
                s.sig.notice.set(Some(format!(
                    "The server refused this page's connection: {message}. This page speaks protocol v{PROTOCOL_VERSION}; reload it (or use a matching server)."
                )));
            }
        }
    });

    let weak = Rc::downgrade(sess);
    let on_close = Closure::<dyn FnMut(CloseEvent)>::new(move |ev: CloseEvent| {
        let Some(sess) = weak.upgrade() else { return };
        let final_status = {
            let s = sess.borrow();
            if s.generation != gen || s.shut_down {
                return;
            }
            s.sig
                .summary
                .with_untracked(|r| r.as_ref().is_some_and(|r| status_is_final(&r.status)))
        };
        if final_status {
            let mut s = sess.borrow_mut();
            drop_socket(&mut s);
            s.sig.conn.set(ConnState::Closed {
                reason: "run has ended".into(),
            });
            return;
        }
        if ev.code() != 1000 && !ev.reason().is_empty() {
            sess.borrow()
                .sig
                .notice
                .set(Some(format!("socket closed: {}", ev.reason())));
        }
        schedule_reconnect(&sess);
    });

    ws.set_onopen(Some(on_open.as_ref().unchecked_ref()));
    ws.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
    ws.set_onclose(Some(on_close.as_ref().unchecked_ref()));
    s.handlers = Some((on_open, on_message, on_close));
    s.ws = Some(ws);
}

fn schedule_reconnect(sess: &SessionRef) {
    let mut s = sess.borrow_mut();
    if s.shut_down {
        return;
    }
    drop_socket(&mut s);
    s.attempt += 1;
    let delay_ms = backoff_ms(s.attempt);
    s.sig.conn.set(ConnState::Reconnecting {
        attempt: s.attempt,
        delay_ms,
    });
    let weak = Rc::downgrade(sess);
    s.retry = Some(gloo_timers::callback::Timeout::new(delay_ms, move || {
        if let Some(sess) = weak.upgrade() {
            connect(&sess);
        }
    }));
}

/// What to do with the socket after a server frame.
#[derive(Debug, Clone, PartialEq)]
enum After {
    /// Keep streaming (and fetch older pages if any are missing).
    Continue,
    /// The server refused the connection before its `hello` (handshake
    /// error, e.g. a protocol version it does not speak): do not retry.
    Refused(String),
}

/// Applies one server frame.
fn handle_message(sess: &SessionRef, text: &str) -> After {
    let sig = sess.borrow().sig;
    let msg: ServerMessage = match serde_json::from_str(text) {
        Ok(m) => m,
        Err(e) => {
            sig.notice
                .set(Some(format!("undecodable message from server: {e}")));
            return After::Continue;
        }
    };
    match msg {
        ServerMessage::Hello { version, run } => {
            if version != PROTOCOL_VERSION {
                sig.notice.set(Some(format!(
                    "server speaks protocol v{version}, this page v{PROTOCOL_VERSION}; reload the page"
                )));
            }
            sig.history.update(|h| h.set_total(run.iterations));
            sig.summary.set(Some(run));
            let mut s = sess.borrow_mut();
            s.attempt = 0;
            s.hello_seen = true;
            // Live frames with scans: the latest iteration's scans are drawn.
            if send_on(&s, &ClientMessage::Subscribe { scans: true }) {
                s.pending.push_back(Pending::Subscribe);
            }
        }
        ServerMessage::History {
            records,
            more_before,
        } => {
            let answer = {
                let mut s = sess.borrow_mut();
                match s.pending.iter().position(|p| *p == Pending::History) {
                    Some(i) => {
                        s.pending.drain(..=i);
                        s.page_in_flight.take()
                    }
                    None => None,
                }
            };
            let mut added = 0;
            sig.history.update(|h| {
                added = match answer {
                    // The answer to our request: `more_before` is about it.
                    Some((before, _)) => h.insert_page(records, more_before, Some(before)).added,
                    // Unasked (after hello or lagged): take the records only.
                    None => h.insert(records).added,
                };
            });
            if let Some(req) = answer {
                sess.borrow_mut().last_page = Some((req, added));
            }
        }
        ServerMessage::Iteration { record } => {
            let tuned = record.tuned;
            let (k, lab) = (record.iteration, record.lab_seconds);
            let mut added = 0;
            sig.history.update(|h| {
                added = h.insert([record]).added;
                h.set_total(h.total().max(k + 1));
            });
            if added > 0 {
                sig.summary.update(|s| {
                    if let Some(s) = s {
                        s.iterations = s.iterations.max(k + 1);
                        s.lab_seconds = lab;
                        s.tuned = tuned;
                    }
                });
            }
        }
        ServerMessage::Scans { iteration, scans } => {
            {
                let mut s = sess.borrow_mut();
                if let Some(i) = s
                    .pending
                    .iter()
                    .position(|p| *p == Pending::Scans(iteration))
                {
                    // Answers come in order: what was asked before was answered.
                    s.pending.drain(..=i);
                }
            }
            sig.history
                .update(|h| h.set_inspected_scans(iteration, scans));
        }
        ServerMessage::Status { run } => {
            {
                let mut s = sess.borrow_mut();
                if s.pending.front() == Some(&Pending::Control) {
                    s.pending.pop_front();
                }
            }
            sig.history.update(|h| h.set_total(run.iterations));
            sig.summary.set(Some(run));
        }
        ServerMessage::Lagged { skipped } => {
            sig.notice.set(Some(format!(
                "this viewer fell behind ({skipped} live messages skipped); catching up from the store"
            )));
        }
        ServerMessage::AuthOk => sig.auth.set(AuthState::Ok),
        ServerMessage::Error { message } => {
            if !sess.borrow().hello_seen {
                // The server sends its hello first on every accepted socket.
                return After::Refused(message);
            }
            if sig.auth.get_untracked() == AuthState::Pending {
                sess.borrow_mut().token = None;
                sig.auth.set(AuthState::Refused(message));
                return After::Continue;
            }
            let refused = sess.borrow_mut().pending.pop_front();
            match refused {
                Some(Pending::History) => {
                    sess.borrow_mut().page_in_flight = None;
                    sig.paging.set(PagingMode::Http);
                    sig.notice.set(Some(format!(
                        "this server does not send history pages over the socket ({message}); loading older iterations over HTTP instead"
                    )));
                }
                Some(Pending::Scans(k)) => {
                    sig.paging.set(PagingMode::Http);
                    fetch_scans_http(sess, k);
                }
                // Refused subscription: this server sends full records anyway.
                Some(Pending::Subscribe) => {}
                Some(Pending::Control) | None => {
                    sig.notice.set(Some(format!("server: {message}")));
                }
            }
        }
    }
    After::Continue
}

/// Ask for the next older page if one is missing and none is on its way.
fn request_more(sess: &SessionRef) {
    let mut s = sess.borrow_mut();
    if s.page_in_flight.is_some() || !s.hello_seen || s.shut_down {
        return;
    }
    let Some(req) = s
        .sig
        .history
        .with_untracked(|h| h.next_page(MAX_HISTORY_PAGE))
    else {
        return;
    };
    if s.last_page == Some((req, 0)) {
        // The same request added nothing last time: the server has no more.
        return;
    }
    let (before, limit) = req;
    match s.sig.paging.get_untracked() {
        PagingMode::Socket => {
            if send_on(
                &s,
                &ClientMessage::History {
                    before: Some(before),
                    limit: Some(limit),
                },
            ) {
                s.pending.push_back(Pending::History);
                s.page_in_flight = Some(req);
            }
        }
        PagingMode::Http => {
            s.page_in_flight = Some(req);
            let url = s.base.url(&format!(
                "/api/runs/{}/iterations?from={}&limit={limit}",
                s.run,
                before - limit as u64
            ));
            let weak = Rc::downgrade(sess);
            drop(s);
            leptos::task::spawn_local(async move {
                let result = get_json::<Vec<IterationRecord>>(&url).await;
                let Some(sess) = weak.upgrade() else { return };
                let sig = sess.borrow().sig;
                let ok = match result {
                    Ok(mut records) => {
                        records.retain(|r| r.iteration < before);
                        let more = !records.is_empty();
                        let mut added = 0;
                        let _ = sig.history.try_update(|h| {
                            added = h.insert_page(records, more, Some(before)).added
                        });
                        sess.borrow_mut().last_page = Some((req, added));
                        true
                    }
                    Err(e) => {
                        let _ = sig
                            .notice
                            .try_set(Some(format!("cannot load older iterations: {e}")));
                        false
                    }
                };
                sess.borrow_mut().page_in_flight = None;
                if ok {
                    request_more(&sess);
                }
            });
        }
    }
}

/// Fetch the scans of iteration `k` over HTTP (the stored full record).
fn fetch_scans_http(sess: &SessionRef, k: u64) {
    let s = sess.borrow();
    let url = s
        .base
        .url(&format!("/api/runs/{}/iterations?from={k}&limit=1", s.run));
    let sig = s.sig;
    drop(s);
    leptos::task::spawn_local(async move {
        match get_json::<Vec<IterationRecord>>(&url).await {
            Ok(records) => {
                let scans = records
                    .into_iter()
                    .find(|r| r.iteration == k)
                    .map(|r| r.scans)
                    .unwrap_or_default();
                let _ = sig.history.try_update(|h| h.set_inspected_scans(k, scans));
            }
            Err(e) => {
                let _ = sig
                    .notice
                    .try_set(Some(format!("cannot load the scans of iteration {k}: {e}")));
            }
        }
    });
}

/// Ask for the scans of iteration `k` (the inspector shows them).
fn request_scans(sess: &SessionRef, k: u64) {
    let mode = sess.borrow().sig.paging.get_untracked();
    if mode == PagingMode::Socket {
        let mut s = sess.borrow_mut();
        if send_on(&s, &ClientMessage::Scans { iteration: k }) {
            s.pending.push_back(Pending::Scans(k));
            return;
        }
    }
    fetch_scans_http(sess, k);
}

fn send_on(s: &Session, msg: &ClientMessage) -> bool {
    let Some(ws) =
        s.ws.as_ref()
            .filter(|ws| ws.ready_state() == WebSocket::OPEN)
    else {
        return false;
    };
    match serde_json::to_string(msg) {
        Ok(json) => ws.send_with_str(&json).is_ok(),
        Err(_) => false,
    }
}

/// Live mode: run list on the left, the selected run on the right.
#[component]
pub fn LiveMode(base: ApiBase) -> impl IntoView {
    let runs = RwSignal::new(Vec::<RunSummary>::new());
    let error = RwSignal::new(None::<String>);
    let loaded = RwSignal::new(false);
    let selected = RwSignal::new(initial_run_from_hash());
    let refresh = {
        let base = base.clone();
        move || {
            let url = base.url("/api/runs");
            leptos::task::spawn_local(async move {
                match get_json::<Vec<RunSummary>>(&url).await {
                    Ok(list) => {
                        let _ = runs.try_set(list);
                        let _ = error.try_set(None);
                    }
                    Err(e) => {
                        let _ = error.try_set(Some(e));
                    }
                }
                let _ = loaded.try_set(true);
            });
        }
    };
    refresh();
    let r2 = refresh.clone();
    if let Ok(handle) = set_interval_with_handle(r2, Duration::from_secs(4)) {
        let handle = SendWrapper::new(handle);
        on_cleanup(move || handle.clear());
    }
    // Open the first run automatically when nothing is selected.
    Effect::new(move |_| {
        if selected.get_untracked().is_none() {
            if let Some(first) = runs.with(|r| r.first().map(|r| r.id)) {
                selected.set(Some(first));
            }
        }
    });
    let mode = use_context::<RwSignal<crate::Mode>>();
    let run_view = move || {
        match selected.get() {
        Some(id) => {
            let _ = window().location().set_hash(&format!("live/{id}"));
            let hint = runs.with_untracked(|r| r.iter().find(|r| r.id == id).map(|r| r.iterations));
            view! { <RunView run=id base=base.clone() total_hint=hint runs=runs /> }.into_any()
        }
        None => view! {
            <div class="empty">
                {move || if error.with(|e| e.is_some()) {
                    view! {
                        <h2>"No spintune server answers at this address."</h2>
                        <p>"Start one with "<code>"spintune serve"</code>" and open the address it prints, or run the whole tuner in this page:"</p>
                        <button class="primary" data-testid="open-local" on:click=move |_| {
                            let _ = window().location().set_hash("local");
                            if let Some(m) = mode { m.set(crate::Mode::Local) }
                        }>"Open the in-browser simulation"</button>
                    }.into_any()
                } else {
                    view! { <p class="hint">"Select a run on the left."</p> }.into_any()
                }}
            </div>
        }.into_any(),
    }
    };
    view! {
        <div class="mode-live">
            <aside class="sidebar">
                <h2>"Runs"</h2>
                <Show when=move || error.with(|e| e.is_some())>
                    <p class="error">{move || error.get().unwrap_or_default()}</p>
                </Show>
                <Show when=move || loaded.get() && error.with(|e| e.is_none()) && runs.with(|r| r.is_empty())>
                    <p class="hint">"The server has no runs."</p>
                </Show>
                <ul class="runs">
                    <For
                        each=move || runs.get()
                        key=|r| (r.id, r.iterations, format!("{:?}", r.status))
                        children=move |r| {
                            let id = r.id;
                            let state = r.status.name();
                            view! {
                                <li>
                                    <button
                                        class="run"
                                        class:selected=move || selected.get() == Some(id)
                                        data-run=id
                                        on:click=move |_| selected.set(Some(id))
                                    >
                                        <span class="run-name">{format!("#{} {}", r.id, r.name)}</span>
                                        <span class="run-meta">
                                            <span class=status_class(&r.status) data-state=state title=status_label(&r.status)>{list_state(&r.status)}</span>
                                            " · "
                                            <span class="run-driver" data-testid="run-driver" title="device driver">
                                                {r.driver.clone().unwrap_or_else(|| "driver ?".to_string())}
                                            </span>
                                            {format!(" · {} it · lab {}", crate::ui::grouped(r.iterations), format_lab_time(r.lab_seconds))}
                                            {if r.tuned { " · tuned" } else { "" }}
                                        </span>
                                    </button>
                                </li>
                            }
                        }
                    />
                </ul>
            </aside>
            <section class="main">{run_view}</section>
        </div>
    }
}

/// Most iterations of a compared run loaded (its newest), to bound memory.
pub const OVERLAY_MAX: u64 = 20_000;

/// The newest `max` iterations of run `id`, over HTTP in pages of
/// [`MAX_HISTORY_PAGE`] (scans dropped on arrival).
pub async fn load_history_http(base: &ApiBase, id: u64, max: u64) -> Result<RunHistory, String> {
    let summary: RunSummary = get_json(&base.url(&format!("/api/runs/{id}"))).await?;
    let mut h = RunHistory::new();
    h.set_total(summary.iterations);
    let mut from = summary.iterations.saturating_sub(max);
    while from < summary.iterations {
        let limit = MAX_HISTORY_PAGE as u64;
        let page: Vec<IterationRecord> = get_json(&base.url(&format!(
            "/api/runs/{id}/iterations?from={from}&limit={limit}"
        )))
        .await?;
        if page.is_empty() {
            break;
        }
        h.insert(page);
        from += limit;
    }
    Ok(h)
}

fn initial_run_from_hash() -> Option<u64> {
    let hash = window().location().hash().ok()?;
    hash.trim_start_matches('#')
        .strip_prefix("live/")?
        .parse()
        .ok()
}

/// One run: connection state, summary, controls, plots.
#[component]
pub fn RunView(
    run: u64,
    base: ApiBase,
    /// Iterations the server holds (from the run list), if known: the
    /// first socket asks only for the newest page.
    #[prop(optional_no_strip)]
    total_hint: Option<u64>,
    /// The run list (to pick a run to compare with).
    #[prop(optional)]
    runs: Option<RwSignal<Vec<RunSummary>>>,
) -> impl IntoView {
    let sig = Signals {
        history: RwSignal::new(RunHistory::new()),
        paging: RwSignal::new(PagingMode::Socket),
        summary: RwSignal::new(None),
        conn: RwSignal::new(ConnState::Connecting { attempt: 0 }),
        auth: RwSignal::new(AuthState::None),
        notice: RwSignal::new(None),
    };
    let export_base = base.clone();
    let overlay_base = base.clone();
    let sess: SessionRef = Rc::new(RefCell::new(Session {
        run,
        base,
        sig,
        ws: None,
        handlers: None,
        generation: 0,
        attempt: 0,
        retry: None,
        shut_down: false,
        token: None,
        hello_seen: false,
        pending: VecDeque::new(),
        page_in_flight: None,
        last_page: None,
        total_hint: total_hint.unwrap_or(0),
    }));
    match total_hint {
        Some(_) => connect(&sess),
        None => {
            // Learn the run's size first, so the first socket asks for one page.
            let url = sess.borrow().base.url(&format!("/api/runs/{run}"));
            let weak = Rc::downgrade(&sess);
            leptos::task::spawn_local(async move {
                let total = get_json::<RunSummary>(&url).await.map(|s| s.iterations);
                if let Some(sess) = weak.upgrade() {
                    sess.borrow_mut().total_hint = total.unwrap_or(0);
                    connect(&sess);
                }
            });
        }
    }
    {
        let sess = SendWrapper::new(sess.clone());
        on_cleanup(move || {
            let mut s = sess.borrow_mut();
            s.shut_down = true;
            s.retry = None;
            drop_socket(&mut s);
        });
    }
    let sess = SendWrapper::new(sess);
    let sess = StoredValue::new(sess);
    let send = move |msg: ClientMessage| {
        sess.with_value(|s| {
            if !send_on(&s.borrow(), &msg) {
                sig.notice.set(Some(
                    "not connected; try again when the badge says live".into(),
                ));
            }
        })
    };
    let token_input = RwSignal::new(String::new());
    let unlock = move || {
        let token = token_input.get_untracked().trim().to_string();
        if token.is_empty() {
            return;
        }
        sig.auth.set(AuthState::Pending);
        sess.with_value(|s| {
            s.borrow_mut().token = Some(token.clone());
            send_on(&s.borrow(), &ClientMessage::Auth { token });
        });
    };
    let control = move |command: ControlCommand| send(ClientMessage::Control { command });
    let title = move || {
        sig.summary.with(|s| match s {
            Some(s) => format!("Run #{} — {}", s.id, s.name),
            None => format!("Run #{run}"),
        })
    };
    let status = Signal::derive(move || sig.summary.with(|s| s.as_ref().map(|s| s.status.clone())));
    let want_scans = Callback::new(move |k: u64| sess.with_value(|s| request_scans(s, k)));
    let hooks = DashboardHooks {
        want_scans: Some(want_scans),
    };
    let paging_note = move || match sig.paging.get() {
        PagingMode::Socket => "history pages over the socket",
        PagingMode::Http => "history pages over HTTP (server without socket paging)",
    };
    // Compare with another run: its newest iterations, over HTTP.
    let overlay = RwSignal::new(None::<RunHistory>);
    let overlay_id = RwSignal::new(None::<u64>);
    let pick_overlay = move |id: Option<u64>| {
        overlay_id.set(id);
        overlay.set(None);
        let Some(id) = id else { return };
        let base = overlay_base.clone();
        leptos::task::spawn_local(async move {
            let h = load_history_http(&base, id, OVERLAY_MAX).await;
            if overlay_id.try_get_untracked() == Some(Some(id)) {
                let _ = overlay.try_set(h.ok());
            }
        });
    };
    let other_runs = move || {
        runs.map(|r| {
            r.with(|r| {
                r.iter()
                    .filter(|s| s.id != run)
                    .map(|s| (s.id, s.name.clone()))
                    .collect::<Vec<_>>()
            })
        })
        .unwrap_or_default()
    };
    view! {
        <div class="run-view">
            <header class="run-head">
                <h2>{title}</h2>
                <StatusBadge status testid="run-status" unknown="…" />
                <span class=move || sig.conn.with(|c| c.class()) data-testid="connection">{move || sig.conn.with(|c| c.label())}</span>
            </header>
            {move || sig.notice.get().map(|n| view! {
                <p class="notice">{n} <button class="link" on:click=move |_| sig.notice.set(None)>"dismiss"</button></p>
            })}
            <StatusNote status />
            <div class="control-panel">
                {move || match sig.auth.get() {
                    AuthState::Ok => view! {
                        <Controls history=sig.history status on_command=Callback::new(control) />
                    }.into_any(),
                    state => view! {
                        <div class="readonly" data-testid="readonly">
                            <p><b>"Read-only view."</b> " Enter the control token printed by "<code>"spintune serve"</code>" to change targets, pause, step or stop this run."</p>
                            <form class="token" on:submit=move |ev| { ev.prevent_default(); unlock(); }>
                                <input type="password" placeholder="control token" data-testid="token"
                                    prop:value=move || token_input.get()
                                    on:input=move |ev| token_input.set(event_target_value(&ev)) />
                                <button type="submit" data-testid="unlock">"Unlock controls"</button>
                            </form>
                            {match state {
                                AuthState::Pending => Some(view! { <p class="hint">"checking token…"</p> }.into_any()),
                                AuthState::Refused(m) => Some(view! { <p class="error" data-testid="auth-error">{format!("Token refused: {m}")}</p> }.into_any()),
                                _ => None,
                            }}
                        </div>
                    }.into_any(),
                }}
            </div>
            <div class="run-tools">
                <span class="paging" data-testid="paging" data-mode=move || format!("{:?}", sig.paging.get()).to_lowercase()>{paging_note}</span>
                <label>"compare with "
                    <select data-testid="overlay" on:change=move |ev| pick_overlay(event_target_value(&ev).parse().ok())>
                        <option value="">"no other run"</option>
                        {move || other_runs().into_iter().map(|(id, name)| view! { <option value=id.to_string()>{format!("#{id} {name}")}</option> }).collect_view()}
                    </select>
                </label>
                <span class="export">"export "
                    <a data-testid="export-csv" href=export_base.url(&format!("/api/runs/{run}/export?format=csv")) download=format!("run-{run}.csv")>"CSV"</a>
                    " · "
                    <a data-testid="export-json" href=export_base.url(&format!("/api/runs/{run}/export?format=json")) download=format!("run-{run}.json")>"JSON"</a>
                </span>
            </div>
            <Dashboard history=sig.history overlay=overlay hooks=hooks />
        </div>
    }
}

/// Control buttons and target/tolerance editors (shown after authentication).
/// A button is enabled only where the run's status accepts it
/// ([`ControlsEnabled::for_status`]; all while the status is unknown).
#[component]
fn Controls(
    history: RwSignal<RunHistory>,
    status: Signal<Option<RunStatus>>,
    on_command: Callback<ControlCommand>,
) -> impl IntoView {
    let enabled = Memo::new(move |_| {
        status.with(|s| {
            s.as_ref()
                .map_or(ControlsEnabled::ALL, ControlsEnabled::for_status)
        })
    });
    let params = Memo::new(move |_| {
        history.with(|h| {
            h.latest()
                .map(|r| {
                    r.parameters
                        .iter()
                        .map(|p| (p.name.clone(), p.unit.clone(), p.target, p.tolerance))
                        .collect::<Vec<_>>()
                })
                .unwrap_or_default()
        })
    });
    view! {
        <div class="controls" data-testid="controls">
            <span class="badge ok">"controls unlocked"</span>
            <button data-testid="pause" disabled=move || !enabled.get().pause on:click=move |_| on_command.run(ControlCommand::Pause)>"Pause"</button>
            <button data-testid="resume" disabled=move || !enabled.get().resume on:click=move |_| on_command.run(ControlCommand::Resume)>"Resume"</button>
            <button data-testid="step" disabled=move || !enabled.get().step on:click=move |_| on_command.run(ControlCommand::Step)>"Single step"</button>
            <button class="danger" data-testid="stop" disabled=move || !enabled.get().stop on:click=move |_| {
                if window().confirm_with_message("Stop this run for good?").unwrap_or(false) {
                    on_command.run(ControlCommand::Stop);
                }
            }>"Stop"</button>
            // Only for a run faulted because gates moved (the table above
            // shows old → new): adopts the read positions, the run stays
            // paused until Resume.
            <Show when=move || enabled.get().accept_positions>
                <button class="primary" data-testid="accept-positions"
                    title="Adopt the positions the instrument reads now (the table above); the run stays paused until Resume, which reads every gate again"
                    on:click=move |_| on_command.run(ControlCommand::AcceptPositions)>"Accept positions"</button>
            </Show>
            <div class="targets">
                <For
                    each=move || params.get()
                    key=|p| p.0.clone()
                    children=move |(name, unit, target, tol)| view! {
                        <TargetEditor name unit target tolerance=tol enabled=Signal::derive(move || enabled.get().targets) on_command />
                    }
                />
            </div>
        </div>
    }
}

/// Edit one parameter's target and tolerance.
#[component]
fn TargetEditor(
    name: String,
    unit: String,
    target: Option<f64>,
    tolerance: Option<f64>,
    enabled: Signal<bool>,
    on_command: Callback<ControlCommand>,
) -> impl IntoView {
    let t = RwSignal::new(target.map(|t| format!("{t}")).unwrap_or_default());
    let tol = RwSignal::new(tolerance.map(|t| format!("{t}")).unwrap_or_default());
    let err = RwSignal::new(None::<String>);
    let n2 = name.clone();
    let apply = move || {
        let tt = t.get_untracked();
        let target = if tt.trim().is_empty() {
            None
        } else {
            match tt.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => Some(v),
                _ => {
                    err.set(Some("target must be a number".into()));
                    return;
                }
            }
        };
        let tl = tol.get_untracked();
        let tolerance = if tl.trim().is_empty() {
            None
        } else {
            match tl.trim().parse::<f64>() {
                Ok(v) if v.is_finite() && v >= 0.0 => Some(Tolerance::Absolute(v)),
                _ => {
                    err.set(Some("tolerance must be a non-negative number".into()));
                    return;
                }
            }
        };
        err.set(None);
        on_command.run(ControlCommand::SetTarget {
            parameter: n2.clone(),
            target,
            tolerance,
        });
    };
    view! {
        <form class="target" data-parameter=name.clone() on:submit=move |ev| { ev.prevent_default(); apply(); }>
            <b>{name.clone()}</b>
            <label>"target "<input type="number" step="any" data-testid=format!("target-{name}")
                prop:value=move || t.get() on:input=move |ev| t.set(event_target_value(&ev)) />{format!(" {unit}")}</label>
            <label>"± "<input type="number" step="any" min="0" data-testid=format!("tolerance-{name}")
                prop:value=move || tol.get() on:input=move |ev| tol.set(event_target_value(&ev)) />{format!(" {unit}")}</label>
            <button type="submit" disabled=move || !enabled.get()>"Apply"</button>
            {move || err.get().map(|e| view! { <span class="error">{e}</span> })}
        </form>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn backoff_grows_and_caps() {
        assert_eq!(backoff_ms(1), 500);
        assert_eq!(backoff_ms(2), 1000);
        assert_eq!(backoff_ms(4), 4000);
        assert_eq!(backoff_ms(6), 10_000);
        assert_eq!(backoff_ms(60), 10_000);
    }

    fn test_session() -> SessionRef {
        Rc::new(RefCell::new(Session {
            run: 1,
            base: ApiBase::new("http://127.0.0.1:9"),
            sig: Signals {
                history: RwSignal::new(RunHistory::new()),
                paging: RwSignal::new(PagingMode::Socket),
                summary: RwSignal::new(None),
                conn: RwSignal::new(ConnState::Connecting { attempt: 0 }),
                auth: RwSignal::new(AuthState::None),
                notice: RwSignal::new(None),
            },
            ws: None,
            handlers: None,
            generation: 0,
            attempt: 0,
            retry: None,
            shut_down: false,
            token: None,
            hello_seen: false,
            pending: VecDeque::new(),
            page_in_flight: None,
            last_page: None,
            total_hint: 0,
        }))
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn an_error_before_hello_is_a_refused_handshake() {
        let sess = test_session();
        let refusal =
            r#"{"type":"error","message":"this server speaks protocol v3; the client stated v2"}"#;
        assert_eq!(
            handle_message(&sess, refusal),
            After::Refused("this server speaks protocol v3; the client stated v2".into())
        );
        // After the hello, an error is a notice (or a refused token) and the socket stays.
        let hello = format!(
            r#"{{"type":"hello","version":{PROTOCOL_VERSION},"run":{{"id":1,"name":"demo","status":{{"state":"faulted","fault":{{"kind":"device","message":"timeout"}}}},"iterations":0,"lab_seconds":0.0,"tuned":false}}}}"#
        );
        assert_eq!(handle_message(&sess, &hello), After::Continue);
        let sig = sess.borrow().sig;
        assert_eq!(
            sig.summary
                .with_untracked(|s| s.as_ref().map(|s| status_label(&s.status))),
            Some(
                "faulted — Instrument fault: timeout — needs a person: check the instrument, then Resume"
                    .into()
            )
        );
        assert_eq!(
            handle_message(&sess, r#"{"type":"error","message":"unknown parameter x"}"#),
            After::Continue
        );
        assert_eq!(
            sig.notice.get_untracked().as_deref(),
            Some("server: unknown parameter x")
        );
        // A server of another version is named in a notice.
        let old = hello.replace(
            &format!(r#""version":{PROTOCOL_VERSION}"#),
            r#""version":1"#,
        );
        assert_eq!(handle_message(&sess, &old), After::Continue);
        assert!(sig
            .notice
            .get_untracked()
            .is_some_and(|n| n.contains("protocol v1")));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pages_scans_live_gaps_and_an_old_server_refusing() {
        use crate::model::fake_records;
        let sess = test_session();
        let recs = fake_records(106);
        let frame = |m: ServerMessage| serde_json::to_string(&m).unwrap();
        let hello = format!(
            r#"{{"type":"hello","version":{PROTOCOL_VERSION},"run":{{"id":1,"name":"demo","status":{{"state":"running"}},"iterations":100,"lab_seconds":0.0,"tuned":false}}}}"#
        );
        assert_eq!(handle_message(&sess, &hello), After::Continue);
        let sig = sess.borrow().sig;
        assert_eq!(sig.history.with_untracked(|h| h.total()), 100);
        // The newest page, unasked after hello.
        let page = |a: usize, b: usize, more: bool| {
            frame(ServerMessage::History {
                records: recs[a..b].iter().map(|r| r.summary()).collect(),
                more_before: more,
            })
        };
        handle_message(&sess, &page(80, 100, true));
        assert_eq!(
            sig.history
                .with_untracked(|h| h.next_page(MAX_HISTORY_PAGE)),
            Some((80, 80))
        );
        // The answer to our request (as `request_more` queues it on an open
        // socket): the server holds nothing older than 30.
        {
            let mut s = sess.borrow_mut();
            s.pending.push_back(Pending::History);
            s.page_in_flight = Some((80, 80));
        }
        handle_message(&sess, &page(30, 80, false));
        assert_eq!(
            sig.history.with_untracked(|h| (h.len(), h.gaps())),
            (70, vec![])
        );
        assert!(sess.borrow().pending.is_empty() && sess.borrow().page_in_flight.is_none());
        // Scans on request go to the inspected iteration.
        sess.borrow_mut().pending.push_back(Pending::Scans(42));
        handle_message(
            &sess,
            &frame(ServerMessage::Scans {
                iteration: 42,
                scans: recs[42].scans.clone(),
            }),
        );
        assert_eq!(
            sig.history.with_untracked(|h| h.scans(42).map(|s| s.len())),
            Some(1)
        );
        assert!(sess.borrow().pending.is_empty());
        // A live frame after a gap (e.g. after `lagged`): kept, the gap is asked for next.
        handle_message(
            &sess,
            &frame(ServerMessage::Iteration {
                record: recs[105].clone(),
            }),
        );
        assert_eq!(
            sig.history
                .with_untracked(|h| h.next_page(MAX_HISTORY_PAGE)),
            Some((105, 5))
        );
        assert_eq!(
            sig.summary
                .with_untracked(|s| s.as_ref().map(|s| s.iterations)),
            Some(106)
        );
        // A server without socket paging refuses `subscribe` and `history`:
        // the first error is the subscription's (ignored), the second moves
        // paging to HTTP with a notice; the socket stays.
        {
            let mut s = sess.borrow_mut();
            s.pending.push_back(Pending::Subscribe);
            s.pending.push_back(Pending::History);
            s.page_in_flight = Some((105, 5));
        }
        let refusal = frame(ServerMessage::Error {
            message: "not implemented yet".into(),
        });
        assert_eq!(handle_message(&sess, &refusal), After::Continue);
        assert_eq!(sig.paging.get_untracked(), PagingMode::Socket);
        assert_eq!(sig.notice.get_untracked(), None);
        assert_eq!(handle_message(&sess, &refusal), After::Continue);
        assert_eq!(sig.paging.get_untracked(), PagingMode::Http);
        assert!(sess.borrow().page_in_flight.is_none());
        assert!(sig
            .notice
            .get_untracked()
            .is_some_and(|n| n.contains("over HTTP") && n.contains("not implemented yet")));
    }
}
