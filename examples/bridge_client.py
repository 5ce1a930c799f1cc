#!/usr/bin/env python3
"""spintune lab bridge client: your measurement script as a run's device.

The server sends requests ("set these gates", "measure scan X"); this script
executes them with the lab's own instruments and answers. Here the answers
come from a toy model so that the script runs anywhere; the two
functions marked ``PLUG IN QCODES HERE`` are where a lab calls its
instruments instead.

Usage (one dependency: ``pip install websockets``)::

    export SPINTUNE_TOKEN=SECRET       # read by the server and by this script
    spintune serve &
    curl -H "Authorization: Bearer $SPINTUNE_TOKEN" -d '{"driver":"bridge"}' \\
         http://127.0.0.1:8080/api/runs            # -> {"id": 1, ...}
    python3 examples/bridge_client.py --url ws://127.0.0.1:8080/api/runs/1/bridge

Protocol (JSON text frames, see docs/instruments.md):

    (the script adds ?protocol=4 to the URL: the server refuses clients
    that do not state the protocol version they speak)
    server: {"type":"hello","version":4,"run":{...}}
    client: {"type":"auth","token":"SECRET"}
    server: {"type":"auth_ok"}
    server: {"type":"request","id":6,"timeout_s":300.0,
             "request":{"request":"read_voltages","gates":["N","SB"]}}
    client: {"type":"response","id":6,
             "response":{"response":"voltages_read","voltages_mv":{"N":-700.0,"SB":-780.0},"lab_seconds":0.0}}
    server: {"type":"request","id":7,"timeout_s":300.0,
             "request":{"request":"set_voltages","voltages_mv":{"SB":-779.2}}}
    client: {"type":"response","id":7,
             "response":{"response":"voltages_set","voltages_mv":{"SB":-779.2},"lab_seconds":0.1}}
    server: {"type":"request","id":8,"timeout_s":300.0,
             "request":{"request":"measure","scan":{"kind":"transition_width","sweep":null}}}
    client: {"type":"response","id":8,"response":{"response":"scanned","lab_seconds":28.0,
             "outcome":{"kind":"evaluated","values":[{"name":"w","value":265.1,"variance":16.0}]}}}

An array run (its cells described in the run config's `array.description`,
docs/array.md) names each scan's cell (`"cell": 1`) and prefixes each cell's
gates (`c1.N`), and asks several cells at once in a `batch`; this script
answers both (see `answer`), with one toy model per cell.

Units: voltages in mV; ``t_sr`` in ns; ``w`` in µV; line positions and the
sensing-dot flank in mV; variances in the unit squared; lab time in s.

If the connection drops, the run pauses; this script reconnects (unless
``--once``) and the run resumes with the request that was outstanding.
"""

import argparse
import asyncio
import json
import math
import os
import random
import sys

import websockets

# The wire protocol this script speaks (spintune::protocol::PROTOCOL_VERSION).
PROTOCOL_VERSION = 4

# --- toy device -------------------------------------------------------------
# A model around a working point: with d = sum_g J[g] * (V_g - V0_g), a line
# position is p0 + d and t_sr, w (positive) are p0 * exp(d / p0).
# Replace it by real measurements (see the two functions below).

WORKING_POINT_MV = {"N": -700.0, "T": -650.0, "SA": -820.0, "SB": -780.0,
                    "PA": -300.0, "PB": -320.0, "SD1": -600.0, "SP": -500.0,
                    "SD2": -620.0, "RFA": 0.0, "RFB": 0.0}
MODEL = {
    # name: (value at the working point, {gate: slope per mV}, standard deviation)
    "t_sr": (40.0, {"N": -1.5, "T": 0.5, "SA": 0.8, "SB": 1.2}, 1.0),          # ns
    "w": (230.0, {"N": 1.0, "T": 2.5, "SA": -1.5, "SB": -2.0}, 4.0),           # µV
    "mu_a_mv": (0.0, {"PA": 0.8, "PB": 0.2, "N": 0.1, "SA": 0.1}, 0.05),      # mV
    "mu_b_mv": (0.0, {"PA": 0.2, "PB": 0.8, "T": 0.1, "SB": 0.1}, 0.05),      # mV
}
SCAN_PARAMETERS = {
    "transition_width": ["w"],
    "reload_time": ["t_sr"],
    "chemical_potential": ["mu_a_mv", "mu_b_mv"],
}
SCAN_LAB_SECONDS = {"sensing_dot": 17.0, "chemical_potential": 38.0,
                    "transition_width": 28.0, "reload_time": 5.0}

