//! What a run broadcasts to its viewers: a [`ViewerUpdate`] is the
//! pre-serialized JSON of one [`spintune::protocol::ServerMessage`], shared
//! (not copied) between all viewers, with its typed [`RunEvent`]; and the
//! hand-built `iteration`/`history` messages around records that are already
//! serialized (the same bytes that were stored).
//!
//! An iteration is serialized twice, once: as a *summary* (the record with
//! `scans` empty, what viewers get by default) and in full (for viewers that
//! subscribed to scans). Both texts are `Utf8Bytes` (reference-counted):
//! every viewer's socket is handed the same bytes.

use std::sync::Arc;

use axum::extract::ws::Utf8Bytes;
use spintune::protocol::{Alert, IterationRecord, RunSummary, ServerMessage};

/// One update broadcast to a run's viewers: the JSON text for sockets (one
/// WebSocket text frame), and the same content typed for in-process
/// observers (the headless CLI), so nobody re-parses JSON.
#[derive(Debug, Clone)]
pub struct ViewerUpdate {
    /// For an iteration: the record's position in the store (0-based).
    pub seq: Option<u64>,
    /// JSON text of the `ServerMessage`; for an iteration the record's
    /// *summary* (`scans` empty).
    pub text: Utf8Bytes,
    /// For an iteration: the message with the full record (scans and
    /// fits), for viewers that subscribed to scans.
    pub full: Option<Utf8Bytes>,
    /// What the update says, typed.
    pub event: RunEvent,
}

/// The typed content of a [`ViewerUpdate`].
#[derive(Debug, Clone)]
pub enum RunEvent {
    /// A committed iteration.
    Iteration(Arc<IterationRecord>),
    /// The run's status changed.
    Status(RunSummary),
    /// The run raised an alert (on the run's alert channel, to viewers
    /// that subscribed to alerts).
    Alert(Alert),
    /// Anything else (errors, notices).
    Other,
}

impl ViewerUpdate {
    /// An update of any server message (no seq).
    pub fn message(msg: &ServerMessage) -> Self {
        let event = match msg {
            ServerMessage::Status { run } => RunEvent::Status(run.clone()),
            ServerMessage::Iteration { record } => RunEvent::Iteration(Arc::new(record.clone())),
            ServerMessage::Alert { alert, .. } => RunEvent::Alert(alert.clone()),
            _ => RunEvent::Other,
        };
        Self {
            seq: None,
            full: None,
            text: Utf8Bytes::from(serde_json::to_string(msg).expect("ServerMessage serializes")),
            event,
        }
    }
}

/// `{"type":"iteration","record":…}` built around an already serialized record,
/// identical to serializing `ServerMessage::Iteration`.
pub fn iteration_message_json(record_json: &str) -> String {
    format!("{{\"type\":\"iteration\",\"record\":{record_json}}}")
}

/// `{"type":"history","records":[…],"more_before":…}` from serialized records.
pub fn history_message_json<S: AsRef<str>>(records_json: &[S], more_before: bool) -> String {
    let mut s = String::with_capacity(
        40 + records_json
            .iter()
            .map(|r| r.as_ref().len() + 1)
            .sum::<usize>(),
    );
    s.push_str("{\"type\":\"history\",\"records\":[");
    for (i, r) in records_json.iter().enumerate() {
        if i > 0 {
            s.push(',');
        }
        s.push_str(r.as_ref());
    }
    s.push_str("],\"more_before\":");
    s.push_str(if more_before { "true" } else { "false" });
    s.push('}');
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::Value;

    #[test]
    fn hand_built_messages_match_serde() {
        let rec = r#"{"iteration":3}"#;
        let v: Value = serde_json::from_str(&iteration_message_json(rec)).unwrap();
        assert_eq!(v["type"], "iteration");
        assert_eq!(v["record"]["iteration"], 3);
        let h: Value = serde_json::from_str(&history_message_json(
            &[rec.to_string(), rec.to_string()],
            true,
        ))
        .unwrap();
        assert_eq!(h["records"].as_array().unwrap().len(), 2);
        assert_eq!(h["more_before"], true);
        let empty = serde_json::to_string(&ServerMessage::History {
            records: vec![],
            more_before: false,
        })
        .unwrap();
        assert_eq!(history_message_json::<String>(&[], false), empty);
    }
}
