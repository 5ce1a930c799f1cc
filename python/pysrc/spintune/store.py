"""Runs stored by the server and the CLI (``spintune serve``, ``spintune run``).

The store is an SQLite file (schema: ``backend/src/store.rs``): a ``runs``
table (config, status, counters, latest checkpoint) and an ``iterations``
table holding each committed ``IterationRecord`` as JSON. This module only
reads it, with Python's ``sqlite3`` (the file is opened read-only)::

    store = spintune.open_store("spintune.db")
    for run in store:
        print(run.id, run.name, run.status["state"], run.iterations)
    ds = store[1].to_xarray()            # no raw scans parsed
    for record in store[1].iter_records():   # streamed, without scans
        ...
    store[1].scans(100, 110)             # raw scans of iterations 100..109

At lab scale (a 20,000-iteration run, ~15 KB a record of which ~88 % are
raw scans) the raw scans are cut out by SQLite (``json_remove``) before
Python parses a record, and records are streamed in batches, never held
all at once: see ``docs/python.md`` for the measured time and memory.
"""

from __future__ import annotations

import json
import os
import sqlite3
from typing import Any, Dict, Iterator, List, Optional


class StoredRun:
    """One stored run. Records are read from the file when first asked for.

    Attributes:
        id: the run's id (as in ``spintune export ID``).
        name: the run's name.
        status: status dict, e.g. ``{"state": "finished"}``.
        iterations: number of committed iterations.
        lab_seconds: cumulative lab time, s.
        tuned: whether the last iteration was tuned.
        config: the run config dict (``{"simulation": {...}, "backend": {...}}``).
        created_unix_s: creation time, Unix seconds.
    """

    def __init__(self, store: "Store", row: tuple):
        (
            self.id,
            self.name,
            status,
            self.iterations,
            self.lab_seconds,
            tuned,
            config,
            self.created_unix_s,
        ) = row
        self._store = store
        self.status: dict = json.loads(status)
        self.tuned = bool(tuned)
        self.config: dict = json.loads(config)
        self._records: Optional[list] = None

    @property
    def simulation_config(self) -> dict:
        """The core part of the config (``name``, ``seed``, ``device``, ``tuner``),
        as ``spintune.SimulationRun`` takes it."""
        return self.config.get("simulation", self.config)

    @property
    def records(self) -> list:
        """Every committed iteration record (list of dicts, JSON
        ``IterationRecord``, raw scans included), in order. Holds the whole
        run in memory: for a long run prefer :meth:`iter_records` or
        :meth:`to_xarray`."""
        if self._records is None:
            self._records = list(self.iter_records(scans=True))
        return self._records

    #: Rows fetched from SQLite at a time by the streaming readers.
    BATCH = 1000

    def iter_records(
        self,
        *,
        scans: bool = False,
        start: Optional[int] = None,
        stop: Optional[int] = None,
    ) -> Iterator[Dict[str, Any]]:
        """Stream the records, oldest first, one dict at a time (read in
        batches of :attr:`BATCH` rows; memory stays flat however long the
        run). ``scans=False`` (default): without the raw scans (key
        ``scans`` absent) — SQLite removes them before Python parses the
        record. ``start``/``stop``: only iterations ``start <= k < stop``
        (the record's ``iteration``)."""
        column = "record" if scans else "json_remove(record, '$.scans')"
        where, args = self._range(start, stop)
        yield from self._stream(f"SELECT seq, {column} FROM iterations WHERE {where}", args)

    def scans(self, start: Optional[int] = None, stop: Optional[int] = None) -> Dict[int, List[Any]]:
        """The raw scans of iterations ``start <= k < stop`` (all if not
        given): iteration → list of scans (as in a record's ``scans``). Only
        these records' scans are parsed."""
        where, args = self._range(start, stop)
        out: Dict[int, List[Any]] = {}
        for rec in self._stream(
            "SELECT seq, json_object('iteration', json_extract(record, '$.iteration'), "
            f"'scans', json_extract(record, '$.scans')) FROM iterations WHERE {where}",
            args,
        ):
            out[int(rec["iteration"])] = rec["scans"] if rec["scans"] is not None else []
        return out

    def _range(self, start: Optional[int], stop: Optional[int]):
        where = "run_id = ?"
        args: List[Any] = [self.id]
        if start is not None:
            where += " AND json_extract(record, '$.iteration') >= ?"
            args.append(int(start))
        if stop is not None:
            where += " AND json_extract(record, '$.iteration') < ?"
            args.append(int(stop))
        return where, args

    def _batches(self, sql: str, args: List[Any]) -> Iterator[List[Any]]:
        """Rows of ``sql`` (selecting ``seq`` first, filtered by ``args``) in
        ``seq`` order, in batches of :attr:`BATCH` fetched by keyset (each
        batch its own short read; nothing is held open between)."""
        after = -1
        while True:
            with self._store._connect() as conn:
                rows = conn.execute(
                    f"{sql} AND seq > ? ORDER BY seq LIMIT ?", (*args, after, self.BATCH)
                ).fetchall()
            if not rows:
                return
            after = rows[-1][0]
            yield rows
            if len(rows) < self.BATCH:
                return

    def _stream(self, sql: str, args: List[Any]) -> Iterator[Dict[str, Any]]:
        """The JSON texts of :meth:`_batches`, parsed one at a time."""
        for rows in self._batches(sql, args):
            for _, text in rows:
                yield json.loads(text)

    @property
    def checkpoint(self) -> str:
        """The latest checkpoint (JSON string: session and device state)."""
        with self._store._connect() as conn:
            (text,) = conn.execute("SELECT checkpoint FROM runs WHERE id = ?", (self.id,)).fetchone()
        return text

    def to_xarray(self, scans: bool = False):
        """The records as an ``xarray.Dataset`` over ``iteration`` (see
        ``SimulationRun.to_xarray`` for the variables and units), built from
        :meth:`iter_records` as a stream. ``scans=False`` (default) reads no
        raw scan; ``scans=True`` adds the variable ``scans`` (per iteration,
        the JSON text of its raw scans)."""
        from ._core import RecordColumns
        from ._xarray import columns_to_dataset

        columns = RecordColumns()
        where, args = self._range(None, None)
        for batch in self._batches(
            f"SELECT seq, json_remove(record, '$.scans', '$.events') FROM iterations WHERE {where}",
            args,
        ):
            columns.add_json([text for _, text in batch])
        ds = columns_to_dataset(
            columns,
            {
                "title": f"spintune run {self.id}: {self.name}",
                "name": self.name,
                "run_id": self.id,
                "status": self.status.get("state", ""),
                "spintune_config": json.dumps(self.config),
            },
        )
        if scans:
            import numpy as np

            by_iteration = self.scans()
            ds["scans"] = (
                ("iteration",),
                np.asarray(
                    [json.dumps(by_iteration.get(int(k), [])) for k in ds["iteration"].values],
                    dtype=object,
                ),
                {"long_name": "raw scans of the iteration (JSON)"},
            )
        return ds

    def to_netcdf(self, path) -> None:
        """Write ``to_xarray()`` to a netCDF file."""
        self.to_xarray().to_netcdf(path)

    def __repr__(self) -> str:
        return (
            f"StoredRun(id={self.id}, name={self.name!r}, status={self.status.get('state')!r}, "
            f"iterations={self.iterations})"
        )


