//! What the viewer and the bridge WebSockets share: the protocol version
//! check of the URL, refusing an upgrade with one error frame, and the 1009
//! close of an inbound message above the limit.

use std::collections::HashMap;

use axum::extract::ws::{Message, Utf8Bytes, WebSocketUpgrade};
use axum::response::Response;
use spintune::protocol::PROTOCOL_VERSION;

/// `Some(error message)` unless the WebSocket URL states `protocol=`[`PROTOCOL_VERSION`].
pub(super) fn version_mismatch(q: &HashMap<String, String>) -> Option<String> {
    match q.get("protocol").map(String::as_str) {
        Some(v) if v == PROTOCOL_VERSION.to_string() => None,
        Some(v) => Some(format!(
            "this server speaks protocol version {PROTOCOL_VERSION}; the client speaks version {v}. Update the client (reload the dashboard, or use the bridge client of this release)."
        )),
        None => Some(format!(
            "this server speaks protocol version {PROTOCOL_VERSION}; the client did not state a version (protocol version 1 clients do not). Connect with `?protocol={PROTOCOL_VERSION}` in the WebSocket URL after updating the client."
        )),
    }
}

/// Accept the upgrade only to send one error frame and close.
pub(super) fn refuse_socket(upgrade: WebSocketUpgrade, frame: Message) -> Response {
    upgrade.on_upgrade(move |mut socket| async move {
        let _ = socket.send(frame).await;
        let _ = socket.send(Message::Close(None)).await;
    })
}

/// The close frame for a receive error that is an inbound message above
/// `max` bytes: code 1009 (Message Too Big) with the sizes; `None` for any
/// other error (the peer went away).
pub(super) fn too_big_close(e: &axum::Error, max: usize) -> Option<Message> {
    use tungstenite::error::CapacityError;
    let inner = std::error::Error::source(e)?.downcast_ref::<tungstenite::Error>()?;
    match inner {
        tungstenite::Error::Capacity(CapacityError::MessageTooLong { size, .. }) => {
            Some(Message::Close(Some(axum::extract::ws::CloseFrame {
                code: axum::extract::ws::close_code::SIZE,
                reason: Utf8Bytes::from(format!(
                    "message of {size} bytes exceeds the limit of {max} bytes"
                )),
            })))
        }
        _ => None,
    }
}
