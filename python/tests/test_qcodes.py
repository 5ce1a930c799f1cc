"""spintune.qcodes with real QCoDeS: a station whose DAC gate parameters (in
V, with validators) are backed by the simulated double dot. Every set is
checked on the instrument side against the limits in force."""

import json
import math
import time
import warnings
from functools import partial

import numpy as np
import pytest

import qcodes  # real QCoDeS from PyPI (installed by `cargo xtask test`)
from qcodes.dataset import initialise_or_create_database_at, load_by_id, load_or_create_experiment
from qcodes.instrument import Instrument
from qcodes.parameters import DelegateParameter, ManualParameter, Parameter
from qcodes.station import Station
from qcodes.validators import Numbers

import spintune
from spintune.qcodes import QcodesTuner, ScanFailed, TuningFault, sweep_points_mv

# Validator ranges of the DAC channels, V. N is stricter than the tuner
# config's [-900, -500] mV; the others are wider than the config.
VALIDATOR_V = {"N": (-0.8, -0.6)}
WIDE_V = (-2.0, 0.5)

# The simulated DAC needs no settling time: tests about something else leave
# QCoDeS's inter_delay at 0 (a sensing-dot sweep is 201 sets, ~900 per
# iteration); the first tuning test and
# test_instrument_step_and_inter_delay_from_the_limits run with the default.
FAST = {"inter_delay_s": 0.0}


class SimulatedDac(Instrument):
    """A DAC whose channels (V) drive the simulated device; logs every get,
    every physical set (each step of a QCoDeS ramp) and every knob a human
    turned by hand."""

    def __init__(self, name, device, ranges_v):
        super().__init__(name)
        self.device = device
        self.log = []  # ("set", gate, mV) / ("get", gate) / ("knob", gate, mV)
        self.interrupt_on_set = None  # (gate, n): the n-th set of gate raises KeyboardInterrupt
        self.interrupt_snapshot = False  # the next snapshot raises KeyboardInterrupt
        self.fail_on_get = None  # (gate, n): the n-th get of gate raises OSError
        for gate, (lo, hi) in ranges_v.items():
            self.add_parameter(
                gate,
                unit="V",
                vals=Numbers(lo, hi),
                get_cmd=partial(self._get, gate),
                set_cmd=partial(self._set, gate),
            )

    def get_idn(self):
        return {"vendor": "spintune", "model": "simulated DAC", "serial": None, "firmware": spintune.__version__}

    def snapshot_base(self, *args, **kwargs):
        if self.interrupt_snapshot:
            self.interrupt_snapshot = False
            raise KeyboardInterrupt  # Ctrl-C while QCoDeS creates the dataset
        return super().snapshot_base(*args, **kwargs)

    def turn_knob(self, gate, mv):
        """A human moves a gate at the instrument; QCoDeS does not know."""
        self.log.append(("knob", gate, mv))
        r = self.device.execute({"request": "set_voltages", "voltages_mv": {gate: mv}})
        assert r["response"] == "voltages_set", r

    def _set(self, gate, volts):
        if self.interrupt_on_set is not None and self.interrupt_on_set[0] == gate:
            g, n = self.interrupt_on_set
            self.interrupt_on_set = (g, n - 1) if n > 1 else None
            if n == 1:
                raise KeyboardInterrupt  # Ctrl-C while the set is at the instrument
        mv = volts * 1000.0
        self.log.append(("set", gate, mv))
        r = self.device.execute({"request": "set_voltages", "voltages_mv": {gate: mv}})
        if r["response"] != "voltages_set":
            raise RuntimeError(r["message"])

    def _get(self, gate):
        if self.fail_on_get is not None and self.fail_on_get[0] == gate:
            g, n = self.fail_on_get
            self.fail_on_get = (g, n - 1) if n > 1 else None
            if n == 1:
                raise OSError("VISA timeout")
        self.log.append(("get", gate))
        return self.device.voltages_mv[gate] / 1000.0

    def sets(self, start=0):
        return [e for e in self.log[start:] if e[0] == "set"]