gates_mv = dict(WORKING_POINT_MV)   # what the toy "instrument" is set to, mV


def local(gate):
    """An array's gate `c1.N` -> `N` (cell 1's copy of gate N); others unchanged."""
    head, dot, rest = gate.partition(".")
    return rest if dot and head[:1] == "c" and head[1:].isdigit() else gate


def voltage(gate):
    """The toy's present output of `gate`, mV (an array cell's gates start at
    the working point too)."""
    return gates_mv.get(gate, WORKING_POINT_MV.get(local(gate), 0.0))
rng = random.Random(1)
# A real DAC keeps its outputs when this script restarts; the toy keeps them
# in this file when --state is given. (Without it a restarted toy is back at
# its working point: the server then faults the run `moved` and waits for a
# person to confirm the positions, as it should for a real instrument.)
state_path = None


def load_state(path):
    global state_path
    state_path = path
    if path and os.path.exists(path):
        with open(path) as f:
            gates_mv.update(json.load(f))


def save_state():
    if state_path:
        tmp = state_path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(gates_mv, f)
        os.replace(tmp, state_path)


def set_gates(voltages_mv):
    """PLUG IN QCODES HERE: set DC gates, return what was applied (read back).

    e.g. ``for g, v in voltages_mv.items(): station.dac.channels[CH[g]].volt(v / 1000)``
    then read them back with ``...volt()`` * 1000. Always answer with the
    read-back values in mV: the server compares them with the request.
    """
    gates_mv.update(voltages_mv)
    save_state()
    return dict(voltages_mv), 0.1


def read_gates(gates):
    """PLUG IN QCODES HERE: read the present output of these DC gates, mV.

    e.g. ``{g: station.dac.channels[CH[g]].volt() * 1000 for g in gates}``.
    Answer exactly the gates asked for: the server checks every step against
    these values, never against its own plan.
    """
    return {g: voltage(g) for g in gates}, 0.0


def measure(scan):
    """PLUG IN QCODES HERE: run the scan, return a ScanOutcome and its lab time.

    Either evaluated values ``{"kind":"evaluated","values":[{"name","value","variance"}]}``
    (your own fits), or raw traces for the server's fits:
    ``{"kind":"raw","scan":{"kind":..., "x_label":..., "y_label":...,
    "traces":[{"label":..., "x":[...], "y":[...]}]}}``, or
    ``{"kind":"failed","reason":"..."}`` when the measurement did not work.
    """
    kind = scan["kind"]
    seconds = SCAN_LAB_SECONDS.get(kind, 1.0)
    # An array's scan names its cell (`"cell": 1`): it measures that cell's
    # gates `c1.N`, … (here: one toy model per cell, without crosstalk).
    prefix = f"c{scan['cell']}." if scan.get("cell") is not None else ""
    if kind == "sensing_dot":
        # Park the sensing dot in the middle of the requested sweep.
        sweep = scan.get("sweep")
        if not sweep:
            return {"kind": "failed", "reason": "sensing-dot scan without a sweep"}, seconds
        centre = 0.5 * (sweep["from_mv"] + sweep["to_mv"])
        values = [{"name": "sd_flank_mv", "value": centre, "variance": 0.01}]
        return {"kind": "evaluated", "values": values}, seconds
    values = []
    for name in SCAN_PARAMETERS.get(kind, []):
        p0, slopes, sigma = MODEL[name]
        change = sum(s * (voltage(prefix + g) - WORKING_POINT_MV.get(g, 0.0))
                     for g, s in slopes.items())
        # t_sr and w are positive: exponential in the gates (the slopes at
        # the working point as given); line positions are linear.
        value = p0 * math.exp(change / p0) if name in ("t_sr", "w") else p0 + change
        value += rng.gauss(0.0, sigma)
        values.append({"name": name, "value": value, "variance": sigma * sigma})
    if not values:
        return {"kind": "failed", "reason": f"the toy model cannot measure {kind}"}, seconds
    return {"kind": "evaluated", "values": values}, seconds


