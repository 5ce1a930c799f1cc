//! The control token and failed-authentication throttling.
//!
//! Every token check (REST `Authorization: Bearer`, `Auth` frames on the
//! viewer and bridge sockets) goes through [`Auth::check`], keyed by the
//! client's IP address:
//!
//! * addresses are IPv4 addresses or IPv6 /64 prefixes; behind a reverse
//!   proxy every client has the proxy's address (one blocked guesser then
//!   blocks all: keep the proxy's own rate limits in front);
//! * the first [`FREE_FAILURES`] wrong tokens from one address answer as
//!   usual (403 / `Error`);
//! * each further failure blocks the address for [`BASE_BLOCK`] · 2^(n−1)
//!   (n = failures beyond the free ones), at most [`MAX_BLOCK`]; while blocked
//!   every attempt answers 429 (`Error` on a socket) at once, **without
//!   comparing the token** (a right token is refused too);
//! * a right token clears the address's record; a record idle for
//!   [`FORGET_AFTER`] is forgotten.
//!
//! Memory is bounded by construction: at most [`MAX_TRACKED_CLIENTS`]
//! addresses are tracked (plus one shared overflow record); when the table is full (after dropping forgotten
//! records) the remaining addresses share one overflow record, so a flood of
//! addresses is throttled together rather than forgotten.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, Request};
use axum::middleware::Next;
use axum::response::Response;

/// Wrong tokens per address answered normally before throttling starts.
pub const FREE_FAILURES: u32 = 10;
/// First block after the free failures.
pub const BASE_BLOCK: Duration = Duration::from_secs(5);
/// Longest block.
pub const MAX_BLOCK: Duration = Duration::from_secs(300);
/// A record without failures for this long is forgotten.
pub const FORGET_AFTER: Duration = Duration::from_secs(900);
/// Addresses tracked individually (about 64 bytes each).
pub const MAX_TRACKED_CLIENTS: usize = 4096;

/// The client's address, put into every request's extensions by [`client_ip`]
/// (`None` when the listener does not provide connection info).
#[derive(Debug, Clone, Copy, Default)]
pub struct ClientIp(pub Option<IpAddr>);

/// Middleware: record the peer address as [`ClientIp`].
pub async fn client_ip(mut req: Request, next: Next) -> Response {
    let ip = req
        .extensions()
        .get::<ConnectInfo<SocketAddr>>()
        .map(|c| c.0.ip());
    req.extensions_mut().insert(ClientIp(ip));
    next.run(req).await
}

/// Why a token was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The token is wrong.
    Wrong,
    /// Too many failures from this address: retry after this long.
    Throttled(Duration),
}

impl Refusal {
    /// The message told to the client.
    pub fn message(&self) -> String {
        match self {
            Refusal::Wrong => "invalid control token".into(),
            Refusal::Throttled(d) => format!(
                "too many wrong tokens from this address; try again in {} s",
                d.as_secs().max(1)
            ),
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Record {
    failures: u32,
    blocked_until: Option<Instant>,
    last: Instant,
}

/// The token and the per-address failure table.
pub struct Auth {
    token: String,
    table: Mutex<HashMap<Option<IpAddr>, Record>>,
}

/// Key of the shared overflow record (no address is `Some(0.0.0.0)` twice…
/// but a peer never has the unspecified address, so it is free to use).
const OVERFLOW: Option<IpAddr> = Some(IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED));

impl Auth {
    /// A checker for `token`.
    pub fn new(token: &str) -> Self {
        Self {
            token: token.to_string(),
            table: Mutex::new(HashMap::new()),
        }
    }

    /// Check `presented` for a client at `ip`.
    pub fn check(&self, ip: Option<IpAddr>, presented: &str) -> Result<(), Refusal> {
        self.check_at(ip, presented, Instant::now())
    }

    fn check_at(&self, ip: Option<IpAddr>, presented: &str, now: Instant) -> Result<(), Refusal> {
        let ip = ip.map(client_key);
        let mut table = self.table.lock().unwrap_or_else(|p| p.into_inner());
        let key = if table.contains_key(&ip) {
            ip
        } else {
            if table.len() >= MAX_TRACKED_CLIENTS {
                table.retain(|_, r| {
                    now.duration_since(r.last) < FORGET_AFTER
                        || r.blocked_until.is_some_and(|b| b > now)
                });
            }
            if table.len() >= MAX_TRACKED_CLIENTS {
                OVERFLOW
            } else {
                ip
            }
        };
        if let Some(r) = table.get(&key) {
            if let Some(until) = r.blocked_until {
                if until > now {
                    return Err(Refusal::Throttled(until - now));
                }
            }
        }
        if token_eq(presented.trim(), &self.token) {
            if key == ip {
                table.remove(&key);
            }
            return Ok(());
        }
        let r = table.entry(key).or_insert(Record {
            failures: 0,
            blocked_until: None,
            last: now,
        });
        r.failures = r.failures.saturating_add(1);
        r.last = now;
        if r.failures > FREE_FAILURES {
            let doublings = (r.failures - FREE_FAILURES - 1).min(16);
            let block = BASE_BLOCK.saturating_mul(1 << doublings).min(MAX_BLOCK);
            r.blocked_until = Some(now + block);
        }
        Err(Refusal::Wrong)
    }

    /// Addresses tracked now (for tests of the bound).
    #[cfg(test)]
    fn tracked(&self) -> usize {
        self.table.lock().unwrap_or_else(|p| p.into_inner()).len()
    }
}

/// The address a client is throttled as: IPv4 as is (also IPv4-mapped IPv6),
/// IPv6 by its /64 prefix (one host usually holds a whole /64).
fn client_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => IpAddr::V6(std::net::Ipv6Addr::from(
                u128::from(v6) & !((1u128 << 64) - 1),
            )),
        },
    }
}

