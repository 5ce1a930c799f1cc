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
