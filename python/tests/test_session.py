"""spintune.RunSession: a Python driver loop (poll/feed/control) over the
core session. The safety checks are the core's; these tests only show that
the Python surface reaches them and mirrors the JSON shapes."""

import json

import numpy as np
import pytest

import spintune
from conftest import canonical_hash


def drive(session, device, max_outputs=100_000, on_commit=None):
    """The loop of the class docstring; returns (records, outputs seen)."""
    records, outputs = [], []
    for _ in range(max_outputs):
        out = session.poll()
        outputs.append(out["output"])
        if out["output"] == "execute":
            session.feed(device.execute(out["request"]))
        elif out["output"] == "commit":
            records.append(out["record"])
            if on_commit:
                on_commit(out["record"])
        elif out["output"] in ("wait", "done"):
            break
    return records, outputs


def test_python_loop_equals_simulation_run():
    config = {"seed": 8, "tuner": {"max_iterations": 3}}
    cfg = spintune.resolve_config(config)
    session = spintune.RunSession(cfg["tuner"])
    device = spintune.SimulatedDevice(config)
    records, outputs = drive(session, device)
    assert outputs[0] == "publish" and outputs[-1] == "done"
    assert session.status == {"state": "finished"}
    assert session.poll() == {"output": "done", "end": "finished"}
    expected = spintune.SimulationRun(config).run()
    assert canonical_hash(records) == canonical_hash(expected)


def test_output_and_request_shapes():
    s = spintune.RunSession({"max_iterations": 1})
    assert s.poll() == {"output": "publish", "status": {"state": "running"}}
    out = s.poll()
    gates = [g["name"] for g in s.tuner_config["gates"]]
    # every gate is read from the instrument before anything moves
    assert out == {"output": "execute", "request": {"request": "read_voltages", "gates": gates}}
    assert s.poll() == out  # still outstanding
    assert s.has_request_in_flight


def read_all(session, device):
    out = session.poll()
    assert out["request"]["request"] == "read_voltages"
    session.feed(device.execute(out["request"]))


def next_execute(session):
    while True:
        out = session.poll()
        if out["output"] == "execute":
            return out["request"]
        assert out["output"] in ("publish", "save", "sleep"), out


def test_lying_readback_faults_and_resume_reads_back_first():
    s = spintune.RunSession({"max_iterations": 2})
    dev = spintune.SimulatedDevice()
    s.poll()
    read_all(s, dev)
    req = next_execute(s)
    while req["request"] != "set_voltages":
        s.feed(dev.execute(req))
        req = next_execute(s)
    answer = dev.execute(req)
    gate = next(iter(answer["voltages_mv"]))
    answer["voltages_mv"][gate] += 1.0  # the instrument reports 1 mV elsewhere
    s.feed(answer)
    status = s.status
    assert status["state"] == "faulted" and status["fault"]["kind"] == "readback"
    assert gate in status["fault"]["message"]
    assert s.poll()["output"] == "publish"
    assert s.poll() == {"output": "wait"}  # nothing goes to the device
    assert s.readback_mv.get(gate) is None
    s.control({"action": "resume"})
    first = next_execute(s)
    assert first["request"] == "read_voltages" and len(first["gates"]) == 11


def test_every_set_is_within_limits_and_one_step_of_the_read_back():
    # The instrument reads N 50 mV away from the config's start voltage: the
    # core starts from the read-back (and walks N back to its plan), and
    # every request it hands out stays within the gate limits and one
    # max_step_mv of the last read-back.
    s = spintune.RunSession({"max_iterations": 3})
    spec = {g["name"]: g for g in s.tuner_config["gates"]}
    dev = spintune.SimulatedDevice()
    for v in (-690.0, -680.0, -670.0, -660.0, -650.0):
        dev.execute({"request": "set_voltages", "voltages_mv": {"N": v}})
    last = {}
    sets = 0
    for _ in range(20_000):
        out = s.poll()
        if out["output"] in ("wait", "done"):
            break
        if out["output"] != "execute":
            continue
        req = out["request"]
        if req["request"] == "set_voltages":
            sets += 1
            for g, v in req["voltages_mv"].items():
                assert spec[g]["min_mv"] <= v <= spec[g]["max_mv"]
                assert abs(v - last[g]) <= spec[g]["max_step_mv"] * (1 + 1e-9) + 1e-12, (g, v, last[g])
        resp = dev.execute(req)
        if resp["response"] in ("voltages_set", "voltages_read"):
            last.update(resp["voltages_mv"])
        s.feed(resp)
    assert s.status == {"state": "finished"} and sets > 10


