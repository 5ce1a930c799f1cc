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
//! | GET | `/api/version` | → `{"protocol_version": 3}` |
//! | GET | `/api/runs` | → `[RunSummary]` |
//! | POST 🔒 | `/api/runs` | run config (JSON form of the TOML file, see [`crate::config`]; `{}` = paper default) → 201 `RunSummary` |
//! | GET | `/api/runs/{id}` | → `RunSummary` |
//! | GET | `/api/runs/{id}/config` | → the run's config (`{"simulation": …, "backend": …}`; without a token instrument addresses, channel maps and secrets are `"<redacted>"`) |
//! | GET | `/api/runs/{id}/iterations?from=N&limit=M` | → `[IterationRecord]` with seq ≥ N (default 0), at most M ([`DEFAULT_PAGE`] if not given, ≤ [`MAX_PAGE`]) |
//! | GET | `/api/runs/{id}/export?format=csv\|json` | → the export table (see [`crate::export`]) |
//! | POST 🔒 | `/api/runs/{id}/control` | `ControlCommand` → `RunSummary` (400 invalid, 409 not applicable) |
//! | DELETE 🔒 | `/api/runs/{id}` | → 204 |
//! | GET | `/api/runs/{id}/ws?protocol=3&from=N` | WebSocket, see below |
//! | GET | `/api/runs/{id}/bridge?protocol=3` | WebSocket of the lab bridge (runs with `driver = "bridge"` or `scpi.measure = "bridge"`), see [`crate::devices::bridge`] |
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
//! Both WebSockets require `protocol=3` ([`PROTOCOL_VERSION`]) in the query;
//! a client that omits it (every version-1 client) or states another version
//! gets one `Error` frame naming both versions, and the socket closes.
//!
//! WebSocket (`ServerMessage` / `ClientMessage` JSON text frames): the server
//! sends `Hello`, then one `History` page (the newest
//! [`DEFAULT_HISTORY_PAGE`] iteration *summaries* — records with `scans`
//! empty — not older than `from`, with `more_before`), then every new
//! `Iteration` live (a summary; the full record after
//! `{"type":"subscribe","scans":true}`) and a `Status` on every status change.
//! The client pages back with `{"type":"history","before":K,"limit":L}` (L ≤
//! [`MAX_HISTORY_PAGE`], larger → `Error`) and asks for one iteration's scans
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
//! [`MAX_HISTORY_PAGE`] summaries, plus the shared broadcast ring); the
//! server pings every [`VIEWER_PING_INTERVAL`] and closes a socket from which
//! nothing arrived for [`VIEWER_PONG_TIMEOUT`]; inbound frames are capped at
//! [`MAX_VIEWER_MESSAGE`] (viewer) and [`MAX_BRIDGE_MESSAGE`] (bridge): a
//! larger message closes the socket with 1009 (Message Too Big); at
//! most [`MAX_VIEWERS_PER_RUN`] viewer sockets per run (one more → 503).
//! Connection limits (header read timeout, connections per IP): [`listener`].

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Extension, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::json;
use spintune::protocol::{
    ClientMessage, ControlCommand, IterationRecord, ProtocolError, ServerMessage,
    DEFAULT_HISTORY_PAGE, MAX_HISTORY_PAGE, PROTOCOL_VERSION,
};
use tokio::sync::broadcast::error::RecvError;
use tower_http::services::ServeDir;

pub mod auth;
mod bridge_socket;
pub mod listener;
pub mod origin;
mod redact;
pub mod tls;

use crate::config::RunConfig;
use crate::run::{history_frame_text, Manager, RunError, ViewerSlot};

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
/// How long the server tries to send a close frame to a viewer it drops for
/// a timeout.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

/// Shared state of the HTTP handlers.
#[derive(Clone)]
pub struct AppState {
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

/// An API error: status + `{"error": message}`.
#[derive(Debug)]
pub struct ApiError(pub StatusCode, pub String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut resp = (self.0, Json(json!({ "error": self.1 }))).into_response();
        if self.0 == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                "Bearer".parse().expect("static header"),
            );
        }
        resp
    }
}

