#!/usr/bin/env python3
"""Benchmark: bulk write and read of the history store, SQLite vs PostgreSQL.

Writes N months of 1-minute readings of 3 sensors (one ``write_readings`` call with a
canonical frame, as ``pseudotwin import`` does), writes them again (all keys present:
the idempotent path), reads everything back (``read_readings`` in its monthly windows) and
writes one twin's estimates for the same span. PostgreSQL: a throwaway local cluster
started like the tests' fixture (tests/postgres_server.py; fsync off there, so this is the
CPU and protocol cost, not the disk's; SQLite runs with its usual synchronous=NORMAL).

Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_store.py [--months 7]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pseudotwin.history.store import EstimateRow, Store, open_store

ROOT = Path(__file__).resolve().parent.parent
SENSORS = ("dining/temp", "ceiling/temp", "hmi/co2")


def readings(months: int) -> pd.DataFrame:
    start = pd.Timestamp("2016-01-01T00:00Z")
    ts = pd.date_range(start, start + pd.DateOffset(months=months), freq="1min",
                       inclusive="left")
    rng = np.random.default_rng(0)
    parts = [pd.DataFrame({"sensor": s, "ts": ts,
                           "value": np.round(20 + rng.normal(0, 1, len(ts)).cumsum() / 50, 3)})
             for s in SENSORS]
    return pd.concat(parts, ignore_index=True).sort_values(["ts", "sensor"],
                                                           ignore_index=True)


def run(store: Store, df: pd.DataFrame) -> dict[str, float]:
    t0 = time.perf_counter()
    assert store.write_readings(df) == len(df)
    t1 = time.perf_counter()
    assert store.write_readings(df) == 0
    t2 = time.perf_counter()
    back = store.read_readings(None)
    t3 = time.perf_counter()
    assert len(back) == len(df)
    one = df[df["sensor"] == SENSORS[0]]
    rows = [EstimateRow("desk", "corrgp-triv", t.to_pydatetime(), v, 0.2, "ok", "sha256:x")
            for t, v in zip(one["ts"], one["value"], strict=True)]
    t4 = time.perf_counter()
    store.write_estimates(rows)
    t5 = time.perf_counter()
    n = len(df)
    return {"write_rows_per_s": n / (t1 - t0), "rewrite_rows_per_s": n / (t2 - t1),
            "read_rows_per_s": n / (t3 - t2), "estimates_rows_per_s": len(rows) / (t5 - t4),
            "write_s": t1 - t0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--months", type=int, default=7)
    a = ap.parse_args()
    df = readings(a.months)
    tmp = Path(tempfile.mkdtemp(prefix="pseudotwin-bench-store-"))
    server = None
    results: dict[str, dict[str, float]] = {}
    try:
        with open_store(tmp / "history.db") as s:
            results["sqlite"] = run(s, df)
        sys.path.insert(0, str(ROOT / "tests"))
        from postgres_server import PostgresServer, find_bindir

        bindir = find_bindir()
        if bindir is None:
            print("PostgreSQL binaries not found (scripts/bootstrap.sh installs them)")
            return 1
        server = PostgresServer(bindir)
        server.start()
        with open_store(server.url()) as s:
            results["postgresql"] = run(s, df)
    finally:
        if server is not None:
            server.destroy()
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"{len(df)} readings = {a.months} months x {len(SENSORS)} sensors x 1 min")
    print(f"{'backend':<11} {'write/s':>10} {'rewrite/s':>10} {'read/s':>10} "
          f"{'estimates/s':>12} {'write s':>8}")
    for name, r in results.items():
        print(f"{name:<11} {r['write_rows_per_s']:>10.0f} {r['rewrite_rows_per_s']:>10.0f} "
              f"{r['read_rows_per_s']:>10.0f} {r['estimates_rows_per_s']:>12.0f} "
              f"{r['write_s']:>8.1f}")
    print(json.dumps({"readings": len(df), "months": a.months, **{
        f"{b}_{k}": round(v, 1 if k == "write_s" else 0)
        for b, r in results.items() for k, v in r.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
