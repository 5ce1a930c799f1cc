"""spintune.SimulationRun against the real `spintune run` binary (bit-identical
records), the config rules, open_store and the xarray/netCDF export."""

import json

import numpy as np
import pytest
import xarray as xr

import spintune
from conftest import REPO, assert_units, canonical_hash

CONFIGS = [
    # (TOML for `spintune run`, the same config as a Python dict)
    (
        'name = "bit-identity"\nseed = 3\n[tuner]\nmax_iterations = 4\nstop_when_tuned = false\n',
        {"name": "bit-identity", "seed": 3, "tuner": {"max_iterations": 4, "stop_when_tuned": False}},
    ),
    (
        'name = "other target"\nseed = 11\n[targets]\nt_sr = 30.0\nw = 250.0\n'
        "[tolerances]\nw = { absolute = 10.0 }\n[tuner]\nmax_iterations = 5\n",
        {
            "name": "other target",
            "seed": 11,
            "targets": {"t_sr": 30.0, "w": 250.0},
            "tolerances": {"w": {"absolute": 10.0}},
            "tuner": {"max_iterations": 5},
        },
    ),
]


@pytest.mark.parametrize("toml,config", CONFIGS, ids=["paper-default-seed3", "targets-seed11"])
def test_bit_identical_to_the_rust_run(tmp_path, run_cli, toml, config):
    (tmp_path / "run.toml").write_text(toml)
    db = tmp_path / "runs.db"
    run_cli("run", "--config", tmp_path / "run.toml", "--db", db, "--quiet")
    stored = spintune.open_store(db)
    assert len(stored) == 1
    (srun,) = stored.runs
    assert srun.status == {"state": "finished"}
    run = spintune.SimulationRun(config)
    records = run.run()
    assert len(records) == srun.iterations == config["tuner"]["max_iterations"]
    assert canonical_hash(records) == canonical_hash(srun.records)
    assert records == srun.records
    # the same config, as the server stored it
    assert canonical_hash(run.config) == canonical_hash(srun.simulation_config)
    again = spintune.SimulationRun(srun.simulation_config)
    assert canonical_hash(list(again)) == canonical_hash(srun.records)


def test_example_toml_runs_from_python():
    tomllib = pytest.importorskip("tomllib", reason="tomllib needs Python ≥ 3.11")

    with open(REPO / "examples" / "paper-first-target.toml", "rb") as f:
        config = tomllib.load(f)
    config["tuner"]["max_iterations"] = 12
    run = spintune.SimulationRun(config)
    records = run.run()
    assert records[-1]["tuned"]  # stop_when_tuned: it finished at the first tuned iteration
    assert run.status == {"state": "finished"}
    assert [p["target"] for p in records[-1]["parameters"]] == [20.0, 270.0]


def test_record_fields_and_iteration_protocol():
    run = spintune.SimulationRun({"tuner": {"max_iterations": 3}})
    first = next(run)
    assert set(first) == {
        "iteration", "voltages_mv", "gates", "parameters", "gradients", "step_mv", "tuned",
        "lab_seconds", "scan_counts", "failed_evaluations", "scans", "events",
    }
    assert first["iteration"] == 0 and first["gates"] == ["N", "SA", "SB", "T"]
    assert [p["unit"] for p in first["parameters"]] == ["ns", "µV"]
    # pause: iteration stops, the status says why, resume continues
    assert run.control({"action": "pause"}) == {"state": "paused"}
    assert list(run) == []
    run.control({"action": "resume"})
    run.control({"action": "set_target", "parameter": "w", "target": 300.0})
    rest = list(run)
    assert [r["iteration"] for r in rest] == [1, 2]
    assert rest[-1]["parameters"][1]["target"] == 300.0
    assert len(run.records) == 3 and run.status == {"state": "finished"}
    with pytest.raises(RuntimeError, match="finished"):
        run.control({"action": "resume"})
    with pytest.raises(ValueError, match="action"):
        run.control({"action": "explode"})
    t = run.truth()
    assert 5.0 < t["t_sr"] < 100.0 and 100.0 < t["w"] < 500.0
    assert set(run.voltages_mv) >= {"N", "SA", "SB", "T", "PA", "PB"}


def test_same_seed_same_records_other_seed_differs():
    a = spintune.SimulationRun({"seed": 4, "tuner": {"max_iterations": 2}}).run()
    b = spintune.SimulationRun({"seed": 4, "tuner": {"max_iterations": 2}}).run()
    c = spintune.SimulationRun({"seed": 5, "tuner": {"max_iterations": 2}}).run()
    assert canonical_hash(a) == canonical_hash(b) != canonical_hash(c)


