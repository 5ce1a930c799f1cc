//! The SCPI DC-source driver against a simulated instrument: a TCP server on
//! 127.0.0.1 that speaks the same SCPI subset (`sour{ch}:volt V`,
//! `sour{ch}:volt?`, `sour{ch}:volt:slew V/s`, and the QDAC-II's
//! `sour{ch}:volt:mode fix`, `sour{ch}:volt:last?`, `read{ch}?`), records
//! every command and misbehaves on demand (drops the connection, answers
//! late, reports a different voltage, leaves a channel in list mode, leaks
//! current). Like a QDAC-II, a channel in list mode keeps its output when
//! `sour{ch}:volt` changes the fixed set point, and `volt?` echoes the set
//! point while `volt:last?` reads the output. Everything is bounded in time.

mod common;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use serde_json::json;
use spintune::protocol::{RunStatus, RunSummary};
use spintune::safety::GateSpec;
use spintune::sim::default_gates;
use spintune_server::cli::Server;
use spintune_server::config::{MeasureSource, ScpiConfig, ScpiProfile};
use spintune_server::DeviceError;
use spintune_server::ScpiSource;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;

/// A misbehaviour, armed to happen after `after_sets` more set commands.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    /// Close the connection on receiving the set command, without applying it.
    Drop,
    /// Answer the next query only after this delay.
    Late(Duration),
    /// Answer the next query with the true value plus this offset, mV.
    Offset(f64),
    /// Answer the next query with this text (e.g. SCPI's NaN, `9.91E37`).
    Raw(&'static str),
}

#[derive(Default)]
struct InstrumentState {
    /// Channel → output, volts.
    volts: BTreeMap<u32, f64>,
    /// Channel → fixed-mode set point, volts (`volt?` echoes it).
    setpoint: BTreeMap<u32, f64>,
    /// Channels in list mode: their output ignores the set point until
    /// `sour{ch}:volt:mode fix`.
    list_mode: std::collections::BTreeSet<u32>,
    /// Channel → the current it sources, A (`read{ch}?`; default 1 pA).
    current_a: BTreeMap<u32, f64>,
    /// (connection number, command) in arrival order.
    log: Vec<(usize, String)>,
    /// Set commands received so far.
    sets: usize,
    /// Fault and the set count at which it fires.
    armed: Option<(Fault, usize)>,
    /// A fault that fired and waits for the next query (Late/Offset).
    query_fault: Option<Fault>,
    /// Violations seen: commands outside limits or with too large increments.
    violations: Vec<String>,
}

/// The simulated instrument.
#[derive(Clone)]
struct Instrument {
    addr: std::net::SocketAddr,
    state: Arc<Mutex<InstrumentState>>,
}

