//! The alert webhook (`spintune serve --alert-webhook URL`, docs/alerts.md):
//! every alert a run raises ([`spintune::alert`] decides when) is POSTed as
//! a small JSON object to one configured `http://` URL.
//!
//! It never blocks a run: the run hands the alert to a bounded queue
//! ([`ALERT_QUEUE`]) with `try_send` ([`AlertSink::offer`]); when the queue
//! is full the alert is dropped and counted (logged once until the queue
//! drains again). One background task drains the queue, one alert at a
//! time: each POST has [`WEBHOOK_TIMEOUT`] in all (connect, send, the
//! answer's status line), and is tried at most [`WEBHOOK_ATTEMPTS`] times,
//! waiting [`WEBHOOK_BACKOFF`] between attempts, again only after a
//! connection error, a timeout or a 5xx answer (never after a 4xx). Every
//! failure is logged on stderr (`alert webhook: …`); nothing panics.
//!
//! This module imports nothing of `run` or `server` (the run handle uses
//! it).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use axum::http::{header, Method, Request, Uri};
use http_body_util::Full;
use serde::Serialize;
use spintune::protocol::Alert;
use tokio::sync::mpsc;

/// Alerts waiting for the webhook sender; one more is dropped and counted.
pub const ALERT_QUEUE: usize = 64;

/// One POST to the webhook, in all (connect, request, the answer's status
/// line); later counts as a failed attempt.
pub const WEBHOOK_TIMEOUT: Duration = Duration::from_secs(5);

/// Attempts per alert (the first and two retries).
pub const WEBHOOK_ATTEMPTS: usize = 3;

/// Waits before the second and third attempt.
pub const WEBHOOK_BACKOFF: [Duration; WEBHOOK_ATTEMPTS - 1] =
    [Duration::from_secs(1), Duration::from_secs(2)];

/// Longest accepted `--alert-webhook` URL, bytes.
pub const MAX_WEBHOOK_URL: usize = 2048;

/// A checked webhook address: `http://host[:port][/path][?query]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WebhookUrl {
    uri: Uri,
    host: String,
    port: u16,
}

impl WebhookUrl {
    /// Parse `text`; the error names the flag and says what is wrong.
    ///
    /// ```
    /// use spintune_server::alerts::WebhookUrl;
    /// assert!(WebhookUrl::parse("http://127.0.0.1:9000/hook").is_ok());
    /// let e = WebhookUrl::parse("https://lab.example/hook").unwrap_err();
    /// assert!(e.starts_with("--alert-webhook: only http:// URLs are supported"), "{e}");
    /// ```
    pub fn parse(text: &str) -> Result<Self, String> {
        let bad = |why: &str| format!("--alert-webhook: {why}, got {text:?}");
        if text.len() > MAX_WEBHOOK_URL {
            return Err(format!(
                "--alert-webhook: the URL is {} bytes, longer than the largest accepted, {MAX_WEBHOOK_URL} bytes",
                text.len()
            ));
        }
        let uri: Uri = text.parse().map_err(|e| bad(&format!("not a URL ({e})")))?;
        match uri.scheme_str() {
            Some("http") => {}
            Some(_) => return Err(bad(
                "only http:// URLs are supported (a lab-internal listener; put a TLS proxy in front for https)",
            )),
            None => return Err(bad("expected an absolute URL such as http://127.0.0.1:9000/alerts")),
        }
        let authority = uri.authority().ok_or_else(|| bad("the URL has no host"))?;
        if authority.as_str().contains('@') {
            return Err(bad("user names or passwords in the URL are not supported"));
        }
        let host = authority
            .host()
            .trim_start_matches('[')
            .trim_end_matches(']');
        if host.is_empty() {
            return Err(bad("the URL has no host"));
        }
        Ok(Self {
            host: host.to_string(),
            port: authority.port_u16().unwrap_or(80),
            uri,
        })
    }

    /// The URL for logs: scheme and host only (a webhook's path may hold a
    /// secret), e.g. `http://127.0.0.1:9000/…`.
    pub fn shown(&self) -> String {
        let authority = self.uri.authority().map_or("", |a| a.as_str());
        let path = self.uri.path_and_query().map_or("/", |p| p.as_str());
        format!("http://{authority}{}", if path == "/" { "/" } else { "/…" })
    }
}

/// The webhook's JSON body: the alert and when the server raised it.
#[derive(Serialize)]
struct Body<'a> {
    #[serde(flatten)]
    alert: &'a Alert,
    at: &'a str,
}

/// The sending side of the alert queue, held by every run handle.
#[derive(Debug, Clone)]
pub struct AlertSink {
    tx: mpsc::Sender<(Alert, String)>,
    dropped: Arc<AtomicU64>,
    /// A drop was logged and the queue has not drained since.
    logged_full: Arc<AtomicBool>,
}

