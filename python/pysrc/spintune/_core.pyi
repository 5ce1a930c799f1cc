"""Type stubs of the native part of spintune (``spintune._core``).

Units: gate voltages in mV, t_sr in ns, w in µV, gradients in parameter unit
per mV, variances in unit², lab time in s. Dicts have the JSON shape of the
core's serde types (``protocol::Request``, ``Response``, ``IterationRecord``,
``ControlCommand``, ``RunStatus``, the configs).
"""

from os import PathLike
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

ArrayLike = Union[npt.ArrayLike, Sequence[float], Sequence[Sequence[float]]]
JsonDict = Dict[str, Any]

PROTOCOL_VERSION: int
__version__: str

class KalmanGradient:
    """The paper's Kalman filter for one parameter's gradient over n gates
    (constant process noise Q)."""

    def __init__(
        self,
        gradient: ArrayLike,
        covariance: ArrayLike,
        process_noise: Union[ArrayLike, float],
        *,
        outlier_sigma: Optional[float] = None,
        min_step_mv: float = 1e-6,
    ) -> None:
        """gradient: g(0), length n, unit/mV; covariance: C(0), n×n,
        (unit/mV)²; process_noise: Q, n×n, (unit/mV)², or a scalar σ² for
        Q = σ²·I. Raises ValueError for NaN, non-PSD covariance, wrong shapes."""
    def update(self, dv: ArrayLike, dz: float, variance: float) -> JsonDict:
        """dv: voltage step (mV, length n); dz: measured change (unit);
        variance: Δz² of that change (unit²). Returns the outcome dict
        (``kind`` = ``updated`` | ``gated`` | ``skipped_small_step``).
        Raises ValueError (state unchanged) for bad input."""
    @property
    def gradient(self) -> npt.NDArray[np.float64]:
        """Gradient estimate, 1-D (n,), unit/mV."""
    @property
    def covariance(self) -> npt.NDArray[np.float64]:
        """Covariance, 2-D (n, n), (unit/mV)²."""
    @property
    def process_noise(self) -> npt.NDArray[np.float64]:
        """Q, 2-D (n, n), (unit/mV)²."""
    @property
    def outlier_sigma(self) -> Optional[float]: ...
    @property
    def min_step_mv(self) -> float: ...
    @property
    def n(self) -> int:
        """Number of gates."""
    def checkpoint(self) -> str:
        """JSON of the filter (every float exact); pickling goes through it."""
    @staticmethod
    def restore(checkpoint: str) -> "KalmanGradient": ...
    def __reduce__(self) -> Tuple[Any, Tuple[str]]: ...
    def copy(self) -> "KalmanGradient": ...
    def __copy__(self) -> "KalmanGradient": ...
    def __deepcopy__(self, memo: Any) -> "KalmanGradient": ...

def newton_step(
    jacobian: ArrayLike,
    residual: ArrayLike,
    max_step_mv: float = 10.0,
    *,
    rank_tolerance: float = 1e-9,
) -> npt.NDArray[np.float64]:
    """Δv = −J⁺Δ (minimum norm), limited to max_step_mv. jacobian m×n
    (unit/mV), residual = measured − target (length m, unit); returns Δv
    (length n, mV). Raises ValueError for bad input."""

class RunSession:
    """The sans-IO run session (poll / feed / control)."""

    def __init__(
        self,
        tuner_config: Optional[Mapping[str, Any]] = None,
        readback_tolerance_mv: float = 0.05,
        iteration_delay_ms: int = 0,
        moved_tolerance_mv: float = 1.0,
    ) -> None: ...
    def poll(self) -> JsonDict:
        """``{"output": "execute" | "commit" | "save" | "publish" | "sleep" | "wait" | "done", ...}``"""
    def feed(self, response: Mapping[str, Any]) -> None:
        """The device's answer (JSON of ``protocol::Response``)."""
    def control(self, command: Mapping[str, Any]) -> JsonDict:
        """A ``protocol::ControlCommand`` dict; returns the new status."""
    def device_recovered(self) -> bool: ...
    @property
    def status(self) -> JsonDict: ...
    @property
    def has_request_in_flight(self) -> bool: ...
    @property
    def at_boundary(self) -> bool: ...
    @property
    def readback_mv(self) -> Dict[str, float]:
        """Last accepted read-back per gate, mV."""
    @property
    def tuner_config(self) -> JsonDict: ...
    @property
    def readback_tolerance_mv(self) -> float: ...
    def checkpoint(self) -> str:
        """The session as JSON."""
    @staticmethod
    def restore(checkpoint: str) -> "RunSession": ...
    def __reduce__(self) -> Tuple[Any, Tuple[str]]: ...
    @property
    def left_mv(self) -> Dict[str, List[float]]:
        """Where the run left each gate, gate → [lo, hi] mV (empty before the first read)."""

class Ramp:
    """The core's ramp of gates to a working point (mV), in steps within the
    limits, through the run session's guard."""

    def __init__(
        self,
        gates: Sequence[Mapping[str, Any]],
        target_mv: Mapping[str, float],
        readback_tolerance_mv: float = 0.05,
    ) -> None: ...
    def poll(self) -> JsonDict:
        """``{"output": "execute", "request": {...}}`` or ``{"output": "done"}``."""
    def feed(self, response: Mapping[str, Any]) -> None: ...
    @property
    def steps_done(self) -> int: ...
    @property
    def steps_planned(self) -> Optional[int]: ...
    @property
    def readback_mv(self) -> Dict[str, float]: ...
    @property
    def target_mv(self) -> Dict[str, float]: ...

