//! `spintune config resolve` and the device description, with the real
//! binary: the lab's few-line example resolves to a config that reads back
//! unchanged and tunes the simulated device; a description's error names
//! its field.

use std::path::{Path, PathBuf};
use std::process::Command;

fn spintune(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_spintune"))
        .args(args)
        .output()
        .expect("run spintune")
}

fn example(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples")
        .join(name)
}

fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spintune-resolve-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn stdout_of(out: &std::process::Output) -> String {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout.clone()).unwrap()
}

#[test]
fn resolved_configs_read_back_unchanged() {
    let dir = temp_dir("roundtrip");
    for name in [
        "lab-device.toml",
        "paper-first-target.toml",
        "paper-benchmark-demo.toml",
        "array-lab.toml",
    ] {
        let first = stdout_of(&spintune(&[
            "config",
            "resolve",
            example(name).to_str().unwrap(),
        ]));
        let again_path = dir.join(name);
        std::fs::write(&again_path, &first).unwrap();
        let again = stdout_of(&spintune(&[
            "config",
            "resolve",
            again_path.to_str().unwrap(),
        ]));
        assert_eq!(
            first, again,
            "{name}: the resolved config does not read back unchanged"
        );
        let json: serde_json::Value = serde_json::from_str(&stdout_of(&spintune(&[
            "config",
            "resolve",
            "--json",
            example(name).to_str().unwrap(),
        ])))
        .unwrap();
        assert!(json["tuner"]["levels"]
            .as_array()
            .is_some_and(|l| !l.is_empty()));
    }
}

/// A lab's array (driver `bridge`) resolves without the simulated world it
/// never uses; the same description on the simulator keeps it.
#[test]
fn a_bridge_array_resolves_without_a_simulated_world() {
    let resolved = stdout_of(&spintune(&[
        "config",
        "resolve",
        example("array-lab.toml").to_str().unwrap(),
    ]));
    assert!(resolved.contains("[array.description]"), "{resolved}");
    assert!(!resolved.contains("[array.array"), "{resolved}");
    assert!(!resolved.contains("[array.device"), "{resolved}");

    let dir = temp_dir("bridge-array");
    let on_simulator = dir.join("array-sim.toml");
    let text = std::fs::read_to_string(example("array-lab.toml"))
        .unwrap()
        .replace("driver = \"bridge\"", "driver = \"simulator\"");
    std::fs::write(&on_simulator, text).unwrap();
    let resolved = stdout_of(&spintune(&[
        "config",
        "resolve",
        on_simulator.to_str().unwrap(),
    ]));
    assert!(resolved.contains("[array.array]"), "{resolved}");
    assert!(resolved.contains("[array.device]"), "{resolved}");
}

#[test]
fn the_lab_description_derives_the_levels_and_tunes_the_simulated_device() {
    let json: serde_json::Value = serde_json::from_str(&stdout_of(&spintune(&[
        "config",
        "resolve",
        "--json",
        example("lab-device.toml").to_str().unwrap(),
    ])))
    .unwrap();
    let names: Vec<&str> = json["tuner"]["levels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["qubit", "chemical_potential", "sensing_dot"]);
    let top = &json["tuner"]["levels"][0];
    assert_eq!(top["parameters"][0]["transform"], "log");
    assert_eq!(top["parameters"][0]["target"], 20.0);
    assert_eq!(top["solver"]["max_moves_per_iteration"], 2);

    let dir = temp_dir("run");
    let db = dir.join("runs.db");
    let out = spintune(&[
        "run",
        "--quiet",
        "--config",
        example("lab-device.toml").to_str().unwrap(),
        "--db",
        db.to_str().unwrap(),
    ]);
    let text = stdout_of(&out);
    assert!(text.contains("tuned: yes"), "{text}");
}

#[test]
fn description_errors_name_the_field() {
    let dir = temp_dir("errors");
    let cases = [
        (
            "[description]\ngates = [{ name = \"A\", min_mv = -10, max_mv = 0, initial_mv = -5 }]\nqubit = { gates = [\"A\", \"B\"] }\n",
            "description.qubit.gates[1]",
        ),
        (
            "[description]\ngates = [{ name = \"A\", min_mv = -10, max_mv = 0, initial_mv = -5 }]\nqubit = { gates = [\"A\"], parameters = [\"t_rs\"] }\n",
            "description.qubit.parameters[0]",
        ),
        (
            "[description]\ngates = [{ name = \"A\", min_mv = -10, max_mv = 0, initial_mv = -5 }]\nqubit = { gates = [\"A\"], step_limt_mv = 3 }\n",
            "description.qubit",
        ),
        (
            "[description]\ngates = [{ name = \"A\", min_mv = -10, max_mv = 0, initial_mv = -5 }]\nqubit = { gates = [\"A\"] }\n[tuner]\nlevels = []\n",
            "tuner.levels",
        ),
    ];
    for (i, (text, field)) in cases.iter().enumerate() {
        let path = dir.join(format!("bad{i}.toml"));
        std::fs::write(&path, text).unwrap();
        let out = spintune(&["config", "resolve", path.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(2), "case {i}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(&format!("`{field}")), "case {i}: {err}");
    }
}
