//! Property test over generated run configs (issue 20, item 7): start from
//! valid configs (the paper default with every backend table, a simulator
//! config, the example files) and mutate one node — a wrong type, a number
//! out of range, an empty array, an unknown key or name — or delete keys and
//! array entries. Then:
//!
//! * validation never panics, whatever the mutation;
//! * every mutation that makes the config invalid by construction is refused
//!   with an error naming a field at or next to the mutated one;
//! * over HTTP (an in-process server) every such config gets a 4xx whose
//!   body names the field, and no run is created (`GET /api/runs` unchanged).
//!
//! Deterministic (`TestRunner::deterministic`), a few seconds in debug.

mod common;

use common::*;
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::TestRunner;
use serde_json::{json, Value};
use spintune_server::config::RunConfig;

/// Valid configs the mutations start from.
fn bases() -> Vec<Value> {
    let mut full = serde_json::to_value(RunConfig::recommended().simulation).unwrap();
    let gates: Vec<String> = spintune::sim::default_gates()
        .into_iter()
        .map(|g| g.name)
        .collect();
    let obj = full.as_object_mut().unwrap();
    obj.insert("driver".into(), json!("scpi"));
    obj.insert("iteration_delay_ms".into(), json!(10));
    obj.insert("targets".into(), json!({ "t_sr": 20.0, "w": 270.0 }));
    obj.insert(
        "tolerances".into(),
        json!({ "w": { "absolute": 5.0 }, "t_sr": { "relative": 0.1 } }),
    );
    obj.insert(
        "scpi".into(),
        json!({
            "address": "127.0.0.1:5025",
            "channels": gates.iter().enumerate().map(|(i, g)| (g.clone(), json!(i + 1))).collect::<serde_json::Map<_, _>>(),
            "ramp_step_mv": 1.0,
            "readback_tolerance_mv": 0.05,
            "timeout_ms": 2000,
            "settle_ms": 0,
            "measure": "bridge",
            "profile": "qdac2",
            "max_leakage_na": 100.0,
            "max_leakage_na_by_gate": { "SB": 20.0 }
        }),
    );
    obj.insert(
        "bridge".into(),
        json!({ "request_timeout_s": 300.0, "readback_tolerance_mv": 0.05 }),
    );
    obj.get_mut("tuner").unwrap()["schedule"] =
        json!([{ "at_iteration": 3, "targets": { "t_sr": 30.0 } }]);
    let mut simulator = serde_json::to_value(RunConfig::recommended().simulation).unwrap();
    simulator["driver"] = json!("simulator");
    simulator["targets"] = json!({ "t_sr": 20.0 });
    let mut out = vec![full, simulator];
    for example in [
        "paper-first-target.toml",
        "paper-benchmark-demo.toml",
        "array-three-cells.toml",
        "array-lab.toml",
    ] {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../examples")
            .join(example);
        let text = std::fs::read_to_string(&path).unwrap();
        out.push(toml::from_str::<Value>(&text).unwrap());
    }
    for b in &out {
        RunConfig::from_value(b.clone()).unwrap_or_else(|e| panic!("a base is invalid: {e}"));
    }
    out
}

/// Every node of `v`: (path as config errors write it, JSON pointer).
fn nodes(v: &Value) -> Vec<(String, String)> {
    json_nodes(v)
        .into_iter()
        .map(|(p, ptr, _)| (p, ptr))
        .collect()
}

/// Arrays that may be empty in a valid config.
const MAY_BE_EMPTY: [&str; 6] = [
    "after_move",
    "cell_gates",
    "schedule",
    "quadratic_per_mv2",
    "line_a_quadratic",
    "line_b_quadratic",
];

/// Strings that name a thing rather than refer to one (any value is fine).
fn is_free_text(path: &str) -> bool {
    let last = last_key(path);
    last == "name" || last == "unit"
}

fn last_key(path: &str) -> &str {
    let key = path.rsplit('.').next().unwrap_or(path);
    key.split('[').next().unwrap_or(key)
}

/// What one mutation did; `invalid`: the config is invalid by construction.
#[derive(Debug, Clone)]
struct Mutated {
    value: Value,
    path: String,
    what: String,
    invalid: bool,
}

