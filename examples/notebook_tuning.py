# %% [markdown]
# # Tuning a spin qubit with spintune — a notebook you run top to bottom
#
# After Teske et al., *A Machine Learning Approach for Automated Fine-Tuning
# of Semiconductor Spin Qubits*, APL 2019. Every cell runs as is (in Jupyter,
# VS Code "# %%" cells, or `python examples/notebook_tuning.py`).
#
# Setup, once, from the repository root:
#
#     python3 -m venv .venv && . .venv/bin/activate
#     pip install "./python[xarray,qcodes]"          # builds the Rust core (needs rustup)
#
# Units everywhere: gate voltages in mV, t_sr in ns, w in µV, gradients in
# ns/mV and µV/mV, lab time in s.
#
# How long it runs: SPINTUNE_EXAMPLE_ITERATIONS (default 30) iterations per
# run; outputs (netCDF file, QCoDeS database) go to SPINTUNE_EXAMPLE_OUT
# (default ./notebook_output).

# %%
import json
import os
import pathlib
from functools import partial

import numpy as np

import spintune

ITERATIONS = int(os.environ.get("SPINTUNE_EXAMPLE_ITERATIONS", "30"))
OUT = pathlib.Path(os.environ.get("SPINTUNE_EXAMPLE_OUT", "notebook_output"))
OUT.mkdir(parents=True, exist_ok=True)
print("spintune", spintune.__version__, "| iterations per run:", ITERATIONS, "| output:", OUT)

# %% [markdown]
# ## 1. The filter and the step, by hand
#
# One parameter (say t_sr, ns) over two gates. The filter learns the
# gradient g (ns/mV) from voltage steps Δv (mV) and measured changes Δz (ns)
# with variance Δz² = δp(k)² + δp(k−1)² (ns²). Q = σ²·I is added after each
# update (the paper's constant process noise).

# %%
true_gradient = np.array([-1.5, 0.8])  # ns/mV
kf = spintune.KalmanGradient(gradient=[0.0, 0.0], covariance=np.eye(2) * 4.0, process_noise=0.075**2)
rng = np.random.default_rng(0)
for k in range(20):
    dv = rng.normal(0.0, 2.0, 2)  # mV
    dz = true_gradient @ dv + rng.normal(0.0, 0.5)  # ns, measured with δp = 0.35 ns
    kf.update(dv, dz, variance=2 * 0.35**2)
print("learned gradient (ns/mV):", kf.gradient, " ±", np.sqrt(np.diag(kf.covariance)))

# The quasi-Newton step towards t_sr = 20 ns from t_sr = 45 ns, limited to 10 mV:
step = spintune.newton_step(kf.gradient[None, :], [45.0 - 20.0], max_step_mv=10.0)
print("Newton step (mV):", step, "norm", np.linalg.norm(step))

# %% [markdown]
# ## 2. A whole run on the simulated double dot
#
# The paper's default setup: the qubit level tunes t_sr and w with gates N,
# SA, SB, T; after every move the sensing dot and the transition lines are
# re-tuned. Target: the paper's first set point (t_sr = 20 ns, w = 270 µV).

# %%
run = spintune.SimulationRun({"seed": 1, "tuner": {"max_iterations": ITERATIONS, "stop_when_tuned": True}})
for record in run:
    t_sr, w = (p["value"] for p in record["parameters"])
    print(f"k={record['iteration']:2d}  t_sr={t_sr:6.2f} ns  w={w:6.1f} µV  "
          f"lab {record['lab_seconds'] / 60:5.1f} min  {'tuned' if record['tuned'] else ''}")
print("status:", run.status, "| true values now:", {k: round(v, 2) for k, v in run.truth().items() if k in ("t_sr", "w")})

# %%
ds = run.to_xarray()
print(ds[["t_sr", "w", "t_sr_std", "w_std"]])
print("units:", {name: ds[name].attrs["units"] for name in ("t_sr", "w", "grad_t_sr", "voltage", "lab_seconds")})
ds.to_netcdf(OUT / "simulated_run.nc")
try:  # plots, if matplotlib is installed
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, sharex=True)
    ds["t_sr"].plot(ax=axes[0], marker="o")
    ds["w"].plot(ax=axes[1], marker="o")
    fig.savefig(OUT / "simulated_run.png")
