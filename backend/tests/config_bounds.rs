//! Every numeric config field is bounded (ARCHITECTURE.md, invariant 8): a
//! table test walks every number of a complete run config (paper default,
//! SCPI and bridge tables included) and sets it to ±1e300; each must be
//! refused with an error naming the field. (NaN cannot be written in JSON; in
//! TOML `nan` is refused by the same checks, see the last test.)

mod common;

use common::json_nodes;
use serde_json::{json, Value};
use spintune_server::config::RunConfig;

/// A complete config as JSON: the paper default plus every backend table.
fn full_config() -> Value {
    let mut v = serde_json::to_value(RunConfig::recommended().simulation).unwrap();
    let gates: Vec<String> = spintune::sim::default_gates()
        .into_iter()
        .map(|g| g.name)
        .collect();
    let obj = v.as_object_mut().unwrap();
    obj.insert("driver".into(), json!("scpi"));
    obj.insert("iteration_delay_ms".into(), json!(10));
    obj.insert("targets".into(), json!({ "t_sr": 20.0 }));
    obj.insert("tolerances".into(), json!({ "w": { "absolute": 5.0 } }));
    obj.insert(
        "scpi".into(),
        json!({
            "address": "127.0.0.1:5025",
            "channels": gates.iter().enumerate().map(|(i, g)| (g.clone(), json!(i + 1))).collect::<serde_json::Map<_, _>>(),
            "ramp_step_mv": 1.0,
            "slew_v_per_s": 0.01,
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
    v
}

/// (path as the config errors write it, pointer) of every number in `v`.
fn numbers(v: &Value) -> Vec<(String, String)> {
    json_nodes(v)
        .into_iter()
        .filter(|(_, _, x)| x.is_number())
        .map(|(p, ptr, _)| (p, ptr))
        .collect()
}

#[test]
fn the_full_config_is_valid() {
    RunConfig::from_value(full_config()).unwrap();
}

#[test]
fn every_numeric_field_refuses_huge_values_naming_the_field() {
    let base = full_config();
    let fields = numbers(&base);
    assert!(
        fields.len() > 50,
        "only {} numeric fields found",
        fields.len()
    );
    let mut accepted = Vec::new();
    let mut unnamed = Vec::new();
    for (path, pointer) in &fields {
        for bad in [1e300, -1e300] {
            let mut v = base.clone();
            *v.pointer_mut(pointer).unwrap() = json!(bad);
            match RunConfig::from_value(v) {
                Ok(_) => accepted.push(format!("{path} = {bad:e}")),
                Err(e) => {
                    if !e.0.contains(&format!("`{path}`")) {
                        unnamed.push(format!("{path} = {bad:e}: {e}"));
                    }
                }
            }
        }
    }
    assert!(accepted.is_empty(), "accepted:\n{}", accepted.join("\n"));
    assert!(
        unnamed.is_empty(),
        "errors not naming the field:\n{}",
        unnamed.join("\n")
    );
}

#[test]
fn every_integer_field_but_the_seed_refuses_huge_values_naming_the_field() {
    let base = full_config();
    let fields = numbers(&base);
    let mut accepted = Vec::new();
    let mut unnamed = Vec::new();
    let ints: Vec<_> = fields
        .iter()
        .filter(|(_, p)| base.pointer(p).unwrap().is_u64())
        .collect();
    assert!(ints.len() >= 5, "{ints:?}");
    for (path, pointer) in ints {
        let mut v = base.clone();
        *v.pointer_mut(pointer).unwrap() = json!(u64::MAX);
        match RunConfig::from_value(v) {
            Ok(_) if path == "seed" => {}
            Ok(_) => accepted.push(path.clone()),
            Err(e) if path == "seed" => panic!("seed {}: {e}", u64::MAX),
            Err(e) => {
                if !e.0.contains(&format!("`{path}`")) {
                    unnamed.push(format!("{path}: {e}"));
                }
            }
        }
    }
    assert!(accepted.is_empty(), "accepted:\n{}", accepted.join("\n"));
    assert!(
        unnamed.is_empty(),
        "errors not naming the field:\n{}",
        unnamed.join("\n")
    );
}

#[test]
fn nan_and_infinity_are_refused_naming_the_field() {
    for (doc, field) in [
        (
            "[scpi]\naddress = \"h:1\"\nchannels = { N = 1 }\nramp_step_mv = nan",
            "scpi.ramp_step_mv",
        ),
        (
            "[device]\nelectron_temperature_mk = inf",
            "device.electron_temperature_mk",
        ),
        ("[targets]\nt_sr = -inf", "targets.t_sr"),
        (
            "[bridge]\nreadback_tolerance_mv = nan",
            "bridge.readback_tolerance_mv",
        ),
    ] {
        let e = RunConfig::from_toml_str(doc).unwrap_err();
        assert!(e.0.contains(&format!("`{field}`")), "{doc}: {e}");
    }
}

#[test]
fn sweep_points_and_ramp_plans_are_bounded() {
    // A ramp step that would plan ~1e8 stages is refused before anything runs.
    let e = RunConfig::from_toml_str(
        "driver = \"scpi\"\n[scpi]\naddress = \"h:1\"\nchannels = { N = 1 }\nramp_step_mv = 1e-7",
    )
    .unwrap_err();
    assert!(
        e.0.contains("`scpi.ramp_step_mv`") && e.0.contains("commands"),
        "{e}"
    );
    // Sweep points above the core's bound are refused naming the field.
    let mut v = full_config();
    let mut found = Vec::new();
    let all = numbers(&v);
    for (path, pointer) in &all {
        if path.ends_with("points") {
            found.push((path.clone(), pointer.clone()));
        }
    }
    assert!(!found.is_empty(), "no `points` field in the config");
    for (path, pointer) in found {
        // Above both bounds: the tuner's sweeps (`tuner::MAX_SWEEP_POINTS`) and the simulated scans (100,000).
        *v.pointer_mut(&pointer).unwrap() = json!(100_001);
        let e = RunConfig::from_value(v.clone()).unwrap_err();
        assert!(e.0.contains(&format!("`{path}`")), "{path}: {e}");
        v = full_config();
    }
}

#[test]
fn the_leakage_check_needs_the_qdac2_profile() {
    let e = RunConfig::from_toml_str(
        "driver = \"scpi\"\n[scpi]\naddress = \"h:1\"\nchannels = { N = 1 }\nmax_leakage_na = 100.0",
    )
    .unwrap_err();
    assert!(
        e.0.contains("`scpi.max_leakage_na`") && e.0.contains("qdac2"),
        "{e}"
    );
    let e = RunConfig::from_toml_str(
        "driver = \"scpi\"\n[scpi]\naddress = \"h:1\"\nchannels = { N = 1 }\nprofile = \"keithley\"",
    )
    .unwrap_err();
    assert!(e.0.contains("scpi.profile"), "{e}");
}

/// The core's own validation (used by the Python package and the browser as
/// well) bounds the gate limits and every number of the device model.
#[test]
fn the_core_validation_bounds_gates_and_the_device_model_itself() {
    let base = serde_json::to_value(spintune::driver::SimulationConfig::paper_default()).unwrap();
    let fields = numbers(&base);
    let mut accepted = Vec::new();
    let mut checked = 0;
    for (path, pointer) in &fields {
        let is_gate_number = path.starts_with("tuner.gates[") && !path.ends_with("name");
        if !(path.starts_with("device.") || is_gate_number)
            || base.pointer(pointer).unwrap().is_u64()
        {
            continue;
        }
        for bad in [1e300, -1e300] {
            let mut v = base.clone();
            *v.pointer_mut(pointer).unwrap() = json!(bad);
            let cfg: spintune::driver::SimulationConfig = serde_json::from_value(v).unwrap();
            checked += 1;
            match cfg.validate() {
                Ok(()) => accepted.push(format!("{path} = {bad:e}")),
                Err(e) => assert!(e.to_string().contains(path.as_str()), "{path}: {e}"),
            }
        }
    }
    assert!(checked > 100, "{checked}");
    assert!(
        accepted.is_empty(),
        "the core accepted:\n{}",
        accepted.join("\n")
    );
}

#[test]
fn the_session_read_back_tolerance_is_bounded_in_the_core() {
    use spintune::session::SessionConfig;
    for bad in [
        1e300,
        SessionConfig::MAX_READBACK_TOLERANCE_MV * 1.01,
        -1.0,
        f64::NAN,
    ] {
        let cfg = SessionConfig {
            readback_tolerance_mv: bad,
            ..SessionConfig::default()
        };
        let e = cfg.validate().unwrap_err();
        assert_eq!(e.field, "readback_tolerance_mv", "{bad}: {e}");
    }
    let ok = SessionConfig {
        readback_tolerance_mv: SessionConfig::MAX_READBACK_TOLERANCE_MV,
        ..SessionConfig::default()
    };
    assert_eq!(ok.validate(), Ok(()));
}

/// The core's tuner validation (also the Python package's) bounds every
/// number of the tuner config itself, naming the field.
#[test]
fn the_core_validation_bounds_every_tuner_number_itself() {
    let base =
        serde_json::to_value(spintune::driver::SimulationConfig::paper_default().tuner).unwrap();
    let fields = numbers(&base);
    let mut accepted = Vec::new();
    let mut checked = 0;
    for (path, pointer) in &fields {
        if base.pointer(pointer).unwrap().is_u64() {
            continue;
        }
        for bad in [1e300, -1e300] {
            let mut v = base.clone();
            *v.pointer_mut(pointer).unwrap() = json!(bad);
            let cfg: spintune::tuner::TunerConfig = serde_json::from_value(v).unwrap();
            checked += 1;
            match cfg.validate() {
                Ok(()) => accepted.push(format!("{path} = {bad:e}")),
                Err(e) => assert!(e.to_string().contains(&format!("`{path}`")), "{path}: {e}"),
            }
        }
    }
    assert!(checked > 50, "{checked}");
    assert!(
        accepted.is_empty(),
        "the core accepted:\n{}",
        accepted.join("\n")
    );
}