impl From<RunError> for ApiError {
    fn from(e: RunError) -> Self {
        let status = match e {
            RunError::NotFound(_) => StatusCode::NOT_FOUND,
            RunError::Conflict(_) => StatusCode::CONFLICT,
            RunError::Invalid(_) => StatusCode::UNPROCESSABLE_ENTITY,
            RunError::Internal(_) | RunError::Store(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        ApiError(status, e.to_string())
    }
}

type ApiResult<T> = Result<T, ApiError>;

/// Compare two strings in time independent of where they differ.
pub fn token_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// A fresh random control token (128 bits, hex).
pub fn random_token() -> String {
    let mut buf = [0u8; 16];
    if getrandom::getrandom(&mut buf).is_err() {
        // Extremely unlikely on Linux; fall back to time and pid.
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        buf = (t ^ ((std::process::id() as u128) << 64)).to_le_bytes();
    }
    buf.iter().map(|b| format!("{b:02x}")).collect()
}

fn authorize(state: &AppState, client: auth::ClientIp, headers: &HeaderMap) -> ApiResult<()> {
    let Some(value) = headers.get(header::AUTHORIZATION) else {
        return Err(ApiError(
            StatusCode::UNAUTHORIZED,
            "control requires the token: send `Authorization: Bearer <token>` (printed by `spintune serve`)".into(),
        ));
    };
    let value = value.to_str().unwrap_or("");
    let token = value
        .strip_prefix("Bearer ")
        .or_else(|| value.strip_prefix("bearer "))
        .unwrap_or("");
    state.auth.check(client.0, token).map_err(|r| match r {
        auth::Refusal::Wrong => ApiError(StatusCode::FORBIDDEN, r.message()),
        auth::Refusal::Throttled(_) => ApiError(StatusCode::TOO_MANY_REQUESTS, r.message()),
    })
}

/// The JSON bodies (`POST /api/runs`, `POST /api/runs/{id}/control`) must be
/// sent as `Content-Type: application/json` (parameters such as
/// `; charset=utf-8` allowed); another type is refused with 415. A request
/// without a Content-Type is read as JSON (scripts; a browser always sends
/// one, so a cross-site form post — `text/plain` or a form type — is
/// refused).
fn require_json(headers: &HeaderMap) -> ApiResult<()> {
    let Some(value) = headers.get(header::CONTENT_TYPE) else {
        return Ok(());
    };
    let text = value.to_str().unwrap_or("");
    let essence = text.split(';').next().unwrap_or("").trim();
    if essence.eq_ignore_ascii_case("application/json") {
        return Ok(());
    }
    Err(ApiError(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        format!(
            "the body must be JSON sent as `Content-Type: application/json`, got {text:?} (curl: add -H 'Content-Type: application/json')"
        ),
    ))
}

fn parse_u64(q: &HashMap<String, String>, key: &str) -> ApiResult<Option<u64>> {
    match q.get(key) {
        None => Ok(None),
        Some(v) => v.parse::<u64>().map(Some).map_err(|_| {
            ApiError(
                StatusCode::BAD_REQUEST,
                format!("query parameter `{key}` must be a non-negative integer, got {v:?}"),
            )
        }),
    }
}

fn parse_id(id: &str) -> ApiResult<u64> {
    id.parse::<u64>().map_err(|_| {
        ApiError(
            StatusCode::BAD_REQUEST,
            format!("run id must be a non-negative integer, got {id:?}"),
        )
    })
}

/// Parse a `ControlCommand` from JSON text, naming the offending field on error.
pub fn parse_control(text: &str) -> Result<ControlCommand, ProtocolError> {
    // Its form here (the core's check); whether the run has the parameter
    // and the target fits it is the run session's.
    let cmd: ControlCommand = parse_strict(text)?;
    cmd.check_form()?;
    Ok(cmd)
}

/// Parse a `ClientMessage` from JSON text, naming the offending field on error.
pub fn parse_client_message(text: &str) -> Result<ClientMessage, ProtocolError> {
    let msg: ClientMessage = parse_strict(text)?;
    if let ClientMessage::Control { command } = &msg {
        command.check_form()?;
    }
    Ok(msg)
}

/// Parse one `T` strictly ([`spintune::strict_json::parse_strict`]): one
/// JSON value and nothing after it but whitespace, no unknown keys at any
/// depth, errors naming the field. Every REST body, viewer frame and bridge
/// frame goes through it.
pub(crate) fn parse_strict<T: serde::de::DeserializeOwned + serde::Serialize>(
    text: &str,
) -> Result<T, ProtocolError> {
    spintune::strict_json::parse_strict(text)
}

/// Build the router. `dist` is the dashboard directory (Trunk output).
pub fn router(state: AppState, dist: PathBuf) -> Router {
    let access = state.access.clone();
    let api = Router::new()
        .route("/api/version", get(version))
        .route("/api/runs", get(list_runs).post(create_run))
        .route("/api/runs/{id}", get(get_run).delete(delete_run))
        .route("/api/runs/{id}/config", get(get_config))
        .route("/api/runs/{id}/iterations", get(iterations))
        .route("/api/runs/{id}/export", get(export))
        .route("/api/runs/{id}/control", post(control))
        .route("/api/runs/{id}/ws", get(ws))
        .route("/api/runs/{id}/bridge", get(bridge_ws))
        .with_state(state);
    let app = if dist.join("index.html").is_file() {
        // Symbolic links inside `dist` are not followed (404): only the
        // files really in the directory are served.
        let root = std::fs::canonicalize(&dist).unwrap_or_else(|_| dist.clone());
        let files = Router::new().fallback_service(ServeDir::new(&root)).layer(
            axum::middleware::from_fn_with_state(Arc::new(root), refuse_links),
        );
        api.fallback_service(files)
    } else {
        let note = dashboard_missing_note(&dist);
        api.fallback(move || {
            let note = note.clone();
            async move { Html(note) }
        })
    };
    origin::guard(app, access)
}

/// 404 for a dashboard path that passes through a symbolic link inside
/// `root` (or resolves outside it); otherwise on to `ServeDir`, which reads
/// the path the same way (percent-decoded, `.` skipped, `..` refused).
async fn refuse_links(
    State(root): State<Arc<PathBuf>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    match dist_path_is_plain(&root, request.uri().path()).await {
        true => next.run(request).await,
        false => (StatusCode::NOT_FOUND, "not found").into_response(),
    }
}

/// Whether every component of the file `path` names under `root` (and
/// `index.html` of a directory) is a plain file or directory, and the file
/// lies inside `root`. A path that does not exist is plain (`ServeDir`
/// answers 404).
async fn dist_path_is_plain(root: &std::path::Path, path: &str) -> bool {
    let Some(decoded) = percent_decode(path.trim_start_matches('/')) else {
        return false;
    };
    let mut here = root.to_path_buf();
    for component in std::path::Path::new(&decoded).components() {
        match component {
            std::path::Component::Normal(c) => here.push(c),
            std::path::Component::CurDir => continue,
            _ => return false,
        }
        match tokio::fs::symlink_metadata(&here).await {
            Ok(m) if m.file_type().is_symlink() => return false,
            Ok(_) => {}
            Err(_) => return true,
        }
    }
    if tokio::fs::metadata(&here).await.is_ok_and(|m| m.is_dir()) {
        here.push("index.html");
        if tokio::fs::symlink_metadata(&here)
            .await
            .is_ok_and(|m| m.file_type().is_symlink())
        {
            return false;
        }
    }
    match tokio::fs::canonicalize(&here).await {
        Ok(real) => real.starts_with(root),
        Err(_) => true,
    }
}

/// `%XX`-decode a URL path (as `ServeDir` does); `None` if it is not UTF-8.
fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            if let (Some(h), Some(l)) = (hex(bytes[i + 1]), hex(bytes[i + 2])) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8(out).ok()
}

fn dashboard_missing_note(dist: &std::path::Path) -> String {
    format!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>spintune</title></head><body>\
<h1>spintune server</h1>\
<p>The dashboard is not built: <code>{}</code> has no <code>index.html</code>.</p>\
<p>Build it from the repository root with <code>trunk build --release</code> \
(see README.md), or start the server with <code>--dist DIR</code>.</p>\
<p>The API works regardless: <a href=\"/api/runs\">/api/runs</a>.</p></body></html>",
        html_escape(&dist.display().to_string())
    )
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

async fn version() -> impl IntoResponse {
    Json(json!({ "protocol_version": PROTOCOL_VERSION }))
}

async fn list_runs(State(s): State<AppState>) -> impl IntoResponse {
    Json(s.manager.list())
}

async fn create_run(
    State(s): State<AppState>,
    Extension(client): Extension<auth::ClientIp>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<impl IntoResponse> {
    authorize(&s, client, &headers)?;
    require_json(&headers)?;
    let text = std::str::from_utf8(&body)
        .map_err(|_| ApiError(StatusCode::BAD_REQUEST, "body is not UTF-8".into()))?;
    let text = if text.trim().is_empty() { "{}" } else { text };
    let config = RunConfig::from_json_str(text)
        .map_err(|e| ApiError(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?;
    let summary = s.manager.create(config, false).await?;
    Ok((StatusCode::CREATED, Json(summary)))
}

async fn get_run(
    State(s): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id(&id)?;
    Ok(Json(s.manager.get(id)?.summary()))
}

async fn get_config(
    State(s): State<AppState>,
    Extension(client): Extension<auth::ClientIp>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id(&id)?;
    let handle = s.manager.get(id)?;
    handle.readable()?;
    let config = handle.config.clone();
    // Full with the token; instrument addresses, channel maps and secrets redacted without.
    if headers.contains_key(header::AUTHORIZATION) {
        authorize(&s, client, &headers)?;
        return Ok(Json(serde_json::to_value(config).map_err(|e| {
            ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string())
        })?));
    }
    Ok(Json(redact::config(&config)))
}

async fn iterations(
    State(s): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id(&id)?;
    let from = parse_u64(&q, "from")?.unwrap_or(0);
    let limit = parse_u64(&q, "limit")?.unwrap_or(DEFAULT_PAGE);
    if limit > MAX_PAGE {
        return Err(ApiError(
            StatusCode::BAD_REQUEST,
            format!("limit {limit} exceeds the largest page, {MAX_PAGE} records; page with `from`"),
        ));
    }
    let scans = match q.get("scans").map(String::as_str) {
        None | Some("true") => true,
        Some("false") => false,
        Some(other) => {
            return Err(ApiError(
                StatusCode::BAD_REQUEST,
                format!("query parameter `scans` must be `true` or `false`, got {other:?}"),
            ))
        }
    };
    s.manager.get(id)?;
    let store = s.manager.store().clone();
    let records = tokio::task::spawn_blocking(move || {
        if scans {
            store.iterations_json(id, from, Some(limit))
        } else {
            store.summaries_json(id, from, limit)
        }
    })
    .await
    .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
    .map_err(|e| ApiError::from(RunError::from(e)))?;
    let body = format!("[{}]", records.join(","));
    Ok(([(header::CONTENT_TYPE, "application/json")], body))
}

async fn export(
    State(s): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> ApiResult<Response> {
    let id = parse_id(&id)?;
    let format = match q.get("format").map(String::as_str) {
        None | Some("csv") => crate::export::Format::Csv,
        Some("json") => crate::export::Format::Json,
        Some(other) => {
            return Err(ApiError(
                StatusCode::BAD_REQUEST,
                format!("format must be `csv` or `json`, got {other:?}"),
            ))
        }
    };
    s.manager.get(id)?;
    let store = s.manager.store().clone();
    let out = tokio::task::spawn_blocking(move || crate::export::export(&store, id, format))
        .await
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e))?;
    let ctype = match format {
        crate::export::Format::Csv => "text/csv; charset=utf-8",
        crate::export::Format::Json => "application/json",
    };
    Ok(([(header::CONTENT_TYPE, ctype)], out).into_response())
}

async fn control(
    State(s): State<AppState>,
    Path(id): Path<String>,
    Extension(client): Extension<auth::ClientIp>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<impl IntoResponse> {
    authorize(&s, client, &headers)?;
    require_json(&headers)?;
    let id = parse_id(&id)?;
    let text = std::str::from_utf8(&body)
        .map_err(|_| ApiError(StatusCode::BAD_REQUEST, "body is not UTF-8".into()))?;
    let cmd = parse_control(text).map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))?;
    Ok(Json(s.manager.control(id, cmd).await?))
}

async fn delete_run(
    State(s): State<AppState>,
    Path(id): Path<String>,
    Extension(client): Extension<auth::ClientIp>,
    headers: HeaderMap,
) -> ApiResult<impl IntoResponse> {
    authorize(&s, client, &headers)?;
    let id = parse_id(&id)?;
    s.manager.delete(id).await?;
    Ok(StatusCode::NO_CONTENT)
}

async fn ws(
    State(s): State<AppState>,
    Extension(client): Extension<auth::ClientIp>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    upgrade: WebSocketUpgrade,
) -> ApiResult<Response> {
    let id = parse_id(&id)?;
    let from = parse_u64(&q, "from")?.unwrap_or(0);
    s.manager.get(id)?;
    let s = s.for_client(client);
    // Client messages are small; a small read buffer keeps each (frequent,
    // usually empty) poll of the socket cheap, since tungstenite zeroes it.
    let handle = s.manager.get(id)?;
    let upgrade = upgrade
        .read_buffer_size(4 * 1024)
        .max_message_size(MAX_VIEWER_MESSAGE)
        .max_frame_size(MAX_VIEWER_MESSAGE);
    if let Some(message) = version_mismatch(&q) {
        return Ok(refuse_socket(
            upgrade,
            text_of(&ServerMessage::Error { message }),
        ));
    }
    let max = s.manager.options().viewers.max_viewers_per_run;
    let Some(slot) = handle.add_viewer(max) else {
        return Err(ApiError(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("run {id} already has {max} open viewer WebSockets, the most the server serves per run; try again later"),
        ));
    };
    drop(handle);
    Ok(upgrade.on_upgrade(move |socket| viewer(s, id, from, socket, slot)))
}

/// The lab bridge's socket (see [`crate::devices::bridge`]).
async fn bridge_ws(
    State(s): State<AppState>,
    Extension(client): Extension<auth::ClientIp>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    upgrade: WebSocketUpgrade,
) -> ApiResult<Response> {
    let id = parse_id(&id)?;
    s.manager.get(id)?;
    let s = s.for_client(client);
    let upgrade = upgrade
        .max_message_size(MAX_BRIDGE_MESSAGE)
        .max_frame_size(MAX_BRIDGE_MESSAGE);
    if let Some(message) = version_mismatch(&q) {
        let frame =
            serde_json::to_string(&spintune::protocol::BridgeServerMessage::Error { message })
                .expect("BridgeServerMessage serializes");
        return Ok(refuse_socket(
            upgrade,
            Message::Text(Utf8Bytes::from(frame)),
        ));
    }
    Ok(upgrade.on_upgrade(move |socket| bridge_socket::serve_socket(s, id, socket)))
}

/// `Some(error message)` unless the WebSocket URL states `protocol=`[`PROTOCOL_VERSION`].
fn version_mismatch(q: &HashMap<String, String>) -> Option<String> {
    match q.get("protocol").map(String::as_str) {
        Some(v) if v == PROTOCOL_VERSION.to_string() => None,
        Some(v) => Some(format!(
            "this server speaks protocol version {PROTOCOL_VERSION}; the client speaks version {v}. Update the client (reload the dashboard, or use the bridge client of this release)."
        )),
        None => Some(format!(
            "this server speaks protocol version {PROTOCOL_VERSION}; the client did not state a version (protocol version 1 clients do not). Connect with `?protocol={PROTOCOL_VERSION}` in the WebSocket URL after updating the client."
        )),
    }
}

/// Accept the upgrade only to send one error frame and close.
fn refuse_socket(upgrade: WebSocketUpgrade, frame: Message) -> Response {
    upgrade.on_upgrade(move |mut socket| async move {
        let _ = socket.send(frame).await;
        let _ = socket.send(Message::Close(None)).await;
    })
}

fn text_of(msg: &ServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).expect("ServerMessage serializes"),
    ))
}

