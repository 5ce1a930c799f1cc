"""Drive a spintune run with QCoDeS: gates are QCoDeS ``Parameter``s, scans
are your own callables, every iteration is recorded into a QCoDeS dataset.

This is a thin, pure-Python driver of :class:`spintune.RunSession`: the tuner,
its fits and every safety check (gate limits, per-gate step from the
instrument's read-back, sweep points, read-back tolerance) are the core's.
The adapter only

* reads each gate parameter's validator limits, intersects them with the
  tuner config's gate limits (the stricter wins) and passes the result into
  the tuner config's ``gates`` before it creates the session;
* executes the session's requests: ``read_voltages`` → ``param.get()``,
  ``set_voltages`` → ``param.set()`` then ``param.get()`` (the read-back),
  ``measure`` → your scan callable, ``wait`` (keep mode, ``tuner_config``'s
  ``keep`` table: lab time between checks) → ``sleep``;
* records each committed iteration into a ``qcodes.dataset`` Measurement.

Units: the tuner works in mV. A gate parameter in V (``unit="V"``) is set to
mV / 1000, one in mV as is; other units need ``mv_per_unit``.

Interrupting (Ctrl-C, the notebook's "interrupt kernel"): the run is
**paused**, not stopped. If a request was at the instrument, its answer is
unknown: the session is told so (a device fault), so that nothing is believed
about the gates; then it is paused. Nothing is set after the interrupt. The
instrument stays where it is, and ``run()`` again resumes: every gate is
read back first, and the interrupted request is checked again against the
read-back before it is re-issued. ``stop()`` ends the run for good.

The same holds for **any exception** that leaves ``run()`` — from a scan
callable, a gate parameter, an ``on_iteration`` callback, QCoDeS creating or
closing the dataset — and wherever it lands (also before the first
iteration): the run is left paused (or faulted), never running, so the next
``run()`` reads every gate first and a gate moved by hand in between is
stepped from where it really is.

Defence in depth: each gate parameter's own QCoDeS ``step`` is set to the
gate's ``max_step_mv`` (in the parameter's unit; a smaller step already set is
kept) and its ``inter_delay`` to at least ``inter_delay_s`` (1 ms). A gate
parameter without a get command of its own (``get()`` returns its cache)
warns: its read-back checks prove nothing.

Example::

    from spintune.qcodes import QcodesTuner

    tuner = QcodesTuner(
        gates={"N": dac.ch01.volt, "T": dac.ch02.volt, ...},   # every gate of the tuner config
        scans={
            "reload_time": measure_reload_time,          # scan dict -> result
            "transition_width": measure_transition,
            "sensing_dot": sweep_sensing_dot,
            "chemical_potential": measure_lines,
        },
        tuner_config={"max_iterations": 50},
    )
    dataset = tuner.run()

A scan callable gets the scan request dict (``{"kind": "reload_time",
"sweep": None}``; for ``sensing_dot`` the sweep ``{"gate", "from_mv",
"to_mv", "points"}`` it must run — see :func:`sweep_points_mv`) and returns
one of

* raw traces for the core's fits: ``{"x_label": "wait time (ns)", "y_label":
  "signal (a.u.)", "traces": [{"label": "...", "x": [...], "y": [...]}]}``
  (lists or numpy arrays);
* evaluated values with variances: ``{"t_sr": (value, variance)}`` (value in
  the parameter's unit, variance in unit²), or a list of ``{"name", "value",
  "variance"}`` dicts;
* a full ``ScanOutcome`` dict (``{"kind": "raw" | "evaluated" | "failed", ...}``).

Raise :class:`ScanFailed` (or return ``None``) when the measurement did not
work: the tuner counts a failed evaluation and carries on. Any other
exception is a device fault: the run pauses (resumable) and the exception
propagates.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import time
import warnings
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import qcodes
from qcodes.dataset import Measurement, load_or_create_experiment

from . import Ramp, RunSession, resolve_tuner_config
from ._xarray import udunits

__all__ = [
    "QcodesTuner",
    "ScanFailed",
    "TuningFault",
    "sweep_points_mv",
    "gate_limits",
    "qdac2_dc_sweep",
]


class ScanFailed(Exception):
    """Raise from a scan callable when the measurement could not be made or
    evaluated; the tuner records a failed evaluation and continues."""


class TuningFault(RuntimeError):
    """The run session paused the run with a fault (a device error, a
    read-back that did not match, a request the safety guard refused). The
    run is resumable: fix the cause, then ``run()`` again."""

    def __init__(self, fault: Mapping[str, Any]):
        self.fault = dict(fault)
        message = str(fault.get("message", ""))
        if fault.get("kind") == "readback" and "outside its limits" in message:
            # e.g. a DAC at its reset state (0 V), outside the tuning window
            message += (
                " with QcodesTuner.ramp_to() (to the config's initial_mv, in steps within "
                "the limits), then run() again"
            )
        super().__init__(f"{fault.get('kind', '?')} fault: {message}")


_UNIT_MV = {"V": 1000.0, "mV": 1.0, "uV": 1e-3, "µV": 1e-3, "μV": 1e-3}


def sweep_points_mv(sweep: Mapping[str, Any]) -> np.ndarray:
    """The voltages (mV) of a sweep request ``{"gate", "from_mv", "to_mv",
    "points"}``, in order: ``points`` evenly spaced values from ``from_mv`` to
    ``to_mv`` (the core's guard has checked every one against the limits)."""
    return np.linspace(float(sweep["from_mv"]), float(sweep["to_mv"]), int(sweep["points"]))


def qdac2_dc_sweep(channel: Any, sweep: Mapping[str, Any], *, dwell_s: float = 1e-3) -> Any:
    """Program a ``sensing_dot`` sweep request on a QDAC-II channel's own DC
    sweep generator (``qcodes_contrib_drivers``' ``QDac2Channel.dc_sweep``,
    stepped) instead of ``points`` single VISA sets: one programming of
    start/stop/points/dwell, the instrument steps through the points itself
    (201 points at the default dwell: 0.2 s instead of 201 round trips).

    The points are exactly the request's (``sweep_points_mv(sweep)``, which
    the core's guard checked: every point inside the limits, the first within
    ``max_step_mv`` of the gate's read-back, the spacing at most
    ``max_step_mv``); the generator's ``values_V()`` is compared with them
    and a mismatch aborts before anything starts (``RuntimeError``).

    Returns the driver's ``Sweep_Context``: arm your digitizer (e.g. on
    ``ctx.start_marker()`` / ``ctx.step_end_marker()``), then
    ``ctx.start()`` and wait for the end (``ctx.time_s()``). **Then set the
    channel back where it was** (``dc_constant_V(start)``, one sweep
    half-width from the last point, which the config keeps within
    ``max_step_mv``): the generator leaves the output at the sweep's last
    point in sweep mode, while ``dc_constant_V.get()`` (``sour:volt?``)
    reads the fixed-mode level — a read-back that is not the output, against
    which the next step would be checked. Back in fixed mode the read-back
    is the output again.
    """
    points_mv = sweep_points_mv(sweep)
    ctx = channel.dc_sweep(
        start_V=float(sweep["from_mv"]) / 1000.0,
        stop_V=float(sweep["to_mv"]) / 1000.0,
        points=int(sweep["points"]),
        dwell_s=dwell_s,
        stepped=True,
    )
    planned_mv = np.asarray(ctx.values_V(), dtype=float) * 1000.0
    if planned_mv.shape != points_mv.shape or not np.allclose(planned_mv, points_mv, rtol=0, atol=1e-6):
        ctx.abort()
        raise RuntimeError(
            f"QDAC-II sweep of {sweep['gate']}: the generator would visit {planned_mv.tolist()[:3]}… "
            f"mV, not the requested {points_mv.tolist()[:3]}… mV; aborted"
        )
    return ctx


def _mv_per_unit(name: str, param: Any, override: Optional[Mapping[str, float]]) -> float:
    if override and name in override:
        scale = float(override[name])
    else:
        unit = getattr(param, "unit", "") or ""
        if unit not in _UNIT_MV:
            raise ValueError(
                f"gate {name}: parameter {getattr(param, 'full_name', param)!r} has unit "
                f"{unit!r}; pass mv_per_unit={{{name!r}: <mV per unit>}}"
            )
        scale = _UNIT_MV[unit]
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"gate {name}: mv_per_unit must be a positive number, got {scale}")
    return scale


