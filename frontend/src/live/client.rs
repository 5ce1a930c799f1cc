//! The live viewer client without IO: everything live mode decides about one
//! run's WebSocket, as a state machine in the style of the core's
//! `RunSession` (plain Rust: no `web_sys`, no Leptos; tested natively).
//!
//! ```text
//! client.handle(event, &mut history)        // feed what happened
//! while let Some(action) = client.poll() { … } // then do what it asks
//! ```
//!
//! **Events** ([`Event`]): the page started, the run's summary answered
//! over HTTP, a socket opened / sent a frame / closed (each names the
//! [`SocketId`] the client gave it: events of an older socket are ignored),
//! an HTTP page or scans answer, a timer tick with the time in ms, and the
//! person's requests (unlock, control, inspect an iteration's scans, leave).
//!
//! **Actions** ([`Action`]): open a socket at `from`, close one, send a text
//! frame, fetch the summary / an older page / an iteration's scans over
//! HTTP, schedule (or cancel) a reconnection after N ms (answered with a
//! [`Event::Tick`]), and the view parts that changed: connection state,
//! token state, paging mode, run summary, a notice. Records are merged into
//! the [`RunHistory`] the shell lends to [`LiveClient::handle`] (the
//! dashboard's data), so the shell knows they changed from
//! [`RunHistory::version`].
//!
//! **The protocol** (v[`PROTOCOL_VERSION`], stated in the socket URL as
//! `?protocol=4`): the server sends `hello`, then the newest page of
//! iteration summaries unasked; the client subscribes to live frames with
//! scans and asks for older pages with `history {before, limit}` (at most
//! [`MAX_HISTORY_PAGE`]) until every gap of [`RunHistory::gaps`] is filled,
//! and for one iteration's scans with `scans {iteration}`; its `subscribe`
//! also asks for the run's `alert` frames, which become [`Action::Alert`]. After `lagged`
//! the server sends the newest page again, unasked; the gap it leaves is
//! paged back like any other. The server answers requests in order, so the
//! client keeps a queue of requests whose answer (or `error`) is due
//! (`subscribe` has no answer when accepted: an `error` while it is first in
//! the queue is its refusal, and any later answer accepts it). A server that
//! refuses `history` or `scans` gets a notice and the same data is fetched
//! over HTTP (`GET /api/runs/{id}/iterations?from=&limit=`).
//!
//! **Connection**: an `error` before `hello` is the server refusing the
//! handshake (e.g. another protocol version): the client closes and does not
//! retry. A dropped socket is reopened after [`backoff_ms`] (0.5 s doubling
//! to 10 s), resuming after the newest held iteration; a `hello` of this
//! protocol version resets the back-off (one of another version does not,
//! so such a server cannot cause a reconnection storm). A socket that closes
//! without ever opening makes the client ask for the run's summary over
//! HTTP: a 404 (the server has no such run, e.g. `#live/99`) stops the
//! retries for good, anything else lets them go on. A socket that closes
//! after the run ended is not reopened.

use std::collections::VecDeque;

use spintune::protocol::{
    Alert, ClientMessage, ControlCommand, IterationRecord, RunStatus, RunSummary, ServerMessage,
    DEFAULT_HISTORY_PAGE, MAX_HISTORY_PAGE, PROTOCOL_VERSION,
};

use crate::api::ApiError;
use crate::history::RunHistory;
use crate::model::status_is_final;

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

/// How history pages and scans are fetched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PagingMode {
    /// Over the run's WebSocket (`history`, `scans`), the protocol's way.
    Socket,
    /// Over HTTP (`/api/runs/{id}/iterations`), after the server refused a
    /// socket request (a server without paged history).
    Http,
}

/// Names one socket the client asked the shell to open; every socket event
/// carries it, so that events of a socket the client has given up are
/// ignored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SocketId(pub u64);