def answer(request):
    """Turn one protocol Request into a Response (both plain dicts)."""
    what = request["request"]
    try:
        if what == "set_voltages":
            applied, seconds = set_gates(request["voltages_mv"])
            return {"response": "voltages_set", "voltages_mv": applied, "lab_seconds": seconds}
        if what == "read_voltages":
            present, seconds = read_gates(request["gates"])
            return {"response": "voltages_read", "voltages_mv": present, "lab_seconds": seconds}
        if what == "measure":
            outcome, seconds = measure(request["scan"])
            return {"response": "scanned", "outcome": outcome, "lab_seconds": seconds}
        if what == "batch":
            # An array run asks several cells at once: answer each request in
            # order. Run them in parallel where the readout allows; the lab
            # time is what the whole batch took (here: one sensor per cell, so
            # the cells' scans run in parallel and the busiest cell counts).
            answers = [answer(r) for r in request["requests"]]
            per_cell = {}
            for r, a in zip(request["requests"], answers):
                cell = (r.get("scan") or {}).get("cell")
                if cell is not None:
                    cell = f"c{cell}"
                else:  # a set or read names its cell in its gates (`c1.N`)
                    names = list(r.get("voltages_mv") or r.get("gates") or [])
                    cell = names[0].partition(".")[0] if names else None
                per_cell[cell] = per_cell.get(cell, 0.0) + a.get("lab_seconds", 0.0)
            seconds = max(per_cell.values(), default=0.0)
            return {"response": "batch", "responses": answers, "lab_seconds": seconds}
        return {"response": "error", "message": f"this bridge does not support {what!r}"}
    except Exception as e:  # an instrument error pauses the run with this message
        return {"response": "error", "message": f"{type(e).__name__}: {e}"}


# --- protocol ---------------------------------------------------------------

class ExitAfter(Exception):
    """--exit-after reached: leave with a request unanswered (tests reconnects)."""


async def serve_once(url, token, budget):
    """One connection: authenticate, then answer requests until it closes.

    ``budget`` is a one-element list: requests still to answer (None: no limit).
    """
    if "protocol=" not in url:
        url += ("&" if "?" in url else "?") + f"protocol={PROTOCOL_VERSION}"
    async with websockets.connect(url, max_size=None) as ws:
        hello = json.loads(await ws.recv())
        if hello.get("type") != "hello":
            raise RuntimeError(f"unexpected first frame: {hello}")
        print(f"bridge: run {hello['run']['id']} ({hello['run']['name']}), "
              f"protocol {hello['version']}", flush=True)
        await ws.send(json.dumps({"type": "auth", "token": token}))
        reply = json.loads(await ws.recv())
        if reply.get("type") != "auth_ok":
            raise RuntimeError(f"refused: {reply.get('message', reply)}")
        print("bridge: authenticated, serving requests", flush=True)
        async for text in ws:
            msg = json.loads(text)
            if msg["type"] == "request":
                if budget[0] is not None:
                    if budget[0] == 0:
                        raise ExitAfter()
                    budget[0] -= 1
                response = answer(msg["request"])
                await ws.send(json.dumps({"type": "response", "id": msg["id"],
                                          "response": response}))
            elif msg["type"] == "error":
                print(f"bridge: server says: {msg['message']}", file=sys.stderr, flush=True)


async def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--url", required=True, help="ws://HOST:PORT/api/runs/ID/bridge")
    ap.add_argument("--token", default=os.environ.get("SPINTUNE_TOKEN"),
                    help="control token of `spintune serve` (default: $SPINTUNE_TOKEN; "
                         "a flag is visible to other users in `ps`)")
    ap.add_argument("--once", action="store_true", help="exit when the connection closes")
    ap.add_argument("--exit-after", type=int, default=None, metavar="N",
                    help="answer N requests, then exit leaving the next one unanswered "
                         "(to try out pause and resume)")
    ap.add_argument("--state", default=None, metavar="FILE",
                    help="keep the toy instrument's gate voltages in FILE across restarts "
                         "(as a real DAC keeps its outputs)")
    args = ap.parse_args()
    load_state(args.state)
    if not args.token:
        ap.error("no token: set SPINTUNE_TOKEN (or pass --token)")
    budget = [args.exit_after]
    while True:
        try:
            await serve_once(args.url, args.token, budget)
        except ExitAfter:
            print(f"bridge: answered {args.exit_after} requests, exiting", flush=True)
            return 0
        except RuntimeError as e:  # refused: reconnecting would not help
            print(f"bridge: {e}", file=sys.stderr, flush=True)
            return 1
        except (OSError, websockets.ConnectionClosed) as e:
            print(f"bridge: connection lost ({e})", file=sys.stderr, flush=True)
        if args.once:
            return 0
        await asyncio.sleep(1.0)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