except ImportError:
    print("(install matplotlib for plots)")

# %% [markdown]
# ## 3. The same tuner through QCoDeS
#
# In the lab, gates are QCoDeS parameters of a DAC and the scans are your own
# measurement functions. Here a small instrument stands in for the DAC: its
# channels (in V, with validators) drive the simulator, so this cell runs
# anywhere. Replace `SimulatedDac` by your DAC driver and the scan functions
# by your measurements; nothing else changes.

# %%
import qcodes
from qcodes.dataset import initialise_or_create_database_at, load_by_id, load_or_create_experiment
from qcodes.instrument import Instrument
from qcodes.validators import Numbers

from spintune.qcodes import QcodesTuner, ScanFailed, sweep_points_mv

initialise_or_create_database_at(str(OUT / "experiments.db"))
experiment = load_or_create_experiment("spintune notebook", sample_name="simulated double dot")
device = spintune.SimulatedDevice({"seed": 2})


class SimulatedDac(Instrument):
    """DAC channels in V backed by the simulated double dot."""

    def __init__(self, name, device):
        super().__init__(name)
        for g in device.gates:
            self.add_parameter(
                g["name"],
                unit="V",
                vals=Numbers(-2.0, 0.5),  # the DAC's own range; the tuner config's limits are stricter
                get_cmd=lambda gate=g["name"]: device.voltages_mv[gate] / 1000.0,
                set_cmd=partial(self._set, g["name"]),
            )

    def get_idn(self):
        return {"vendor": "spintune", "model": "simulated DAC", "serial": None, "firmware": spintune.__version__}

    def _set(self, gate, volts):
        r = device.execute({"request": "set_voltages", "voltages_mv": {gate: volts * 1000.0}})
        if r["response"] != "voltages_set":
            raise RuntimeError(r["message"])


Instrument.close_all()
dac = SimulatedDac("dac", device)
station = qcodes.Station(dac)


def measure(scan):
    """A scan: here raw traces from the simulator; in the lab, your measurement.
    Return raw traces (the core fits them) or {"t_sr": (value, variance)}."""
    r = device.execute({"request": "measure", "scan": scan})
    if r["outcome"]["kind"] != "raw":
        raise ScanFailed(r["outcome"].get("reason", "failed"))
    return r["outcome"]["scan"]


def sensing_dot(scan):
    """The sensing-dot scan sweeps a gate: step through the requested points, then go back."""
    gate = dac.parameters[scan["sweep"]["gate"]]
    start = gate()
    for mv in sweep_points_mv(scan["sweep"]):
        gate(mv / 1000.0)
    trace = measure(scan)
    gate(start)
    return trace


tuner = QcodesTuner(
    gates={g["name"]: dac.parameters[g["name"]] for g in device.gates},
    scans={"reload_time": measure, "transition_width": measure, "chemical_potential": measure,
           "sensing_dot": sensing_dot},
    tuner_config={"max_iterations": ITERATIONS, "stop_when_tuned": True},
    experiment=experiment,
    station=station,
    name="tune to the first set point",
)
print("limits in force (mV):", tuner.limits["N"])
# Interrupt the kernel at any time: the run pauses (nothing is set after the
# interrupt); run this cell's last line again to resume.
dataset = tuner.run(on_iteration=lambda r: print("k =", r["iteration"], [round(p["value"] or 0, 2) for p in r["parameters"]]))
print("status:", tuner.status)

# %%
loaded = load_by_id(dataset.run_id)
data = loaded.get_parameter_data()
print("QCoDeS dataset", loaded.run_id, "t_sr (ns):", np.round(data["t_sr"]["t_sr"], 2))
print("tuner config stored with it:", json.loads(loaded.metadata["spintune_tuner_config"])["levels"][0]["name"])
Instrument.close_all()
