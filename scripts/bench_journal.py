#!/usr/bin/env python3
"""Benchmark: the daemon's journal over one UTC day of many readings: write rate, file size
and the resident memory it adds (the journal keeps no copy of its lines: a state dir deleted
under the daemon is rebuilt from the open files).

Appends N readings of 100 sensors within one UTC day in batches of 64 (as the worker does),
then deletes the folder and appends once more (the rebuild), and prints a table and, last,
one JSON line. ``--fsync`` makes the journal durable and syncs it after every batch, as the
daemon does with ``journal_fsync`` (the default) before it acknowledges the batch.
Usage: .venv/bin/python scripts/bench_journal.py [--readings 1000000] [--fsync]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import tempfile
import time
from pathlib import Path

from pseudotwin.edge.journal import Journal
from pseudotwin.live.readings import Reading

SENSORS = 100
BATCH = 64


def rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--readings", type=int, default=1_000_000)
    ap.add_argument("--fsync", action="store_true",
                    help="sync the journal to disk after every batch (journal_fsync)")
    args = ap.parse_args()
    n = args.readings
    day = dt.datetime(2024, 5, 13, tzinfo=dt.UTC)
    step = dt.timedelta(seconds=86_000 / n)
    folder = Path(tempfile.mkdtemp(prefix="bench-journal-"))
    try:
        journal = Journal(folder / "journal", durable=args.fsync)
        before = rss_mb()
        t0 = time.perf_counter()
        for start in range(0, n, BATCH):
            journal.append_many([Reading(f"floor{i % SENSORS}/room/temp", day + i * step,
                                         21.0 + (i % 37) / 10)
                                 for i in range(start, min(start + BATCH, n))])
            journal.sync()  # nothing to do unless durable
        took = time.perf_counter() - t0
        grown = rss_mb() - before
        size = sum(p.stat().st_size for p in (folder / "journal").iterdir()) / 1e6
        shutil.rmtree(folder / "journal")
        t1 = time.perf_counter()
        journal.append(Reading("floor0/room/temp", day + n * step, 21.0))
        rebuild = time.perf_counter() - t1
        journal.close()
        back = sum(1 for _ in Journal(folder / "journal").replay(day))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    out = {"readings": n, "fsync": args.fsync, "seconds": round(took, 2),
           "readings_per_s": round(n / took),
           "file_mb": round(size, 1), "rss_growth_mb": round(grown, 1),
           "rebuild_s": round(rebuild, 3), "replayed_after_rebuild": back}
    print("| readings | fsync per batch | write s | readings/s | file MB | RSS growth MB | "
          "rebuild s | replayed after rebuild |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    print(f"| {n} | {'yes' if args.fsync else 'no'} | {out['seconds']} | "
          f"{out['readings_per_s']} | {out['file_mb']} | "
          f"{out['rss_growth_mb']} | {out['rebuild_s']} | {back} |")
    print(json.dumps({"bench_journal": out}))


if __name__ == "__main__":
    main()
