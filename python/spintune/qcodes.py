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
  ``measure`` → your scan callable;
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

import json
import math
import re
import time
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import qcodes
from qcodes.dataset import Measurement, load_or_create_experiment

from . import RunSession, resolve_tuner_config

__all__ = ["QcodesTuner", "ScanFailed", "TuningFault", "sweep_points_mv", "gate_limits"]


class ScanFailed(Exception):
    """Raise from a scan callable when the measurement could not be made or
    evaluated; the tuner records a failed evaluation and continues."""


class TuningFault(RuntimeError):
    """The run session paused the run with a fault (a device error, a
    read-back that did not match, a request the safety guard refused). The
    run is resumable: fix the cause, then ``run()`` again."""

    def __init__(self, fault: Mapping[str, Any]):
        self.fault = dict(fault)
        super().__init__(f"{fault.get('kind', '?')} fault: {fault.get('message', '')}")


_UNIT_MV = {"V": 1000.0, "mV": 1.0, "uV": 1e-3, "µV": 1e-3, "μV": 1e-3}


def sweep_points_mv(sweep: Mapping[str, Any]) -> np.ndarray:
    """The voltages (mV) of a sweep request ``{"gate", "from_mv", "to_mv",
    "points"}``, in order: ``points`` evenly spaced values from ``from_mv`` to
    ``to_mv`` (the core's guard has checked every one against the limits)."""
    return np.linspace(float(sweep["from_mv"]), float(sweep["to_mv"]), int(sweep["points"]))


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
        sleep: function used for the session's ``sleep`` outputs, s.
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
    ):
        config = resolve_tuner_config(dict(tuner_config or {}))
        config["gates"] = gate_limits(config["gates"], gates, mv_per_unit)
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

        Raises :class:`TuningFault` if the session faulted, re-raises an
        exception of a scan callable or a gate parameter (after pausing the
        run with a device fault), and re-raises ``KeyboardInterrupt`` after
        pausing the run (see the module docstring).
        """
        state = self.session.status["state"]
        if state in ("finished", "stopped"):
            raise RuntimeError(f"the run is {state}; create a new QcodesTuner to tune again")
        if state in ("paused", "faulted"):
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
                except KeyboardInterrupt as e:
                    self._interrupted()
                    interrupted = e
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

    def _interrupted(self) -> None:
        """Ctrl-C: nothing more goes to the instrument; the run is paused."""
        if self.session.has_request_in_flight:
            # Its outcome is unknown: let the session believe nothing about the gates.
            self.session.feed(
                {
                    "response": "error",
                    "message": "interrupted by the user (KeyboardInterrupt) while a request "
                    "was at the instrument; its outcome is unknown",
                }
            )
        try:
            self.session.control({"action": "pause"})
        except RuntimeError:
            pass  # already stopped or finished
        self.checkpoint = self.session.checkpoint()

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
        return {"response": "error", "message": f"`{kind}` is not available on instruments"}

    # -- the QCoDeS dataset --------------------------------------------------

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