/// What happened, fed to [`LiveClient::handle`].
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The view was created: fetch the summary first
    /// ([`LiveClient::new`] without a total) or connect.
    Start,
    /// The answer to [`Action::FetchSummary`]; an error is the HTTP
    /// client's text (`"HTTP 404: …"` for a refused request).
    Summary(Result<RunSummary, ApiError>),
    /// The socket opened.
    Opened(SocketId),
    /// The socket could not even be created (`WebSocket::new` failed).
    OpenFailed {
        /// Which socket.
        socket: SocketId,
        /// The URL and why, shown in a notice (`cannot open {error}`).
        error: String,
    },
    /// A text frame arrived.
    Frame {
        /// On which socket.
        socket: SocketId,
        /// Its text (a [`ServerMessage`] as JSON).
        text: String,
    },
    /// A frame arrived, already decoded.
    Message {
        /// On which socket.
        socket: SocketId,
        /// The message.
        message: ServerMessage,
    },
    /// The socket closed (or never opened).
    Closed {
        /// Which socket.
        socket: SocketId,
        /// Close code (1000: normal; 1006: dropped or never opened).
        code: u16,
        /// Close reason, possibly empty.
        reason: String,
    },
    /// The answer to [`Action::FetchPage`].
    Page {
        /// The request's `before`.
        before: u64,
        /// The request's `limit`.
        limit: u32,
        /// The records, or the HTTP client's error.
        result: Result<Vec<IterationRecord>, ApiError>,
    },
    /// The answer to [`Action::FetchScans`].
    Scans {
        /// The iteration asked for.
        iteration: u64,
        /// The stored records from it on (its scans are taken), or the error.
        result: Result<Vec<IterationRecord>, ApiError>,
    },
    /// The time, ms (any monotonic clock): a due reconnection is made.
    Tick {
        /// Now, ms.
        now_ms: u64,
    },
    /// The person entered the control token.
    Unlock {
        /// The token.
        token: String,
    },
    /// The person pressed a control.
    Control(ControlCommand),
    /// The inspector wants the scans of this iteration.
    WantScans(u64),
    /// The view goes away: close and never retry.
    Shutdown,
}

/// What the shell must do, from [`LiveClient::poll`].
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Open a socket on the run's stream resuming at iteration `from`
    /// (`ApiBase::run_ws_url(run, from)`: the URL states `?protocol=4`).
    Open {
        /// Its name for later events.
        socket: SocketId,
        /// First iteration wanted live.
        from: u64,
    },
    /// Close this socket and forget its events.
    Close {
        /// Which.
        socket: SocketId,
    },
    /// Send a text frame.
    Send {
        /// On which socket.
        socket: SocketId,
        /// A [`ClientMessage`] as JSON.
        text: String,
    },
    /// `GET path` → a [`RunSummary`]; answer with [`Event::Summary`].
    FetchSummary {
        /// e.g. `/api/runs/3`.
        path: String,
    },
    /// `GET path` → records; answer with [`Event::Page`].
    FetchPage {
        /// Only records below this iteration are wanted.
        before: u64,
        /// Page size.
        limit: u32,
        /// e.g. `/api/runs/3/iterations?from=80&limit=20`.
        path: String,
    },
    /// `GET path` → records; answer with [`Event::Scans`].
    FetchScans {
        /// The iteration whose scans are wanted.
        iteration: u64,
        /// e.g. `/api/runs/3/iterations?from=42&limit=1`.
        path: String,
    },
    /// Feed an [`Event::Tick`] after this delay (replacing any earlier
    /// timer): the reconnection is then due.
    ScheduleReconnect {
        /// Delay, ms.
        delay_ms: u32,
    },
    /// Drop the reconnection timer.
    CancelReconnect,
    /// Show this connection state.
    Conn(ConnState),
    /// Show this token state.
    Auth(AuthState),
    /// Show this paging mode.
    Paging(PagingMode),
    /// Show this run summary.
    Summary(RunSummary),
    /// Show this notice.
    Notice(String),
    /// The run raised an alert (the server's `alert` frame): list it and
    /// ask for attention.
    Alert {
        /// What happened.
        alert: Alert,
        /// When the server raised it, RFC 3339 UTC.
        at: String,
    },
}

