//! The one raw HTTP/1.1 client of the tests: requests written byte for byte
//! (any header, any source address, half a body) and answers read until the
//! server closes, bounded in time and in size.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;

use super::STEP;

/// Most bytes read from one connection; more is a test failure.
pub const MAX_ANSWER_BYTES: usize = 16 * 1024 * 1024;

/// A TCP connection to `addr`, from the source address `from` if given
/// (e.g. `127.0.0.2`, to be another client for per-address limits).
pub async fn connect_from(addr: SocketAddr, from: Option<IpAddr>) -> TcpStream {
    match from {
        Some(ip) => {
            let sock = tokio::net::TcpSocket::new_v4().unwrap();
            sock.bind(SocketAddr::new(ip, 0)).unwrap();
            sock.connect(addr).await.unwrap()
        }
        None => TcpStream::connect(addr).await.unwrap(),
    }
}

/// Read until the peer closes (EOF, reset or any read error), at most
/// [`MAX_ANSWER_BYTES`]; `None` if it is still open after `within`.
pub async fn read_until_closed<S: AsyncRead + Unpin>(
    s: &mut S,
    within: Duration,
) -> Option<Vec<u8>> {
    tokio::time::timeout(within, async {
        let mut all = Vec::new();
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            match s.read(&mut buf).await {
                Ok(0) | Err(_) => return all,
                Ok(n) => {
                    all.extend_from_slice(&buf[..n]);
                    assert!(
                        all.len() <= MAX_ANSWER_BYTES,
                        "the answer exceeds {MAX_ANSWER_BYTES} bytes"
                    );
                }
            }
        }
    })
    .await
    .ok()
}

/// Write `request` as is, then read the answer until the peer closes
/// ([`read_until_closed`]).
pub async fn exchange<S: AsyncRead + AsyncWrite + Unpin>(
    s: &mut S,
    request: &[u8],
    within: Duration,
) -> Option<Vec<u8>> {
    s.write_all(request).await.unwrap();
    read_until_closed(s, within).await
}

/// Status and body of a complete answer (a chunked body de-chunked).
pub fn status_and_body(answer: &[u8]) -> (u16, String) {
    let text = String::from_utf8_lossy(answer);
    let status: u16 = text
        .get(9..12)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP answer: {text:?}"));
    let (head, rest) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let body = if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        dechunk(rest)
    } else {
        rest.to_string()
    };
    (status, body)
}

fn dechunk(mut s: &str) -> String {
    let mut out = String::new();
    while let Some((len, rest)) = s.split_once("\r\n") {
        let n = usize::from_str_radix(len.trim(), 16).unwrap_or(0);
        if n == 0 {
            break;
        }
        out.push_str(&rest[..n]);
        s = &rest[n + 2..];
    }
    out
}

/// One request on a connection of its own, from `from` if given: `head` is
/// the request line and headers (no blank line); `Connection: close` and
/// `Content-Length` are added. Returns (status, body) within [`STEP`].
pub async fn raw_request(
    addr: SocketAddr,
    from: Option<IpAddr>,
    head: &str,
    body: &str,
) -> (u16, String) {
    let request = format!(
        "{head}\r\nConnection: close\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    tokio::time::timeout(STEP, async {
        let mut s = connect_from(addr, from).await;
        let answer = exchange(&mut s, request.as_bytes(), STEP)
            .await
            .expect("the server did not close the connection");
        status_and_body(&answer)
    })
    .await
    .expect("HTTP request timed out")
}
