"""examples/notebook_tuning.py runs top to bottom (with few iterations)."""

import os
import subprocess
import sys

from conftest import REPO


def test_notebook_example_runs(tmp_path):
    env = dict(os.environ, SPINTUNE_EXAMPLE_ITERATIONS="3", SPINTUNE_EXAMPLE_OUT=str(tmp_path), MPLBACKEND="Agg")
    out = subprocess.run(
        [sys.executable, str(REPO / "examples" / "notebook_tuning.py")],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "learned gradient" in out.stdout and "QCoDeS dataset" in out.stdout
    assert (tmp_path / "simulated_run.nc").is_file() and (tmp_path / "experiments.db").is_file()


def test_background_run_example_runs(tmp_path):
    """python/examples/background_run.py: a run in a thread, watched and
    retargeted from the main thread, an endless run stopped from it."""
    env = dict(os.environ, SPINTUNE_EXAMPLE_ITERATIONS="8", SPINTUNE_EXAMPLE_OUT=str(tmp_path), MPLBACKEND="Agg")
    out = subprocess.run(
        [sys.executable, str(REPO / "python" / "examples" / "background_run.py")],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "run ended: finished after 8 iterations" in out.stdout, out.stdout
    assert "stopping: {'state': 'stopped'}" in out.stdout, out.stdout
    assert "thread alive: False" in out.stdout, out.stdout