/// A request on the socket whose answer (or `error`) is still due; the
/// server answers in order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pending {
    Auth,
    Control,
    History,
    Scans(u64),
    /// `subscribe` has no answer when accepted; an `error` while it is first
    /// in the queue is its refusal (a server without it sends full records).
    Subscribe,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Socket {
    None,
    Connecting(SocketId),
    Open(SocketId),
}

/// Why the summary was fetched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SummaryFetch {
    /// Before the first socket, to ask only for the newest page.
    Initial,
    /// A socket closed without opening: does the run exist?
    Check,
}

/// The sans-IO viewer client of one run (see the module doc).
#[derive(Debug)]
pub struct LiveClient {
    run: u64,
    /// Iterations the server holds, from the run list or the summary (the
    /// first socket's `from`); `None` until known.
    total_hint: Option<u64>,
    socket: Socket,
    next_socket: u64,
    conn: ConnState,
    auth: AuthState,
    paging: PagingMode,
    summary: Option<RunSummary>,
    token: Option<String>,
    /// Reconnection attempts since the last good `hello`.
    attempt: u32,
    /// The newest time seen ([`Event::Tick`]), ms.
    now_ms: u64,
    /// When the scheduled reconnection is due, ms.
    retry_due: Option<u64>,
    summary_fetch: Option<SummaryFetch>,
    /// The view went away, the server refused the handshake or has no such
    /// run: no more sockets.
    stopped: bool,
    /// The server's `hello` arrived on the current socket.
    hello_seen: bool,
    /// Pages the server sends unasked and has not yet sent (after `hello`
    /// and after `lagged`), which come before any answer.
    unasked_pages: u32,
    /// Requests on the current socket awaiting their answer.
    pending: VecDeque<Pending>,
    /// The older page being fetched: (before, limit).
    page_in_flight: Option<(u64, u32)>,
    /// The last page asked for and how many rows it added (stops a loop on
    /// a server that keeps answering nothing for a gap).
    last_page: Option<((u64, u32), usize)>,
    /// The iteration whose scans were asked for to show the latest scans
    /// (once per iteration: a run that is over, paused or reopened has no
    /// live frames with scans).
    latest_scans_asked: Option<u64>,
    actions: VecDeque<Action>,
}

impl LiveClient {
    /// The client of run `run`. `total_hint`: iterations the server holds
    /// (from the run list), if known; without it the client fetches the
    /// run's summary before the first socket, which then asks only for the
    /// newest page. Nothing happens before [`Event::Start`].
    pub fn new(run: u64, total_hint: Option<u64>) -> Self {
        Self {
            run,
            total_hint,
            socket: Socket::None,
            next_socket: 0,
            conn: ConnState::Connecting { attempt: 0 },
            auth: AuthState::None,
            paging: PagingMode::Socket,
            summary: None,
            token: None,
            attempt: 0,
            now_ms: 0,
            retry_due: None,
            summary_fetch: None,
            stopped: false,
            hello_seen: false,
            unasked_pages: 0,
            pending: VecDeque::new(),
            page_in_flight: None,
            last_page: None,
            latest_scans_asked: None,
            actions: VecDeque::new(),
        }
    }

    /// The run.
    pub fn run(&self) -> u64 {
        self.run
    }

    /// The connection state (as last sent in [`Action::Conn`]).
    pub fn conn(&self) -> &ConnState {
        &self.conn
    }

    /// The token state.
    pub fn auth(&self) -> &AuthState {
        &self.auth
    }

    /// How older pages are fetched.
    pub fn paging(&self) -> PagingMode {
        self.paging
    }

    /// The run's summary, once the server sent one.
    pub fn summary(&self) -> Option<&RunSummary> {
        self.summary.as_ref()
    }

    /// The next thing to do, if any.
    pub fn poll(&mut self) -> Option<Action> {
        self.actions.pop_front()
    }