impl Instrument {
    /// Start on an ephemeral loopback port with `volts` (channel → V).
    /// `limits` (channel → (min, max) mV) and `ramp_step_mv` are checked on
    /// every set command.
    async fn start(
        volts: BTreeMap<u32, f64>,
        limits: BTreeMap<u32, (f64, f64)>,
        ramp_step_mv: f64,
    ) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let state = Arc::new(Mutex::new(InstrumentState {
            setpoint: volts.clone(),
            volts,
            ..Default::default()
        }));
        let st = state.clone();
        tokio::spawn(async move {
            let mut conn_no = 0;
            loop {
                let Ok((stream, _)) = listener.accept().await else {
                    return;
                };
                conn_no += 1;
                let st = st.clone();
                let limits = limits.clone();
                tokio::spawn(async move {
                    let (r, mut w) = stream.into_split();
                    let mut lines = BufReader::new(r).lines();
                    while let Ok(Some(line)) = lines.next_line().await {
                        let cmd = line.trim().to_string();
                        let mut answer = None;
                        let mut delay = None;
                        {
                            let mut s = st.lock().unwrap();
                            s.log.push((conn_no, cmd.clone()));
                            'cmd: {
                                if let Some(rest) = cmd.strip_prefix("read") {
                                    let ch: u32 =
                                        rest.trim_end_matches('?').parse().expect("channel");
                                    let i = s.current_a.get(&ch).copied().unwrap_or(1e-12);
                                    // QDAC-II answers a comma-separated list.
                                    answer = Some(format!("{},{i}\n", i / 2.0));
                                    break 'cmd;
                                }
                                let (head, arg) = cmd.split_once(' ').unwrap_or((&cmd, ""));
                                let ch: u32 = head
                                    .trim_start_matches("sour")
                                    .split(':')
                                    .next()
                                    .unwrap()
                                    .parse()
                                    .expect("channel number");
                                if head.ends_with(":volt:slew") {
                                    // accepted, nothing to model
                                } else if head.ends_with(":volt:mode") {
                                    assert_eq!(arg, "fix", "only fixed mode is ever requested");
                                    if s.list_mode.remove(&ch) {
                                        // The output jumps to the fixed set point.
                                        let sp = s.setpoint.get(&ch).copied().unwrap_or(0.0);
                                        s.volts.insert(ch, sp);
                                    }
                                } else if head.ends_with(":volt?") || head.ends_with(":volt:last?")
                                {
                                    let map = if head.ends_with(":volt:last?") {
                                        &s.volts
                                    } else {
                                        &s.setpoint
                                    };
                                    let mut v = map.get(&ch).copied().unwrap_or(0.0);
                                    let mut raw = None;
                                    match s.query_fault.take() {
                                        Some(Fault::Late(d)) => delay = Some(d),
                                        Some(Fault::Offset(mv)) => v += mv / 1000.0,
                                        Some(Fault::Raw(text)) => raw = Some(text),
                                        _ => {}
                                    }
                                    answer = Some(match raw {
                                        Some(text) => format!("{text}\n"),
                                        None => format!("{v}\n"),
                                    });
                                } else if head.ends_with(":volt") {
                                    s.sets += 1;
                                    let v: f64 = arg.parse().expect("volts");
                                    if let Some((fault, at)) = s.armed {
                                        if s.sets >= at {
                                            s.armed = None;
                                            if fault == Fault::Drop {
                                                return; // closes the connection, not applied
                                            }
                                            s.query_fault = Some(fault);
                                        }
                                    }
                                    let old = s.volts.get(&ch).copied().unwrap_or(0.0);
                                    let (lo, hi) = limits[&ch];
                                    let mv = v * 1000.0;
                                    if mv < lo - 1e-9 || mv > hi + 1e-9 {
                                        s.violations
                                            .push(format!("{cmd}: outside [{lo}, {hi}] mV"));
                                    }
                                    // 1 µV formatting resolution
                                    if ((v - old) * 1000.0).abs() > ramp_step_mv + 2e-3 {
                                        s.violations.push(format!(
                                            "{cmd}: increment {} mV from {} V",
                                            (v - old) * 1000.0,
                                            old
                                        ));
                                    }
                                    s.setpoint.insert(ch, v);
                                    if !s.list_mode.contains(&ch) {
                                        s.volts.insert(ch, v);
                                    }
                                } else {
                                    panic!("unknown command {cmd:?}");
                                }
                            }
                        }
                        if let Some(d) = delay {
                            tokio::time::sleep(d).await;
                        }
                        if let Some(a) = answer {
                            if w.write_all(a.as_bytes()).await.is_err() {
                                return;
                            }
                        }
                    }
                });
            }
        });
        Self { addr, state }
    }

    fn arm(&self, fault: Fault, after_sets: usize) {
        let mut s = self.state.lock().unwrap();
        let at = s.sets + after_sets;
        s.armed = Some((fault, at));
    }

    fn log(&self) -> Vec<(usize, String)> {
        self.state.lock().unwrap().log.clone()
    }

    fn commands(&self) -> Vec<String> {
        self.log().into_iter().map(|(_, c)| c).collect()
    }

    fn violations(&self) -> Vec<String> {
        self.state.lock().unwrap().violations.clone()
    }

    fn set_list_mode(&self, channel: u32) {
        self.state.lock().unwrap().list_mode.insert(channel);
    }

    fn set_current(&self, channel: u32, amps: f64) {
        self.state.lock().unwrap().current_a.insert(channel, amps);
    }

    fn output_mv(&self, channel: u32) -> f64 {
        self.state.lock().unwrap().volts[&channel] * 1000.0
    }

    fn clear_log(&self) {
        self.state.lock().unwrap().log.clear();
    }
}