@pytest.fixture()
def station(tmp_path):
    initialise_or_create_database_at(str(tmp_path / "qcodes.db"))
    exp = load_or_create_experiment("spintune-test", sample_name="simulated double dot")
    config = {"seed": 7}
    device = spintune.SimulatedDevice(config)
    ranges = {g["name"]: VALIDATOR_V.get(g["name"], WIDE_V) for g in device.gates}
    dac = SimulatedDac("dac", device, ranges)
    st = Station(dac)
    calls = {"reload_time": 0, "transition_width": 0}
    rng = np.random.default_rng(3)

    def raw(scan):
        """Raw traces from the simulator (the core fits them)."""
        calls[scan["kind"]] = calls.get(scan["kind"], 0) + 1
        r = device.execute({"request": "measure", "scan": scan})
        outcome = r["outcome"]
        if outcome["kind"] != "raw":
            raise ScanFailed(outcome.get("reason", "failed"))
        s = outcome["scan"]
        return {
            "x_label": s["x_label"],
            "y_label": s["y_label"],
            "traces": [{"label": t["label"], "x": np.asarray(t["x"]), "y": np.asarray(t["y"])} for t in s["traces"]],
        }

    def reload_time(scan):
        """Evaluated values ± variance (as a lab's own analysis would give)."""
        calls["reload_time"] += 1
        t_sr = device.truth()["t_sr"]
        return {"t_sr": (t_sr + rng.normal(0.0, 0.5), 0.25)}  # ns, ns²

    def sensing_dot(scan):
        """Sweep the sensing-dot gate on the instrument, then go back."""
        sweep = scan["sweep"]
        param = dac.parameters[sweep["gate"]]
        start = param.get()
        for mv in sweep_points_mv(sweep):
            param.set(mv / 1000.0)
        trace = raw(scan)
        param.set(start)
        return trace

    scans = {
        "reload_time": reload_time,
        "transition_width": raw,
        "chemical_potential": raw,
        "sensing_dot": sensing_dot,
    }
    gates = {name: dac.parameters[name] for name in ranges}
    yield {"dac": dac, "device": device, "station": st, "exp": exp, "scans": scans, "gates": gates, "calls": calls}
    Instrument.close_all()


def check_instrument_log(dac, limits, readback_mv):
    """Every physical set within the limits in force and one max step of the
    gate's previous value (a knob turned by hand moves the previous value)."""
    last = dict(readback_mv)
    for entry in dac.log:
        if entry[0] == "knob":
            last[entry[1]] = entry[2]
        elif entry[0] == "set":
            _, gate, mv = entry
            lim = limits[gate]
            assert lim["min_mv"] - 1e-9 <= mv <= lim["max_mv"] + 1e-9, (gate, mv, lim)
            assert abs(mv - last[gate]) <= lim["max_step_mv"] * (1 + 1e-9) + 1e-9, (gate, mv, last[gate])
            last[gate] = mv


def assert_reads_every_gate_first(dac, start, gates):
    """After log position `start`, every gate is read before the first set."""
    after = dac.log[start:]
    first_set = next((i for i, e in enumerate(after) if e[0] == "set"), len(after))
    assert {e[1] for e in after[:first_set] if e[0] == "get"} == set(gates), after[: first_set + 1]


def test_tunes_to_the_first_target_within_limits(station):
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(
        station["gates"],
        station["scans"],
        {"max_iterations": 12, "stop_when_tuned": True},
        experiment=station["exp"],
        station=station["station"],
        name="tune first target",
    )
    # the stricter limit wins: N's validator is [-0.8, -0.6] V, the config [-900, -500] mV
    assert tuner.limits["N"]["min_mv"] == pytest.approx(-800.0)
    assert tuner.limits["N"]["max_mv"] == pytest.approx(-600.0)
    assert tuner.limits["T"]["min_mv"] == -850.0  # config stricter than the validator
    seen = []
    dataset = tuner.run(on_iteration=seen.append)
    assert tuner.status == {"state": "finished"}
    last = tuner.records[-1]
    assert last["tuned"], [(p["name"], p["value"]) for p in last["parameters"]]
    t_sr, w = (p["value"] for p in last["parameters"])
    assert abs(t_sr - 20.0) <= 2.0 and abs(w - 270.0) <= 27.0  # ns, µV: the paper's first target
    truth = station["device"].truth()
    assert abs(truth["t_sr"] - 20.0) < 4.0
    assert seen == tuner.records
    check_instrument_log(station["dac"], tuner.limits, start_mv)
    assert station["calls"]["reload_time"] > 0 and station["calls"]["transition_width"] > 0
    # the dataset, read back by QCoDeS
    loaded = load_by_id(dataset.run_id)
    data = loaded.get_parameter_data()
    n = len(tuner.records)
    np.testing.assert_array_equal(data["t_sr"]["iteration"], [r["iteration"] for r in tuner.records])
    np.testing.assert_allclose(data["t_sr"]["t_sr"], [r["parameters"][0]["value"] for r in tuner.records])
    np.testing.assert_allclose(data["V_N"]["V_N"], [r["voltages_mv"]["N"] for r in tuner.records])
    assert len(data["grad_w_T"]["grad_w_T"]) == n
    assert [json.loads(x) for x in data["record"]["record"]] == tuner.records
    assert loaded.paramspecs["t_sr"].unit == "ns" and loaded.paramspecs["V_N"].unit == "mV"
    assert json.loads(loaded.metadata["spintune_status"]) == {"state": "finished"}
    assert json.loads(loaded.metadata["spintune_tuner_config"])["gates"][0]["min_mv"] == pytest.approx(-800.0)
    with pytest.raises(RuntimeError, match="finished"):
        tuner.run()


