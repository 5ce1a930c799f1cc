"""spintune.ArraySimulation: a simulated array of double-dot cells tuned
jointly (the core's ArraySimulationRun), its config rules, control,
checkpoints and the xarray export with a ``cell`` dimension."""

import pickle

import numpy as np
import pytest
import xarray as xr

import spintune
from conftest import assert_units, canonical_hash

THREE = {"name": "three", "array": {"cells": 3, "device_seed": 5, "seed": 3}}


def cell_values(record, cells):
    """{(cell, "t_sr" | "w"): parameter dict} of an array record."""
    by_name = {p["name"]: p for p in record["parameters"]}
    return {(k, p): by_name[f"c{k}.{p}"] for k in range(cells) for p in ("t_sr", "w")}


def assert_in_band(record, cells, band=0.1):
    for (k, p), par in cell_values(record, cells).items():
        assert abs(par["value"] - par["target"]) <= band * par["target"], (k, p, par)


def test_three_cells_tune_into_band():
    run = spintune.ArraySimulation(THREE)
    assert run.cells == 3 and run.targets == [(20.0, 270.0)] * 3
    records = run.run(max_iterations=60)
    assert run.status == {"state": "finished"}, "every cell in band within 60 iterations"
    last = records[-1]
    assert last["tuned"] and not any(r["tuned"] for r in records[:-1])
    assert [p["name"] for p in last["parameters"]] == ["c0.t_sr", "c0.w", "c1.t_sr", "c1.w", "c2.t_sr", "c2.w"]
    assert [p["unit"] for p in last["parameters"]] == ["ns", "µV"] * 3
    assert_in_band(last, 3)
    assert [r["iteration"] for r in records] == list(range(len(records)))
    assert run.records == records and list(run) == []
    # the simulator's truth (world side): one dict per cell, t_sr in ns, w in µV
    truth = run.truth()
    assert len(truth) == 3 and all(5.0 < t["t_sr"] < 100.0 and 100.0 < t["w"] < 500.0 for t in truth)
    assert set(run.voltages_mv) >= {f"c{k}.{g}" for k in range(3) for g in ("N", "SA", "SB", "T", "PA", "PB")}
    assert repr(run) == f'ArraySimulation(name="three", cells=3, iterations={len(records)}, status="finished")'


def test_run_is_bounded_and_pause_stop_control_it():
    run = spintune.ArraySimulation(THREE)
    assert len(run.run(max_iterations=2)) == 2 and run.status == {"state": "running"}
    assert run.control({"action": "pause"}) == {"state": "paused"}
    assert list(run) == [] and len(run.run()) == 2
    run.control({"action": "resume"})
    assert next(run)["iteration"] == 2
    run.control({"action": "stop"})
    assert list(run) == [] and len(run.records) == 3
    with pytest.raises(ValueError, match="action"):
        run.control({"action": "explode"})