def _validator_range(param: Any) -> Tuple[Optional[float], Optional[float]]:
    vals = getattr(param, "vals", None)
    lo = getattr(vals, "min_value", None)
    hi = getattr(vals, "max_value", None)
    lo = float(lo) if lo is not None and math.isfinite(float(lo)) else None
    hi = float(hi) if hi is not None and math.isfinite(float(hi)) else None
    return lo, hi


def _cache_only_get(param: Any) -> Any:
    """The parameter whose cached value (the last value set) ``param.get()``
    returns instead of asking the instrument, or ``None``: a QCoDeS
    ``Parameter`` made with ``get_cmd=None`` (the default when only
    ``set_cmd`` is given; ``ManualParameter``), or the one a delegate/scaled
    parameter reads through to."""
    seen = set()
    while param is not None and id(param) not in seen:
        seen.add(id(param))
        get_raw = getattr(param, "get_raw", None)
        func = getattr(get_raw, "__func__", get_raw)
        qualname = getattr(func, "__qualname__", "") or ""
        if "_get_manual_parameter" in qualname:  # QCoDeS >= 0.40
            return param
        if qualname == "Parameter.__init__.<locals>.<lambda>":  # older QCoDeS: lambda: cache
            return param
        # look through a DelegateParameter / ScaledParameter to what it reads
        inner = None
        for attr in ("source", "_wrapped_parameter"):
            try:
                inner = getattr(param, attr, None)
            except Exception:
                inner = None
            if inner is not None:
                break
        param = inner
    return None