/// Where the control token comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TokenSource {
    /// `--token` on the command line (visible in `ps`).
    Flag,
    /// The `SPINTUNE_TOKEN` environment variable.
    Env,
    /// `--token-file PATH`.
    File(std::path::PathBuf),
    /// Generated at start (printed).
    Random,
}

/// Why a token file gave no token; the message names the path.
#[derive(Debug, thiserror::Error)]
pub enum TokenFileError {
    /// The file could not be read.
    #[error("cannot read the token file {}: {error}", path.display())]
    Unreadable {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The file holds only white space.
    #[error("the token file {} is empty; put the control token in it", path.display())]
    Empty { path: PathBuf },
}

/// Read a token file: contents trimmed; an unreadable or empty file is an
/// error naming the path.
pub fn read_token_file(path: &Path) -> Result<String, TokenFileError> {
    let text = std::fs::read_to_string(path).map_err(|error| TokenFileError::Unreadable {
        path: path.to_path_buf(),
        error,
    })?;
    let token = text.trim();
    if token.is_empty() {
        return Err(TokenFileError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(token.to_string())
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn after_the_free_failures_attempts_are_throttled_without_comparing() {
        let auth = Auth::new("secret");
        let ip = Some("10.0.0.1".parse().unwrap());
        let t0 = Instant::now();
        for _ in 0..FREE_FAILURES {
            assert_eq!(auth.check_at(ip, "guess", t0), Err(Refusal::Wrong));
        }
        // The next failure starts a block.
        assert_eq!(auth.check_at(ip, "guess", t0), Err(Refusal::Wrong));
        assert!(matches!(
            auth.check_at(ip, "secret", t0),
            Err(Refusal::Throttled(_))
        ));
        // Another address is unaffected.
        assert_eq!(
            auth.check_at(Some("10.0.0.2".parse().unwrap()), "secret", t0),
            Ok(())
        );
        // After the block, the right token works and clears the record.
        let later = t0 + BASE_BLOCK + Duration::from_millis(1);
        assert_eq!(auth.check_at(ip, "secret", later), Ok(()));
        assert_eq!(auth.tracked(), 0);
    }

    #[test]
    fn ipv6_addresses_of_one_64_prefix_share_a_record() {
        let auth = Auth::new("secret");
        let now = Instant::now();
        for i in 0..=FREE_FAILURES {
            let ip: IpAddr = format!("2001:db8::{:x}", i + 1).parse().unwrap();
            assert_eq!(auth.check_at(Some(ip), "guess", now), Err(Refusal::Wrong));
        }
        let same_64: IpAddr = "2001:db8::ffff:1".parse().unwrap();
        assert!(matches!(
            auth.check_at(Some(same_64), "secret", now),
            Err(Refusal::Throttled(_))
        ));
        let other_64: IpAddr = "2001:db8:0:1::1".parse().unwrap();
        assert_eq!(auth.check_at(Some(other_64), "secret", now), Ok(()));
    }

    #[test]
    fn blocks_double_up_to_the_maximum() {
        let auth = Auth::new("secret");
        let ip = Some("10.0.0.1".parse().unwrap());
        let mut now = Instant::now();
        let mut last = Duration::ZERO;
        for _ in 0..FREE_FAILURES + 30 {
            let _ = auth.check_at(ip, "guess", now);
            match auth.check_at(ip, "guess", now) {
                Err(Refusal::Throttled(d)) => {
                    assert!(d >= last.min(MAX_BLOCK) && d <= MAX_BLOCK, "{d:?}");
                    last = d;
                    now += d + Duration::from_millis(1);
                }
                Err(Refusal::Wrong) => {}
                Ok(()) => panic!("wrong token accepted"),
            }
        }
        assert_eq!(last, MAX_BLOCK);
    }

    #[test]
    fn the_table_is_bounded_and_overflow_addresses_share_a_record() {
        let auth = Auth::new("secret");
        let now = Instant::now();
        for i in 0..(MAX_TRACKED_CLIENTS as u32 + 100) {
            let ip = Some(IpAddr::V4(std::net::Ipv4Addr::from(0x0a00_0000 + i)));
            let _ = auth.check_at(ip, "guess", now);
        }
        // Plus the one shared overflow record.
        assert_eq!(auth.tracked(), MAX_TRACKED_CLIENTS + 1);
        // 100 overflow failures were counted together: that record is blocked.
        let fresh = Some("192.168.1.1".parse().unwrap());
        assert!(matches!(
            auth.check_at(fresh, "secret", now),
            Err(Refusal::Throttled(_))
        ));
    }

    #[test]
    fn token_file_errors_name_the_path() {
        let dir = std::env::temp_dir().join(format!("spintune-tokfile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let empty = dir.join("empty");
        std::fs::write(&empty, "  \n").unwrap();
        let e = read_token_file(&empty).unwrap_err().to_string();
        assert!(
            e.contains(&empty.display().to_string()) && e.contains("empty"),
            "{e}"
        );
        let missing = dir.join("missing");
        let e = read_token_file(&missing).unwrap_err().to_string();
        assert!(e.contains(&missing.display().to_string()), "{e}");
        let good = dir.join("good");
        std::fs::write(&good, "s3cret\n").unwrap();
        assert_eq!(read_token_file(&good).unwrap(), "s3cret");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
