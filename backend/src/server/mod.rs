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
//! | GET | `/api/version` | → `{"protocol_version": 2}` |
//! | GET | `/api/runs` | → `[RunSummary]` |
//! | POST 🔒 | `/api/runs` | run config (JSON form of the TOML file, see [`crate::config`]; `{}` = paper default) → 201 `RunSummary` |
//! | GET | `/api/runs/{id}` | → `RunSummary` |
//! | GET | `/api/runs/{id}/config` | → the run's config (`{"simulation": …, "backend": …}`; without a token instrument addresses, channel maps and secrets are `"<redacted>"`) |
//! | GET | `/api/runs/{id}/iterations?from=N&limit=M` | → `[IterationRecord]` with seq ≥ N (default 0), at most M ([`DEFAULT_PAGE`] if not given, ≤ [`MAX_PAGE`]) |
//! | GET | `/api/runs/{id}/export?format=csv\|json` | → the export table (see [`crate::export`]) |
//! | POST 🔒 | `/api/runs/{id}/control` | `ControlCommand` → `RunSummary` (400 invalid, 409 not applicable) |
//! | DELETE 🔒 | `/api/runs/{id}` | → 204 |
//! | GET | `/api/runs/{id}/ws?protocol=2&from=N` | WebSocket, see below |
//! | GET | `/api/runs/{id}/bridge?protocol=2` | WebSocket of the lab bridge (runs with `driver = "bridge"` or `scpi.measure = "bridge"`), see [`crate::devices::bridge`] |
//! | GET | `/*` | the dashboard (Trunk's `dist/`), or a note on how to build it |
//!
//! Both WebSockets require `protocol=2` ([`PROTOCOL_VERSION`]) in the query;
//! a client that omits it (every version-1 client) or states another version
//! gets one `Error` frame naming both versions, and the socket closes.
//!
//! WebSocket (`ServerMessage` / `ClientMessage` JSON text frames): the server
//! sends `Hello`, then `History` (stored records with seq ≥ `from`), then every
//! new `Iteration` live and a `Status` on every status change. A viewer whose
//! buffer ([`crate::run::ManagerOptions::viewer_buffer`] frames) overflows gets
//! `Lagged{skipped}` followed by a `History` refill from the store, so it
//! still sees every iteration exactly once and in order. The client may send
//! `Auth{token}` (→ `AuthOk` or `Error`) and then `Control{command}` (→ `Status`
//! or `Error`). Malformed or unauthorised frames get an `Error`; the socket
//! stays open.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Extension, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::json;
use spintune::protocol::{
    ClientMessage, ControlCommand, ProtocolError, ServerMessage, PROTOCOL_VERSION,
};
use tokio::sync::broadcast::error::RecvError;
use tower_http::services::ServeDir;

pub mod auth;
mod bridge_socket;
pub mod origin;
mod redact;

use crate::config::RunConfig;
use crate::run::{history_frame_text, Manager, RunError};

/// Records per `GET /api/runs/{id}/iterations` page when no `limit` is given.
pub const DEFAULT_PAGE: u64 = 1_000;
/// Largest `limit` of `GET /api/runs/{id}/iterations`.
pub const MAX_PAGE: u64 = 10_000;
/// Largest frame a viewer may send (auth and control messages are tiny), bytes.
pub const MAX_VIEWER_MESSAGE: usize = 64 * 1024;
/// Largest frame a lab bridge may send (a raw scan: e.g. 4 traces of 100,000
/// points as JSON numbers), bytes.
pub const MAX_BRIDGE_MESSAGE: usize = 16 * 1024 * 1024;

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
    let cmd: ControlCommand = parse_strict(text)?;
    validate_control(&cmd)?;
    Ok(cmd)
}

/// Parse a `ClientMessage` from JSON text, naming the offending field on error.
pub fn parse_client_message(text: &str) -> Result<ClientMessage, ProtocolError> {
    let msg: ClientMessage = parse_strict(text)?;
    if let ClientMessage::Control { command } = &msg {
        validate_control(command)?;
    }
    Ok(msg)
}

/// Deserialize `T`, then refuse keys that `T` does not have. (serde ignores
/// `deny_unknown_fields` on unit variants of internally tagged enums, e.g.
/// `{"action":"pause","extra":1}`; comparing with the re-serialized value
/// catches those.)
pub(crate) fn parse_strict<T: serde::de::DeserializeOwned + serde::Serialize>(
    text: &str,
) -> Result<T, ProtocolError> {
    let de = &mut serde_json::Deserializer::from_str(text);
    let raw: serde_json::Value = serde_path_to_error::deserialize(de).map_err(malformed)?;
    let typed: T = serde_path_to_error::deserialize(raw.clone()).map_err(malformed)?;
    let back = serde_json::to_value(&typed).map_err(|e| ProtocolError::malformed("", e))?;
    unknown_keys(&raw, &back, "")?;
    Ok(typed)
}