fn gates() -> Vec<GateSpec> {
    default_gates()
}

/// Channel numbers 1… for all default gates, in their order.
fn channel_map() -> BTreeMap<String, u32> {
    gates()
        .iter()
        .enumerate()
        .map(|(i, g)| (g.name.clone(), i as u32 + 1))
        .collect()
}

fn instrument_at_initial() -> (BTreeMap<u32, f64>, BTreeMap<u32, (f64, f64)>) {
    let map = channel_map();
    let mut volts = BTreeMap::new();
    let mut limits = BTreeMap::new();
    for g in gates() {
        let ch = map[&g.name];
        volts.insert(ch, g.initial_mv / 1000.0);
        limits.insert(ch, (g.min_mv, g.max_mv));
    }
    (volts, limits)
}

fn scpi_config(addr: std::net::SocketAddr, channels: BTreeMap<String, u32>) -> ScpiConfig {
    ScpiConfig {
        address: addr.to_string(),
        channels,
        ramp_step_mv: 1.0,
        slew_v_per_s: Some(5.0),
        readback_tolerance_mv: 0.05,
        timeout_ms: 300,
        settle_ms: 0,
        measure: MeasureSource::Simulator,
        profile: Default::default(),
        max_leakage_na: None,
        max_leakage_na_by_gate: Default::default(),
    }
}

#[tokio::test]
async fn exact_command_sequence_and_refusals_send_nothing() {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 1.0).await;
    let channels = BTreeMap::from([("N".to_string(), 1), ("SB".to_string(), 4)]);
    let mut src = ScpiSource::new(scpi_config(inst.addr, channels), &gates());

    // Refused before connecting: out of limits (SB: [-980, -580] mV), unmapped gate.
    let e = src
        .set(&BTreeMap::from([("SB".to_string(), -1000.0)]))
        .await
        .unwrap_err();
    assert!(matches!(e, DeviceError::Refused(_)), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("outside its limits") && e.contains("nothing sent"),
        "{e}"
    );
    let e = src
        .set(&BTreeMap::from([("T".to_string(), -650.0)]))
        .await
        .unwrap_err();
    assert_eq!(
        e,
        DeviceError::Unmapped {
            gate: "T".to_string()
        }
    );
    let e = e.to_string();
    assert!(
        e.contains("no channel") && e.contains("nothing sent"),
        "{e}"
    );
    assert!(inst.commands().is_empty(), "{:?}", inst.commands());

    // One gate, 2.5 mV in 1 mV increments: connect (slew + read back), ramp, read back.
    let rb = src
        .set(&BTreeMap::from([("SB".to_string(), -777.5)]))
        .await
        .unwrap();
    assert!((rb["SB"] + 777.5).abs() < 1e-9, "{rb:?}");
    assert_eq!(
        inst.commands(),
        [
            "sour1:volt:slew 5",
            "sour1:volt?",
            "sour4:volt:slew 5",
            "sour4:volt?",
            "sour4:volt -0.779167",
            "sour4:volt -0.778333",
            "sour4:volt -0.777500",
            "sour4:volt?",
        ]
    );
    inst.clear_log();

    // Two gates advance together; the larger move sets the number of increments.
    src.set(&BTreeMap::from([
        ("N".to_string(), -698.0),
        ("SB".to_string(), -778.0),
    ]))
    .await
    .unwrap();
    assert_eq!(
        inst.commands(),
        [
            "sour1:volt -0.699000",
            "sour4:volt -0.777750",
            "sour1:volt -0.698000",
            "sour4:volt -0.778000",
            "sour1:volt?",
            "sour4:volt?",
        ]
    );
    inst.clear_log();

    // A jump larger than the gate's max_step (10 mV) from the instrument's
    // read-back is refused without a command.
    let e = src
        .set(&BTreeMap::from([("SB".to_string(), -765.0)]))
        .await
        .unwrap_err();
    assert!(matches!(e, DeviceError::Refused(_)), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("exceeds its maximal step") && e.contains("nothing sent"),
        "{e}"
    );
    assert!(inst.commands().is_empty(), "{:?}", inst.commands());

    // Read-back mismatch: error, connection dropped; the next request re-reads
    // every channel before sending anything.
    inst.arm(Fault::Offset(3.0), 1);
    let e = src
        .set(&BTreeMap::from([("SB".to_string(), -779.0)]))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::ReadbackMismatch { gate, channel: 4, .. } if gate == "SB"),
        "{e:?}"
    );
    let e = e.to_string();
    assert!(e.contains("read-back mismatch on SB (channel 4)"), "{e}");
    assert!(!src.is_connected());
    inst.clear_log();
    src.set(&BTreeMap::from([("SB".to_string(), -779.5)]))
        .await
        .unwrap();
    let cmds = inst.commands();
    assert_eq!(
        &cmds[..4],
        [
            "sour1:volt:slew 5",
            "sour1:volt?",
            "sour4:volt:slew 5",
            "sour4:volt?"
        ]
    );
    assert_eq!(&cmds[4..], ["sour4:volt -0.779500", "sour4:volt?"]);

    // Late answer: timeout, connection dropped, nothing re-sent by the driver.
    inst.arm(Fault::Late(Duration::from_millis(700)), 1);
    inst.clear_log();
    let e = src
        .set(&BTreeMap::from([("SB".to_string(), -780.0)]))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::ReadbackFailed { error, .. } if matches!(**error, DeviceError::NoAnswer { ms: 300, .. })),
        "{e:?}"
    );
    let e = e.to_string();
    assert!(e.contains("no answer") && e.contains("300 ms"), "{e}");
    assert_eq!(inst.commands(), ["sour4:volt -0.780000", "sour4:volt?"]);
    assert!(!src.is_connected());
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}

