//! `spintune bench` and `bench-server` end to end: JSON keys as documented, markdown tables,
//! zero limit violations, clear errors for bad input.

use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_spintune"))
}

/// Run `cmd` and require success (its stderr in the failure message).
fn run_ok(cmd: &mut Command) -> std::process::Output {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

#[test]
fn bench_writes_json_with_the_documented_keys() {
    let dir = std::env::temp_dir().join(format!("spintune-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("bench.json");
    let out = run_ok(
        bin()
            .args([
                "bench",
                "--seeds",
                "1",
                "--strategies",
                "kalman,oracle,oracle-log",
                "--json",
            ])
            .arg(&json),
    );
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(
        table.contains("| kalman |") && table.contains("| oracle |"),
        "{table}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let strategies = v["strategies"].as_array().unwrap();
    assert_eq!(strategies.len(), 3);
    for s in strategies {
        for key in ["iterations_per_change", "lab_minutes_per_change"] {
            assert!(s[key]["median"].is_number(), "{key} in {s}");
            assert!(s[key]["p90"].is_number(), "{key} in {s}");
        }
        assert!(s["iterations_per_change"]["max"].is_number());
        assert!(s["not_converged"].is_u64());
        assert_eq!(s["limit_violations"].as_u64(), Some(0), "{s}");
        assert!(s["failed_fits"].is_u64());
        assert!(s["ratio_to_oracle"].is_number());
        assert!(s["ratio_to_oracle_log"].is_number());
    }
    assert_eq!(strategies[0]["name"], "kalman");
    assert_eq!(strategies[1]["ratio_to_oracle"].as_f64(), Some(1.0));
    assert_eq!(strategies[2]["ratio_to_oracle_log"].as_f64(), Some(1.0));
    // no strategy but the oracles reads the truth; the oracles do
    assert_eq!(strategies[0]["truth_queries"].as_u64(), Some(0));
    assert!(strategies[1]["truth_queries"].as_u64().unwrap() > 0);
    // the Kalman strategy reports its filter consistency, the oracles do not
    for p in ["t_sr", "w"] {
        let c = &strategies[0]["consistency"][p];
        assert!(c["nis_mean"].as_f64().unwrap() > 0.0, "{c}");
        assert!(
            (0.0..=1.0).contains(&c["beyond_2sigma"].as_f64().unwrap()),
            "{c}"
        );
    }
    assert!(strategies[1].get("consistency").is_none());
    assert!(table.contains("NIS mean"), "{table}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_rejects_unknown_strategy_and_bad_device_file() {
    let out = bin()
        .args(["bench", "--seeds", "1", "--strategies", "kalmann"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown strategy \"kalmann\""), "{err}");

    let dir = std::env::temp_dir().join(format!("spintune-bench-dev-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let dev = dir.join("device.toml");
    std::fs::write(&dev, "lever_arm_typo = 3.0\n").unwrap();
    let out = bin()
        .args(["bench", "--seeds", "1", "--device"])
        .arg(&dev)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("lever_arm_typo"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `bench` and `bench-keep` share their device, band and thread options
/// (`bench_runner::DeviceArgs`): both refuse a band that is not a fraction
/// and a device file with an unknown key, naming them, before any seed runs.
#[test]
fn bench_and_bench_keep_check_their_shared_options_alike() {
    let dir = std::env::temp_dir().join(format!("spintune-bench-shared-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let dev = dir.join("device.json");
    std::fs::write(&dev, r#"{"lever_arm_typo": 3.0}"#).unwrap();
    for command in ["bench", "bench-keep"] {
        for tolerance in ["0", "1", "1.5", "nan"] {
            let out = bin()
                .args([command, "--seeds", "1", "--tolerance", tolerance])
                .output()
                .unwrap();
            assert_eq!(
                out.status.code(),
                Some(2),
                "{command} --tolerance {tolerance}"
            );
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                err.contains("--tolerance must be in (0, 1)"),
                "{command}: {err}"
            );
        }
        let out = bin()
            .args([command, "--seeds", "1", "--device"])
            .arg(&dev)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{command} --device");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("lever_arm_typo"), "{command}: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The rows of a markdown table in `stdout` whose first cell is `clients`.
fn rows<'a>(stdout: &'a str, clients: &str) -> Vec<Vec<&'a str>> {
    stdout
        .lines()
        .filter(|l| l.starts_with(&format!("| {clients} |")))
        .map(|l| l.trim_matches('|').split('|').map(str::trim).collect())
        .collect()
}

#[test]
fn bench_server_measures_viewers_in_this_and_in_a_separate_process() {
    let out = bin()
        .args([
            "bench-server",
            "--viewers",
            "3",
            "--rate",
            "40",
            "--seconds",
            "0.5",
            "--clients",
            "both",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for clients in ["separate", "same"] {
        let r = rows(&stdout, clients);
        assert_eq!(r.len(), 1, "{clients}: {stdout}");
        // | clients | viewers | published | achieved Hz | delivered / expected | lagged | p50 | p99 | max | RSS |
        assert_eq!(r[0][1], "3");
        assert_eq!(r[0][2], "20");
        assert_eq!(
            r[0][4], "60 / 60",
            "{clients}: every frame reached every viewer"
        );
        let p50: f64 = r[0][6].parse().unwrap();
        let max: f64 = r[0][8].parse().unwrap();
        assert!(
            p50 > 0.0 && p50 <= max,
            "{clients}: latencies {p50} / {max}"
        );
    }
}

#[test]
fn bench_server_stalled_mode_reports_the_server_memory() {
    let out = bin()
        .args([
            "bench-server",
            "--stalled",
            "4",
            "--rate",
            "40",
            "--seconds",
            "0.5",
            "--full-frames",
            "--clients",
            "separate",
            "--viewer-send-timeout-ms",
            "200",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    let r = rows(&stdout, "separate");
    assert_eq!(r.len(), 1, "{stdout}");
    // | clients | stalled viewers | before MiB | peak MiB | dropped | achieved Hz |
    assert_eq!(r[0][1], "4");
    let before: f64 = r[0][2].parse().unwrap();
    let peak: f64 = r[0][3].parse().unwrap();
    assert!(before > 1.0 && peak >= before, "{before} → {peak}");
    assert!(r[0][4].ends_with("/ 4"), "{stdout}");
}

#[test]
fn bench_server_rejects_bad_numbers_naming_the_flag() {
    for (flag, value) in [("--rate", "0"), ("--seconds", "nan"), ("--viewers", "0")] {
        let out = bin().args(["bench-server", flag, value]).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{flag} {value} was accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(flag), "{flag}: {err}");
    }
}

#[test]
fn bench_keep_runs_a_frontier_point_and_reports_where_the_time_goes() {
    let dir = std::env::temp_dir().join(format!("spintune-bench-keep-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("keep.json");
    let runs = dir.join("runs.json");
    let out = run_ok(
        bin()
            .args([
                "bench-keep",
                "--hours",
                "2",
                "--seeds",
                "1",
                "--threads",
                "1",
                "--strategies",
                "predictive@5%,fixed-25min",
                "--json",
            ])
            .arg(&json)
            .arg("--runs-json")
            .arg(&runs),
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("| predictive@5% |"), "{stdout}");
    assert!(
        stdout.contains("Where the measurement time goes"),
        "{stdout}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let strategies = report["strategies"].as_array().unwrap();
    let names: Vec<&str> = strategies
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["predictive@5%", "fixed-25min"]);
    // the goals are judged on what ran: no `predictive` or `never` here,
    // and the fixed interval is the reference only if it reached 0.99
    let goals = &report["goals"];
    assert!(goals["predictive_in_band"].is_null(), "{goals}");
    assert!(goals["drift_is_real"].is_null(), "{goals}");
    assert_eq!(goals["safe"], true, "{goals}");
    let fixed_in_band = strategies[1]["fraction_in_band"].as_f64().unwrap();
    assert_eq!(
        goals["cheapest_fixed_in_band"].is_null(),
        fixed_in_band < 0.99,
        "{goals}"
    );
    assert!(stdout.contains("Goals (issue 23"), "{stdout}");
    for s in strategies {
        // the parts add up to the measurement time
        let by_kind = s["minutes_per_hour_by_kind"].as_object().unwrap();
        let sum: f64 = by_kind.values().map(|v| v.as_f64().unwrap()).sum();
        let total = s["measurement_minutes_per_hour"].as_f64().unwrap();
        assert!(
            total > 0.0 && (sum - total).abs() < 1e-6 * total.max(1.0),
            "{sum} vs {total}"
        );
        assert!(by_kind.keys().all(|k| k.starts_with("check/")
            || k.starts_with("retune/")
            || k.starts_with("tuning/")));
    }
    // every run, with its day sampled at least every lab minute
    let runs: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&runs).unwrap()).unwrap();
    let runs = runs.as_array().unwrap();
    assert_eq!(runs.len(), 2);
    for r in runs {
        let trace = r["trace"].as_array().unwrap();
        let hours: Vec<f64> = trace
            .iter()
            .map(|s| s["hours"].as_f64().unwrap())
            .filter(|&h| h >= 0.0)
            .collect();
        assert!(hours.windows(2).all(|w| w[1] - w[0] <= 1.0 / 60.0 + 1e-9));
        assert!(*hours.last().unwrap() > 1.9);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_keep_rejects_a_bad_strategy_naming_the_choices() {
    for bad in [
        "predictive@0%",
        "predictive@70%",
        "predictive@2",
        "fixed-0min",
        "fixed-1441min",
        "fixed-2.5min",
        "fixed-5s",
        "fixed-",
        "sometimes",
    ] {
        let out = bin()
            .args([
                "bench-keep",
                "--hours",
                "1",
                "--seeds",
                "1",
                "--strategies",
                bad,
            ])
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{bad}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("unknown keep strategy")
                && err.contains("predictive@P%")
                && err.contains("fixed-Nmin / fixed-Ns (10 s to 1 day)"),
            "{err}"
        );
    }
}

/// `--plot-time` draws a PNG, and the JSON's lab time by kind is whole
/// scans: each kind's mean seconds × the converged changes is a multiple of
/// that scan's lab time on the default device (17, 38, 28, 5 s).
#[test]
fn bench_breaks_a_changes_lab_time_down_by_scan_kind() {
    let dir = std::env::temp_dir().join(format!("spintune-bench-kind-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (json, png) = (dir.join("bench.json"), dir.join("time.png"));
    let out = run_ok(
        bin()
            .args(["bench", "--seeds", "2", "--strategies", "default", "--json"])
            .arg(&json)
            .arg("--plot-time")
            .arg(&png),
    );
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(table.contains("Where a change's lab time goes"), "{table}");
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let s = &v["strategies"][0];
    let converged = (s["changes"].as_u64().unwrap() - s["not_converged"].as_u64().unwrap()) as f64;
    let by = &s["lab_seconds_per_change_by_kind"];
    for (kind, scan_s) in [
        ("sensing_dot", 17.0),
        ("chemical_potential", 38.0),
        ("transition_width", 28.0),
        ("reload_time", 5.0),
    ] {
        let scans = by[kind].as_f64().unwrap_or(0.0) * converged / scan_s;
        assert!(scans > 0.5, "{kind}: {by}");
        assert!(
            (scans - scans.round()).abs() < 1e-6,
            "{kind}: {scans} scans? {by}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `bench-array` end to end on the smallest array: the JSON has the
/// documented keys per strategy, no move was refused and nothing but the
/// oracle read the truth; `--tuning` takes the joint loop's settings from
/// a file (a bad key is refused naming the file and the field).
#[test]
fn bench_array_writes_the_documented_keys_and_reads_tuning_from_a_file() {
    let dir = std::env::temp_dir().join(format!("spintune-bench-array-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("array.json");
    let tuning = dir.join("tuning.toml");
    let plot = dir.join("timeline.png");
    std::fs::write(
        &tuning,
        "line_rounds = 2\nhold_in_band = true\nreset_flat_row_fraction = 0\nreset_stalled_row_after = 3\nstalled_row_from = \"prior\"\n[joint]\nneighbour_prior_fraction = 0.4\ncorrelated_prior = false\nlockstep_correction = true\nexcitation = 0.3\n[line_forecast]\nmax_skips = 2\n",
    )
    .unwrap();
    let out = run_ok(
        bin()
            .args([
                "bench-array",
                "--cells",
                "2",
                "--seeds",
                "1",
                "--strategies",
                "joint",
                "--threads",
                "1",
                "--tuning",
            ])
            .arg(&tuning)
            .arg("--json")
            .arg(&json)
            .arg("--plot")
            .arg(&plot)
            .args(["--trace-cell", "1"]),
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("| joint |"), "{stdout}");
    // cell 1 followed through the run: a line per iteration with units,
    // and a trace at every point of the JSON timeline
    assert!(stdout.contains("Cell 1, joint on device"), "{stdout}");
    assert!(stdout.contains("c1.SB") && stdout.contains(" µV, rows /mV learned ["));
    // each traced line says what the measurement made of the cell, and
    // states its targets beside the truth
    let traced: Vec<&str> = stdout.lines().filter(|l| l.contains("c1.SB")).collect();
    assert!(!traced.is_empty(), "{stdout}");
    for line in &traced {
        assert!(
            ["in band", "out of band", "not measured"]
                .iter()
                .any(|v| line.contains(v)),
            "{line}"
        );
        assert!(
            line.contains(", target ") && line.contains(") ns,"),
            "{line}"
        );
    }
    // …and how often its scans' error bars covered the truth, with a count
    let coverage = stdout
        .lines()
        .find(|l| l.starts_with("Cell 1's scans within 1 reported σ of the truth"))
        .unwrap_or_else(|| panic!("no coverage line: {stdout}"));
    assert!(
        coverage.contains("t_sr ") && coverage.contains(" % of "),
        "{coverage}"
    );
    let png = std::fs::read(&plot).unwrap();
    assert!(png.starts_with(b"\x89PNG"), "--plot wrote no PNG");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let timeline = report["runs"][0]["timeline"].as_array().unwrap();
    assert!(!timeline.is_empty());
    assert!(
        timeline.iter().all(|p| p["trace"]["cell"] == 1),
        "{timeline:?}"
    );
    // the targets traced are the record's: the protocol's set points
    // (positive, one per parameter)
    assert!(
        timeline.iter().all(|p| {
            let t = &p["trace"]["targets"];
            (0..2).all(|i| t[i].as_f64().is_some_and(|x| x > 0.0))
        }),
        "{timeline:?}"
    );
    assert_eq!(report["protocol"]["trace_cell"], 1);
    assert_eq!(
        report["protocol"]["tuning"]["borrow_failed_gradients"],
        true
    );
    // this round's defaults, not in the file: central and pooled initial rows
    assert_eq!(report["protocol"]["tuning"]["central_differences"], true);
    assert_eq!(report["protocol"]["tuning"]["pool_initial_gradients"], true);
    // a cell counts in band on its measurements (the estimate's rules measured no better)
    assert_eq!(report["protocol"]["tuning"]["in_band"], "measured");
    // the file's stalled-row rule
    assert_eq!(report["protocol"]["tuning"]["reset_stalled_row_after"], 3);
    assert_eq!(report["protocol"]["tuning"]["stalled_row_from"], "prior");
    assert_eq!(report["protocol"]["tuning"]["line_rounds"], 2);
    // the line forecast (on by default): the file's field, the rest defaults
    assert_eq!(
        report["protocol"]["tuning"]["line_forecast"]["max_skips"],
        2
    );
    assert_eq!(
        report["protocol"]["tuning"]["line_forecast"]["skip_std"],
        0.3
    );
    // how the cells came into band in the all-cell changes: first ≤ half ≤ every
    let entry = &report["strategies"][0]["change_band_entry"];
    let e: Vec<f64> = (0..3).map(|i| entry[i].as_f64().unwrap()).collect();
    assert!(1.0 <= e[0] && e[0] <= e[1] && e[1] <= e[2], "{entry}");
    assert!(
        stdout.contains("| first cell | half the cells | every cell |"),
        "{stdout}"
    );
    // the learned rows against the truth before the cells came into band:
    // a length ratio and a cosine per parameter
    let rows = &report["strategies"][0]["rows_before_band"];
    for p in 0..2 {
        let (length, cosine) = (rows[p][0].as_f64().unwrap(), rows[p][1].as_f64().unwrap());
        assert!(length > 0.0 && (-1.0..=1.0).contains(&cosine), "{rows}");
    }
    assert!(
        stdout.contains("| t_sr length | t_sr cosine | w length | w cosine |"),
        "{stdout}"
    );
    // the trust region (on by default) reported in the protocol
    assert_eq!(report["protocol"]["tuning"]["joint"]["trust_region"], true);
    assert_eq!(
        report["protocol"]["tuning"]["joint"]["neighbour_prior_fraction"],
        0.4
    );
    // earlier rounds' loop, as docs/array-history.md compares it, and the lockstep
    // correction and the excitation (both off by default) switched on
    assert_eq!(report["protocol"]["tuning"]["hold_in_band"], true);
    assert_eq!(report["protocol"]["tuning"]["reset_flat_row_fraction"], 0.0);
    assert_eq!(
        report["protocol"]["tuning"]["joint"]["correlated_prior"],
        false
    );
    assert_eq!(
        report["protocol"]["tuning"]["joint"]["lockstep_correction"],
        true
    );
    assert_eq!(report["protocol"]["tuning"]["joint"]["excitation"], 0.3);
    let joint = &report["strategies"][0];
    assert_eq!(joint["name"], "joint");
    for key in [
        "cold_start_lab_minutes",
        "lab_minutes_per_change",
        "not_converged",
        "not_converged_where_oracle_converged",
        "neighbours_left_out_of_band",
        "limit_violations",
        "truth_queries",
        "failed_fits",
        "measurements",
    ] {
        assert!(joint.get(key).is_some(), "{key} missing: {joint}");
    }
    assert_eq!(joint["limit_violations"], 0);
    assert_eq!(joint["truth_queries"], 0);
    let by_kind = joint["lab_minutes_by_kind"].as_object().unwrap();
    assert!(
        by_kind["transition_width"].as_f64().unwrap() > 0.0,
        "{by_kind:?}"
    );
    assert!(
        stdout.contains("| strategy | t_sr scans | w scans |"),
        "{stdout}"
    );
    // the timeline is the joint loop's: without it `--plot` is refused
    // before anything runs, and so is a seed that is not run
    for (extra, expected) in [
        (["--strategies", "serial"], "--strategies"),
        (["--plot-seed", "2"], "--plot-seed"),
    ] {
        let out = bin()
            .args(["bench-array", "--cells", "2", "--seeds", "1", "--plot"])
            .arg(&plot)
            .args(extra)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{err}");
    }

    // a tuning file's bad value, unknown key or unknown rule names the
    // flag, the file and the field (a rule: also the rules that exist)
    for (contents, expected) in [
        ("line_rounds = 9\n", &["--tuning", "tuning.line_rounds"][..]),
        ("colour = \"red\"\n", &["tuning.toml", "colour"][..]),
        (
            "in_band = \"estimated\"\n",
            &["in_band", "measured_and_estimate"][..],
        ),
        (
            "reset_stalled_row_after = 1\n",
            &["tuning.reset_stalled_row_after", "1"][..],
        ),
        (
            "stalled_row_from = \"neighbours\"\n",
            &["stalled_row_from", "peers", "widened"][..],
        ),
        (
            "flat_reset_refuted_sigma = 7\n",
            &["tuning.flat_reset_refuted_sigma", "7"][..],
        ),
        (
            "line_max_step_mv = 12.5\n",
            &["tuning.line_max_step_mv", "12.5"][..],
        ),
        (
            "rearm_line_search_after = 31\n",
            &["tuning.rearm_line_search_after", "31"][..],
        ),
        (
            "retreat = \"lines\"\n",
            &["retreat", "every_gate_lines_kept", "tuning_gates"][..],
        ),
        ("t_sr_floor = 0.25\n", &["tuning.t_sr_floor", "0.25"][..]),
    ] {
        std::fs::write(&tuning, contents).unwrap();
        let out = bin()
            .args(["bench-array", "--cells", "2", "--seeds", "1", "--tuning"])
            .arg(&tuning)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{contents}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            expected.iter().all(|e| err.contains(e)),
            "{contents}: {err}"
        );
    }
    // every bound of the array flags, before anything runs; the lab's
    // calibration is two finite numbers, each within [0, 0.9]
    for (value, expected) in [
        ("--cells-per-sensor=17", "--cells-per-sensor"),
        ("--trace-cell=2", "--trace-cell 2: the cells are 0..2"),
        ("--skip-confident-sigma=0.1", "skip_confident_sigma"),
        ("--cross-calibration=0.3", "two numbers"),
        ("--cross-calibration=0.3,x", "not a finite number"),
        ("--cross-calibration=0.3,1.5", "cross_calibration[1]"),
        ("--cross-calibration=-0.1,0", "cross_calibration[0]"),
    ] {
        let out = bin()
            .args(["bench-array", "--cells", "2", "--seeds", "1", value])
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{value}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{value}: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `bench-array --oracle-twin`: the oracle again on seeds N+1..=2N, paired
/// with its own runs on 1..=N. Its counts equal those derived from a plain
/// run of both seeds' oracle (the JSON's phases, paired by hand), its runs
/// stay out of the report's `runs`, and it needs the oracle.
#[test]
fn bench_array_oracle_twin_pairs_the_oracle_with_itself() {
    let dir = std::env::temp_dir().join(format!("spintune-oracle-twin-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (twin_json, plain_json) = (dir.join("twin.json"), dir.join("plain.json"));
    let base = [
        "bench-array",
        "--cells",
        "2",
        "--strategies",
        "oracle",
        "--threads",
        "1",
    ];
    let out = run_ok(
        bin()
            .args(base)
            .args(["--seeds", "1", "--oracle-twin", "--json"])
            .arg(&twin_json),
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("The oracle against itself (noise seeds 2..=2 paired with 1..=1"),
        "{stdout}"
    );
    run_ok(
        bin()
            .args(base)
            .args(["--seeds", "2", "--json"])
            .arg(&plain_json),
    );
    let read = |p: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    };
    let (twin, plain) = (read(&twin_json), read(&plain_json));
    let runs = twin["runs"].as_array().unwrap();
    assert!(runs.iter().all(|r| r["seed"] == 1), "only seed 1 reported");
    // by hand: seed 2's phases against seed 1's on the same device
    let phases = |r: &serde_json::Value| -> Vec<bool> {
        std::iter::once(&r["cold_start_lab_minutes"])
            .chain(r["changes"].as_array().unwrap())
            .chain(r["single_cell_changes"].as_array().unwrap())
            .map(|p| p.is_null())
            .collect()
    };
    let plain_runs = plain["runs"].as_array().unwrap();
    let (mut pairs, mut missed, mut missed_where, mut out_of_band) = (0, 0, 0, 0);
    for t in plain_runs.iter().filter(|r| r["seed"] == 2) {
        let o = plain_runs
            .iter()
            .find(|o| o["seed"] == 1 && o["device"] == t["device"])
            .unwrap();
        // the plain run's seed 1 is the twin report's seed 1
        assert!(runs.iter().any(|r| r == o), "seed 1 as in the plain run");
        pairs += 1;
        let (a, b) = (phases(t), phases(o));
        missed += a.iter().filter(|&&x| x).count();
        missed_where += a.iter().zip(&b).filter(|(x, y)| **x && !**y).count();
        out_of_band += t["neighbours_left_out_of_band"].as_u64().unwrap();
    }
    let t = &twin["oracle_twin"];
    assert_eq!(t["runs"], pairs);
    assert_eq!(t["not_converged"], missed);
    assert_eq!(t["not_converged_where_oracle_converged"], missed_where);
    assert_eq!(t["neighbours_left_out_of_band"], out_of_band);
    // without the oracle it is refused before anything runs
    let out = bin()
        .args([
            "bench-array",
            "--cells",
            "2",
            "--seeds",
            "1",
            "--strategies",
            "joint",
            "--oracle-twin",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--oracle-twin"));
    let _ = std::fs::remove_dir_all(&dir);
}
