"""The real QDAC-II driver (``qcodes_contrib_drivers``, in pyvisa-sim
simulation) in a QCoDeS station: from the instrument's reset state (0 V on
every channel) the tuner refuses to start, naming the gate, its read-back
and its range; ``ramp_to`` brings the gates to the working point; the tuner
then tunes to the paper's first target, with the sensing-dot scan on the
QDAC-II's own DC sweep generator.

Every SCPI write the driver sends is recorded on the instrument's side
(``write_raw``) and checked against the limits: each fixed voltage inside
the gate's range and within one ``max_step_mv`` of the channel's previous
output, each programmed sweep inside the limits, starting within one step
of the output and stepping by at most one step.

The measured quantities come from the simulated double dot, kept at the
QDAC-II's outputs (as the other QCoDeS tests do with their simulated DAC).
"""

import re

import numpy as np
import pytest

from qcodes.dataset import initialise_or_create_database_at, load_or_create_experiment
from qcodes.instrument import Instrument
from qcodes.station import Station
from qcodes_contrib_drivers.drivers.QDevil.QDAC2 import QDac2

import spintune
from spintune.qcodes import QcodesTuner, ScanFailed, TuningFault, qdac2_dc_sweep

VOLT = re.compile(r"^sour(\d+):volt (\S+)$")
SWEEP = re.compile(r"^sour(\d+):swe:(star|stop|poin) (\S+)$")


class RecordingQDac2(QDac2):
    """The QDAC-II driver, with every SCPI write recorded as sent."""

    def __init__(self, *args, **kwargs):
        self.writes = []
        super().__init__(*args, **kwargs)

    def write_raw(self, cmd: str) -> None:
        self.writes.append(cmd)
        super().write_raw(cmd)


def instrument_events(writes, channel_gate):
    """The driver's writes as events: ("set", gate, mV) for a fixed voltage,
    ("sweep", gate, {"star", "stop", "poin"}) for a programmed sweep (when
    its three settings are complete)."""
    events = []
    pending = {}
    for w in writes:
        m = VOLT.match(w)
        if m and int(m.group(1)) in channel_gate:
            events.append(("set", channel_gate[int(m.group(1))], float(m.group(2)) * 1000.0))
            continue
        m = SWEEP.match(w)
        if m and int(m.group(1)) in channel_gate:
            gate = channel_gate[int(m.group(1))]
            p = pending.setdefault(gate, {})
            p[m.group(2)] = float(m.group(3))
            if {"star", "stop", "poin"} <= p.keys():
                events.append(("sweep", gate, pending.pop(gate)))
    return events


def check_instrument_side(events, limits, start_mv):
    """Every programmed voltage within the limits, every step within the
    gate's max_step_mv of the channel's previous output. Returns the number
    of fixed sets and of sweeps checked."""
    last = dict(start_mv)
    sets = sweeps = 0
    for kind, gate, value in events:
        lim = limits[gate]
        if kind == "set":
            mv = value
            assert lim["min_mv"] - 1e-6 <= mv <= lim["max_mv"] + 1e-6, (gate, mv, lim)
            assert abs(mv - last[gate]) <= lim["max_step_mv"] * (1 + 1e-9) + 1e-6, (gate, mv, last[gate])
            last[gate] = mv
            sets += 1
        else:
            a, b, n = value["star"] * 1000.0, value["stop"] * 1000.0, int(value["poin"])
            for mv in (a, b):
                assert lim["min_mv"] - 1e-6 <= mv <= lim["max_mv"] + 1e-6, (gate, mv, lim)
            assert abs(a - last[gate]) <= lim["max_step_mv"] * (1 + 1e-9) + 1e-6, (gate, a, last[gate])
            assert n >= 2 and abs(b - a) / (n - 1) <= lim["max_step_mv"] * (1 + 1e-9) + 1e-6, value
            last[gate] = b  # the generator leaves the channel at the last point
            sweeps += 1
    return sets, sweeps


