"""Benchmark: open_store on a 20,000-iteration run (issue 26, "stores at lab
scale"). Targets: ``to_xarray(scans=False)`` in < 2 s and < 200 MB.

Usage (from the repository root, with the package installed and the
`spintune` binary built, e.g. by `cargo xtask test`)::

    python python/benchmarks/store_scale.py --bin "$CARGO_TARGET_DIR/debug/spintune" [--iterations 20000] [--keep store.db]

1. A real store: `spintune run --db` writes a short simulated run (the
   server's schema, real ~15 KB records of which ~88 % are raw scans).
2. It is grown to N iterations with the same SQL the server uses
   (`INSERT INTO iterations (run_id, seq, record)`): the real records
   cycled, their `iteration` renumbered (synthetic, but of realistic size
   and shape).
3. Each measurement runs in a fresh Python process (so one does not inherit
   another's memory): wall time (`time.perf_counter`) and the process's
   peak resident memory (`resource.getrusage(...).ru_maxrss`, which
   includes the interpreter, numpy and xarray: the baseline after the
   imports is printed too); then once more with `tracemalloc` for the peak
   of Python's own allocations (tracemalloc slows allocation-heavy code, so
   its run is not timed).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sqlite3
import subprocess
import sys
import tempfile
import time

MEASURE = r'''
import json, resource, sys, time, tracemalloc
import numpy, xarray, spintune
path, what, trace = sys.argv[1], sys.argv[2], sys.argv[3] == "trace"
base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if trace:
    tracemalloc.start()
t0 = time.perf_counter()
run = spintune.open_store(path).run(1)
if what == "to_xarray":
    ds = run.to_xarray(scans=False)
    out = {"iterations": int(ds.sizes["iteration"]), "dataset_mb": ds.nbytes / 1e6}
elif what == "iter_records":
    n = 0
    for r in run.iter_records():
        n += 1
    out = {"iterations": n}
elif what == "scans":
    s = run.scans(10_000, 10_010)
    out = {"iterations": len(s)}
elif what == "records_full":
    out = {"iterations": len(run.records)}
seconds = time.perf_counter() - t0
peak = tracemalloc.get_traced_memory()[1] if trace else 0
out.update(seconds=seconds, tracemalloc_peak_mb=peak / 2**20,
           maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, base_rss_mb=base_rss)
print(json.dumps(out))
'''


def make_store(bin_path: str, iterations: int, path: pathlib.Path) -> float:
    cfg = path.with_suffix(".toml")
    cfg.write_text('name = "store-scale"\nseed = 1\n[tuner]\nmax_iterations = 4\nstop_when_tuned = false\n')
    subprocess.run([bin_path, "run", "--config", str(cfg), "--db", str(path), "--quiet"], check=True)
    t0 = time.perf_counter()
    conn = sqlite3.connect(path)
    real = [json.loads(r[0]) for r in conn.execute("SELECT record FROM iterations WHERE run_id = 1 ORDER BY seq")]
    have = len(real)
    with conn:
        rows = []
        for k in range(have, iterations):
            rec = dict(real[k % have], iteration=k)
            rows.append((1, k, json.dumps(rec)))
            if len(rows) == 2000:
                conn.executemany("INSERT INTO iterations (run_id, seq, record) VALUES (?, ?, ?)", rows)
                rows = []
        conn.executemany("INSERT INTO iterations (run_id, seq, record) VALUES (?, ?, ?)", rows)
        conn.execute("UPDATE runs SET iterations = ? WHERE id = 1", (iterations,))
    conn.close()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default=os.environ.get("SPINTUNE_BIN"), help="the spintune binary")
    ap.add_argument("--iterations", type=int, default=20_000)
    ap.add_argument("--keep", help="write the store here and keep it")
    ap.add_argument("--full", action="store_true", help="also time `run.records` (every scan parsed)")
    args = ap.parse_args()
    if not args.bin:
        ap.error("--bin (or SPINTUNE_BIN) is required: the `spintune` binary writes the store")
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(args.keep) if args.keep else pathlib.Path(tmp) / "store.db"
        if path.exists():
            path.unlink()
        gen = make_store(args.bin, args.iterations, path)
        size = path.stat().st_size / 1e6
        n = args.iterations
        print(f"store: {n} iterations, {size:.0f} MB on disk (grown in {gen:.1f} s)")
        whats = ["to_xarray", "iter_records", "scans"] + (["records_full"] if args.full else [])
        ok = True
        for what in whats:
            def measure(trace: str) -> dict:
                out = subprocess.run(
                    [sys.executable, "-c", MEASURE, str(path), what, trace],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                return json.loads(out.stdout)

            r = measure("time")
            r["tracemalloc_peak_mb"] = measure("trace")["tracemalloc_peak_mb"]
            extra = f", dataset {r['dataset_mb']:.1f} MB" if "dataset_mb" in r else ""
            print(
                f"{what:>13}: {r['iterations']} iterations in {r['seconds']:.2f} s, "
                f"tracemalloc peak {r['tracemalloc_peak_mb']:.0f} MB, "
                f"max RSS {r['maxrss_mb']:.0f} MB (after imports {r['base_rss_mb']:.0f} MB){extra}"
            )
            if what == "to_xarray":
                ok = r["seconds"] < 2.0 and r["maxrss_mb"] < 200
        print("targets (< 2 s, < 200 MB max RSS) for to_xarray(scans=False):", "met" if ok else "NOT met")
        return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