def test_tight_validator_is_never_exceeded(station):
    # N may move by ±1 mV only (its validator), less than the FD step of 4 mV:
    # the core keeps every request inside; the instrument never sees more.
    station["dac"].N.vals = Numbers(-0.701, -0.699)
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"], **FAST)
    try:
        tuner.run()
    except TuningFault:
        pass  # refusing a move is fine; exceeding a limit is not
    n_sets = [mv for _, g, mv in station["dac"].sets() if g == "N"]
    assert all(-701.0 - 1e-9 <= mv <= -699.0 + 1e-9 for mv in n_sets), n_sets
    check_instrument_log(station["dac"], tuner.limits, start_mv)


def test_interrupt_pauses_sets_nothing_and_resumes(station):
    calls = {"n": 0}
    measure = station["scans"]["transition_width"]

    def interrupted_once(scan):
        calls["n"] += 1
        # mid-iteration 0, after the finite differences (the default's cold
        # start: a base and 4 offsets, one w scan each)
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return measure(scan)

    scans = dict(station["scans"], transition_width=interrupted_once)
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], scans, {"max_iterations": 2}, experiment=station["exp"], **FAST)
    with pytest.raises(KeyboardInterrupt):
        tuner.run()
    assert tuner.status == {"state": "paused"}
    assert not tuner.session.has_request_in_flight
    n_log = len(station["dac"].log)
    assert tuner.session.poll()["output"] in ("publish", "wait")
    assert tuner.session.poll() == {"output": "wait"}
    assert len(station["dac"].log) == n_log  # nothing after the interrupt
    assert len(tuner.datasets) == 1  # the interrupted segment is a complete dataset
    # resume: every gate is read back before anything is set
    tuner.run()
    after = station["dac"].log[n_log:]
    first_set = next(i for i, e in enumerate(after) if e[0] == "set")
    assert {e[1] for e in after[:first_set] if e[0] == "get"} == set(station["gates"])
    assert tuner.status == {"state": "finished"}
    assert [r["iteration"] for r in tuner.records] == [0, 1]
    check_instrument_log(station["dac"], tuner.limits, start_mv)


def test_run_in_segments_and_scan_errors(station):
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"], **FAST)
    tuner.run(iterations=1)
    assert tuner.status == {"state": "paused"} and len(tuner.records) == 1
    tuner.set_target("t_sr", 25.0)
    boom = {"on": True}
    measure = station["scans"]["chemical_potential"]

    def failing(scan):
        if boom["on"]:
            boom["on"] = False
            raise OSError("VISA timeout")
        return measure(scan)

    tuner._scans["chemical_potential"] = failing
    with pytest.raises(OSError, match="VISA timeout"):
        tuner.run()
    assert tuner.status["state"] == "faulted"
    assert "VISA timeout" in tuner.status["fault"]["message"]
    tuner.run()
    assert tuner.status == {"state": "finished"} and len(tuner.records) == 3
    assert tuner.records[-1]["parameters"][0]["target"] == 25.0
    assert len(tuner.datasets) == 3