    /// Feed one event; records go into `history`.
    pub fn handle(&mut self, event: Event, history: &mut RunHistory) {
        match event {
            Event::Start => {
                if self.total_hint.is_some() {
                    self.connect(history);
                } else {
                    self.fetch_summary(SummaryFetch::Initial);
                }
            }
            Event::Summary(result) => self.on_summary(result, history),
            Event::Opened(socket) => self.on_open(socket),
            Event::OpenFailed { socket, error } => {
                if self.socket == Socket::Connecting(socket) && !self.stopped {
                    self.notice(format!("cannot open {error}"));
                    self.schedule_reconnect();
                }
            }
            Event::Frame { socket, text } => {
                if !self.is_current(socket) {
                    return;
                }
                match serde_json::from_str::<ServerMessage>(&text) {
                    Ok(message) => self.on_message(message, history),
                    Err(e) => {
                        self.notice(format!("undecodable message from server: {e}"));
                        self.request_more(history);
                    }
                }
            }
            Event::Message { socket, message } => {
                if self.is_current(socket) {
                    self.on_message(message, history);
                }
            }
            Event::Closed {
                socket,
                code,
                reason,
            } => self.on_close(socket, code, &reason),
            Event::Page {
                before,
                limit,
                result,
            } => self.on_page(before, limit, result, history),
            Event::Scans { iteration, result } => match result {
                Ok(records) => {
                    let scans = records
                        .into_iter()
                        .find(|r| r.iteration == iteration)
                        .map(|r| r.scans)
                        .unwrap_or_default();
                    history.offer_scans(iteration, scans);
                }
                Err(e) => self.notice(format!(
                    "cannot load the scans of iteration {iteration}: {e}"
                )),
            },
            Event::Tick { now_ms } => {
                self.now_ms = self.now_ms.max(now_ms);
                if self.retry_due.is_some_and(|due| self.now_ms >= due) {
                    self.retry_due = None;
                    self.connect(history);
                }
            }
            Event::Unlock { token } => {
                let token = token.trim().to_string();
                if token.is_empty() {
                    return;
                }
                self.set_auth(AuthState::Pending);
                self.token = Some(token.clone());
                if self.send(&ClientMessage::Auth { token }) {
                    self.pending.push_back(Pending::Auth);
                }
            }
            Event::Control(command) => {
                if self.send(&ClientMessage::Control { command }) {
                    self.pending.push_back(Pending::Control);
                } else {
                    self.notice("not connected; try again when the badge says live".into());
                }
            }
            Event::WantScans(k) => self.request_scans(k),
            Event::Shutdown => {
                self.stopped = true;
                self.cancel_retry();
                self.drop_socket();
            }
        }
    }

    fn is_current(&self, socket: SocketId) -> bool {
        matches!(self.socket, Socket::Connecting(s) | Socket::Open(s) if s == socket)
    }

    fn notice(&mut self, text: String) {
        self.actions.push_back(Action::Notice(text));
    }

    fn set_conn(&mut self, conn: ConnState) {
        self.conn = conn.clone();
        self.actions.push_back(Action::Conn(conn));
    }

    fn set_auth(&mut self, auth: AuthState) {
        self.auth = auth.clone();
        self.actions.push_back(Action::Auth(auth));
    }

    fn set_paging(&mut self, paging: PagingMode) {
        if self.paging != paging {
            self.paging = paging;
            self.actions.push_back(Action::Paging(paging));
        }
    }

    fn set_summary(&mut self, summary: RunSummary) {
        self.summary = Some(summary.clone());
        self.actions.push_back(Action::Summary(summary));
    }

    /// Send `msg` on the open socket; `false` when there is none.
    fn send(&mut self, msg: &ClientMessage) -> bool {
        let Socket::Open(socket) = self.socket else {
            return false;
        };
        match serde_json::to_string(msg) {
            Ok(text) => {
                self.actions.push_back(Action::Send { socket, text });
                true
            }
            Err(_) => false,
        }
    }

