//! The viewer WebSocket `/api/runs/{id}/ws` (protocol in [`super`]):
//! `Hello`, the newest page, then live frames in batches; paging, scans,
//! auth and control from the client; send timeouts, pings, lag handling.

use std::collections::HashMap;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Extension, Path, Query, State};
use axum::http::StatusCode;
use axum::response::Response;
use spintune::protocol::{
    ClientMessage, IterationRecord, ServerMessage, DEFAULT_HISTORY_PAGE, MAX_HISTORY_PAGE,
    PROTOCOL_VERSION,
};
use tokio::sync::broadcast::error::RecvError;

use super::error::{ApiError, ApiResult};
use super::parse::{parse_client_message, parse_id, parse_u64};
use super::socket::{refuse_socket, too_big_close, version_mismatch};
use super::{auth, AppState, MAX_VIEWER_MESSAGE};
use crate::run::{history_message_json, ViewerSlot, ViewerUpdate};

/// How long the server tries to send a close frame to a viewer it drops for
/// a timeout.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

pub(super) async fn ws(
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
    let handle = s.manager.get(id)?;
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
    let max = s.manager.options().viewers.max_viewers_per_run;
    let Some(slot) = handle.add_viewer(max) else {
        return Err(ApiError(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("run {id} already has {max} open viewer WebSockets, the most the server serves per run; try again later"),
        ));
    };
    drop(handle);
    Ok(upgrade.on_upgrade(move |socket| viewer(s, id, from, socket, slot)))
}

fn text_of(msg: &ServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).expect("ServerMessage serializes"),
    ))
}
/// What the viewer's socket loop answers itself (it needs the socket).
enum ViewerRequest {
    History { before: Option<u64>, limit: u32 },
    Scans { iteration: u64 },
}

/// Per-socket state that client messages change.
#[derive(Default)]
struct ViewerState {
    /// Live `Iteration` frames carry the full record.
    scans: bool,
    /// The run's `Alert` frames are sent (`subscribe` with `alerts: true`).
    alerts: bool,
    /// A request for the socket loop.
    request: Option<ViewerRequest>,
}

/// Why a viewer's socket ended.
enum ViewerEnd {
    /// The client went away, closed, or the run was deleted.
    Gone,
    /// A send did not complete within the send timeout.
    SendTimeout(Duration),
    /// Nothing arrived within the pong timeout.
    Idle(Duration),
    /// The viewer sent a message above [`MAX_VIEWER_MESSAGE`]: this close
    /// frame (1009) ends the socket.
    TooBig(Message),
}

/// Send one frame within `timeout`.
async fn send_within(
    socket: &mut WebSocket,
    msg: Message,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    let deadline = tokio::time::Instant::now() + timeout;
    by_deadline(socket.send(msg), deadline, timeout).await
}

/// Run a socket write by `deadline`: a failed write means the viewer is
/// gone, a late one a [`ViewerEnd::SendTimeout`] of `timeout` (what the
/// deadline was set from).
async fn by_deadline(
    write: impl std::future::Future<Output = Result<(), axum::Error>>,
    deadline: tokio::time::Instant,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    match tokio::time::timeout_at(deadline, write).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err(ViewerEnd::Gone),
        Err(_) => Err(ViewerEnd::SendTimeout(timeout)),
    }
}

/// A `History` frame of summaries with seq in `[from.max(end - limit), end)`,
/// `end` = `before` or the newest; with the page's `end` (see
/// `run::handle::RecentPage::end`). From the run's ring of recent summaries
/// when it holds the page, else from the store. `None`: the run is gone or
/// the store failed.
async fn history_page(
    state: &AppState,
    id: u64,
    before: Option<u64>,
    limit: u64,
    from: u64,
) -> Option<(Message, u64)> {
    let handle = state.manager.get(id).ok()?;
    if let Some(page) = handle.recent_page(before, limit, from) {
        let records: Vec<&str> = page.records.iter().map(Utf8Bytes::as_str).collect();
        let text = history_message_json(&records, page.more_before);
        return Some((Message::Text(Utf8Bytes::from(text)), page.end));
    }
    drop(handle);
    let store = state.manager.store().clone();
    let page = tokio::task::spawn_blocking(move || store.summary_page(id, before, limit))
        .await
        .ok()?
        .ok()?;
    let first = page.first_seq.unwrap_or(0);
    let len = page.records.len() as u64;
    let end = page.first_seq.map_or(before.unwrap_or(0), |f| f + len);
    let skip = from.saturating_sub(first).min(len);
    let records = &page.records[skip as usize..];
    // Seq is contiguous from 0: a page starting above 0 has older iterations.
    let more_before = if skip > 0 {
        first + skip > 0
    } else {
        page.more_before
    };
    let text = history_message_json(records, more_before);
    Some((Message::Text(Utf8Bytes::from(text)), end))
}