def _check_readable(name: str, param: Any) -> None:
    """Refuse a gate parameter that cannot be read; warn for one whose get()
    only returns its cache (its read-back checks prove nothing)."""
    full = getattr(param, "full_name", None) or repr(param)
    if getattr(param, "gettable", True) is False or not callable(getattr(param, "get", None)):
        raise ValueError(
            f"gate {name}: parameter {full!r} cannot be read (no get command); the run reads "
            "every gate from the instrument before it moves one: give it a get_cmd"
        )
    cached = _cache_only_get(param)
    if cached is not None:
        via = ""
        if cached is not param:
            via = f" (it reads {getattr(cached, 'full_name', None) or repr(cached)!r}, which has none)"
        warnings.warn(
            f"gate {name}: QCoDeS parameter {full!r} has no get command{via}: get() "
            "returns the cached last set value, not the instrument's, so the read-back checks "
            f"of gate {name} are vacuous (a gate moved outside the run goes unnoticed, and a "
            "set that did not take effect looks like one that did). Give it a get_cmd that "
            "asks the instrument.",
            UserWarning,
            stacklevel=3,
        )


def _configure_ramp(
    name: str, param: Any, max_step_mv: float, mv_per_unit: float, inter_delay_s: Optional[float]
) -> Dict[str, Any]:
    """Defence in depth: QCoDeS's own ramp. ``param.step`` becomes the gate's
    ``max_step_mv`` in the parameter's unit (unless a smaller step is set
    already), ``param.inter_delay`` at least ``inter_delay_s``. Returns what is
    in force: ``{"step": ..., "inter_delay": ...}`` (``None`` if the parameter
    has no such attribute or refused the value; a ``UserWarning`` says why)."""
    out: Dict[str, Any] = {"step": None, "inter_delay": None}
    full = getattr(param, "full_name", None) or repr(param)
    if hasattr(param, "step"):
        step = max_step_mv / mv_per_unit
        while step * mv_per_unit > max_step_mv:  # rounding must not loosen the limit
            step = math.nextafter(step, 0.0)
        try:
            old = param.step
            if old is not None and 0 < float(old) <= step:
                pass  # the user's step is at least as strict: keep it
            else:
                try:
                    param.step = step
                except TypeError:
                    # an integer parameter takes an integer step
                    if int(step) < 1:
                        raise
                    param.step = int(step)
            out["step"] = param.step
        except (TypeError, ValueError, AttributeError) as e:
            warnings.warn(
                f"gate {name}: could not set the step of QCoDeS parameter {full!r} to "
                f"{step:g} {getattr(param, 'unit', '')} ({e}); the run's own guard still "
                f"limits every set to {max_step_mv:g} mV",
                UserWarning,
                stacklevel=3,
            )
    if inter_delay_s is not None and hasattr(param, "inter_delay"):
        try:
            if not float(param.inter_delay) >= inter_delay_s:
                param.inter_delay = inter_delay_s
            out["inter_delay"] = param.inter_delay
        except (TypeError, ValueError, AttributeError) as e:
            warnings.warn(
                f"gate {name}: could not set the inter_delay of QCoDeS parameter {full!r} "
                f"to {inter_delay_s:g} s ({e})",
                UserWarning,
                stacklevel=3,
            )
    return out


def gate_limits(
    gate_specs: Sequence[Mapping[str, Any]],
    gates: Mapping[str, Any],
    mv_per_unit: Optional[Mapping[str, float]] = None,
) -> List[Dict[str, Any]]:
    """The tuner config's ``gates`` with each gate's limits narrowed to its
    QCoDeS parameter's validator range (converted to mV): the stricter limit
    wins. ``initial_mv`` is clamped into the result (the session reads every
    gate from the instrument before it moves one). Raises ``ValueError`` if a
    gate has no parameter or its ranges do not overlap."""
    missing = [g["name"] for g in gate_specs if g["name"] not in gates]
    if missing:
        raise ValueError(
            "no QCoDeS parameter for the tuner gates "
            + ", ".join(missing)
            + "; map every gate in `gates`, or remove it from tuner_config['gates']"
        )
    out = []
    for spec in gate_specs:
        spec = dict(spec)
        name = spec["name"]
        param = gates[name]
        scale = _mv_per_unit(name, param, mv_per_unit)
        vlo, vhi = _validator_range(param)
        lo, hi = float(spec["min_mv"]), float(spec["max_mv"])
        if vlo is not None:
            m = vlo * scale
            while m / scale < vlo:  # rounding must not put a limit outside the validator
                m = math.nextafter(m, math.inf)
            lo = max(lo, m)
        if vhi is not None:
            m = vhi * scale
            while m / scale > vhi:
                m = math.nextafter(m, -math.inf)
            hi = min(hi, m)
        if lo > hi:
            raise ValueError(
                f"gate {name}: the config allows [{spec['min_mv']}, {spec['max_mv']}] mV, the "
                f"parameter's validator [{vlo}, {vhi}] {getattr(param, 'unit', '')}: no overlap"
            )
        spec["min_mv"], spec["max_mv"] = lo, hi
        spec["initial_mv"] = min(max(float(spec["initial_mv"]), lo), hi)
        out.append(spec)
    return out


#: The scans a tuner can ask for (``protocol::ScanKind``).
SCAN_KINDS = ("sensing_dot", "chemical_potential", "transition_width", "reload_time")


