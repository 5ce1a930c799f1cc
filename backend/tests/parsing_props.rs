//! Property tests: config and message parsing never panic, whatever the input.

use proptest::prelude::*;
use spintune_server::config::RunConfig;
use spintune_server::server::{parse_client_message, parse_control};

/// JSON-ish text built from the protocol's own vocabulary, so that the parser
/// gets past the first character often.
fn jsonish() -> impl Strategy<Value = String> {
    let atoms = prop::sample::select(vec![
        "{",
        "}",
        "[",
        "]",
        ":",
        ",",
        "\"type\"",
        "\"auth\"",
        "\"control\"",
        "\"command\"",
        "\"action\"",
        "\"pause\"",
        "\"set_target\"",
        "\"parameter\"",
        "\"target\"",
        "\"tolerance\"",
        "\"relative\"",
        "\"absolute\"",
        "\"token\"",
        "\"seed\"",
        "\"tuner\"",
        "\"levels\"",
        "\"gates\"",
        "\"device\"",
        "\"targets\"",
        "\"t_sr\"",
        "\"w\"",
        "null",
        "true",
        "1",
        "-1",
        "1e308",
        "1e999",
        "0.5",
        "\"x\"",
        "\"max_iterations\"",
        "\"kind\"",
        "\"newton\"",
    ]);
    prop::collection::vec(atoms, 0..40).prop_map(|v| v.concat())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn client_messages_never_panic(s in any::<String>(), t in jsonish()) {
        let _ = parse_client_message(&s);
        let _ = parse_client_message(&t);
        let _ = parse_control(&s);
        let _ = parse_control(&t);
    }

    #[test]
    fn configs_never_panic(s in any::<String>(), t in jsonish()) {
        let _ = RunConfig::from_json_str(&s);
        let _ = RunConfig::from_json_str(&t);
        let _ = RunConfig::from_toml_str(&s);
    }

    #[test]
    fn toml_configs_with_random_values_never_panic(
        seed in any::<i64>(),
        max in any::<i64>(),
        target in any::<f64>(),
        key in "[a-z_]{1,8}",
    ) {
        let text = format!("seed = {seed}\n[tuner]\nmax_iterations = {max}\n[targets]\n{key} = {target:?}\n");
        let _ = RunConfig::from_toml_str(&text);
        let text = format!("[tolerances]\nw = {{ relative = {target:?} }}\n");
        let _ = RunConfig::from_toml_str(&text);
    }

    #[test]
    fn replay_inputs_never_panic(s in any::<String>(), t in jsonish()) {
        for x in [&s, &t] {
            if let Ok(input) = spintune_server::replay::parse(x) {
                let _ = spintune_server::replay::replay(&input);
            }
        }
    }

    #[test]
    fn valid_targets_roundtrip(target in 1.0f64..500.0, rel in 0.0f64..1.0) {
        let msg = format!(
            r#"{{"type":"control","command":{{"action":"set_target","parameter":"w","target":{target:?},"tolerance":{{"relative":{rel:?}}}}}}}"#
        );
        prop_assert!(parse_client_message(&msg).is_ok(), "{}", msg);
    }
}
