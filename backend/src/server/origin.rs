//! Origin and Host checks (an axum middleware, [`check`]).
//!
//! * **Host** (DNS-rebinding defence): a request whose `Host` names this
//!   server by something other than `localhost`, a loopback address, the
//!   bound address (any IP literal when bound to `0.0.0.0`/`::`) or a name
//!   given with `--allow-host` is refused with 421 and a body naming the
//!   flag. A request without `Host` (HTTP/1.0 scripts) passes: a browser
//!   always sends one.
//! * **Origin** (cross-site requests): a WebSocket upgrade (viewer and
//!   bridge sockets) or a state-changing request (any method but
//!   GET/HEAD/OPTIONS) that carries an `Origin` header must come from the
//!   served origin — the origin's host and port equal the request's `Host`
//!   (a `Host` without a port matches the scheme's default port) — or from an
//!   origin given with `--allow-origin`; otherwise 403 naming the flag.
//!   Clients that send no `Origin` (scripts, the Python bridge, curl) pass;
//!   browsers always send it on WebSocket upgrades and cross-site POSTs.

use std::collections::BTreeSet;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::error::ApiError;

/// A malformed `--allow-origin` or `--allow-host` value, named with its flag.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AccessError {
    /// An origin that is not `scheme://host[:port]`.
    #[error("--allow-origin {0:?}: expected scheme://host[:port], e.g. https://lab.example:8443")]
    Origin(String),
    /// A host that is empty or holds a `/`.
    #[error("--allow-host {0:?}: expected a host name such as lab.example")]
    Host(String),
}

/// Which Hosts and Origins the server accepts besides its own.
#[derive(Debug, Clone, Default)]
pub struct Access {
    /// The bound address (`None`: only loopback names and the allowed hosts).
    pub bind: Option<SocketAddr>,
    /// Extra host names (`--allow-host`), lower case, without port.
    pub hosts: BTreeSet<String>,
    /// Extra origins (`--allow-origin`), normalized (`scheme://host[:port]`, lower case).
    pub origins: BTreeSet<String>,
}

impl Access {
    /// From the bound address and the `--allow-host` / `--allow-origin` lists.
    /// An origin that is not `scheme://host[:port]` is an error naming it.
    pub fn new(
        bind: Option<SocketAddr>,
        hosts: &[String],
        origins: &[String],
    ) -> Result<Self, AccessError> {
        let mut o = BTreeSet::new();
        for origin in origins {
            if origin.trim() == "null" {
                o.insert("null".to_string());
                continue;
            }
            let parsed = parse_origin(origin).ok_or_else(|| AccessError::Origin(origin.clone()))?;
            o.insert(parsed.normalized());
        }
        let mut h = BTreeSet::new();
        for host in hosts {
            let host = host.trim().trim_end_matches('.').to_ascii_lowercase();
            if host.is_empty() || host.contains('/') {
                return Err(AccessError::Host(host));
            }
            h.insert(host);
        }
        Ok(Self {
            bind,
            hosts: h,
            origins: o,
        })
    }

    /// Whether `host` (no port; IPv6 without brackets) names this server.
    pub fn host_allowed(&self, host: &str) -> bool {
        let host = host.trim_end_matches('.').to_ascii_lowercase();
        if host == "localhost" || host.ends_with(".localhost") || self.hosts.contains(&host) {
            return true;
        }
        match host.parse::<IpAddr>() {
            Ok(ip) => {
                // An IP literal cannot be rebound by DNS.
                ip.is_loopback()
                    || self
                        .bind
                        .is_some_and(|b| b.ip().is_unspecified() || b.ip() == ip)
            }
            Err(_) => false,
        }
    }

    /// Whether a request with `Origin: origin` and `Host: host` may act.
    pub fn origin_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        let origin = origin.trim();
        if origin == "null" {
            return self.origins.contains("null");
        }
        let Some(o) = parse_origin(origin) else {
            return false;
        };
        if self.origins.contains(&o.normalized()) {
            return true;
        }
        let Some((h, port)) = host.and_then(split_host) else {
            return false;
        };
        o.host == h.trim_end_matches('.').to_ascii_lowercase()
            && o.port == port.unwrap_or_else(|| default_port(&o.scheme))
    }
}

struct Origin {
    scheme: String,
    host: String,
    port: u16,
    explicit_port: bool,
}

impl Origin {
    fn normalized(&self) -> String {
        let host = if self.host.contains(':') {
            format!("[{}]", self.host)
        } else {
            self.host.clone()
        };
        if self.explicit_port && self.port != default_port(&self.scheme) {
            format!("{}://{host}:{}", self.scheme, self.port)
        } else {
            format!("{}://{host}", self.scheme)
        }
    }
}

fn default_port(scheme: &str) -> u16 {
    match scheme {
        "https" | "wss" => 443,
        _ => 80,
    }
}

fn parse_origin(s: &str) -> Option<Origin> {
    let s = s.trim().trim_end_matches('/');
    let (scheme, rest) = s.split_once("://")?;
    let scheme = scheme.to_ascii_lowercase();
    if !matches!(scheme.as_str(), "http" | "https" | "ws" | "wss") || rest.contains('/') {
        return None;
    }
    let (host, port) = split_host(rest)?;
    Some(Origin {
        port: port.unwrap_or_else(|| default_port(&scheme)),
        explicit_port: port.is_some(),
        scheme,
        host: host.trim_end_matches('.').to_ascii_lowercase(),
    })
}

