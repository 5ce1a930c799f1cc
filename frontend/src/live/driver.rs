//! The IO around one run's [`LiveClient`]: the WebSocket and its callbacks,
//! HTTP fetches, the reconnection timer, and the signals the page shows.
//! Nothing is decided here: every callback becomes an [`Event`], every
//! [`Action`] is carried out as asked.

use std::cell::RefCell;
use std::rc::{Rc, Weak};

use leptos::prelude::*;
use spintune::protocol::{IterationRecord, RunSummary};
use wasm_bindgen::prelude::*;
use web_sys::{CloseEvent, MessageEvent, WebSocket};

use super::client::{Action, AuthState, ConnState, Event, LiveClient, PagingMode, SocketId};
use crate::api::{get_json, ApiBase, ApiError};
use crate::history::RunHistory;

/// What the page shows of a run's connection.
#[derive(Clone, Copy)]
pub struct Signals {
    /// The run's iterations.
    pub history: RwSignal<RunHistory>,
    /// How older pages are fetched (shown next to the progress).
    pub paging: RwSignal<PagingMode>,
    /// The run's summary (status included).
    pub summary: RwSignal<Option<RunSummary>>,
    /// The connection badge.
    pub conn: RwSignal<ConnState>,
    /// The control token's state.
    pub auth: RwSignal<AuthState>,
    /// A notice above the charts.
    pub notice: RwSignal<Option<String>>,
    /// The page's alerts (the app's, from the context).
    pub alerts: crate::attention::Alerts,
}

impl Signals {
    /// Before anything is known.
    pub fn new() -> Self {
        Self {
            history: RwSignal::new(RunHistory::new()),
            paging: RwSignal::new(PagingMode::Socket),
            summary: RwSignal::new(None),
            conn: RwSignal::new(ConnState::Connecting { attempt: 0 }),
            auth: RwSignal::new(AuthState::None),
            notice: RwSignal::new(None),
            alerts: crate::attention::use_alerts(),
        }
    }
}

type Handler<T> = Closure<dyn FnMut(T)>;

struct Socket {
    id: SocketId,
    ws: WebSocket,
    _handlers: (
        Handler<web_sys::Event>,
        Handler<MessageEvent>,
        Handler<CloseEvent>,
    ),
}

impl Socket {
    fn close(self) {
        self.ws.set_onopen(None);
        self.ws.set_onmessage(None);
        self.ws.set_onclose(None);
        let _ = self.ws.close();
    }
}

struct Inner {
    client: LiveClient,
    base: ApiBase,
    sig: Signals,
    socket: Option<Socket>,
    retry: Option<gloo_timers::callback::Timeout>,
}

/// One run's connection: [`Driver::feed`] it what the person does; the
/// browser's callbacks feed it the rest.
#[derive(Clone)]
pub struct Driver(Rc<RefCell<Inner>>);

impl Driver {
    /// The connection of run `run`, showing itself in `sig`; it starts at once
    /// (see [`LiveClient::new`] for `total_hint`).
    pub fn start(run: u64, total_hint: Option<u64>, base: ApiBase, sig: Signals) -> Self {
        let driver = Driver(Rc::new(RefCell::new(Inner {
            client: LiveClient::new(run, total_hint),
            base,
            sig,
            socket: None,
            retry: None,
        })));
        driver.feed(Event::Start);
        driver
    }

    /// Hand `event` to the client and carry out what it asks.
    pub fn feed(&self, event: Event) {
        let actions: Vec<Action> = {
            let mut inner = self.0.borrow_mut();
            let Inner { client, sig, .. } = &mut *inner;
            let mut event = Some(event);
            // Notify the history's readers only when it changed.
            sig.history.try_maybe_update(|h| {
                let before = h.version();
                if let Some(event) = event.take() {
                    client.handle(event, h);
                }
                (h.version() != before, ())
            });
            if let Some(event) = event {
                // The view is gone (its signals disposed): still close and stop.
                client.handle(event, &mut RunHistory::new());
            }
            std::iter::from_fn(|| client.poll()).collect()
        };
        for action in actions {
            self.apply(action);
        }
    }

    fn weak(&self) -> Weak<RefCell<Inner>> {
        Rc::downgrade(&self.0)
    }