@pytest.fixture()
def qdac_station(tmp_path):
    initialise_or_create_database_at(str(tmp_path / "qcodes.db"))
    exp = load_or_create_experiment("spintune-qdac2", sample_name="simulated double dot")
    qdac = RecordingQDac2(
        "qdac", address="GPIB::1::INSTR", pyvisa_sim_file="qcodes_contrib_drivers.sims:QDAC2.yaml"
    )
    try:
        device = spintune.SimulatedDevice({"seed": 11})
        names = [g["name"] for g in device.gates]
        channel_gate = {i + 1: name for i, name in enumerate(names)}
        gates = {name: qdac.channel(i + 1).dc_constant_V for i, name in enumerate(names)}
        station = Station(qdac)
        yield {
            "qdac": qdac,
            "device": device,
            "gates": gates,
            "channel_gate": channel_gate,
            "station": station,
            "exp": exp,
        }
    finally:
        Instrument.close_all()


def make_scans(qdac_station, counts):
    qdac, device, gates = qdac_station["qdac"], qdac_station["device"], qdac_station["gates"]

    def sync():
        """The double dot sees what the QDAC-II outputs."""
        out = {g: float(p.get()) * 1000.0 for g, p in gates.items()}
        r = device.execute({"request": "set_voltages", "voltages_mv": out})
        assert r["response"] == "voltages_set", r

    def raw(scan):
        sync()
        r = device.execute({"request": "measure", "scan": scan})
        outcome = r["outcome"]
        if outcome["kind"] != "raw":
            raise ScanFailed(outcome.get("reason", "failed"))
        counts[scan["kind"]] = counts.get(scan["kind"], 0) + 1
        return outcome["scan"]

    def sensing_dot(scan):
        """The sweep on the QDAC-II's own generator: programmed once, the
        digitizer (here: the simulator) records the trace."""
        sweep = scan["sweep"]
        channel = next(c for c, g in qdac_station["channel_gate"].items() if g == sweep["gate"])
        sync()
        param = gates[sweep["gate"]]
        start = param.get()
        ctx = qdac2_dc_sweep(qdac.channel(channel), sweep, dwell_s=1e-4)
        ctx.start()
        counts["hardware_sweeps"] = counts.get("hardware_sweeps", 0) + 1
        r = device.execute({"request": "measure", "scan": scan})
        # back to fixed mode where the gate was (one half-width from the
        # sweep's last point): `sour:volt?` reads the fixed level, not the
        # generator's last point, so the read-back must be the output again
        param.set(start)
        outcome = r["outcome"]
        if outcome["kind"] != "raw":
            raise ScanFailed(outcome.get("reason", "failed"))
        return outcome["scan"]

    return {
        "reload_time": raw,
        "transition_width": raw,
        "chemical_potential": raw,
        "sensing_dot": sensing_dot,
    }


