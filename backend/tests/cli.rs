//! The binary's offline subcommands: replay (good and malformed input, exit
//! code 2) and config errors.

mod common;

fn spintune(args: &[&str]) -> std::process::Output {
    common::spintune()
        .args(args)
        .output()
        .expect("run spintune")
}

fn temp_file(name: &str, text: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("spintune-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn replay_prints_one_line_per_update() {
    let p = temp_file(
        "good.json",
        r#"{"gates":["SB","T"],"initial_gradient":[0.5,-0.5],
            "initial_covariance":[[1,0],[0,1]],"process_noise":[[0.01,0],[0,0.01]],
            "outlier_sigma":null,
            "steps":[{"voltages":[0,0],"value":10,"variance":0.1},
                     {"voltages":[1,0],"value":12,"variance":0.1},
                     {"voltages":[1,2],"value":11,"variance":0.2}]}"#,
    );
    let out = spintune(&["replay", p.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2);
    assert_eq!(lines[0]["step"], 1);
    assert_eq!(lines[1]["step"], 2);
    assert_eq!(lines[1]["gradient"].as_array().unwrap().len(), 2);
    assert_eq!(lines[1]["covariance"].as_array().unwrap().len(), 2);
    // Same numbers as the core's filter called directly.
    use nalgebra::{DMatrix, DVector};
    use spintune::kalman::{KalmanGradient, ProcessNoise};
    let mut f = KalmanGradient::new(
        DVector::from_vec(vec![0.5, -0.5]),
        DMatrix::identity(2, 2),
        ProcessNoise::Constant {
            q: DMatrix::identity(2, 2) * 0.01,
        },
    )
    .unwrap();
    f.update(&DVector::from_vec(vec![1.0, 0.0]), 2.0, 0.2)
        .unwrap();
    f.update(
        &DVector::from_vec(vec![0.0, 2.0]),
        -1.0,
        0.30000000000000004,
    )
    .unwrap();
    assert_eq!(lines[1]["gradient"][0].as_f64().unwrap(), f.gradient()[0]);
    assert_eq!(
        lines[1]["covariance"][0][1].as_f64().unwrap(),
        f.covariance()[(0, 1)]
    );
}

#[test]
fn replay_rejects_bad_input_with_exit_code_2() {
    for (name, text, needle) in [
        ("syntax.json", "{not json", "invalid replay input"),
        (
            "unknown.json",
            r#"{"gates":["a"],"initial_gradient":[1],"initial_covariance":[[1]],"process_noise":[[0]],"outlier_sigma":null,"steps":[],"q":1}"#,
            "q",
        ),
        (
            "dims.json",
            r#"{"gates":["a","b"],"initial_gradient":[1,2],"initial_covariance":[[1]],"process_noise":[[0,0],[0,0]],"outlier_sigma":null,"steps":[]}"#,
            "initial_covariance",
        ),
        (
            "negvar.json",
            r#"{"gates":["a"],"initial_gradient":[1],"initial_covariance":[[1]],"process_noise":[[0]],"outlier_sigma":null,"steps":[{"voltages":[0],"value":1,"variance":-1}]}"#,
            "steps[0].variance",
        ),
        (
            "notpsd.json",
            r#"{"gates":["a"],"initial_gradient":[1],"initial_covariance":[[-1]],"process_noise":[[0]],"outlier_sigma":null,"steps":[]}"#,
            "covariance",
        ),
    ] {
        let p = temp_file(name, text);
        let out = spintune(&["replay", p.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(2), "{name}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{name}: {err}");
        assert!(out.stdout.is_empty(), "{name}");
    }
    let out = spintune(&["replay", "/nonexistent/file.json"]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn run_rejects_a_bad_config_naming_the_field() {
    let p = temp_file("bad.toml", "seed = \"one\"\n");
    let out = spintune(&[
        "run",
        "--config",
        p.to_str().unwrap(),
        "--db",
        "/nonexistent/x.db",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("seed"));
}

#[test]
fn run_with_targets_over_empty_levels_exits_2_naming_the_field() {
    // Issue 20 item 7: this config panicked (exit 101) while applying the targets.
    for (name, text, field) in [
        (
            "empty-levels.toml",
            "[targets]\nt_sr = 20.0\n[tuner]\nlevels = []\n",
            "tuner.levels",
        ),
        (
            "late-delay.toml",
            "iteration_delay_ms = 3600001\n",
            "iteration_delay_ms",
        ),
        (
            "device-gate.toml",
            "[device.reference_mv]\nNOPE = 1.0\n",
            "device.reference_mv.NOPE",
        ),
    ] {
        let p = temp_file(name, text);
        let out = spintune(&[
            "run",
            "--config",
            p.to_str().unwrap(),
            "--db",
            "/nonexistent/x.db",
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(&format!("`{field}`")), "{name}: {err}");
        assert!(!err.contains("panicked"), "{name}: {err}");
    }
}

#[test]
fn serve_refuses_an_iteration_delay_above_its_bound() {
    let out = spintune(&[
        "serve",
        "--iteration-delay-ms",
        "3600001",
        "--bind",
        "127.0.0.1:0",
        "--demo",
        "never",
        "--db",
        "/nonexistent/x.db",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--iteration-delay-ms 3600001"), "{err}");
}

#[test]
fn headless_run_refuses_a_bridge_config() {
    let dir = std::env::temp_dir().join(format!("spintune-cli-bridge-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("bridge.toml");
    std::fs::write(&cfg, "driver = \"bridge\"\n").unwrap();
    let out = common::spintune()
        .args(["run", "--quiet", "--db"])
        .arg(dir.join("x.db"))
        .arg("--config")
        .arg(&cfg)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("spintune serve"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
