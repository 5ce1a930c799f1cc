//! `GET /api/runs/{id}/config` without the token: the config with instrument
//! addresses, channel maps and anything secret-looking replaced by
//! [`REDACTED`] (the tuner, device model and limits stay visible: the
//! dashboard shows them).

use serde_json::Value;

use crate::config::RunConfig;

/// What a redacted value reads.
pub const REDACTED: &str = "<redacted>";

/// Keys (at any depth) whose values are always redacted.
const SECRET_KEYS: [&str; 4] = ["token", "password", "secret", "api_key"];

/// Keys of `backend.scpi` that locate or wire the instrument.
const INSTRUMENT_KEYS: [&str; 2] = ["address", "channels"];

/// The redacted JSON form of `config`.
pub fn config(config: &RunConfig) -> Value {
    let mut v = serde_json::to_value(config).unwrap_or(Value::Null);
    if let Some(scpi) = v
        .get_mut("backend")
        .and_then(|b| b.get_mut("scpi"))
        .and_then(Value::as_object_mut)
    {
        for key in INSTRUMENT_KEYS {
            if let Some(x) = scpi.get_mut(key) {
                *x = Value::String(REDACTED.into());
            }
        }
    }
    redact_secrets(&mut v);
    v
}

fn redact_secrets(v: &mut Value) {
    match v {
        Value::Object(map) => {
            for (k, x) in map.iter_mut() {
                let k = k.to_ascii_lowercase();
                if SECRET_KEYS.iter().any(|s| k.contains(s)) {
                    *x = Value::String(REDACTED.into());
                } else {
                    redact_secrets(x);
                }
            }
        }
        Value::Array(items) => items.iter_mut().for_each(redact_secrets),
        _ => {}
    }
}
