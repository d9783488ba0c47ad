#!/usr/bin/env python3
"""Benchmark: a chatty sensor through the live twin — one reading every 2 s per reference
for a whole operating day — and the window's thinning (core/thinning.py).

Data: Room Climate location A. The twin (ref, triv, corrgp-triv, corrgp-lcm, varma; VARMA by
OLS to keep the run short) is trained on the 1-minute means of 2016-03-15 … 2016-03-21. The
live day's raw samples (~5 s per node, converted with ``--raw``) of references A1 and A3 are
interpolated onto a 2-s grid from the init start to day end (held flat before the first and
after the last sample), then fed reading by reading through ``Twin.observe``, timed per call.

Then the same twin replays every day after training through ``replay_estimates`` (what
``evaluate`` scores), once from the 1-minute means and once from the raw samples: CPU time and
mean daily NRMSE per model of both (the thinning's faithfulness, training held fixed); the
replays alternate ``--repeat`` times and the median CPU times are reported.

Prints a table, and as its last line one JSON object with the figures.
Usage: .venv/bin/python scripts/bench_chatty.py [--day 2016-03-22] [--every 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
import tracemalloc

import numpy as np
import pandas as pd

import pseudotwin  # noqa: F401  (one BLAS thread, before numpy is used)
from pseudotwin.analysis.evaluate import daily_scores, first_scored_day
from pseudotwin.analysis.replay import replay_estimates
from pseudotwin.analysis.training import train_twin
from pseudotwin.core.horizon import OperatingHours
from pseudotwin.core.spec import Quantity, TwinSpec
from pseudotwin.history.convert import load
from pseudotwin.live.twin import Twin

REFS = ("A1/temp", "A3/temp")
TARGET = "A4/temp"
HOURS = OperatingHours(timezone="Europe/Berlin")


def chatty_day(raw: pd.DataFrame, day: dt.date, every_s: float
               ) -> list[tuple[str, dt.datetime, float]]:
    """Both references on one 2-s grid (interleaved, in time order)."""
    start, end = HOURS.at(day, HOURS.init_start), HOURS.at(day, HOURS.day_end)
    grid = pd.date_range(start, end, freq=pd.Timedelta(seconds=every_s), inclusive="left")
    x = grid.asi8.astype(float)
    out: list[tuple[str, dt.datetime, float]] = []
    per_ref = {}
    for ref in REFS:
        r = raw[raw["sensor"] == ref]
        ts = pd.DatetimeIndex(r["ts"]).asi8.astype(float)
        if not len(ts):
            raise SystemExit(f"no raw readings of {ref} on {day}")
        per_ref[ref] = np.interp(x, ts, r["value"].to_numpy())
    stamps = grid.to_pydatetime()
    for i, ts in enumerate(stamps):
        for ref in REFS:
            out.append((ref, ts, float(per_ref[ref][i])))
    return out


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--day", type=dt.date.fromisoformat, default=dt.date(2016, 3, 22))
    ap.add_argument("--every", type=float, default=2.0, help="seconds between readings")
    ap.add_argument("--repeat", type=int, default=3,
                    help="replays of each history, alternating; the medians are reported")
    a = ap.parse_args()
    if a.repeat < 1:
        ap.error("--repeat must be at least 1")

    minute = load("room-climate-a")
    raw = load("room-climate-a", raw=True)
    spec = TwinSpec(REFS, TARGET, Quantity.TEMPERATURE, HOURS)
    t0 = time.perf_counter()
    art = train_twin(minute, spec, dt.date(2016, 3, 15), 5,
                     models=("ref", "triv", "corrgp-triv", "corrgp-lcm", "varma"),
                     options={"varma": {"force_fallback": True}}, validate=False)
    train_s = time.perf_counter() - t0

    lo, hi = pd.Timestamp(HOURS.at(a.day, 0.0)), pd.Timestamp(HOURS.at(a.day, 23.99))
    readings = chatty_day(raw[(raw["ts"] >= lo) & (raw["ts"] < hi)], a.day, a.every)
    twin = Twin(art, models=list(art.models))
    last_hour = HOURS.at(a.day, HOURS.day_end - 1.0)
    all_ms: list[float] = []
    end_ms: list[float] = []
    t0 = time.perf_counter()
    for sensor, ts, value in readings:
        c0 = time.perf_counter_ns()
        twin.observe(sensor, ts, value)
        ms = (time.perf_counter_ns() - c0) / 1e6
        all_ms.append(ms)
        if ts >= last_hour:
            end_ms.append(ms)
    feed_s = time.perf_counter() - t0
    # Memory in a second pass: tracemalloc hooks every allocation, so timings under it
    # would be tracemalloc's, not the twin's.
    traced = Twin(art, models=list(art.models))
    tracemalloc.start()
    for sensor, ts, value in readings:
        traced.observe(sensor, ts, value)
    _, peak_bytes = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    est_ms = []
    for k in range(20):
        c0 = time.perf_counter_ns()
        twin.estimate(HOURS.at(a.day, HOURS.day_end - 0.01 * k))
        est_ms.append((time.perf_counter_ns() - c0) / 1e6)
    nums = twin.numerics()

    start = first_scored_day(art)
    # Alternating repeats, medians: this machine's CPU times vary by tens of percent from
    # run to run, and a single pair made the raw/1-minute ratio a draw.
    cpu: dict[str, list[float]] = {"minute": [], "raw": []}
    nrmse: dict[str, dict[str, float]] = {}
    for _ in range(a.repeat):
        for name, frame in (("minute", minute), ("raw", raw)):
            cpu0 = time.process_time()
            est = replay_estimates(art, frame, start)
            cpu[name].append(time.process_time() - cpu0)
            means = daily_scores(est, HOURS).groupby("model")["nrmse_pct"].mean()
            nrmse[name] = {k: round(float(v), 4) for k, v in means.items()}
    median_cpu = {name: round(float(np.median(runs)), 2) for name, runs in cpu.items()}

    fig = {
        "day": a.day.isoformat(),
        "every_s": a.every,
        "readings": len(readings),
        "window_points": len(twin.window),
        "gp_points": int(nums["gp_points"]),
        "observe_p50_ms": round(pct(all_ms, 50), 4),
        "observe_p99_ms": round(pct(all_ms, 99), 4),
        "observe_max_ms": round(max(all_ms), 3),
        "last_hour_p50_ms": round(pct(end_ms, 50), 4),
        "last_hour_p99_ms": round(pct(end_ms, 99), 4),
        "estimate_all_models_p50_ms": round(pct(est_ms, 50), 3),
        "feed_seconds": round(feed_s, 2),
        "traced_peak_mb": round(peak_bytes / 1e6, 2),
        "train_seconds": round(train_s, 1),
        "models": list(art.models),
        "replay_minute_cpu_s": median_cpu["minute"],
        "replay_raw_cpu_s": median_cpu["raw"],
        "replay_cpu_ratio": round(median_cpu["raw"] / median_cpu["minute"], 2),
        "replay_minute_cpu_runs_s": [round(c, 2) for c in cpu["minute"]],
        "replay_raw_cpu_runs_s": [round(c, 2) for c in cpu["raw"]],
        "replay_nrmse_pct": {k: {"minute": v, "raw": nrmse["raw"].get(k)}
                             for k, v in nrmse["minute"].items()},
    }
    print(f"chatty sensor: {len(readings)} readings ({len(REFS)} references every "
          f"{a.every:g} s, {HOURS.describe()}) on {a.day}, models {', '.join(art.models)}")
    print(f"{'figure':<34} {'value':>12}")
    for key in ("window_points", "gp_points", "observe_p50_ms", "observe_p99_ms",
                "observe_max_ms", "last_hour_p50_ms", "last_hour_p99_ms",
                "estimate_all_models_p50_ms", "feed_seconds", "traced_peak_mb"):
        print(f"{key:<34} {fig[key]:>12}")
    print(f"\nreplay of the days after training (the twin above), CPU, median of {a.repeat} "
          f"alternating runs: 1-minute means {fig['replay_minute_cpu_s']} s "
          f"({fig['replay_minute_cpu_runs_s']}), raw samples {fig['replay_raw_cpu_s']} s "
          f"({fig['replay_raw_cpu_runs_s']}); raw / 1-minute {fig['replay_cpu_ratio']}")
    print(f"{'model':<16} {'NRMSE % 1-min':>14} {'NRMSE % raw':>12}")
    for k, v in fig["replay_nrmse_pct"].items():
        print(f"{k:<16} {v['minute']:>14} {v['raw']:>12}")
    print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())