/// The close frame for a receive error that is an inbound message above
/// `max` bytes: code 1009 (Message Too Big) with the sizes; `None` for any
/// other error (the peer went away).
pub(crate) fn too_big_close(e: &axum::Error, max: usize) -> Option<Message> {
    use tungstenite::error::CapacityError;
    let inner = std::error::Error::source(e)?.downcast_ref::<tungstenite::Error>()?;
    match inner {
        tungstenite::Error::Capacity(CapacityError::MessageTooLong { size, .. }) => {
            Some(Message::Close(Some(axum::extract::ws::CloseFrame {
                code: axum::extract::ws::close_code::SIZE,
                reason: Utf8Bytes::from(format!(
                    "message of {size} bytes exceeds the limit of {max} bytes"
                )),
            })))
        }
        _ => None,
    }
}

/// What the viewer's socket loop answers itself (it needs the socket).
enum ViewerRequest {
    History { before: Option<u64>, limit: u32 },
    Scans { iteration: u64 },
}

/// Per-socket state that client messages change.
#[derive(Default)]
struct ViewerState {
    /// Live `Iteration` frames carry the full record.
    scans: bool,
    /// A request for the socket loop.
    request: Option<ViewerRequest>,
}

/// Why a viewer's socket ended.
enum ViewerEnd {
    /// The client went away, closed, or the run was deleted.
    Gone,
    /// A send did not complete within the send timeout.
    SendTimeout(Duration),
    /// Nothing arrived within the pong timeout.
    Idle(Duration),
    /// The viewer sent a message above [`MAX_VIEWER_MESSAGE`]: this close
    /// frame (1009) ends the socket.
    TooBig(Message),
}