def test_configuration_errors(station):
    gates = dict(station["gates"])
    del gates["RFA"]
    with pytest.raises(ValueError, match="RFA"):
        QcodesTuner(gates, station["scans"])
    scans = dict(station["scans"])
    del scans["sensing_dot"]
    with pytest.raises(ValueError, match="sensing_dot"):
        QcodesTuner(station["gates"], scans)
    # a misspelt scan key is named (it would leave its scan unmapped)
    scans = dict(station["scans"])
    scans["reload_tme"] = scans["reload_time"]
    with pytest.raises(ValueError, match="unknown scan 'reload_tme'.*did you mean 'reload_time'"):
        QcodesTuner(station["gates"], scans)
    # one parameter mapped to two gates: setting one would move the other
    twice = dict(station["gates"])
    twice["T"] = twice["N"]
    with pytest.raises(ValueError, match="gates 'N' and 'T' are mapped to the same parameter"):
        QcodesTuner(twice, station["scans"])
    station["dac"].N.vals = Numbers(0.1, 0.2)
    with pytest.raises(ValueError, match="gate N.*no overlap"):
        QcodesTuner(station["gates"], station["scans"])
    station["dac"].N.unit = "a.u."
    with pytest.raises(ValueError, match="mv_per_unit"):
        QcodesTuner(station["gates"], station["scans"])
    with pytest.raises(ValueError, match="max_iterations"):
        QcodesTuner(station["gates"], station["scans"], {"max_iterations": "many"}, mv_per_unit={"N": 1000.0})
    assert not math.isnan(station["device"].lab_seconds)


# -- issue 20: an exception never leaves the run running ----------------------

def run_after_a_turned_knob(tuner, station, gate, delta_mv):
    """A human turns `gate` by `delta_mv` at the instrument, then run() again.
    The run either goes on (from where the gate really is) or stops with a
    fault (a core that refuses a gate far from where the run left it); either
    way every gate is read before anything is set."""
    dac, device = station["dac"], station["device"]
    n_log = len(dac.log)
    dac.turn_knob(gate, device.voltages_mv[gate] + delta_mv)
    try:
        tuner.run()
    except TuningFault:
        assert tuner.status["state"] == "faulted"
    else:
        assert tuner.status == {"state": "finished"}
    assert_reads_every_gate_first(dac, n_log + 1, station["gates"])


def test_raising_callback_then_a_turned_knob_never_steps_beyond_the_limit(station):
    # The case: on_iteration raises, a human moves T by 40 mV (4× its
    # max step), run() again. Before the fix the session stayed `running`,
    # the gates were not read again, and T was stepped ~40 mV at once.
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"], **FAST)

    class AnalysisFailed(Exception):
        pass

    def callback(record):
        raise AnalysisFailed(f"iteration {record['iteration']}")

    with pytest.raises(AnalysisFailed):
        tuner.run(on_iteration=callback)
    assert tuner.status == {"state": "paused"}
    assert not tuner.session.has_request_in_flight
    assert [r["iteration"] for r in tuner.records] == [0]
    assert len(tuner.datasets) == 1
    assert json.loads(tuner.datasets[0].metadata["spintune_status"]) == {"state": "paused"}
    run_after_a_turned_knob(tuner, station, "T", 40.0)
    check_instrument_log(station["dac"], tuner.limits, start_mv)


def test_keyboard_interrupt_inside_a_parameter_set_leaves_the_run_paused(station):
    dac = station["dac"]
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"], **FAST)
    dac.interrupt_on_set = ("N", 2)  # the second set of N: Ctrl-C before it reaches the DAC
    with pytest.raises(KeyboardInterrupt):
        tuner.run()
    assert dac.interrupt_on_set is None  # it did land inside the set
    assert tuner.status == {"state": "paused"}
    assert not tuner.session.has_request_in_flight
    assert len(tuner.datasets) == 1
    n_log = len(dac.log)
    assert tuner.session.poll()["output"] in ("publish", "wait")
    assert tuner.session.poll() == {"output": "wait"}
    assert len(dac.log) == n_log  # nothing after the interrupt
    run_after_a_turned_knob(tuner, station, "SA", -35.0)
    check_instrument_log(dac, tuner.limits, start_mv)


def test_keyboard_interrupt_while_the_dataset_is_created_leaves_the_run_paused(station):
    # Ctrl-C lands while QCoDeS snapshots the station for the new dataset,
    # after run() resumed the session and before the first request.
    dac = station["dac"]
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(
        station["gates"], station["scans"], {"max_iterations": 3},
        experiment=station["exp"], station=station["station"], **FAST,
    )
    tuner.run(iterations=1)
    assert tuner.status == {"state": "paused"}
    dac.interrupt_snapshot = True
    n_log = len(dac.log)
    with pytest.raises(KeyboardInterrupt):
        tuner.run()
    assert not dac.interrupt_snapshot  # it did land in the snapshot
    assert tuner.status == {"state": "paused"}
    assert len(dac.log) == n_log
    run_after_a_turned_knob(tuner, station, "N", 40.0)
    check_instrument_log(dac, tuner.limits, start_mv)


