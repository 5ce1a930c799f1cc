//! The simulator's slow drift of t_c and Γ (so of w and t_sr): with the
//! defaults an untouched point leaves a ±10 % band within one to a few lab
//! hours; switched off, nothing drifts; old checkpoints (without the new
//! state) still load.

use spintune::sim::{default_gates, DeviceConfig, DriftState, SimulatedDevice, SlowDrift};

/// Hours until t_sr or w first leaves ±10 % of its value at the start,
/// checked every minute up to `max_h`.
fn exit_hours(config: &DeviceConfig, seed: u64, max_h: f64) -> Option<f64> {
    let mut dev = SimulatedDevice::new(config.clone(), &default_gates(), seed).unwrap();
    let start = dev.truth();
    let mut t = 0.0;
    while t < max_h * 3600.0 {
        dev.idle(60.0);
        t += 60.0;
        let now = dev.truth();
        let off = |a: f64, b: f64| (a / b - 1.0).abs() > 0.1;
        if off(now.t_sr_ns, start.t_sr_ns) || off(now.w_uv, start.w_uv) {
            return Some(t / 3600.0);
        }
    }
    None
}

#[test]
fn an_untouched_point_leaves_its_band_within_one_to_a_few_hours() {
    let config = DeviceConfig::default();
    let mut hours: Vec<f64> = (1..=40)
        .map(|seed| exit_hours(&config, seed, 24.0).unwrap_or(24.0))
        .collect();
    hours.sort_by(f64::total_cmp);
    let median = (hours[19] + hours[20]) / 2.0;
    assert!(
        (0.5..=5.0).contains(&median),
        "median time to leave ±10 %: {median:.2} h ({hours:?})"
    );
    // and it is a drift, not noise: nothing leaves within the first minutes
    assert!(hours[0] > 0.1, "{hours:?}");
}

#[test]
fn without_slow_drift_t_c_and_gamma_stay_put() {
    let mut config = DeviceConfig::default();
    config.noise.slow = SlowDrift::none();
    let mut dev = SimulatedDevice::new(config, &default_gates(), 5).unwrap();
    let start = dev.truth();
    dev.idle(24.0 * 3600.0);
    let end = dev.truth();
    assert_eq!((start.t_sr_ns, start.w_uv), (end.t_sr_ns, end.w_uv));
    assert_eq!(dev.drift().lead_rate_factor(), 1.0);
}

#[test]
fn drift_state_of_an_old_checkpoint_still_loads() {
    let old =
        r#"{"mu_a_mv":0.1,"mu_b_mv":-0.2,"sd_u_mv":0.0,"signal":0.0,"jump_u_mv":0.5,"jumps":2}"#;
    let d: DriftState = serde_json::from_str(old).unwrap();
    assert_eq!(d.jumps, 2);
    assert_eq!(d.tunnel_coupling_factor(), 1.0);
}

#[test]
fn slow_drift_bounds_are_named() {
    let mut config = DeviceConfig::default();
    config.noise.slow.lead_rate_rel = -0.1;
    assert_eq!(
        config.validate().unwrap_err().field,
        "noise.slow.lead_rate_rel"
    );
    let mut config = DeviceConfig::default();
    config.noise.slow.time_s = 0.0;
    assert_eq!(config.validate().unwrap_err().field, "noise.slow.time_s");
}