    fn fetch_summary(&mut self, why: SummaryFetch) {
        if self.summary_fetch.is_some() {
            return;
        }
        self.summary_fetch = Some(why);
        self.actions.push_back(Action::FetchSummary {
            path: format!("/api/runs/{}", self.run),
        });
    }

    fn fetch_scans(&mut self, k: u64) {
        self.actions.push_back(Action::FetchScans {
            iteration: k,
            path: format!("/api/runs/{}/iterations?from={k}&limit=1", self.run),
        });
    }

    fn cancel_retry(&mut self) {
        if self.retry_due.take().is_some() {
            self.actions.push_back(Action::CancelReconnect);
        }
    }

    /// Forget the current socket (closing it) and what was asked on it.
    fn drop_socket(&mut self) {
        if let Socket::Connecting(socket) | Socket::Open(socket) = self.socket {
            self.actions.push_back(Action::Close { socket });
        }
        self.socket = Socket::None;
        self.pending.clear();
        self.page_in_flight = None;
        self.unasked_pages = 0;
    }

    fn connect(&mut self, history: &RunHistory) {
        if self.stopped {
            return;
        }
        self.drop_socket();
        self.cancel_retry();
        self.hello_seen = false;
        // Resume after the newest held iteration; on the first connection
        // ask for the newest page only (a server that ignores paging sends
        // everything from `from`, so `from` keeps that to one page too).
        let from = history
            .extent()
            .map(|(_, last)| last + 1)
            .unwrap_or_else(|| {
                self.total_hint
                    .unwrap_or(0)
                    .saturating_sub(DEFAULT_HISTORY_PAGE as u64)
            });
        let socket = SocketId(self.next_socket);
        self.next_socket += 1;
        self.socket = Socket::Connecting(socket);
        self.set_conn(ConnState::Connecting {
            attempt: self.attempt,
        });
        self.actions.push_back(Action::Open { socket, from });
    }

    fn schedule_reconnect(&mut self) {
        if self.stopped {
            return;
        }
        self.drop_socket();
        self.attempt += 1;
        let delay_ms = backoff_ms(self.attempt);
        self.set_conn(ConnState::Reconnecting {
            attempt: self.attempt,
            delay_ms,
        });
        self.retry_due = Some(self.now_ms + delay_ms as u64);
        self.actions
            .push_back(Action::ScheduleReconnect { delay_ms });
    }

    /// Stop for good, closed for `reason`, with a notice.
    fn give_up(&mut self, reason: String, notice: String) {
        self.stopped = true;
        self.cancel_retry();
        self.drop_socket();
        self.set_conn(ConnState::Closed { reason });
        self.notice(notice);
    }

    fn on_summary(&mut self, result: Result<RunSummary, ApiError>, history: &RunHistory) {
        let Some(why) = self.summary_fetch.take() else {
            return;
        };
        if self.stopped {
            return;
        }
        match result {
            Err(e) if e.is_not_found() => {
                let detail = e.detail();
                self.give_up(
                    format!("no run {} on the server", self.run),
                    format!(
                        "The server has no run #{} ({detail}); it may have been deleted. Pick a run from the list.",
                        self.run
                    ),
                );
            }
            result => {
                if why == SummaryFetch::Initial {
                    // Learn the run's size, so the first socket asks for one page.
                    self.total_hint = Some(result.map(|s| s.iterations).unwrap_or(0));
                    self.connect(history);
                }
            }
        }
    }

    fn on_open(&mut self, socket: SocketId) {
        if self.socket != Socket::Connecting(socket) {
            return;
        }
        self.socket = Socket::Open(socket);
        self.set_conn(ConnState::Open);
        if let Some(token) = self.token.clone() {
            if self.send(&ClientMessage::Auth { token }) {
                self.pending.push_back(Pending::Auth);
            }
        }
    }

