"""spintune.qcodes with real QCoDeS: a station whose DAC gate parameters (in
V, with validators) are backed by the simulated double dot. Every set is
checked on the instrument side against the limits in force."""

import json
import math
from functools import partial

import numpy as np
import pytest

import qcodes  # real QCoDeS from PyPI (installed by `cargo xtask test`)
from qcodes.dataset import initialise_or_create_database_at, load_by_id, load_or_create_experiment
from qcodes.instrument import Instrument
from qcodes.station import Station
from qcodes.validators import Numbers

import spintune
from spintune.qcodes import QcodesTuner, ScanFailed, TuningFault, sweep_points_mv

# Validator ranges of the DAC channels, V. N is stricter than the tuner
# config's [-900, -500] mV; the others are wider than the config.
VALIDATOR_V = {"N": (-0.8, -0.6)}
WIDE_V = (-2.0, 0.5)


class SimulatedDac(Instrument):
    """A DAC whose channels (V) drive the simulated device; logs every get/set."""

    def __init__(self, name, device, ranges_v):
        super().__init__(name)
        self.device = device
        self.log = []  # ("set", gate, mV) / ("get", gate)
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

    def _set(self, gate, volts):
        mv = volts * 1000.0
        self.log.append(("set", gate, mv))
        r = self.device.execute({"request": "set_voltages", "voltages_mv": {gate: mv}})
        if r["response"] != "voltages_set":
            raise RuntimeError(r["message"])

    def _get(self, gate):
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
    """Every set within the limits in force and one max step of the previous value."""
    last = dict(readback_mv)
    for _, gate, mv in dac.sets():
        lim = limits[gate]
        assert lim["min_mv"] - 1e-9 <= mv <= lim["max_mv"] + 1e-9, (gate, mv, lim)
        assert abs(mv - last[gate]) <= lim["max_step_mv"] * (1 + 1e-9) + 1e-9, (gate, mv, last[gate])
        last[gate] = mv


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
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"])
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
        if calls["n"] == 9:  # mid-iteration, after the finite differences
            raise KeyboardInterrupt
        return measure(scan)

    scans = dict(station["scans"], transition_width=interrupted_once)
    start_mv = dict(station["device"].voltages_mv)
    tuner = QcodesTuner(station["gates"], scans, {"max_iterations": 2}, experiment=station["exp"])
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
    tuner = QcodesTuner(station["gates"], station["scans"], {"max_iterations": 3}, experiment=station["exp"])
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
    station["dac"].N.vals = Numbers(0.1, 0.2)
    with pytest.raises(ValueError, match="gate N.*no overlap"):
        QcodesTuner(station["gates"], station["scans"])
    station["dac"].N.unit = "a.u."
    with pytest.raises(ValueError, match="mv_per_unit"):
        QcodesTuner(station["gates"], station["scans"])
    with pytest.raises(ValueError, match="max_iterations"):
        QcodesTuner(station["gates"], station["scans"], {"max_iterations": "many"}, mv_per_unit={"N": 1000.0})
    assert not math.isnan(station["device"].lab_seconds)