def test_qdac2_from_reset_ramp_then_tune_within_limits(qdac_station, capsys):
    qdac, gates = qdac_station["qdac"], qdac_station["gates"]
    # the instrument's reset state: every channel at 0 V
    assert all(float(p.get()) == 0.0 for p in gates.values())
    counts = {}
    tuner = QcodesTuner(
        gates,
        make_scans(qdac_station, counts),
        {"max_iterations": 15, "stop_when_tuned": True},
        experiment=qdac_station["exp"],
        station=qdac_station["station"],
        name="qdac2",
        inter_delay_s=0.0,
    )
    limits = tuner.limits
    # 1. From 0 V the tuner refuses, naming the gate, the read-back and the range.
    n0 = len(qdac.writes)
    with pytest.raises(TuningFault) as refused:
        tuner.run()
    msg = str(refused.value)
    m = re.search(r"gate (\w+) reads 0 mV, outside its limits \[(\S+), (\S+)\] mV", msg)
    assert m, msg
    gate = m.group(1)
    assert (float(m.group(2)), float(m.group(3))) == (limits[gate]["min_mv"], limits[gate]["max_mv"])
    assert "ramp_to" in msg
    assert not instrument_events(qdac.writes[n0:], qdac_station["channel_gate"]), "nothing may move"
    assert tuner.status["state"] == "faulted"

    # 2. ramp_to: the working point (the config's initial_mv), within the
    # travel range (the driver's validator, ±10 V) in steps of max_step_mv.
    n1 = len(qdac.writes)
    final = tuner.ramp_to()
    travel = {g["name"]: g for g in tuner.travel_limits()}
    assert travel["SD1"]["min_mv"] == pytest.approx(-10000.0) and travel["SD1"]["max_mv"] == pytest.approx(10000.0)
    ramp_events = instrument_events(qdac.writes[n1:], qdac_station["channel_gate"])
    sets, _ = check_instrument_side(ramp_events, travel, {g: 0.0 for g in gates})
    initial = {g["name"]: g["initial_mv"] for g in tuner.tuner_config["gates"]}
    # SA: 0 → -820 mV at 10 mV a step: 82 sets, every gate moved in the same sets
    assert sets >= 82
    assert final == pytest.approx(initial, abs=1e-6)
    assert {g: float(p.get()) * 1000.0 for g, p in gates.items()} == pytest.approx(initial, abs=1e-6)
    assert "ramp to the working point" in capsys.readouterr().err  # the progress bar (tqdm)

    # 3. Tune: every programmed step, fixed or swept, within the tuning limits.
    n2 = len(qdac.writes)
    tuner.run()
    assert tuner.status["state"] == "finished", tuner.status
    last = tuner.records[-1]
    assert last["tuned"], [(p["name"], p["value"]) for p in last["parameters"]]
    t_sr, w = (p["value"] for p in last["parameters"])
    assert abs(t_sr - 20.0) <= 2.0 and abs(w - 270.0) <= 27.0  # ns, µV
    events = instrument_events(qdac.writes[n2:], qdac_station["channel_gate"])
    sets, sweeps = check_instrument_side(events, limits, initial)
    assert sets > 0 and sweeps > 0
    assert sweeps == counts["hardware_sweeps"]
    # the sweeps were programmed, not stepped by VISA sets: far fewer writes
    # than 201 sets per sweep
    assert sets < 201 * sweeps

    # the QCoDeS dataset as xarray: integer iterations, UDUNITS units
    x = tuner.to_xarray()
    assert x["iteration"].dtype == np.int64
    assert list(x["iteration"].values) == [r["iteration"] for r in tuner.records]
    assert x["w"].attrs["units"] == "uV" and x["t_sr"].attrs["units"] == "ns"
    assert x["grad_w_T"].attrs["units"] == "uV/mV"

    # a second ramp is refused: the run knows where it left the gates
    with pytest.raises(RuntimeError, match="before the first run"):
        tuner.ramp_to()


def test_ramp_to_refuses_a_gate_outside_its_travel_range(qdac_station):
    gates = qdac_station["gates"]
    gates["SD1"].set(0.0)
    tuner = QcodesTuner(
        gates,
        make_scans(qdac_station, {}),
        {"max_iterations": 1},
        experiment=qdac_station["exp"],
        inter_delay_s=0.0,
    )
    n = len(qdac_station["qdac"].writes)
    with pytest.raises(ValueError) as e:
        tuner.ramp_to(travel_limits_mv={"SD1": (-800.0, -100.0)}, progress=False)
    assert "SD1 reads 0 mV, outside [-800, -100] mV" in str(e.value), e.value
    assert not instrument_events(qdac_station["qdac"].writes[n:], qdac_station["channel_gate"])
    # a working point outside the tuning limits is refused before anything is read
    with pytest.raises(ValueError, match="SD1: target -900 mV is outside \\[-750, -450\\] mV"):
        tuner.ramp_to({"SD1": -900.0})
    with pytest.raises(ValueError, match="unknown gates XX"):
        tuner.ramp_to({"XX": 0.0})


def test_qdac2_dc_sweep_programs_exactly_the_checked_points(qdac_station):
    qdac = qdac_station["qdac"]
    sweep = {"gate": "SD1", "from_mv": -610.0, "to_mv": -590.0, "points": 201}
    ctx = qdac2_dc_sweep(qdac.ch07, sweep)
    np.testing.assert_allclose(np.asarray(ctx.values_V()) * 1000.0, np.linspace(-610.0, -590.0, 201), atol=1e-9)
    programmed = [w for w in qdac.writes if w.startswith("sour7:swe:")]
    assert "sour7:swe:star -0.61" in programmed and "sour7:swe:stop -0.59" in programmed
    assert "sour7:swe:poin 201" in programmed