/// The answer to `Scans{iteration}`: the stored record's scans.
async fn scans_of(state: &AppState, id: u64, iteration: u64) -> ServerMessage {
    let store = state.manager.store().clone();
    let stored = tokio::task::spawn_blocking(move || store.iteration_json(id, iteration))
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r.map_err(|e| e.to_string()));
    let record = match stored {
        Ok(Some(json)) => serde_json::from_str::<IterationRecord>(&json).map_err(|e| e.to_string()),
        Ok(None) => {
            return ServerMessage::Error {
                message: format!("run {id} has no stored iteration {iteration}"),
            }
        }
        Err(e) => Err(e),
    };
    match record {
        Ok(r) if r.iteration == iteration => ServerMessage::Scans {
            iteration,
            scans: r.scans,
        },
        Ok(r) => ServerMessage::Error {
            message: format!(
                "run {id}: the record stored at position {iteration} is iteration {}",
                r.iteration
            ),
        },
        Err(e) => ServerMessage::Error {
            message: format!("run {id}: cannot read iteration {iteration}: {e}"),
        },
    }
}

/// One viewer's socket: the loop, then a close frame with the reason if the
/// server ends it for a timeout. `_slot` counts the socket against
/// [`MAX_VIEWERS_PER_RUN`](super::MAX_VIEWERS_PER_RUN) until it ends.
async fn viewer(state: AppState, id: u64, from: u64, mut socket: WebSocket, _slot: ViewerSlot) {
    let end = viewer_loop(&state, id, from, &mut socket).await;
    let reason = match end {
        ViewerEnd::Gone => return,
        ViewerEnd::TooBig(close) => {
            eprintln!("viewer of run {id} disconnected: inbound message too big");
            let _ = tokio::time::timeout(CLOSE_GRACE, socket.send(close)).await;
            return;
        }
        ViewerEnd::SendTimeout(t) => format!(
            "send timed out after {} s: the viewer does not read",
            t.as_secs_f64()
        ),
        ViewerEnd::Idle(t) => format!("nothing received for {} s (no pong)", t.as_secs_f64()),
    };
    eprintln!("viewer of run {id} disconnected: {reason}");
    let close = Message::Close(Some(axum::extract::ws::CloseFrame {
        code: axum::extract::ws::close_code::POLICY,
        reason: Utf8Bytes::from(reason),
    }));
    let _ = tokio::time::timeout(CLOSE_GRACE, socket.send(close)).await;
}

