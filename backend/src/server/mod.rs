//! HTTP API, WebSocket streaming and the dashboard's static files.
//!
//! All bodies are JSON; errors are `{"error": "<message naming the problem>"}`.
//! Viewing is open; endpoints marked 🔒 need `Authorization: Bearer <token>`
//! (401 without a token, 403 with a wrong one, 429 while the address is
//! throttled, see [`auth`]; nothing changes in any case). Every request passes
//! the Host and Origin checks of [`origin`] first (421 / 403).
//!
//! | method | path | body → answer |
//! |---|---|---|
//! | GET | `/api/version` | → `{"protocol_version": 4}` |
//! | GET | `/api/runs` | → `[RunSummary]` |
//! | POST 🔒 | `/api/runs` | run config (JSON form of the TOML file, see [`crate::config`]; `{}` = paper default) → 201 `RunSummary` |
//! | GET | `/api/runs/{id}` | → `RunSummary` |
//! | GET | `/api/runs/{id}/config` | → the run's config (`{"simulation": …, "backend": …}`; without a token instrument addresses, channel maps and secrets are `"<redacted>"`) |
//! | GET | `/api/runs/{id}/iterations?from=N&limit=M` | → `[IterationRecord]` with seq ≥ N (default 0), at most M ([`DEFAULT_PAGE`] if not given, ≤ [`MAX_PAGE`]) |
//! | GET | `/api/runs/{id}/export?format=csv\|json` | → the export table (see [`crate::export`]) |
//! | POST 🔒 | `/api/runs/{id}/control` | `ControlCommand` → `RunSummary` (400 invalid, 409 not applicable) |
//! | DELETE 🔒 | `/api/runs/{id}` | → 204 |
//! | GET | `/api/runs/{id}/ws?protocol=4&from=N` | WebSocket, see below |
//! | GET | `/api/runs/{id}/bridge?protocol=4` | WebSocket of the lab bridge (runs with `driver = "bridge"` or `scpi.measure = "bridge"`), see [`crate::devices::bridge`] |
//! | GET | `/*` | the dashboard (Trunk's `dist/`), or a note on how to build it; a symbolic link inside `dist/` (or a path leaving it) → 404 |
//!
//! The JSON bodies must come as `Content-Type: application/json` (optional
//! parameters); another Content-Type → 415, none → read as JSON. A body is
//! exactly one JSON value: anything but whitespace after it → 400 / 422
//! (the same strict parser reads viewer and bridge frames:
//! [`spintune::strict_json`]). Bodies: at most
//! [`listener::MAX_BODY_BYTES`], in full within
//! [`listener::BODY_READ_TIMEOUT`] of the headers (413 / 408).
//!
//! Both WebSockets require `protocol=4` ([`PROTOCOL_VERSION`](spintune::protocol::PROTOCOL_VERSION)) in the query;
//! a client that omits it (every version-1 client) or states another version
//! gets one `Error` frame naming both versions, and the socket closes.
//!
//! WebSocket (`ServerMessage` / `ClientMessage` JSON text frames): the server
//! sends `Hello`, then one `History` page (the newest
//! [`DEFAULT_HISTORY_PAGE`](spintune::protocol::DEFAULT_HISTORY_PAGE) iteration *summaries* — records with `scans`
//! empty — not older than `from`, with `more_before`), then every new
//! `Iteration` live (a summary; the full record after
//! `{"type":"subscribe","scans":true}`) and a `Status` on every status change;
//! after `{"type":"subscribe","scans":…,"alerts":true}` the run's recent
//! alerts (at most [`crate::run::RECENT_ALERTS`]) and then an `Alert` when
//! the run raises one (docs/alerts.md; never to a socket that did not ask).
//! The client pages back with `{"type":"history","before":K,"limit":L}` (L ≤
//! [`MAX_HISTORY_PAGE`](spintune::protocol::MAX_HISTORY_PAGE), larger → `Error`) and asks for one iteration's scans
//! with `{"type":"scans","iteration":K}` (→ `Scans`). A viewer whose buffer
//! ([`crate::run::ManagerOptions::viewer_buffer`] frames) overflows gets
//! `Lagged{skipped}` followed by the newest page again (not older than what
//! the socket was already sent); it pages back to fill the gap. The client
//! may send `Auth{token}` (→ `AuthOk` or `Error`) and then `Control{command}`
//! (→ `Status` or `Error`). Malformed or unauthorised frames get an `Error`;
//! the socket stays open.
//!
//! Bounds (ARCHITECTURE.md, invariant 8): a send to a viewer that does not
//! complete within [`VIEWER_SEND_TIMEOUT`] closes the socket (so a viewer
//! that never reads holds at most one frame, a page of at most
//! [`MAX_HISTORY_PAGE`](spintune::protocol::MAX_HISTORY_PAGE) summaries, plus the shared broadcast ring); the
//! server pings every [`VIEWER_PING_INTERVAL`] and closes a socket from which
//! nothing arrived for [`VIEWER_PONG_TIMEOUT`]; inbound frames are capped at
//! [`MAX_VIEWER_MESSAGE`] (viewer) and [`MAX_BRIDGE_MESSAGE`] (bridge): a
//! larger message closes the socket with 1009 (Message Too Big); at
//! most [`MAX_VIEWERS_PER_RUN`] viewer sockets per run (one more → 503).
//! Connection limits (header read timeout, connections per IP): [`listener`].
//!
//! | file | what it is |
//! |---|---|
//! | this one | the router, [`AppState`] and the bounds above |
//! | [`http`] | the REST handlers and the token check of a request |
//! | [`viewer`] | the viewer WebSocket: its upgrade and its socket loop |
//! | [`bridge_socket`] | the lab bridge's WebSocket |
//! | [`socket`] | what both sockets share: the version check, refusals, the 1009 close |
//! | [`parse`] | strict parsing of commands, frames, Content-Types, ids, query numbers |
//! | [`error`] | [`ApiError`](error::ApiError): status and `{"error": …}` |
//! | [`dashboard`] | the dashboard's static files (no symbolic links) |
//! | [`auth`], [`origin`], [`listener`], [`tls`], [`redact`] | token checks and throttling, Host/Origin checks, connections, TLS, the redacted config |

