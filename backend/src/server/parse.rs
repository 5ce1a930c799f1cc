//! Strict parsing of what arrives: control commands and viewer frames (the
//! core's strict JSON, [`spintune::strict_json`], plus the core's form check
//! of a command), the Content-Type of JSON bodies, run ids and query numbers.

use std::collections::HashMap;

use axum::http::{header, HeaderMap, StatusCode};
use spintune::protocol::{ClientMessage, ControlCommand, ProtocolError};

use super::error::{ApiError, ApiResult};

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
pub(super) fn parse_strict<T: serde::de::DeserializeOwned + serde::Serialize>(
    text: &str,
) -> Result<T, ProtocolError> {
    spintune::strict_json::parse_strict(text)
}

/// The JSON bodies (`POST /api/runs`, `POST /api/runs/{id}/control`) must be
/// sent as `Content-Type: application/json` (parameters such as
/// `; charset=utf-8` allowed); another type is refused with 415. A request
/// without a Content-Type is read as JSON (scripts; a browser always sends
/// one, so a cross-site form post — `text/plain` or a form type — is
/// refused).
pub(super) fn require_json(headers: &HeaderMap) -> ApiResult<()> {
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

pub(super) fn parse_u64(q: &HashMap<String, String>, key: &str) -> ApiResult<Option<u64>> {
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

pub(super) fn parse_id(id: &str) -> ApiResult<u64> {
    id.parse::<u64>().map_err(|_| {
        ApiError(
            StatusCode::BAD_REQUEST,
            format!("run id must be a non-negative integer, got {id:?}"),
        )
    })
}
