"""Issue 26's rough edges: NaN named, one config error format, pickling
through checkpoints, the src layout (the tests import the installed wheel)."""

import math
import os
import pathlib
import pickle
import re
import subprocess
import sys

import numpy as np
import pytest

import spintune
from conftest import REPO

#: The one format of config errors (the core's ``ConfigError``).
CONFIG_ERROR = re.compile(r"^invalid config( at `[^`]+`)?: ")


def config_error(f, *args):
    with pytest.raises(ValueError) as e:
        f(*args)
    msg = str(e.value)
    assert CONFIG_ERROR.match(msg), msg
    assert msg.count(" at `") <= 1, f"the path is said twice: {msg}"
    return msg


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, np.float64("nan")])
def test_a_nan_target_names_the_field(bad):
    msg = config_error(spintune.SimulationRun, {"targets": {"t_sr": bad}})
    assert msg.startswith("invalid config at `targets.t_sr`: "), msg
    assert "not a finite number" in msg and "null" not in msg, msg
    msg = config_error(spintune.resolve_config, {"tuner": {"gates": [{"name": "N", "min_mv": bad}]}})
    assert msg.startswith("invalid config at `tuner.gates[0].min_mv`: "), msg
    msg = config_error(spintune.RunSession, {"levels": [{"parameters": [{"target": bad}]}]})
    assert msg.startswith("invalid config at `tuner.levels[0].parameters[0].target`: "), msg


def test_a_nan_target_in_a_control_command_names_the_field():
    session = spintune.RunSession({"max_iterations": 1})
    with pytest.raises(ValueError) as e:
        session.control({"action": "set_target", "parameter": "t_sr", "target": math.nan})
    msg = str(e.value)
    assert "target" in msg and "null" not in msg and "finite" in msg, msg


def test_one_format_for_config_errors():
    # the tuner table of a RunSession: paths below `tuner`
    msg = config_error(spintune.RunSession, {"levels": [{"kind": "bogus"}]})
    assert msg.startswith("invalid config at `tuner.levels"), msg
    msg = config_error(spintune.RunSession, {"max_iterations": "many"})
    assert msg.startswith("invalid config at `tuner.max_iterations`: "), msg
    msg = config_error(spintune.resolve_tuner_config, {"gates": [{"name": "N"}]})
    assert msg.startswith("invalid config at `tuner.gates"), msg
    # a whole run config
    msg = config_error(spintune.resolve_config, {"tuner": {"max_iterations": "many"}})
    assert msg.startswith("invalid config at `tuner.max_iterations`: "), msg
    msg = config_error(spintune.SimulationRun, {"driver": "scpi"})
    assert msg.startswith("invalid config at `driver`: "), msg
    msg = config_error(spintune.SimulationRun, {"scpi": {}})
    assert msg.startswith("invalid config at `scpi`: "), msg
    msg = config_error(spintune.SimulationRun, {"targets": {"t_sr": "twenty"}})
    assert msg.startswith("invalid config at `targets.t_sr`: "), msg
    msg = config_error(spintune.SimulationRun, {"targets": {"t_sr": -50.0}})
    assert msg.startswith("invalid config at `targets.t_sr`: "), msg
    msg = config_error(spintune.SimulationRun, {"tolerances": {"w": {"relative": "x"}}})
    assert msg.startswith("invalid config at `tolerances.w"), msg
    config_error(spintune.SimulationRun, [1, 2])
    config_error(spintune.RunSession, "tuner")


def test_kalman_gradient_pickles_through_its_checkpoint():
    f = spintune.KalmanGradient([1.0, -2.0, 0.5], np.eye(3) * 0.3, 1e-3, outlier_sigma=4.0, min_step_mv=1e-3)
    rng = np.random.default_rng(1)
    for _ in range(5):
        f.update(rng.normal(size=3), rng.normal(), 0.1)
    g = pickle.loads(pickle.dumps(f))
    assert type(g) is spintune.KalmanGradient
    assert g.gradient.tobytes() == f.gradient.tobytes()
    assert g.covariance.tobytes() == f.covariance.tobytes()
    assert (g.outlier_sigma, g.min_step_mv) == (4.0, 1e-3)
    for _ in range(5):
        dv, dz = rng.normal(size=3), rng.normal()
        assert f.update(dv, dz, 0.1) == g.update(dv, dz, 0.1)
    assert g.gradient.tobytes() == f.gradient.tobytes()
    assert spintune.KalmanGradient.restore(f.checkpoint()).covariance.tobytes() == f.covariance.tobytes()
    with pytest.raises(ValueError, match="invalid checkpoint"):
        spintune.KalmanGradient.restore("{}")


def test_simulation_run_pickles_and_continues_bit_for_bit():
    run = spintune.SimulationRun({"seed": 4, "tuner": {"max_iterations": 5}})
    run.run(max_iterations=2)
    copy = pickle.loads(pickle.dumps(run))
    assert type(copy) is spintune.SimulationRun
    assert copy.records == run.records and copy.config == run.config
    assert copy.status == run.status and copy.voltages_mv == run.voltages_mv
    assert copy.run() == run.run()
    assert len(run.records) == 5 and run.status == {"state": "finished"}


def test_run_session_pickles_and_reads_every_gate_first():
    device = spintune.SimulatedDevice({"seed": 2})
    session = spintune.RunSession({"max_iterations": 3})
    commits = 0
    while commits < 1:
        out = session.poll()
        if out["output"] == "execute":
            session.feed(device.execute(out["request"]))
        elif out["output"] == "commit":
            commits += 1
    copy = pickle.loads(pickle.dumps(session))
    assert type(copy) is spintune.RunSession
    assert copy.checkpoint() == session.checkpoint()
    assert copy.readback_mv == {}  # read-backs are never restored
    out = copy.poll()
    assert out["output"] == "execute" and out["request"]["request"] == "read_voltages", out
    assert set(out["request"]["gates"]) == {g["name"] for g in copy.tuner_config["gates"]}


def test_the_tests_import_the_installed_package_not_the_source_tree():
    here = pathlib.Path(spintune.__file__).resolve()
    assert REPO not in here.parents, f"spintune imported from the source tree: {here}"
    # `python -m pytest` inside python/ puts python/ on sys.path: the
    # package's Python sources live in python/pysrc, so nothing shadows it
    out = subprocess.run(
        [sys.executable, "-c", "import spintune, spintune._core; print(spintune.__file__)"],
        cwd=REPO / "python",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert REPO not in pathlib.Path(out.stdout.strip()).resolve().parents, out.stdout
    assert not (REPO / "python" / "spintune").exists()
    assert (REPO / "python" / "pysrc" / "spintune" / "__init__.py").is_file()
    assert os.path.isfile(os.path.join(os.path.dirname(spintune.__file__), "py.typed"))
