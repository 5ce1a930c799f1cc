//! The accept loop: HTTP/1.1 (with WebSocket upgrades) served by hyper on
//! each accepted TCP connection, with the connection limits `axum::serve`
//! does not offer (ARCHITECTURE.md, invariant 8):
//!
//! * [`HEADER_READ_TIMEOUT`]: a connection that does not complete a
//!   request's headers in this time is closed — also an idle keep-alive
//!   connection between requests (hyper's `header_read_timeout`, which runs
//!   whenever the connection waits for a request head).
//! * [`BODY_READ_TIMEOUT`]: a request whose body does not arrive in full
//!   within this time after its headers is answered 408 and the connection
//!   closed (hyper has no body timeout of its own); bodies above
//!   [`MAX_BODY_BYTES`] are answered 413.
//! * [`MAX_CONNECTIONS_PER_IP`]: concurrent connections (HTTP and WebSocket)
//!   from one client IP address; a connection beyond it is closed at once,
//!   before anything is read from it.
//!
//! Every accepted socket gets `TCP_NODELAY` (small frames at high rates must
//! not wait for Nagle's algorithm).
//!
//! With a [`crate::server::tls::TlsAcceptor`] every connection is TLS
//! (`--tls-cert/--tls-key`): the handshake must complete within the same
//! [`HEADER_READ_TIMEOUT`], and a client that does not speak TLS is closed.

use std::collections::HashMap;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpListener;

use super::tls::TlsAcceptor;
use crate::run::ViewerLimits;

/// A connection that does not complete its request headers in this time is
/// closed.
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);

/// A request body that has not arrived in full this long after the
/// request's headers is answered 408 (Request Timeout) and the connection
/// closed: a body that never completes cannot hold a connection (and a
/// slot of [`MAX_CONNECTIONS_PER_IP`]) for longer.
pub const BODY_READ_TIMEOUT: Duration = Duration::from_secs(10);

/// Largest request body, bytes (axum's default body limit); larger → 413.
pub const MAX_BODY_BYTES: usize = 2 * 1024 * 1024;

/// Concurrent connections per client IP address; more are closed at once.
pub const MAX_CONNECTIONS_PER_IP: usize = 64;

/// Connection limits of [`serve`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// See [`HEADER_READ_TIMEOUT`].
    pub header_read_timeout: Duration,
    /// See [`BODY_READ_TIMEOUT`].
    pub body_read_timeout: Duration,
    /// See [`MAX_CONNECTIONS_PER_IP`].
    pub max_connections_per_ip: usize,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self {
            header_read_timeout: HEADER_READ_TIMEOUT,
            body_read_timeout: BODY_READ_TIMEOUT,
            max_connections_per_ip: MAX_CONNECTIONS_PER_IP,
        }
    }
}

/// `spintune serve` flags of the connection and viewer limits (defaults: the
/// constants).
#[derive(Debug, Clone, clap::Args)]
pub struct LimitArgs {
    /// Close a connection that does not complete its request headers in this time, ms.
    #[arg(long, default_value_t = HEADER_READ_TIMEOUT.as_millis() as u64)]
    pub header_read_timeout_ms: u64,
    /// Answer 408 and close a connection whose request body has not arrived in full this long after its headers, ms.
    #[arg(long, default_value_t = BODY_READ_TIMEOUT.as_millis() as u64)]
    pub body_read_timeout_ms: u64,
    /// Concurrent connections per client IP address (more are closed at once).
    #[arg(long, default_value_t = MAX_CONNECTIONS_PER_IP)]
    pub max_connections_per_ip: usize,
    /// Disconnect a viewer whose frame is not sent within this time, ms.
    #[arg(long, default_value_t = super::VIEWER_SEND_TIMEOUT.as_millis() as u64)]
    pub viewer_send_timeout_ms: u64,
    /// Ping every viewer this often, ms.
    #[arg(long, default_value_t = super::VIEWER_PING_INTERVAL.as_millis() as u64)]
    pub viewer_ping_interval_ms: u64,
    /// Disconnect a viewer from which nothing arrived for this long, ms.
    #[arg(long, default_value_t = super::VIEWER_PONG_TIMEOUT.as_millis() as u64)]
    pub viewer_pong_timeout_ms: u64,
    /// Open viewer WebSockets per run (one more gets 503).
    #[arg(long, default_value_t = super::MAX_VIEWERS_PER_RUN)]
    pub max_viewers_per_run: usize,
}

impl Default for LimitArgs {
    fn default() -> Self {
        let v = ViewerLimits::default();
        let c = ConnectionLimits::default();
        Self {
            header_read_timeout_ms: c.header_read_timeout.as_millis() as u64,
            body_read_timeout_ms: c.body_read_timeout.as_millis() as u64,
            max_connections_per_ip: c.max_connections_per_ip,
            viewer_send_timeout_ms: v.send_timeout.as_millis() as u64,
            viewer_ping_interval_ms: v.ping_interval.as_millis() as u64,
            viewer_pong_timeout_ms: v.pong_timeout.as_millis() as u64,
            max_viewers_per_run: v.max_viewers_per_run,
        }
    }
}

impl LimitArgs {
    /// The connection limits (zero durations and counts become the smallest
    /// useful value: 1 ms, 1 connection).
    pub fn connection_limits(&self) -> ConnectionLimits {
        ConnectionLimits {
            header_read_timeout: Duration::from_millis(self.header_read_timeout_ms.max(1)),
            body_read_timeout: Duration::from_millis(self.body_read_timeout_ms.max(1)),
            max_connections_per_ip: self.max_connections_per_ip.max(1),
        }
    }