fn unknown_keys(
    raw: &serde_json::Value,
    known: &serde_json::Value,
    path: &str,
) -> Result<(), ProtocolError> {
    if let (serde_json::Value::Object(r), serde_json::Value::Object(k)) = (raw, known) {
        for (key, v) in r {
            let here = if path.is_empty() {
                key.clone()
            } else {
                format!("{path}.{key}")
            };
            match k.get(key) {
                None => return Err(ProtocolError::UnknownField { field: here }),
                Some(kv) => unknown_keys(v, kv, &here)?,
            }
        }
    }
    Ok(())
}

fn malformed(e: serde_path_to_error::Error<serde_json::Error>) -> ProtocolError {
    ProtocolError::malformed(&e.path().to_string(), e.inner())
}

fn validate_control(cmd: &ControlCommand) -> Result<(), ProtocolError> {
    if let ControlCommand::SetTarget {
        parameter,
        target,
        tolerance,
    } = cmd
    {
        if let Some(t) = target {
            if !t.is_finite() {
                return Err(ProtocolError::NotFinite {
                    field: format!("target of {parameter:?}"),
                    value: *t,
                });
            }
        }
        if let Some(tol) = tolerance {
            tol.validate()
                .map_err(|error| ProtocolError::InvalidTolerance {
                    parameter: parameter.clone(),
                    error,
                })?;
        }
    }
    Ok(())
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
        api.fallback_service(ServeDir::new(dist))
    } else {
        let note = dashboard_missing_note(&dist);
        api.fallback(move || {
            let note = note.clone();
            async move { Html(note) }
        })
    };
    origin::guard(app, access)
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
    s.manager.get(id)?;
    let store = s.manager.store().clone();
    let records = tokio::task::spawn_blocking(move || store.iterations_json(id, from, Some(limit)))
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
    Ok(upgrade.on_upgrade(move |socket| async move {
        if let Err(e) = viewer(s, id, from, socket).await {
            // A viewer going away is normal; nothing else to do.
            let _ = e;
        }
    }))
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

/// Send stored records with seq ≥ `next` as one `History` frame; returns the new `next`.
async fn refill(
    state: &AppState,
    id: u64,
    next: u64,
    socket: &mut WebSocket,
) -> Result<u64, axum::Error> {
    let store = state.manager.store().clone();
    let records = tokio::task::spawn_blocking(move || store.iterations_json(id, next, None))
        .await
        .ok()
        .and_then(Result::ok)
        .unwrap_or_default();
    let n = records.len() as u64;
    socket
        .send(Message::Text(Utf8Bytes::from(history_frame_text(&records))))
        .await?;
    Ok(next + n)
}

/// One viewer's socket: history, then live frames; answers client messages.
async fn viewer(
    state: AppState,
    id: u64,
    from: u64,
    mut socket: WebSocket,
) -> Result<(), axum::Error> {
    let Ok(handle) = state.manager.get(id) else {
        return Ok(());
    };
    // Subscribe before reading the store so that nothing falls in between;
    // duplicates are dropped by seq below.
    let mut rx = handle.subscribe();
    let hello = text_of(&ServerMessage::Hello {
        version: PROTOCOL_VERSION,
        run: handle.summary(),
    });
    drop(handle);
    socket.send(hello).await?;
    // Only the receiver is held: when the run is deleted the channel closes.
    let mut next = refill(&state, id, from, &mut socket).await?;
    let mut authed = false;
    loop {
        tokio::select! {
            frame = rx.recv() => match frame {
                Ok(frame) => {
                    if let Some(seq) = frame.seq {
                        if seq < next {
                            continue;
                        }
                        if seq > next {
                            // Missed something (cannot normally happen): refill.
                            next = refill(&state, id, next, &mut socket).await?;
                            if seq < next {
                                continue;
                            }
                        }
                        next = seq + 1;
                    }
                    socket.send(Message::Text(frame.text)).await?;
                }
                Err(RecvError::Lagged(skipped)) => {
                    socket.send(text_of(&ServerMessage::Lagged { skipped })).await?;
                    next = refill(&state, id, next, &mut socket).await?;
                }
                Err(RecvError::Closed) => {
                    let _ = socket.send(Message::Close(None)).await;
                    return Ok(());
                }
            },
            incoming = socket.recv() => {
                let Some(incoming) = incoming else { return Ok(()) };
                let reply = match incoming? {
                    Message::Text(text) => {
                        client_message(&state, id, text.as_str(), &mut authed).await
                    }
                    Message::Binary(_) => Some(ServerMessage::Error {
                        message: "binary frames are not supported; send JSON text".into(),
                    }),
                    Message::Close(_) => return Ok(()),
                    Message::Ping(_) | Message::Pong(_) => None,
                };
                if let Some(reply) = reply {
                    socket.send(text_of(&reply)).await?;
                }
            }
        }
    }
}

async fn client_message(
    state: &AppState,
    id: u64,
    text: &str,
    authed: &mut bool,
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
    })
}