fn run_config(addr: std::net::SocketAddr, n: u64) -> serde_json::Value {
    json!({
        "name": "scpi",
        "seed": 3,
        "iteration_delay_ms": 0,
        "driver": "scpi",
        "scpi": {
            "address": addr.to_string(),
            "channels": channel_map(),
            "ramp_step_mv": 2.0,
            "timeout_ms": 300,
            "measure": "simulator"
        },
        "tuner": { "max_iterations": n, "stop_when_tuned": false }
    })
}

fn is_fault(r: &RunSummary) -> bool {
    matches!(&r.status, RunStatus::Faulted { .. })
}

fn fault_message(r: &RunSummary) -> String {
    match &r.status {
        RunStatus::Faulted { fault } => fault.to_string(),
        other => panic!("expected a fault, got {other:?}"),
    }
}

/// Wait until the run is faulted, then check nothing is sent while paused.
async fn expect_fault(srv: &Server, inst: &Instrument, id: u64, needle: &str) -> RunSummary {
    let r = wait_status(srv.addr, id, |r| {
        is_fault(r) || matches!(r.status, RunStatus::Finished)
    })
    .await;
    let msg = fault_message(&r);
    assert!(msg.contains(needle), "expected {needle:?} in {msg:?}");
    let before = inst.log().len();
    tokio::time::sleep(Duration::from_millis(150)).await;
    assert_eq!(
        inst.log().len(),
        before,
        "commands were sent while the run was paused"
    );
    assert_eq!(get_run(srv.addr, id).await.status, r.status);
    r
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn faults_pause_the_run_without_losing_data_and_limits_always_hold() {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    let dir = TempDir::new("scpi");
    let srv = server(&dir, 256).await;
    let n = 4;

    // 1. The connection drops in the middle of a ramp.
    inst.arm(Fault::Drop, 40);
    let run = create_run(srv.addr, &run_config(inst.addr, n)).await;
    let r1 = expect_fault(&srv, &inst, run.id, "SCPI source").await;
    let stored1 = records(srv.addr, run.id).await;
    assert_eq!(stored1.len() as u64, r1.iterations);
    let conn1 = inst.log().last().unwrap().0;

    // 2. On resume the driver reconnects and reads every channel back before
    //    any set command; then an answer comes late.
    inst.arm(Fault::Late(Duration::from_millis(800)), 60);
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let r2 = expect_fault(&srv, &inst, run.id, "no answer").await;
    let log = inst.log();
    let first_new: Vec<&String> = log
        .iter()
        .filter(|(c, _)| *c == conn1 + 1)
        .map(|(_, cmd)| cmd)
        .take(channel_map().len())
        .collect();
    assert_eq!(first_new.len(), channel_map().len());
    assert!(
        first_new.iter().all(|c| c.ends_with(":volt?")),
        "reconnect did not start by reading back: {first_new:?}"
    );
    assert!(r2.iterations >= r1.iterations);

    // 3. The instrument reports a different voltage.
    inst.arm(Fault::Offset(1.0), 30);
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let r3 = expect_fault(&srv, &inst, run.id, "read-back mismatch").await;
    assert!(r3.iterations >= r2.iterations);

    // Resume to the end: every iteration is there, once, in order.
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    let done = wait_status(srv.addr, run.id, is_finished).await;
    assert_eq!(done.iterations, n);
    let stored = records(srv.addr, run.id).await;
    assert_eq!(stored.len() as u64, n);
    for (k, r) in stored.iter().enumerate() {
        assert_eq!(r["iteration"], k as u64);
    }
    // Records committed before the faults are unchanged.
    assert_eq!(stored[..stored1.len()], stored1[..]);

    // No command ever left the limits or exceeded the ramp increment.
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
    let sets = inst
        .commands()
        .iter()
        .filter(|c| c.contains(":volt ") && !c.contains("slew"))
        .count();
    assert!(sets > 100, "only {sets} set commands");
}

/// SCPI's special values are not voltages: an instrument that answers
/// `9.91E37` (NaN) or `-9.9E37` (overflow) to a read-back faults the run
/// (a person must resume), nothing further is set, and the stored state
/// never holds the value. (Before, `9.91E37` V was adopted as 9.91e40 mV.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scpi_nan_and_overflow_answers_fault_and_nothing_is_set() {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    let dir = TempDir::new("scpi-nan");
    let srv = server(&dir, 256).await;
    inst.arm(Fault::Raw("9.91E37"), 20);
    let run = create_run(srv.addr, &run_config(inst.addr, 3)).await;
    let r = expect_fault(&srv, &inst, run.id, "not a voltage").await;
    let RunStatus::Faulted { fault } = &r.status else {
        unreachable!()
    };
    assert_eq!(fault.kind, spintune::protocol::FaultKind::Device, "{fault}");
    assert!(fault.message.contains("9.91E37"), "{fault}");
    // Overflow on the read-back of every channel after a resume.
    inst.arm(Fault::Raw("-9.9E37"), 0);
    inst.state.lock().unwrap().query_fault = Some(Fault::Raw("-9.9E37"));
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    expect_fault(&srv, &inst, run.id, "not a voltage").await;
    // An honest instrument again: the run finishes, every command within limits.
    inst.state.lock().unwrap().armed = None;
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    wait_status(srv.addr, run.id, is_finished).await;
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
    for rec in records(srv.addr, run.id).await {
        let text = rec.to_string();
        assert!(!text.contains("e37") && !text.contains("e40"), "{text}");
    }
}

