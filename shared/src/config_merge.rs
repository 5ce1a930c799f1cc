//! The merge rule of partial run configs (TOML files, JSON bodies, Python
//! dicts): every key is optional and is merged into the default, objects key
//! by key, anything else (arrays included) replaces the default whole, and an
//! object whose tag (`kind`, `type`, …) differs from the default's is another
//! enum variant and replaces it whole. One rule for the server, the CLI and
//! the Python package.

use serde_json::Value;

/// Keys that name the variant of an internally tagged enum.
pub const TAG_KEYS: [&str; 6] = ["kind", "type", "state", "action", "request", "response"];

/// Merge `user` into `base` by the rule above.
///
/// ```
/// use serde_json::json;
/// let mut base = json!({"seed": 1, "tuner": {"max_iterations": null, "stop_when_tuned": false},
///                       "est": {"kind": "kalman", "q": 0.1}});
/// spintune::config_merge::merge(&mut base, json!({"tuner": {"max_iterations": 5},
///                                                  "est": {"kind": "broyden"}}));
/// assert_eq!(base, json!({"seed": 1, "tuner": {"max_iterations": 5, "stop_when_tuned": false},
///                         "est": {"kind": "broyden"}}));
/// ```
pub fn merge(base: &mut Value, user: Value) {
    match (base, user) {
        (Value::Object(b), Value::Object(u)) => {
            let other_variant = TAG_KEYS.iter().any(|k| match (b.get(*k), u.get(*k)) {
                (Some(x), Some(y)) => x != y,
                _ => false,
            });
            if other_variant {
                *b = u;
                return;
            }
            for (k, v) in u {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, u) => *slot = u,
    }
}