/// Send one frame within `timeout`.
async fn send_within(
    socket: &mut WebSocket,
    msg: Message,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    let deadline = tokio::time::Instant::now() + timeout;
    by_deadline(socket.send(msg), deadline, timeout).await
}

/// Run a socket write by `deadline`: a failed write means the viewer is
/// gone, a late one a [`ViewerEnd::SendTimeout`] of `timeout` (what the
/// deadline was set from).
async fn by_deadline(
    write: impl std::future::Future<Output = Result<(), axum::Error>>,
    deadline: tokio::time::Instant,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    match tokio::time::timeout_at(deadline, write).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err(ViewerEnd::Gone),
        Err(_) => Err(ViewerEnd::SendTimeout(timeout)),
    }
}

/// A `History` frame of summaries with seq in `[from.max(end - limit), end)`,
/// `end` = `before` or the newest; with the page's `end` (see
/// [`crate::run::RecentPage::end`]). From the run's ring of recent summaries
/// when it holds the page, else from the store. `None`: the run is gone or
/// the store failed.
async fn history_page(
    state: &AppState,
    id: u64,
    before: Option<u64>,
    limit: u64,
    from: u64,
) -> Option<(Message, u64)> {
    let handle = state.manager.get(id).ok()?;
    if let Some(page) = handle.recent_page(before, limit, from) {
        let records: Vec<&str> = page.records.iter().map(Utf8Bytes::as_str).collect();
        let text = history_frame_text(&records, page.more_before);
        return Some((Message::Text(Utf8Bytes::from(text)), page.end));
    }
    drop(handle);
    let store = state.manager.store().clone();
    let page = tokio::task::spawn_blocking(move || store.summary_page(id, before, limit))
        .await
        .ok()?
        .ok()?;
    let first = page.first_seq.unwrap_or(0);
    let len = page.records.len() as u64;
    let end = page.first_seq.map_or(before.unwrap_or(0), |f| f + len);
    let skip = from.saturating_sub(first).min(len);
    let records = &page.records[skip as usize..];
    // Seq is contiguous from 0: a page starting above 0 has older iterations.
    let more_before = if skip > 0 {
        first + skip > 0
    } else {
        page.more_before
    };
    let text = history_frame_text(records, more_before);
    Some((Message::Text(Utf8Bytes::from(text)), end))
}