def _check_mapping(gates: Mapping[str, Any], scans: Mapping[str, Any]) -> None:
    """Refuse one parameter mapped to two gates (setting one would move the
    other behind the guard's back) and scan keys the tuner never asks for (a
    misspelt key would leave its scan unmapped)."""
    seen: Dict[int, str] = {}
    for name, param in gates.items():
        other = seen.get(id(param))
        if other is not None:
            raise ValueError(
                f"gates {other!r} and {name!r} are mapped to the same parameter "
                f"{getattr(param, 'full_name', param)!r}: each gate needs its own"
            )
        seen[id(param)] = name
    for key in scans:
        if key not in SCAN_KINDS:
            close = difflib.get_close_matches(str(key), SCAN_KINDS, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(
                f"scans: unknown scan {key!r}{hint}; the scans are {', '.join(SCAN_KINDS)}"
            )


def _scan_kinds(tuner_config: Mapping[str, Any]) -> List[str]:
    kinds: List[str] = []
    for level in tuner_config["levels"]:
        if level["kind"] == "sensing_dot":
            found = ["sensing_dot"]
        else:
            found = [p["scan"] for p in level.get("parameters", [])]
        for k in found:
            if k not in kinds:
                kinds.append(k)
    return kinds


def _outcome(kind: str, result: Any) -> Dict[str, Any]:
    """A scan callable's result as a ``ScanOutcome`` dict."""
    if result is None:
        return {"kind": "failed", "reason": f"the {kind} scan function returned None"}
    if isinstance(result, Mapping):
        if result.get("kind") in ("raw", "evaluated", "failed"):
            return dict(result)
        if "traces" in result:
            scan = {
                "kind": kind,
                "x_label": str(result.get("x_label", "")),
                "y_label": str(result.get("y_label", "")),
                "traces": [
                    {"label": str(t.get("label", "")), "x": t["x"], "y": t["y"]}
                    for t in result["traces"]
                ],
            }
            return {"kind": "raw", "scan": scan}
        values = []
        for name, v in result.items():
            if isinstance(v, Mapping):
                values.append({"name": str(name), "value": v["value"], "variance": v["variance"]})
            else:
                value, variance = v
                values.append({"name": str(name), "value": value, "variance": variance})
        return {"kind": "evaluated", "values": values}
    if isinstance(result, (list, tuple)) and all(isinstance(v, Mapping) for v in result):
        return {"kind": "evaluated", "values": [dict(v) for v in result]}
    raise TypeError(
        f"the {kind} scan function returned {type(result).__name__}; expected raw traces "
        "({'traces': [...]}), evaluated values ({name: (value, variance)}) or None"
    )


class _Progress:
    """A progress bar: ``tqdm`` (``tqdm.auto``, so notebooks get a widget)
    if installed, else a printed line per 10 %; nothing if not ``enabled``."""

    def __init__(self, enabled: bool, what: str):
        self._what = what
        self._bar: Any = None
        self._enabled = enabled
        self._printed = -1
        self._tqdm: Any = None
        if enabled:
            try:
                from tqdm.auto import tqdm

                self._tqdm = tqdm
            except ImportError:
                self._tqdm = None

    def update(self, done: int, total: Optional[int]) -> None:
        if not self._enabled or not total:
            return
        if self._tqdm is not None:
            if self._bar is None:
                self._bar = self._tqdm(total=total, desc=self._what, unit="step")
            self._bar.total = total
            self._bar.n = done
            self._bar.refresh()
            return
        tenth = (10 * done) // total
        if tenth != self._printed:
            self._printed = tenth
            print(f"{self._what}: {done}/{total} steps", flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _ident(name: str) -> str:
    s = re.sub(r"\W", "_", name)
    return s if s.isidentifier() else "_" + s


class QcodesTuner:
    """A spintune run on instruments reached through QCoDeS.

    Args:
        gates: tuner gate name → QCoDeS ``Parameter`` setting that gate. Every
            gate of the tuner config needs one.
        scans: scan kind (``"reload_time"``, ``"transition_width"``,
            ``"sensing_dot"``, ``"chemical_potential"``) → callable taking the
            scan request dict and returning raw traces or evaluated values
            (see the module docstring). Every kind the tuner config measures
            needs one.
        tuner_config: the tuner (the run config's ``tuner`` table) as a dict,
            merged into the paper default (gates with limits in mV, levels,
            targets, ``max_iterations``, ``stop_when_tuned``). The gates'
            limits are narrowed to the parameters' validators.
        readback_tolerance_mv: largest accepted |read-back − set value|, mV.
        mv_per_unit: per gate, mV per unit of its parameter (default from
            the parameter's unit: V → 1000, mV → 1).
        experiment: QCoDeS experiment for the datasets (default:
            ``load_or_create_experiment("spintune", sample_name=name)``).
        station: QCoDeS station recorded with the datasets' snapshot.
        name: name of the QCoDeS measurement.
        sleep: function used for the session's ``sleep`` outputs and keep
            mode's ``wait`` requests (lab time between checks), s.
        inter_delay_s: least time between two sets of one gate parameter, s
            (QCoDeS ``inter_delay``; default 1 ms, ``None`` leaves it as it
            is). A larger ``inter_delay`` already set is kept.

    Defence in depth: each gate parameter's QCoDeS ``step`` is set to the
    gate's ``max_step_mv`` in the parameter's unit (a smaller step already set
    is kept), so QCoDeS itself ramps any larger set in steps no longer than
    that, at most one per ``inter_delay``. QCoDeS ramps from its cached value,
    which every read of the run refreshes. ``ramps`` shows what is in force.

    A gate parameter that cannot be read raises ``ValueError``; one whose
    ``get()`` only returns its cached value (no ``get_cmd``) warns
    (``UserWarning``): its read-back checks prove nothing.
    """

    def __init__(
        self,
        gates: Mapping[str, Any],
        scans: Mapping[str, Callable[[Dict[str, Any]], Any]],
        tuner_config: Optional[Mapping[str, Any]] = None,
        *,
        readback_tolerance_mv: float = 0.05,
        mv_per_unit: Optional[Mapping[str, float]] = None,
        experiment: Any = None,
        station: Any = None,
        name: str = "spintune",
        sleep: Callable[[float], None] = time.sleep,
        inter_delay_s: Optional[float] = 0.001,
    ):
        if inter_delay_s is not None and not (
            isinstance(inter_delay_s, (int, float)) and 0 <= inter_delay_s < math.inf
        ):
            raise ValueError(f"inter_delay_s must be a number of seconds >= 0 or None, got {inter_delay_s!r}")
        config = resolve_tuner_config(dict(tuner_config or {}))
        config["gates"] = gate_limits(config["gates"], gates, mv_per_unit)
        for g in config["gates"]:
            _check_readable(g["name"], gates[g["name"]])
        _check_mapping(gates, scans)
        missing = [k for k in _scan_kinds(config) if k not in scans]
        if missing:
            raise ValueError(
                "no scan function for " + ", ".join(missing) + " (the tuner config measures them)"
            )
        self._gates = {g["name"]: gates[g["name"]] for g in config["gates"]}
        self._scale = {g: _mv_per_unit(g, p, mv_per_unit) for g, p in self._gates.items()}
        self._scans = dict(scans)
        self.session = RunSession(config, readback_tolerance_mv=readback_tolerance_mv)
        self.tuner_config: Dict[str, Any] = self.session.tuner_config
        self.experiment = experiment
        self.station = station
        self.name = name
        self._sleep = sleep
        self.records: List[Dict[str, Any]] = []
        self.datasets: List[Any] = []
        self.checkpoint: str = self.session.checkpoint()
        top = config["levels"][0]
        self._top_gates: List[str] = list(top.get("gates", []))
        self._top_params: List[Tuple[str, str]] = [
            (p["name"], p["unit"]) for p in top.get("parameters", [])
        ]
        # Only now that everything is valid: the parameters' own ramp.
        self.ramps: Dict[str, Dict[str, Any]] = {}
        for g in self.tuner_config["gates"]:
            gate = g["name"]
            self.ramps[gate] = _configure_ramp(
                gate, self._gates[gate], float(g["max_step_mv"]), self._scale[gate], inter_delay_s
            )

    # -- getting to the working point ----------------------------------------

    def travel_limits(
        self, travel_limits_mv: Optional[Mapping[str, Tuple[float, float]]] = None
    ) -> List[Dict[str, Any]]:
        """The range each gate may be ramped through (list of gate dicts with
        ``name``, ``min_mv``, ``max_mv``, ``max_step_mv``, mV): the gate
        parameter's validator range (converted to mV), narrowed to
        ``travel_limits_mv[gate] = (lo, hi)`` if given; a gate with neither
        travels only inside its tuning limits. ``max_step_mv`` is the
        tuner config's."""
        out = []
        for g in self.tuner_config["gates"]:
            name = g["name"]
            param, scale = self._gates[name], self._scale[name]
            vlo, vhi = _validator_range(param)
            lo = vlo * scale if vlo is not None else None
            hi = vhi * scale if vhi is not None else None
            if travel_limits_mv and name in travel_limits_mv:
                tlo, thi = (float(x) for x in travel_limits_mv[name])
                lo = tlo if lo is None else max(lo, tlo)
                hi = thi if hi is None else min(hi, thi)
            if lo is None or hi is None:
                lo = float(g["min_mv"]) if lo is None else lo
                hi = float(g["max_mv"]) if hi is None else hi
            out.append(
                {"name": name, "min_mv": lo, "max_mv": hi, "max_step_mv": float(g["max_step_mv"])}
            )
        return out

    def ramp_to(
        self,
        working_point_mv: Optional[Mapping[str, float]] = None,
        *,
        travel_limits_mv: Optional[Mapping[str, Tuple[float, float]]] = None,
        progress: bool = True,
    ) -> Dict[str, float]:
        """Move the gates from where the instrument says they are to a working
        point (mV), in steps within the limits, before the run starts — e.g.
        from a DAC's reset state (0 V) into the tuning window.

        The ramp is the core's (:class:`spintune.Ramp`), through the same
        safety guard as the tuning: every gate is read first; then all gates
        move together along straight lines, each set checked against the
        travel range (:meth:`travel_limits`) and the gate's ``max_step_mv``
        from the last **read-back**, each read-back against the set value
        (``readback_tolerance_mv``). The working point must lie inside the
        tuning limits (:attr:`limits`), so the run accepts it.

        Args:
            working_point_mv: gate → mV; default: every gate's ``initial_mv``
                of the tuner config. Only the gates named are moved.
            travel_limits_mv: gate → ``(lo, hi)`` mV, narrowing the range a
                gate may be ramped through (default: the parameter's
                validator range; the tuning limits without a validator).
            progress: show a progress bar (``tqdm`` if installed, else one
                printed line per 10 %).

        Returns the final read-backs, gate → mV.

        Raises ``ValueError`` (nothing more is moved) if a target is outside
        the tuning limits, a gate reads outside its travel range (``"SD1
        reads 0 mV, outside [-750, -450] mV …"``) or the instrument's answer
        is refused; ``RuntimeError`` once the run has started (its gates would
        read as moved). An exception of a gate parameter propagates after the
        ramp is ended.
        """
        if self.session.left_mv:
            raise RuntimeError(
                "ramp_to is for before the run: this run has started, and would find its "
                "gates moved (a `moved` fault); ramp before the first run()"
            )
        limits = self.limits
        if working_point_mv is None:
            target = {g["name"]: float(g["initial_mv"]) for g in self.tuner_config["gates"]}
        else:
            unknown = [g for g in working_point_mv if g not in limits]
            if unknown:
                raise ValueError(
                    f"ramp_to: unknown gates {', '.join(map(str, unknown))}; the gates are "
                    + ", ".join(limits)
                )
            target = {g: float(v) for g, v in working_point_mv.items()}
        # The working point must be one the run accepts: the core checks it
        # against the tuning limits.
        tuning = [{"name": g, **lim} for g, lim in limits.items()]
        try:
            Ramp(tuning, target)
        except ValueError as e:
            raise ValueError(f"ramp_to: the working point is outside the tuning limits: {e}") from None
        travel = self.travel_limits(travel_limits_mv)
        ramp = Ramp(travel, target, readback_tolerance_mv=self.session.readback_tolerance_mv)
        bar = _Progress(progress, "ramp to the working point")
        try:
            while True:
                out = ramp.poll()
                if out["output"] == "done":
                    break
                request = out["request"]
                try:
                    response = self._execute(request)
                except Exception as e:
                    ramp.feed({"response": "error", "message": f"{type(e).__name__}: {e}"})
                    raise
                try:
                    ramp.feed(response)
                except ValueError as e:
                    if request["request"] == "read_voltages" and "reads" in str(e):
                        raise ValueError(
                            f"ramp_to: {e} (the travel range is the gate parameter's validator "
                            "range, narrowed by travel_limits_mv)"
                        ) from None
                    raise
                bar.update(ramp.steps_done, ramp.steps_planned)
        finally:
            bar.close()
        return dict(ramp.readback_mv)

    # -- state and control ---------------------------------------------------

    @property
    def limits(self) -> Dict[str, Dict[str, float]]:
        """The limits in force per gate (mV): ``min_mv``, ``max_mv``, ``max_step_mv``."""
        return {
            g["name"]: {k: g[k] for k in ("min_mv", "max_mv", "max_step_mv")}
            for g in self.tuner_config["gates"]
        }

    @property
    def status(self) -> Dict[str, Any]:
        """The session's status dict, e.g. ``{"state": "paused"}``."""
        return self.session.status

    def pause(self) -> Dict[str, Any]:
        """Pause (between ``run()`` calls, or from a callback)."""
        return self.session.control({"action": "pause"})

    def stop(self) -> Dict[str, Any]:
        """Stop the run for good: no request is issued afterwards."""
        return self.session.control({"action": "stop"})

    def set_target(
        self, parameter: str, target: Optional[float], tolerance: Optional[Mapping[str, float]] = None
    ) -> Dict[str, Any]:
        """Change a parameter's target (its unit; ``None`` removes it) and
        optionally its tolerance (``{"relative": 0.1}`` or ``{"absolute": x}``);
        applies from the next iteration."""
        cmd: Dict[str, Any] = {"action": "set_target", "parameter": parameter, "target": target}
        if tolerance is not None:
            cmd["tolerance"] = dict(tolerance)
        return self.session.control(cmd)

    # -- the driver loop -----------------------------------------------------

    def run(
        self,
        iterations: Optional[int] = None,
        *,
        on_iteration: Optional[Callable[[Dict[str, Any]], None]] = None,
    ):
        """Drive the session until the run is over, paused or faulted — or,
        with ``iterations``, until that many more iterations are committed
        (then it pauses; ``run()`` again continues). A paused or faulted run
        is resumed first (every gate is read back before anything moves).

        Each call records its iterations into a new QCoDeS dataset (returned;
        also appended to ``datasets``). ``on_iteration(record)`` is called
        after each iteration is recorded.

        Raises :class:`TuningFault` if the session faulted. Any other
        exception — of a scan callable, a gate parameter, ``on_iteration``,
        QCoDeS, or ``KeyboardInterrupt`` — propagates after the run is made
        safe: a request that was at the instrument is reported to the session
        as a device fault (its outcome is unknown), and a running run is
        paused. So the next ``run()`` reads every gate back before it moves
        one (see the module docstring).
        """
        state = self.session.status["state"]
        if state in ("finished", "stopped"):
            raise RuntimeError(f"the run is {state}; create a new QcodesTuner to tune again")
        try:
            return self._run(iterations, on_iteration)
        except BaseException as e:
            # Whatever escaped, from wherever (the resume, the dataset's
            # creation, the loop, a callback, closing the dataset): the
            # session must not be left running on read-backs that the next
            # run() would trust.
            self._make_safe(e)
            raise

    def _run(
        self,
        iterations: Optional[int],
        on_iteration: Optional[Callable[[Dict[str, Any]], None]],
    ):
        state = self.session.status["state"]
        if state in ("running", "stepping") and (
            self.session.readback_mv or self.session.has_request_in_flight
        ):
            # Left moving by a driver outside run() (the session driven by
            # hand): whatever happened to the gates since, read them first.
            self._make_safe(None)
            self.session.control({"action": "step" if state == "stepping" else "resume"})
        elif state in ("paused", "faulted"):
            self.session.control({"action": "resume"})
        if self.experiment is None:
            self.experiment = load_or_create_experiment("spintune", sample_name=self.name)
        meas = Measurement(exp=self.experiment, station=self.station, name=self.name)
        columns = self._register(meas)
        committed = 0
        interrupted: Optional[BaseException] = None
        saver = None
        try:
            with meas.run() as saver:
                saver.dataset.add_metadata("spintune_tuner_config", json.dumps(self.tuner_config))
                try:
                    while True:
                        out = self.session.poll()
                        kind = out["output"]
                        if kind == "execute":
                            request = out["request"]
                            try:
                                response = self._execute(request)
                            except Exception as e:  # the instrument or a scan function failed
                                self.session.feed(
                                    {
                                        "response": "error",
                                        "message": f"{request['request']}: {type(e).__name__}: {e}",
                                    }
                                )
                                raise
                            self.session.feed(response)
                        elif kind == "commit":
                            record = out["record"]
                            self.checkpoint = self.session.checkpoint()
                            self.records.append(record)
                            saver.add_result(*self._row(columns, record))
                            committed += 1
                            if on_iteration is not None:
                                on_iteration(record)
                            if iterations is not None and committed >= iterations:
                                self.session.control({"action": "pause"})
                        elif kind == "save":
                            self.checkpoint = self.session.checkpoint()
                        elif kind == "sleep":
                            self._sleep(out["ms"] / 1000.0)
                        elif kind in ("wait", "done"):
                            break
                        # "publish": the status is read from the session when needed
                except BaseException as e:
                    # safe before the dataset records the status
                    self._make_safe(e)
                    if not isinstance(e, KeyboardInterrupt):
                        raise
                    interrupted = e  # the segment's dataset is completed first
                finally:
                    saver.dataset.add_metadata("spintune_status", json.dumps(self.session.status))
        finally:
            if saver is not None:  # also an interrupted or failed segment
                self.datasets.append(saver.dataset)
        dataset = saver.dataset
        if interrupted is not None:
            raise interrupted
        status = self.session.status
        if status["state"] == "faulted":
            raise TuningFault(status["fault"])
        return dataset

    def _make_safe(self, exc: Optional[BaseException]) -> None:
        """Leave the session so that nothing moves until every gate is read
        back: a request at the instrument is answered with a device error
        (its outcome is unknown, so nothing is believed about the gates), a
        running run is paused. A ``KeyboardInterrupt`` always ends paused
        (the user asked for a pause); for another exception a fault it caused
        stays visible. Idempotent."""
        session = self.session
        if exc is None:
            what = "run() found a request unanswered (left by a driver outside run())"
        elif isinstance(exc, KeyboardInterrupt):
            what = "interrupted by the user (KeyboardInterrupt)"
        else:
            text = str(exc)
            text = text if len(text) <= 300 else text[:300] + "…"
            what = f"{type(exc).__name__} in run(): {text}" if text else f"{type(exc).__name__} in run()"
        fed = False
        if session.has_request_in_flight:
            session.feed(
                {
                    "response": "error",
                    "message": f"{what} while a request was at the instrument; its outcome is unknown",
                }
            )
            fed = True
        state = session.status["state"]
        if state in ("running", "stepping") or (
            state == "faulted" and (exc is None or isinstance(exc, KeyboardInterrupt)) and fed
        ):
            session.control({"action": "pause"})
        self.checkpoint = session.checkpoint()

    def _get_mv(self, gate: str) -> float:
        return float(self._gates[gate].get()) * self._scale[gate]

    def _execute(self, request: Mapping[str, Any]) -> Dict[str, Any]:
        kind = request["request"]
        t0 = time.monotonic()
        if kind == "read_voltages":
            voltages = {g: self._get_mv(g) for g in request["gates"]}
            return {
                "response": "voltages_read",
                "voltages_mv": voltages,
                "lab_seconds": time.monotonic() - t0,
            }
        if kind == "set_voltages":
            for gate, mv in request["voltages_mv"].items():
                self._gates[gate].set(mv / self._scale[gate])
            voltages = {g: self._get_mv(g) for g in request["voltages_mv"]}
            return {
                "response": "voltages_set",
                "voltages_mv": voltages,
                "lab_seconds": time.monotonic() - t0,
            }
        if kind == "measure":
            scan = request["scan"]
            try:
                outcome = _outcome(scan["kind"], self._scans[scan["kind"]](dict(scan)))
            except ScanFailed as e:
                outcome = {"kind": "failed", "reason": str(e) or "scan failed"}
            return {"response": "scanned", "outcome": outcome, "lab_seconds": time.monotonic() - t0}
        if kind == "wait":
            # keep mode: lab time passes between checks (at most 600 s per request);
            # nothing touches the instrument
            seconds = float(request["seconds"])
            self._sleep(seconds)
            # `sleep` returned: the requested lab time has passed (a test's
            # or a scheduler's `sleep` may return at once and stand for it)
            return {"response": "waited", "lab_seconds": max(seconds, time.monotonic() - t0)}
        return {"response": "error", "message": f"`{kind}` is not available on instruments"}

    # -- the QCoDeS dataset --------------------------------------------------

    def to_xarray(self, dataset: Any = None) -> Any:
        """A QCoDeS dataset of this tuner (default: the last of
        :attr:`datasets`; or a ``run_id``) as an ``xarray.Dataset`` with an
        integer ``iteration`` coordinate. QCoDeS stores a ``numeric``
        setpoint as float64 (its ``array`` type would keep integers, but
        then every dependent, the text ``record`` too, must be an array,
        which QCoDeS cannot store for text), so ``to_xarray_dataset()``
        gives float iterations; this converts them back (exactly: they are
        whole numbers below 2**53). Units are UDUNITS (``uV``)."""
        import numpy as np
        from qcodes.dataset import load_by_id

        if dataset is None:
            if not self.datasets:
                raise ValueError("no dataset yet: run() first")
            dataset = self.datasets[-1]
        elif isinstance(dataset, (int, np.integer)):
            dataset = load_by_id(int(dataset))
        ds = dataset.to_xarray_dataset()
        k = ds["iteration"].values
        if k.size and not np.array_equal(k, np.round(k)):
            raise ValueError("the dataset's iteration values are not whole numbers")
        return ds.assign_coords(iteration=("iteration", k.astype(np.int64), ds["iteration"].attrs))

    def _register(self, meas: Measurement) -> Dict[str, str]:
        cols: Dict[str, str] = {}

        def reg(key: str, label: str, unit: str, paramtype: str = "numeric") -> None:
            name = _ident(key)
            cols[key] = name
            meas.register_custom_parameter(
                name, label=label, unit=unit, setpoints=("iteration",), paramtype=paramtype
            )

        meas.register_custom_parameter("iteration", label="iteration k", unit="")
        for g in self._gates:
            reg(f"V_{g}", f"{g} voltage", "mV")
        for p, unit in self._top_params:
            unit = udunits(unit)
            reg(p, p, unit)
            reg(f"{p}_std", f"std of {p}", unit)
            reg(f"{p}_target", f"target of {p}", unit)
            for g in self._top_gates:
                reg(f"grad_{p}_{g}", f"d{p}/d{g}", f"{unit}/mV")
                reg(f"grad_{p}_{g}_std", f"std of d{p}/d{g}", f"{unit}/mV")
        for g in self._top_gates:
            reg(f"step_{g}", f"step of {g}", "mV")
        reg("lab_seconds", "lab time", "s")
        reg("tuned", "tuned", "")
        reg("failed_evaluations", "failed evaluations", "")
        reg("record", "iteration record (JSON)", "", paramtype="text")
        return cols

    def _row(self, cols: Mapping[str, str], r: Mapping[str, Any]) -> List[Tuple[str, Any]]:
        def f(x: Any) -> float:
            return math.nan if x is None else float(x)

        vals: Dict[str, Any] = {}
        for g in self._gates:
            vals[f"V_{g}"] = f(r["voltages_mv"].get(g))
        params = {p["name"]: p for p in r["parameters"]}
        grads = {g["parameter"]: g for g in r["gradients"]}
        for p, _ in self._top_params:
            rep = params.get(p, {})
            vals[p] = f(rep.get("value"))
            vals[f"{p}_std"] = f(rep.get("std"))
            vals[f"{p}_target"] = f(rep.get("target"))
            grad = grads.get(p)
            for j, g in enumerate(self._top_gates):
                vals[f"grad_{p}_{g}"] = f(grad["gradient"][j]) if grad else math.nan
                cov = grad.get("covariance") if grad else None
                vals[f"grad_{p}_{g}_std"] = math.sqrt(max(f(cov[j][j]), 0.0)) if cov else math.nan
        for j, g in enumerate(self._top_gates):
            vals[f"step_{g}"] = f(r["step_mv"][j]) if j < len(r["step_mv"]) else math.nan
        vals["lab_seconds"] = f(r["lab_seconds"])
        vals["tuned"] = 1.0 if r["tuned"] else 0.0
        vals["failed_evaluations"] = float(r["failed_evaluations"])
        vals["record"] = json.dumps(r)
        row = [("iteration", int(r["iteration"]))]
        row += [(cols[k], v) for k, v in vals.items()]
        return row


# `qcodes` is imported so that a missing installation fails at import time
# with a clear ModuleNotFoundError naming qcodes.
_ = qcodes
