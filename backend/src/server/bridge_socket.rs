//! The lab bridge's WebSocket `/api/runs/{id}/bridge`: authenticates a lab
//! script and pumps frames between it and the run's
//! [`crate::devices::bridge::BridgeLink`]. Wire protocol: see
//! [`crate::devices::bridge`].

use std::collections::HashMap;
use std::time::Duration;

use axum::extract::ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Extension, Path, Query, State};
use axum::response::Response;
use spintune::protocol::{BridgeClientMessage, BridgeServerMessage, PROTOCOL_VERSION};
use tokio::sync::mpsc;

use super::error::ApiResult;
use super::parse::{parse_id, parse_strict};
use super::socket::{refuse_socket, too_big_close, version_mismatch};
use super::{auth, AppState, MAX_BRIDGE_MESSAGE};
use crate::devices::bridge::{BridgeLink, AUTH_TIMEOUT_S};

fn frame(msg: &BridgeServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).expect("BridgeServerMessage serializes"),
    ))
}

fn error_frame(message: impl Into<String>) -> Message {
    frame(&BridgeServerMessage::Error {
        message: message.into(),
    })
}

/// The lab bridge's socket (see [`crate::devices::bridge`]).
pub(super) async fn bridge_ws(
    State(s): State<AppState>,
    Extension(client): Extension<auth::ClientIp>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    upgrade: WebSocketUpgrade,
) -> ApiResult<Response> {
    let id = parse_id(&id)?;
    s.manager.get(id)?;
    let s = s.for_client(client);
    let upgrade = upgrade
        .max_message_size(MAX_BRIDGE_MESSAGE)
        .max_frame_size(MAX_BRIDGE_MESSAGE);
    if let Some(message) = version_mismatch(&q) {
        let frame =
            serde_json::to_string(&spintune::protocol::BridgeServerMessage::Error { message })
                .expect("BridgeServerMessage serializes");
        return Ok(refuse_socket(
            upgrade,
            Message::Text(Utf8Bytes::from(frame)),
        ));
    }
    Ok(upgrade.on_upgrade(move |socket| serve_socket(s, id, socket)))
}

/// Serve one bridge socket of run `id` (the handler of `/api/runs/{id}/bridge`).
pub async fn serve_socket(state: AppState, id: u64, mut socket: WebSocket) {
    // A message above MAX_BRIDGE_MESSAGE closes with 1009 (Message Too Big).
    let close = match serve(&state, id, &mut socket).await {
        Err(e) => too_big_close(&e, MAX_BRIDGE_MESSAGE),
        Ok(()) => None,
    };
    let _ = socket.send(close.unwrap_or(Message::Close(None))).await;
}

async fn serve(state: &AppState, id: u64, socket: &mut WebSocket) -> Result<(), axum::Error> {
    let Ok(handle) = state.manager.get(id) else {
        return socket
            .send(error_frame(format!("no run with id {id}")))
            .await;
    };
    socket
        .send(frame(&BridgeServerMessage::Hello {
            version: PROTOCOL_VERSION,
            run: handle.summary(),
        }))
        .await?;
    drop(handle);
    // Authentication first.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(AUTH_TIMEOUT_S);
    loop {
        let incoming = match tokio::time::timeout_at(deadline, socket.recv()).await {
            Err(_) => {
                return socket
                    .send(error_frame(format!(
                        "no auth frame within {AUTH_TIMEOUT_S} s; send {{\"type\":\"auth\",\"token\":\"…\"}} first"
                    )))
                    .await
            }
            Ok(None) => return Ok(()),
            Ok(Some(m)) => m?,
        };
        let text = match incoming {
            Message::Text(t) => t,
            Message::Close(_) => return Ok(()),
            Message::Ping(_) | Message::Pong(_) => continue,
            Message::Binary(_) => {
                return socket
                    .send(error_frame(
                        "binary frames are not supported; send JSON text",
                    ))
                    .await
            }
        };
        match parse_strict::<BridgeClientMessage>(text.as_str()) {
            Ok(BridgeClientMessage::Auth { token }) => match state.auth.check(state.client, &token)
            {
                Ok(()) => break,
                Err(refusal) => return socket.send(error_frame(refusal.message())).await,
            },
            Ok(BridgeClientMessage::Response { .. }) => return socket
                .send(error_frame(
                    "the bridge must authenticate first: send {\"type\":\"auth\",\"token\":\"…\"}",
                ))
                .await,
            Err(e) => return socket.send(error_frame(e.to_string())).await,
        }
    }
    let link = match state.manager.bridge_link(id) {
        Ok(l) => l,
        Err(e) => return socket.send(error_frame(e.to_string())).await,
    };
    socket.send(frame(&BridgeServerMessage::AuthOk)).await?;
    let (generation, mut outbox) = link.attach();
    let result = pump(&link, generation, &mut outbox, socket).await;
    link.detach(generation);
    result
}

async fn pump(
    link: &BridgeLink,
    generation: u64,
    outbox: &mut mpsc::UnboundedReceiver<Utf8Bytes>,
    socket: &mut WebSocket,
) -> Result<(), axum::Error> {
    loop {
        tokio::select! {
            out = outbox.recv() => match out {
                Some(text) => socket.send(Message::Text(text)).await?,
                None => {
                    return socket
                        .send(error_frame("replaced by a newer bridge connection for this run"))
                        .await;
                }
            },
            incoming = socket.recv() => {
                let Some(incoming) = incoming else { return Ok(()) };
                let reply = match incoming? {
                    Message::Text(text) => match parse_strict::<BridgeClientMessage>(text.as_str()) {
                        Ok(BridgeClientMessage::Response { id, response }) => {
                            link
                                .answer(generation, id, response)
                                .err()
                                .map(|e| error_frame(e.to_string()))
                        }
                        // Never an unchecked `auth_ok`: the socket is
                        // authenticated once, for its lifetime.
                        Ok(BridgeClientMessage::Auth { .. }) => Some(error_frame(
                            "this bridge socket is already authenticated; a second auth is \
                             not checked and changes nothing (reconnect to use another token)",
                        )),
                        Err(e) => Some(error_frame(e.to_string())),
                    },
                    Message::Binary(_) => {
                        Some(error_frame("binary frames are not supported; send JSON text"))
                    }
                    Message::Close(_) => return Ok(()),
                    Message::Ping(_) | Message::Pong(_) => None,
                };
                if let Some(reply) = reply {
                    socket.send(reply).await?;
                }
            }
        }
    }
}