impl AlertSink {
    /// Start the sender task (on the present tokio runtime) posting to `url`.
    pub fn start(url: WebhookUrl) -> Self {
        let (tx, rx) = mpsc::channel(ALERT_QUEUE);
        let sink = Self {
            tx,
            dropped: Arc::new(AtomicU64::new(0)),
            logged_full: Arc::new(AtomicBool::new(false)),
        };
        tokio::spawn(sender(url, rx, sink.logged_full.clone()));
        sink
    }

    /// Queue `alert` raised `at` (RFC 3339) without waiting: when the queue
    /// is full it is dropped, counted, and the first drop is logged.
    pub fn offer(&self, alert: Alert, at: String) {
        match self.tx.try_send((alert, at)) {
            Ok(()) => {}
            Err(mpsc::error::TrySendError::Full((alert, _))) => {
                let n = self.dropped.fetch_add(1, Ordering::AcqRel) + 1;
                if !self.logged_full.swap(true, Ordering::AcqRel) {
                    eprintln!(
                        "alert webhook: the queue is full ({ALERT_QUEUE} alerts waiting); dropped the {} alert of run {} ({n} dropped since start); further drops are not logged until it drains",
                        alert.kind.name(),
                        alert.run
                    );
                }
            }
            // The sender task is gone (runtime shutting down): nothing to do.
            Err(mpsc::error::TrySendError::Closed(_)) => {}
        }
    }

    /// Alerts dropped because the queue was full, since start.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Acquire)
    }
}

/// The one sender task: deliver the queued alerts one at a time.
async fn sender(
    url: WebhookUrl,
    mut rx: mpsc::Receiver<(Alert, String)>,
    logged_full: Arc<AtomicBool>,
) {
    while let Some((alert, at)) = rx.recv().await {
        let body = match serde_json::to_vec(&Body {
            alert: &alert,
            at: &at,
        }) {
            Ok(b) => b,
            Err(e) => {
                eprintln!("alert webhook: cannot serialize an alert: {e}");
                continue;
            }
        };
        deliver(&url, &alert, body).await;
        if rx.is_empty() {
            logged_full.store(false, Ordering::Release);
        }
    }
}

/// What one attempt gave.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Attempt {
    /// The listener answered with this status.
    Answered(u16),
    /// No answer: connection refused or broken, or the timeout passed.
    NoAnswer(String),
}

/// Whether another attempt may help: no answer, or a server error (5xx).
fn retryable(attempt: &Attempt) -> bool {
    match attempt {
        Attempt::Answered(status) => (500..600).contains(status),
        Attempt::NoAnswer(_) => true,
    }
}

/// Up to [`WEBHOOK_ATTEMPTS`] POSTs of `body`; logs how it ended unless the
/// first attempt succeeded.
async fn deliver(url: &WebhookUrl, alert: &Alert, body: Vec<u8>) {
    let what = format!("the {} alert of run {}", alert.kind.name(), alert.run);
    for n in 0..WEBHOOK_ATTEMPTS {
        if n > 0 {
            tokio::time::sleep(WEBHOOK_BACKOFF[n - 1]).await;
        }
        let attempt = match tokio::time::timeout(WEBHOOK_TIMEOUT, post(url, body.clone())).await {
            Ok(Ok(status)) => Attempt::Answered(status),
            Ok(Err(e)) => Attempt::NoAnswer(e),
            Err(_) => {
                Attempt::NoAnswer(format!("no answer within {} s", WEBHOOK_TIMEOUT.as_secs()))
            }
        };
        let outcome = match &attempt {
            Attempt::Answered(s) if (200..300).contains(s) => {
                if n > 0 {
                    eprintln!(
                        "alert webhook: delivered {what} to {} on attempt {} of {WEBHOOK_ATTEMPTS}",
                        url.shown(),
                        n + 1
                    );
                }
                return;
            }
            Attempt::Answered(s) => format!("the listener answered HTTP {s}"),
            Attempt::NoAnswer(e) => e.clone(),
        };
        if !retryable(&attempt) {
            eprintln!(
                "alert webhook: gave up on {what}: POST {} failed: {outcome} (a 4xx answer is not retried)",
                url.shown()
            );
            return;
        }
        if n + 1 < WEBHOOK_ATTEMPTS {
            eprintln!(
                "alert webhook: POST {} for {what} failed (attempt {} of {WEBHOOK_ATTEMPTS}): {outcome}; retrying in {} s",
                url.shown(),
                n + 1,
                WEBHOOK_BACKOFF[n].as_secs()
            );
        } else {
            eprintln!(
                "alert webhook: gave up on {what} after {WEBHOOK_ATTEMPTS} attempts: POST {} failed: {outcome}",
                url.shown()
            );
        }
    }
}