def test_a_session_left_running_is_read_again(station):
    # A driver outside run() left the session running with read-backs (here:
    # one request polled by hand, never answered): run() reads every gate
    # before it moves one, and the unanswered request counts as unknown.
    dac = station["dac"]
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 2}, experiment=station["exp"], **FAST)
    session = tuner.session
    assert session.poll()["output"] == "publish"
    out = session.poll()
    assert out["request"]["request"] == "read_voltages"
    session.feed(tuner._execute(out["request"]))
    out = session.poll()
    # (a new run saves where its gates are after the first read)
    assert out["output"] == "save"
    out = session.poll()
    assert out["output"] == "execute" and session.has_request_in_flight
    assert tuner.status == {"state": "running"} and session.readback_mv
    run_after_a_turned_knob(tuner, station, "T", 40.0)
    check_instrument_log(dac, tuner.limits, start_mv)


def test_exception_from_a_parameter_faults_and_is_read_again(station):
    # Any other exception of a gate parameter: a device fault (visible), not
    # a running run; run() again reads every gate.
    dac = station["dac"]
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 2}, experiment=station["exp"], **FAST)
    dac.fail_on_get = ("T", 3)  # the third read of T (a read-back after a set) times out
    with pytest.raises(OSError, match="VISA timeout"):
        tuner.run()
    assert dac.fail_on_get is None
    assert tuner.status["state"] == "faulted" and tuner.status["fault"]["kind"] == "device"
    assert not tuner.session.has_request_in_flight
    run_after_a_turned_knob(tuner, station, "T", 40.0)
    check_instrument_log(dac, tuner.limits, start_mv)


def test_a_malformed_scan_result_faults_and_is_read_again(station):
    # The answer cannot even be fed (ValueError from the session): the request
    # stays unanswered until run() reports it as a device fault.
    dac = station["dac"]
    start_mv = dict(station["device"].voltages_mv)
    scans = dict(station["scans"], reload_time=lambda scan: {"t_sr": ("twenty", 0.25)})
    tuner = QcodesTuner(station["gates"], scans, {"max_iterations": 2}, experiment=station["exp"], **FAST)
    with pytest.raises(ValueError):
        tuner.run()
    assert tuner.status["state"] == "faulted" and tuner.status["fault"]["kind"] == "device"
    assert "ValueError in run()" in tuner.status["fault"]["message"]
    assert not tuner.session.has_request_in_flight
    tuner._scans["reload_time"] = station["scans"]["reload_time"]
    run_after_a_turned_knob(tuner, station, "N", -40.0)
    check_instrument_log(dac, tuner.limits, start_mv)


# -- issue 20: read-back checks that prove nothing, the instrument's own ramp ---


def our_warnings(record):
    return [str(w.message) for w in record if issubclass(w.category, UserWarning) and "gate " in str(w.message)]


def test_cache_only_parameter_warns(station):
    dac = station["dac"]
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        QcodesTuner(station["gates"], station["scans"], **FAST)
    assert our_warnings(record) == []  # every DAC channel asks the instrument

    gates = dict(station["gates"])
    # only a set_cmd: get() returns the last value set
    gates["RFA"] = Parameter("rfa_set_only", unit="V", set_cmd=lambda v: None, initial_cache_value=0.0)
    gates["RFB"] = ManualParameter("rfb_manual", unit="V", initial_value=0.0)
    gates["SP"] = DelegateParameter("sp_delegate", source=ManualParameter("sp_cache", unit="V", initial_value=-0.5))
    gates["SD2"] = DelegateParameter("sd2_delegate", source=dac.SD2)  # asks the DAC: fine
    with pytest.warns(UserWarning) as record:
        QcodesTuner(gates, station["scans"], **FAST)
    messages = {m.split(":")[0]: m for m in our_warnings(record)}
    assert sorted(messages) == ["gate RFA", "gate RFB", "gate SP"], messages
    assert "'rfa_set_only' has no get command" in messages["gate RFA"] and "vacuous" in messages["gate RFA"]
    assert "'rfb_manual' has no get command" in messages["gate RFB"]
    assert "'sp_delegate' has no get command (it reads 'sp_cache', which has none)" in messages["gate SP"]

    # no get at all: the run could not read the gate; refused at once
    gates = dict(station["gates"], RFA=Parameter("rfa_no_get", unit="V", set_cmd=lambda v: None, get_cmd=False))
    with pytest.raises(ValueError, match="gate RFA: parameter 'rfa_no_get' cannot be read"):
        QcodesTuner(gates, station["scans"], **FAST)