/// The answer to `Scans{iteration}`: the stored record's scans.
async fn scans_of(state: &AppState, id: u64, iteration: u64) -> ServerMessage {
    let store = state.manager.store().clone();
    let stored = tokio::task::spawn_blocking(move || store.iteration_json(id, iteration))
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r.map_err(|e| e.to_string()));
    let record = match stored {
        Ok(Some(json)) => serde_json::from_str::<IterationRecord>(&json).map_err(|e| e.to_string()),
        Ok(None) => {
            return ServerMessage::Error {
                message: format!("run {id} has no stored iteration {iteration}"),
            }
        }
        Err(e) => Err(e),
    };
    match record {
        Ok(r) if r.iteration == iteration => ServerMessage::Scans {
            iteration,
            scans: r.scans,
        },
        Ok(r) => ServerMessage::Error {
            message: format!(
                "run {id}: the record stored at position {iteration} is iteration {}",
                r.iteration
            ),
        },
        Err(e) => ServerMessage::Error {
            message: format!("run {id}: cannot read iteration {iteration}: {e}"),
        },
    }
}

/// One viewer's socket: the loop, then a close frame with the reason if the
/// server ends it for a timeout. `_slot` counts the socket against
/// [`MAX_VIEWERS_PER_RUN`] until it ends.
async fn viewer(state: AppState, id: u64, from: u64, mut socket: WebSocket, _slot: ViewerSlot) {
    let end = viewer_loop(&state, id, from, &mut socket).await;
    let reason = match end {
        ViewerEnd::Gone => return,
        ViewerEnd::TooBig(close) => {
            eprintln!("viewer of run {id} disconnected: inbound message too big");
            let _ = tokio::time::timeout(CLOSE_GRACE, socket.send(close)).await;
            return;
        }
        ViewerEnd::SendTimeout(t) => format!(
            "send timed out after {} s: the viewer does not read",
            t.as_secs_f64()
        ),
        ViewerEnd::Idle(t) => format!("nothing received for {} s (no pong)", t.as_secs_f64()),
    };
    eprintln!("viewer of run {id} disconnected: {reason}");
    let close = Message::Close(Some(axum::extract::ws::CloseFrame {
        code: axum::extract::ws::close_code::POLICY,
        reason: Utf8Bytes::from(reason),
    }));
    let _ = tokio::time::timeout(CLOSE_GRACE, socket.send(close)).await;
}