/// Hello and the newest page, then live frames; answers client messages.
async fn viewer_loop(state: &AppState, id: u64, from: u64, socket: &mut WebSocket) -> ViewerEnd {
    let limits = state.manager.options().viewers;
    let timeout = limits.send_timeout;
    let Ok(handle) = state.manager.get(id) else {
        return ViewerEnd::Gone;
    };
    // Subscribe before reading the page so that nothing falls in between;
    // duplicates are dropped by seq below. Only the receiver is held: when
    // the run is deleted the channel closes.
    let mut rx = handle.subscribe();
    let hello = text_of(&ServerMessage::Hello {
        version: PROTOCOL_VERSION,
        run: handle.summary(),
    });
    drop(handle);
    if let Err(e) = send_within(socket, hello, timeout).await {
        return e;
    }
    let page = DEFAULT_HISTORY_PAGE as u64;
    // `next`: the seq of the next live iteration this socket needs.
    let Some((frame, mut next)) = history_page(state, id, None, page, from).await else {
        return ViewerEnd::Gone;
    };
    if let Err(e) = send_within(socket, frame, timeout).await {
        return e;
    }
    let mut authed = false;
    let mut view = ViewerState::default();
    // The run's alerts, on their own channel (so that they take no room in
    // the live frames' ring of viewers that did not ask for them); only
    // after `subscribe` with `alerts: true`.
    let mut alerts: Option<tokio::sync::broadcast::Receiver<ViewerUpdate>> = None;
    let mut last_heard = tokio::time::Instant::now();
    let mut ping = tokio::time::interval_at(
        tokio::time::Instant::now() + limits.ping_interval,
        limits.ping_interval,
    );
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let result = tokio::select! {
            frame = rx.recv() => match frame {
                Ok(frame) => {
                    live_batch(state, id, socket, &mut rx, frame, &mut next, view.scans, timeout)
                        .await
                }
                Err(RecvError::Lagged(skipped)) => {
                    send_lagged(state, id, socket, skipped, &mut next, timeout).await
                }
                Err(RecvError::Closed) => {
                    let _ = send_within(socket, Message::Close(None), CLOSE_GRACE).await;
                    Err(ViewerEnd::Gone)
                }
            },
            incoming = socket.recv() => {
                let incoming = match incoming {
                    Some(Ok(incoming)) => incoming,
                    Some(Err(e)) => {
                        return too_big_close(&e, MAX_VIEWER_MESSAGE)
                            .map_or(ViewerEnd::Gone, ViewerEnd::TooBig)
                    }
                    None => return ViewerEnd::Gone,
                };
                last_heard = tokio::time::Instant::now();
                let reply = match incoming {
                    Message::Text(text) => {
                        client_message(state, id, text.as_str(), &mut authed, &mut view).await
                    }
                    Message::Binary(_) => Some(ServerMessage::Error {
                        message: "binary frames are not supported; send JSON text".into(),
                    }),
                    Message::Close(_) => return ViewerEnd::Gone,
                    Message::Ping(_) | Message::Pong(_) => None,
                };
                // alerts raised before this viewer asked: sent after the reply
                let mut earlier = Vec::new();
                if view.alerts != alerts.is_some() {
                    alerts = match state.manager.get(id) {
                        Ok(handle) if view.alerts => {
                            let (rx, recent) = handle.subscribe_alerts();
                            earlier = recent;
                            Some(rx)
                        }
                        _ => None,
                    };
                }
                let reply = match (reply, view.request.take()) {
                    (Some(reply), _) => Some(text_of(&reply)),
                    (None, Some(ViewerRequest::History { before, limit })) => {
                        match history_page(state, id, before, limit as u64, 0).await {
                            Some((frame, _)) => Some(frame),
                            None => return ViewerEnd::Gone,
                        }
                    }
                    (None, Some(ViewerRequest::Scans { iteration })) => {
                        Some(text_of(&scans_of(state, id, iteration).await))
                    }
                    (None, None) => None,
                };
                let mut sent = match reply {
                    Some(reply) => send_within(socket, reply, timeout).await,
                    None => Ok(()),
                };
                for text in earlier {
                    if sent.is_err() {
                        break;
                    }
                    sent = send_within(socket, Message::Text(text), timeout).await;
                }
                sent
            }
            alert = async {
                match alerts.as_mut() {
                    Some(rx) => rx.recv().await,
                    None => std::future::pending().await,
                }
            } => match alert {
                Ok(update) => send_within(socket, Message::Text(update.text), timeout).await,
                // More than `run::ALERTS_PER_VIEWER` alerts behind: the older are skipped.
                Err(RecvError::Lagged(_)) => Ok(()),
                Err(RecvError::Closed) => {
                    alerts = None;
                    Ok(())
                }
            },
            _ = ping.tick() => {
                if last_heard.elapsed() >= limits.pong_timeout {
                    return ViewerEnd::Idle(limits.pong_timeout);
                }
                send_within(socket, Message::Ping(Bytes::new()), timeout).await
            }
        };
        if let Err(e) = result {
            return e;
        }
    }
}

