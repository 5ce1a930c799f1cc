//! The REST handlers (`/api/version`, `/api/runs…`; the table is in
//! [`super`]) and the token check of a request.

use std::collections::HashMap;

use axum::body::Bytes;
use axum::extract::{Extension, Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;
use spintune::protocol::PROTOCOL_VERSION;

use super::error::{ApiError, ApiResult};
use super::parse::{parse_control, parse_id, parse_u64, require_json};
use super::{auth, redact, AppState, DEFAULT_PAGE, MAX_PAGE};
use crate::config::RunConfig;
use crate::run::RunError;

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

pub(super) async fn version() -> impl IntoResponse {
    Json(json!({ "protocol_version": PROTOCOL_VERSION }))
}

pub(super) async fn list_runs(State(s): State<AppState>) -> impl IntoResponse {
    Json(s.manager.list())
}

pub(super) async fn create_run(
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

pub(super) async fn get_run(
    State(s): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id(&id)?;
    Ok(Json(s.manager.get(id)?.summary()))
}

pub(super) async fn get_config(
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

pub(super) async fn iterations(
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

pub(super) async fn export(
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
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    let ctype = match format {
        crate::export::Format::Csv => "text/csv; charset=utf-8",
        crate::export::Format::Json => "application/json",
    };
    Ok(([(header::CONTENT_TYPE, ctype)], out).into_response())
}

pub(super) async fn control(
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

pub(super) async fn delete_run(
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
