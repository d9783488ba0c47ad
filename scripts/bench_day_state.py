#!/usr/bin/env python3
"""Benchmark: what many twins' day state costs in memory and in garbage collection.

The twin of ``scripts/bench_daemon.py`` (SML2010, one reference; trained here, or read with
``--artifact``) is loaded ``--twins`` times in one process, as the daemon loads its twins,
and the process's long-lived objects are frozen out of the collector's way as the daemon
does (core/heap.py). Every twin then gets a reading every 5 minutes of day time from the init
start to day end and its estimate of every model at each one, for ``--days`` days. No MQTT
and no clock: this measures the twins alone.

Reported per day and hour of day time: resident memory of the day state per twin (RSS above
the loaded twins), the objects the cyclic garbage collector tracks, and the full (gen 2)
collections Python ran with their longest pause, which stops every thread of a daemon.

Prints a table, and as its last line one JSON object with the figures.
Usage: .venv/bin/python scripts/bench_day_state.py [--twins 1000] [--days 2] [--artifact FILE]
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import sys
import time
from pathlib import Path
from typing import Any

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy is used)
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.heap import freeze_long_lived
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

TZ = "Europe/Madrid"
REF, TARGET = "dining/temp", "room/temp"
FIRST_DAY = dt.date(2012, 3, 20)


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 1e6


class Pauses:
    """Full collections and their pauses [s], from gc.callbacks."""

    def __init__(self) -> None:
        self.started = 0.0
        self.full: list[float] = []
        gc.callbacks.append(self)

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self.started = time.perf_counter()
        elif info["generation"] == 2:
            self.full.append(time.perf_counter() - self.started)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--twins", type=int, default=1000)
    ap.add_argument("--days", type=int, default=2)
    ap.add_argument("--artifact", type=Path, default=None,
                    help="the trained twin: read from this file if it exists, else trained "
                         "(≈ 1 min) and written there")
    a = ap.parse_args()
    hours = OperatingHours(timezone=TZ)
    if a.artifact is not None and a.artifact.exists():
        d = json.loads(a.artifact.read_text())
    else:
        spec = TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, hours)
        d = json.loads(json.dumps(train_twin(load("sml2010"), spec, dt.date(2012, 3, 14), 5)
                                  .to_dict(), allow_nan=True))
        if a.artifact is not None:
            a.artifact.write_text(json.dumps(d))
    twins = [Twin(Artifact.from_dict(d), stale_after=dt.timedelta(minutes=30))
             for _ in range(a.twins)]
    freeze_long_lived()
    loaded = rss_mb()
    pauses = Pauses()
    rows = []
    step = 5 / 60
    for k in range(a.days):
        day = FIRST_DAY + dt.timedelta(days=k)
        h = hours.init_start
        mark = 10.0
        while h < hours.day_end:
            ts = hours.at(day, h)
            for i, tw in enumerate(twins):
                tw.observe(REF, ts, 19.0 + 0.3 * ((h * 7 + i % 7) % 5))
                tw.estimate(ts)
            h += step
            if h >= mark or h >= hours.day_end:
                rows.append({"day": k + 1, "hour": round(h, 1),
                             "day_state_kb_per_twin": round((rss_mb() - loaded) / a.twins * 1e3, 1),
                             "tracked_objects": len(gc.get_objects()),
                             "full_collections": len(pauses.full),
                             "longest_full_pause_ms": round(max(pauses.full, default=0.0) * 1e3)})
                mark += 3.0
    print(f"{a.twins} twins, readings every 5 min of day time, {a.days} day(s); "
          f"RSS of the loaded twins {loaded:.0f} MB")
    print(f"{'day':>3} {'hour':>5} {'day state KB/twin':>18} {'tracked objects':>16} "
          f"{'full GCs':>9} {'longest pause ms':>17}")
    for r in rows:
        print(f"{r['day']:>3} {r['hour']:>5} {r['day_state_kb_per_twin']:>18} "
              f"{r['tracked_objects']:>16} {r['full_collections']:>9} "
              f"{r['longest_full_pause_ms']:>17}")
    print(json.dumps({"twins": a.twins, "days": a.days, "loaded_rss_mb": round(loaded, 1),
                      "rows": rows,
                      "full_pauses_ms": [round(p * 1e3) for p in pauses.full]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
