"""examples/notebook_tuning.py runs top to bottom (with few iterations)."""

import os
import subprocess
import sys

from conftest import REPO


def run_example(script, iterations, tmp_path):
    """Run an example script with few iterations, its outputs in `tmp_path`;
    the finished process (it must exit 0)."""
    env = dict(os.environ, SPINTUNE_EXAMPLE_ITERATIONS=str(iterations), SPINTUNE_EXAMPLE_OUT=str(tmp_path), MPLBACKEND="Agg")
    out = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    return out


def test_notebook_example_runs(tmp_path):
    out = run_example(REPO / "examples" / "notebook_tuning.py", 3, tmp_path)
    assert "learned gradient" in out.stdout and "QCoDeS dataset" in out.stdout
    assert (tmp_path / "simulated_run.nc").is_file() and (tmp_path / "experiments.db").is_file()


def test_background_run_example_runs(tmp_path):
    """python/examples/background_run.py: a run in a thread, watched and
    retargeted from the main thread, an endless run stopped from it."""
    out = run_example(REPO / "python" / "examples" / "background_run.py", 8, tmp_path)
    assert "run ended: finished after 8 iterations" in out.stdout, out.stdout
    assert "stopping: {'state': 'stopped'}" in out.stdout, out.stdout
    assert "thread alive: False" in out.stdout, out.stdout
