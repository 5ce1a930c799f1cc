//! Talking to the backend: base URL, REST (fetch) and WebSocket URLs.

use serde::de::DeserializeOwned;
use spintune::protocol::PROTOCOL_VERSION;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::JsFuture;

/// Where the backend lives: the page's own origin, or `?server=http://host:port`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ApiBase {
    /// e.g. `http://127.0.0.1:8080` (no trailing slash).
    pub http: String,
}

impl ApiBase {
    /// From the page location (`?server=` overrides the origin).
    pub fn from_location() -> Self {
        let loc = leptos::prelude::location();
        let search = loc.search().unwrap_or_default();
        let server = search
            .trim_start_matches('?')
            .split('&')
            .find_map(|kv| kv.strip_prefix("server="))
            .and_then(|v| js_sys::decode_uri_component(v).ok())
            .and_then(|v| v.as_string());
        let http = server.unwrap_or_else(|| {
            loc.origin()
                .unwrap_or_else(|_| "http://127.0.0.1:8080".into())
        });
        Self::new(&http)
    }

    /// From an explicit base URL.
    pub fn new(http: &str) -> Self {
        Self {
            http: http.trim_end_matches('/').to_string(),
        }
    }

    /// REST URL of a path such as `/api/runs`.
    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.http, path)
    }

    /// WebSocket URL of a path (http → ws, https → wss).
    pub fn ws_url(&self, path: &str) -> String {
        let base = if let Some(rest) = self.http.strip_prefix("https://") {
            format!("wss://{rest}")
        } else if let Some(rest) = self.http.strip_prefix("http://") {
            format!("ws://{rest}")
        } else {
            self.http.clone()
        };
        format!("{base}{path}")
    }

    /// WebSocket URL of a run's stream, resuming at iteration `from`. States
    /// the protocol version this page speaks (`protocol=`), as the server
    /// requires since protocol version 2.
    pub fn run_ws_url(&self, run: u64, from: u64) -> String {
        self.ws_url(&format!(
            "/api/runs/{run}/ws?protocol={PROTOCOL_VERSION}&from={from}"
        ))
    }
}

fn js_err(e: wasm_bindgen::JsValue) -> String {
    e.as_string()
        .or_else(|| {
            js_sys::Reflect::get(&e, &"message".into())
                .ok()
                .and_then(|m| m.as_string())
        })
        .unwrap_or_else(|| format!("{e:?}"))
}

/// Why a request to the server failed: the one error type of the
/// dashboard's HTTP boundary.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ApiError {
    /// No answer (network, CORS, server down).
    #[error("cannot reach the server: {0}")]
    Unreachable(String),
    /// An answer with an error status; `detail` is the body when it is short
    /// text (empty otherwise).
    #[error("HTTP {status}{}", if detail.is_empty() { String::new() } else { format!(": {detail}") })]
    Status {
        /// HTTP status.
        status: u16,
        /// The body (e.g. `{"error":"no run with id 99"}`), or empty.
        detail: String,
    },
    /// A 2xx answer that is not what was asked for.
    #[error("unexpected reply: {0}")]
    Reply(String),
}

impl ApiError {
    /// Whether the server said it has no such thing (404).
    pub fn is_not_found(&self) -> bool {
        matches!(self, ApiError::Status { status: 404, .. })
    }

    /// The server's words: the `error` field of a JSON body
    /// (`{"error":"no run with id 99"}` → `no run with id 99`), else the
    /// whole message.
    pub fn detail(&self) -> String {
        if let ApiError::Status { detail, .. } = self {
            if let Some(e) = serde_json::from_str::<serde_json::Value>(detail)
                .ok()
                .and_then(|v| v.get("error")?.as_str().map(str::to_string))
            {
                return e;
            }
        }
        self.to_string()
    }
}

/// `GET url` and decode the JSON body.
pub async fn get_json<T: DeserializeOwned>(url: &str) -> Result<T, ApiError> {
    let window = leptos::prelude::window();
    let unreachable = |e| ApiError::Unreachable(js_err(e));
    let resp = JsFuture::from(window.fetch_with_str(url))
        .await
        .map_err(unreachable)?;
    let resp: web_sys::Response = resp.dyn_into().map_err(unreachable)?;
    let status = resp.status();
    let text = JsFuture::from(resp.text().map_err(unreachable)?)
        .await
        .map_err(unreachable)?
        .as_string()
        .unwrap_or_default();
    if !(200..300).contains(&status) {
        let detail = text.trim();
        let detail = if detail.starts_with('<') || detail.len() > 200 {
            String::new()
        } else {
            detail.to_string()
        };
        return Err(ApiError::Status { status, detail });
    }
    serde_json::from_str(&text).map_err(|e| ApiError::Reply(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn api_errors_say_what_the_server_said() {
        let e = ApiError::Status {
            status: 404,
            detail: r#"{"error":"no run with id 99"}"#.into(),
        };
        assert!(e.is_not_found());
        assert_eq!(e.detail(), "no run with id 99");
        assert_eq!(e.to_string(), r#"HTTP 404: {"error":"no run with id 99"}"#);
        let e = ApiError::Status {
            status: 503,
            detail: String::new(),
        };
        assert!(!e.is_not_found());
        assert_eq!(e.to_string(), "HTTP 503");
        assert_eq!(
            ApiError::Unreachable("x".into()).to_string(),
            "cannot reach the server: x"
        );
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn ws_urls() {
        let b = ApiBase::new("http://127.0.0.1:8080/");
        assert_eq!(b.url("/api/runs"), "http://127.0.0.1:8080/api/runs");
        assert_eq!(
            b.run_ws_url(3, 17),
            "ws://127.0.0.1:8080/api/runs/3/ws?protocol=4&from=17"
        );
        assert_eq!(PROTOCOL_VERSION, 4);
        assert_eq!(
            ApiBase::new("https://lab.example").ws_url("/x"),
            "wss://lab.example/x"
        );
    }
}