use std::path::PathBuf;
use std::sync::Arc;

use axum::routing::{get, post};
use axum::Router;

pub(crate) mod auth;
mod bridge_socket;
mod dashboard;
mod error;
mod http;
pub mod listener;
pub(crate) mod origin;
mod parse;
mod redact;
mod socket;
pub(crate) mod tls;
mod viewer;

pub use parse::{parse_client_message, parse_control};
pub use viewer::MAX_LIVE_BATCH;

use crate::run::Manager;

/// Records per `GET /api/runs/{id}/iterations` page when no `limit` is given.
pub const DEFAULT_PAGE: u64 = 1_000;
/// Largest `limit` of `GET /api/runs/{id}/iterations`.
pub const MAX_PAGE: u64 = 10_000;
/// Largest frame a viewer may send (auth and control messages are tiny), bytes.
pub const MAX_VIEWER_MESSAGE: usize = 64 * 1024;
/// Largest frame a lab bridge may send (a raw scan: e.g. 4 traces of 100,000
/// points as JSON numbers), bytes.
pub const MAX_BRIDGE_MESSAGE: usize = 16 * 1024 * 1024;
pub use crate::run::viewer_limits::{
    MAX_VIEWERS_PER_RUN, VIEWER_PING_INTERVAL, VIEWER_PONG_TIMEOUT, VIEWER_SEND_TIMEOUT,
};

/// Shared state of the HTTP handlers.
#[derive(Clone)]
pub(crate) struct AppState {
    /// The run manager.
    pub manager: Arc<Manager>,
    /// The control token and the failed-auth throttle ([`auth`]).
    pub auth: Arc<auth::Auth>,
    /// Accepted Hosts and Origins ([`origin`]).
    pub access: Arc<origin::Access>,
    /// The client of the present request (set by the socket handlers for the
    /// throttle; `None` in the shared state).
    pub client: Option<std::net::IpAddr>,
}

impl AppState {
    /// The state for one client's socket (its address feeds the auth throttle).
    pub fn for_client(self, client: auth::ClientIp) -> Self {
        Self {
            client: client.0,
            ..self
        }
    }
}

/// Build the router. `dist` is the dashboard directory (Trunk output).
pub(crate) fn router(state: AppState, dist: PathBuf) -> Router {
    let access = state.access.clone();
    let api = Router::new()
        .route("/api/version", get(http::version))
        .route("/api/runs", get(http::list_runs).post(http::create_run))
        .route(
            "/api/runs/{id}",
            get(http::get_run).delete(http::delete_run),
        )
        .route("/api/runs/{id}/config", get(http::get_config))
        .route("/api/runs/{id}/iterations", get(http::iterations))
        .route("/api/runs/{id}/export", get(http::export))
        .route("/api/runs/{id}/control", post(http::control))
        .route("/api/runs/{id}/ws", get(viewer::ws))
        .route("/api/runs/{id}/bridge", get(bridge_socket::bridge_ws))
        .with_state(state);
    origin::guard(dashboard::fallback(api, dist), access)
}