/// One HTTP/1.1 POST of `body` (JSON) to `url`; the answer's status.
async fn post(url: &WebhookUrl, body: Vec<u8>) -> Result<u16, String> {
    let stream = tokio::net::TcpStream::connect((url.host.as_str(), url.port))
        .await
        .map_err(|e| format!("cannot connect to {}:{}: {e}", url.host, url.port))?;
    let _ = stream.set_nodelay(true);
    let (mut send, connection) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
            .await
            .map_err(|e| format!("HTTP handshake: {e}"))?;
    // Drives the connection; aborted when this attempt ends.
    let driver = AbortOnDrop(tokio::spawn(async move {
        let _ = connection.await;
    }));
    let path = url
        .uri
        .path_and_query()
        .map_or("/", |p| p.as_str())
        .to_string();
    let authority = url.uri.authority().map_or("", |a| a.as_str()).to_string();
    let request = Request::builder()
        .method(Method::POST)
        .uri(path)
        .header(header::HOST, authority)
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::USER_AGENT, "spintune-alerts")
        .header(header::CONNECTION, "close")
        .body(Full::new(axum::body::Bytes::from(body)))
        .map_err(|e| format!("cannot build the request: {e}"))?;
    let response = send
        .send_request(request)
        .await
        .map_err(|e| format!("no answer: {e}"))?;
    drop(driver);
    Ok(response.status().as_u16())
}

struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// `time` as RFC 3339 in UTC with whole seconds, e.g. `2026-11-24T09:10:11Z`.
///
/// ```
/// use std::time::{Duration, UNIX_EPOCH};
/// use spintune_server::alerts::rfc3339_utc;
/// assert_eq!(rfc3339_utc(UNIX_EPOCH), "1970-01-01T00:00:00Z");
/// assert_eq!(rfc3339_utc(UNIX_EPOCH + Duration::from_secs(1_795_000_000)), "2026-11-18T11:06:40Z");
/// ```
pub fn rfc3339_utc(time: SystemTime) -> String {
    let secs = time
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// The present wall-clock time, [`rfc3339_utc`].
pub fn now_rfc3339() -> String {
    rfc3339_utc(SystemTime::now())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_checked_naming_the_flag() {
        let u = WebhookUrl::parse("http://localhost:9000/a/b?x=1").unwrap();
        assert_eq!((u.host.as_str(), u.port), ("localhost", 9000));
        assert_eq!(WebhookUrl::parse("http://[::1]/").unwrap().host, "::1");
        assert_eq!(WebhookUrl::parse("http://10.0.0.2").unwrap().port, 80);
        for bad in [
            "",
            "localhost:9000",
            "ftp://x/",
            "https://x/",
            "http://user:pw@x/",
            "/just/a/path",
        ] {
            let e = WebhookUrl::parse(bad).unwrap_err();
            assert!(e.starts_with("--alert-webhook: "), "{bad:?}: {e}");
        }
        let long = format!("http://x/{}", "a".repeat(MAX_WEBHOOK_URL));
        assert!(WebhookUrl::parse(&long).unwrap_err().contains("2048 bytes"));
    }

    #[test]
    fn a_full_queue_drops_and_counts_without_waiting() {
        let (tx, mut rx) = mpsc::channel(ALERT_QUEUE);
        let sink = AlertSink {
            tx,
            dropped: Arc::new(AtomicU64::new(0)),
            logged_full: Arc::new(AtomicBool::new(false)),
        };
        let alert = |run| Alert {
            run,
            name: "r".into(),
            kind: spintune::protocol::AlertKind::Finished,
            message: "finished".into(),
            lab_seconds: 1.0,
            iteration: Some(0),
        };
        for run in 0..ALERT_QUEUE as u64 + 5 {
            sink.offer(alert(run), "2026-11-24T09:00:00Z".into());
        }
        assert_eq!(sink.dropped(), 5);
        assert!(sink.logged_full.load(Ordering::Acquire));
        // The queue holds the first ALERT_QUEUE, in order.
        assert_eq!(rx.try_recv().unwrap().0.run, 0);
        assert_eq!(rx.len(), ALERT_QUEUE - 1);
    }

    #[test]
    fn only_no_answer_and_server_errors_are_retried() {
        assert!(retryable(&Attempt::NoAnswer("refused".into())));
        assert!(retryable(&Attempt::Answered(500)));
        assert!(retryable(&Attempt::Answered(503)));
        assert!(!retryable(&Attempt::Answered(400)));
        assert!(!retryable(&Attempt::Answered(404)));
        assert!(!retryable(&Attempt::Answered(200)));
    }

    #[test]
    fn dates_are_civil_utc() {
        // 2000-02-29 (leap day) 12:34:56
        assert_eq!(
            rfc3339_utc(UNIX_EPOCH + Duration::from_secs(951_827_696)),
            "2000-02-29T12:34:56Z"
        );
        assert_eq!(
            rfc3339_utc(UNIX_EPOCH + Duration::from_secs(4_102_444_799)),
            "2099-12-31T23:59:59Z"
        );
    }
}
