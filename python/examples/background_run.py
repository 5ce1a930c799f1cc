# %% [markdown]
# # A run in the background, watched live
#
# `SimulationRun.run()` releases the GIL while it computes and the run is
# thread-safe: start it in a thread, and the notebook stays responsive —
# read `status` and `records`, plot them as they come, change a target or
# stop the run from the main thread. (The same pattern works for a
# `QcodesTuner`: call `tuner.run()` in the thread, read `tuner.records`, and
# `tuner.pause()`/`tuner.stop()` from the notebook between iterations.)
#
# Run it as a script or cell by cell (`# %%` cells in Jupyter/VS Code).
# `SPINTUNE_EXAMPLE_ITERATIONS` bounds the run (default 200);
# `SPINTUNE_EXAMPLE_OUT` is where the final plot goes (default: here).

# %%
import os
import threading
import time

import spintune

iterations = int(os.environ.get("SPINTUNE_EXAMPLE_ITERATIONS", "200"))
out_dir = os.environ.get("SPINTUNE_EXAMPLE_OUT", ".")
run = spintune.SimulationRun(
    {"seed": 5, "tuner": {"max_iterations": iterations, "stop_when_tuned": False}}
)
errors = []


def work():
    try:
        run.run()
    except Exception as e:  # shown by the watcher below
        errors.append(e)


worker = threading.Thread(target=work, name="spintune run", daemon=True)
worker.start()

# %% [markdown]
# ## Watch it live
# In Jupyter the figure is redrawn in place (`IPython.display`); as a script
# one line per update is printed. Without matplotlib only the lines.

# %%
try:
    import matplotlib

    if not os.environ.get("MPLBACKEND"):
        try:
            get_ipython  # type: ignore[name-defined]  # noqa: B018 - in Jupyter?
        except NameError:
            matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    plt = None

try:
    from IPython import get_ipython as _gi
    from IPython.display import clear_output, display

    in_notebook = _gi() is not None and hasattr(_gi(), "kernel")
except ImportError:
    in_notebook = False


def plot(records):
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(6, 5))
    k = [r["iteration"] for r in records]
    for ax, name, unit in ((ax1, "t_sr", "ns"), (ax2, "w", "uV")):
        values = [next(p["value"] for p in r["parameters"] if p["name"] == name) for r in records]
        target = next(p["target"] for p in records[-1]["parameters"] if p["name"] == name)
        ax.plot(k, values, ".-")
        ax.axhline(target, color="k", lw=0.8)
        ax.set_ylabel(f"{name} ({unit})")
    ax2.set_xlabel("iteration")
    return fig


shown = -1
retargeted = False
while True:
    status = run.status  # safe while run() is computing in the thread
    records = run.records
    if len(records) != shown and records:
        shown = len(records)
        last = {p["name"]: p["value"] for p in records[-1]["parameters"]}
        print(
            f"{status['state']:>8}: {shown} iterations, t_sr = {last['t_sr']:.2f} ns, "
            f"w = {last['w']:.1f} uV, tuned = {records[-1]['tuned']}",
            flush=True,
        )
        if plt is not None and in_notebook:
            fig = plot(records)
            clear_output(wait=True)
            display(fig)
            plt.close(fig)
    if not worker.is_alive():
        break
    if not retargeted and shown >= iterations // 2 and status["state"] == "running":
        # a change from the main thread while the run goes on
        retargeted = True
        print("main thread: new target for w, 300 uV", flush=True)
        run.control({"action": "set_target", "parameter": "w", "target": 300.0})
    time.sleep(0.2)

worker.join()
if errors:
    raise errors[0]
print(f"run ended: {run.status['state']} after {len(run.records)} iterations", flush=True)

# %% [markdown]
# ## Stop a run from the main thread
# A stop is honoured at once; `run()` in the thread returns.

# %%
endless = spintune.SimulationRun({"seed": 6, "tuner": {"stop_when_tuned": False}})
t = threading.Thread(target=endless.run, daemon=True)
t.start()
while len(endless.records) < 3:
    time.sleep(0.05)
print("stopping:", endless.control({"action": "stop"}), flush=True)
t.join(timeout=60)
print(f"stopped after {len(endless.records)} iterations, thread alive: {t.is_alive()}", flush=True)

if plt is not None:
    fig = plot(run.records)
    fig.savefig(os.path.join(out_dir, "background_run.png"))
    print("figure:", os.path.join(out_dir, "background_run.png"), flush=True)