    fn on_close(&mut self, socket: SocketId, code: u16, reason: &str) {
        if !self.is_current(socket) || self.stopped {
            return;
        }
        let opened = matches!(self.socket, Socket::Open(_));
        if self
            .summary
            .as_ref()
            .is_some_and(|r| status_is_final(&r.status))
        {
            self.drop_socket();
            self.set_conn(ConnState::Closed {
                reason: "run has ended".into(),
            });
            return;
        }
        if code != 1000 && !reason.is_empty() {
            self.notice(format!("socket closed: {reason}"));
        }
        self.schedule_reconnect();
        if !opened {
            // Refused before the upgrade: no server, or no such run.
            self.fetch_summary(SummaryFetch::Check);
        }
    }

    fn on_message(&mut self, msg: ServerMessage, history: &mut RunHistory) {
        match msg {
            ServerMessage::Hello { version, run } => {
                if version == PROTOCOL_VERSION {
                    self.attempt = 0;
                } else {
                    self.notice(format!(
                        "server speaks protocol v{version}, this page v{PROTOCOL_VERSION}; reload the page"
                    ));
                }
                history.set_total(run.iterations);
                self.set_summary(run);
                self.hello_seen = true;
                self.unasked_pages = 1;
                // Live frames with scans: the latest iteration's scans are drawn.
                if self.send(&ClientMessage::Subscribe {
                    scans: true,
                    alerts: true,
                }) {
                    self.pending.push_back(Pending::Subscribe);
                }
            }
            ServerMessage::History {
                records,
                more_before,
            } => {
                let answer = if self.unasked_pages > 0 {
                    self.unasked_pages -= 1;
                    None
                } else if self.answered(Pending::History) {
                    self.page_in_flight.take()
                } else {
                    None
                };
                match answer {
                    // The answer to our request: `more_before` is about it.
                    Some(req) => {
                        let added = history.insert_page(records, more_before, Some(req.0)).added;
                        self.last_page = Some((req, added));
                    }
                    // Unasked (after hello or lagged): take the records only.
                    None => {
                        history.insert(records);
                    }
                }
            }
            ServerMessage::Iteration { record } => {
                let tuned = record.tuned;
                let (k, lab) = (record.iteration, record.lab_seconds);
                let added = history.insert([record]).added;
                history.set_total(history.total().max(k + 1));
                if added > 0 {
                    if let Some(mut s) = self.summary.clone() {
                        s.iterations = s.iterations.max(k + 1);
                        s.lab_seconds = lab;
                        s.tuned = tuned;
                        self.set_summary(s);
                    }
                }
            }
            ServerMessage::Scans { iteration, scans } => {
                self.answered(Pending::Scans(iteration));
                history.offer_scans(iteration, scans);
            }
            ServerMessage::Status { run } => {
                // The answer to a control (if a control is the next request
                // due: only an unanswered `subscribe` may come before it), or
                // a change broadcast to every viewer: either way the run's
                // new status.
                let due = self.pending.iter().position(|p| *p != Pending::Subscribe);
                if let Some(i) = due.filter(|&i| self.pending[i] == Pending::Control) {
                    self.pending.drain(..=i);
                }
                history.set_total(run.iterations);
                self.set_summary(run);
            }
            ServerMessage::Lagged { skipped } => {
                self.unasked_pages += 1;
                self.notice(format!(
                    "this viewer fell behind ({skipped} live messages skipped); catching up from the store"
                ));
            }
            ServerMessage::Alert { alert, at } => {
                self.actions.push_back(Action::Alert { alert, at });
            }
            ServerMessage::AuthOk => {
                self.answered(Pending::Auth);
                self.set_auth(AuthState::Ok);
            }
            ServerMessage::Error { message } => {
                if !self.hello_seen {
                    // The server sends its hello first on every accepted
                    // socket: this is a refused handshake (e.g. a protocol
                    // version it does not speak). Retrying cannot help.
                    self.give_up(
                        format!("refused by the server: {message}"),
                        format!(
                            "The server refused this page's connection: {message}. This page speaks protocol v{PROTOCOL_VERSION}; reload it (or use a matching server)."
                        ),
                    );
                    return;
                }
                self.on_error(message);
            }
        }
        self.request_more(history);
    }

