"""Iteration records → ``xarray.Dataset`` (used by ``SimulationRun.to_xarray``
and ``StoredRun.to_xarray``). Pure bookkeeping: no tuner logic.

Layout (dimension ``iteration``, coordinate = the records' iteration numbers):

* per parameter ``p`` (e.g. ``t_sr`` in ns, ``w`` in uV): ``p`` (measured
  value), ``p_std`` (its standard deviation δp), ``p_target``,
  ``p_tolerance`` (half-width of the band); NaN where missing;
* per gradient ``grad_p`` over ``tuning_gate`` (the estimate after the
  iteration's update, unit of p per mV) and ``grad_p_std`` (√ of the
  covariance's diagonal; NaN without a covariance);
* ``voltage`` over ``gate``: every gate voltage at the measurement, mV;
* ``step`` over ``tuning_gate``: the step decided in the iteration, mV;
* ``lab_seconds`` (s, cumulative), ``tuned`` (bool), ``failed_evaluations``
  and ``scans_<kind>`` (cumulative counts).

Units are UDUNITS-clean (CF conventions): ``uV``, not ``µV``. Every data
variable but ``tuned`` (a bool) has a ``units`` attribute (counts: ``1``);
the coordinates ``iteration`` (int64), ``gate`` and ``tuning_gate`` (names)
have none.

The records are consumed one at a time (a generator is fine): a store's
20,000 iterations are never held as dicts at once.
"""

from __future__ import annotations

import math
from array import array
from typing import Any, Dict, Iterable, List, Mapping, Optional


def _f(x: Any) -> float:
    return math.nan if x is None else float(x)


def udunits(unit: str) -> str:
    """A unit string as UDUNITS spells it: the micro sign (``µ``, ``μ``)
    becomes ``u`` (``µV`` → ``uV``, ``µV/mV`` → ``uV/mV``)."""
    return unit.replace("\u00b5", "u").replace("\u03bc", "u")


class _Columns:
    """Growing float64 columns of a fixed width, NaN-padded when a column
    first appears after some rows."""

    def __init__(self) -> None:
        self.rows = 0
        self.cols: Dict[str, array] = {}

    def put(self, name: str, values: List[float]) -> None:
        col = self.cols.get(name)
        if col is None:
            col = array("d", [math.nan]) * (self.rows * len(values))
            self.cols[name] = col
        missing = self.rows * len(values) - len(col)
        if missing > 0:
            col.extend(array("d", [math.nan]) * missing)
        col.extend(values)

    def end_row(self) -> None:
        self.rows += 1

    def get(self, name: str, width: int):
        import numpy as np

        col = self.cols.get(name)
        a = np.frombuffer(col, dtype=np.float64).copy() if col is not None else np.empty(0)
        out = np.full(self.rows * width, math.nan)
        out[: len(a)] = a
        return out.reshape(self.rows, width) if width != 1 else out