/// Hello and the newest page, then live frames; answers client messages.
async fn viewer_loop(state: &AppState, id: u64, from: u64, socket: &mut WebSocket) -> ViewerEnd {
    let limits = state.manager.options().viewers;
    let timeout = limits.send_timeout;
    let Ok(handle) = state.manager.get(id) else {
        return ViewerEnd::Gone;
    };
    // Subscribe before reading the page so that nothing falls in between;
    // duplicates are dropped by seq below. Only the receiver is held: when
    // the run is deleted the channel closes.
    let mut rx = handle.subscribe();
    let hello = text_of(&ServerMessage::Hello {
        version: PROTOCOL_VERSION,
        run: handle.summary(),
    });
    drop(handle);
    if let Err(e) = send_within(socket, hello, timeout).await {
        return e;
    }
    let page = DEFAULT_HISTORY_PAGE as u64;
    // `next`: the seq of the next live iteration this socket needs.
    let Some((frame, mut next)) = history_page(state, id, None, page, from).await else {
        return ViewerEnd::Gone;
    };
    if let Err(e) = send_within(socket, frame, timeout).await {
        return e;
    }
    let mut authed = false;
    let mut view = ViewerState::default();
    let mut last_heard = tokio::time::Instant::now();
    let mut ping = tokio::time::interval_at(
        tokio::time::Instant::now() + limits.ping_interval,
        limits.ping_interval,
    );
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let result = tokio::select! {
            frame = rx.recv() => match frame {
                Ok(frame) => {
                    live_batch(state, id, socket, &mut rx, frame, &mut next, view.scans, timeout)
                        .await
                }
                Err(RecvError::Lagged(skipped)) => {
                    send_lagged(state, id, socket, skipped, &mut next, timeout).await
                }
                Err(RecvError::Closed) => {
                    let _ = send_within(socket, Message::Close(None), CLOSE_GRACE).await;
                    Err(ViewerEnd::Gone)
                }
            },
            incoming = socket.recv() => {
                let incoming = match incoming {
                    Some(Ok(incoming)) => incoming,
                    Some(Err(e)) => {
                        return too_big_close(&e, MAX_VIEWER_MESSAGE)
                            .map_or(ViewerEnd::Gone, ViewerEnd::TooBig)
                    }
                    None => return ViewerEnd::Gone,
                };
                last_heard = tokio::time::Instant::now();
                let reply = match incoming {
                    Message::Text(text) => {
                        client_message(state, id, text.as_str(), &mut authed, &mut view).await
                    }
                    Message::Binary(_) => Some(ServerMessage::Error {
                        message: "binary frames are not supported; send JSON text".into(),
                    }),
                    Message::Close(_) => return ViewerEnd::Gone,
                    Message::Ping(_) | Message::Pong(_) => None,
                };
                let reply = match (reply, view.request.take()) {
                    (Some(reply), _) => Some(text_of(&reply)),
                    (None, Some(ViewerRequest::History { before, limit })) => {
                        match history_page(state, id, before, limit as u64, 0).await {
                            Some((frame, _)) => Some(frame),
                            None => return ViewerEnd::Gone,
                        }
                    }
                    (None, Some(ViewerRequest::Scans { iteration })) => {
                        Some(text_of(&scans_of(state, id, iteration).await))
                    }
                    (None, None) => None,
                };
                match reply {
                    Some(reply) => send_within(socket, reply, timeout).await,
                    None => Ok(()),
                }
            }
            _ = ping.tick() => {
                if last_heard.elapsed() >= limits.pong_timeout {
                    return ViewerEnd::Idle(limits.pong_timeout);
                }
                send_within(socket, Message::Ping(Bytes::new()), timeout).await
            }
        };
        if let Err(e) = result {
            return e;
        }
    }
}