def test_to_xarray_has_a_cell_dimension(tmp_path):
    run = spintune.ArraySimulation({**THREE, "targets": [[20.0, 270.0], [25.0, 300.0], [20.0, 250.0]]})
    records = run.run(max_iterations=5)
    n = len(records)
    ds = run.to_xarray()
    assert ds.sizes["cell"] == 3 and ds.sizes["iteration"] == n
    assert ds["cell"].values.tolist() == [0, 1, 2] and ds["cell"].dtype == np.int64
    assert ds["iteration"].values.tolist() == [r["iteration"] for r in records]
    for p, unit in [("t_sr", "ns"), ("w", "uV")]:
        for name in (p, f"{p}_std", f"{p}_target", f"{p}_tolerance"):
            assert ds[name].dims == ("iteration", "cell"), name
            assert ds[name].attrs["units"] == unit, name
        # a failed measurement is None in the record, NaN in the Dataset
        values = [[cell_values(r, 3)[(k, p)]["value"] for k in range(3)] for r in records]
        np.testing.assert_array_equal(ds[p].values, np.array(values, dtype=float))
    np.testing.assert_array_equal(ds["w_target"].values[-1], [270.0, 300.0, 250.0])
    np.testing.assert_array_equal(ds["t_sr_target"].sel(cell=1).values, [25.0] * n)
    assert ds["lab_seconds"].dims == ("iteration",) and ds["lab_seconds"].attrs["units"] == "s"
    np.testing.assert_array_equal(ds["lab_seconds"].values, [r["lab_seconds"] for r in records])
    assert ds["grad_w"].dims == ("iteration", "cell", "tuning_gate") and ds.sizes["tuning_gate"] == 12
    assert ds["grad_w"].attrs["units"] == "1/mV" and "ln w (log space)" in ds["grad_w"].attrs["long_name"]
    np.testing.assert_array_equal(
        ds["grad_w"].sel(cell=2, tuning_gate="c1.T").values,
        [next(g for g in r["gradients"] if g["parameter"] == "c2.w")["gradient"][7] for r in records],
    )
    assert ds["voltage"].attrs["units"] == "mV" and "c2.PB" in ds["gate"].values
    assert ds.attrs["cells"] == 3 and "c0.t_sr" not in ds and "grad_c0.w" not in ds
    assert_units(ds)
    path = tmp_path / "array.nc"
    run.to_netcdf(path)
    with xr.open_dataset(path) as back:
        back = back.load()
    xr.testing.assert_identical(back, ds)


@pytest.mark.parametrize(
    "config,field",
    [
        ({"bogus": 1}, "`bogus`"),
        ({"array": {"cells": 3, "nope": 1}}, r"`array\.nope`"),
        ({"array": {"cells": 17}}, r"`array\.cells`"),
        ({"array": {"seed": "x"}}, r"`array\.seed`"),
        ({"targets": [[20.0, 270.0], [20.0, 270.0]]}, "`targets`"),
        ({"targets": [[20.0, 5.0]]}, r"`targets\[0\]`"),
        ({"tuning": {"line_rounds": 9}}, r"`tuning\.line_rounds`"),
        ({"tuning": {"relative_tolerance": float("nan")}}, r"`tuning\.relative_tolerance`"),
        ({"device": {"bogus": 1}}, r"`device\.bogus`"),
        ({"array": {"crosstalk": {"nearest": 2.0}}}, r"`array\.crosstalk\.nearest`"),
        ({"array": {"cells": 3, "layout": "ladder"}}, r"`array\.layout`"),
        ({"array": {"cells": 4, "layout": "ring"}}, r"`array\.layout`"),
        ([1, 2], "dict"),
    ],
)
def test_bad_config_raises_value_error_naming_the_field(config, field):
    with pytest.raises(ValueError, match=field):
        spintune.ArraySimulation(config)


def test_a_ladder_of_two_by_two_cells_tunes_and_exports():
    """A 2×2 ladder (cells 0 1 over 2 3): the layout only changes which
    cells are neighbours; the records and the export name the cells as in
    a chain."""
    run = spintune.ArraySimulation({"name": "ladder", "array": {"cells": 4, "layout": "ladder", "device_seed": 5, "seed": 3}})
    assert run.cells == 4 and run.config["array"]["layout"] == "ladder"
    records = run.run(max_iterations=80)
    assert run.status == {"state": "finished"}, "every cell in band within 80 iterations"
    assert_in_band(records[-1], 4)
    ds = run.to_xarray()
    assert ds.sizes["cell"] == 4


def test_partial_config_merges_into_the_default():
    cfg = spintune.ArraySimulation({"array": {"cells": 2}}).config
    assert cfg["array"]["cells"] == 2 and cfg["array"]["seed"] == 1
    assert cfg["targets"] == [(20.0, 270.0)] and cfg["tuning"]["relative_tolerance"] == 0.1
    assert spintune.ArraySimulation(cfg).config == cfg


