"""Iteration records → ``xarray.Dataset`` (used by ``SimulationRun.to_xarray``,
``StoredRun.to_xarray`` and, with a ``cell`` dimension,
``ArraySimulation.to_xarray``). Pure bookkeeping: no tuner logic.

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

The columns are built by the core side (``_core.RecordColumns``), one
record at a time (a generator is fine): a store's 20,000 iterations are
never held as dicts at once, and a store's rows go in as JSON text whose
raw scans are never turned into Python objects.
"""

from __future__ import annotations

import math
import re
from typing import Any, Dict, Iterable, Mapping, Optional


def _f(x: Any) -> float:
    return math.nan if x is None else float(x)


def udunits(unit: str) -> str:
    """A unit string as UDUNITS spells it: the micro sign (``µ``, ``μ``)
    becomes ``u`` (``µV`` → ``uV``, ``µV/mV`` → ``uV/mV``), and a
    log-space gradient's ``1/mV (log space)`` is ``1/mV`` (its
    ``long_name`` says log space)."""
    return unit.replace(" (log space)", "").replace("\u00b5", "u").replace("\u03bc", "u")


def records_to_dataset(
    records: Iterable[Mapping[str, Any]], attrs: Optional[Mapping[str, Any]] = None
):
    """Iteration records (dicts; any iterable, consumed one at a time) as an
    ``xarray.Dataset``."""
    from ._core import RecordColumns

    columns = RecordColumns()
    for r in records:
        columns.add(r)
    return columns_to_dataset(columns, attrs)


def columns_to_dataset(columns: Any, attrs: Optional[Mapping[str, Any]] = None):
    """The Dataset of a filled ``_core.RecordColumns`` (records added as
    dicts or as JSON texts, e.g. a store's rows)."""
    import numpy as np
    import xarray as xr

    c = columns.finish()
    data: Dict[str, Any] = {}

    def meta(units: Optional[str], long_name: str) -> Dict[str, str]:
        return {"units": units, "long_name": long_name} if units is not None else {"long_name": long_name}

    for name, unit, block in c["parameters"]:
        unit = udunits(unit)
        for j, (suffix, what) in enumerate(
            [
                ("", "measured"),
                ("_std", "standard deviation of the measured"),
                ("_target", "target of"),
                ("_tolerance", "half-width of the tolerance band of"),
            ]
        ):
            data[name + suffix] = (("iteration",), np.ascontiguousarray(block[:, j]), meta(unit, f"{what} {name}"))
    for name, unit, grad, std in c["gradients"]:
        of = f"ln {name} (log space)" if "(log space)" in unit else name
        unit = udunits(unit)
        data[f"grad_{name}"] = (
            ("iteration", "tuning_gate"),
            grad,
            meta(unit, f"estimated gradient of {of} (after the update)"),
        )
        data[f"grad_{name}_std"] = (
            ("iteration", "tuning_gate"),
            std,
            meta(unit, f"standard deviation of the gradient of {of}"),
        )
    data["voltage"] = (("iteration", "gate"), c["voltage"], meta("mV", "gate voltage at the measurement"))
    data["step"] = (("iteration", "tuning_gate"), c["step"], meta("mV", "step decided in the iteration"))
    data["lab_seconds"] = (("iteration",), c["lab_seconds"], meta("s", "cumulative lab time"))
    data["tuned"] = (("iteration",), c["tuned"], meta(None, "every target inside its band"))
    data["failed_evaluations"] = (
        ("iteration",),
        c["failed_evaluations"],
        meta("1", "cumulative failed or rejected evaluations"),
    )
    for kind, counts in c["scan_counts"]:
        data[f"scans_{kind}"] = (("iteration",), counts, meta("1", f"cumulative number of {kind} scans"))
    coords = {
        "iteration": (("iteration",), c["iteration"], {"long_name": "iteration k"}),
        "gate": (("gate",), np.asarray(c["gates"], dtype=str), {"long_name": "gate"}),
        "tuning_gate": (
            ("tuning_gate",),
            np.asarray(c["tuning_gates"], dtype=str),
            {"long_name": "gate of the top tuner level"},
        ),
    }
    return xr.Dataset(data_vars=data, coords=coords, attrs=dict(attrs or {}))


# an array's per-cell names: ``c3.t_sr``, ``c3.t_sr_std``, ``grad_c3.w``, …
_CELL_NAME = re.compile(r"^(grad_)?c(\d+)\.(.+)$")


def array_records_to_dataset(
    records: Iterable[Mapping[str, Any]], cells: int, attrs: Optional[Mapping[str, Any]] = None
):
    """An array run's records (parameters ``c{k}.t_sr``, ``c{k}.w``) as an
    ``xarray.Dataset``: the layout of :func:`records_to_dataset` with every
    per-cell variable ``c{k}.p…`` stacked into ``p…`` over a ``cell``
    dimension (int64 coordinate ``0 … cells-1``), e.g. ``t_sr`` over
    ``(iteration, cell)`` and ``grad_w`` over ``(iteration, cell,
    tuning_gate)`` (of ln w when its unit is 1/mV); NaN where a cell has
    no value, and no per-cell variable without records. The other
    variables (``voltage`` over ``gate``, ``step``, ``lab_seconds``,
    ``tuned``, …) are as in :func:`records_to_dataset`."""
    import numpy as np
    import xarray as xr

    flat = records_to_dataset(records, attrs)
    stacked: Dict[str, Dict[int, str]] = {}
    for name in flat.data_vars:
        m = _CELL_NAME.match(str(name))
        if m and int(m.group(2)) < cells:
            stacked.setdefault((m.group(1) or "") + m.group(3), {})[int(m.group(2))] = str(name)
    data: Dict[str, Any] = {}
    for name, by_cell in stacked.items():
        first = flat[next(iter(by_cell.values()))]
        parts = [
            flat[by_cell[k]].values if k in by_cell else np.full(first.shape, np.nan)
            for k in range(cells)
        ]
        attrs_ = dict(first.attrs)
        attrs_["long_name"] = re.sub(r"\bc\d+\.", "", attrs_.get("long_name", name))
        log = attrs_.get("units") == "1/mV" and "log space" not in attrs_["long_name"]
        if name.startswith("grad_") and log:
            # a gradient of t_sr (ns) or w (uV) in 1/mV is the log-space one
            attrs_["long_name"] = re.sub(
                r"gradient of (\S+)", r"gradient of ln \1 (log space)", attrs_["long_name"]
            )
        dims = (first.dims[0], "cell") + tuple(first.dims[1:])
        data[name] = (dims, np.stack(parts, axis=1), attrs_)
    used = {n for by_cell in stacked.values() for n in by_cell.values()}
    for name, var in flat.data_vars.items():
        if name not in used:
            data[str(name)] = var
    coords = dict(flat.coords)
    coords["cell"] = (
        ("cell",),
        np.arange(cells, dtype=np.int64),
        {"long_name": "cell k of the array (gates and parameters c{k}.*)"},
    )
    return xr.Dataset(data_vars=data, coords=coords, attrs=flat.attrs)