    fn apply(&self, action: Action) {
        let sig = self.0.borrow().sig;
        match action {
            Action::Open { socket, from } => self.open(socket, from),
            Action::Close { socket } => {
                let mut inner = self.0.borrow_mut();
                if inner.socket.as_ref().is_some_and(|s| s.id == socket) {
                    if let Some(s) = inner.socket.take() {
                        s.close();
                    }
                }
            }
            Action::Send { socket, text } => {
                let inner = self.0.borrow();
                if let Some(s) = inner.socket.as_ref().filter(|s| s.id == socket) {
                    if s.ws.ready_state() == WebSocket::OPEN {
                        let _ = s.ws.send_with_str(&text);
                    }
                }
            }
            Action::FetchSummary { path } => {
                self.fetch::<RunSummary>(&path, Event::Summary);
            }
            Action::FetchPage {
                before,
                limit,
                path,
            } => self.fetch::<Vec<IterationRecord>>(&path, move |result| Event::Page {
                before,
                limit,
                result,
            }),
            Action::FetchScans { iteration, path } => {
                self.fetch::<Vec<IterationRecord>>(&path, move |result| Event::Scans {
                    iteration,
                    result,
                })
            }
            Action::ScheduleReconnect { delay_ms } => {
                let weak = self.weak();
                let timer = gloo_timers::callback::Timeout::new(delay_ms, move || {
                    if let Some(inner) = weak.upgrade() {
                        Driver(inner).feed(Event::Tick { now_ms: now_ms() });
                    }
                });
                self.0.borrow_mut().retry = Some(timer);
            }
            Action::CancelReconnect => self.0.borrow_mut().retry = None,
            Action::Conn(conn) => {
                let _ = sig.conn.try_set(conn);
            }
            Action::Auth(auth) => {
                let _ = sig.auth.try_set(auth);
            }
            Action::Paging(paging) => {
                let _ = sig.paging.try_set(paging);
            }
            Action::Summary(summary) => {
                let _ = sig.summary.try_set(Some(summary));
            }
            Action::Notice(notice) => {
                let _ = sig.notice.try_set(Some(notice));
            }
            Action::Alert { alert, at } => crate::attention::raise(sig.alerts, alert, Some(at)),
        }
    }

    /// `GET path`, then feed `event(result)`.
    fn fetch<T: serde::de::DeserializeOwned + 'static>(
        &self,
        path: &str,
        event: impl FnOnce(Result<T, ApiError>) -> Event + 'static,
    ) {
        let url = self.0.borrow().base.url(path);
        let weak = self.weak();
        leptos::task::spawn_local(async move {
            let result = get_json::<T>(&url).await;
            if let Some(inner) = weak.upgrade() {
                Driver(inner).feed(event(result));
            }
        });
    }

    fn open(&self, id: SocketId, from: u64) {
        let url = {
            let inner = self.0.borrow();
            inner.base.run_ws_url(inner.client.run(), from)
        };
        let ws = match WebSocket::new(&url) {
            Ok(ws) => ws,
            Err(e) => {
                return self.feed(Event::OpenFailed {
                    socket: id,
                    error: format!("{url}: {e:?}"),
                })
            }
        };
        let weak = self.weak();
        let on_open = Closure::<dyn FnMut(web_sys::Event)>::new(move |_| {
            if let Some(inner) = weak.upgrade() {
                Driver(inner).feed(Event::Opened(id));
            }
        });
        let weak = self.weak();
        let on_message = Closure::<dyn FnMut(MessageEvent)>::new(move |ev: MessageEvent| {
            let Some(text) = ev.data().as_string() else {
                return;
            };
            if let Some(inner) = weak.upgrade() {
                Driver(inner).feed(Event::Frame { socket: id, text });
            }
        });
        let weak = self.weak();
        let on_close = Closure::<dyn FnMut(CloseEvent)>::new(move |ev: CloseEvent| {
            if let Some(inner) = weak.upgrade() {
                Driver(inner).feed(Event::Closed {
                    socket: id,
                    code: ev.code(),
                    reason: ev.reason(),
                });
            }
        });
        ws.set_onopen(Some(on_open.as_ref().unchecked_ref()));
        ws.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
        ws.set_onclose(Some(on_close.as_ref().unchecked_ref()));
        let previous = self.0.borrow_mut().socket.replace(Socket {
            id,
            ws,
            _handlers: (on_open, on_message, on_close),
        });
        if let Some(previous) = previous {
            previous.close();
        }
    }
}

/// A monotonic clock, ms (the page's `performance.now()`).
fn now_ms() -> u64 {
    window()
        .performance()
        .map(|p| p.now())
        .unwrap_or(0.0)
        .max(0.0) as u64
}