#: Store schema version this package reads (``PRAGMA user_version``), the
#: server's ``spintune_server::store::SCHEMA_VERSION``: a newer store is
#: refused with a clear error rather than misread.
SCHEMA_VERSION = 1


class Store:
    """A spintune store (SQLite file), read-only. Iterating yields the runs
    (oldest first); ``store[id]`` is one run."""

    def __init__(self, path: "str | os.PathLike[str]"):
        self.path = os.fspath(path)
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"no spintune store at {self.path}")
        with self._connect() as conn:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            version = conn.execute("PRAGMA user_version").fetchone()[0]
        if not {"runs", "iterations"} <= tables:
            raise ValueError(f"{self.path} is not a spintune store (no `runs`/`iterations` tables)")
        if version > SCHEMA_VERSION:
            raise ValueError(
                f"{self.path} has store schema version {version}; this spintune package "
                f"reads up to {SCHEMA_VERSION}: it was written by a newer spintune server, "
                "upgrade the package"
            )
        #: The store's schema version (``PRAGMA user_version``; 0: an older,
        #: unversioned store).
        self.schema_version = version

    def _connect(self) -> sqlite3.Connection:
        uri = "file:" + os.path.abspath(self.path).replace("?", "%3f").replace("#", "%23") + "?mode=ro"
        conn = sqlite3.connect(uri, uri=True, timeout=10.0)
        return _Closing(conn)

    @property
    def runs(self) -> list:
        """Every run, oldest first (fresh from the file)."""
        with self._connect() as conn:
            rows = conn.execute(
                "SELECT id, name, status, iterations, lab_seconds, tuned, config, created_unix_s "
                "FROM runs ORDER BY id"
            ).fetchall()
        return [StoredRun(self, row) for row in rows]

    def run(self, run_id: int) -> StoredRun:
        """The run with this id; ``KeyError`` if there is none."""
        with self._connect() as conn:
            row = conn.execute(
                "SELECT id, name, status, iterations, lab_seconds, tuned, config, created_unix_s "
                "FROM runs WHERE id = ?",
                (int(run_id),),
            ).fetchone()
        if row is None:
            raise KeyError(f"no run with id {run_id} in {self.path}")
        return StoredRun(self, row)

    def __getitem__(self, run_id: int) -> StoredRun:
        return self.run(run_id)

    def __iter__(self) -> Iterator[StoredRun]:
        return iter(self.runs)

    def __len__(self) -> int:
        with self._connect() as conn:
            return conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0]

    def __repr__(self) -> str:
        return f"Store({self.path!r}, runs={len(self)})"


class _Closing:
    """``with`` a connection that closes it afterwards (sqlite3's own
    context manager only commits)."""

    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn

    def __enter__(self) -> sqlite3.Connection:
        return self._conn

    def __exit__(self, *exc: Any) -> None:
        self._conn.close()


def open_store(path: "str | os.PathLike[str]") -> Store:
    """Open a spintune store (the SQLite file of ``spintune serve --db`` /
    ``spintune run --db``) for reading."""
    return Store(path)
