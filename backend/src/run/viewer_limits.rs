//! Limits of a run's viewer WebSockets: the defaults (the server serves
//! them, `crate::server`) and the per-manager settings.

use std::time::Duration;

/// A send to a viewer (one frame into the socket) that does not complete in
/// this time closes the viewer's socket: a viewer that stops reading holds
/// at most one frame for at most this long.
pub const VIEWER_SEND_TIMEOUT: Duration = Duration::from_secs(10);
/// The server pings every viewer this often.
pub const VIEWER_PING_INTERVAL: Duration = Duration::from_secs(15);
/// A viewer from which nothing (a pong or any frame) arrived for this long
/// is disconnected; checked at each ping, so it goes within
/// `VIEWER_PONG_TIMEOUT + VIEWER_PING_INTERVAL`.
pub const VIEWER_PONG_TIMEOUT: Duration = Duration::from_secs(45);
/// Open viewer WebSockets per run; one more is refused with 503.
pub const MAX_VIEWERS_PER_RUN: usize = 1024;

/// Limits of a run's viewer WebSockets (what happens when one is reached:
/// `crate::server`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewerLimits {
    /// A send to a viewer that does not complete in this time disconnects it.
    pub send_timeout: Duration,
    /// The server pings every viewer this often.
    pub ping_interval: Duration,
    /// A viewer from which nothing (pong or any frame) arrived for this long
    /// is disconnected (checked at each ping).
    pub pong_timeout: Duration,
    /// Open viewer WebSockets per run; one more is refused with 503.
    pub max_viewers_per_run: usize,
}

impl Default for ViewerLimits {
    fn default() -> Self {
        Self {
            send_timeout: VIEWER_SEND_TIMEOUT,
            ping_interval: VIEWER_PING_INTERVAL,
            pong_timeout: VIEWER_PONG_TIMEOUT,
            max_viewers_per_run: MAX_VIEWERS_PER_RUN,
        }
    }
}