@pytest.mark.parametrize(
    "config,field",
    [
        ({"seed": "abc"}, "seed"),
        ({"bogus": 1}, "bogus"),
        ({"targets": {"nope": 1.0}}, "targets.nope"),
        ({"tolerances": {"w": {"relative": -1.0}}}, "tolerances.w"),
        ({"driver": "scpi"}, "driver"),
        ({"bridge": {}}, "bridge"),
        ({"tuner": {"gates": []}}, "gates"),
        ({"tuner": {"max_iterations": -1}}, "max_iterations"),
        ({"tuner": {"levels": [{"name": "x", "kind": "newton"}]}}, "levels"),
        ([1, 2], "dict"),
    ],
)
def test_bad_config_raises_value_error_naming_the_field(config, field):
    with pytest.raises(ValueError, match=field):
        spintune.SimulationRun(config)


def test_resolve_config_is_the_merge_of_the_run_config():
    default = spintune.default_config()
    assert spintune.resolve_config(None) == default
    merged = spintune.resolve_config({"seed": 9, "device": {}, "tuner": {"max_iterations": 7}})
    assert merged["seed"] == 9 and merged["tuner"]["max_iterations"] == 7
    assert merged["tuner"]["levels"] == default["tuner"]["levels"]
    assert spintune.resolve_tuner_config({"max_iterations": 7}) == merged["tuner"]


LAB_DESCRIPTION = {
    "gates": [
        {"name": "N", "min_mv": -900, "max_mv": -500, "initial_mv": -700},
        {"name": "T", "min_mv": -850, "max_mv": -450, "initial_mv": -650},
        {"name": "SA", "min_mv": -1020, "max_mv": -620, "initial_mv": -820},
        {"name": "SB", "min_mv": -980, "max_mv": -580, "initial_mv": -780},
        {"name": "PA", "min_mv": -550, "max_mv": -50, "initial_mv": -300, "max_step_mv": 30},
        {"name": "PB", "min_mv": -570, "max_mv": -70, "initial_mv": -320, "max_step_mv": 30},
        {"name": "SD1", "min_mv": -750, "max_mv": -450, "initial_mv": -600, "max_step_mv": 30},
    ],
    "qubit": {"gates": ["N", "SA", "SB", "T"]},
    "lines": {"gates": ["PA", "PB"],
              "compensation": [[-0.36, -0.50, 0.0042, -0.039], [-0.12, 0.013, -0.50, -0.46]]},
    "sensing_dot": {"gate": "SD1"},
}


def test_the_default_is_the_recommended_strategy_and_the_paper_rule_a_choice():
    top = spintune.default_config()["tuner"]["levels"][0]
    assert [p["transform"] for p in top["parameters"]] == ["log", "log"]
    assert top["solver"]["max_moves_per_iteration"] == 2
    paper = spintune.paper_config()["tuner"]["levels"][0]
    assert [p["transform"] for p in paper["parameters"]] == ["linear", "linear"]
    assert paper["solver"]["rule"] == "pseudo_inverse"


def test_a_device_description_derives_the_levels_and_tunes_the_simulator():
    tuner = spintune.resolve_tuner_config({"description": LAB_DESCRIPTION, "max_iterations": 30})
    assert [l["name"] for l in tuner["levels"]] == ["qubit", "chemical_potential", "sensing_dot"]
    assert tuner["max_iterations"] == 30
    run = spintune.SimulationRun({
        "description": LAB_DESCRIPTION,
        "targets": {"t_sr": 20.0, "w": 270.0},
        "tuner": {"max_iterations": 30, "stop_when_tuned": True},
    })
    records = run.run()
    assert records and records[-1]["tuned"]
    with pytest.raises(ValueError, match=r"description\.qubit\.gates\[1\]"):
        spintune.resolve_tuner_config({"description": {**LAB_DESCRIPTION, "qubit": {"gates": ["N", "X"]}}})
    with pytest.raises(ValueError, match=r"tuner\.levels"):
        spintune.resolve_tuner_config({"description": LAB_DESCRIPTION, "levels": []})