/// Most live frames written to one viewer between two flushes.
pub const MAX_LIVE_BATCH: usize = 64;

/// Write `first` and whatever else is already queued for this viewer (at
/// most [`MAX_LIVE_BATCH`] frames), then flush once: a viewer that fell
/// behind catches up with one write instead of one per frame, which keeps
/// the fan-out's system calls, and so its latency, down under load. The
/// whole batch must be written within `timeout`. Frames with a seq below
/// `next` (already sent in a page) are skipped; a gap is filled from the
/// store first.
#[allow(clippy::too_many_arguments)]
async fn live_batch(
    state: &AppState,
    id: u64,
    socket: &mut WebSocket,
    rx: &mut tokio::sync::broadcast::Receiver<crate::run::Frame>,
    first: crate::run::Frame,
    next: &mut u64,
    scans: bool,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    use futures_util::SinkExt;
    use tokio::sync::broadcast::error::TryRecvError;
    let deadline = tokio::time::Instant::now() + timeout;
    let mut frame = first;
    let mut lag = None;
    for n in 1.. {
        match frame.seq {
            Some(seq) if seq < *next => {}
            seq => {
                if let Some(seq) = seq {
                    if seq > *next {
                        // Missed something (cannot normally happen): send the gap.
                        let Some((gap, _)) =
                            history_page(state, id, Some(seq), seq - *next, *next).await
                        else {
                            return Err(ViewerEnd::Gone);
                        };
                        by_deadline(socket.feed(gap), deadline, timeout).await?;
                    }
                    *next = seq + 1;
                }
                let text = match (&frame.full, scans) {
                    (Some(full), true) => full.clone(),
                    _ => frame.text,
                };
                by_deadline(socket.feed(Message::Text(text)), deadline, timeout).await?;
            }
        }
        if n >= MAX_LIVE_BATCH {
            break;
        }
        match rx.try_recv() {
            Ok(f) => frame = f,
            Err(TryRecvError::Lagged(skipped)) => {
                lag = Some(skipped);
                break;
            }
            // Empty; or Closed, which the next `recv` reports.
            Err(_) => break,
        }
    }
    by_deadline(socket.flush(), deadline, timeout).await?;
    match lag {
        Some(skipped) => send_lagged(state, id, socket, skipped, next, timeout).await,
        None => Ok(()),
    }
}