/// Every single mutation of node `pointer` (at `path`) of `base`.
fn mutations_at(base: &Value, path: &str, pointer: &str) -> Vec<Mutated> {
    let node = base.pointer(pointer).unwrap();
    let top = pointer.is_empty();
    let is_seed = path == "seed" || path.ends_with(".seed");
    // (replacement, description, invalid by construction)
    let mut options: Vec<(Value, String, bool)> = Vec::new();
    match node {
        Value::Number(n) => {
            options.push((json!("x"), "a string for a number".into(), true));
            options.push((json!(true), "a bool for a number".into(), true));
            options.push((json!("NaN"), "\"NaN\" for a number".into(), true));
            if !is_seed {
                let huge = if n.is_f64() {
                    json!(-1e300)
                } else {
                    json!(1u64 << 50)
                };
                options.push((huge, "out of range".into(), true));
            }
        }
        Value::String(_) => {
            options.push((json!(7), "a number for a string".into(), true));
            options.push((json!(["x"]), "an array for a string".into(), true));
            if !is_free_text(path) {
                options.push((json!("zz_unknown"), "an unknown name".into(), true));
            }
        }
        Value::Bool(_) => options.push((json!("yes"), "a string for a bool".into(), true)),
        Value::Null => options.push((json!("x"), "a string for null".into(), true)),
        Value::Array(a) => {
            if !a.is_empty() {
                let may = MAY_BE_EMPTY.contains(&last_key(path));
                options.push((json!([]), "emptied".into(), !may));
            }
            if a.len() > 1 {
                let mut shorter = a.clone();
                shorter.pop();
                options.push((Value::Array(shorter), "last entry deleted".into(), false));
            }
            options.push((json!({"x": 1}), "an object for an array".into(), true));
            options.push((json!(3), "a number for an array".into(), true));
        }
        Value::Object(m) => {
            let mut with_unknown = m.clone();
            with_unknown.insert("zz_unknown".into(), json!(1));
            options.push((Value::Object(with_unknown), "an unknown key".into(), true));
            if !top {
                options.push((json!(5), "a number for a table".into(), true));
                options.push((json!("t"), "a string for a table".into(), true));
            }
            for k in m.keys() {
                let mut without = m.clone();
                without.remove(k);
                options.push((Value::Object(without), format!("key {k:?} deleted"), false));
            }
        }
    }
    options
        .into_iter()
        .map(|(replacement, what, invalid)| {
            let mut value = base.clone();
            *value.pointer_mut(pointer).unwrap() = replacement;
            Mutated {
                value,
                path: path.to_string(),
                what,
                invalid,
            }
        })
        .collect()
}

/// Every single mutation of every node of `base`.
fn all_mutations(base: &Value) -> Vec<Mutated> {
    let all = nodes(base);
    all.iter()
        .flat_map(|(path, pointer)| mutations_at(base, path, pointer))
        .collect()
}

/// Mutation `kind` (taken modulo the mutations that fit) of node `pick` of `base`.
fn mutate(base: &Value, pick: prop::sample::Index, kind: usize) -> Mutated {
    let all = nodes(base);
    let (path, pointer) = &all[pick.index(all.len())];
    let mut options = mutations_at(base, path, pointer);
    let n = options.len();
    options.swap_remove(kind % n)
}

/// The field a config error names: the first `…` in the message.
fn named_field(message: &str) -> Option<&str> {
    let start = message.find('`')? + 1;
    let len = message[start..].find('`')?;
    Some(&message[start..start + len])
}

/// Whether `field` is the mutated node, inside it, one of its ancestors, or
/// a sibling (e.g. `compensation.matrix` when `compensation.gates` changed).
fn near(field: &str, mutated: &str) -> bool {
    let parent = |p: &str| -> String {
        match (p.rfind('.'), p.rfind('[')) {
            (Some(d), Some(b)) => p[..d.max(b)].to_string(),
            (Some(i), None) | (None, Some(i)) => p[..i].to_string(),
            (None, None) => String::new(),
        }
    };
    let under = |a: &str, b: &str| {
        b.is_empty() || a == b || a.starts_with(&format!("{b}.")) || a.starts_with(&format!("{b}["))
    };
    let parent = parent(mutated);
    under(field, mutated)
        || (!field.is_empty() && under(mutated, field))
        || (!parent.is_empty() && under(field, &parent))
}

