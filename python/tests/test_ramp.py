"""spintune.Ramp: the core's ramp to a working point, through the guard."""

import pytest

import spintune

GATES = [
    {"name": "A", "min_mv": -1000.0, "max_mv": 100.0, "max_step_mv": 10.0},
    {"name": "B", "min_mv": -1000.0, "max_mv": 100.0, "max_step_mv": 30.0, "initial_mv": -5.0},
]


def drive(ramp, dac, offset=0.0):
    sets = []
    while True:
        out = ramp.poll()
        if out["output"] == "done":
            return sets
        req = out["request"]
        if req["request"] == "read_voltages":
            ramp.feed({"response": "voltages_read", "voltages_mv": {g: dac[g] for g in req["gates"]}})
        else:
            assert req["request"] == "set_voltages", req
            for g, v in req["voltages_mv"].items():
                step = {"A": 10.0, "B": 30.0}[g]
                assert abs(v - dac[g]) <= step * (1 + 1e-12), (g, v, dac[g])
                dac[g] = v + offset
            sets.append(dict(req["voltages_mv"]))
            ramp.feed(
                {
                    "response": "voltages_set",
                    "voltages_mv": {g: dac[g] for g in req["voltages_mv"]},
                    "lab_seconds": 0.0,
                }
            )
        assert ramp.steps_done == len(sets)


def test_ramps_all_gates_together_within_steps():
    ramp = spintune.Ramp(GATES, {"A": -95.0, "B": -600.0})
    assert ramp.steps_planned is None
    dac = {"A": 0.0, "B": 0.0}
    sets = drive(ramp, dac)
    assert len(sets) == 20 == ramp.steps_planned
    assert dac == {"A": -95.0, "B": -600.0}
    assert ramp.readback_mv == dac
    assert all(set(s) == {"A", "B"} for s in sets[:-1])


def test_refusals_name_the_gate_the_read_back_and_the_range():
    ramp = spintune.Ramp(GATES, {"B": -600.0})
    with pytest.raises(ValueError, match=r"B reads 500 mV, outside \[-1000, 100\] mV"):
        drive(ramp, {"B": 500.0})
    with pytest.raises(ValueError, match="B reads 500 mV"):
        ramp.poll()  # over: nothing more is requested
    with pytest.raises(ValueError, match=r"A: target 200 mV is outside \[-1000, 100\] mV"):
        spintune.Ramp(GATES, {"A": 200.0})
    with pytest.raises(ValueError, match="not a gate of the ramp"):
        spintune.Ramp(GATES, {"C": 0.0})
    with pytest.raises(ValueError, match="max_step_mv"):
        spintune.Ramp([{"name": "A", "min_mv": 0.0, "max_mv": 1.0, "max_step_mv": 0.0}], {"A": 0.5})
    with pytest.raises(ValueError, match="invalid gates"):
        spintune.Ramp([{"name": "A"}], {"A": 0.5})


def test_a_read_back_off_the_set_value_ends_the_ramp():
    ramp = spintune.Ramp(GATES, {"A": -100.0})
    with pytest.raises(ValueError, match="read-back refused"):
        drive(ramp, {"A": 0.0}, offset=1.0)
    assert ramp.steps_done == 1
    with pytest.raises(RuntimeError, match="no request is outstanding"):
        spintune.Ramp(GATES, {"A": -100.0}).feed({"response": "voltages_read", "voltages_mv": {}})


def test_a_device_error_ends_the_ramp():
    ramp = spintune.Ramp(GATES, {"A": -100.0})
    ramp.poll()
    with pytest.raises(ValueError, match="instrument failed: VISA timeout"):
        ramp.feed({"response": "error", "message": "VISA timeout"})