/// The real binary as a process against the scripted instrument: `kill -9`
/// mid-run, restart, eight concurrent `resume`s. Exactly one task may drive
/// the run (one new instrument connection, paced iterations, contiguous
/// unique iteration numbers), and after `stop` is acknowledged the
/// instrument receives nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_resumes_after_kill_9_start_one_task_and_nothing_reaches_the_instrument_after_stop(
) {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    let dir = TempDir::new("scpi-kill");
    let db = dir.0.join("kill.db");
    let delay_ms = 100;
    let mut cfg = run_config(inst.addr, 10_000);
    cfg["iteration_delay_ms"] = json!(delay_ms);

    let (proc1, addr) = spawn_server(&db);
    let run = create_run(addr, &cfg).await;
    wait_status(addr, run.id, |r| r.iterations >= 2).await;
    proc1.kill_9();
    let connections_before = inst.log().last().map_or(0, |(c, _)| *c);

    let (_proc2, addr) = spawn_server(&db);
    let stored = get_run(addr, run.id).await;
    assert_eq!(stored.status, RunStatus::Interrupted, "{stored:?}");
    let resumes = (0..8).map(|_| control(addr, run.id, r#"{"action":"resume"}"#));
    for (s, body) in futures_util::future::join_all(resumes).await {
        assert_eq!(s, 200, "{body}");
    }
    let t0 = std::time::Instant::now();
    let start = get_run(addr, run.id).await.iterations;
    wait_status(addr, run.id, |r| r.iterations >= start + 4).await;
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let now = get_run(addr, run.id).await;
    assert_eq!(now.status, RunStatus::Running);
    // One paced task: at most one iteration per `delay_ms` (an orphan task
    // would run unpaced, hundreds per second).
    let ran = now.iterations - start;
    let bound = t0.elapsed().as_millis() as u64 / delay_ms + 2;
    assert!(ran <= bound, "{ran} iterations in {:?}", t0.elapsed());
    // One task, one instrument connection after the restart.
    let connections: std::collections::BTreeSet<usize> = inst
        .log()
        .iter()
        .map(|(c, _)| *c)
        .filter(|c| *c > connections_before)
        .collect();
    assert_eq!(connections.len(), 1, "{connections:?}");

    // Stop: acknowledged, then silence on the instrument.
    let (s, body) = control(addr, run.id, r#"{"action":"stop"}"#).await;
    assert_eq!(s, 200, "{body}");
    // bytes already in flight when the stop was acknowledged may still arrive
    tokio::time::sleep(Duration::from_millis(200)).await;
    let sent = inst.commands().len();
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        inst.commands().len(),
        sent,
        "commands reached the instrument after stop: {:?}",
        &inst.commands()[sent..]
    );
    assert_eq!(get_run(addr, run.id).await.status, RunStatus::Stopped);
    let (s, _) = control(addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 409, "a stopped run must not resume");
    // Every stored iteration once, in order, across the crash.
    let recs = records(addr, run.id).await;
    for (k, r) in recs.iter().enumerate() {
        assert_eq!(r["iteration"], k as u64);
    }
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}

/// Headless `spintune run` against an instrument that is not there: the
/// device fault is printed and the process exits non-zero (3) instead of
/// hanging; the run stays resumable in the store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn headless_run_exits_non_zero_on_a_device_fault_and_leaves_the_run_resumable() {
    // a port nobody listens on
    let closed = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap()
    };
    let dir = TempDir::new("headless-fault");
    let toml_cfg = format!(
        "name = \"headless\"\ndriver = \"scpi\"\n[scpi]\naddress = \"{closed}\"\ntimeout_ms = 300\nmeasure = \"simulator\"\n[scpi.channels]\nN = 1\nT = 2\nSA = 3\nSB = 4\n[tuner]\nmax_iterations = 3\n"
    );
    let cfg_path = dir.0.join("run.toml");
    std::fs::write(&cfg_path, toml_cfg).unwrap();
    let db = dir.0.join("h.db");
    let out = tokio::task::spawn_blocking(move || {
        spintune()
            .args(["run", "--quiet", "--config"])
            .arg(&cfg_path)
            .arg("--db")
            .arg(&db)
            .output()
            .unwrap()
    });
    let out = tokio::time::timeout(Duration::from_secs(60), out)
        .await
        .expect("headless run hung on a device fault")
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("device fault"), "{stderr}");
    assert!(stderr.contains("cannot connect"), "{stderr}");
    assert!(stderr.contains("resumable"), "{stderr}");
    let store = spintune_server::store::Store::open(&dir.0.join("h.db")).unwrap();
    let run = store.list_runs().unwrap().pop().unwrap();
    assert!(
        matches!(run.summary.status, RunStatus::Faulted { .. }),
        "{:?}",
        run.summary.status
    );
    assert!(run.summary.status.is_resumable());
}

