"""Iteration records → ``xarray.Dataset`` (used by ``SimulationRun.to_xarray``
and ``StoredRun.to_xarray``). Pure bookkeeping: no tuner logic.

Layout (dimension ``iteration``, coordinate = the records' iteration numbers):

* per parameter ``p`` (e.g. ``t_sr`` in ns, ``w`` in µV): ``p`` (measured
  value), ``p_std`` (its standard deviation δp), ``p_target``,
  ``p_tolerance`` (half-width of the band); NaN where missing;
* per gradient ``grad_p`` over ``tuning_gate`` (the estimate after the
  iteration's update, unit of p per mV) and ``grad_p_std`` (√ of the
  covariance's diagonal; NaN without a covariance);
* ``voltage`` over ``gate``: every gate voltage at the measurement, mV;
* ``step`` over ``tuning_gate``: the step decided in the iteration, mV;
* ``lab_seconds`` (s, cumulative), ``tuned`` (bool), ``failed_evaluations``
  and ``scans_<kind>`` (cumulative counts).

Every data variable and coordinate has a ``units`` attribute.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Sequence


def _f(x: Any) -> float:
    return math.nan if x is None else float(x)


def records_to_dataset(
    records: Sequence[Mapping[str, Any]], attrs: Optional[Mapping[str, Any]] = None
):
    import numpy as np
    import xarray as xr

    records = list(records)
    n = len(records)
    tuning_gates: list[str] = list(records[0]["gates"]) if records else []
    gates: list[str] = []
    params: dict[str, str] = {}
    grads: dict[str, str] = {}
    scan_kinds: list[str] = []
    for r in records:
        for g in r["voltages_mv"]:
            if g not in gates:
                gates.append(g)
        for p in r["parameters"]:
            params.setdefault(p["name"], p["unit"])
        for g in r["gradients"]:
            grads.setdefault(g["parameter"], g["unit"])
        for k in r["scan_counts"]:
            if k not in scan_kinds:
                scan_kinds.append(k)
        if list(r["gates"]) != tuning_gates:
            raise ValueError(
                f"iteration {r['iteration']}: top-level gates {r['gates']} differ from "
                f"{tuning_gates}; one dataset holds one tuner"
            )

    data: dict[str, Any] = {}

    def scalar(name: str, values, units: str, long_name: str, dtype=float):
        data[name] = (
            ("iteration",),
            np.asarray(values, dtype=dtype),
            {"units": units, "long_name": long_name},
        )

    for name, unit in params.items():
        rows = [next((p for p in r["parameters"] if p["name"] == name), None) for r in records]
        for suffix, key, what in [
            ("", "value", "measured"),
            ("_std", "std", "standard deviation of the measured"),
            ("_target", "target", "target of"),
            ("_tolerance", "tolerance", "half-width of the tolerance band of"),
        ]:
            scalar(
                name + suffix,
                [_f(p[key]) if p else math.nan for p in rows],
                unit,
                f"{what} {name}",
            )
    m = len(tuning_gates)
    for name, unit in grads.items():
        g = np.full((n, m), math.nan)
        s = np.full((n, m), math.nan)
        for i, r in enumerate(records):
            rep = next((x for x in r["gradients"] if x["parameter"] == name), None)
            if rep is None:
                continue
            g[i, :] = [_f(x) for x in rep["gradient"]]
            cov = rep.get("covariance")
            if cov is not None:
                s[i, :] = [math.sqrt(max(_f(cov[j][j]), 0.0)) for j in range(m)]
        data[f"grad_{name}"] = (
            ("iteration", "tuning_gate"),
            g,
            {"units": unit, "long_name": f"estimated gradient of {name} (after the update)"},
        )
        data[f"grad_{name}_std"] = (
            ("iteration", "tuning_gate"),
            s,
            {"units": unit, "long_name": f"standard deviation of the gradient of {name}"},
        )
    v = np.full((n, len(gates)), math.nan)
    for i, r in enumerate(records):
        for j, gname in enumerate(gates):
            v[i, j] = _f(r["voltages_mv"].get(gname))
    data["voltage"] = (
        ("iteration", "gate"),
        v,
        {"units": "mV", "long_name": "gate voltage at the measurement"},
    )
    step = np.full((n, m), math.nan)
    for i, r in enumerate(records):
        step[i, :] = [_f(x) for x in r["step_mv"]] if r["step_mv"] else math.nan
    data["step"] = (
        ("iteration", "tuning_gate"),
        step,
        {"units": "mV", "long_name": "step decided in the iteration"},
    )
    scalar("lab_seconds", [r["lab_seconds"] for r in records], "s", "cumulative lab time")
    scalar("tuned", [bool(r["tuned"]) for r in records], "1", "every target inside its band", bool)
    scalar(
        "failed_evaluations",
        [int(r["failed_evaluations"]) for r in records],
        "1",
        "cumulative failed or rejected evaluations",
        np.int64,
    )
    for k in scan_kinds:
        scalar(
            f"scans_{k}",
            [int(r["scan_counts"].get(k, 0)) for r in records],
            "1",
            f"cumulative number of {k} scans",
            np.int64,
        )
    coords = {
        "iteration": (
            ("iteration",),
            np.asarray([int(r["iteration"]) for r in records], dtype=np.int64),
            {"units": "1", "long_name": "iteration k"},
        ),
        "gate": (("gate",), np.asarray(gates, dtype=str), {"units": "1", "long_name": "gate"}),
        "tuning_gate": (
            ("tuning_gate",),
            np.asarray(tuning_gates, dtype=str),
            {"units": "1", "long_name": "gate of the top tuner level"},
        ),
    }
    ds = xr.Dataset(data_vars=data, coords=coords, attrs=dict(attrs or {}))
    return ds