def resolve_tuner_config(tuner_config: Optional[Mapping[str, Any]] = None) -> JsonDict:
    """A partial tuner config (optionally with a device ``description``) merged into the recommended tuner and validated."""

class SimulationRun:
    """A run of the paper's setup on the simulated double dot; iterating
    yields one IterationRecord dict per iteration."""

    def __init__(self, config: Optional[Mapping[str, Any]] = None) -> None: ...
    def __iter__(self) -> Iterator[JsonDict]: ...
    def __next__(self) -> JsonDict: ...
    def run(self, max_iterations: Optional[int] = None) -> List[JsonDict]:
        """Run to the end (or at most max_iterations more); all records so far."""
    @property
    def records(self) -> List[JsonDict]: ...
    @property
    def config(self) -> JsonDict: ...
    @property
    def status(self) -> JsonDict: ...
    def control(self, command: Mapping[str, Any]) -> JsonDict: ...
    def truth(self) -> Dict[str, float]:
        """Noiseless truth: w (µV), t_sr (ns), t_c_uev (µeV), gamma_per_ns (1/ns),
        mu_a_mv, mu_b_mv, sd_flank_mv (mV), sd_contrast."""
    @property
    def voltages_mv(self) -> Dict[str, float]: ...
    def to_xarray(self) -> Any:
        """``xarray.Dataset`` over ``iteration`` (variables with ``units``)."""
    def to_netcdf(self, path: Union[str, "PathLike[str]"]) -> None: ...
    def checkpoint(self) -> str:
        """JSON of the whole run (config, session, device, records); pickling goes through it."""
    @staticmethod
    def restore(checkpoint: str) -> "SimulationRun": ...
    def __reduce__(self) -> Tuple[Any, Tuple[str]]: ...

class ArraySimulation:
    """A simulated array of double-dot cells tuned jointly; iterating yields
    one IterationRecord dict per iteration (parameters ``c{k}.t_sr`` in ns,
    ``c{k}.w`` in µV; gates ``c{k}.N``, … in mV)."""

    def __init__(self, config: Optional[Mapping[str, Any]] = None) -> None:
        """config: partial array config (name, array, device, targets as
        ``(t_sr ns, w µV)`` pairs, tuning, cross_calibration); ValueError names a bad field."""
    def __iter__(self) -> Iterator[JsonDict]: ...
    def __next__(self) -> JsonDict: ...
    def run(self, max_iterations: int = 200) -> List[JsonDict]:
        """At most max_iterations more (fewer once every cell is in band); all records so far."""
    @property
    def records(self) -> List[JsonDict]: ...
    @property
    def config(self) -> JsonDict: ...
    @property
    def cells(self) -> int: ...
    @property
    def targets(self) -> List[Tuple[float, float]]:
        """Present targets per cell, (t_sr ns, w µV)."""
    @property
    def status(self) -> JsonDict: ...
    def control(self, command: Mapping[str, Any]) -> JsonDict:
        """pause / resume / stop, or set_target of ``c{k}.t_sr`` (ns) / ``c{k}.w`` (µV)."""
    def truth(self) -> List[Dict[str, float]]:
        """The simulator's noiseless truth per cell (world side, for teaching):
        w (µV), t_sr (ns), t_c_uev (µeV), gamma_per_ns (1/ns), mu_a_mv, mu_b_mv,
        sd_flank_mv (mV), sd_contrast."""
    @property
    def voltages_mv(self) -> Dict[str, float]: ...
    def to_xarray(self) -> Any:
        """``xarray.Dataset`` over ``iteration`` and ``cell``: t_sr (ns), w (uV),
        their _std, _target, _tolerance; lab_seconds (s)."""
    def to_netcdf(self, path: Union[str, "PathLike[str]"]) -> None: ...
    def checkpoint(self) -> str:
        """JSON of the whole array run (config, session, array, records)."""
    @staticmethod
    def restore(checkpoint: str) -> "ArraySimulation": ...
    def __reduce__(self) -> Tuple[Any, Tuple[str]]: ...

class RecordColumns:
    """Internal: iteration records → the columns of ``to_xarray()``'s Dataset."""

    def __init__(self) -> None: ...
    def add(self, record: Mapping[str, Any]) -> None: ...
    def add_json(self, texts: List[str]) -> None: ...
    def finish(self) -> JsonDict: ...
    def __len__(self) -> int: ...

class SimulatedDevice:
    """The simulated double dot alone: ``execute(request) -> response``."""

    def __init__(self, config: Optional[Mapping[str, Any]] = None, seed: Optional[int] = None) -> None: ...
    def execute(self, request: Mapping[str, Any]) -> JsonDict: ...
    @property
    def voltages_mv(self) -> Dict[str, float]: ...
    @property
    def gates(self) -> List[JsonDict]: ...
    @property
    def lab_seconds(self) -> float: ...
    def truth(self) -> Dict[str, float]: ...

def default_config() -> JsonDict:
    """The default run config (name, seed, device, tuner): the recommended strategy."""

def paper_config() -> JsonDict:
    """The paper's own rule on its device (linear, pseudo-inverse, one move)."""

def resolve_config(config: Optional[Mapping[str, Any]] = None) -> JsonDict:
    """A partial run config (optionally with a device ``description``) merged into the default and validated."""
