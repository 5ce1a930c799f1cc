"""Shared helpers of the Python package tests (run by `cargo xtask test`,
which installs the package into its virtual environment and sets
SPINTUNE_BIN to the debug `spintune` binary)."""

import hashlib
import json
import os
import pathlib
import subprocess

import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]


def canonical_hash(value) -> str:
    """SHA-256 of canonical JSON (sorted keys, no NaN)."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


@pytest.fixture(scope="session")
def spintune_bin() -> pathlib.Path:
    """The `spintune` binary (the Rust core behind a CLI)."""
    candidates = []
    if os.environ.get("SPINTUNE_BIN"):
        candidates.append(pathlib.Path(os.environ["SPINTUNE_BIN"]))
    else:
        target = os.environ.get(
            "CARGO_TARGET_DIR", str(pathlib.Path.home() / ".cache/spintune/target")
        )
        candidates.append(pathlib.Path(target) / "debug" / "spintune")
    for c in candidates:
        if c.is_file():
            return c
    pytest.fail(
        f"the spintune binary was not found ({', '.join(map(str, candidates))}); "
        "run the tests with `cargo xtask test`, or build it (`cargo build -p spintune-server`) "
        "and set SPINTUNE_BIN"
    )


@pytest.fixture(scope="session")
def run_cli(spintune_bin):
    def run(*args, cwd=None, input=None):
        out = subprocess.run(
            [str(spintune_bin), *map(str, args)],
            cwd=cwd,
            input=input,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert out.returncode == 0, f"spintune {args} failed ({out.returncode}):\n{out.stderr}"
        return out.stdout

    return run


def assert_units(ds):
    """UDUNITS-clean: every numeric data variable has a unit, none is
    spelt with a micro sign; the coordinates (iteration numbers, gate names)
    and the bool ``tuned`` carry none (a plot would show ``iteration [1]``)."""
    for name, var in ds.data_vars.items():
        if var.dtype == bool:
            assert "units" not in var.attrs, name
        else:
            assert "units" in var.attrs, name
            assert "µ" not in var.attrs["units"] and "μ" not in var.attrs["units"], (name, var.attrs)
    for name, var in ds.coords.items():
        assert "units" not in var.attrs, name
    assert ds["iteration"].dtype == np.int64