    /// The viewer limits (zero durations become 1 ms).
    pub fn viewer_limits(&self) -> ViewerLimits {
        let ms = |v: u64| Duration::from_millis(v.max(1));
        ViewerLimits {
            send_timeout: ms(self.viewer_send_timeout_ms),
            ping_interval: ms(self.viewer_ping_interval_ms),
            pong_timeout: ms(self.viewer_pong_timeout_ms),
            max_viewers_per_run: self.max_viewers_per_run,
        }
    }
}

/// Open connections per client IP.
#[derive(Default)]
struct PerIp(Mutex<HashMap<IpAddr, usize>>);

/// One counted connection; uncounted on drop.
struct IpSlot(Arc<PerIp>, IpAddr);

impl PerIp {
    fn acquire(self: &Arc<Self>, ip: IpAddr, max: usize) -> Option<IpSlot> {
        let mut map = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let n = map.entry(ip).or_insert(0);
        if *n >= max {
            return None;
        }
        *n += 1;
        Some(IpSlot(self.clone(), ip))
    }
}

impl Drop for IpSlot {
    fn drop(&mut self) {
        let mut map = self.0 .0.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = map.get_mut(&self.1) {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.1);
            }
        }
    }
}

/// A connection's socket with its per-IP slot: the slot is released when the
/// socket is dropped, which for a WebSocket is when the upgraded connection
/// ends (hyper hands the same IO object to the upgrade).
struct Counted<T> {
    io: T,
    _slot: IpSlot,
}

impl<T: AsyncRead + Unpin> AsyncRead for Counted<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Counted<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.io).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

/// Serve `app` on `listener` until the task is dropped, over TLS when `tls`
/// is given. Errors of single connections end those connections only; an
/// accept error (e.g. out of file descriptors) is retried after a short
/// pause.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnectionLimits,
    tls: Option<TlsAcceptor>,
) {
    let per_ip = Arc::new(PerIp::default());
    let app = app.layer(axum::middleware::from_fn_with_state(
        limits.body_read_timeout,
        read_body_by_deadline,
    ));
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                eprintln!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Some(slot) = per_ip.acquire(peer.ip(), limits.max_connections_per_ip) else {
            // Closed before anything is read.
            drop(tcp);
            continue;
        };
        let _ = tcp.set_nodelay(true);
        // The peer address for handlers and middleware (`ConnectInfo`), as
        // `into_make_service_with_connect_info` would provide it.
        let service = TowerToHyperService::new(
            app.clone()
                .layer(axum::Extension(ConnectInfo::<std::net::SocketAddr>(peer))),
        );
        let io = Counted {
            io: tcp,
            _slot: slot,
        };
        let tls = tls.clone();
        tokio::spawn(async move {
            match tls {
                None => serve_connection(io, service, limits).await,
                Some(acceptor) => {
                    let handshake =
                        tokio::time::timeout(limits.header_read_timeout, acceptor.accept(io));
                    // A failed or slow handshake (e.g. plain HTTP) closes the connection.
                    if let Ok(Ok(tls_io)) = handshake.await {
                        serve_connection(tls_io, service, limits).await;
                    }
                }
            }
        });
    }
}

/// Read the request's whole body (at most [`MAX_BODY_BYTES`]) within
/// `timeout` before the handlers see it: 408 and `Connection: close` if it
/// does not arrive in time, 413 if it is too large.
async fn read_body_by_deadline(
    State(timeout): State<Duration>,
    request: Request,
    next: Next,
) -> Response {
    let (parts, body) = request.into_parts();
    let error = |status: StatusCode, message: String| {
        let mut resp =
            (status, axum::Json(serde_json::json!({ "error": message }))).into_response();
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
        resp
    };
    let bytes =
        match tokio::time::timeout(timeout, axum::body::to_bytes(body, MAX_BODY_BYTES)).await {
            Ok(Ok(bytes)) => bytes,
            Err(_) => {
                return error(
                    StatusCode::REQUEST_TIMEOUT,
                    format!(
                        "the request body did not arrive within {} s of the headers",
                        timeout.as_secs_f64()
                    ),
                )
            }
            Ok(Err(e)) => {
                let e = e.into_inner();
                let too_large = e.is::<http_body_util::LengthLimitError>();
                return if too_large {
                    error(
                        StatusCode::PAYLOAD_TOO_LARGE,
                        format!("the request body exceeds {MAX_BODY_BYTES} bytes"),
                    )
                } else {
                    error(
                        StatusCode::BAD_REQUEST,
                        format!("cannot read the request body: {e}"),
                    )
                };
            }
        };
    next.run(Request::from_parts(parts, Body::from(bytes)))
        .await
}

/// HTTP/1.1 with upgrades on one connection, with the header-read timeout.
async fn serve_connection<I>(io: I, service: TowerToHyperService<Router>, limits: ConnectionLimits)
where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_read_timeout);
    let conn = builder
        .serve_connection(TokioIo::new(io), service)
        .with_upgrades();
    // A client going away or timing out is normal.
    let _ = conn.await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn per_ip_slots_are_counted_and_released() {
        let per_ip = Arc::new(PerIp::default());
        let ip: IpAddr = "127.0.0.1".parse().unwrap();
        let other: IpAddr = "10.0.0.1".parse().unwrap();
        let a = per_ip.acquire(ip, 2).unwrap();
        let _b = per_ip.acquire(ip, 2).unwrap();
        assert!(per_ip.acquire(ip, 2).is_none());
        assert!(per_ip.acquire(other, 2).is_some());
        drop(a);
        assert!(per_ip.acquire(ip, 2).is_some());
    }
}