/// The viewer lagged by `skipped` live frames: tell it, then send the
/// newest page (it asks for older pages to fill any gap).
async fn send_lagged(
    state: &AppState,
    id: u64,
    socket: &mut WebSocket,
    skipped: u64,
    next: &mut u64,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    let lagged = text_of(&ServerMessage::Lagged { skipped });
    send_within(socket, lagged, timeout).await?;
    match history_page(state, id, None, DEFAULT_HISTORY_PAGE as u64, *next).await {
        Some((frame, end)) => {
            *next = (*next).max(end);
            send_within(socket, frame, timeout).await
        }
        None => Err(ViewerEnd::Gone),
    }
}

async fn client_message(
    state: &AppState,
    id: u64,
    text: &str,
    authed: &mut bool,
    view: &mut ViewerState,
) -> Option<ServerMessage> {
    let msg = match parse_client_message(text) {
        Ok(m) => m,
        Err(e) => {
            return Some(ServerMessage::Error {
                message: e.to_string(),
            })
        }
    };
    Some(match msg {
        ClientMessage::Auth { token } => match state.auth.check(state.client, &token) {
            Ok(()) => {
                *authed = true;
                ServerMessage::AuthOk
            }
            Err(refusal) => ServerMessage::Error {
                message: refusal.message(),
            },
        },
        ClientMessage::Control { command } => {
            if !*authed {
                ServerMessage::Error {
                    message:
                        "control requires the token: send {\"type\":\"auth\",\"token\":\"…\"} first"
                            .into(),
                }
            } else {
                match state.manager.control(id, command).await {
                    Ok(run) => ServerMessage::Status { run },
                    Err(e) => ServerMessage::Error {
                        message: e.to_string(),
                    },
                }
            }
        }
        // Paging and scans are answered by the socket loop (`viewer_loop`).
        ClientMessage::History { before, limit } => {
            let limit = limit.unwrap_or(DEFAULT_HISTORY_PAGE);
            if limit > MAX_HISTORY_PAGE {
                ServerMessage::Error {
                    message: format!(
                        "history limit {limit} exceeds the largest page, {MAX_HISTORY_PAGE} records; ask for older pages with `before`"
                    ),
                }
            } else {
                view.request = Some(ViewerRequest::History { before, limit });
                return None;
            }
        }
        ClientMessage::Scans { iteration } => {
            view.request = Some(ViewerRequest::Scans { iteration });
            return None;
        }
        ClientMessage::Subscribe { scans } => {
            view.scans = scans;
            return None;
        }
    })
}
