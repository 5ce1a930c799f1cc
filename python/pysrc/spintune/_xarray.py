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

The columns are built by the core side (``_core.RecordColumns``), one
record at a time (a generator is fine): a store's 20,000 iterations are
never held as dicts at once, and a store's rows go in as JSON text whose
raw scans are never turned into Python objects.
"""

from __future__ import annotations

import math
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