/// `host[:port]` or `[v6][:port]` → (host without brackets, port).
fn split_host(s: &str) -> Option<(&str, Option<u16>)> {
    if s.is_empty() || s.contains('@') {
        return None;
    }
    if let Some(rest) = s.strip_prefix('[') {
        let (h, after) = rest.split_once(']')?;
        let port = match after.strip_prefix(':') {
            Some(p) => Some(p.parse().ok()?),
            None if after.is_empty() => None,
            None => return None,
        };
        return Some((h, port));
    }
    match s.rsplit_once(':') {
        Some((h, p)) if !h.contains(':') => Some((h, Some(p.parse().ok()?))),
        Some(_) => None,
        None => Some((s, None)),
    }
}

/// Wrap `app` in the client-address recorder and the Host/Origin checks.
pub fn guard(app: axum::Router, access: Arc<Access>) -> axum::Router {
    app.layer(axum::middleware::from_fn_with_state(access, check))
        .layer(axum::middleware::from_fn(super::auth::client_ip))
}

fn refuse(status: StatusCode, message: String) -> Response {
    ApiError(status, message).into_response()
}

/// The middleware: Host on every request, Origin on upgrades and state changes.
pub async fn check(State(access): State<Arc<Access>>, req: Request, next: Next) -> Response {
    let host = req
        .headers()
        .get(header::HOST)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string)
        .or_else(|| req.uri().authority().map(|a| a.to_string()));
    if let Some(h) = &host {
        let name = split_host(h).map(|(n, _)| n);
        if !name.is_some_and(|n| access.host_allowed(n)) {
            let shown = name.unwrap_or(h);
            return refuse(
                StatusCode::MISDIRECTED_REQUEST,
                format!(
                    "this server does not answer to the host name {shown:?} (DNS-rebinding defence); if that is how you reach it, start it with `--allow-host {shown}`"
                ),
            );
        }
    }
    let upgrade = req
        .headers()
        .get(header::UPGRADE)
        .is_some_and(|v| v.as_bytes().eq_ignore_ascii_case(b"websocket"));
    let changes = !matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS);
    if upgrade || changes {
        if let Some(origin) = req.headers().get(header::ORIGIN) {
            let origin = origin.to_str().unwrap_or("<not text>");
            if !access.origin_allowed(origin, host.as_deref()) {
                let what = if upgrade {
                    "WebSocket connections"
                } else {
                    "state-changing requests"
                };
                return refuse(
                    StatusCode::FORBIDDEN,
                    format!(
                        "{what} from the web origin {origin:?} are refused (not the origin this server is reached at); to allow that page, start the server with `--allow-origin {origin}`"
                    ),
                );
            }
        }
    }
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn access(bind: &str) -> Access {
        Access::new(
            Some(bind.parse().unwrap()),
            &["lab.example".into()],
            &["https://dash.example".into()],
        )
        .unwrap()
    }

    #[test]
    fn hosts_allowed_are_loopback_bind_and_listed_names() {
        let a = access("127.0.0.1:8080");
        for ok in [
            "localhost",
            "127.0.0.1",
            "::1",
            "LAB.example",
            "lab.example.",
        ] {
            assert!(a.host_allowed(ok), "{ok}");
        }
        for bad in ["evil.example", "10.0.0.5", "lab.example.evil"] {
            assert!(!a.host_allowed(bad), "{bad}");
        }
        // Bound to every interface: IP literals (not rebindable) are fine, names are not.
        let any = access("0.0.0.0:8080");
        assert!(any.host_allowed("10.0.0.5"));
        assert!(!any.host_allowed("evil.example"));
    }

    #[test]
    fn origin_must_match_host_or_the_allow_list() {
        let a = access("127.0.0.1:8080");
        assert!(a.origin_allowed("http://127.0.0.1:8080", Some("127.0.0.1:8080")));
        assert!(a.origin_allowed("https://lab.example", Some("lab.example")));
        assert!(a.origin_allowed("http://LAB.example:80", Some("lab.example")));
        assert!(a.origin_allowed("https://dash.example/", Some("127.0.0.1:8080")));
        assert!(!a.origin_allowed("https://evil.example", Some("127.0.0.1:8080")));
        assert!(!a.origin_allowed("http://127.0.0.1:9999", Some("127.0.0.1:8080")));
        assert!(!a.origin_allowed("null", Some("127.0.0.1:8080")));
        assert!(!a.origin_allowed("garbage", Some("127.0.0.1:8080")));
        assert!(!a.origin_allowed("http://127.0.0.1:8080", None));
        assert!(a.origin_allowed("http://[::1]:8080", Some("[::1]:8080")));
    }

    #[test]
    fn a_malformed_allow_origin_is_refused_naming_it() {
        let e = Access::new(None, &[], &["lab.example".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("--allow-origin \"lab.example\""), "{e}");
    }
}