def test_instrument_step_and_inter_delay_from_the_limits(station):
    dac = station["dac"]
    dac.SD1.step = 0.005  # the user's stricter step (5 mV < 30 mV) is kept
    dac.SA.step = 0.5  # a looser one (500 mV) is tightened
    dac.SB.inter_delay = 0.2  # a longer inter_delay is kept
    gates = dict(station["gates"])
    rfa = Parameter("rfa_mv", unit="mV", get_cmd=lambda: 0.0, set_cmd=lambda v: None)
    gates["RFA"] = rfa
    tuner = QcodesTuner(gates, station["scans"], experiment=station["exp"])
    limits = tuner.limits
    for gate, param in gates.items():
        scale = 1.0 if gate == "RFA" else 1000.0
        expected = 0.005 if gate == "SD1" else limits[gate]["max_step_mv"] / scale
        assert param.step == pytest.approx(expected, rel=1e-12), gate
        assert param.step * scale <= limits[gate]["max_step_mv"], gate  # never looser than the limit
        assert param.inter_delay == (0.2 if gate == "SB" else 0.001), gate
        assert tuner.ramps[gate] == {"step": param.step, "inter_delay": param.inter_delay}
    assert dac.N.step == pytest.approx(0.010) and dac.PA.step == pytest.approx(0.030)
    assert rfa.step == pytest.approx(5.0)  # RFA in mV, max_step_mv 5

    # QCoDeS itself now ramps a large set: 25 mV on N goes out in steps of
    # at most 10 mV, at least inter_delay apart
    n0 = dac.N.get()
    start = len(dac.log)
    t0 = time.perf_counter()
    dac.N.set(n0 + 0.025)
    elapsed = time.perf_counter() - t0
    sets = [mv for kind, *rest in dac.log[start:] if kind == "set" for _, mv in [rest]]
    assert len(sets) == 3 and sets[-1] == pytest.approx((n0 + 0.025) * 1000)
    prev = n0 * 1000
    for mv in sets:
        assert abs(mv - prev) <= 10.0 + 1e-9
        prev = mv
    assert elapsed >= 2 * 0.001

    # inter_delay_s=None leaves inter_delay alone; a bad value is refused
    dac.N.inter_delay = 0.0
    QcodesTuner(station["gates"], station["scans"], inter_delay_s=None)
    assert dac.N.inter_delay == 0.0
    with pytest.raises(ValueError, match="inter_delay_s"):
        QcodesTuner(station["gates"], station["scans"], inter_delay_s=-1.0)


def test_keep_mode_waits_through_sleep_then_checks_on_the_instruments(station):
    """Keep mode (the tuner config's ``keep`` table): once tuned, lab time
    passes through ``sleep`` (here it advances the simulated device's clock,
    so it drifts as a real one would), then checks measure again; the gates
    stay within every limit and step throughout."""
    start_mv = dict(station["device"].voltages_mv)
    waited = []

    def sleep(seconds):
        waited.append(seconds)
        r = station["device"].execute({"request": "wait", "seconds": seconds})
        assert r["response"] == "waited"

    tuner = QcodesTuner(
        station["gates"],
        station["scans"],
        {"keep": {"duration_s": 4 * 3600.0, "min_check_interval_s": 60.0}},
        experiment=station["exp"],
        sleep=sleep,
        **FAST,
    )
    tuner.run()
    assert tuner.status == {"state": "finished"}
    phases = [r["keep"]["phase"] for r in tuner.records]
    assert phases[0] == "tuning" and "check" in phases, phases
    assert 3 * 3600.0 < sum(waited) <= 4 * 3600.0 + 1.0
    assert max(waited) <= 600.0  # one wait request is at most 10 lab minutes
    check_instrument_log(station["dac"], tuner.limits, start_mv)
