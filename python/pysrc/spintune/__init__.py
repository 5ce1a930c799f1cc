"""spintune: automated fine-tuning of gate-defined spin qubits.

Teske et al., "A Machine Learning Approach for Automated Fine-Tuning of
Semiconductor Spin Qubits", APL 2019: a Kalman filter per parameter learns
the gradient over the gate voltages, a quasi-Newton solver moves the gates in
limited steps. This package wraps the Rust core (the numbers, the run session
and its safety checks are the core's) and adds readers and adapters:

* :class:`KalmanGradient`, :func:`newton_step` — the paper's filter and step.
* :class:`SimulationRun` — a whole run on the simulated double dot.
* :class:`ArraySimulation` — a simulated array of double dots tuned jointly.
* :class:`RunSession` — the sans-IO run session, for driving real instruments.
* :class:`Ramp` — bring gates to a working point within the limits (same guard).
* :class:`SimulatedDevice` — the simulator alone (answers requests).
* :func:`open_store` — runs stored by ``spintune serve`` / ``spintune run``.
* :mod:`spintune.qcodes` — drive the session with QCoDeS parameters.

Units: gate voltages in mV, t_sr in ns, w in µV, gradients in parameter unit
per mV, lab time in s. See ``docs/python.md``.
"""

from ._core import (
    PROTOCOL_VERSION,
    ArraySimulation,
    KalmanGradient,
    Ramp,
    RunSession,
    SimulatedDevice,
    SimulationRun,
    __version__,
    default_config,
    newton_step,
    paper_config,
    resolve_config,
    resolve_tuner_config,
)
from .store import Store, StoredRun, open_store

__all__ = [
    "PROTOCOL_VERSION",
    "ArraySimulation",
    "KalmanGradient",
    "Ramp",
    "RunSession",
    "SimulatedDevice",
    "SimulationRun",
    "Store",
    "StoredRun",
    "__version__",
    "default_config",
    "newton_step",
    "open_store",
    "paper_config",
    "resolve_config",
    "resolve_tuner_config",
    "records_to_dataset",
]


def records_to_dataset(records, attrs=None):
    """Iteration records (list of dicts) as an ``xarray.Dataset``; see
    :meth:`SimulationRun.to_xarray` for the variables."""
    from ._xarray import records_to_dataset as _impl

    return _impl(records, attrs)