def records_to_dataset(
    records: Iterable[Mapping[str, Any]], attrs: Optional[Mapping[str, Any]] = None
):
    import numpy as np
    import xarray as xr

    tuning_gates: Optional[List[str]] = None
    gates: List[str] = []
    params: Dict[str, str] = {}
    grads: Dict[str, str] = {}
    scan_kinds: List[str] = []
    iterations = array("q")
    cols = _Columns()
    tuned: List[bool] = []
    counts: Dict[str, array] = {}
    failed = array("q")
    for r in records:
        if tuning_gates is None:
            tuning_gates = list(r["gates"])
        elif list(r["gates"]) != tuning_gates:
            raise ValueError(
                f"iteration {r['iteration']}: top-level gates {r['gates']} differ from "
                f"{tuning_gates}; one dataset holds one tuner"
            )
        m = len(tuning_gates)
        n = len(iterations)
        iterations.append(int(r["iteration"]))
        for g in r["voltages_mv"]:
            if g not in gates:
                gates.append(g)
        for g, v in r["voltages_mv"].items():
            cols.put("V:" + g, [_f(v)])
        for p in r["parameters"]:
            params.setdefault(p["name"], udunits(p["unit"]))
            cols.put("P:" + p["name"], [_f(p["value"]), _f(p["std"]), _f(p["target"]), _f(p["tolerance"])])
        for rep in r["gradients"]:
            grads.setdefault(rep["parameter"], udunits(rep["unit"]))
            g = [_f(x) for x in rep["gradient"]]
            cov = rep.get("covariance")
            sd = (
                [math.sqrt(max(_f(cov[j][j]), 0.0)) for j in range(m)]
                if cov is not None
                else [math.nan] * m
            )
            cols.put("G:" + rep["parameter"], g + sd)
        cols.put("step", [_f(x) for x in r["step_mv"]] if r["step_mv"] else [math.nan] * m)
        cols.put("lab_seconds", [_f(r["lab_seconds"])])
        cols.end_row()
        tuned.append(bool(r["tuned"]))
        failed.append(int(r["failed_evaluations"]))
        for k, c in r["scan_counts"].items():
            if k not in counts:
                scan_kinds.append(k)
                counts[k] = array("q", [0]) * n
            counts[k].append(int(c))
        for k in scan_kinds:
            if len(counts[k]) < n + 1:
                counts[k].append(0)
    tuning_gates = tuning_gates or []
    m = len(tuning_gates)
    data: Dict[str, Any] = {}

    def meta(units: Optional[str], long_name: str) -> Dict[str, str]:
        return {"units": units, "long_name": long_name} if units is not None else {"long_name": long_name}

    for name, unit in params.items():
        block = cols.get("P:" + name, 4)
        for j, (suffix, what) in enumerate(
            [
                ("", "measured"),
                ("_std", "standard deviation of the measured"),
                ("_target", "target of"),
                ("_tolerance", "half-width of the tolerance band of"),
            ]
        ):
            data[name + suffix] = (("iteration",), block[:, j] if block.ndim == 2 else block, meta(unit, f"{what} {name}"))
    for name, unit in grads.items():
        block = cols.get("G:" + name, 2 * m).reshape(-1, 2 * m) if m else np.empty((len(iterations), 0))
        data[f"grad_{name}"] = (
            ("iteration", "tuning_gate"),
            block[:, :m],
            meta(unit, f"estimated gradient of {name} (after the update)"),
        )
        data[f"grad_{name}_std"] = (
            ("iteration", "tuning_gate"),
            block[:, m:],
            meta(unit, f"standard deviation of the gradient of {name}"),
        )
    v = np.stack([cols.get("V:" + g, 1) for g in gates], axis=1) if gates else np.empty((len(iterations), 0))
    data["voltage"] = (("iteration", "gate"), v, meta("mV", "gate voltage at the measurement"))
    step = cols.get("step", m).reshape(-1, m) if m else np.empty((len(iterations), 0))
    data["step"] = (("iteration", "tuning_gate"), step, meta("mV", "step decided in the iteration"))
    data["lab_seconds"] = (("iteration",), cols.get("lab_seconds", 1), meta("s", "cumulative lab time"))
    data["tuned"] = (("iteration",), np.asarray(tuned, dtype=bool), meta(None, "every target inside its band"))
    data["failed_evaluations"] = (
        ("iteration",),
        np.frombuffer(failed, dtype=np.int64).copy(),
        meta("1", "cumulative failed or rejected evaluations"),
    )
    for k in scan_kinds:
        data[f"scans_{k}"] = (
            ("iteration",),
            np.frombuffer(counts[k], dtype=np.int64).copy(),
            meta("1", f"cumulative number of {k} scans"),
        )
    coords = {
        "iteration": (
            ("iteration",),
            np.frombuffer(iterations, dtype=np.int64).copy(),
            {"long_name": "iteration k"},
        ),
        "gate": (("gate",), np.asarray(gates, dtype=str), {"long_name": "gate"}),
        "tuning_gate": (
            ("tuning_gate",),
            np.asarray(tuning_gates, dtype=str),
            {"long_name": "gate of the top tuner level"},
        ),
    }
    return xr.Dataset(data_vars=data, coords=coords, attrs=dict(attrs or {}))