def test_to_xarray_round_trips_through_netcdf(tmp_path):
    run = spintune.SimulationRun({"seed": 2, "tuner": {"max_iterations": 4}})
    records = run.run()
    ds = run.to_xarray()
    assert ds.sizes["iteration"] == 4
    assert list(ds["iteration"].values) == [0, 1, 2, 3]
    assert ds["t_sr"].attrs["units"] == "ns" and ds["w"].attrs["units"] == "uV"
    assert ds["t_sr_std"].attrs["units"] == "ns" and ds["w_target"].attrs["units"] == "uV"
    # the default tunes w in log space: its gradient is ∂ln w/∂V, 1/mV
    assert ds["grad_w"].attrs["units"] == "1/mV" and ds["failed_evaluations"].attrs["units"] == "1"
    assert ds["grad_t_sr"].attrs["units"] == "1/mV" and ds["grad_w"].dims == ("iteration", "tuning_gate")
    assert "log space" in ds["grad_t_sr"].attrs["long_name"]
    assert ds["voltage"].attrs["units"] == "mV" and ds["lab_seconds"].attrs["units"] == "s"
    assert_units(ds)
    np.testing.assert_array_equal(ds["t_sr"].values, [r["parameters"][0]["value"] for r in records])
    np.testing.assert_array_equal(
        ds["voltage"].sel(gate="SB").values, [r["voltages_mv"]["SB"] for r in records]
    )
    np.testing.assert_array_equal(
        ds["grad_w"].sel(tuning_gate="T").values, [r["gradients"][1]["gradient"][3] for r in records]
    )
    assert json.loads(ds.attrs["spintune_config"]) == run.config
    path = tmp_path / "run.nc"
    run.to_netcdf(path)
    with xr.open_dataset(path) as back:
        back = back.load()
    xr.testing.assert_identical(back, ds)
    assert back["tuned"].dtype == bool


def test_store_to_xarray(tmp_path, run_cli):
    (tmp_path / "run.toml").write_text('seed = 6\n[tuner]\nmax_iterations = 3\n')
    db = tmp_path / "s.db"
    run_cli("run", "--config", tmp_path / "run.toml", "--db", db, "--quiet")
    run_cli("run", "--config", tmp_path / "run.toml", "--db", db, "--quiet")
    store = spintune.open_store(db)
    assert [r.id for r in store] == [1, 2]
    ds = store[2].to_xarray()
    assert ds.sizes["iteration"] == 3 and ds.attrs["run_id"] == 2
    assert_units(ds)
    store[2].to_netcdf(tmp_path / "s.nc")
    with xr.open_dataset(tmp_path / "s.nc") as back:
        xr.testing.assert_identical(back.load(), ds)
    assert json.loads(store[1].checkpoint)["session"] is not None
    with pytest.raises(KeyError):
        store[3]
    with pytest.raises(FileNotFoundError):
        spintune.open_store(tmp_path / "missing.db")
    (tmp_path / "other.db").write_bytes(b"")
    with pytest.raises(ValueError, match="not a spintune store"):
        spintune.open_store(tmp_path / "other.db")
    # the server writes its schema version; a newer one is refused, not misread
    assert store.schema_version == spintune.store.SCHEMA_VERSION
    import sqlite3
    conn = sqlite3.connect(db)
    conn.execute(f"PRAGMA user_version = {spintune.store.SCHEMA_VERSION + 1}")
    conn.commit()
    conn.close()
    with pytest.raises(ValueError, match="newer spintune"):
        spintune.open_store(db)


def test_a_background_run_can_be_watched_and_stopped_from_another_thread():
    """Issue 26: reading ``status``/``records`` while another thread is in
    ``run()`` raised ``Already mutably borrowed``; a stop from the watching
    thread must end the run. The watcher is served within an iteration (the
    lock is handed over fairly), so it sees the run running and stops it
    long before its 10 000 iterations are done."""
    import threading
    import time

    run = spintune.SimulationRun({"seed": 3, "tuner": {"max_iterations": 10_000, "stop_when_tuned": False}})
    errors = []

    def work():
        try:
            run.run()
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    t = threading.Thread(target=work)
    t.start()
    seen = []
    deadline = time.monotonic() + 60
    while len(seen) < 3 and time.monotonic() < deadline:
        status = run.status
        assert status["state"] == "running", status
        seen.append(len(run.records))
        time.sleep(0.05)
    assert run.control({"action": "stop"}) == {"state": "stopped"}
    t.join(timeout=60)
    assert not t.is_alive(), "run() did not end after the stop"
    assert not errors, errors
    assert run.status == {"state": "stopped"}
    assert len(run.records) >= max(seen)
    assert len(run.records) < 10_000


def test_keep_mode_in_python_checks_retunes_and_exports():
    """``SimulationRun`` with a ``keep`` table: tuned once, then kept for
    six lab hours of drift; every record says what it was."""
    run = spintune.SimulationRun({"seed": 3, "tuner": {"keep": {"duration_s": 6 * 3600.0}}})
    records = run.run()
    assert run.status == {"state": "finished"}
    phases = [r["keep"]["phase"] for r in records]
    assert phases[0] == "tuning"
    assert phases.count("check") >= 3
    assert records[-1]["lab_seconds"] > 4 * 3600.0
    keeping = [r for r in records if r["keep"]["next_check_lab_seconds"] is not None]
    assert keeping and all(r["keep"]["next_check_lab_seconds"] > r["lab_seconds"] for r in keeping)
    ds = run.to_xarray()
    assert ds.sizes["iteration"] == len(records)