    /// `request`'s answer arrived: it and everything asked before it
    /// (answers come in order) are done. `false` if it was not asked.
    fn answered(&mut self, request: Pending) -> bool {
        match self.pending.iter().position(|p| *p == request) {
            Some(i) => {
                self.pending.drain(..=i);
                true
            }
            None => false,
        }
    }

    fn on_error(&mut self, message: String) {
        if self.auth == AuthState::Pending {
            if let Some(i) = self.pending.iter().position(|p| *p == Pending::Auth) {
                self.pending.remove(i);
            }
            self.token = None;
            self.set_auth(AuthState::Refused(message));
            return;
        }
        match self.pending.pop_front() {
            // A token that worked on an earlier socket was refused on this one.
            Some(Pending::Auth) => {
                self.token = None;
                self.set_auth(AuthState::Refused(message));
            }
            Some(Pending::History) => {
                self.page_in_flight = None;
                self.set_paging(PagingMode::Http);
                self.notice(format!(
                    "this server does not send history pages over the socket ({message}); loading older iterations over HTTP instead"
                ));
            }
            Some(Pending::Scans(k)) => {
                self.set_paging(PagingMode::Http);
                self.fetch_scans(k);
            }
            // Refused subscription: this server sends full records anyway.
            Some(Pending::Subscribe) => {}
            Some(Pending::Control) | None => self.notice(format!("server: {message}")),
        }
    }

    /// The scans of iteration `k`: over the socket, or over HTTP.
    fn request_scans(&mut self, k: u64) {
        if self.paging == PagingMode::Socket && self.send(&ClientMessage::Scans { iteration: k }) {
            self.pending.push_back(Pending::Scans(k));
        } else {
            self.fetch_scans(k);
        }
    }

    /// For a run that is not iterating (finished, stopped, paused,
    /// faulted, reopened: no live frame will bring scans), ask for the
    /// newest iteration's scans if they are not held (once per iteration);
    /// then for the next older page if one is missing and none is on its way.
    fn request_more(&mut self, history: &RunHistory) {
        if !self.hello_seen || self.stopped {
            return;
        }
        let iterating = self
            .summary
            .as_ref()
            .is_none_or(|s| matches!(s.status, RunStatus::Running | RunStatus::Stepping));
        if let Some(k) = history
            .missing_latest_scans()
            .filter(|k| !iterating && self.latest_scans_asked != Some(*k))
        {
            self.latest_scans_asked = Some(k);
            self.request_scans(k);
        }
        if self.page_in_flight.is_some() {
            return;
        }
        let Some(req) = history.next_page(MAX_HISTORY_PAGE) else {
            return;
        };
        if self.last_page == Some((req, 0)) {
            // The same request added nothing last time: the server has no more.
            return;
        }
        let (before, limit) = req;
        match self.paging {
            PagingMode::Socket => {
                if self.send(&ClientMessage::History {
                    before: Some(before),
                    limit: Some(limit),
                }) {
                    self.pending.push_back(Pending::History);
                    self.page_in_flight = Some(req);
                }
            }
            PagingMode::Http => {
                self.page_in_flight = Some(req);
                self.actions.push_back(Action::FetchPage {
                    before,
                    limit,
                    path: format!(
                        "/api/runs/{}/iterations?from={}&limit={limit}",
                        self.run,
                        before - limit as u64
                    ),
                });
            }
        }
    }

    fn on_page(
        &mut self,
        before: u64,
        limit: u32,
        result: Result<Vec<IterationRecord>, ApiError>,
        history: &mut RunHistory,
    ) {
        self.page_in_flight = None;
        match result {
            Ok(mut records) => {
                records.retain(|r| r.iteration < before);
                let more = !records.is_empty();
                let added = history.insert_page(records, more, Some(before)).added;
                self.last_page = Some(((before, limit), added));
                self.request_more(history);
            }
            Err(e) => self.notice(format!("cannot load older iterations: {e}")),
        }
    }
}

#[cfg(test)]
mod tests;
