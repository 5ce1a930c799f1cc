"""open_store at lab scale: streaming records without their raw scans, raw
scans on request for a range of iterations, to_xarray(scans=False) that
parses no scan. (The 20,000-iteration time/memory figures are a benchmark:
python/benchmarks/store_scale.py, numbers in docs/python.md.)"""

import json

import numpy as np
import pytest
import xarray as xr

import spintune
import spintune.store
from spintune import records_to_dataset


@pytest.fixture(scope="module")
def stored(tmp_path_factory, run_cli):
    tmp = tmp_path_factory.mktemp("store")
    (tmp / "run.toml").write_text("seed = 8\n[tuner]\nmax_iterations = 5\n")
    db = tmp / "s.db"
    run_cli("run", "--config", tmp / "run.toml", "--db", db, "--quiet")
    return spintune.open_store(db)[1]


def without_scans(r):
    return {k: v for k, v in r.items() if k != "scans"}


def test_iter_records_streams_with_and_without_scans(stored, monkeypatch):
    full = stored.records
    assert len(full) == 5 and all(r["scans"] for r in full)
    monkeypatch.setattr(spintune.store.StoredRun, "BATCH", 2)  # several batches
    assert list(stored.iter_records(scans=True)) == full
    light = list(stored.iter_records())
    # the same records, every float bit for bit, without the raw scans
    assert light == [without_scans(r) for r in full]
    assert json.dumps(light) == json.dumps([without_scans(r) for r in full])
    assert [r["iteration"] for r in stored.iter_records(start=1, stop=4)] == [1, 2, 3]
    assert [r["iteration"] for r in stored.iter_records(start=3)] == [3, 4]
    assert list(stored.iter_records(start=7)) == []
    it = stored.iter_records()
    assert next(it)["iteration"] == 0  # a generator: nothing read beyond what is asked


def test_scans_on_request_for_a_range(stored):
    full = stored.records
    scans = stored.scans(1, 3)
    assert scans == {1: full[1]["scans"], 2: full[2]["scans"]}
    assert stored.scans() == {r["iteration"]: r["scans"] for r in full}


def test_to_xarray_without_scans_parses_no_scan(stored, monkeypatch):
    """What reaches a parser — Python's json.loads or the core's record
    columns — holds no raw scan: SQLite cut them out."""
    import spintune._core

    parsed = []
    real_loads = json.loads
    real_columns = spintune._core.RecordColumns

    def loads(text, *a, **k):
        parsed.append(text)
        return real_loads(text, *a, **k)

    class Spy:
        def __init__(self):
            self._c = real_columns()

        def add_json(self, texts):
            parsed.extend(texts)
            self._c.add_json(texts)

        def add(self, record):
            parsed.append(json.dumps(record))
            self._c.add(record)

        def finish(self):
            return self._c.finish()

    monkeypatch.setattr(spintune.store.json, "loads", loads)
    monkeypatch.setattr(spintune._core, "RecordColumns", Spy)
    ds = stored.to_xarray()
    assert len(parsed) == 5
    assert not any('"scans"' in t or '"traces"' in t for t in parsed), parsed[0][:200]
    assert "scans" not in ds
    monkeypatch.undo()
    reference = records_to_dataset(stored.records, ds.attrs)
    xr.testing.assert_identical(ds, reference)
    assert ds["iteration"].dtype == np.int64
    with_scans = stored.to_xarray(scans=True)
    assert [json.loads(s) for s in with_scans["scans"].values] == [r["scans"] for r in stored.records]
    xr.testing.assert_identical(with_scans.drop_vars("scans"), ds)


def test_records_to_dataset_takes_a_stream_with_changing_columns():
    run = spintune.SimulationRun({"seed": 3, "tuner": {"max_iterations": 3}})
    records = run.run()
    ds_list = records_to_dataset(records)
    ds_gen = records_to_dataset(r for r in records)
    xr.testing.assert_identical(ds_list, ds_gen)
    # a parameter missing in one iteration, a gate appearing late: NaN there
    edited = [dict(r) for r in records]
    edited[1] = dict(edited[1], parameters=[p for p in edited[1]["parameters"] if p["name"] != "w"])
    edited[2] = dict(edited[2], voltages_mv=dict(edited[2]["voltages_mv"], EXTRA=1.5))
    ds = records_to_dataset(edited)
    assert np.isnan(ds["w"].values[1]) and ds["w"].values[2] == records[2]["parameters"][1]["value"]
    assert list(np.isnan(ds["voltage"].sel(gate="EXTRA").values)) == [True, True, False]
    assert ds["voltage"].sel(gate="EXTRA").values[2] == 1.5
    empty = records_to_dataset([])
    assert empty.sizes["iteration"] == 0
