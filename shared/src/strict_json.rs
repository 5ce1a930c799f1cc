//! Strict JSON for everything that crosses a process boundary (REST bodies,
//! viewer and bridge frames; the Python package may use the same parser):
//!
//! * exactly **one** JSON value, then only whitespace — `{"action":"pause"}
//!   {"action":"stop"}` or an `auth` frame followed by garbage is refused
//!   as a whole, never half-applied ([`parse_value`]);
//! * no key the target type does not have, at any depth — also on unit
//!   variants of internally tagged enums, where serde ignores
//!   `deny_unknown_fields` ([`parse_strict`]);
//! * errors name the offending field ([`ProtocolError`]).
//!
//! ```
//! use spintune::protocol::{ControlCommand, ProtocolError};
//! use spintune::strict_json::parse_strict;
//! let c: ControlCommand = parse_strict(r#" {"action":"pause"} "#).unwrap();
//! assert_eq!(c, ControlCommand::Pause);
//! let e = parse_strict::<ControlCommand>(r#"{"action":"pause"}{"action":"stop"}"#).unwrap_err();
//! assert!(e.to_string().contains("trailing characters"), "{e}");
//! let e = parse_strict::<ControlCommand>(r#"{"action":"pause","extra":1}"#).unwrap_err();
//! assert_eq!(e, ProtocolError::UnknownField { field: "extra".into() });
//! ```

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

use crate::protocol::ProtocolError;

/// Parse exactly one JSON value from `text`; anything but whitespace after
/// it is refused (`trailing characters at line L column C`). Errors inside
/// the value name its path.
pub fn parse_value(text: &str) -> Result<Value, ProtocolError> {
    let mut de = serde_json::Deserializer::from_str(text);
    let value: Value = serde_path_to_error::deserialize(&mut de).map_err(malformed)?;
    de.end().map_err(|e| {
        ProtocolError::malformed(
            "",
            format!("{e} (one JSON value per message: nothing may follow it)"),
        )
    })?;
    Ok(value)
}

/// Parse one `T` from `text` strictly: [`parse_value`], then deserialize
/// with the path of any offending field, then refuse keys that `T` does not
/// have (found by comparing with the re-serialized value).
pub fn parse_strict<T: DeserializeOwned + Serialize>(text: &str) -> Result<T, ProtocolError> {
    from_value_strict(parse_value(text)?)
}

/// [`parse_strict`] for a value already parsed (e.g. by [`parse_value`]).
pub fn from_value_strict<T: DeserializeOwned + Serialize>(raw: Value) -> Result<T, ProtocolError> {
    let typed: T = serde_path_to_error::deserialize(&raw).map_err(malformed)?;
    let back = serde_json::to_value(&typed).map_err(|e| ProtocolError::malformed("", e))?;
    unknown_keys(&raw, &back, "")?;
    Ok(typed)
}

fn unknown_keys(raw: &Value, known: &Value, path: &str) -> Result<(), ProtocolError> {
    if let (Value::Object(r), Value::Object(k)) = (raw, known) {
        for (key, v) in r {
            let here = if path.is_empty() {
                key.clone()
            } else {
                format!("{path}.{key}")
            };
            match k.get(key) {
                None => return Err(ProtocolError::UnknownField { field: here }),
                Some(kv) => unknown_keys(v, kv, &here)?,
            }
        }
    }
    Ok(())
}

fn malformed<E: std::fmt::Display>(e: serde_path_to_error::Error<E>) -> ProtocolError {
    ProtocolError::malformed(&e.path().to_string(), e.inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{BridgeClientMessage, ClientMessage, ControlCommand};

    #[test]
    fn one_value_then_only_whitespace() {
        assert_eq!(parse_value(" \n{\"a\":1}\r\n\t ").unwrap()["a"], 1);
        for text in [
            r#"{"action":"pause"}{"action":"stop"}"#,
            r#"{"action":"pause"} x"#,
            r#"{"action":"pause"},"#,
            r#"{"action":"pause"}]"#,
            "1 2",
            "{}\u{0}",
        ] {
            let e = parse_value(text).unwrap_err();
            assert!(e.to_string().contains("trailing characters"), "{text}: {e}");
            assert!(parse_strict::<ControlCommand>(text).is_err(), "{text}");
        }
    }

    #[test]
    fn auth_frames_followed_by_garbage_are_refused() {
        let ok: ClientMessage = parse_strict(r#"{"type":"auth","token":"t"}"#).unwrap();
        assert_eq!(ok, ClientMessage::Auth { token: "t".into() });
        assert!(parse_strict::<ClientMessage>(r#"{"type":"auth","token":"t"}garbage"#).is_err());
        assert!(parse_strict::<BridgeClientMessage>(r#"{"type":"auth","token":"t"} {"#).is_err());
    }

    #[test]
    fn errors_name_the_field() {
        #[derive(Debug, serde::Deserialize, Serialize)]
        struct Outer {
            inner: Inner,
        }
        #[derive(Debug, serde::Deserialize, Serialize)]
        struct Inner {
            x: f64,
        }
        let e = parse_strict::<Outer>(r#"{"inner":{"x":"high"}}"#).unwrap_err();
        assert!(e.to_string().contains("at `inner.x`"), "{e}");
        let e = parse_strict::<ClientMessage>(
            r#"{"type":"control","command":{"action":"stop","now":true}}"#,
        )
        .unwrap_err();
        assert_eq!(
            e,
            ProtocolError::UnknownField {
                field: "command.now".into()
            }
        );
    }
}
