#!/usr/bin/env python3
"""Benchmark: the model work of scripts/bench_daemon.py's load, in-process, without MQTT.

The same twins (one SML2010 artifact per room), the same 5-minute readings and the same
15-minute grid, fed straight to ``Twin`` objects as the daemon's worker does: observe each
reading, estimate the primary at it, every published model at each grid instant. What is
left of bench_daemon.py's CPU per reading beyond this is the daemon's own cost (MQTT,
payloads, journal). Prints a table and, last, one JSON line.
Usage: .venv/bin/python scripts/bench_daemon_models.py [--twins 1000] [--hours 1]
       [--artifact FILE]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

import pseudotwin  # noqa: F401
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.edge.outputs import estimate_payload
from pseudotwin.history.convert import load
from pseudotwin.live.artifact import Artifact
from pseudotwin.live.twin import Twin

TZ = "Europe/Madrid"
DAY = dt.date(2012, 3, 20)
REF, TARGET = "dining/temp", "room/temp"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--twins", type=int, default=1000)
    ap.add_argument("--hours", type=float, default=1.0, help="day time to replay from 08:00")
    ap.add_argument("--artifact", type=Path, default=None,
                    help="the trained twin (as bench_daemon.py's --artifact): read from this "
                         "file if it exists, else trained (≈ 1 min) and written there")
    a = ap.parse_args()
    hours = OperatingHours(timezone=TZ)
    df = load("sml2010")
    if a.artifact is not None and a.artifact.exists():
        art = Artifact.load(a.artifact)
    else:
        art = train_twin(df, TwinSpec((REF,), TARGET, Quantity.TEMPERATURE, hours),
                         dt.date(2012, 3, 14), 5)
        if a.artifact is not None:
            a.artifact.write_text(json.dumps(art.to_dict(), allow_nan=True))
    # the readings of bench_daemon.py: 5-minute, interpolated, a few seconds apart per room
    day = df[(df["sensor"] == REF) & (df["ts"] >= hours.at(DAY, 0.0))
             & (df["ts"] < hours.at(DAY, 23.9))]
    t0 = hours.at(DAY, 7.5)
    grid = [t0 + dt.timedelta(minutes=5 * k) for k in range(int((a.hours + 0.5) * 12))]
    vals = np.interp([g.timestamp() for g in grid],
                     day["ts"].astype("int64").to_numpy() / 1e9, day["value"].to_numpy())
    events = sorted((g + dt.timedelta(seconds=(7 * i) % 290), i, float(v) + 0.01 * (i % 7))
                    for g, v in zip(grid, vals, strict=True) for i in range(a.twins))
    ticks = [t for t in hours.grid(DAY, 0.25) if t0 <= t <= events[-1][0]]
    twins = [Twin(art, stale_after=dt.timedelta(minutes=30)) for _ in range(a.twins)]
    cpu = dict.fromkeys(("observe", "estimate_reading", "estimate_grid", "payloads"), 0.0)
    k = twin_ticks = 0
    start = time.process_time()
    for ts, i, v in events:
        while k < len(ticks) and ticks[k] <= ts:
            c0 = time.process_time()
            outs = [tw.estimate(ticks[k]) for tw in twins]
            c1 = time.process_time()
            for out in outs:
                for e in out.values():
                    if e.publishable:
                        estimate_payload(e, art.unit)
            cpu["estimate_grid"] += c1 - c0
            cpu["payloads"] += time.process_time() - c1
            k += 1
            twin_ticks += a.twins
        c0 = time.process_time()
        moved = twins[i].observe(REF, ts, v)
        c1 = time.process_time()
        cpu["observe"] += c1 - c0
        if moved:
            twins[i].estimate(ts, kinds=(art.primary,))
            cpu["estimate_reading"] += time.process_time() - c1
    total = time.process_time() - start
    n = len(events)
    fig = {"twins": a.twins, "day_hours": a.hours, "readings": n, "twin_grid_steps": twin_ticks,
           "published_models": len(art.published), "primary": art.primary,
           "cpu_ms_per_reading": round(1e3 * total / n, 3),
           **{f"{key}_ms_per_reading": round(1e3 * v / n, 3) for key, v in cpu.items()},
           "estimate_grid_ms_per_twin_step": round(1e3 * cpu["estimate_grid"]
                                                   / max(twin_ticks, 1), 3)}
    print(f"{a.twins} twins, {n} readings, {twin_ticks} twin grid steps, "
          f"{len(art.published)} published models (primary {art.primary})")
    print(f"  in-process CPU: {fig['cpu_ms_per_reading']} ms per reading")
    for key in cpu:
        print(f"    {key}: {fig[key + '_ms_per_reading']} ms per reading")
    print(f"  every model at a grid step: {fig['estimate_grid_ms_per_twin_step']} ms per twin")
    print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())
