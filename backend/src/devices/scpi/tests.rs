//! Unit tests of the SCPI driver.

use std::collections::BTreeMap;

use super::config::{default_ramp_step_mv, default_readback_tolerance_mv, default_timeout_ms};
use super::*;
use crate::devices::DeviceError;

/// A config with the defaults of a run config, `generic` profile, no
/// leakage check.
fn config(address: &str, channels: &[(&str, u32)]) -> ScpiConfig {
    ScpiConfig {
        address: address.into(),
        channels: channels.iter().map(|(g, c)| (g.to_string(), *c)).collect(),
        ramp_step_mv: default_ramp_step_mv(),
        slew_v_per_s: None,
        readback_tolerance_mv: default_readback_tolerance_mv(),
        timeout_ms: default_timeout_ms(),
        settle_ms: 0,
        measure: MeasureSource::Simulator,
        profile: Default::default(),
        max_leakage_na: None,
        max_leakage_na_by_gate: BTreeMap::new(),
    }
}

#[test]
fn ramp_increments_never_exceed_the_step_and_end_on_target() {
    let present = BTreeMap::from([("A".to_string(), -780.0), ("B".to_string(), 10.0)]);
    let target = BTreeMap::from([("A".to_string(), -777.5), ("B".to_string(), 10.0)]);
    let stages = plan_ramp(&present, &target, 1.0);
    assert_eq!(stages.len(), 3);
    assert!(stages.iter().all(|s| s.len() == 1 && s[0].0 == "A"));
    assert_eq!(stages[2][0].1, -777.5);
    let mut prev = -780.0;
    for s in &stages {
        assert!((s[0].1 - prev).abs() <= 1.0 + 1e-12);
        prev = s[0].1;
    }
    // exactly one step's worth: one command
    let t = BTreeMap::from([("A".to_string(), -779.0)]);
    assert_eq!(plan_ramp(&present, &t, 1.0).len(), 1);
    // nothing to do
    assert!(plan_ramp(&present, &present, 1.0).is_empty());
}

#[test]
fn config_errors_name_the_field_within_the_scpi_table() {
    let gates = spintune::sim::default_gates();
    let cfg = |channels: &[(&str, u32)]| config("127.0.0.1:5025", channels);
    assert_eq!(cfg(&[("N", 1), ("SB", 4)]).validate(&gates), Ok(()));
    let e = cfg(&[("NOPE", 1)]).validate(&gates).unwrap_err();
    assert_eq!(e.field, "channels.NOPE");
    assert!(e.message.contains("\"NOPE\" is not a gate"), "{e}");
    let e = cfg(&[("N", 2), ("SB", 2)]).validate(&gates).unwrap_err();
    assert_eq!(e.field, "channels.SB");
    assert_eq!(e.message, "channel 2 is already used by \"N\"");
    assert_eq!(e.within("scpi").field, "scpi.channels.SB");
    let mut c = cfg(&[("N", 1)]);
    c.ramp_step_mv = f64::NAN;
    let e = c.validate(&gates).unwrap_err();
    assert_eq!(
        e.to_string(),
        "invalid config at `ramp_step_mv`: must be a positive number of mV, at most 1000, got NaN"
    );
    c.ramp_step_mv = 1e-7;
    let e = c.validate(&gates).unwrap_err();
    assert_eq!(e.field, "ramp_step_mv");
    assert!(e.to_string().contains("more than 1000 commands"), "{e}");
    c.ramp_step_mv = 1.0;
    c.timeout_ms = 0;
    assert_eq!(c.validate(&gates).unwrap_err().field, "timeout_ms");
    c.timeout_ms = 1;
    c.address = "localhost".into();
    assert_eq!(c.validate(&gates).unwrap_err().field, "address");
}

#[test]
fn per_gate_leakage_limits_override_the_default_and_are_validated() {
    let gates = spintune::sim::default_gates();
    let mut c = ScpiConfig {
        profile: ScpiProfile::Qdac2,
        max_leakage_na_by_gate: BTreeMap::from([("SB".to_string(), 20.0)]),
        ..config("127.0.0.1:5025", &[("N", 1), ("SB", 4)])
    };
    assert_eq!(c.validate(&gates), Ok(()));
    // Only the named gate is checked without a default...
    assert_eq!(
        c.leakage_limit_na("SB"),
        Some(("max_leakage_na_by_gate.SB".to_string(), 20.0))
    );
    assert_eq!(c.leakage_limit_na("N"), None);
    // ...and with one, the others get the default.
    c.max_leakage_na = Some(100.0);
    assert_eq!(
        c.leakage_limit_na("N"),
        Some(("max_leakage_na".to_string(), 100.0))
    );
    assert_eq!(c.leakage_limit_na("SB").map(|l| l.1), Some(20.0));
    // A gate that is not mapped, a bad value, or the generic profile: errors naming the key.
    c.max_leakage_na_by_gate.insert("PA".into(), 5.0);
    let e = c.validate(&gates).unwrap_err();
    assert_eq!(e.field, "max_leakage_na_by_gate.PA");
    assert!(e.message.contains("not a gate of `channels`"), "{e}");
    c.max_leakage_na_by_gate.remove("PA");
    c.max_leakage_na_by_gate.insert("SB".into(), -1.0);
    assert_eq!(
        c.validate(&gates).unwrap_err().field,
        "max_leakage_na_by_gate.SB"
    );
    c.max_leakage_na_by_gate.insert("SB".into(), 20.0);
    c.max_leakage_na = None;
    c.profile = ScpiProfile::Generic;
    let e = c.validate(&gates).unwrap_err();
    assert_eq!(e.field, "max_leakage_na_by_gate.SB");
    assert!(e.message.contains("qdac2"), "{e}");
}

#[tokio::test]
async fn refusals_and_connection_failures_are_typed() {
    let gates = spintune::sim::default_gates();
    // A port nobody listens on (bound, then released).
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let cfg = ScpiConfig {
        timeout_ms: 500,
        ..config(&addr.to_string(), &[("SB", 4)])
    };
    let mut src = ScpiSource::new(cfg, &gates);
    assert_eq!(
        src.set(&BTreeMap::from([("N".to_string(), -700.0)])).await,
        Err(DeviceError::Unmapped { gate: "N".into() })
    );
    assert!(matches!(
        src.set(&BTreeMap::from([("SB".to_string(), 1e6)])).await,
        Err(DeviceError::Refused(_))
    ));
    let e = src.read(&["SB".to_string()]).await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Connect { address, .. } if *address == addr.to_string()),
        "{e:?}"
    );
    assert!(
        e.to_string().starts_with("cannot connect to 127.0.0.1:"),
        "{e}"
    );
    assert!(!src.is_connected());
}

#[test]
fn instrument_numbers_are_finite_and_not_scpi_special_values() {
    assert_eq!(scpi_number(" -0.75 "), Some(-0.75));
    assert_eq!(scpi_number("9.91E37"), None);
    assert_eq!(scpi_number("-9.9e37"), None);
    assert_eq!(scpi_number("nan"), None);
    assert_eq!(scpi_number("1 V"), None);
}

#[test]
fn commands_are_in_volts() {
    assert_eq!(set_command(4, -777.5), "sour4:volt -0.777500");
    assert_eq!(query_command(12), "sour12:volt?");
    assert_eq!(slew_command(1, 0.5), "sour1:volt:slew 0.5");
}