fn qdac2_config(addr: std::net::SocketAddr, channels: BTreeMap<String, u32>) -> ScpiConfig {
    ScpiConfig {
        profile: ScpiProfile::Qdac2,
        ..scpi_config(addr, channels)
    }
}

#[tokio::test]
async fn qdac2_profile_fixes_a_list_mode_channel_before_moving_it_and_reads_the_output() {
    let channels = BTreeMap::from([("N".to_string(), 1), ("SB".to_string(), 4)]);

    // The generic profile cannot see a channel left in list mode: `volt?`
    // echoes the set point while the output stays where it was.
    let (volts, limits) = instrument_at_initial();
    let generic = Instrument::start(volts, limits, 1.0).await;
    generic.set_list_mode(4);
    let mut src = ScpiSource::new(scpi_config(generic.addr, channels.clone()), &gates());
    src.set(&BTreeMap::from([("SB".to_string(), -777.5)]))
        .await
        .unwrap();
    assert!(
        (generic.output_mv(4) + 780.0).abs() < 1e-9,
        "{}",
        generic.output_mv(4)
    );

    // QDAC-II: fixed mode for every channel on connect, before the read-back
    // and any set; `volt:last?` reads the output; the channel really moves.
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 1.0).await;
    inst.set_list_mode(4);
    let mut src = ScpiSource::new(qdac2_config(inst.addr, channels), &gates());
    let rb = src
        .set(&BTreeMap::from([("SB".to_string(), -777.5)]))
        .await
        .unwrap();
    assert!((rb["SB"] + 777.5).abs() < 1e-9, "{rb:?}");
    assert!(
        (inst.output_mv(4) + 777.5).abs() < 1e-9,
        "{}",
        inst.output_mv(4)
    );
    assert_eq!(
        inst.commands(),
        [
            "sour1:volt:mode fix",
            "sour1:volt:slew 5",
            "sour1:volt:last?",
            "sour4:volt:mode fix",
            "sour4:volt:slew 5",
            "sour4:volt:last?",
            "sour4:volt -0.779167",
            "sour4:volt -0.778333",
            "sour4:volt -0.777500",
            "sour4:volt:last?",
        ]
    );
    // A channel switched to list mode behind the driver's back does not
    // move: `volt:last?` shows it, and the move is a read-back fault.
    inst.set_list_mode(4);
    let e = src
        .set(&BTreeMap::from([("SB".to_string(), -778.5)]))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::ReadbackMismatch { gate, channel: 4, .. } if gate == "SB"),
        "{e:?}"
    );
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_per_gate_leakage_limit_overrides_the_default_for_that_gate() {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    // SB sources 0.5 µA: under the 1 µA default, above its own 100 nA.
    let sb = channel_map()["SB"];
    inst.set_current(sb, 5e-7);
    let dir = TempDir::new("scpi-leak-gate");
    let srv = server(&dir, 256).await;
    let mut config = run_config(inst.addr, 50);
    config["scpi"]["profile"] = json!("qdac2");
    config["scpi"]["max_leakage_na"] = json!(1000.0);
    config["scpi"]["max_leakage_na_by_gate"] = json!({ "SB": 100.0 });
    let run = create_run(srv.addr, &config).await;
    let r = expect_fault(
        &srv,
        &inst,
        run.id,
        "exceeds max_leakage_na_by_gate.SB = 100 nA",
    )
    .await;
    assert!(
        matches!(&r.status, RunStatus::Faulted { fault } if fault.kind == spintune::protocol::FaultKind::Device),
        "{r:?}"
    );
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_leaking_gate_faults_the_run_with_channel_and_current_and_nothing_further_is_set() {
    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    // SB (channel 4) sources 0.5 µA: far above a 100 nA limit.
    let sb = channel_map()["SB"];
    inst.set_current(sb, 5e-7);
    let dir = TempDir::new("scpi-leak");
    let srv = server(&dir, 256).await;
    let mut config = run_config(inst.addr, 50);
    config["scpi"]["profile"] = json!("qdac2");
    config["scpi"]["max_leakage_na"] = json!(100.0);
    let run = create_run(srv.addr, &config).await;
    let r = expect_fault(
        &srv,
        &inst,
        run.id,
        &format!("leakage on SB (channel {sb})"),
    )
    .await;
    let RunStatus::Faulted { fault } = &r.status else {
        unreachable!()
    };
    assert_eq!(fault.kind, spintune::protocol::FaultKind::Device, "{fault}");
    assert!(
        fault.message.contains("500.000 nA") && fault.message.contains("100 nA"),
        "{fault}"
    );
    // Nothing was set after SB's current was read.
    let cmds = inst.commands();
    let read = cmds
        .iter()
        .rposition(|c| c == &format!("read{sb}?"))
        .expect("SB's current was never read");
    let after: Vec<&String> = cmds[read + 1..]
        .iter()
        .filter(|c| c.contains(":volt "))
        .collect();
    assert!(after.is_empty(), "set after the leak: {after:?}");
    // The check follows a move (the request's gates are read, moved or not).
    assert!(
        cmds[..read].iter().any(|c| c.contains(":volt -")),
        "the current was read before any move"
    );
    // Other channels under the limit were read too (their moves passed), and
    // the run is resumable: a resume reads the current again and faults again.
    let (s, b) = control(srv.addr, run.id, r#"{"action":"resume"}"#).await;
    assert_eq!(s, 200, "{b}");
    expect_fault(&srv, &inst, run.id, "leakage on SB").await;
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}

/// Issue 20's first finding: a SCPI run measured through a lab bridge faults
/// on leakage, then the bridge reconnects. The leakage fault needs a person:
/// the reconnect clears nothing and not one more set command reaches the
/// instrument (before, 1,740 did and the run finished).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_leakage_fault_is_not_cleared_by_a_bridge_reconnect() {
    use common::bridge_client::{answer, bridge, next_bridge};
    use spintune::protocol::BridgeServerMessage;

    let (volts, limits) = instrument_at_initial();
    let inst = Instrument::start(volts, limits, 2.0).await;
    let sb = channel_map()["SB"];
    inst.set_current(sb, 5e-7);
    let dir = TempDir::new("scpi-leak-bridge");
    let srv = server(&dir, 256).await;
    let mut config = run_config(inst.addr, 50);
    config["scpi"]["profile"] = json!("qdac2");
    config["scpi"]["max_leakage_na"] = json!(100.0);
    config["scpi"]["measure"] = json!("bridge");
    let parsed = spintune_server::config::RunConfig::from_json_str(&config.to_string()).unwrap();
    let mut lab = spintune::driver::SimulationRun::new(parsed.simulation)
        .unwrap()
        .device()
        .clone();
    let run = create_run(srv.addr, &config).await;
    let mut ws = bridge(srv.addr, run.id).await;
    // Serve measurements until the leakage fault.
    let fault = tokio::time::timeout(Duration::from_secs(60), async {
        let mut tick = tokio::time::interval(Duration::from_millis(50));
        loop {
            tokio::select! {
                frame = next_bridge(&mut ws) => {
                    if let BridgeServerMessage::Request { id, request, .. } = frame {
                        let resp = lab.execute(&request);
                        answer(&mut ws, id, resp).await;
                    }
                }
                _ = tick.tick() => {
                    // (until the bridge has authenticated the run waits
                    // `Disconnected`, a fault that clears by itself: wait on)
                    if let RunStatus::Faulted { fault } = get_run(srv.addr, run.id).await.status {
                        if fault.kind != spintune::protocol::FaultKind::Disconnected {
                            return fault;
                        }
                    }
                }
            }
        }
    })
    .await
    .expect("no leakage fault");
    assert_eq!(fault.kind, spintune::protocol::FaultKind::Device, "{fault}");
    assert!(fault.message.contains("leakage on SB"), "{fault}");
    let sets_at_fault = inst
        .commands()
        .iter()
        .filter(|c| c.contains(":volt ") && !c.contains("slew"))
        .count();
    // The bridge drops and reconnects.
    drop(ws);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut ws = bridge(srv.addr, run.id).await;
    let quiet = tokio::time::timeout(Duration::from_millis(1500), async {
        loop {
            if let BridgeServerMessage::Request { .. } = next_bridge(&mut ws).await {
                return;
            }
        }
    })
    .await;
    assert!(
        quiet.is_err(),
        "a measurement was requested after the reconnect"
    );
    let sets_after = inst
        .commands()
        .iter()
        .filter(|c| c.contains(":volt ") && !c.contains("slew"))
        .count();
    assert_eq!(
        sets_after, sets_at_fault,
        "set commands after the reconnect"
    );
    assert!(
        matches!(&get_run(srv.addr, run.id).await.status, RunStatus::Faulted { fault } if fault.message.contains("leakage")),
        "the leakage fault cleared by itself"
    );
    assert!(inst.violations().is_empty(), "{:?}", inst.violations());
}