/// Random cases: one mutation, or (one in four) two on top of each other
/// (then only "never panics" and "an error names a field" are checked).
fn random_cases(bases: &[Value], n: u32) -> Vec<Mutated> {
    let strategy = (
        0..bases.len(),
        any::<prop::sample::Index>(),
        any::<usize>(),
        0..4usize,
        any::<prop::sample::Index>(),
        any::<usize>(),
    );
    let mut runner = TestRunner::deterministic();
    (0..n)
        .map(|_| {
            let (b, pick, kind, extra, pick2, kind2) =
                strategy.new_tree(&mut runner).unwrap().current();
            let m = mutate(&bases[b], pick, kind);
            if extra != 0 {
                return m;
            }
            let second = mutate(&m.value, pick2, kind2);
            Mutated {
                value: second.value,
                path: format!("{} + {}", m.path, second.path),
                what: format!("{} + {}", m.what, second.what),
                invalid: false,
            }
        })
        .collect()
}

fn describe(m: &Mutated) -> String {
    format!("`{}` {}", m.path, m.what)
}

#[test]
fn mutated_configs_never_panic_and_invalid_ones_name_the_field() {
    let bases = bases();
    // Every single mutation of every base (complete), then random double ones.
    let mut cases: Vec<Mutated> = bases.iter().flat_map(all_mutations).collect();
    cases.extend(random_cases(&bases, 500));
    let mut accepted = Vec::new();
    let mut unnamed = Vec::new();
    let mut invalid = 0;
    for m in &cases {
        let text = m.value.to_string();
        let parsed = RunConfig::from_json_str(&text);
        if !m.invalid {
            // Deletions may leave a valid config; an error still names a field.
            if let Err(e) = parsed {
                if named_field(&e.0).is_none() {
                    unnamed.push(format!("{}: {e}", describe(m)));
                }
            }
            continue;
        }
        invalid += 1;
        match parsed {
            Ok(_) => accepted.push(describe(m)),
            Err(e) => match named_field(&e.0) {
                Some(f) if near(f, &m.path) => {}
                _ => unnamed.push(format!("{}: {e}", describe(m))),
            },
        }
    }
    assert!(invalid > 2000, "only {invalid} invalid configs generated");
    eprintln!("{} configs, {invalid} invalid by construction", cases.len());
    assert!(
        accepted.is_empty(),
        "{} invalid configs accepted:\n{}",
        accepted.len(),
        accepted.join("\n")
    );
    assert!(
        unnamed.is_empty(),
        "{} errors not naming the mutated field:\n{}",
        unnamed.len(),
        unnamed.join("\n")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_configs_over_http_get_a_4xx_naming_the_field_and_create_no_run() {
    let dir = TempDir::new("config-props");
    let srv = server(&dir, 16).await;
    let count = |body: String| serde_json::from_str::<Vec<Value>>(&body).unwrap().len();
    let before = count(http(srv.addr, "GET", "/api/runs", None, None).await.1);
    let invalid: Vec<Mutated> = random_cases(&bases(), 800)
        .into_iter()
        .filter(|m| m.invalid)
        .collect();
    assert!(
        invalid.len() > 300,
        "only {} invalid configs",
        invalid.len()
    );
    let mut wrong = Vec::new();
    for m in &invalid {
        let body = m.value.to_string();
        let (status, text) = http(srv.addr, "POST", "/api/runs", Some(TOKEN), Some(&body)).await;
        let error = serde_json::from_str::<Value>(&text)
            .ok()
            .and_then(|v| v["error"].as_str().map(str::to_string));
        let named = error
            .as_deref()
            .and_then(named_field)
            .is_some_and(|f| near(f, &m.path));
        if !(400..500).contains(&status) || !named {
            wrong.push(format!("{} → {status} {text}", describe(m)));
        }
    }
    let after = count(http(srv.addr, "GET", "/api/runs", None, None).await.1);
    assert!(
        wrong.is_empty(),
        "{} invalid configs not refused with a 4xx naming the field:\n{}",
        wrong.len(),
        wrong.join("\n")
    );
    assert_eq!(after, before, "runs were created from invalid configs");
}