def test_stop_pause_and_control_errors():
    s = spintune.RunSession()
    dev = spintune.SimulatedDevice()
    s.poll()
    req = next_execute(s)
    assert s.control({"action": "pause"}) == {"state": "paused"}
    assert s.poll()["output"] == "publish"
    assert s.poll() == {"output": "wait"}  # the outstanding answer is still expected, nothing new
    s.feed(dev.execute(req))
    assert s.control({"action": "stop"}) == {"state": "stopped"}
    outs = [s.poll() for _ in range(4)]
    assert outs[0] == {"output": "publish", "status": {"state": "stopped"}}
    # the answered request was the new run's first read-back: its positions are saved
    assert outs[1] == {"output": "save"}
    assert outs[2:] == [{"output": "done", "end": "stopped"}] * 2
    with pytest.raises(RuntimeError, match="stopped"):
        s.control({"action": "resume"})
    with pytest.raises(RuntimeError, match="no request"):
        s.feed({"response": "error", "message": "x"})


def test_targets_out_of_bounds_are_refused_naming_the_parameter():
    s = spintune.RunSession()
    s.poll()
    for target, needle in [(-50.0, "> 0"), (1e8, "at most")]:
        with pytest.raises(ValueError, match="t_sr") as e:
            s.control({"action": "set_target", "parameter": "t_sr", "target": target})
        assert needle in str(e.value)
    with pytest.raises(ValueError, match="targets.t_sr"):
        spintune.resolve_config({"targets": {"t_sr": -50.0}})


def test_bad_dicts_raise_value_error_naming_the_field():
    s = spintune.RunSession()
    s.poll()
    s.poll()
    with pytest.raises(ValueError, match="response"):
        s.feed({"response": "voltages_sent"})
    # (serde's internally tagged enums do not keep the field path here)
    with pytest.raises(ValueError, match="invalid response.*expected f64"):
        s.feed({"response": "voltages_read", "voltages_mv": {"N": "high"}})
    assert s.has_request_in_flight  # nothing changed
    with pytest.raises(ValueError, match="t_srr|parameter"):
        s.control({"action": "set_target", "parameter": "t_srr", "target": 1.0})
    with pytest.raises(ValueError, match="action"):
        s.control({"action": "jump"})
    with pytest.raises(ValueError, match="readback_tolerance_mv"):
        spintune.RunSession(readback_tolerance_mv=-1.0)
    with pytest.raises(ValueError, match="tuner.gates"):
        spintune.RunSession({"gates": [{"name": "N", "min_mv": 0, "max_mv": -1, "initial_mv": 0}]})


def test_numpy_answers_and_evaluated_values():
    # A scan answered with numpy arrays (raw) or evaluated values: both accepted.
    s = spintune.RunSession({"max_iterations": 1})
    dev = spintune.SimulatedDevice()
    kinds = set()
    for _ in range(10_000):
        out = s.poll()
        if out["output"] in ("done", "wait"):
            break
        if out["output"] != "execute":
            continue
        resp = dev.execute(out["request"])
        if resp["response"] == "scanned" and resp["outcome"]["kind"] == "raw":
            scan = resp["outcome"]["scan"]
            kinds.add(scan["kind"])
            if scan["kind"] == "reload_time":
                truth = dev.truth()
                resp["outcome"] = {
                    "kind": "evaluated",
                    "values": [{"name": "t_sr", "value": np.float64(truth["t_sr"]), "variance": np.float32(0.25)}],
                }
            else:
                for t in scan["traces"]:
                    t["x"], t["y"] = np.asarray(t["x"]), np.asarray(t["y"])
        s.feed(resp)
    assert s.status == {"state": "finished"}
    assert "transition_width" in kinds and "reload_time" in kinds


def test_checkpoint_restore_reads_every_gate_first():
    s = spintune.RunSession({"max_iterations": 3})
    dev = spintune.SimulatedDevice()
    records, _ = drive(s, dev, on_commit=lambda r: s.control({"action": "pause"}))
    assert len(records) == 1 and s.status == {"state": "paused"}
    text = s.checkpoint()
    json.loads(text)
    r = spintune.RunSession.restore(text)
    assert r.readback_mv == {}
    r.control({"action": "resume"})
    assert next_execute(r)["request"] == "read_voltages"
    more, _ = drive(r, dev)
    assert [x["iteration"] for x in more] == [1, 2]
    with pytest.raises(ValueError, match="checkpoint"):
        spintune.RunSession.restore("{}")


def test_sleep_after_each_iteration():
    s = spintune.RunSession({"max_iterations": 2}, iteration_delay_ms=250)
    _, outputs = drive(s, spintune.SimulatedDevice())
    assert outputs.count("commit") == 2
    i = outputs.index("commit")
    assert outputs[i + 1] == "sleep"