/// Most live frames written to one viewer between two flushes.
pub const MAX_LIVE_BATCH: usize = 64;

/// Write `first` and whatever else is already queued for this viewer (at
/// most [`MAX_LIVE_BATCH`] frames), then flush once: a viewer that fell
/// behind catches up with one write instead of one per frame, which keeps
/// the fan-out's system calls, and so its latency, down under load. The
/// whole batch must be written within `timeout`. Frames with a seq below
/// `next` (already sent in a page) are skipped; a gap is filled from the
/// store first.
#[allow(clippy::too_many_arguments)]
async fn live_batch(
    state: &AppState,
    id: u64,
    socket: &mut WebSocket,
    rx: &mut tokio::sync::broadcast::Receiver<ViewerUpdate>,
    first: ViewerUpdate,
    next: &mut u64,
    scans: bool,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    use futures_util::SinkExt;
    use tokio::sync::broadcast::error::TryRecvError;
    let deadline = tokio::time::Instant::now() + timeout;
    let mut update = first;
    let mut lag = None;
    for n in 1.. {
        match update.seq {
            Some(seq) if seq < *next => {}
            seq => {
                if let Some(seq) = seq {
                    if seq > *next {
                        // Missed something (cannot normally happen): send the gap.
                        let Some((gap, _)) =
                            history_page(state, id, Some(seq), seq - *next, *next).await
                        else {
                            return Err(ViewerEnd::Gone);
                        };
                        by_deadline(socket.feed(gap), deadline, timeout).await?;
                    }
                    *next = seq + 1;
                }
                let text = match (&update.full, scans) {
                    (Some(full), true) => full.clone(),
                    _ => update.text,
                };
                by_deadline(socket.feed(Message::Text(text)), deadline, timeout).await?;
            }
        }
        if n >= MAX_LIVE_BATCH {
            break;
        }
        match rx.try_recv() {
            Ok(u) => update = u,
            Err(TryRecvError::Lagged(skipped)) => {
                lag = Some(skipped);
                break;
            }
            // Empty; or Closed, which the next `recv` reports.
            Err(_) => break,
        }
    }
    by_deadline(socket.flush(), deadline, timeout).await?;
    match lag {
        Some(skipped) => send_lagged(state, id, socket, skipped, next, timeout).await,
        None => Ok(()),
    }
}

/// The viewer lagged by `skipped` live frames: tell it, then send the
/// newest page (it asks for older pages to fill any gap).
async fn send_lagged(
    state: &AppState,
    id: u64,
    socket: &mut WebSocket,
    skipped: u64,
    next: &mut u64,
    timeout: Duration,
) -> Result<(), ViewerEnd> {
    let lagged = text_of(&ServerMessage::Lagged { skipped });
    send_within(socket, lagged, timeout).await?;
    match history_page(state, id, None, DEFAULT_HISTORY_PAGE as u64, *next).await {
        Some((frame, end)) => {
            *next = (*next).max(end);
            send_within(socket, frame, timeout).await
        }
        None => Err(ViewerEnd::Gone),
    }
}

async fn client_message(
    state: &AppState,
    id: u64,
    text: &str,
    authed: &mut bool,
    view: &mut ViewerState,
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
        // Paging and scans are answered by the socket loop (`viewer_loop`).
        ClientMessage::History { before, limit } => {
            let limit = limit.unwrap_or(DEFAULT_HISTORY_PAGE);
            if limit > MAX_HISTORY_PAGE {
                ServerMessage::Error {
                    message: format!(
                        "history limit {limit} exceeds the largest page, {MAX_HISTORY_PAGE} records; ask for older pages with `before`"
                    ),
                }
            } else {
                view.request = Some(ViewerRequest::History { before, limit });
                return None;
            }
        }
        ClientMessage::Scans { iteration } => {
            view.request = Some(ViewerRequest::Scans { iteration });
            return None;
        }
        ClientMessage::Subscribe { scans, alerts } => {
            view.scans = scans;
            view.alerts = alerts;
            return None;
        }
    })
}