def test_checkpoint_restore_continues_identically():
    straight = spintune.ArraySimulation(THREE)
    expected = straight.run(max_iterations=5)
    run = spintune.ArraySimulation(THREE)
    run.run(max_iterations=2)
    restored = spintune.ArraySimulation.restore(run.checkpoint())
    unpickled = pickle.loads(pickle.dumps(run))
    assert restored.records == run.records and restored.config == run.config
    for r in (run, restored, unpickled):
        assert canonical_hash(r.run(max_iterations=3)) == canonical_hash(expected)
    with pytest.raises(ValueError, match="invalid checkpoint"):
        spintune.ArraySimulation.restore('{"config": {}}')


def test_a_target_change_revives_a_finished_run():
    run = spintune.ArraySimulation(THREE)
    done = len(run.run(max_iterations=60))
    assert run.status == {"state": "finished"}
    status = run.control({"action": "set_target", "parameter": "c1.t_sr", "target": 30.0})
    assert status == {"state": "paused"} and run.targets[1] == (30.0, 270.0)
    assert list(run) == []  # paused until resumed
    run.control({"action": "resume"})
    records = run.run(max_iterations=60)
    assert len(records) > done and run.status == {"state": "finished"}
    last = records[-1]
    assert last["tuned"] and cell_values(last, 3)[(1, "t_sr")]["target"] == 30.0
    assert_in_band(last, 3)
    # a bad change names what is wrong and changes nothing
    for command, needle in [
        ({"parameter": "c7.t_sr", "target": 30.0}, "unknown parameter"),
        ({"parameter": "c1.w", "target": 200.0, "tolerance": {"relative": 0.2}}, "band of an array run"),
    ]:
        with pytest.raises(ValueError, match=needle):
            run.control({"action": "set_target", **command})
    assert run.targets[1] == (30.0, 270.0)


def test_a_described_array_takes_its_cells_and_limits_from_the_description():
    # The simulated cell's gates, described as a lab would (limits and start
    # in mV), with cell 1's SB given limits of its own; two cells, not the
    # `array.cells` of THREE: the description is the one source of the cells.
    gates = [
        {"name": "N", "min_mv": -900, "max_mv": -500, "initial_mv": -700},
        {"name": "T", "min_mv": -850, "max_mv": -450, "initial_mv": -650},
        {"name": "SA", "min_mv": -1020, "max_mv": -620, "initial_mv": -820},
        {"name": "SB", "min_mv": -980, "max_mv": -580, "initial_mv": -780},
        {"name": "PA", "min_mv": -550, "max_mv": -50, "initial_mv": -300, "max_step_mv": 30},
        {"name": "PB", "min_mv": -570, "max_mv": -70, "initial_mv": -320, "max_step_mv": 30},
        {"name": "SD1", "min_mv": -750, "max_mv": -450, "initial_mv": -600, "max_step_mv": 30},
    ]
    description = {
        "cells": 2,
        "readout_groups": [[0, 1]],
        "cell": {
            "gates": gates,
            "qubit": {"gates": ["N", "SA", "SB", "T"]},
            "sensing_dot": {"gate": "SD1"},
            "lines": {"gates": ["PA", "PB"],
                      "compensation": [[-0.36, -0.50, 0.0042, -0.039], [-0.12, 0.013, -0.50, -0.46]]},
        },
        "cell_gates": [{"cell": 1, "gates": [
            {"name": "SB", "min_mv": -790, "max_mv": -770, "initial_mv": -780}]}],
    }
    run = spintune.ArraySimulation({**THREE, "description": description})
    assert run.cells == 2
    records = run.run(max_iterations=40)
    assert records, "no iteration"
    names = [p["name"] for p in records[-1]["parameters"]]
    assert names == ["c0.t_sr", "c0.w", "c1.t_sr", "c1.w"]
    # cell 1's SB never left its own 20 mV window (the guard checks the described limits)
    assert all(-790 <= r["voltages_mv"]["c1.SB"] <= -770 for r in records)
    with pytest.raises(ValueError, match=r"`description\.cell_gates\[0\]\.gates\[0\]\.name`"):
        spintune.ArraySimulation({**THREE, "description": {
            **description, "cell_gates": [{"cell": 1, "gates": [{**gates[0], "name": "X"}]}]}})
